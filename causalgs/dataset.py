"""The dataset reader: D-NeRF / NVFi / FreeGave multi-view video folders.

Layout (see DESIGN.md "Data conventions")::

    DIR/transforms_train.json   required
    DIR/transforms_val.json     optional: held-out views inside the observed time window (interpolation)
    DIR/transforms_test.json    optional: future frames from every view (extrapolation)
    DIR/points3d.ply            optional initial point cloud

Each JSON holds ``camera_angle_x`` (radians) or ``fl_x`` (+ ``fl_y``, ``cx``, ``cy``, ``w``, ``h``), optional ``fps``
and ``background``, and ``frames`` with ``file_path`` (relative to DIR, extension optional), ``time`` in [0, 1] and an
OpenGL camera-to-world ``transform_matrix``; frames may override the intrinsics and carry integer ``view``/``frame``.

Everything is checked while loading, so that a broken dataset fails at once with one line naming the file and the
value, instead of as a shape error deep inside training.
"""

from __future__ import annotations

import dataclasses
import math
import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from causalgs.cameras import Camera, check_rigid
from causalgs.errors import DataError
from causalgs.io import read_json
from causalgs.ply import read_points_ply

__all__ = ["SPLITS", "Dataset", "Frame", "load_dataset"]

SPLITS = ("train", "val", "test")
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg")
_INTRINSICS = ("camera_angle_x", "fl_x", "fl_y", "cx", "cy", "w", "h")
_WHITE = np.ones(3, dtype=np.float32)


@dataclass(eq=False)
class Frame:
    """One image of one camera at one time. Pixels stay as read (8 or 16 bit) to keep memory low; floats on demand."""

    split: str
    index: int
    path: Path
    time: float
    camera: Camera = field(repr=False)
    view: int | None
    frame: int | None
    rgba: np.ndarray = field(repr=False)  # uint8 or uint16 [H, W, 3|4], RGB(A) order, after downscale
    background: np.ndarray = field(repr=False)  # float32 [3]

    @property
    def _scale(self) -> float:
        return 65535.0 if self.rgba.dtype == np.uint16 else 255.0

    @property
    def alpha(self) -> np.ndarray:
        """Opacity float32 [H, W] in [0, 1] (ones when the file has no alpha channel)."""
        if self.rgba.shape[2] < 4:
            return np.ones(self.rgba.shape[:2], dtype=np.float32)
        return self.rgba[..., 3].astype(np.float32) / np.float32(self._scale)

    @property
    def image(self) -> np.ndarray:
        """Colour float32 [H, W, 3] in [0, 1], composited on the background: ``alpha * rgb + (1 - alpha) * bg``."""
        rgb = self.rgba[..., :3].astype(np.float32) / np.float32(self._scale)
        if self.rgba.shape[2] < 4:
            return rgb
        a = self.alpha[..., None]
        return a * rgb + (np.float32(1.0) - a) * self.background.astype(np.float32)


@dataclass(eq=False)
class Dataset:
    """All splits of a dataset; ``splits`` always has the keys ``train``, ``val`` and ``test`` (maybe empty)."""

    root: Path
    splits: dict[str, list[Frame]]
    background: np.ndarray
    fps: float | None = None
    points: np.ndarray | None = field(default=None, repr=False)
    point_colors: np.ndarray | None = field(default=None, repr=False)

    @property
    def train(self) -> list[Frame]:
        return self.splits["train"]

    @property
    def val(self) -> list[Frame]:
        return self.splits["val"]

    @property
    def test(self) -> list[Frame]:
        return self.splits["test"]

    def frames(self) -> list[Frame]:
        """Every loaded frame, split by split."""
        return [f for s in SPLITS for f in self.splits.get(s, [])]

    @property
    def image_size(self) -> tuple[int, int]:
        """``(width, height)`` shared by every image (after downscale)."""
        first = self.frames()[0].camera
        return first.width, first.height

    def times(self, split: str | None = None) -> np.ndarray:
        """Sorted unique frame times (float64) of one split, or of all splits."""
        frames = self.frames() if split is None else self.splits[split]
        return np.unique(np.array([f.time for f in frames], dtype=np.float64))

    def reframed(self, sim) -> Dataset:
        """The same images seen by cameras re-posed by the similarity ``sim`` (and the initial points with them):
        the dataset in another world frame (:mod:`causalgs.similarity`). Images are shared, not copied."""
        if sim.is_identity:
            return self
        splits = {}
        for name, frames in self.splits.items():
            splits[name] = [dataclasses.replace(f, camera=Camera(f.camera.K, np.linalg.inv(
                sim.camera_to_world(f.camera.c2w)), f.camera.width, f.camera.height)) for f in frames]  # fmt: skip
        points = None if self.points is None else sim.points(self.points).astype(self.points.dtype)
        return dataclasses.replace(self, splits=splits, points=points)

    def summary(self) -> str:
        """A few human-readable lines: what `causalgs info` prints."""
        w, h = self.image_size
        channels = {f.rgba.shape[2] for f in self.frames()}
        kind = "RGBA" if 4 in channels else "RGB"
        bg = ", ".join(f"{v:g}" for v in self.background.tolist())
        lines = [f"Dataset: {self.root}", f"  images: {w}x{h} {kind}, background [{bg}]"]
        for name in SPLITS:
            frames = self.splits[name]
            if not frames:
                lines.append(f"  {name + ':':6} none")
                continue
            t = self.times(name)
            lines.append(
                f"  {name + ':':6} {len(frames)} frames, {_count_views(frames)} views, "
                f"{len(t)} times in [{t[0]:.4g}, {t[-1]:.4g}]"
            )
        if self.points is None:
            lines.append("  points3d.ply: none")
        else:
            colours = "with colours" if self.point_colors is not None else "no colours"
            lines.append(f"  points3d.ply: {len(self.points)} points ({colours})")
        lines.append(f"  fps: {self.fps:g}" if self.fps is not None else "  fps: not given")
        return "\n".join(lines)


def _count_views(frames: Sequence[Frame]) -> int:
    """Distinct cameras: the ``view`` ids when every frame has one, else distinct poses and intrinsics."""
    if all(f.view is not None for f in frames):
        return len({f.view for f in frames})
    keys = {tuple(np.round(np.concatenate([f.camera.viewmat.ravel(), f.camera.K.ravel()]), 6)) for f in frames}
    return len(keys)


# ---------------------------------------------------------------------------------------------------------------------
# Value checks: each raises DataError naming ``what`` (which starts with the file path) and the value.
# ---------------------------------------------------------------------------------------------------------------------
def _show(value) -> str:
    """A value as it would be written in the file, short and on one line."""
    if isinstance(value, np.ndarray):
        value = [float(f"{v:.6g}") for v in value.ravel().tolist()]
    text = " ".join(repr(value).split())
    return text if len(text) <= 60 else text[:57] + "..."


def _number(value, what: str) -> float:
    """A finite JSON number (bools and numeric strings are rejected: they are always a mistake in these files)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise DataError(f"{what} = {_show(value)} is not a number")
    v = float(value)
    if not math.isfinite(v):
        raise DataError(f"{what} = {v} is not finite")
    return v


def _index(value, what: str) -> int:
    v = _number(value, what)
    if v < 0 or not v.is_integer():
        raise DataError(f"{what} = {_show(value)} must be a non-negative integer")
    return int(v)


def _rgb(value, what: str) -> np.ndarray:
    ok = isinstance(value, (list, tuple, np.ndarray)) and len(value) == 3
    if ok:
        try:
            vals = [_number(v, what) for v in value]
        except DataError:
            ok = False
        else:
            ok = all(0.0 <= v <= 1.0 for v in vals)
    if not ok:
        raise DataError(f"{what} = {_show(value)} must be three numbers in [0, 1]")
    return np.array(vals, dtype=np.float32)


def _intrinsics(d: dict, where: str) -> dict[str, float]:
    """The intrinsics keys present in ``d``, checked: focal terms positive, ``w``/``h`` positive integers."""
    out = {}
    for key in _INTRINSICS:
        if key not in d:
            continue
        what = f"{where} {key}"
        if key in ("w", "h"):
            v = _index(d[key], what)
            if v == 0:
                raise DataError(f"{what} = 0 must be positive")
        else:
            v = _number(d[key], what)
            if key in ("camera_angle_x", "fl_x", "fl_y") and v <= 0:
                raise DataError(f"{what} = {v:g} must be positive")
            if key == "camera_angle_x" and v >= math.pi:
                raise DataError(f"{what} = {v:g} must be below pi radians")
        out[key] = v
    return out


# ---------------------------------------------------------------------------------------------------------------------
# Images
# ---------------------------------------------------------------------------------------------------------------------
def _find_image(root: Path, file_path: str, what: str) -> Path:
    base = root / file_path
    candidates = [base] + [Path(str(base) + ext) for ext in IMAGE_EXTENSIONS]
    for c in candidates:
        if c.is_file():
            return c
    raise DataError(f"{what}: image file not found: {base} (also tried {', '.join(IMAGE_EXTENSIONS)})")


def _read_image(path: Path, what: str) -> np.ndarray:
    """RGB(A) uint8/uint16 [H, W, 3|4]. Decoded from bytes so that non-ASCII paths work and cv2 stays quiet."""
    try:
        buf = np.fromfile(path, dtype=np.uint8)
    except OSError as e:
        raise DataError(f"{path}: cannot read image ({e.strerror or type(e).__name__}; {what})") from None
    img = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED) if buf.size else None
    if img is None:
        raise DataError(f"{path}: unreadable or corrupt image ({what})")
    if img.dtype not in (np.uint8, np.uint16):
        raise DataError(f"{path}: unsupported pixel type {img.dtype} (expected 8- or 16-bit; {what})")
    if img.ndim == 2 or (img.ndim == 3 and img.shape[2] == 1):
        img = cv2.cvtColor(img.reshape(img.shape[:2]), cv2.COLOR_GRAY2RGB)
    elif img.ndim == 3 and img.shape[2] == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    elif img.ndim == 3 and img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2RGBA)
    else:
        raise DataError(f"{path}: unsupported image layout {list(img.shape)} ({what})")
    return img


# ---------------------------------------------------------------------------------------------------------------------
# Loading
# ---------------------------------------------------------------------------------------------------------------------
class _SizeCheck:
    """Every image of the dataset must have one size; the first image read sets it."""

    def __init__(self):
        self.size: tuple[int, int] | None = None

    def __call__(self, path: Path, w: int, h: int) -> None:
        if self.size is None:
            self.size = (w, h)
        elif self.size != (w, h):
            w0, h0 = self.size
            raise DataError(f"{path} is {w}x{h} but the other images are {w0}x{h0}")


def _read_split_json(path: Path) -> tuple[dict, list]:
    data = read_json(path, what=path.name)
    if not isinstance(data, dict):
        raise DataError(f"{path}: the top level must be a JSON object, got {type(data).__name__}")
    if "frames" not in data:
        raise DataError(f"{path}: missing key 'frames'")
    frames = data["frames"]
    if not isinstance(frames, list):
        raise DataError(f"{path}: 'frames' must be a list, got {type(frames).__name__}")
    if not frames:
        raise DataError(f"{path}: 'frames' is empty (remove the file if the split has no frames)")
    return data, frames


def _load_frame(
    split: str, i: int, raw, json_path: Path, root: Path, top: dict[str, float], downscale: float, sizes: _SizeCheck
) -> Frame:
    where = f"{json_path}: frame {i}"
    if not isinstance(raw, dict):
        raise DataError(f"{where} must be a JSON object, got {type(raw).__name__}")
    for key in ("file_path", "time", "transform_matrix"):
        if key not in raw:
            raise DataError(f"{where}: missing key '{key}'")
    file_path = raw["file_path"]
    if not isinstance(file_path, str) or not file_path.strip():
        raise DataError(f"{where} file_path = {_show(file_path)} must be a non-empty string")
    t = _number(raw["time"], f"{where} time")
    if not 0.0 <= t <= 1.0:
        raise DataError(f"{where} time = {t:g} must be in [0, 1]")
    c2w = check_rigid(raw["transform_matrix"], f"{where} transform_matrix")
    own = _intrinsics(raw, where)
    intr = dict(top)
    if "camera_angle_x" in own or "fl_x" in own:  # a frame's own focal length replaces the top-level one entirely
        for key in ("camera_angle_x", "fl_x", "fl_y"):
            intr.pop(key, None)
    intr.update(own)
    if "camera_angle_x" not in intr and "fl_x" not in intr:
        raise DataError(f"{json_path}: missing key 'camera_angle_x' (or 'fl_x'), at the top level or in frame {i}")
    view = _index(raw["view"], f"{where} view") if raw.get("view") is not None else None
    frame_no = _index(raw["frame"], f"{where} frame") if raw.get("frame") is not None else None

    image_path = _find_image(root, file_path, where)
    rgba = _read_image(image_path, f"{json_path.name} frame {i}")
    h, w = rgba.shape[:2]
    sizes(image_path, w, h)
    if ("w" in intr and intr["w"] != w) or ("h" in intr and intr["h"] != h):
        raise DataError(
            f"{image_path} is {w}x{h} but {json_path.name} frame {i} says w={intr.get('w', w)}, h={intr.get('h', h)}"
        )
    focal = {"fov_x": intr.get("camera_angle_x"), "fl_x": intr.get("fl_x"), "fl_y": intr.get("fl_y")}
    camera = Camera.from_blender(c2w, w, h, cx=intr.get("cx"), cy=intr.get("cy"), **focal)
    if downscale != 1.0:
        # The image is resized to the camera's rounded size, so images and cameras always agree.
        camera = camera.scaled(downscale)
        rgba = cv2.resize(rgba, (camera.width, camera.height), interpolation=cv2.INTER_AREA)
    return Frame(split, i, image_path, t, camera, view, frame_no, rgba, _WHITE)


def _agreed(values: list[tuple[Path, object]], key: str, same) -> object | None:
    """The one value of a dataset-level key given in several split files; they must agree."""
    if not values:
        return None
    first_path, first = values[0]
    for path, v in values[1:]:
        if not same(v, first):
            raise DataError(f"{path}: {key} = {_show(v)} differs from {first_path.name}'s {_show(first)}")
    return first


def load_dataset(
    root: str | os.PathLike,
    *,
    downscale: float = 1.0,
    background=None,
    splits: Iterable[str] = SPLITS,
) -> Dataset:
    """Load and check a dataset folder; raise :class:`DataError` (one line naming file and value) on any problem.

    ``downscale`` in (0, 1] resizes images (``cv2.INTER_AREA``) and cameras alike. ``background`` ([r, g, b] in
    [0, 1]) overrides the JSON's ``background`` key, which overrides white (the D-NeRF convention). ``splits`` chooses
    which split files are read; the others stay empty, but ``transforms_train.json`` must always exist.
    """
    root = Path(root)
    wanted = tuple(splits)
    unknown = [s for s in wanted if s not in SPLITS]
    if unknown or not wanted:
        raise ValueError(f"splits must name some of {SPLITS}, got {wanted!r}")
    if isinstance(downscale, bool) or not isinstance(downscale, (int, float, np.floating, np.integer)):
        raise DataError(f"{root}: downscale = {_show(downscale)} must be a number in (0, 1]")
    downscale = float(downscale)
    if not (math.isfinite(downscale) and 0.0 < downscale <= 1.0):
        raise DataError(f"{root}: downscale = {downscale:g} must be in (0, 1]")
    bg_arg = None if background is None else _rgb(background, "background argument")
    if not root.exists():
        raise DataError(f"dataset folder not found: {root}")
    if not root.is_dir():
        raise DataError(f"{root}: not a folder (expected a dataset folder with transforms_train.json)")
    train_json = root / "transforms_train.json"
    if not train_json.is_file():
        raise DataError(f"{train_json}: not found (every dataset needs a train split)")

    sizes = _SizeCheck()
    loaded: dict[str, list[Frame]] = {s: [] for s in SPLITS}
    backgrounds: list[tuple[Path, np.ndarray]] = []
    fps_values: list[tuple[Path, float]] = []
    for split in SPLITS:
        json_path = root / f"transforms_{split}.json"
        if split not in wanted or not json_path.is_file():
            continue
        data, raw_frames = _read_split_json(json_path)
        if data.get("background") is not None:
            backgrounds.append((json_path, _rgb(data["background"], f"{json_path}: background")))
        if data.get("fps") is not None:
            fps = _number(data["fps"], f"{json_path}: fps")
            if fps <= 0:
                raise DataError(f"{json_path}: fps = {fps:g} must be positive")
            fps_values.append((json_path, fps))
        top = _intrinsics(data, f"{json_path}:")
        for i, raw in enumerate(raw_frames):
            loaded[split].append(_load_frame(split, i, raw, json_path, root, top, downscale, sizes))

    json_bg = _agreed(backgrounds, "background", lambda a, b: bool(np.allclose(a, b, atol=1e-6)))
    bg = bg_arg if bg_arg is not None else json_bg if json_bg is not None else _WHITE.copy()
    bg = np.asarray(bg, dtype=np.float32)
    bg.setflags(write=False)
    for frames in loaded.values():
        for f in frames:
            f.background = bg
    fps = _agreed(fps_values, "fps", lambda a, b: abs(a - b) <= 1e-9 * max(abs(a), abs(b)))

    points = colors = None
    ply_path = root / "points3d.ply"
    if ply_path.exists():
        points, colors = read_points_ply(ply_path)
    return Dataset(root=root, splits=loaded, background=bg, fps=fps, points=points, point_colors=colors)
