"""Pinhole cameras.

Conventions (the same as gsplat and COLMAP):
- ``K`` is the 3×3 intrinsic matrix ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`` in pixels; the continuous image plane has
  its origin at the top-left *corner* of the top-left pixel, so pixel ``(row i, column j)`` has its centre at
  ``(u, v) = (j + 0.5, i + 0.5)``.
- ``viewmat`` is the 4×4 world-to-camera transform in the OpenCV frame: x right, y down, z forward (depth > 0 in
  front of the camera).
- Blender-style datasets (D-NeRF, NVFi, FreeGave) store camera-to-world matrices in the OpenGL frame: x right, y up,
  z backward. :func:`opengl_to_opencv` converts them by flipping the camera's y and z axes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from causalgs.errors import DataError

# Camera-frame axis flip between OpenGL (y up, z back) and OpenCV (y down, z forward); its own inverse.
_GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])


def fov_to_focal(fov: float, size: float) -> float:
    """Focal length in pixels for a full field of view ``fov`` (radians) across ``size`` pixels."""
    return 0.5 * size / math.tan(0.5 * fov)


def focal_to_fov(focal: float, size: float) -> float:
    """Full field of view (radians) across ``size`` pixels for a focal length in pixels."""
    return 2.0 * math.atan(0.5 * size / focal)


def opengl_to_opencv(c2w: np.ndarray) -> np.ndarray:
    """Convert a camera-to-world matrix [4, 4] from the OpenGL camera frame to the OpenCV one (and back)."""
    return np.asarray(c2w, dtype=np.float64) @ _GL_TO_CV


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """OpenGL camera-to-world matrix [4, 4] of a camera at ``eye`` looking at ``target`` (Blender's convention)."""
    eye = np.asarray(eye, dtype=np.float64)
    back = eye - np.asarray(target, dtype=np.float64)
    back /= np.linalg.norm(back)
    right = np.cross(np.asarray(up, dtype=np.float64), back)
    if np.linalg.norm(right) < 1e-9:
        raise ValueError("look_at: the up vector is parallel to the viewing direction")
    right /= np.linalg.norm(right)
    cam_up = np.cross(back, right)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, cam_up, back, eye
    return c2w


def check_rigid(matrix, what: str, tol: float = 1e-3) -> np.ndarray:
    """Return ``matrix`` as a float64 [4, 4] array if it is a finite rigid transform, else raise :class:`DataError`.

    ``what`` names the matrix in the message (e.g. ``"transforms_train.json: frame 3 transform_matrix"``). The
    tolerance is loose because datasets store matrices printed with a few digits.
    """
    try:
        m = np.asarray(matrix, dtype=np.float64)
    except (TypeError, ValueError):
        raise DataError(f"{what} is not a 4x4 matrix of numbers") from None
    if m.shape != (4, 4):
        raise DataError(f"{what} has shape {list(m.shape)}, expected a 4x4 matrix")
    if not np.all(np.isfinite(m)):
        raise DataError(f"{what} has non-finite values")
    if np.abs(m[3] - [0.0, 0.0, 0.0, 1.0]).max() > tol:
        raise DataError(f"{what} is not rigid: last row is {m[3].tolist()}, expected [0, 0, 0, 1]")
    r = m[:3, :3]
    ortho = np.abs(r.T @ r - np.eye(3)).max()
    if ortho > tol:
        raise DataError(f"{what} is not rigid: rotation part is not orthonormal (max |RᵀR − I| = {ortho:.3g})")
    if np.linalg.det(r) < 0:
        raise DataError(f"{what} is not rigid: rotation part is a reflection (det < 0)")
    return m


@dataclass(frozen=True)
class Camera:
    """A pinhole camera: intrinsics ``K`` [3, 3], world-to-camera ``viewmat`` [4, 4] (OpenCV frame), image size."""

    K: np.ndarray
    viewmat: np.ndarray
    width: int
    height: int

    def __post_init__(self):
        object.__setattr__(self, "K", np.asarray(self.K, dtype=np.float64).reshape(3, 3))
        object.__setattr__(self, "viewmat", np.asarray(self.viewmat, dtype=np.float64).reshape(4, 4))
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))

    # -- construction -------------------------------------------------------------------------------------------
    @classmethod
    def from_intrinsics(cls, fx, fy, cx, cy, width, height, c2w_opencv) -> Camera:
        K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        return cls(K, np.linalg.inv(np.asarray(c2w_opencv, dtype=np.float64)), width, height)

    @classmethod
    def from_blender(
        cls, c2w_opengl, width: int, height: int, *, fov_x: float | None = None, fl_x=None, fl_y=None, cx=None, cy=None
    ) -> Camera:
        """A camera from a Blender-style OpenGL camera-to-world matrix and either ``fov_x`` or ``fl_x``.

        Missing values follow the datasets' conventions: ``fl_y = fl_x`` (square pixels), principal point at the
        image centre.
        """
        if fl_x is None:
            if fov_x is None:
                raise ValueError("from_blender needs fov_x or fl_x")
            fl_x = fov_to_focal(fov_x, width)
        fl_y = fl_x if fl_y is None else fl_y
        cx = 0.5 * width if cx is None else cx
        cy = 0.5 * height if cy is None else cy
        return cls.from_intrinsics(fl_x, fl_y, cx, cy, width, height, opengl_to_opencv(c2w_opengl))

    # -- properties ---------------------------------------------------------------------------------------------
    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        return float(self.K[1, 2])

    @property
    def fov_x(self) -> float:
        return focal_to_fov(self.fx, self.width)

    @property
    def c2w(self) -> np.ndarray:
        """Camera-to-world [4, 4] in the OpenCV camera frame."""
        return np.linalg.inv(self.viewmat)

    @property
    def c2w_opengl(self) -> np.ndarray:
        """Camera-to-world [4, 4] in the OpenGL (Blender) camera frame, as datasets store it."""
        return opengl_to_opencv(self.c2w)

    @property
    def center(self) -> np.ndarray:
        """Camera centre in world coordinates [3]."""
        return self.c2w[:3, 3]

    # -- geometry -----------------------------------------------------------------------------------------------
    def world_to_camera(self, points: np.ndarray) -> np.ndarray:
        """Points [..., 3] in world coordinates to the OpenCV camera frame [..., 3]."""
        p = np.asarray(points, dtype=np.float64)
        return p @ self.viewmat[:3, :3].T + self.viewmat[:3, 3]

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project world points [..., 3] to pixel coordinates ``uv`` [..., 2] and depths [...].

        ``uv`` uses the corner-origin convention (pixel centres at +0.5). Points at or behind the camera plane get
        non-finite ``uv``; check ``depth > 0``.
        """
        pc = self.world_to_camera(points)
        z = pc[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = self.fx * pc[..., 0] / z + self.cx
            v = self.fy * pc[..., 1] / z + self.cy
        uv = np.stack([u, v], axis=-1)
        uv[z <= 0] = np.nan
        return uv, z

    def pixel_centers(self) -> np.ndarray:
        """Continuous coordinates ``(u, v)`` [H, W, 2] of every pixel centre."""
        u, v = np.meshgrid(np.arange(self.width) + 0.5, np.arange(self.height) + 0.5)
        return np.stack([u, v], axis=-1)

    def rays(self, uv: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """World-space ray origins and unit directions through pixel positions ``uv`` [..., 2].

        Without ``uv``, the rays through every pixel centre, shaped [H, W, 3].
        """
        uv = self.pixel_centers() if uv is None else np.asarray(uv, dtype=np.float64)
        d_cam = np.stack(
            [(uv[..., 0] - self.cx) / self.fx, (uv[..., 1] - self.cy) / self.fy, np.ones(uv.shape[:-1])], axis=-1
        )
        c2w = self.c2w
        d = d_cam @ c2w[:3, :3].T
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        o = np.broadcast_to(c2w[:3, 3], d.shape).copy()
        return o, d

    def scaled(self, factor: float) -> Camera:
        """The same camera for an image resized by ``factor`` (sizes rounded; K scaled by the exact size ratios)."""
        w = max(1, round(self.width * factor))
        h = max(1, round(self.height * factor))
        sx, sy = w / self.width, h / self.height
        K = self.K.copy()
        K[0] *= sx
        K[1] *= sy
        return Camera(K, self.viewmat, w, h)

    # -- JSON form ----------------------------------------------------------------------------------------------
    def to_json(self) -> dict:
        """The dataset's camera form: ``camera_angle_x``, ``w``, ``h``, intrinsics, OpenGL ``transform_matrix``."""
        return {
            "camera_angle_x": self.fov_x,
            "w": self.width,
            "h": self.height,
            "fl_x": self.fx,
            "fl_y": self.fy,
            "cx": self.cx,
            "cy": self.cy,
            "transform_matrix": self.c2w_opengl.tolist(),
        }

    @classmethod
    def from_json(cls, d: dict, what: str = "camera") -> Camera:
        """Inverse of :meth:`to_json`; needs ``w``, ``h``, ``transform_matrix`` and ``camera_angle_x`` or ``fl_x``."""
        for key in ("w", "h", "transform_matrix"):
            if key not in d:
                raise DataError(f"{what}: missing key '{key}'")
        if "camera_angle_x" not in d and "fl_x" not in d:
            raise DataError(f"{what}: missing key 'camera_angle_x' (or 'fl_x')")
        c2w = check_rigid(d["transform_matrix"], f"{what}: transform_matrix")
        try:
            w, h = int(d["w"]), int(d["h"])
            intr = {k: float(d[k]) for k in ("camera_angle_x", "fl_x", "fl_y", "cx", "cy") if k in d}
        except (TypeError, ValueError):
            raise DataError(f"{what}: w, h and intrinsics must be numbers") from None
        if w <= 0 or h <= 0:
            raise DataError(f"{what}: image size {w}x{h} must be positive")
        bad = [k for k, val in intr.items() if not math.isfinite(val) or val <= 0]
        if bad:
            raise DataError(f"{what}: {bad[0]} = {intr[bad[0]]} must be a positive finite number")
        fov = intr.get("camera_angle_x")
        if fov is not None and fov >= math.pi:
            raise DataError(f"{what}: camera_angle_x = {fov} must be below pi radians")
        return cls.from_blender(
            c2w, w, h, fov_x=fov, fl_x=intr.get("fl_x"), fl_y=intr.get("fl_y"), cx=intr.get("cx"), cy=intr.get("cy")
        )


def ring_direction(i: int, views: int, elevations_deg) -> np.ndarray:
    """Unit direction of camera ``i`` of ``views`` on a ring around +z: evenly spaced azimuths, elevations taken in
    turn from ``elevations_deg``."""
    az = 2.0 * math.pi * i / views
    el = math.radians(elevations_deg[i % len(elevations_deg)])
    return np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])


def fit_ring_distance(points, directions, target, fov_x: float, fill: float = 0.9, radii=None,
                      start: float = 0.1, iters: int = 40) -> float:  # fmt: skip
    """The smallest distance d at which cameras at ``target + d * directions[i]``, looking at ``target`` (square
    images, horizontal field of view ``fov_x``), all see every point — a sphere of radius ``radii[j]`` (default 0) —
    inside ``fill`` of the image. Bisection from ``start``: the fit is monotone in d because every camera looks at
    the target."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    rad = np.zeros(len(pts)) if radii is None else np.asarray(radii, dtype=np.float64)
    target = np.asarray(target, dtype=np.float64)
    tan_a = fill * math.tan(fov_x / 2.0)
    norm = math.sqrt(1.0 + tan_a * tan_a)

    def fits(dist: float) -> bool:
        for direction in directions:
            c2w = look_at(target + dist * np.asarray(direction), target)
            rel = pts - c2w[:3, 3]
            x, y, z = rel @ c2w[:3, 0], rel @ c2w[:3, 1], -(rel @ c2w[:3, 2])  # depth along the view
            # Distance to the four frustum side planes |x| = z tan_a, |y| = z tan_a must exceed the radius.
            if np.any((z * tan_a - np.maximum(np.abs(x), np.abs(y))) / norm < rad):
                return False
        return True

    lo, hi = start, 2.0 * start
    while not fits(hi):
        lo, hi = hi, 2.0 * hi
    for _ in range(iters):
        mid = 0.5 * (lo + hi)
        lo, hi = (lo, mid) if fits(mid) else (mid, hi)
    return hi
