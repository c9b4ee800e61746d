"""The deformation residual: bounded, zero at the start, unable to move a body as a whole (its rigid part removed per
pattern, by construction and under training), re-posed with the world, and its gradients against finite
differences in float64."""

from __future__ import annotations

import pytest
import torch

from causalgs.errors import CausalGSError
from causalgs.model.residual import Residual, ResidualConfig, remove_rigid
from causalgs.similarity import Similarity, random_rotation


def _body(n: int = 200, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.rand(n, 3, generator=g, dtype=torch.float64) * torch.tensor([0.4, 0.2, 0.3], dtype=torch.float64)


def _two_bodies() -> tuple[torch.Tensor, torch.Tensor]:
    x = torch.cat([_body(150, 0), _body(120, 1) + 1.0])
    h = torch.zeros(len(x), 2, dtype=torch.float64)
    h[:150, 0] = 1.0
    h[150:, 1] = 1.0
    return x, h


def test_a_rigid_displacement_is_removed_entirely():
    x, h = _two_bodies()
    a = torch.tensor([[0.3, -0.1, 0.2], [-0.5, 0.0, 0.1]], dtype=torch.float64)
    w = torch.tensor([[0.2, 0.5, -0.3], [0.0, 0.0, 1.5]], dtype=torch.float64)
    p = torch.tensor([[1.0, 2.0, 0.0], [0.3, -0.7, 2.0]], dtype=torch.float64)  # any pivot
    k = h.argmax(1)
    rigid = a[k] + torch.linalg.cross(w[k], x - p[k])
    assert float(remove_rigid(rigid, x, h).abs().max()) < 1e-8 * float(rigid.abs().max())  # the ridge's share


def test_what_is_left_has_no_mean_and_no_angular_moment_per_pattern_and_is_a_projection():
    x, h = _two_bodies()
    dx = torch.randn(len(x), 3, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    r = remove_rigid(dx, x, h)
    for k in range(2):
        sel = h[:, k] > 0
        c = x[sel].mean(0)
        assert float(r[sel].mean(0).abs().max()) < 1e-12
        assert float(torch.linalg.cross(x[sel] - c, r[sel]).sum(0).abs().max()) < 1e-8
    assert torch.allclose(remove_rigid(r, x, h), r, atol=1e-12)  # idempotent
    assert float(r.norm()) > 0.5 * float(dx.norm())  # a random field is mostly not rigid: it stays


def test_trained_to_move_a_body_the_residual_cannot_but_it_can_bulge_it():
    """Fitted to a whole translation and rotation of a body, the projected residual moves nothing; fitted to a
    bulge, it reaches its bound."""
    torch.manual_seed(0)
    x, h = _body(300), None
    h = torch.ones(len(x), 1, dtype=torch.float64)
    c = x.mean(0)
    cfg = ResidualConfig(max_offset=0.2, width=32, depth=2)
    spin = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand_as(x)
    targets = {"rigid": 0.05 + 0.3 * torch.linalg.cross(spin, x - c), "bulge": 0.1 * (x - c)}
    z = torch.cat([x, torch.sin(3 * x), torch.cos(3 * x)], dim=1)  # a code that tells the particles apart
    moved = {}
    for name, target in targets.items():
        res = Residual(cfg, code_dim=9, duration=1.0, size=1.0).double()
        opt = torch.optim.Adam(res.parameters(), lr=3e-3)
        for _ in range(300):
            dx = remove_rigid(res(z, 0.5).dx, x, h)
            loss = (dx - target).square().sum(-1).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
        dx = remove_rigid(res(z, 0.5).dx, x, h).detach()
        moved[name] = (dx, float(loss))
    dx, _ = moved["rigid"]
    assert float(dx.mean(0).norm()) < 1e-12  # no translation
    assert float(torch.linalg.cross(x - c, dx).mean(0).norm()) < 1e-12  # no rotation
    dx, loss = moved["bulge"]
    assert loss < 0.1 * float(targets["bulge"].square().sum(-1).mean())  # a deformation it does learn


def test_outputs_are_bounded_zero_at_the_start_and_turn_with_the_world():
    cfg = ResidualConfig(max_offset=0.01, max_angle=0.1, max_log_scale=0.2)
    res = Residual(cfg, code_dim=4, duration=2.0, size=3.0).double()
    z = torch.randn(50, 4, dtype=torch.float64)
    d = res(z, 0.7)
    assert float(torch.cat([d.dx, d.drot, d.dlog_scale]).abs().max()) == 0.0
    with torch.no_grad():
        for p in res.parameters():
            p.normal_(0.0, 30.0)
    d = res(z, 0.7)
    assert float(d.dx.abs().max()) <= 0.03 + 1e-12 and float(d.dx.abs().max()) > 0.02
    assert float(d.drot.abs().max()) <= 0.1 + 1e-12 and float(d.dlog_scale.abs().max()) <= 0.2 + 1e-12
    sim = Similarity.make(random_rotation(2), 0.5, [1.0, 2.0, 3.0])
    res.reframe(sim)
    e = res(z, 0.7)
    R = torch.tensor(sim.R, dtype=torch.float64)
    assert torch.allclose(e.dx, 0.5 * d.dx @ R.T, atol=1e-14) and torch.allclose(e.drot, d.drot @ R.T, atol=1e-14)
    assert torch.allclose(e.dlog_scale, d.dlog_scale) and res.bound() == pytest.approx(0.5 * 0.03)


def test_gradcheck_float64():
    x, h = _two_bodies()
    x, h = x[::20], h[::20]
    dx = torch.randn(len(x), 3, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda d: remove_rigid(d, x, h), (dx,))
    hs = torch.softmax(torch.randn(len(x), 2, dtype=torch.float64), 1)  # blended mixtures
    assert torch.autograd.gradcheck(lambda d: remove_rigid(d, x, hs), (dx,))
    res = Residual(ResidualConfig(width=6, depth=1, time_freqs=1), code_dim=3, duration=1.0, size=1.0).double()
    with torch.no_grad():
        for p in res.parameters():
            p.normal_(0.0, 0.5)
    z = torch.randn(5, 3, dtype=torch.float64)
    params = dict(res.named_parameters())
    w = params["net.0.weight"].detach().clone().requires_grad_(True)

    def out(weight):
        d = torch.func.functional_call(res, {**params, "net.0.weight": weight}, (z, 0.4))
        return d.dx, d.drot, d.dlog_scale

    assert torch.autograd.gradcheck(out, (w,))


def test_bad_settings_are_one_line_errors():
    with pytest.raises(CausalGSError, match="max_offset"):
        ResidualConfig(max_offset=-1.0)
    with pytest.raises(CausalGSError, match="start"):
        ResidualConfig(start=1.5)
