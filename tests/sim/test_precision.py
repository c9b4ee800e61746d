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
