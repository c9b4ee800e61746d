"""``causalgs reframe``: a dataset re-posed in another world frame and scale by a similarity transform.

The same cameras see the same scene, so the images stay byte for byte as they are; what changes is every quantity
that lives in the world: the cameras' camera-to-world matrices, ``points3d.ply`` and the ground truth in ``gt/``
(trajectories, poses, velocities, spins, deformation gradients, surface meshes; the object table, the effects'
gravity and planes, the cameras' target and up). Arrays of ``gt/motion.npz`` that are not world quantities (times,
ids, triangles, body-frame samples) are copied; any array this module does not know is copied too and listed in
``gt/meta.json`` under ``frame.unchanged``. ``gt/meta.json`` records the transform from the original frame
(``frame``, composed when a re-posed dataset is re-posed again), so its truth can be compared with a model's.

The output folder is written beside its final place and moved there at the end: a failure leaves nothing.
"""

from __future__ import annotations

import re
import shutil
import tempfile
from pathlib import Path

import numpy as np

from causalgs.dataset import SPLITS, load_dataset
from causalgs.errors import CausalGSError
from causalgs.io import read_json, write_json, write_npz
from causalgs.ply import read_points_ply, write_points_ply
from causalgs.similarity import Similarity

__all__ = ["reframe_dataset", "transform_motion"]

# gt/motion.npz keys by how they transform (full names or prefixes ending in "_"): positions, velocity-like vectors,
# directions (spins, normals), orientations (body-to-world rotations), deformation gradients, and what is not a
# world quantity at all.
_RULES: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("points", ("particles_rest", "particles", "trajectories", "c0", "c", "vertices_", "pose_c_",
                "contact_event_position")),
    ("vectors", ("velocity", "velocity_", "v")),
    ("directions", ("omega", "omega_", "contact_event_normal")),
    ("orientations", ("R", "pose_R_")),
    ("deformations", ("F",)),
    ("same", ("times", "seconds", "fps", "object_ids", "part_ids", "particle_object", "triangles_", "body_points",
              "body_normals", "contact", "contact_event_seconds", "contact_event_frame", "contact_event_pair")),
)


def _rule(key: str) -> str | None:
    for kind, names in _RULES:
        for n in names:
            if key == n or (n.endswith("_") and key.startswith(n) and key[len(n) :].isdigit()):
                return kind
    return None


def transform_motion(arrays: dict[str, np.ndarray], sim: Similarity) -> tuple[dict[str, np.ndarray], list[str]]:
    """gt/motion.npz arrays re-posed by ``sim`` (each kept in its dtype) and the keys copied as they were."""
    out, unknown = {}, []
    for key, a in arrays.items():
        kind = _rule(key)
        if kind is None:
            unknown.append(key)
        if kind in (None, "same") or not np.issubdtype(a.dtype, np.floating):
            out[key] = a
            continue
        out[key] = getattr(sim, kind)(a).astype(a.dtype)
    return out, unknown


def _transform_meta(meta: dict, sim: Similarity, unknown: list[str]) -> dict:
    """gt/meta.json with its world quantities re-posed and the composed transform from the original frame."""
    meta = dict(meta)
    for o in meta.get("objects", []):
        if o.get("center") is not None:
            o["center"] = sim.points(o["center"]).tolist()
        if o.get("velocity") is not None:
            o["velocity"] = sim.vectors(o["velocity"]).tolist()
        if o.get("omega") is not None:
            o["omega"] = sim.directions(o["omega"]).tolist()
        if o.get("quat") is not None:  # the body's orientation at t = 0 (wxyz, body to world)
            o["quat"] = sim.quaternions(o["quat"]).tolist()
    motion = meta.get("motion", {})
    if isinstance(motion.get("gravity"), list):
        motion["gravity"] = sim.vectors(motion["gravity"]).tolist()
    effects = motion.get("effects", {})
    if isinstance(effects, dict):
        for name, params in effects.items():
            if name == "gravity" and "g" in params:
                params["g"] = sim.vectors(params["g"]).tolist()
            if "n" in params and "d" in params:
                n, d = sim.plane(params["n"], float(np.ravel(params["d"])[0]))
                params["n"], params["d"] = n.tolist(), [d]
    cams = meta.get("cameras", {})
    if isinstance(cams, dict):
        if cams.get("target") is not None:
            cams["target"] = sim.points(cams["target"]).tolist()
        if cams.get("up") is not None:
            cams["up"] = sim.directions(cams["up"]).tolist()
        if cams.get("distance") is not None:
            cams["distance"] = float(cams["distance"]) * sim.scale
    before = Similarity.from_json(meta["frame"], "gt/meta.json frame") if "frame" in meta else Similarity.identity()
    meta["frame"] = {**before.then(sim).to_json(), "unchanged": sorted(unknown),
                     "rule": "x_here = scale * rotation @ x_original + translation"}  # fmt: skip
    return meta


def _check_out(out: Path, src: Path, overwrite: bool) -> None:
    if out.resolve() == src.resolve():
        raise CausalGSError(f"--out {out} is the dataset itself; choose another folder")
    if out.exists() and not out.is_dir():
        raise CausalGSError(f"--out {out} is a file, not a folder")
    if out.is_dir() and any(out.iterdir()) and not overwrite:
        raise CausalGSError(f"{out} already holds files; pass --force to overwrite")


def _copy_tree_files(src: Path, dst: Path, skip: set[Path]) -> None:
    """Every file under ``src`` into ``dst`` (hard links where the file system allows, else copies), but ``skip``."""
    for p in sorted(src.rglob("*")):
        if p.is_dir() or p in skip:
            continue
        target = dst / p.relative_to(src)
        target.parent.mkdir(parents=True, exist_ok=True)
        try:
            target.hardlink_to(p)
        except OSError:
            shutil.copy2(p, target)


def reframe_dataset(data, out, sim: Similarity, *, overwrite: bool = False) -> str:
    """Write the dataset ``data`` re-posed by ``sim`` into ``out``; return a one-line summary."""
    src, out = Path(data), Path(out)
    load_dataset(src)  # a broken dataset is its own one-line error, before anything is written
    _check_out(out, src, overwrite)
    rewritten: dict[Path, object] = {}
    for split in SPLITS:
        path = src / f"transforms_{split}.json"
        if path.is_file():
            d = read_json(path, path.name)
            for f in d["frames"]:
                f["transform_matrix"] = sim.camera_to_world(f["transform_matrix"]).tolist()
            rewritten[path] = d
    ply = src / "points3d.ply"
    motion, meta = src / "gt" / "motion.npz", src / "gt" / "meta.json"
    skip = set(rewritten) | {p for p in (ply, motion, meta) if p.is_file()}
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    try:
        _copy_tree_files(src, tmp, skip)
        for path, d in rewritten.items():
            write_json(tmp / path.name, d)
        if ply.is_file():
            xyz, rgb = read_points_ply(ply)
            write_points_ply(tmp / "points3d.ply", sim.points(xyz).astype(np.float32), rgb)
        unknown: list[str] = []
        if motion.is_file():
            with np.load(motion) as z:
                arrays, unknown = transform_motion({k: z[k] for k in z.files}, sim)
            write_npz(tmp / "gt" / "motion.npz", **arrays)
        if meta.is_file():
            write_json(tmp / "gt" / "meta.json", _transform_meta(read_json(meta, "ground truth"), sim, unknown))
        _move_into_place(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    angle = np.degrees(np.arccos(np.clip((np.trace(sim.R) - 1) / 2, -1, 1)))
    return (f"Wrote {src} re-posed to {out}: rotated {angle:.1f}°, scale {sim.scale:g}, translated "
            f"{np.round(sim.t, 4).tolist()}")  # fmt: skip


def _move_into_place(tmp: Path, out: Path) -> None:
    """Replace ``out`` by the finished folder ``tmp``; an old ``out`` is moved aside first and removed after."""
    old = None
    if out.exists():
        old = out.with_name(f".{out.name}.old-{re.sub(r'[^0-9]', '', tmp.name)[-8:] or 'x'}")
        out.rename(old)
    try:
        tmp.rename(out)
    except BaseException:
        if old is not None:
            old.rename(out)
        raise
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)
