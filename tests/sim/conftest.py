"""Shared helpers for the simulator tests: one ParticleStore per Taichi runtime, reused across tests (every new store
is a new set of fields and so a new compile of every MPM kernel), and small particle blocks."""

from __future__ import annotations

import itertools
import math
from types import SimpleNamespace

import pytest
import torch

DX = 1.0 / 16  # the tests' grid: res 16 on the unit box
SLOTS = 16  # substeps per segment the test store can hold (any test may use a segment up to this)
_stores: dict = {}


def shared_store(n: int):
    """The runtime's test store, emptied and resized to ``n`` rows (rows take their fill values)."""
    from causalgs import _ti
    from causalgs.sim.mpm import segment_specs
    from causalgs.store import ParticleStore

    key = _ti.generation()
    if key not in _stores:
        _stores.clear()
        _stores[key] = ParticleStore(0, sh_degree=0)
        _stores[key].add_fields(segment_specs(SLOTS))
    store = _stores[key]
    store.resize(0)
    store.resize(n)
    return store


def block(center, count: int = 6, spacing: float = DX / 2, dtype=torch.float64) -> torch.Tensor:
    """A cube of count³ lattice points around ``center`` (8 particles per cell at the default spacing)."""
    idx = torch.tensor(list(itertools.product(range(count), repeat=3)), dtype=dtype)
    return torch.tensor(center, dtype=dtype) + (idx - (count - 1) / 2) * spacing


def fill_block(store, x: torch.Tensor, E: float = 1.0e4, nu: float = 0.3, density: float = 1.0e3, spacing=DX / 2):
    """Write positions and uniform materials; each particle carries the mass of its lattice cell."""
    n = len(x)
    vol = spacing**3
    store.from_torch("x", x)
    store.from_torch("vol", torch.full((n,), vol))
    store.from_torch("mass", torch.full((n,), density * vol))
    store.from_torch("E", torch.full((n,), E))
    store.from_torch("nu", torch.full((n,), nu))
    store.from_torch("density", torch.full((n,), density))


def random_materials(n: int, seed: int) -> dict[str, torch.Tensor]:
    """Per-particle volumes, densities, Young's moduli and Poisson ratios drawn around a soft solid's (float64)."""
    g = torch.Generator().manual_seed(seed)
    d = torch.float64
    return {
        "vol": torch.rand(n, generator=g, dtype=d) * 1e-4 + 1e-4,
        "density": torch.rand(n, generator=g, dtype=d) * 1e3 + 5e2,
        "E": torch.rand(n, generator=g, dtype=d) * 9e3 + 1e3,
        "nu": torch.rand(n, generator=g, dtype=d) * 0.2 + 0.2,
    }


def random_state(n: int, seed: int) -> dict[str, torch.Tensor]:
    """A random MPM state (float64): positions spread over the box, so some particles sit in the wall band and the
    walls term acts; velocities, affine velocities and deformation gradients near the identity."""
    g = torch.Generator().manual_seed(seed)
    d = torch.float64
    return {
        "x": torch.rand(n, 3, generator=g, dtype=d) * 0.8 + 0.1,
        "v": torch.randn(n, 3, generator=g, dtype=d),
        "C": torch.randn(n, 3, 3, generator=g, dtype=d) * 0.5,
        "F": torch.eye(3, dtype=d) + 0.1 * torch.randn(n, 3, 3, generator=g, dtype=d),
    }


def run_against_reference(store, state, mat, cfg, steps: int, dt: float, label: str = "") -> dict:
    """Write ``mat`` into ``store``, take ``steps`` substeps of ``dt`` from ``state`` with the Taichi simulator of
    ``cfg`` and with the plain-torch reference, assert they agree to 1e-10 (relative to each quantity's scale), and
    return the simulator's state."""
    from causalgs.sim import Simulator
    from causalgs.sim.reference import effects_list, substep

    for k, t in mat.items():
        store.from_torch(k, t)
    sim = Simulator(store, cfg)
    sim.set_state(**state)
    sim.step(steps, dt)
    got = sim.state()
    ref, geo, effects = dict(state), cfg.geometry, effects_list(cfg.effects)
    for _ in range(steps):
        ref = substep(ref, mat, dt, geo.lo, geo.dx, geo.shape, cfg.material, effects)
    for k in ("x", "v", "C", "F"):
        assert got[k].device.type == "cpu" and got[k].dtype == torch.float64, f"{label}{k}: {got[k].dtype}"
        scale = max(1.0, float(ref[k].abs().max()))
        err = float((got[k] - ref[k]).abs().max())
        assert err <= 1e-10 * scale, f"{label}{k} differs by {err:.3g} (scale {scale:.3g})"
    assert abs(sim.time - steps * dt) < 1e-15
    return got


# Every registered effect, each with a parameter that matters for the throw below.
ALL_EFFECTS = (
    "gravity:g=0.5,-0.3,-9.8;force:b=0.4,0.8,0.3;linear_drag:c=0.6;quadratic_drag:k=0.8;"
    "ground:n=0.1,0.05,1:d=0.12:mu=0.4;ground_sticky:n=-1,0,0.02:d=-0.575;damping:eta=40;"
    "plasticity:yield_stress=300;attractor:k=2.0:c=0.5,0.45,0.3;floor:n=-0.05,0.1,1:d=0.165:mu=0.3;walls"
)
THROW_TIMES = (0.012, 0.03, 0.042)  # with dt = 3 ms: 14 substeps, 7 segments of 2 (outputs inside and at segment ends)
THROW_DT = 3e-3


def throw(segment: int):
    """An elastoplastic block thrown with a spin against the grounds, floor and sticky plane of ``ALL_EFFECTS``
    (fixed substep, so finite differences see the same schedule): the simulator, the inputs of ``simulate`` with
    random per-particle materials, and random loss weights on positions, velocities and deformation gradients."""
    from causalgs.sim import SimConfig, Simulator

    d = torch.float64
    x0 = block((0.52, 0.5, 0.175), count=4)
    n = len(x0)
    store = shared_store(n)
    fill_block(store, x0, E=2e4, nu=0.3, density=800.0)
    sim = Simulator(store, SimConfig(res=16, effects=ALL_EFFECTS, segment=segment, dt=THROW_DT))
    g = torch.Generator().manual_seed(5)
    r = x0 - x0.mean(0)
    v0 = torch.tensor([0.6, 0.2, -0.9], dtype=d) + torch.linalg.cross(torch.tensor([2.0, -1.0, 3.0], dtype=d)
                                                                     .expand(n, 3), r)  # fmt: skip
    v0 = v0 + 0.05 * torch.randn(n, 3, generator=g, dtype=d)
    E = 2e4 * (1 + 0.2 * torch.rand(n, generator=g, dtype=d))
    nu = 0.25 + 0.1 * torch.rand(n, generator=g, dtype=d)
    rho = 800.0 * (1 + 0.2 * torch.rand(n, generator=g, dtype=d))
    params = torch.as_tensor(sim.effects.flat(), dtype=d)
    w = {
        "x": torch.randn(len(THROW_TIMES), n, 3, generator=g, dtype=d),
        "v": torch.randn(len(THROW_TIMES), n, 3, generator=g, dtype=d),
        "F": torch.randn(len(THROW_TIMES), n, 3, 3, generator=g, dtype=d),
    }
    return sim, {"x0": x0, "v0": v0, "E": E, "nu": nu, "density": rho, "params": params}, w


def throw_loss(sim, inp, w):
    """A weighted sum of the throw's positions, velocities and deformation gradients at ``THROW_TIMES``."""
    from causalgs.sim.autograd import simulate

    x, v, F = simulate(sim, inp["x0"], inp["v0"], inp["E"], inp["nu"], inp["density"], THROW_TIMES, inp["params"])
    return (w["x"] * x).sum() + 0.1 * (w["v"] * v).sum() + (w["F"] * F).sum()


def throw_gradients(segment: int) -> dict:
    """The throw's loss (``"loss"``) and its gradient for every input of :func:`throw`, by name."""
    sim, inp, w = throw(segment)
    leaves = {k: v.clone().requires_grad_(True) for k, v in inp.items()}
    loss = throw_loss(sim, leaves, w)
    loss.backward()
    return {"loss": loss.detach(), **{k: v.grad for k, v in leaves.items()}}


def check_gradients(sim, inp, w, seed: int = 11) -> None:
    """The throw's autodiff gradients against float64 central differences: x0 and v0 along random directions, the
    materials along random relative directions, every effect parameter on its own."""
    d = torch.float64
    leaves = {k: v.clone().requires_grad_(True) for k, v in inp.items()}
    throw_loss(sim, leaves, w).backward()
    g = torch.Generator().manual_seed(seed)

    def check(name, direction, h, label):
        ad = float((leaves[name].grad * direction).sum())
        plus = {**inp, name: inp[name] + h * direction}
        minus = {**inp, name: inp[name] - h * direction}
        with torch.no_grad():
            num = (float(throw_loss(sim, plus, w)) - float(throw_loss(sim, minus, w))) / (2 * h)
        assert math.isfinite(ad) and abs(num) > 1e-8, f"{label}: derivative {num:.3g} too small to test"
        rel = abs(ad - num) / abs(num)
        assert rel < 1e-4, f"{label}: autodiff {ad:.10g} vs finite differences {num:.10g} (relative {rel:.2g})"

    check("x0", torch.randn(inp["x0"].shape, generator=g, dtype=d), 1e-6, "x0")
    check("v0", torch.randn(inp["v0"].shape, generator=g, dtype=d), 1e-6, "v0")
    for name in ("E", "nu", "density"):
        direction = inp[name] * torch.randn(inp[name].shape, generator=g, dtype=d) * (0.1 if name == "nu" else 1)
        check(name, direction, 1e-6, name)
    names = sim.effects.param_names()
    assert len(names) == len(inp["params"])
    for i, label in enumerate(names):
        e = torch.zeros(len(names), dtype=d)
        e[i] = 1.0
        check("params", e, 1e-6 * max(1.0, abs(float(inp["params"][i]))), label)


@pytest.fixture
def mk():
    """Helpers: ``mk.store(n)``, ``mk.block(center, count)``, ``mk.fill(store, x, E=...)``, ``mk.DX``,
    ``mk.materials(n, seed)``, ``mk.state(n, seed)``, ``mk.against_reference(store, state, mat, cfg, steps, dt)``;
    the throw with every effect: ``mk.throw(segment)``, ``mk.throw_loss``, ``mk.throw_gradients(segment)``,
    ``mk.check_gradients``,
    ``mk.ALL_EFFECTS``, ``mk.THROW_TIMES``."""
    return SimpleNamespace(
        store=shared_store, block=block, fill=fill_block, DX=DX, materials=random_materials, state=random_state,
        against_reference=run_against_reference, throw=throw,
        throw_loss=throw_loss, throw_gradients=throw_gradients, check_gradients=check_gradients,
        ALL_EFFECTS=ALL_EFFECTS, THROW_TIMES=THROW_TIMES,
    )  # fmt: skip
