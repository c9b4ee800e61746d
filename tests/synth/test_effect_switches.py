"""Every effect switch of the synthetic scenes changes the true trajectories the way its law says.

The jelly scene's bodies are simulated (no rendering) under effect specs that isolate one term; the centre of mass
(or the shape) is compared with the closed-form law or with the same scene without the term.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from causalgs.synth import physics

SIM_RES = 32
# The checks below are timed in 24 fps frames (the jelly lands within a second); the data's own rate is not the point.
FPS = 24.0


@pytest.fixture(scope="module", autouse=True)
def _runtime():
    from causalgs import _ti

    _ti.init("cpu", "float32")


def _run(effects: str, frames: int, seed: int = 0, spin: bool = True) -> dict:
    setup = physics.SETUPS["jelly"](seed=seed, effects=effects, reference_res=SIM_RES)
    if not spin:
        setup.bodies[0].omega = (0.0, 0.0, 0.0)
    run = physics.simulate(setup, frames, FPS, progress=False)
    run["t"] = np.arange(frames) / FPS
    run["com"] = run["x"].astype(np.float64).mean(1)
    run["v0"] = np.asarray(setup.bodies[0].velocity)
    run["dt"] = 1.0 / (FPS * min(run["substeps"]))
    return run


def _strain(F) -> np.ndarray:
    F = F.astype(np.float64)
    return np.abs(np.swapaxes(F, -1, -2) @ F - np.eye(3)).max(axis=(-1, -2))


def test_gravity_vector_sets_the_fall():
    r = _run("gravity:g=0.5,0,-5;walls", 6)
    for k in range(1, 6):
        t = r["t"][k]
        law = r["com"][0] + r["v0"] * t + 0.5 * np.array([0.5, 0.0, -5.0]) * t * t
        assert np.abs(r["com"][k] - law).max() < 0.01 * 2.5 * t * t + 5.0 * t * r["dt"], k


def test_force_field_adds_its_acceleration():
    r = _run("force:b=1.5,-1,0;walls", 8)
    for k in range(1, 8):
        t = r["t"][k]
        law = r["com"][0] + r["v0"] * t + 0.5 * np.array([1.5, -1.0, 0.0]) * t * t
        assert np.abs(r["com"][k] - law).max() < 0.01 * 0.9 * t * t + 1.5 * t * r["dt"] + 1e-5, k


def test_linear_drag_decays_velocity_exponentially():
    c = 3.0
    r = _run(f"linear_drag:c={c};walls", 10)
    for k in range(1, 10):
        t = r["t"][k]
        law = r["com"][0] + r["v0"] * (1 - math.exp(-c * t)) / c
        assert np.abs(r["com"][k] - law).max() < 0.03 * np.linalg.norm(law - r["com"][0]) + 1e-5, k


def test_quadratic_drag_follows_its_law():
    """a = −k|v|v keeps the direction and gives |x − x0| = ln(1 + k|v0| t) / k (for a body that does not spin: with
    spin, |v| varies over the body and the mean of |v| v is not |v̄| v̄)."""
    k_ = 4.0
    r = _run(f"quadratic_drag:k={k_};walls", 10, spin=False)
    speed = np.linalg.norm(r["v0"])
    for k in range(1, 10):
        t = r["t"][k]
        law = r["com"][0] + r["v0"] / speed * math.log1p(k_ * speed * t) / k_
        assert np.abs(r["com"][k] - law).max() < 0.03 * np.linalg.norm(law - r["com"][0]) + 1e-5, k
    linear = r["com"][0] + r["v0"] * r["t"][9]
    assert np.linalg.norm(r["com"][9] - linear) > 0.1 * np.linalg.norm(linear - r["com"][0]), "drag must act"


def test_ground_friction_slows_sliding_and_slip_keeps_it():
    """The jelly lands and bounces. On a slip ground (mu = 0) no horizontal force acts, so its centre of mass moves
    horizontally at v0 throughout; Coulomb friction (mu = 1) takes horizontal momentum at every contact; a sticky
    ground holds the particles that touch it."""
    frames = 24
    runs = {mu: _run(f"gravity;ground:mu={mu};walls", frames) for mu in (0.0, 1.0)}
    slip = runs[0.0]
    law = slip["com"][:, :2] - slip["com"][0, :2] - slip["v0"][:2] * slip["t"][:, None]
    assert np.abs(law).max() < 1e-3, f"slip ground: horizontal drift off v0 t by {np.abs(law).max():.2g} m"
    assert slip["x"][:, :, 2].min() < 0.01, "the jelly must reach the ground"
    travel = {mu: np.linalg.norm(r["com"][-1, :2] - r["com"][0, :2]) for mu, r in runs.items()}
    assert travel[1.0] < 0.7 * travel[0.0], f"friction: {travel[1.0]:.3f} m vs slip {travel[0.0]:.3f} m"
    # Sticky: the jelly is held where it lands: its bottom layer barely creeps (the grid condition pins nodes, and
    # particles half a cell up still see free nodes) and its centre travels far less than on slip.
    sticky = _run("gravity;ground_sticky;walls", frames)

    def bottom_drift(r):
        x = r["x"].astype(np.float64)
        bottom = x[-1, :, 2] < 0.01
        assert bottom.sum() > 10
        return np.linalg.norm(x[-1, bottom, :2] - x[-5, bottom, :2], axis=1).mean()

    assert bottom_drift(sticky) < 0.35 * bottom_drift(slip)
    assert np.linalg.norm(sticky["com"][-1, :2] - sticky["com"][0, :2]) < 0.5 * travel[0.0]


def test_damping_and_plasticity_change_the_shape_history():
    """After landing: material damping takes the wobble out (strain varies far less over the last frames), and a
    low yield stress leaves a permanent set (the jelly ends flatter than the elastic one)."""
    frames = 30
    base = _run("gravity;ground:mu=0.4;walls", frames)
    damped = _run("gravity;ground:mu=0.4;damping:eta=200;walls", frames)
    plastic = _run("gravity;ground:mu=0.4;plasticity:yield_stress=150;walls", frames)

    def wobble(r):
        return np.std(np.linalg.det(r["F"][-12:].astype(np.float64)).mean(1)) + np.std(_strain(r["F"][-12:]).mean(1))

    assert wobble(damped) < 0.5 * wobble(base), f"damped {wobble(damped):.4f} vs {wobble(base):.4f}"

    def height(r):
        z = r["x"][-1, :, 2].astype(np.float64)
        return np.percentile(z, 99) - np.percentile(z, 1)

    h0 = float(np.ptp(base["x"][0, :, 2]))
    assert abs(height(base) / h0 - 1) < 0.06, "the elastic jelly recovers its height"
    assert height(plastic) < 0.9 * height(base), f"plastic {height(plastic):.3f} vs elastic {height(base):.3f}"
