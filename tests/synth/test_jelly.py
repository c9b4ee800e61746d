"""The jelly scene: MPM-driven truth, mesh renderer, layout, determinism and the physics of the generated data.

A coarser reference grid than the default (``reference_res``) keeps the suite fast; the physics checks hold at any
resolution.
"""

from __future__ import annotations

import hashlib
import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from causalgs.dataset import load_dataset
from causalgs.errors import CausalGSError
from causalgs.synth import generate, physics
from causalgs.synth.writer import write_dataset

VIEWS, FRAMES, RES, SIM_RES = 4, 8, 40, 32
FPS = 24.0  # 8 frames at 24 fps: the jelly falls, lands and bounces
BG = (1.0, 1.0, 1.0)


def _make(out: Path, seed: int = 0, effects: str | None = None, frames: int = FRAMES) -> None:
    scene = physics.jelly(views=VIEWS, frames=frames, resolution=RES, seed=seed, effects=effects, progress=False,
                          reference_res=SIM_RES, fps=FPS)  # fmt: skip
    write_dataset(out, scene, background=BG, progress=False, options={"seed": seed})


def _hashes(root: Path) -> dict[str, str]:
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(root.rglob("*"))
            if p.is_file()}  # fmt: skip


@pytest.fixture(scope="module")
def jelly(tmp_path_factory):
    from causalgs import _ti

    _ti.init("cpu", "float32")
    out = tmp_path_factory.mktemp("jelly") / "data"
    _make(out)
    with np.load(out / "gt" / "motion.npz") as z:
        motion = dict(z)
    return out, load_dataset(out), motion, json.loads((out / "gt" / "meta.json").read_text())


def test_layout_meta_and_contact_sheet(jelly):
    out, ds, motion, meta = jelly
    assert {s: len(f) for s, f in ds.splits.items()} == {"train": 18, "val": 6, "test": 8}
    assert meta["renderer"].startswith("z-buffer triangle rasterizer")
    assert meta["motion"]["effects"]["ground"]["mu"] == [0.4] and "gravity" in meta["motion"]["effects"]
    (body,) = [o for o in meta["objects"] if o["name"] == "jelly"]
    assert body["id"] == 2 and 1.5e4 <= body["E"] <= 2.5e4 and body["particles"] == len(motion["particles_rest"])
    assert motion["particles"].shape == (FRAMES, len(motion["particles_rest"]), 3)
    sheet = cv2.imread(str(out / "contact_sheet.png"))
    assert sheet.shape == (4 * RES, 8 * RES, 3)


def test_volume_is_nearly_preserved(jelly):
    """The nearly incompressible jelly (nu = 0.45) keeps its volume within a few percent through the fall and the
    impact: the mean det F of the particles, and the volume enclosed by the carried surface mesh."""
    _, _, motion, _ = jelly
    J = np.linalg.det(motion["F"].astype(np.float64))
    assert np.abs(J.mean(1) - 1).max() < 0.04
    V, T = motion["vertices_2"].astype(np.float64), motion["triangles_2"]
    tri = V[:, T]  # [frames, T, 3, 3]
    vol = np.einsum("ftj,ftj->ft", tri[:, :, 0], np.cross(tri[:, :, 1], tri[:, :, 2])).sum(1) / 6.0
    assert vol[0] > 0, "outward winding"
    assert np.abs(vol / vol[0] - 1).max() < 0.05


def _dt_max(meta) -> float:
    """The largest substep of the run (symplectic Euler adds g·t·dt/2 to a free fall)."""
    return 1.0 / (meta["fps"] * min(meta["motion"]["substeps_per_frame"]))


def test_falls_under_gravity_until_contact(jelly):
    """Before touching the ground the centre of mass follows z0 − g t²/2 (no drag in the default effects)."""
    _, _, motion, meta = jelly
    com = motion["particles"].astype(np.float64).mean(1)
    t = motion["seconds"]
    lowest = motion["particles"][:, :, 2].min(1)
    airborne = [k for k in range(1, FRAMES) if lowest[k] > 0.05]
    assert len(airborne) >= 3
    for k in airborne:
        law = com[0, 2] - 0.5 * 9.8 * t[k] ** 2
        tol = 0.01 * 0.5 * 9.8 * t[k] ** 2 + 9.8 * t[k] * _dt_max(meta)
        assert abs(com[k, 2] - law) < tol, f"frame {k}: z {com[k, 2]:.5f}, law {law:.5f}"


def test_masks_agree_with_projected_vertices(jelly):
    out, ds, motion, _ = jelly
    for f in ds.frames():
        mask = cv2.imread(str(out / "gt" / "masks" / f"r_{f.view:03d}_{f.frame:03d}.png"), cv2.IMREAD_UNCHANGED)
        assert set(np.unique(mask).tolist()) <= {0, 1, 2} and (mask == 2).any()
        uv, depth = f.camera.project(motion["vertices_2"][f.frame])
        assert np.all(depth > 0)
        ys, xs = np.nonzero(mask == 2)
        # The body's silhouette is the projection of its surface: the same box to within a pixel.
        assert abs(xs.min() - uv[:, 0].min()) < 1.5 and abs(xs.max() + 1 - uv[:, 0].max()) < 1.5
        assert abs(ys.min() - uv[:, 1].min()) < 1.5 and abs(ys.max() + 1 - uv[:, 1].max()) < 1.5
        # Alpha covers body and floor; it agrees with the mask away from edges.
        assert np.abs((f.alpha > 0.5).astype(float) - (mask > 0)).mean() < 0.05


def test_deterministic_for_a_seed(jelly, tmp_path):
    again = tmp_path / "again"
    _make(again)
    assert _hashes(again) == _hashes(jelly[0])


def test_linear_drag_switch_changes_the_fall_as_its_law_says(jelly, tmp_path):
    """With 'linear_drag:c=4' the fall follows z0 − (g/c)(t − (1 − e^(−ct))/c) and the horizontal velocity decays
    as e^(−ct), instead of free fall."""
    out = tmp_path / "drag"
    c = 4.0
    _make(out, effects=f"gravity;ground:mu=0.4;linear_drag:c={c};walls", frames=5)
    with np.load(out / "gt" / "motion.npz") as z:
        x, t = z["particles"].astype(np.float64), z["seconds"]
    dt = _dt_max(json.loads((out / "gt" / "meta.json").read_text()))
    com = x.mean(1)
    free = jelly[2]["particles"].astype(np.float64).mean(1)
    for k in range(1, 5):
        drop = (9.8 / c) * (t[k] - (1 - math.exp(-c * t[k])) / c)
        assert abs(com[0, 2] - com[k, 2] - drop) < 0.03 * drop + 9.8 * t[k] * dt, k
    assert com[0, 2] - com[4, 2] < 0.9 * (free[0, 2] - free[4, 2]), "drag must slow the fall"
    # Horizontal drift: displacement (v0/c)(1 − e^(−ct)) instead of v0 t.
    v_free = (free[1, :2] - free[0, :2]) / t[1]
    disp = com[4, :2] - com[0, :2]
    np.testing.assert_allclose(disp, v_free * (1 - math.exp(-c * t[4])) / c, rtol=0.1, atol=2e-3)


def test_effects_are_checked_and_only_for_simulated_scenes(tmp_path):
    with pytest.raises(CausalGSError, match="unknown effect 'wind'"):
        generate("jelly", tmp_path / "a", effects="gravity;wind", progress=False)
    with pytest.raises(CausalGSError, match="scene 'spin' has analytic motion and takes no --effects"):
        generate("spin", tmp_path / "b", effects="gravity", progress=False)
