"""Physics checks of the simulator against laws: free fall, conservation of momentum, walls, blow-up detection."""

from __future__ import annotations

import math

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


def _com_velocity(state) -> torch.Tensor:
    return state["v"].mean(0)


def test_elastic_bar_first_longitudinal_mode(ti64, mk):
    """A free bar started in its first longitudinal mode oscillates at f = (1/2L)·sqrt(E/ρ) (nu = 0, so the bar and
    the P-wave speed coincide whatever the cross-section), within 10%."""
    L, E, rho = 0.75, 1.0e4, 1.0e3
    n_along, n_across = round(L / (mk.DX / 2)), 4
    x0 = mk.block((0.5, 0.5, 0.5), count=n_along)  # a cube of lattice points, then cut to the bar
    keep = (x0[:, 1] - 0.5).abs() < n_across * mk.DX / 4
    keep &= (x0[:, 2] - 0.5).abs() < n_across * mk.DX / 4
    x0 = x0[keep]
    store = mk.store(len(x0))
    mk.fill(store, x0, E=E, nu=0.0, density=rho)
    lo, hi = float(x0[:, 0].min()), float(x0[:, 0].max())
    length = hi - lo + mk.DX / 2  # each particle stands for a cell of spacing DX/2
    xi = (x0[:, 0] - lo + mk.DX / 4) / length
    v = torch.zeros_like(x0)
    v[:, 0] = 0.05 * torch.cos(math.pi * xi)
    sim = Simulator(store, SimConfig(res=16, effects=""))
    sim.set_state(x0, v)
    left, right = xi < 0.15, xi > 0.85
    fps = 200.0
    ext = [0.0]
    for _ in range(130):
        x = sim.advance(1, fps)["x"]
        ext.append(float(x[right, 0].mean() - x[left, 0].mean()) - float(x0[right, 0].mean() - x0[left, 0].mean()))
    ext = torch.tensor(ext)
    # The extension starts at 0 going negative; crossings of zero at T/2, T, 3T/2, ...
    s = torch.sign(ext[1:])
    idx = torch.nonzero(s[1:] != s[:-1]).flatten() + 1
    crossings = [(float(i) + float(ext[i] / (ext[i] - ext[i + 1]))) / fps for i in idx.tolist()]
    assert len(crossings) >= 2, f"no oscillation seen: extension {ext[::10].tolist()}"
    period = 2 * (crossings[1] - crossings[0])
    law = 2 * length / math.sqrt(E / rho)
    assert abs(period - law) < 0.1 * law, f"period {period:.4g} s, law {law:.4g} s"


def _drop(mk, centre, effects: str):
    """A block released at rest above a plane, after 1.6 s: its rest shape, its state, and whether it still stands
    (at least 80% of its rest height, not flattened into the plane)."""
    x0 = mk.block(centre)
    store = mk.store(len(x0))
    mk.fill(store, x0)
    sim = Simulator(store, SimConfig(res=16, effects=effects))
    sim.set_state(x0, torch.zeros(len(x0), 3, dtype=torch.float64))
    out = sim.advance(40, 25.0)
    height = float(out["x"][:, 2].max() - out["x"][:, 2].min())
    return out, height > 0.8 * float(x0[:, 2].max() - x0[:, 2].min())


def test_block_dropped_on_the_ground_comes_to_rest(ti64, mk):
    out, stands = _drop(mk, (0.5, 0.5, 0.4), "gravity;ground:d=0.2:mu=0.5;walls")
    assert float(out["v"].norm(dim=1).max()) < 0.05, "the block should be at rest after 1.6 s"
    bottom = float(out["x"][:, 2].min())
    assert 0.2 - mk.DX < bottom < 0.2 + mk.DX, f"resting bottom at z = {bottom:.4g}, the ground is at 0.2"
    assert stands, "the block should stand on the ground, not flatten into it"


def test_a_block_rests_on_the_particle_floor_at_the_plane(ti64, mk):
    """A floor met by the particles stops a dropped block with its lowest particles on the plane (within a tenth of
    a cell), where a grid-node plane holds them up to a cell and a half off it, by an amount that changes with the
    grid spacing. (Without the grid's contact layer less is damped: the block still wobbles a little.)"""
    out, stands = _drop(mk, (0.5, 0.5, 0.5), "gravity;floor:d=0.3:mu=0.5;walls")
    assert float(_com_velocity(out).norm()) < 0.02, "the block should be at rest after 1.6 s"
    bottom = float(out["x"][:, 2].min())
    assert abs(bottom - 0.3) < 0.1 * mk.DX, f"resting bottom at z = {bottom:.4g}, the floor is at 0.3"
    assert stands, "the block should stand on the floor, not flatten into it"


@pytest.mark.parametrize("plane", ["ground", "floor"])
@pytest.mark.parametrize("mu", [0.2, 0.4])
def test_coulomb_ground_decelerates_at_mu_g(ti64, mk, mu, plane):
    """A stiff block sliding on a Coulomb ground slows at mu·g (within 10%) until it stops. (A soft one rocks as it
    slides, so its normal force, and with it the friction, oscillates about m·g.)"""
    # The floor meets the particles, so it is placed above the walls' band (three cells, whose nodes would hold the
    # block up without friction); the grid-node ground holds it about a cell above its plane.
    d = 0.2 if plane == "ground" else 0.3
    x0 = mk.block((0.25, 0.5, d + (3 * mk.DX / 4 + 0.01 if plane == "ground" else 1.25 * mk.DX + 0.005)))
    store = mk.store(len(x0))
    mk.fill(store, x0, E=1e5)
    sim = Simulator(store, SimConfig(res=16, effects=f"gravity;{plane}:d={d}:mu={mu};walls"))
    v0 = torch.zeros(len(x0), 3, dtype=torch.float64)
    v0[:, 0] = 1.2
    sim.set_state(x0, v0)
    fps, t, vx = 50.0, [], []
    for f in range(12):
        state = sim.advance(1, fps)
        t.append((f + 1) / fps)
        vx.append(float(_com_velocity(state)[0]))
    t, vx = torch.tensor(t[2:], dtype=torch.float64), torch.tensor(vx[2:], dtype=torch.float64)  # after touch-down
    assert float(vx.min()) > 0.05, "still sliding over the fitted window"
    slope = float(((t - t.mean()) * (vx - vx.mean())).sum() / ((t - t.mean()) ** 2).sum())
    assert abs(-slope - mu * 9.8) < 0.1 * mu * 9.8, f"deceleration {-slope:.4g} m/s², mu·g = {mu * 9.8:.4g}"


def test_drag_and_force_field_laws(ti64, mk):
    """Linear drag: v = v0 e^(-ct) (within 5%); quadratic drag: v = v0 / (1 + k|v0| t); a uniform force field:
    v = v0 + b t. One compiled simulator, each law switched on through its parameters."""
    x0 = mk.block((0.5, 0.5, 0.5), count=4)
    store = mk.store(len(x0))
    mk.fill(store, x0)
    sim = Simulator(store, SimConfig(res=16, effects="linear_drag:c=0;quadratic_drag:k=0;force:b=0,0,0"))
    v0 = torch.tensor([0.4, -0.3, 0.2], dtype=torch.float64)
    speed = float(v0.norm())
    fps, frames = 25.0, 12
    t = frames / fps
    cases = [
        ({"linear_drag": {"c": 2.0}}, v0 * math.exp(-2.0 * t)),
        ({"quadratic_drag": {"k": 3.0}}, v0 / (1 + 3.0 * speed * t)),
        ({"force": {"b": (0.5, 0.0, -1.0)}}, v0 + torch.tensor([0.5, 0.0, -1.0], dtype=torch.float64) * t),
    ]
    for settings, law in cases:
        for name in ("linear_drag", "quadratic_drag"):
            sim.effects.set(name, **{"c" if name == "linear_drag" else "k": 0.0})
        sim.effects.set("force", b=(0.0, 0.0, 0.0))
        for name, vals in settings.items():
            sim.effects.set(name, **vals)
        sim.set_state(x0, v0.expand(len(x0), 3))
        got = _com_velocity(sim.advance(frames, fps))
        err = float((got - law).norm())
        assert err < 0.05 * float((law - v0).norm()), f"{settings}: velocity {got.tolist()} vs law {law.tolist()}"


def test_attractor_law(ti64, mk):
    """A pull towards c with a = -k (x - c): the centre of mass oscillates as c + (x0 - c) cos(√k t) (the grid
    force acts at the nodes, so the law holds for the mass-weighted centre within a few per cent of the swing)."""
    x0 = mk.block((0.5, 0.5, 0.5), count=4)
    store = mk.store(len(x0))
    mk.fill(store, x0)
    c = torch.tensor([0.4, 0.55, 0.5], dtype=torch.float64)
    k = 20.0
    sim = Simulator(store, SimConfig(res=16, effects=f"attractor:k={k}:c=0.4,0.55,0.5"))
    sim.set_state(x0, torch.zeros(len(x0), 3, dtype=torch.float64))
    fps, frames = 25.0, 10
    centre0 = x0.mean(0)
    t = frames / fps
    got = sim.advance(frames, fps)["x"].mean(0)
    law = c + (centre0 - c) * math.cos(math.sqrt(k) * t)
    swing = float((centre0 - c).norm())
    assert float((got - law).norm()) < 0.05 * swing, f"centre {got.tolist()} vs law {law.tolist()}"


def _elastic_energy(F, E, nu, vol):
    mu, lam = E / (2 * (1 + nu)), E * nu / ((1 + nu) * (1 - 2 * nu))
    J = torch.linalg.det(F)
    tr = (F * F).sum((-1, -2))
    return float((vol * (0.5 * mu * (tr - 3) - mu * torch.log(J) + 0.5 * lam * torch.log(J) ** 2)).sum())


def test_material_damping_dissipates_wobble_but_not_momentum(ti64, mk):
    """Viscous stress is internal and symmetric: linear and angular momentum stay constant while the internal energy
    (kinetic energy about the centre of mass + neo-Hookean strain energy) decays."""
    x0 = mk.block((0.5, 0.5, 0.5))
    n = len(x0)
    store = mk.store(n)
    mk.fill(store, x0)
    sim = Simulator(store, SimConfig(res=16, effects="damping:eta=0;plasticity:yield_stress=1e12"))
    r = x0 - x0.mean(0)
    S = torch.tensor([[1.5, 0.4, 0.0], [0.4, -1.0, 0.3], [0.0, 0.3, 0.8]], dtype=torch.float64)
    v = torch.tensor([0.3, -0.2, 0.1], dtype=torch.float64) + r @ S.T
    mass = store.to_torch("mass")
    vol = store.to_torch("vol")

    def energy(state):
        ke = 0.5 * float((mass[:, None] * (state["v"] - state["v"].mean(0)) ** 2).sum())
        return ke + _elastic_energy(state["F"], 1.0e4, 0.3, vol)

    final = {}
    for eta in (0.0, 20.0):
        sim.effects.set("damping", eta=eta)
        sim.set_state(x0, v)
        e0 = energy(sim.state())
        P0, L0 = momenta(sim.state(), mass, mk.DX)
        state = sim.advance(10, 25.0)
        P, L = momenta(state, mass, mk.DX)
        assert float((P - P0).norm()) < 1e-8 * float(P0.norm())
        assert float((L - L0).norm()) < 1e-5 * max(float(L0.norm()), 1e-3)
        final[eta] = energy(state) / e0
    # The coarse MPM dissipates too (measured: ~0.36 of the energy left after 0.4 s); damping takes nearly all of it.
    assert final[0.0] > 0.25, f"undamped internal energy fell to {final[0.0]:.2f} of its start"
    assert final[20.0] < 0.1 * final[0.0], f"damped {final[20.0]:.3f} vs undamped {final[0.0]:.3f}"


def test_plasticity_leaves_permanent_deformation(ti64, mk):
    """Squeeze a block along z, let material damping settle it: an elastic block springs back to its height, a
    plastic one (yield stress well below the squeeze stress) keeps a permanent set."""
    x0 = mk.block((0.5, 0.5, 0.5))
    n = len(x0)
    store = mk.store(n)
    mk.fill(store, x0)
    sim = Simulator(store, SimConfig(res=16, effects="damping:eta=20;plasticity:yield_stress=1e12"))
    r = x0 - x0.mean(0)
    v = torch.zeros_like(x0)
    v[:, 2] = -6.0 * r[:, 2]  # squeeze: the top moves down, the bottom up
    height0 = float(x0[:, 2].max() - x0[:, 2].min())
    heights = {}
    for ys in (1e12, 50.0):
        sim.effects.set("plasticity", yield_stress=ys)
        sim.set_state(x0, v)
        x = sim.advance(25, 25.0)["x"]
        heights[ys] = float(x[:, 2].max() - x[:, 2].min()) / height0
    assert abs(heights[1e12] - 1.0) < 0.03, f"elastic block ends at {heights[1e12]:.3f} of its height"
    assert heights[50.0] < 0.93, f"plastic block ends at {heights[50.0]:.3f} of its height (no permanent set)"
