"""The Taichi MLS-MPM substep against the plain-torch reference (float64), for every material model."""

from __future__ import annotations

import pytest
import torch

from causalgs.sim import MODELS, SimConfig, Simulator
from causalgs.sim.reference import kirchhoff
from causalgs.store import ParticleStore

SPEC = "gravity:g=0.3,-1,-9.8;linear_drag:c=0.7;walls"


@pytest.mark.parametrize("model", list(MODELS))
@pytest.mark.parametrize("substeps", [1, 3])
def test_substeps_match_reference(ti64, mk, model, substeps):
    n = 200
    cfg = SimConfig(res=16, material=model, effects=SPEC, segment=8)
    mk.against_reference(mk.store(n), mk.state(n, seed=substeps), mk.materials(n, seed=7), cfg, substeps, 1e-3,
                         f"{model}, {substeps} substep(s): ")  # fmt: skip


def test_particle_floor_matches_reference(ti64, mk):
    """The particle-stage floor (a tilted Coulomb plane met by the particles) against the reference, with particles
    above it, crossing it within the substep and below it."""
    n = 200
    state = mk.state(n, seed=9)
    mat = {"vol": torch.full((n,), 1e-4, dtype=torch.float64), "density": torch.full((n,), 1e3, dtype=torch.float64),
           "E": torch.full((n,), 5e3, dtype=torch.float64), "nu": torch.full((n,), 0.3, dtype=torch.float64)}
    spec = "gravity;floor:n=0.1,-0.2,1:d=0.35:mu=0.4;walls"
    normal = torch.tensor([0.1, -0.2, 1.0], dtype=torch.float64)
    normal = normal / normal.norm()
    # Move every particle below the plane and a third of the others to within 5 mm of it, on either side (below:
    # pushed out; above and moving towards it: landing within a substep).
    g = torch.Generator().manual_seed(3)
    near = (torch.arange(n) % 3 == 0) | ((state["x"] @ normal) < 0.35)
    gap = (torch.rand(n, generator=g, dtype=torch.float64) - 0.5) * 0.01
    state["x"] = torch.where(near[:, None], state["x"] - ((state["x"] @ normal) - 0.35 - gap)[:, None] * normal,
                             state["x"])  # fmt: skip
    mk.against_reference(mk.store(n), state, mat, SimConfig(res=16, effects=spec, segment=8), 3, 2e-3)
    below = (state["x"] @ normal) < 0.35
    assert int((below & near).sum()) > 10 and int(below.sum()) < n - 20  # it acts on some particles, not all


def test_every_effect_at_once_matches_reference_in_any_spec_order(ti64, mk):
    """All registered effects together, the spec written in two orders: the kernels apply the terms of a stage by
    name whatever the spec's order, and so must the reference (a drag and an attractor do not commute within a
    substep: in the spec's order the reference differed by 3e-5 m/s after three substeps)."""
    from causalgs.sim import REGISTRY

    terms = mk.ALL_EFFECTS.split(";")
    assert {part.split(":")[0] for part in terms} == set(REGISTRY)
    store, state, mat = mk.store(400), mk.state(400, seed=2), mk.materials(400, seed=8)
    results = []
    for spec in (mk.ALL_EFFECTS, ";".join(reversed(terms))):
        cfg = SimConfig(res=16, effects=spec, segment=8)
        results.append(mk.against_reference(store, state, mat, cfg, 3, 1e-3, f"spec {spec!r}: "))
    for k in ("x", "v", "C", "F"):
        assert torch.equal(results[0][k], results[1][k]), f"{k} depends on the spec's order"


def test_segment_boundary_is_seamless(ti64, mk):
    """Five substeps in segments of 2 (two checkpoint boundaries) equal the same substeps in one segment of 8."""
    n = 100
    state = mk.state(n, seed=4)
    # The segment length is a field shape, so the second run needs a store of its own.
    stores = [mk.store(n), ParticleStore(n, sh_degree=0)]
    out = []
    for store, segment in zip(stores, (8, 2), strict=True):
        store.resize(n)
        for name, val in (("density", 1e3), ("vol", 1e-4), ("E", 5e3)):
            store.from_torch(name, torch.full((n,), val))
        sim = Simulator(store, SimConfig(res=16, effects=SPEC, segment=segment))
        sim.set_state(**state)
        sim.step(5, 1e-3)
        out.append(sim.state())
    for k in ("x", "v", "C", "F"):
        assert torch.equal(out[0][k], out[1][k]), k


def test_stress_free_at_rest_and_symmetric():
    """Every model's Kirchhoff stress vanishes at F = I and is symmetric (no torque on the grid)."""
    g = torch.Generator().manual_seed(3)
    F = torch.eye(3, dtype=torch.float64) + 0.2 * torch.randn(16, 3, 3, generator=g, dtype=torch.float64)
    mu, lam = torch.full((16,), 2.0, dtype=torch.float64), torch.full((16,), 3.0, dtype=torch.float64)
    for model in MODELS:
        tau0 = kirchhoff(torch.eye(3, dtype=torch.float64).expand(16, 3, 3), mu, lam, model)
        assert float(tau0.abs().max()) < 1e-14, model
        tau = kirchhoff(F, mu, lam, model)
        assert float((tau - tau.transpose(-1, -2)).abs().max()) < 1e-12, model


def test_fused_substep_equals_the_phase_kernels(ti64, mk, monkeypatch):
    """The one-launch substep against the same phases launched one by one (every effect, so the particle stage and
    the plastic return map run too), across a segment boundary: the same arithmetic, so bit for bit. Each run is
    held to its own path (the other one fails if called), so the comparison cannot be of one path with itself."""
    n = 300
    store, state, mat = mk.store(n), mk.state(n, seed=5), mk.materials(n, seed=6)
    for k, t in mat.items():
        store.from_torch(k, t)
    sim = Simulator(store, SimConfig(res=16, effects=mk.ALL_EFFECTS, segment=4))
    out = []
    for phased in (False, True):
        other = "substep" if phased else "substep_phased"
        with monkeypatch.context() as m:
            m.setattr(sim, other, lambda *a, name=other: pytest.fail(f"{name} ran"))
            sim.set_state(**state)
            sim.step(6, 1e-3, phased=phased)
        out.append(sim.state())
    for k in ("x", "v", "C", "F"):
        assert torch.equal(out[0][k], out[1][k]), k
    assert not torch.equal(out[0]["x"], state["x"])  # it moved
