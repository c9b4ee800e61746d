"""Write a synthetic scene as a D-NeRF / NVFi / FreeGave dataset plus ground truth.

Every built-in scene goes through this one writer so that all of them share the same layout and split protocol (see
DESIGN.md "Data conventions")::

    OUT/transforms_{train,val,test}.json camera_angle_x, fps, background, frames (file_path, time, matrix, view, frame)
    OUT/{train,val,test}/r_VVV_FFF.png   RGBA, alpha = pixel coverage, RGB = background where alpha = 0
    OUT/points3d.ply                     surface samples at t = 0 with colours (an SfM-like initial cloud)
    OUT/gt/masks/r_VVV_FFF.png           uint8 object ids at pixel centres, for every view and frame
    OUT/gt/motion.npz                    the true motion (scene-specific arrays)
    OUT/gt/meta.json                     options, protocol, motion law, object table, renderer
    OUT/contact_sheet.png                a grid of views (rows) × times (columns), to look at

The protocol scales the 20-view / 89-frame benchmark: a few views spread around the ring are held out for
interpolation (val), the last quarter of the frames is kept for extrapolation (test, every view).
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from causalgs.cameras import Camera
from causalgs.errors import CausalGSError
from causalgs.io import write_image, write_json, write_npz
from causalgs.ply import write_points_ply
from causalgs.progress import progress_bar

__all__ = ["Protocol", "SynthScene", "protocol", "write_dataset"]

_IMAGE_NAME = re.compile(r"^r_\d{3,}_\d{3,}\.png$")
SHEET_VIEWS, SHEET_FRAMES = 4, 8  # the contact sheet: evenly spaced views (rows) and frames (columns)


def _round_half_up(x: float) -> int:
    """Rounding that does not depend on Python's banker's rounding of exact halves."""
    return math.floor(x + 0.5)


@dataclass(frozen=True)
class Protocol:
    """Which views and frames go to which split."""

    views: int
    frames: int
    val_views: tuple[int, ...]
    n_obs: int

    @property
    def train_views(self) -> tuple[int, ...]:
        return tuple(v for v in range(self.views) if v not in self.val_views)

    def split_of(self, view: int, frame: int) -> str:
        if frame >= self.n_obs:
            return "test"
        return "val" if view in self.val_views else "train"

    def counts(self) -> dict[str, int]:
        n_future = self.frames - self.n_obs
        return {
            "train": len(self.train_views) * self.n_obs,
            "val": len(self.val_views) * self.n_obs,
            "test": self.views * n_future,
        }

    def to_json(self) -> dict:
        return {
            "val_views": list(self.val_views),
            "train_views": list(self.train_views),
            "n_val_views": len(self.val_views),
            "n_observed_frames": self.n_obs,
            "n_future_frames": self.frames - self.n_obs,
            "counts": self.counts(),
            "rule": "scaled from 20 views / 89 frames: val = round(0.15 views) held-out views spread evenly, "
            "observed = round(67/89 frames); train/val = observed frames, test = future frames from all views",
        }


def protocol(views: int, frames: int) -> Protocol:
    """The split protocol for ``views`` cameras and ``frames`` times (needs ``views >= 2``, ``frames >= 2``)."""
    n_val = max(1, _round_half_up(0.15 * views))
    val = tuple(sorted({_round_half_up((j + 0.5) * views / n_val) % views for j in range(n_val)}))
    n_obs = min(frames - 1, max(1, _round_half_up(frames * 67 / 89)))
    return Protocol(views, frames, val, n_obs)


@dataclass
class SynthScene:
    """What a scene builder hands to the writer.

    ``render(k)`` yields, for every camera in order, ``(rgb, alpha, ids)`` at frame ``k``: straight (not premultiplied)
    colour float [H, W, 3] in [0, 1] (the mean over covered subsamples), coverage float [H, W] in [0, 1] and uint8
    object ids [H, W] at pixel centres. ``motion`` goes to gt/motion.npz, ``meta`` into gt/meta.json.
    """

    name: str
    cameras: list[Camera]
    fps: float
    frames: int
    render: Callable[[int], Iterator[tuple[np.ndarray, np.ndarray, np.ndarray]]]
    points: np.ndarray
    point_colors: np.ndarray
    motion: dict[str, np.ndarray]
    meta: dict = field(default_factory=dict)

    @property
    def times(self) -> np.ndarray:
        """Normalised frame times t_k = k / (frames - 1) in [0, 1]."""
        return np.arange(self.frames, dtype=np.float64) / (self.frames - 1)


def check_out(out: Path, overwrite: bool) -> None:
    """Refuse to write over an existing dataset unless asked; a file in the way is an error either way."""
    if out.exists() and not out.is_dir():
        raise CausalGSError(f"--out {out} is a file, not a folder")
    if out.is_dir() and any(out.iterdir()) and not overwrite:
        raise CausalGSError(f"{out} already holds a dataset; pass --force to overwrite")


def _to_uint8(x: np.ndarray) -> np.ndarray:
    return np.clip(np.round(np.asarray(x, dtype=np.float64) * 255.0), 0, 255).astype(np.uint8)


def encode_rgba(rgb: np.ndarray, alpha: np.ndarray, background) -> np.ndarray:
    """RGBA uint8 with straight colour; fully transparent pixels carry the background colour (readers that ignore
    alpha then still see the right image)."""
    a = _to_uint8(alpha)
    c = _to_uint8(rgb)
    c[a == 0] = _to_uint8(np.asarray(background))
    return np.concatenate([c, a[..., None]], axis=-1)


def _progress(enabled: bool):
    return progress_bar(enabled)


def write_dataset(
    out, scene: SynthScene, *, background, overwrite: bool = False, progress: bool = True, options: dict | None = None
) -> dict:
    """Render ``scene`` into ``out`` and return the protocol counts; every file is written atomically."""
    out = Path(out)
    check_out(out, overwrite)
    views, frames = len(scene.cameras), scene.frames
    proto = protocol(views, frames)
    times = scene.times
    fov = scene.cameras[0].fov_x
    bg = [float(v) for v in background]
    entries: dict[str, list] = {"train": [], "val": [], "test": []}
    written: set[Path] = set()

    sheet_views = sorted(
        {round(i * (views - 1) / max(1, min(views, SHEET_VIEWS) - 1)) for i in range(min(views, SHEET_VIEWS))}
    )
    sheet_frames = sorted(
        {round(i * (frames - 1) / max(1, min(frames, SHEET_FRAMES) - 1)) for i in range(min(frames, SHEET_FRAMES))}
    )
    sheet: dict[tuple[int, int], np.ndarray] = {}
    with _progress(progress) as bar:
        task = bar.add_task(f"rendering {scene.name}", total=frames)
        for k in range(frames):
            for v, (rgb, alpha, ids) in enumerate(scene.render(k)):
                if v in sheet_views and k in sheet_frames:
                    a = np.asarray(alpha, dtype=np.float64)[..., None]
                    sheet[v, k] = _to_uint8(a * np.asarray(rgb) + (1 - a) * np.asarray(bg))
                split = proto.split_of(v, k)
                stem = f"r_{v:03d}_{k:03d}"
                img_path, mask_path = out / split / f"{stem}.png", out / "gt" / "masks" / f"{stem}.png"
                write_image(img_path, encode_rgba(rgb, alpha, bg))
                write_image(mask_path, np.ascontiguousarray(ids, dtype=np.uint8))
                written.update((img_path, mask_path))
                entries[split].append(
                    {
                        "file_path": f"./{split}/{stem}",
                        "time": float(times[k]),
                        "transform_matrix": scene.cameras[v].c2w_opengl.tolist(),
                        "view": v,
                        "frame": k,
                    }
                )
            bar.advance(task)

    for split, frs in entries.items():  # frame-major order, as rendered
        write_json(
            out / f"transforms_{split}.json",
            {"camera_angle_x": fov, "fps": float(scene.fps), "background": bg, "frames": frs},
        )
    write_points_ply(out / "points3d.ply", np.asarray(scene.points, dtype=np.float32), scene.point_colors)
    write_npz(out / "gt" / "motion.npz", **scene.motion)
    meta = {
        "scene": scene.name,
        **(options or {}),
        "image_size": [scene.cameras[0].width, scene.cameras[0].height],
        "camera_angle_x": fov,
        "fps": float(scene.fps),
        "protocol": proto.to_json(),
        **scene.meta,
        "renderer": scene.meta.get("renderer", "analytic ray casting"),
    }
    write_json(out / "gt" / "meta.json", meta)
    rows = [np.concatenate([sheet[v, k] for k in sheet_frames], axis=1) for v in sheet_views]
    write_image(out / "contact_sheet.png", np.concatenate(rows, axis=0))
    _remove_stale(out, written)
    return proto.counts()


def _remove_stale(out: Path, written: set[Path]) -> None:
    """After an overwrite with fewer views or frames, drop old images this run did not write (only ours)."""
    for folder in (out / "train", out / "val", out / "test", out / "gt" / "masks"):
        if folder.is_dir():
            for p in folder.iterdir():
                if p.is_file() and _IMAGE_NAME.match(p.name) and p not in written:
                    p.unlink()
