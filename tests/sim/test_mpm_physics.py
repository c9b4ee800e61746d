"""Physics checks of the simulator against laws: free fall, conservation of momentum, walls, blow-up detection."""

from __future__ import annotations

import pytest
import torch

from causalgs.errors import CausalGSError
from causalgs.sim import MODELS, SimConfig, Simulator, momenta


def test_free_fall_follows_the_law(ti64, mk):
    """An elastic block away from the walls falls as x0 + v0 t + g t²/2 (within 1% of the displacement), and exactly
    as symplectic Euler predicts for the substeps taken."""
    x0 = mk.block((0.4, 0.4, 0.4))
    store = mk.store(len(x0))
    mk.fill(store, x0)
    g = torch.tensor([0.0, 0.0, -4.0], dtype=torch.float64)
    v0 = torch.tensor([0.5, 0.25, 1.0], dtype=torch.float64)
    sim = Simulator(store, SimConfig(res=16, cfl=0.1, effects="gravity:g=0,0,-4"))
    sim.set_state(x0, v0.expand(len(x0), 3))
    frames, fps = 10, 25.0
    out = sim.advance(frames, fps)
    t = frames / fps
    law = v0 * t + 0.5 * g * t * t
    disp = out["x"] - x0
    com_err = float((disp.mean(0) - law).norm())
    assert com_err < 0.01 * float(law.norm()), f"centre of mass off the law by {com_err:.3g}"
    assert float((disp - law).norm(dim=1).max()) < 0.01 * float(law.norm())
    # Symplectic Euler with equal substeps dt: x = x0 + v0 t + g t²/2 + g t dt/2 (the O(dt) term above).
    (m, dt), *_ = sim.schedule
    assert all(s == (m, dt) for s in sim.schedule)
    exact = law + 0.5 * g * t * dt
    assert float((disp - exact).abs().max()) < 1e-10
    assert float((out["v"] - (v0 + g * t)).abs().max()) < 1e-10
    assert float((out["F"] - torch.eye(3, dtype=torch.float64)).abs().max()) < 1e-10


@pytest.mark.parametrize("model", list(MODELS))
def test_momentum_conserved_without_effects(ti64, mk, model):
    """No effects, particles far from the boundary: total linear and APIC angular momentum stay constant while the
    body spins, stretches and deforms elastically."""
    x0 = mk.block((0.5, 0.5, 0.5))
    n = len(x0)
    store = mk.store(n)
    mk.fill(store, x0)
    r = x0 - x0.mean(0)
    omega = torch.tensor([1.0, -2.0, 4.0], dtype=torch.float64)
    S = torch.tensor([[0.8, 0.3, 0.0], [0.3, -0.5, 0.2], [0.0, 0.2, 0.4]], dtype=torch.float64)
    v = torch.tensor([0.3, -0.2, 0.1], dtype=torch.float64) + torch.linalg.cross(omega.expand(n, 3), r) + r @ S.T
    sim = Simulator(store, SimConfig(res=16, effects="", material=model))
    sim.set_state(x0, v)
    mass = store.to_torch("mass")
    P0, L0 = momenta(sim.state(), mass, mk.DX)
    pscale = float((mass[:, None] * v).norm(dim=1).sum())
    for _ in range(10):
        state = sim.advance(1, 50.0)
        P, L = momenta(state, mass, mk.DX)
        assert float((P - P0).norm()) < 1e-5 * pscale
        assert float((L - L0).norm()) < 1e-5 * float(L0.norm())
    F = state["F"]
    strain = F.transpose(-1, -2) @ F - torch.eye(3, dtype=torch.float64)
    assert float(strain.abs().max()) > 1e-2, "the body should have deformed"


def test_walls_stop_a_falling_block(ti64, mk):
    x0 = mk.block((0.5, 0.5, 0.3))
    store = mk.store(len(x0))
    mk.fill(store, x0)
    sim = Simulator(store, SimConfig(res=16, effects="gravity;walls"))
    sim.set_state(x0, torch.zeros(len(x0), 3, dtype=torch.float64))
    out = sim.advance(15, 25.0)  # free fall would be 2.9 m below the start
    assert float(out["x"][:, 2].min()) > mk.DX
    assert abs(float(out["v"][:, 2].mean())) < 1.0


def test_blow_up_is_one_line_naming_the_frame(ti64, mk):
    x0 = mk.block((0.5, 0.5, 0.5))
    store = mk.store(len(x0))
    mk.fill(store, x0, E=1e12)
    F = torch.diag(torch.tensor([1.05, 0.97, 1.0], dtype=torch.float64)).expand(len(x0), 3, 3)
    sim = Simulator(store, SimConfig(res=16, effects="gravity", dt=0.01))
    sim.set_state(x0, torch.zeros(len(x0), 3, dtype=torch.float64), F=F)
    with pytest.raises(CausalGSError, match=r"blew up in frame 1 ") as e:
        sim.advance(3, 25.0)
    assert "\n" not in str(e.value)
    # With the CFL time step instead, the same stiffness needs more substeps than allowed.
    sim = Simulator(store, SimConfig(res=16, effects="gravity", max_substeps=100))
    sim.set_state(x0, torch.zeros(len(x0), 3, dtype=torch.float64), F=F)
    with pytest.raises(CausalGSError, match=r"frame 1 needs \d+ substeps"):
        sim.advance(1, 25.0)


def test_particles_leaving_the_grid_are_reported(ti64, mk):
    x0 = mk.block((0.5, 0.5, 0.5))
    store = mk.store(len(x0))
    mk.fill(store, x0)
    sim = Simulator(store, SimConfig(res=16, effects=""))
    sim.set_state(x0, torch.tensor([[20.0, 0.0, 0.0]], dtype=torch.float64).expand(len(x0), 3))
    with pytest.raises(CausalGSError, match=r"frame 1 .*left the grid") as e:
        sim.advance(2, 25.0)
    assert "\n" not in str(e.value)


def test_unphysical_materials_are_refused(ti64, mk):
    x0 = mk.block((0.5, 0.5, 0.5), count=2)
    store = mk.store(len(x0))
    mk.fill(store, x0)
    store.from_torch("nu", torch.tensor([0.5]), start=3)
    sim = Simulator(store, SimConfig(res=16))
    sim.set_state(x0, torch.zeros(len(x0), 3, dtype=torch.float64))
    with pytest.raises(CausalGSError, match=r"particle 3 has nu = 0.5; the simulator needs nu in \(-1, 0.5\)"):
        sim.advance(1, 25.0)
