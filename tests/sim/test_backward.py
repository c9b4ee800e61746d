"""The checkpointed backward and its torch boundary against float64 finite differences and a full tape.

One scene exercises every registered effect at once (each with a parameter that matters): an elastoplastic block
thrown against a tilted Coulomb ground (on grid nodes), a tilted Coulomb floor (met by the particles) and a sticky
side plane, under gravity, a force field, linear and quadratic drag, an attractor and material damping. Its rollout
spans several checkpoint segments; a loss on positions, velocities and deformation gradients at three output times
is differentiated with respect to x0, v0, E, nu, density and every effect parameter. The substep is fixed
(``SimConfig.dt``) so that finite differences see the same schedule.
"""

from __future__ import annotations

import math

import pytest
import torch

from causalgs.errors import CausalGSError
from causalgs.sim import REGISTRY, SimConfig, Simulator
from causalgs.sim.autograd import simulate

pytestmark = [pytest.mark.gradcheck]

D = torch.float64
SPEC = (
    "gravity:g=0.5,-0.3,-9.8;force:b=0.4,0.8,0.3;linear_drag:c=0.6;quadratic_drag:k=0.8;"
    "ground:n=0.1,0.05,1:d=0.12:mu=0.4;ground_sticky:n=-1,0,0.02:d=-0.575;damping:eta=40;"
    "plasticity:yield_stress=300;attractor:k=2.0:c=0.5,0.45,0.3;floor:n=-0.05,0.1,1:d=0.165:mu=0.3;walls"
)
TIMES = (0.012, 0.03, 0.042)  # with dt = 3 ms: 14 substeps, 7 segments of 2 (outputs inside and at segment ends)
DT = 3e-3


def _scene(mk, segment: int):
    x0 = mk.block((0.52, 0.5, 0.175), count=4)
    n = len(x0)
    store = mk.store(n)
    mk.fill(store, x0, E=2e4, nu=0.3, density=800.0)
    sim = Simulator(store, SimConfig(res=16, effects=SPEC, segment=segment, dt=DT))
    g = torch.Generator().manual_seed(5)
    r = x0 - x0.mean(0)
    v0 = torch.tensor([0.6, 0.2, -0.9], dtype=D) + torch.linalg.cross(torch.tensor([2.0, -1.0, 3.0], dtype=D)
                                                                     .expand(n, 3), r)  # fmt: skip
    v0 = v0 + 0.05 * torch.randn(n, 3, generator=g, dtype=D)
    E = 2e4 * (1 + 0.2 * torch.rand(n, generator=g, dtype=D))
    nu = 0.25 + 0.1 * torch.rand(n, generator=g, dtype=D)
    rho = 800.0 * (1 + 0.2 * torch.rand(n, generator=g, dtype=D))
    params = torch.as_tensor(sim.effects.flat(), dtype=D)
    w = {
        "x": torch.randn(len(TIMES), n, 3, generator=g, dtype=D),
        "v": torch.randn(len(TIMES), n, 3, generator=g, dtype=D),
        "F": torch.randn(len(TIMES), n, 3, 3, generator=g, dtype=D),
    }
    return sim, {"x0": x0, "v0": v0, "E": E, "nu": nu, "density": rho, "params": params}, w


def _loss(sim, inp, w):
    x, v, F = simulate(sim, inp["x0"], inp["v0"], inp["E"], inp["nu"], inp["density"], TIMES, inp["params"])
    return (w["x"] * x).sum() + 0.1 * (w["v"] * v).sum() + (w["F"] * F).sum()


def test_every_effect_parameter_is_exercised():
    names = {part.split(":")[0] for part in SPEC.split(";")}
    assert names == set(REGISTRY), "the gradient scene must use every registered effect"


def test_gradients_match_finite_differences(ti64, mk):
    sim, inp, w = _scene(mk, segment=2)
    leaves = {k: v.clone().requires_grad_(True) for k, v in inp.items()}
    loss = _loss(sim, leaves, w)
    loss.backward()
    assert sum(len(s.dts) for s in sim_tape_segments(sim, inp, w)) == 14
    g = torch.Generator().manual_seed(11)

    def check(name, direction, h, label):
        ad = float((leaves[name].grad * direction).sum())
        plus = {**inp, name: inp[name] + h * direction}
        minus = {**inp, name: inp[name] - h * direction}
        with torch.no_grad():
            num = (float(_loss(sim, plus, w)) - float(_loss(sim, minus, w))) / (2 * h)
        assert math.isfinite(ad) and abs(num) > 1e-8, f"{label}: derivative {num:.3g} too small to test"
        rel = abs(ad - num) / abs(num)
        assert rel < 1e-4, f"{label}: autodiff {ad:.10g} vs finite differences {num:.10g} (relative {rel:.2g})"

    # Per-particle inputs along random directions (relative steps for the materials).
    check("x0", torch.randn(inp["x0"].shape, generator=g, dtype=D), 1e-6, "x0")
    check("v0", torch.randn(inp["v0"].shape, generator=g, dtype=D), 1e-6, "v0")
    for name in ("E", "nu", "density"):
        direction = inp[name] * torch.randn(inp[name].shape, generator=g, dtype=D) * (0.1 if name == "nu" else 1)
        check(name, direction, 1e-6, name)
    # Every effect parameter on its own.
    names = sim.effects.param_names()
    assert len(names) == len(inp["params"])
    for i, label in enumerate(names):
        e = torch.zeros(len(names), dtype=D)
        e[i] = 1.0
        check("params", e, 1e-6 * max(1.0, abs(float(inp["params"][i]))), label)


def sim_tape_segments(sim, inp, w):
    """The segments of a fresh rollout of the scene (to check it spans several checkpoints)."""
    for name in ("E", "nu", "density"):
        sim.store.from_torch(name, inp[name])
    sim.set_state(inp["x0"], inp["v0"])
    _, tape = sim.rollout(TIMES)
    return tape.segments


def test_checkpointed_equals_full_tape(ti64, mk):
    """Segments of 2 substeps (7 checkpoints, 6 replays) against one segment holding all 14 substeps."""
    grads = []
    for segment in (2, 16):
        sim, inp, w = _scene(mk, segment=segment)
        leaves = {k: v.clone().requires_grad_(True) for k, v in inp.items()}
        _loss(sim, leaves, w).backward()
        grads.append({k: v.grad for k, v in leaves.items()})
    for k in grads[0]:
        scale = float(grads[1][k].abs().max())
        err = float((grads[0][k] - grads[1][k]).abs().max())
        assert err <= 1e-10 * max(scale, 1.0), f"{k}: checkpointed and full-tape gradients differ by {err:.3g}"


def test_backward_after_another_rollout(ti64, mk):
    """A second forward between a forward and its backward does not change the first one's gradients."""
    sim, inp, w = _scene(mk, segment=2)
    a = {k: v.clone().requires_grad_(True) for k, v in inp.items()}
    _loss(sim, a, w).backward()
    b = {k: v.clone().requires_grad_(True) for k, v in inp.items()}
    loss_b = _loss(sim, b, w)
    other = {**inp, "E": inp["E"] * 2, "v0": -inp["v0"]}
    with torch.no_grad():
        _loss(sim, other, w)
    loss_b.backward()
    for k in a:
        assert torch.allclose(a[k].grad, b[k].grad, rtol=1e-10, atol=1e-12), k


def test_bad_inputs_are_one_line_errors(ti64, mk):
    sim, inp, _ = _scene(mk, segment=2)
    with pytest.raises(CausalGSError, match=r"x0 has shape \[3, 3\]"):
        simulate(sim, inp["x0"][:3], inp["v0"], inp["E"], inp["nu"], inp["density"], TIMES)
    with pytest.raises(CausalGSError, match="sorted"):
        simulate(sim, inp["x0"], inp["v0"], inp["E"], inp["nu"], inp["density"], (0.02, 0.01))
    with pytest.raises(CausalGSError, match=r"effect parameters: got 2 values"):
        simulate(sim, inp["x0"], inp["v0"], inp["E"], inp["nu"], inp["density"], TIMES, torch.zeros(2, dtype=D))
    with pytest.raises(CausalGSError, match=r"material 'nu' has shape"):
        simulate(sim, inp["x0"], inp["v0"], inp["E"], inp["nu"][:5], inp["density"], TIMES)


@pytest.mark.slow
def test_hand_written_p2g_adjoint_equals_autodiff(ti64, mk):
    """p2g_adjoint against Taichi's own autodiff of p2g (slow: p2g.grad compiles for about a minute)."""
    from causalgs.sim import kernels

    sim, inp, _ = _scene(mk, segment=2)
    st, g = sim.store, sim.grid
    n = st.n
    gen = torch.Generator().manual_seed(3)
    sim.set_state(inp["x0"] + 0.01 * torch.randn(n, 3, generator=gen, dtype=D), inp["v0"])
    st.from_torch("mpm_affine", torch.randn(n, 3, 3, generator=gen, dtype=D))
    kernels.particle_box(st.x_seg, 0, n, sim._lo(), sim.geo.inv_dx, sim.geo.shape, g.box)
    g.v_in.grad.from_torch(torch.randn(*g.v_in.shape, 3, generator=gen, dtype=D))
    g.m.grad.from_torch(torch.randn(*g.m.shape, generator=gen, dtype=D))
    out = []
    for kernel in (kernels.p2g.grad, kernels.p2g_adjoint):
        st.zero_grad(["x_seg", "v_seg", "mpm_affine", "density"])
        kernel(*sim._p2g_args(0))
        out.append([st.to_torch(k, grad=True) for k in ("x_seg", "v_seg", "mpm_affine", "density")])
    for a, b, name in zip(*out, ("x", "v", "affine", "density"), strict=True):
        assert torch.allclose(a, b, rtol=1e-12, atol=1e-12 * float(a.abs().max())), name


@pytest.mark.slow
def test_hand_written_g2p_adjoint_equals_autodiff(ti64, mk):
    """g2p_adjoint against Taichi's own autodiff of g2p (slow: g2p.grad compiles for tens of seconds)."""
    from causalgs.sim import kernels

    sim, inp, _ = _scene(mk, segment=2)
    st, g, geo = sim.store, sim.grid, sim.geo
    n = st.n
    gen = torch.Generator().manual_seed(4)
    sim.set_state(inp["x0"] + 0.01 * torch.randn(n, 3, generator=gen, dtype=D), inp["v0"])
    kernels.particle_box(st.x_seg, 0, n, sim._lo(), geo.inv_dx, geo.shape, g.box)
    g.v_out.from_torch(torch.randn(*g.v_out.shape, 3, generator=gen, dtype=D))
    seeds = {"x_seg": (3,), "v_seg": (3,), "C_seg": (3, 3)}
    out = []
    for kernel in (kernels.g2p.grad, kernels.g2p_adjoint):
        st.zero_grad(list(seeds))
        g.v_out.grad.fill(0)
        for k, shape in seeds.items():
            st.from_torch(k, torch.randn(n, *shape, generator=torch.Generator().manual_seed(9), dtype=D), grad=True,
                          slot=1)  # fmt: skip
        kernel(st.x_seg, st.v_seg, st.C_seg, g.v_out, 0, n, 1e-3, sim._lo(), geo.inv_dx)
        out.append([st.to_torch("x_seg", grad=True, slot=0), g.v_out.grad.to_torch()])
    for a, b, name in zip(*out, ("x", "grid v_out"), strict=True):
        assert torch.allclose(a, b, rtol=1e-12, atol=1e-12 * float(a.abs().max())), name
