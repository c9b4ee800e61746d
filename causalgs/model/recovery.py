"""How well a fit recovered the causes, on datasets with ground truth (``gt/meta.json`` and ``gt/motion.npz``).

Every dynamic Gaussian of the model is assigned to the true object whose rest particle is nearest to it (within
``reach`` metres; farther ones are left out). Per object this reports the model's median Young's modulus, Poisson
ratio and density at those Gaussians and the error of the learned initial velocity against the true rigid initial
velocity v + ω × (p − centre), as the mean vector error and relative to the true mean speed, and the learned
spin: ω of the least-squares rigid motion a + ω × (p − centre) through the learned velocities, beside the true ω
(a spinning body's texture turns with it; a velocity error of a few per cent can hide a spin that is not learned at
all). ``stiffness_order_ok``
says whether the objects' median E rank as the true E do (the question for scenes with bodies of different
materials).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from causalgs.io import read_json


def recovery_report(physics_npz, data_dir, reach: float = 0.03) -> dict | None:
    """The report described in the module docstring, or None when the dataset has no ground-truth motion."""
    data_dir = Path(data_dir)
    meta_path = data_dir / "gt" / "meta.json"
    if not meta_path.is_file():
        return None
    with np.load(physics_npz) as z:
        means, dyn = z["means"], z["dynamic"].astype(bool)
        vel, E, nu, rho = z["velocity"], z["E"], z["nu"], z["density"]
    label = true_objects(means, data_dir, reach)
    if label is None:
        return None
    meta = read_json(meta_path, "ground truth")
    objects = {o["id"]: o for o in meta.get("objects", []) if o.get("kind") != "static" and "velocity" in o}
    label = np.where(dyn, label, -1)
    rows = []
    for oid, o in sorted(objects.items()):
        sel = label == oid
        if not sel.any():
            rows.append({"id": oid, "name": o.get("name"), "gaussians": 0})
            continue
        centre = np.asarray(o.get("center", [0, 0, 0]), dtype=np.float64)
        v_true = np.asarray(o.get("velocity", [0, 0, 0])) + np.cross(np.asarray(o.get("omega", [0, 0, 0])),
                                                                      means[sel] - centre)  # fmt: skip
        err = np.linalg.norm(vel[sel] - v_true, axis=1)
        omega = rigid_spin(means[sel] - centre, vel[sel])
        speed = float(np.linalg.norm(v_true, axis=1).mean())
        rows.append({
            "id": oid, "name": o.get("name"), "gaussians": int(sel.sum()),
            "E_true": o.get("E"), "E_model": float(np.median(E[sel])),
            "nu_true": o.get("nu"), "nu_model": float(np.median(nu[sel])),
            "density_true": o.get("density"), "density_model": float(np.median(rho[sel])),
            "velocity_true_mean": v_true.mean(0).tolist(), "velocity_model_mean": vel[sel].mean(0).tolist(),
            "velocity_error_mean": float(err.mean()),
            "velocity_error_relative": float(err.mean() / speed) if speed > 0 else None,
            "omega_true": np.asarray(o.get("omega", [0, 0, 0]), dtype=np.float64).tolist(),
            "omega_model": None if omega is None else omega.tolist(),
        })  # fmt: skip
    found = [r for r in rows if r.get("gaussians") and r.get("E_true") is not None]
    order_ok = None
    if len(found) >= 2:
        true_rank = np.argsort([r["E_true"] for r in found])
        model_rank = np.argsort([r["E_model"] for r in found])
        order_ok = bool(np.array_equal(true_rank, model_rank))
    unassigned = int((dyn & (label < 0)).sum())
    return {"objects": rows, "stiffness_order_ok": order_ok, "dynamic_gaussians_unassigned": unassigned,
            "reach_m": reach}  # fmt: skip


def true_objects(points, data_dir, reach: float = 0.03) -> np.ndarray | None:
    """Each of ``points``' [n, 3] true object id: the object of the nearest true particle at rest
    (``gt/motion.npz``; a scene starts at rest), -1 farther than ``reach`` metres; None without ground-truth motion."""
    motion_path = Path(data_dir) / "gt" / "motion.npz"
    if not motion_path.is_file():
        return None
    with np.load(motion_path) as z:
        if "particles_rest" not in z or "particle_object" not in z:
            return None
        rest, owner = z["particles_rest"], z["particle_object"]
    reach = reach * truth_scale(data_dir)
    dist, idx = cKDTree(rest).query(np.asarray(points, dtype=np.float64))
    return np.where(dist < reach, owner[idx], -1)


def true_gravity(data_dir) -> np.ndarray | None:
    """The scene's gravity vector in the dataset's frame (``gt/meta.json``: an MPM scene's ``gravity`` effect or an
    engine scene's ``motion.gravity``, re-posed with the dataset); None when the truth does not say."""
    meta_path = Path(data_dir) / "gt" / "meta.json"
    if not meta_path.is_file():
        return None
    motion = read_json(meta_path, "ground truth").get("motion", {})
    g = motion.get("gravity")
    if g is None:
        g = motion.get("effects", {}).get("gravity", {}).get("g")
    return None if g is None else np.asarray(g, dtype=np.float64)


def frame_report(frame: dict | None, data_dir) -> dict | None:
    """The inferred physics frame (run.json ``frame``) against the truth: the angle between the inferred and the true
    up (degrees) and the inferred gravity's magnitude over the true one; None without either."""
    g = true_gravity(data_dir)
    if not frame or g is None or not np.linalg.norm(g) > 0:
        return None
    up_true = -g / np.linalg.norm(g)
    up = np.asarray(frame["up"], dtype=np.float64)
    angle = float(np.degrees(np.arccos(np.clip(up @ up_true / np.linalg.norm(up), -1.0, 1.0))))
    gravity = frame.get("gravity_learned", frame.get("gravity"))
    return {"up": up.tolist(), "up_true": up_true.tolist(), "up_error_deg": angle, "source": frame.get("source"),
            "gravity": gravity, "gravity_measured": frame.get("gravity"), "gravity_true": float(np.linalg.norm(g)),
            "gravity_ratio": None if gravity is None else float(gravity / np.linalg.norm(g))}  # fmt: skip


def truth_scale(data_dir) -> float:
    """The dataset's length unit per original metre: the scale of ``gt/meta.json`` ``frame`` for a dataset re-posed
    by ``causalgs reframe``, else 1."""
    meta = Path(data_dir) / "gt" / "meta.json"
    if not meta.is_file():
        return 1.0
    frame = read_json(meta, "ground truth").get("frame")
    return float(frame["scale"]) if isinstance(frame, dict) and "scale" in frame else 1.0


def rigid_spin(r: np.ndarray, v: np.ndarray) -> np.ndarray | None:
    """ω [3] of the least-squares rigid velocity field v_i ≈ a + ω × r_i through velocities ``v`` [n, 3] at offsets
    ``r`` [n, 3]; None when the points are too few or collinear for ω to be determined."""
    r, v = np.asarray(r, dtype=np.float64), np.asarray(v, dtype=np.float64)
    if len(r) < 3:
        return None
    rc = r - r.mean(0)  # ω × r with r about the points' centroid: the translation separates from ω
    A = np.zeros((len(r), 3, 3))
    A[:, 0, 1], A[:, 0, 2] = rc[:, 2], -rc[:, 1]  # ω × r = -[r]× ω
    A[:, 1, 0], A[:, 1, 2] = -rc[:, 2], rc[:, 0]
    A[:, 2, 0], A[:, 2, 1] = rc[:, 1], -rc[:, 0]
    A = A.reshape(-1, 3)
    if np.linalg.matrix_rank(A, tol=1e-9 * max(1.0, float(np.abs(A).max()))) < 3:
        return None
    b = (v - v.mean(0)).reshape(-1)
    return np.linalg.lstsq(A, b, rcond=None)[0]
