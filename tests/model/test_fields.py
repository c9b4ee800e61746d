"""The inverse-physics fields and the kinematic integrator: bounds, the divergence-free basis, RK2 and rotation order
against a closed-form rigid rotation, and gradients reaching every network."""

from __future__ import annotations

import math

import pytest
import torch

from causalgs.errors import CausalGSError
from causalgs.model.fields import FieldsConfig, InversePhysics, basis
from causalgs.model.kinematic import flow_paths, integrate, quat_mul, rotvec_quat


def _fields(frames: int = 11, **kw) -> InversePhysics:
    torch.manual_seed(0)
    return InversePhysics(FieldsConfig(**kw), lo=(-1, -1, -1), hi=(1, 1, 1), duration=1.0, frames=frames).double()


def test_materials_stay_in_their_ranges_and_start_at_init():
    f = _fields(E_range=(1e3, 1e6), E_init=3e4, nu_range=(0.1, 0.4), nu_init=0.25, density_range=(500.0, 2000.0))
    p = torch.rand(200, 3, dtype=torch.float64) * 2 - 1
    m = f.materials(p)
    assert torch.allclose(m["E"], torch.full_like(m["E"], 3e4), rtol=0.05)
    assert torch.allclose(m["nu"], torch.full_like(m["nu"], 0.25), atol=0.01)
    with torch.no_grad():  # push the decoder to its extremes: outputs saturate at the bounds, never beyond
        f.f_mat[-1].bias.copy_(torch.tensor([50.0, -50.0, 50.0]))
        m = f.materials(p)
    assert float(m["E"].max()) <= 1e6 * (1 + 1e-9) and float(m["E"].min()) > 0.99e6
    assert float(m["nu"].min()) >= 0.1 - 1e-12 and float(m["nu"].max()) < 0.1 + 1e-6
    assert float(m["density"].max()) <= 2000.0 + 1e-9


def test_pattern_materials_move_only_their_own_bodies():
    """m = f_mat(γ(p)) + h·Θ: with Θ = 0 the offsets change nothing; a loss on the particles of one pattern reaches
    that pattern's row of Θ only; a set row shifts log E exactly where the mixtures put that pattern."""
    f = _fields(patterns=4)
    p = torch.rand(60, 3, dtype=torch.float64) * 2 - 1
    h = torch.zeros(60, 4, dtype=torch.float64)
    h[:30, 1] = 1.0
    h[30:, 2] = 1.0
    base = f.materials(p)
    assert all(torch.equal(base[k], v) for k, v in f.materials(p, h).items())
    loss = f.materials(p, h)["E"][:30].log().sum()  # evidence about the body of pattern 1 only
    loss.backward()
    g = f.pattern_materials.grad
    assert float(g[1].abs().sum()) > 0 and float(g[[0, 2, 3]].abs().sum()) == 0.0
    with torch.no_grad():
        f.pattern_materials[2, 0] = 1.0
    m = f.materials(p, h)
    assert torch.equal(m["E"][:30], base["E"][:30]) and bool((m["E"][30:] > base["E"][30:]).all())
    # A model saved before the offsets existed loads with Θ = 0.
    old = {k: v for k, v in f.state_dict().items() if k != "pattern_materials"}
    g = _fields(patterns=4)
    g.load_state_dict(old)
    assert float(g.pattern_materials.abs().sum()) == 0.0


def test_bad_ranges_are_one_line_errors():
    with pytest.raises(CausalGSError, match="E_init"):
        FieldsConfig(E_range=(1e3, 1e4), E_init=1e5)
    with pytest.raises(CausalGSError, match="nu_init"):
        FieldsConfig(nu_range=(0.1, 0.5), nu_init=0.3)


def test_basis_fields_are_divergence_free_and_match_the_affine_form():
    torch.manual_seed(1)
    p = torch.randn(30, 3, dtype=torch.float64, requires_grad=True)
    c = torch.randn(3, dtype=torch.float64)
    B = basis(p, c)  # [N, 6, 3]
    for j in range(6):
        div = sum(torch.autograd.grad(B[:, j, d].sum(), p, retain_graph=True)[0][:, d] for d in range(3))
        assert float(div.abs().max()) < 1e-12
    # v = V · B(p) equals the integrator's affine form a + ω × p with a = u − ω × c.
    V = torch.randn(6, dtype=torch.float64)
    v = torch.einsum("j,njd->nd", V, B)
    u, w = V[:3], V[3:]
    assert torch.allclose(v, u - torch.linalg.cross(w, c) + torch.linalg.cross(w.expand(30, 3), p), atol=1e-12)


def _rigid_spin(f: InversePhysics, omega: float, centre) -> None:
    """Set every pattern to a constant spin ω about z through ``centre`` (u = ω × c cancels the origin term)."""
    with torch.no_grad():
        for layer in f.f_weight:
            if isinstance(layer, torch.nn.Linear):
                layer.weight.zero_()
                layer.bias.zero_()
        K = f.config.patterns
        twist = torch.zeros(K, 6, dtype=torch.float64)
        w = torch.tensor([0.0, 0.0, omega], dtype=torch.float64)
        c = torch.tensor(centre, dtype=torch.float64)
        twist[:, 3:] = w
        f.centres.copy_(c.expand(K, 3))
        f.f_weight[-1].bias.copy_(twist.flatten())  # u = 0: the rotation is about c


def test_rk2_positions_and_rotations_converge_at_second_order():
    f = _fields(patterns=3)
    omega, centre = 2.0, (0.3, -0.2, 0.0)
    _rigid_spin(f, omega, centre)
    x0 = torch.tensor([[1.0, 0.5, 0.2], [-0.4, 0.1, -0.3]], dtype=torch.float64)
    q0 = torch.tensor([[1.0, 0.0, 0.0, 0.0], [0.8, 0.2, -0.1, 0.3]], dtype=torch.float64)
    h = f.mixture(f.code(x0))
    T = 1.0
    theta = omega * T
    c = torch.tensor(centre, dtype=torch.float64)
    R = torch.tensor([[math.cos(theta), -math.sin(theta), 0], [math.sin(theta), math.cos(theta), 0], [0, 0, 1]],
                     dtype=torch.float64)  # fmt: skip
    x_true = (x0 - c) @ R.T + c
    q_true = quat_mul(rotvec_quat(torch.tensor([0.0, 0.0, theta], dtype=torch.float64)).expand(2, 4),
                      q0 / q0.norm(dim=-1, keepdim=True))  # fmt: skip
    errs = []
    for steps in (10, 20, 40):
        xs, qs = integrate(f, h, x0, q0, steps, T / steps)
        errs.append(float((xs[-1] - x_true).norm(dim=-1).max()))
        # constant ω: the midpoint rotation update is exact
        assert torch.allclose(qs[-1], q_true, atol=1e-12)
    assert errs[0] / errs[1] > 3.5 and errs[1] / errs[2] > 3.5, errs  # second order: error / 4 per halving
    # substeps split each frame: 2 substeps of 20 frames == 40 frames
    xs2, _ = integrate(f, h, x0, None, 20, T / 20, substeps=2)
    assert float((xs2[-1] - x_true).norm(dim=-1).max()) == pytest.approx(errs[2], rel=1e-9)


def test_gradients_reach_every_network():
    f = _fields(patterns=4)
    with torch.no_grad():
        f.f_weight[-1].weight.normal_(0, 0.3)
    x0 = torch.rand(20, 3, dtype=torch.float64)
    h = f.mixture(f.code(x0))
    xs, _ = integrate(f, h, x0, None, 5, 0.1)
    loss = (xs[-1] ** 2).sum() + f.materials(x0)["E"].log().sum()
    loss.backward()
    for name in ("f_vel", "f_neck", "f_weight", "f_mat"):
        g = torch.cat([p.grad.flatten() for p in getattr(f, name).parameters()])
        assert float(g.abs().max()) > 0, name
    assert float(f.centres.grad.abs().max()) > 0


def test_velocity_gradcheck_float64():
    f = _fields(patterns=2, width=8, depth=1, pos_freqs=1, time_freqs=1)
    with torch.no_grad():
        f.f_weight[-1].weight.normal_(0, 0.5)
    p = torch.rand(4, 3, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda q: f.velocity(q, 0.3), (p,))


def test_pattern_motion_blend_equals_per_particle_rk2_for_one_pattern_particles():
    """Stepping each pattern's affine map is exactly stepping its points; a particle of one pattern moves (and
    rotates) as the per-particle integrator moves it, whatever the twists do in time."""
    from causalgs.model.kinematic import blend, pattern_motion

    f = _fields(patterns=3)
    with torch.no_grad():
        f.f_weight[-1].weight.normal_(0, 0.5)
        f.f_weight[-1].bias.normal_(0, 0.5)
    torch.manual_seed(2)
    x0 = torch.randn(12, 3, dtype=torch.float64)
    q0 = torch.randn(12, 4, dtype=torch.float64)
    h = torch.nn.functional.one_hot(torch.arange(12) % 3, 3).double()
    xs, qs = integrate(f, h, x0, q0, 8, 0.05, substeps=2)
    R, t, q = pattern_motion(f, 8, 0.05, substeps=2)
    for k in (0, 3, 8):
        x, r = blend(h, x0, q0, R[k], t[k], q[k])
        assert torch.allclose(x, xs[k], atol=1e-12)
        # the same rotation (a quaternion and its negative are one rotation)
        assert torch.allclose((r * qs[k]).sum(-1).abs(), torch.ones(12, dtype=torch.float64), atol=1e-12)
    # A mixed particle moves with the h-weighted blend of its patterns' rigid motions.
    hm = torch.tensor([[0.25, 0.75, 0.0]], dtype=torch.float64)
    x, _ = blend(hm, x0[:1], None, R[8], t[8], q[8])
    expect = 0.25 * (R[8][0] @ x0[0] + t[8][0]) + 0.75 * (R[8][1] @ x0[0] + t[8][1])
    assert torch.allclose(x[0], expect, atol=1e-12)


def test_reframed_fields_describe_the_same_motion():
    """Re-posed by x' = s R x + t, a material point keeps its code, mixture and material, and its velocity turns
    with the world (v' = s R v), at every time."""
    from causalgs.similarity import Similarity, random_rotation

    f = _fields()
    with torch.no_grad():
        for p in f.parameters():
            p.add_(0.2 * torch.randn_like(p))
    sim = Similarity.make(random_rotation(0), 0.3, [1.0, -2.0, 0.5])
    x = torch.rand(40, 3, dtype=torch.float64) * 2 - 1
    h = f.mixture(f.code(x))
    before = {"h": h, "E": f.materials(x, h)["E"], "v": [f.velocity(x, t, h) for t in (0.0, 0.4, 0.9)]}
    f.reframe(sim)
    y = torch.as_tensor(sim.points(x.numpy()))
    h2 = f.mixture(f.code(y))
    assert torch.allclose(h2, before["h"], atol=1e-12)
    assert torch.allclose(f.materials(y, h2)["E"], before["E"], rtol=1e-12)
    for t, v in zip((0.0, 0.4, 0.9), before["v"], strict=True):
        assert torch.allclose(f.velocity(y, t, h2), torch.as_tensor(sim.vectors(v.detach().numpy())), atol=1e-12)


def test_frame_twists_add_one_twist_per_frame_interpolated_and_held_after_the_window():
    """T(t): at a frame's time its own twist, linear between frames, the last one after the window; zero at the
    start (the MLP alone); none when switched off."""
    f = _fields(patterns=3)
    t = torch.tensor([0.0, 0.1, 0.15, 0.95, 1.0, 1.7], dtype=torch.float64)
    mlp_only = f.twists(t).detach()
    with torch.no_grad():
        f.frame_twists.normal_()
    T = f.frame_twists.detach()
    W = f.twists(t).detach() - mlp_only
    assert torch.allclose(W[0], T[0]) and torch.allclose(W[1], T[1]) and torch.allclose(W[4], T[10])
    assert torch.allclose(W[2], 0.5 * (T[1] + T[2])) and torch.allclose(W[3], 0.5 * (T[9] + T[10]))
    assert torch.allclose(W[5], T[10])  # held after the window
    assert len(_fields(frame_twists=False).frame_twists) == 0 and len(_fields(frames=0).frame_twists) == 0


def test_frame_twists_gradcheck_float64():
    """Twists through the model's own path against finite differences in the per-frame table (and time)."""
    f = _fields(patterns=2, width=8, depth=1, pos_freqs=1, time_freqs=1, frames=5)

    class Twists(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.f = f

        def forward(self, t):
            return self.f.twists(t)

    T = torch.randn(5, 2, 6, dtype=torch.float64, requires_grad=True)
    t = torch.tensor([0.0, 0.33, 0.6, 1.4], dtype=torch.float64)
    model = Twists()
    assert torch.autograd.gradcheck(lambda table: torch.func.functional_call(model, {"f.frame_twists": table}, (t,)),
                                    (T,))  # fmt: skip


def test_a_global_material_is_one_material_for_every_particle_and_learns():
    """``materials = "global"`` (the IPI ablation): every particle gets the same E, nu, density, whatever its place
    or pattern, and its gradient reaches the one vector that holds it."""
    f = _fields(materials="global", patterns=3)
    with torch.no_grad():
        for q in f.parameters():
            q.add_(0.5 * torch.randn_like(q))
    p = torch.rand(30, 3, dtype=torch.float64) * 2 - 1
    m = f.materials(p, f.mixture(f.code(p)))
    assert torch.allclose(m["E"], m["E"][0].expand(30), rtol=1e-14) and torch.allclose(m["nu"], m["nu"][0].expand(30))
    m["E"].log().sum().backward()
    assert float(f.f_mat[-1].bias.grad.abs().max()) > 0 and f.pattern_materials.grad is None
    with pytest.raises(CausalGSError, match="materials"):
        FieldsConfig(materials="per-body")


def test_a_pattern_turns_about_the_centre_it_carries():
    """With moving centres (the default) u_k is the velocity of the pattern's centre and ω_k its spin: a body whose
    centre is its mass centre travels in a straight line while it turns, whatever the spin; with a fixed centre the
    same twist swings it around a point in space."""
    from causalgs.model.kinematic import pattern_motion

    f = _fields(patterns=1, frames=0)
    with torch.no_grad():
        f.f_weight[-1].weight.zero_()
        f.f_weight[-1].bias.copy_(torch.tensor([0.5, 0.0, 0.2, 0.0, 3.0, 1.0], dtype=torch.float64))
    x0 = torch.rand(50, 3, dtype=torch.float64) * 0.2 + torch.tensor([0.4, -0.3, 0.1], dtype=torch.float64)
    h = torch.ones(50, 1, dtype=torch.float64)
    gyration = f.place_centres(x0, h)
    assert torch.allclose(f.centres[0], x0.mean(0))
    assert torch.allclose(gyration[0], (x0 - x0.mean(0)).square().sum(-1).mean().sqrt())
    xs, _ = integrate(f, h, x0, None, 20, 0.05, substeps=2)
    t = torch.arange(21, dtype=torch.float64)[:, None] * 0.05
    path = x0.mean(0) + t * torch.tensor([0.5, 0.0, 0.2], dtype=torch.float64)
    assert float((xs.mean(1) - path).norm(dim=-1).max()) < 1e-12  # the mass centre moves with u exactly
    spread = (xs - xs.mean(1, keepdim=True)).norm(dim=-1)
    assert torch.allclose(spread, spread[:1].expand_as(spread), atol=1e-3)  # and the body only turns about it
    R, tr, _ = pattern_motion(f, 20, 0.05, 2)
    assert torch.allclose((R[:, 0] @ x0.T).transpose(1, 2) + tr[:, 0, None], xs, atol=1e-12)
    with torch.no_grad():
        f.moving_centres.fill_(False)
    fixed, _ = integrate(f, h, x0, None, 20, 0.05, substeps=2)
    assert float((fixed.mean(1) - path).norm(dim=-1).max()) > 0.05


def _flow_fields(**kw) -> InversePhysics:
    f = _fields(velocity="mlp", **kw)
    with torch.no_grad():
        for p in f.flow.parameters():
            p.add_(0.3 * torch.randn_like(p))
    return f


def test_the_unstructured_field_starts_at_rest_and_integrates_by_the_midpoint_rule():
    """VFD off (fields.velocity=mlp): v(x0, t) per material point, zero-ish at the start; its paths are the midpoint
    sums of a plain loop over the velocity at every half step, with substeps refining the same rule."""
    f0 = _fields(velocity="mlp")
    x0 = torch.rand(30, 3, dtype=torch.float64) * 2 - 1
    assert float(f0.velocity(x0, 0.3).detach().abs().max()) < 0.05 and not f0.structured and _fields().structured
    f = _flow_fields()
    dt, steps = 0.1, 6
    ref, x = [x0], x0
    for j in range(steps):
        x = x + dt * f.velocity(x0, (j + 0.5) * dt)
        ref.append(x)
    assert torch.allclose(flow_paths(f, x0, steps, dt), torch.stack(ref), atol=1e-12)
    fine = flow_paths(f, x0, steps, dt, substeps=2)
    ref2, x = [x0], x0
    for j in range(2 * steps):
        x = x + 0.5 * dt * f.velocity(x0, (j + 0.5) * 0.5 * dt)
        if j % 2 == 1:
            ref2.append(x)
    assert torch.allclose(fine, torch.stack(ref2), atol=1e-12)
    assert torch.equal(flow_paths(f, x0, 0, dt), x0[None])
    with pytest.raises(CausalGSError, match="fields.velocity"):
        FieldsConfig(velocity="grid")


def test_unstructured_paths_gradcheck_float64():
    """The paths against finite differences in the flow's weights and the canonical positions."""
    f = _flow_fields(width=6, pos_freqs=1, time_freqs=1)
    x0 = (torch.rand(4, 3, dtype=torch.float64) * 2 - 1).requires_grad_(True)

    class Paths(torch.nn.Module):  # flow_paths as a function of the fields' parameters (functional_call)
        def __init__(self):
            super().__init__()
            self.f = f

        def forward(self, x):
            return flow_paths(self.f, x, 3, 0.2)

    paths_of = Paths()

    def paths(x, weight):
        return torch.func.functional_call(paths_of, {"f.flow.out.weight": weight}, (x,))

    weight = f.flow.out.weight.detach().clone().requires_grad_(True)
    assert torch.autograd.gradcheck(paths, (x0, weight), eps=1e-6, atol=1e-8)


def test_the_unstructured_field_turns_with_the_world():
    """Re-posed by x' = s R x + t, the material point's velocity becomes s R v at every time."""
    from causalgs.similarity import Similarity, random_rotation

    f = _flow_fields()
    sim = Similarity.make(random_rotation(1), 2.5, [0.3, 1.0, -1.0])
    x = torch.rand(20, 3, dtype=torch.float64) * 2 - 1
    before = [f.velocity(x, t).detach() for t in (0.0, 0.5)]
    f.reframe(sim)
    y = torch.as_tensor(sim.points(x.numpy()))
    for t, v in zip((0.0, 0.5), before, strict=True):
        assert torch.allclose(f.velocity(y, t), torch.as_tensor(sim.vectors(v.numpy())), atol=1e-12)
