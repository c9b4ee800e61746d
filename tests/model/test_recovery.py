"""The recovery report's learned spin: the rigid ω through a velocity field, against exact rigid motions."""

from __future__ import annotations

import json

import numpy as np
import pytest

from causalgs.model.recovery import recovery_report, rigid_spin


def test_rigid_spin_is_exact_for_a_rigid_motion():
    rng = np.random.default_rng(0)
    r = rng.normal(0, 0.05, (200, 3))
    a, w = np.array([0.3, -0.1, 0.8]), np.array([0.5, 3.9, -0.2])
    v = a + np.cross(w, r)
    assert np.allclose(rigid_spin(r, v), w, atol=1e-10)
    assert np.allclose(rigid_spin(r + 1.0, v), w, atol=1e-10)  # about any point: the translation takes the offset
    assert np.allclose(rigid_spin(r, np.tile(a, (200, 1))), 0.0, atol=1e-12)  # a translation has no spin
    # Noise on the velocities: the least-squares ω stays close.
    noisy = v + rng.normal(0, 0.01, v.shape)
    assert np.linalg.norm(rigid_spin(r, noisy) - w) < 0.1


def test_rigid_spin_is_undetermined_on_a_line():
    t = np.linspace(-1, 1, 20)[:, None]
    r = t * np.array([[1.0, 0.0, 0.0]])
    assert rigid_spin(r, np.zeros_like(r)) is None  # spin about the line itself is invisible
    assert rigid_spin(r[:2], np.zeros_like(r[:2])) is None


def test_report_gives_each_object_its_spin(tmp_path):
    rng = np.random.default_rng(1)
    centre, w = np.array([0.1, 0.0, 0.3]), np.array([0.0, 4.0, 0.0])
    rest = centre + rng.normal(0, 0.04, (500, 3))
    (tmp_path / "gt").mkdir()
    meta = {"objects": [{"id": 1, "name": "ball", "E": 2e5, "nu": 0.3, "density": 1000.0, "center": centre.tolist(),
                         "velocity": [0.2, 0.0, 0.0], "omega": w.tolist()}]}  # fmt: skip
    (tmp_path / "gt" / "meta.json").write_text(json.dumps(meta))
    np.savez(tmp_path / "gt" / "motion.npz", particles_rest=rest, particle_object=np.ones(500, dtype=np.int64))
    means = rest[::5] + 1e-3
    learned = np.array([0.2, 0.0, 0.0]) + np.cross(0.5 * w, means - centre)  # half the true spin learned
    np.savez(tmp_path / "physics.npz", means=means, dynamic=np.ones(len(means), bool), velocity=learned,
             E=np.full(len(means), 1e5), nu=np.full(len(means), 0.3), density=np.full(len(means), 1e3))  # fmt: skip
    rep = recovery_report(tmp_path / "physics.npz", tmp_path)
    (row,) = rep["objects"]
    assert row["omega_true"] == pytest.approx(w.tolist())
    assert row["omega_model"] == pytest.approx((0.5 * w).tolist(), abs=1e-9)
    assert row["velocity_error_mean"] > 0
