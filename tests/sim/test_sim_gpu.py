"""The simulator on CUDA (float64): its substeps against the plain-torch reference and its checkpointed backward
against finite differences, with every registered effect. The same kernels are checked on the CPU by
``test_mpm_reference.py`` and ``test_backward.py``; here they are compiled for the GPU, where the particle-to-grid
scatter runs as concurrent atomic adds in an order that changes from run to run. Skipped without a CUDA device."""

from __future__ import annotations

import math

import pytest
import torch

from causalgs.sim import MODELS, REGISTRY, SimConfig, Simulator
from causalgs.sim.autograd import simulate
from causalgs.sim.reference import effects_list, substep

pytestmark = [pytest.mark.gpu]

D = torch.float64
SPEC = (
    "gravity:g=0.5,-0.3,-9.8;force:b=0.4,0.8,0.3;linear_drag:c=0.6;quadratic_drag:k=0.8;"
    "ground:n=0.1,0.05,1:d=0.12:mu=0.4;ground_sticky:n=-1,0,0.02:d=-0.575;damping:eta=40;"
    "plasticity:yield_stress=300;attractor:k=2.0:c=0.5,0.45,0.3;floor:n=-0.05,0.1,1:d=0.165:mu=0.3;walls"
)


def test_the_scene_uses_every_registered_effect():
    assert {part.split(":")[0] for part in SPEC.split(";")} == set(REGISTRY)


def _state(n: int, seed: int) -> tuple[dict, dict]:
    """Particles spread over the box (in the wall band, below the floor and grounds, in flight) and random materials."""
    g = torch.Generator().manual_seed(seed)
    state = {
        "x": torch.rand(n, 3, generator=g, dtype=D) * 0.8 + 0.1,
        "v": torch.randn(n, 3, generator=g, dtype=D),
        "C": torch.randn(n, 3, 3, generator=g, dtype=D) * 0.5,
        "F": torch.eye(3, dtype=D) + 0.1 * torch.randn(n, 3, 3, generator=g, dtype=D),
    }
    mat = {
        "vol": torch.rand(n, generator=g, dtype=D) * 1e-4 + 1e-4,
        "density": torch.rand(n, generator=g, dtype=D) * 1e3 + 5e2,
        "E": torch.rand(n, generator=g, dtype=D) * 9e3 + 1e3,
        "nu": torch.rand(n, generator=g, dtype=D) * 0.2 + 0.2,
    }
    return state, mat


@pytest.mark.parametrize("model", list(MODELS))
def test_cuda_substeps_match_reference(cuda64, mk, model):
    n, steps, dt = 400, 3, 1e-3
    store = mk.store(n)
    state, mat = _state(n, seed=2)
    for k, t in mat.items():
        store.from_torch(k, t)
    cfg = SimConfig(res=16, material=model, effects=SPEC, segment=8)
    sim = Simulator(store, cfg)
    sim.set_state(**state)
    sim.step(steps, dt)
    got = sim.state()
    ref, geo = dict(state), cfg.geometry
    for _ in range(steps):
        ref = substep(ref, mat, dt, geo.lo, geo.dx, geo.shape, model, effects_list(SPEC))
    for k in ("x", "v", "C", "F"):
        assert got[k].device.type == "cpu" and got[k].dtype == D
        scale = max(1.0, float(ref[k].abs().max()))
        err = float((got[k] - ref[k]).abs().max())
        assert err <= 1e-10 * scale, f"{model}: {k} differs by {err:.3g} (scale {scale:.3g})"


def _throw(mk):
    """An elastoplastic block thrown with a spin against the grounds, floor and sticky plane of SPEC, over 14
    substeps of 3 ms in checkpoint segments of 2."""
    x0 = mk.block((0.52, 0.5, 0.175), count=4)
    n = len(x0)
    store = mk.store(n)
    mk.fill(store, x0, E=2e4, nu=0.3, density=800.0)
    sim = Simulator(store, SimConfig(res=16, effects=SPEC, segment=2, dt=3e-3))
    g = torch.Generator().manual_seed(5)
    r = x0 - x0.mean(0)
    spin = torch.linalg.cross(torch.tensor([2.0, -1.0, 3.0], dtype=D).expand(n, 3), r)
    inp = {
        "x0": x0,
        "v0": torch.tensor([0.6, 0.2, -0.9], dtype=D) + spin + 0.05 * torch.randn(n, 3, generator=g, dtype=D),
        "E": 2e4 * (1 + 0.2 * torch.rand(n, generator=g, dtype=D)),
        "nu": 0.25 + 0.1 * torch.rand(n, generator=g, dtype=D),
        "density": 800.0 * (1 + 0.2 * torch.rand(n, generator=g, dtype=D)),
        "params": torch.as_tensor(sim.effects.flat(), dtype=D),
    }
    times = (0.012, 0.03, 0.042)
    w = [torch.randn(len(times), n, *shape, generator=g, dtype=D) for shape in ((3,), (3,), (3, 3))]

    def loss(q):
        x, v, F = simulate(sim, q["x0"], q["v0"], q["E"], q["nu"], q["density"], times, q["params"])
        return (w[0] * x).sum() + 0.1 * (w[1] * v).sum() + (w[2] * F).sum()

    return sim, inp, loss


@pytest.mark.gradcheck
def test_cuda_gradients_match_finite_differences(cuda64, mk):
    sim, inp, loss = _throw(mk)
    leaves = {k: v.clone().requires_grad_(True) for k, v in inp.items()}
    loss(leaves).backward()
    g = torch.Generator().manual_seed(11)

    def check(name, direction, h, label):
        ad = float((leaves[name].grad * direction).sum())
        with torch.no_grad():
            num = (float(loss({**inp, name: inp[name] + h * direction}))
                   - float(loss({**inp, name: inp[name] - h * direction}))) / (2 * h)  # fmt: skip
        assert math.isfinite(ad) and abs(num) > 1e-8, f"{label}: derivative {num:.3g} too small to test"
        rel = abs(ad - num) / abs(num)
        assert rel < 1e-4, f"{label}: autodiff {ad:.10g} vs finite differences {num:.10g} (relative {rel:.2g})"

    check("x0", torch.randn(inp["x0"].shape, generator=g, dtype=D), 1e-6, "x0")
    check("v0", torch.randn(inp["v0"].shape, generator=g, dtype=D), 1e-6, "v0")
    for name in ("E", "nu", "density"):
        direction = inp[name] * torch.randn(inp[name].shape, generator=g, dtype=D) * (0.1 if name == "nu" else 1)
        check(name, direction, 1e-6, name)
    names = sim.effects.param_names()
    for i, label in enumerate(names):
        e = torch.zeros(len(names), dtype=D)
        e[i] = 1.0
        check("params", e, 1e-6 * max(1.0, abs(float(inp["params"][i]))), label)


def test_cuda_backward_is_repeatable(cuda64, mk):
    """Two backward passes of one rollout agree to round-off, though the GPU's atomic adds sum in varying order."""
    _, inp, loss = _throw(mk)
    grads = []
    for _ in range(2):
        leaves = {k: v.clone().requires_grad_(True) for k, v in inp.items()}
        loss(leaves).backward()
        grads.append({k: v.grad for k, v in leaves.items()})
    for k in grads[0]:
        scale = max(1.0, float(grads[0][k].abs().max()))
        assert float((grads[0][k] - grads[1][k]).abs().max()) <= 1e-9 * scale, k
