"""The simulator in float32 (one Taichi re-initialisation: keep this module small)."""

from __future__ import annotations

import torch

from causalgs.sim import SimConfig, Simulator


def test_free_fall_float32(ti32, mk):
    x0 = mk.block((0.4, 0.4, 0.4), dtype=torch.float32)
    store = mk.store(len(x0))
    mk.fill(store, x0)
    sim = Simulator(store, SimConfig(res=16, cfl=0.1, effects="gravity:g=0,0,-4;walls"))
    v0 = torch.tensor([0.5, 0.25, 1.0])
    sim.set_state(x0, v0.expand(len(x0), 3))
    out = sim.advance(10, 25.0)
    assert out["x"].dtype == torch.float32
    t = 0.4
    law = v0 * t + 0.5 * torch.tensor([0.0, 0.0, -4.0]) * t * t
    assert float(((out["x"] - x0).mean(0) - law).norm()) < 0.01 * float(law.norm())


def test_float32_backward_stays_finite_next_to_nearly_empty_nodes(ti32, mk):
    """A particle just inside a node's B-spline support gives that node a mass of ~1e-27 kg; its adjoint −mv/m² used
    to overflow float32 and turn every particle's gradient into NaN (such nodes now count as empty)."""
    dx = mk.DX
    eps = 1e-4
    # fx = 1.5 - eps in cell units on every axis: the far node's weight is (eps²/2)³.
    lone = torch.tensor([[0.5 + (1.5 - eps) * dx] * 3], dtype=torch.float32)
    x0 = torch.cat([mk.block((0.3, 0.3, 0.3), count=4, dtype=torch.float32), lone])
    store = mk.store(len(x0))
    mk.fill(store, x0)
    sim = Simulator(store, SimConfig(res=16, effects="gravity;walls", segment=4, dt=1e-3))
    sim.set_state(x0, torch.zeros_like(x0))
    out, tape = sim.rollout([0.002, 0.004])
    g = sim.backward(tape, {"x": torch.ones_like(out["x"])})
    for name, t in g.items():
        assert bool(torch.isfinite(t).all()), name
    assert float(g["v0"].abs().max()) > 0
