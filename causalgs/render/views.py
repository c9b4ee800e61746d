"""Rendering Gaussians from cameras for people: still images, orbit cameras and turntable videos.

- :func:`render_camera` renders a dict of raw Gaussian parameters (the form :func:`causalgs.ply.read_gaussians_ply`
  returns) from a :class:`~causalgs.cameras.Camera` to an 8-bit RGB image, with no autograd graph.
- :func:`orbit_cameras` puts ``n`` cameras on the horizontal circle (up = +z) through a camera's position around a
  centre, keeping its distance, elevation and intrinsics; :func:`orbit_center` chooses that centre.
- :func:`render_turntable` renders an orbit and writes it as an MP4 (OpenCV, fourcc ``mp4v``), atomically.
- :func:`load_camera_json` reads a camera file in the dataset's camera form.

Taichi must be initialised (``causalgs._ti.init``) before rendering; these helpers never initialise it, so that a
library caller's fields are never invalidated by a reset.
"""

from __future__ import annotations

import contextlib
import math
import os
import tempfile
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path

import numpy as np
import torch

from causalgs import _ti
from causalgs.cameras import Camera, look_at, opengl_to_opencv
from causalgs.errors import CausalGSError, DataError
from causalgs.io import read_json
from causalgs.progress import progress_bar

__all__ = [
    "ORBIT_CENTERS",
    "load_camera_json",
    "orbit_cameras",
    "orbit_center",
    "render_camera",
    "render_turntable",
    "to_uint8",
    "write_video",
]

GAUSSIAN_KEYS = ("means", "quats", "scales", "opacities", "sh")
ORBIT_CENTERS = ("lookat", "centroid")


# ---------------------------------------------------------------------------------------------------------------------
# Cameras
# ---------------------------------------------------------------------------------------------------------------------
def load_camera_json(path: str | os.PathLike) -> tuple[Camera, tuple[float, float, float] | None]:
    """A camera file in the dataset's camera form, and its optional ``background``.

    The file is a JSON object with ``w``, ``h``, ``camera_angle_x`` (or ``fl_x`` and optionally ``fl_y``, ``cx``,
    ``cy``), an OpenGL camera-to-world ``transform_matrix`` and optionally ``background`` (three numbers in [0, 1]);
    :meth:`Camera.to_json` writes this form. Problems are one-line :class:`DataError`\\ s naming the file.
    """
    path = Path(path)
    data = read_json(path, what="camera file")
    if not isinstance(data, dict):
        raise DataError(f"{path}: the top level must be a JSON object, got {type(data).__name__}")
    camera = Camera.from_json(data, what=str(path))
    bg = data.get("background")
    if bg is None:
        return camera, None
    ok = isinstance(bg, list) and len(bg) == 3
    ok = ok and all(isinstance(v, (int, float)) and not isinstance(v, bool) and 0.0 <= v <= 1.0 for v in bg)
    if not ok:
        raise DataError(f"{path}: background = {bg!r} must be three numbers in [0, 1]")
    return camera, (float(bg[0]), float(bg[1]), float(bg[2]))


def orbit_center(camera: Camera, means, mode: str = "lookat") -> np.ndarray:
    """The centre a turntable orbits around [3].

    ``"centroid"``: the mean of the Gaussians' centres. ``"lookat"``: the point of the camera's viewing axis nearest
    that centroid (so the first orbit frame looks where the camera looks); the centroid itself when it lies behind
    the camera. Without Gaussians both fall back to the origin (projected on the viewing axis for ``"lookat"``).
    """
    if mode not in ORBIT_CENTERS:
        raise CausalGSError(f"orbit centre '{mode}' is not one of {', '.join(ORBIT_CENTERS)}")
    pts = np.asarray(means, dtype=np.float64).reshape(-1, 3)
    centroid = pts.mean(axis=0) if len(pts) else np.zeros(3)
    if mode == "centroid":
        return centroid
    eye = camera.center
    forward = camera.c2w[:3, 2]  # OpenCV: +z looks forward
    t = float(np.dot(centroid - eye, forward))
    return eye + t * forward if t > 1e-9 else centroid


def orbit_cameras(camera: Camera, center, n: int, up=(0.0, 0.0, 1.0)) -> list[Camera]:
    """``n`` cameras evenly spaced on one turn around the vertical axis (``up``) through ``center``.

    Every camera keeps ``camera``'s intrinsics, image size, distance to ``center`` and elevation, and looks at
    ``center`` with ``up`` pointing up in the image (no roll). The first camera sits where ``camera`` is; the others
    follow counter-clockwise seen from above. Raises :class:`CausalGSError` when the camera is at the centre or on
    the vertical axis through it (no circle to orbit on).
    """
    n = int(n)
    if n < 1:
        raise CausalGSError(f"an orbit needs at least 1 camera, got {n}")
    c = np.asarray(center, dtype=np.float64).reshape(3)
    z = np.asarray(up, dtype=np.float64).reshape(3)
    if not (np.all(np.isfinite(c)) and np.all(np.isfinite(z))) or np.linalg.norm(z) < 1e-12:
        raise CausalGSError("orbit centre and up vector must be finite (and up non-zero)")
    z = z / np.linalg.norm(z)
    offset = camera.center - c
    dist = float(np.linalg.norm(offset))
    height = float(np.dot(offset, z))
    radial = offset - height * z
    radius = float(np.linalg.norm(radial))
    if dist < 1e-9 or radius < 1e-6 * dist:
        raise CausalGSError(
            "cannot orbit: the camera is at the orbit centre or straight above/below it (distance "
            f"{dist:.4g}, horizontal radius {radius:.3g})"
        )
    x = radial / radius
    y = np.cross(z, x)
    cams = []
    for k in range(n):
        a = 2.0 * math.pi * k / n
        eye = c + radius * (math.cos(a) * x + math.sin(a) * y) + height * z
        c2w_cv = opengl_to_opencv(look_at(eye, c, up=z))
        cams.append(Camera(camera.K, np.linalg.inv(c2w_cv), camera.width, camera.height))
    return cams


# ---------------------------------------------------------------------------------------------------------------------
# Rendering
# ---------------------------------------------------------------------------------------------------------------------
def to_uint8(image) -> np.ndarray:
    """A float image in [0, 1] (numpy or torch) to uint8, clipped and rounded to the nearest level."""
    if isinstance(image, torch.Tensor):
        image = image.detach().cpu().numpy()
    img = np.nan_to_num(np.asarray(image, dtype=np.float64), nan=0.0)
    return np.rint(np.clip(img, 0.0, 1.0) * 255.0).astype(np.uint8)


def _tensors(gaussians: dict) -> dict[str, torch.Tensor]:
    missing = [k for k in GAUSSIAN_KEYS if k not in gaussians]
    if missing:
        raise CausalGSError(f"Gaussians need {', '.join(GAUSSIAN_KEYS)}; missing {', '.join(missing)}")
    dt = _ti.torch_dtype()
    out = {}
    for k in GAUSSIAN_KEYS:
        v = gaussians[k]
        out[k] = (v.detach() if isinstance(v, torch.Tensor) else torch.as_tensor(np.asarray(v))).to(dt)
    return out


def render_camera(
    gaussians: dict,
    camera: Camera,
    background=(1.0, 1.0, 1.0),
    *,
    sh_degree: int | None = None,
) -> np.ndarray:
    """Render raw Gaussian parameters (``means``, ``quats``, ``scales``, ``opacities``, ``sh`` as in
    :func:`causalgs.render.rasterize`; numpy or torch) from ``camera``: uint8 RGB [H, W, 3].

    Runs :func:`~causalgs.render.rasterize` under ``torch.no_grad()`` in the precision of the current Taichi runtime
    (which must be initialised).
    """
    from causalgs.render.rasterizer import rasterize

    _ti.runtime()  # a one-line error if Taichi is not initialised
    g = _tensors(gaussians)
    with torch.no_grad():
        image, _, _ = rasterize(
            g["means"], g["quats"], g["scales"], g["opacities"], g["sh"], torch.from_numpy(camera.viewmat),
            torch.from_numpy(camera.K), camera.width, camera.height, background=tuple(background), sh_degree=sh_degree,
        )  # fmt: skip
    return to_uint8(image)


def write_video(path: str | os.PathLike, frames: Iterable[np.ndarray], fps: float = 24.0) -> int:
    """Write uint8 RGB frames [H, W, 3] (all one size) as an MP4 (fourcc ``mp4v``), atomically; returns the count.

    The video is written to a temporary ``.mp4`` beside ``path`` and moved into place when complete. Odd sizes are
    padded by one row/column (repeating the edge), because MPEG-4 encoders need even sizes.
    """
    import cv2

    path = Path(path)
    if not (math.isfinite(fps) and fps > 0):
        raise CausalGSError(f"fps = {fps} must be a positive number")
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=".mp4", dir=path.parent)
    os.close(fd)
    writer = None
    count = 0
    try:
        size = None
        for frame in frames:
            img = np.asarray(frame)
            if img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] != 3:
                raise CausalGSError(f"video frames must be uint8 [H, W, 3], got {img.dtype} {list(img.shape)}")
            if size is None:
                size = img.shape[:2]
                h2, w2 = size[0] + size[0] % 2, size[1] + size[1] % 2
                writer = cv2.VideoWriter(tmp, cv2.VideoWriter_fourcc(*"mp4v"), float(fps), (w2, h2))
                if not writer.isOpened():
                    raise CausalGSError(f"{path}: OpenCV cannot open an MP4 writer (fourcc mp4v)")
            elif img.shape[:2] != size:
                raise CausalGSError(f"video frame {count} is {list(img.shape[:2])}, the first was {list(size)}")
            pad = ((0, size[0] % 2), (0, size[1] % 2), (0, 0))
            writer.write(np.ascontiguousarray(np.pad(img, pad, mode="edge")[..., ::-1]))
            count += 1
        if writer is None:
            raise CausalGSError(f"{path}: no frames to write")
        writer.release()
        writer = None
        os.replace(tmp, path)
    except BaseException:
        if writer is not None:
            writer.release()
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
    return count


def _progress(enabled: bool):
    return progress_bar(enabled)


def render_turntable(
    gaussians: dict,
    camera: Camera,
    n: int,
    path: str | os.PathLike,
    *,
    background=(1.0, 1.0, 1.0),
    fps: float = 24.0,
    center: str | Sequence[float] = "lookat",
    progress: bool | Callable[[int, int], None] = True,
    sh_degree: int | None = None,
) -> list[Camera]:
    """Render ``n`` frames orbiting ``camera`` around ``center`` and write them to the MP4 ``path``.

    ``center`` is a point [3] or a mode of :func:`orbit_center` (``"lookat"`` or ``"centroid"``). ``progress`` is a
    flag for a rich progress bar on stderr, or a callback ``(done, total)``. Returns the cameras of the frames.
    """
    if isinstance(center, str):
        center = orbit_center(camera, gaussians["means"], center)
    cams = orbit_cameras(camera, center, n)
    g = _tensors(gaussians)  # convert once
    callback = progress if callable(progress) else None

    def frames(bar=None, task=None):
        for i, cam in enumerate(cams):
            yield render_camera(g, cam, background, sh_degree=sh_degree)
            if bar is not None:
                bar.advance(task)
            if callback is not None:
                callback(i + 1, len(cams))

    if callback is not None or not progress:
        write_video(path, frames(), fps)
    else:
        with _progress(True) as bar:
            task = bar.add_task("turntable", total=len(cams))
            write_video(path, frames(bar, task), fps)
    return cams
