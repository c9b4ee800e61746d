"""Similarity transforms of a scene: x' = s R x + t (a rotation R, a positive scale s, a translation t).

Two parts of the program re-pose a scene by one:

- ``causalgs reframe`` writes a dataset re-posed in another world frame and scale (cameras, initial points and ground
  truth transformed; the images unchanged, since the same cameras see the same scene);
- a fit maps the data's world frame to its *physics frame* (z up, gravity 9.8 in its units), inferred from the video
  (:mod:`causalgs.model.upright`), because the simulator, the ground and the box are written for that frame.

How each kind of quantity transforms: positions ``s R x + t``; velocities and lengths along a direction ``s R v``;
angular velocities, normals and directions ``R w``; orientations (rotation matrices, wxyz quaternions) ``R Q``;
deformation gradients ``R F Rᵀ``; camera-to-world matrices keep their rigid form (``R`` on the rotation, the
centre as a position); accelerations like velocities.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

import numpy as np

from causalgs.errors import CausalGSError

__all__ = ["Similarity", "parse_rotation", "rotation_between"]

_ORTHO_TOL = 1e-6


@dataclass(frozen=True)
class Similarity:
    """x' = scale · R x + t. Build with :meth:`make`, which checks that R is a rotation and the scale positive."""

    R: np.ndarray  # [3, 3]
    scale: float
    t: np.ndarray  # [3]

    @classmethod
    def make(cls, R=None, scale: float = 1.0, t=None, what: str = "transform") -> Similarity:
        R = np.eye(3) if R is None else np.asarray(R, dtype=np.float64)
        t = np.zeros(3) if t is None else np.asarray(t, dtype=np.float64)
        if R.shape != (3, 3) or not np.all(np.isfinite(R)):
            raise CausalGSError(f"{what}: the rotation {R.tolist()} is not a finite 3x3 matrix")
        if np.abs(R @ R.T - np.eye(3)).max() > _ORTHO_TOL or np.linalg.det(R) < 0:
            raise CausalGSError(f"{what}: the matrix {np.round(R, 6).tolist()} is not a rotation (RRᵀ ≠ I or det ≠ 1)")
        if isinstance(scale, bool) or not isinstance(scale, (int, float, np.floating)) or not math.isfinite(scale) \
                or scale <= 0:  # fmt: skip
            raise CausalGSError(f"{what}: scale = {scale!r} must be a positive number")
        if t.shape != (3,) or not np.all(np.isfinite(t)):
            raise CausalGSError(f"{what}: translation = {t.tolist()} must be three finite numbers")
        R.setflags(write=False)
        t.setflags(write=False)
        return cls(R, float(scale), t)

    @classmethod
    def identity(cls) -> Similarity:
        return cls.make()

    @property
    def is_identity(self) -> bool:
        return bool(np.array_equal(self.R, np.eye(3)) and self.scale == 1.0 and not self.t.any())

    def matrix(self) -> np.ndarray:
        """The 4×4 homogeneous matrix [[sR, t], [0, 1]]."""
        m = np.eye(4)
        m[:3, :3] = self.scale * self.R
        m[:3, 3] = self.t
        return m

    def inverse(self) -> Similarity:
        return Similarity.make(self.R.T, 1.0 / self.scale, -(self.R.T @ self.t) / self.scale)

    def then(self, other: Similarity) -> Similarity:
        """``other`` after ``self``: x ↦ other(self(x))."""
        return Similarity.make(other.R @ self.R, other.scale * self.scale, other.scale * (other.R @ self.t) + other.t)

    # -- quantities ------------------------------------------------------------------------------------------------
    def points(self, x) -> np.ndarray:
        return self.scale * (np.asarray(x, dtype=np.float64) @ self.R.T) + self.t

    def vectors(self, v) -> np.ndarray:
        """Velocities, accelerations, displacements: s R v."""
        return self.scale * (np.asarray(v, dtype=np.float64) @ self.R.T)

    def directions(self, n) -> np.ndarray:
        """Angular velocities, normals, unit directions: R n."""
        return np.asarray(n, dtype=np.float64) @ self.R.T

    def orientations(self, Q) -> np.ndarray:
        """Rotation matrices [..., 3, 3] (body to world): R Q."""
        return self.R @ np.asarray(Q, dtype=np.float64)

    def deformations(self, F) -> np.ndarray:
        """Deformation gradients [..., 3, 3]: R F Rᵀ."""
        return self.R @ np.asarray(F, dtype=np.float64) @ self.R.T

    def quaternions(self, q) -> np.ndarray:
        """Orientations as wxyz quaternions [..., 4] (body to world), turned: q_R ⊗ q."""
        aw, ax, ay, az = self.quaternion()
        bw, bx, by, bz = np.moveaxis(np.asarray(q, dtype=np.float64), -1, 0)
        return np.stack([aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                         aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw], -1)  # fmt: skip

    def quaternion(self) -> np.ndarray:
        """R as a unit wxyz quaternion."""
        return _rotmat_quat(self.R)

    def camera_to_world(self, c2w) -> np.ndarray:
        """A rigid camera-to-world matrix [4, 4] re-posed: the rotation turned by R, the centre moved as a point."""
        c2w = np.asarray(c2w, dtype=np.float64)
        out = np.eye(4)
        out[:3, :3] = self.R @ c2w[:3, :3]
        out[:3, 3] = self.points(c2w[:3, 3])
        return out

    def plane(self, n, d: float) -> tuple[np.ndarray, float]:
        """The plane n·x = d re-posed: n' = R n / |n| and d' = s d / |n| + n'·t."""
        n = np.asarray(n, dtype=np.float64)
        norm = float(np.linalg.norm(n))
        n_unit = self.R @ (n / norm)
        return n_unit, float(self.scale * d / norm + n_unit @ self.t)

    # -- persistence -----------------------------------------------------------------------------------------------
    def to_json(self) -> dict:
        return {"rotation": self.R.tolist(), "scale": self.scale, "translation": self.t.tolist(),
                "matrix": self.matrix().tolist()}  # fmt: skip

    @classmethod
    def from_json(cls, d: dict, what: str = "transform") -> Similarity:
        try:
            return cls.make(d["rotation"], d["scale"], d["translation"], what)
        except (KeyError, TypeError, ValueError):
            raise CausalGSError(f"{what}: expected rotation, scale and translation, got {d!r}") from None


def _rotmat_quat(R: np.ndarray) -> np.ndarray:
    """wxyz quaternion of a rotation matrix (Shepperd's method, the largest diagonal term first)."""
    tr = np.trace(R)
    if tr > 0:
        s = 2.0 * math.sqrt(tr + 1.0)
        q = [0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    else:
        i = int(np.argmax(np.diag(R)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * math.sqrt(1.0 + R[i, i] - R[j, j] - R[k, k])
        q = [0.0] * 4
        q[0] = (R[k, j] - R[j, k]) / s
        q[1 + i] = 0.25 * s
        q[1 + j] = (R[j, i] + R[i, j]) / s
        q[1 + k] = (R[k, i] + R[i, k]) / s
    q = np.asarray(q)
    return q / np.linalg.norm(q) * (1.0 if q[0] >= 0 else -1.0)


def axis_angle(axis, angle: float) -> np.ndarray:
    """The rotation by ``angle`` radians about ``axis`` (Rodrigues)."""
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K


def rotation_between(a, b) -> np.ndarray:
    """The smallest rotation taking direction ``a`` to direction ``b`` (about a ⟂ b; a half turn about an axis
    perpendicular to both when they are opposite)."""
    a = np.asarray(a, dtype=np.float64) / np.linalg.norm(a)
    b = np.asarray(b, dtype=np.float64) / np.linalg.norm(b)
    c = float(np.clip(a @ b, -1.0, 1.0))
    axis = np.cross(a, b)
    if np.linalg.norm(axis) < 1e-12:
        if c > 0:
            return np.eye(3)
        perp = np.cross(a, [1.0, 0.0, 0.0] if abs(a[0]) < 0.9 else [0.0, 1.0, 0.0])
        return axis_angle(perp, math.pi)
    return axis_angle(axis, math.atan2(float(np.linalg.norm(axis)), c))


def random_rotation(seed: int) -> np.ndarray:
    """A rotation drawn uniformly (a normalised Gaussian quaternion)."""
    q = np.random.default_rng(seed).normal(size=4)
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])  # fmt: skip


_AXES = {"x": (1.0, 0.0, 0.0), "y": (0.0, 1.0, 0.0), "z": (0.0, 0.0, 1.0)}
_NUMBER = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"


def parse_rotation(text: str, seed: int = 0) -> np.ndarray:
    """``AXIS:DEG`` (AXIS ``x``, ``y``, ``z`` or three numbers ``a,b,c``), ``random`` (seeded), or nine numbers
    (a row-major matrix, checked to be a rotation by :meth:`Similarity.make`)."""
    s = str(text).strip().lower()
    if s == "random":
        return random_rotation(seed)
    m = re.fullmatch(rf"(x|y|z|{_NUMBER},{_NUMBER},{_NUMBER}):({_NUMBER})", s.replace(" ", ""))
    if m:
        axis = _AXES.get(m.group(1)) or tuple(float(v) for v in m.group(1).split(","))
        if not np.linalg.norm(axis) > 0:
            raise CausalGSError(f"--rotate {text!r}: the axis must not be zero")
        return axis_angle(axis, math.radians(float(m.group(2))))
    parts = s.replace(" ", "").split(",")
    if len(parts) == 9:
        try:
            return np.asarray([float(p) for p in parts]).reshape(3, 3)
        except ValueError:
            pass
    raise CausalGSError(f"--rotate {text!r}: expected AXIS:DEG (AXIS x, y, z or a,b,c), 'random' or nine numbers")
