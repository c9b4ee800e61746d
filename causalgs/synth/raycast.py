"""Analytic ray casting of simple primitives, vectorised in numpy.

Synthetic scenes are rendered here and never by the model's own rasterizer, so that a bug shared by the renderer
and the model cannot cancel out (no inverse crime). Rays are intersected exactly with spheres, oriented boxes (slab
method in the box's local frame) and capped cylinders; a rigid body is a list of primitives in its own body frame and
is cast by moving the rays into that frame, so the hit point comes back in body coordinates (where solid textures
live) and the normal comes back in world coordinates (where the light is).

Conventions: origins and directions are float64 ``[..., 3]`` (directions need not be unit, ``t`` is in units of the
direction's length); a miss has ``t = inf``, ``part = -1`` and ``obj = 0``. Only hits with ``t > EPS`` count, so a
ray never hits the surface it starts on.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import numpy as np

EPS = 1e-9

__all__ = ["EPS", "Box", "Cylinder", "Hit", "RigidBody", "Sphere", "cast", "rotation_exp", "sphere_hits"]


def _as_rot(rotation) -> np.ndarray:
    return np.eye(3) if rotation is None else np.asarray(rotation, dtype=np.float64).reshape(3, 3)


def rotation_exp(omega) -> np.ndarray:
    """Rotation matrix exp(ω̂) for a rotation vector ``omega`` [3] (Rodrigues); the gt motion law uses it."""
    w = np.asarray(omega, dtype=np.float64)
    theta = float(np.linalg.norm(w))
    if theta < 1e-12:
        return np.eye(3)
    k = w / theta
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(theta) * kx + (1.0 - np.cos(theta)) * (kx @ kx)


def _quiet(fn):
    """Silence the overflow warnings of near-parallel rays (their ±huge slab distances are handled as misses)."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            return fn(*args, **kwargs)

    return wrapper


def _first_positive(t0: np.ndarray, t1: np.ndarray) -> np.ndarray:
    """The smaller of two root arrays that is > EPS (``t0 <= t1``), else inf."""
    return np.where(t0 > EPS, t0, np.where(t1 > EPS, t1, np.inf))


def sphere_hits(o, d, center, radius) -> np.ndarray:
    """Nearest hit distance of rays with a sphere (inf on a miss); also the bounding-sphere cull test."""
    oc = o - np.asarray(center, dtype=np.float64)
    a = np.einsum("...i,...i->...", d, d)
    b = np.einsum("...i,...i->...", oc, d)
    c = np.einsum("...i,...i->...", oc, oc) - radius * radius
    disc = b * b - a * c
    hit = disc >= 0.0
    sq = np.sqrt(np.where(hit, disc, 0.0))
    t = _first_positive((-b - sq) / a, (-b + sq) / a)
    return np.where(hit, t, np.inf)


@dataclass(frozen=True)
class Sphere:
    """A sphere of ``radius`` at ``center``; ``part`` indexes the scene's material/colour table."""

    center: tuple
    radius: float
    part: int = 0

    @_quiet
    def intersect(self, o, d):
        t = sphere_hits(o, d, self.center, self.radius)
        p = o + np.where(np.isfinite(t), t, 0.0)[..., None] * d
        return t, (p - np.asarray(self.center)) / self.radius

    def contains(self, p, tol: float = 1e-6) -> np.ndarray:
        return np.linalg.norm(p - np.asarray(self.center), axis=-1) < self.radius - tol

    def bsphere(self) -> tuple[np.ndarray, float]:
        """Centre and radius of a sphere enclosing the primitive (the cull test before the exact one)."""
        return np.asarray(self.center, dtype=np.float64), float(self.radius)

    def area(self) -> float:
        return 4.0 * np.pi * self.radius**2

    def bound(self) -> float:
        """Radius about the frame origin of a sphere enclosing the primitive."""
        return float(np.linalg.norm(self.center)) + self.radius

    def sample(self, rng: np.random.Generator, n: int):
        nrm = rng.normal(size=(n, 3))
        nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
        return np.asarray(self.center) + self.radius * nrm, nrm


@dataclass(frozen=True)
class _Local:
    """Shared frame handling of primitives with an orientation: columns of ``rotation`` are the local axes."""

    def _to_local(self, o, d):
        r = _as_rot(self.rotation)
        return (o - np.asarray(self.center)) @ r, d @ r

    def _from_local(self, p_local, n_local):
        r = _as_rot(self.rotation)
        return p_local @ r.T + np.asarray(self.center), n_local @ r.T


@dataclass(frozen=True)
class Box(_Local):
    """An oriented box: ``half`` extents along the local axes (columns of ``rotation``) about ``center``."""

    center: tuple
    half: tuple
    rotation: np.ndarray | None = None
    part: int = 0

    @_quiet
    def intersect(self, o, d):
        ol, dl = self._to_local(o, d)
        h = np.asarray(self.half, dtype=np.float64)
        # Per-axis slabs, written component by component: numpy reductions over a length-3 axis are slow.
        tmin, tmax = np.full(dl.shape[:-1], -np.inf), np.full(dl.shape[:-1], np.inf)
        axis = np.zeros(dl.shape[:-1], dtype=np.int64)
        for i in range(3):
            # A zero direction component would give 0/0; a tiny same-signed stand-in gives ±huge slabs instead.
            di = dl[..., i]
            inv = 1.0 / np.where(np.abs(di) < 1e-300, 1e-300, di)
            t1, t2 = (-h[i] - ol[..., i]) * inv, (h[i] - ol[..., i]) * inv
            lo = np.minimum(t1, t2)
            later = lo > tmin
            axis = np.where(later, i, axis)
            tmin = np.where(later, lo, tmin)
            tmax = np.minimum(tmax, np.maximum(t1, t2))
        hit = tmax >= np.maximum(tmin, EPS)
        t = np.where(hit, np.where(tmin > EPS, tmin, tmax), np.inf)
        # Entering through the face of the slab that was crossed last: normal against the ray on that axis.
        sign = -np.sign(np.take_along_axis(dl, axis[..., None], axis=-1))
        n = np.where(np.arange(3) == axis[..., None], sign, 0.0)
        return t, n @ _as_rot(self.rotation).T

    def bsphere(self) -> tuple[np.ndarray, float]:
        return np.asarray(self.center, dtype=np.float64), float(np.linalg.norm(self.half))

    def contains(self, p, tol: float = 1e-6) -> np.ndarray:
        pl = (p - np.asarray(self.center)) @ _as_rot(self.rotation)
        return np.all(np.abs(pl) < np.asarray(self.half) - tol, axis=-1)

    def area(self) -> float:
        x, y, z = self.half
        return 8.0 * (x * y + y * z + z * x)

    def bound(self) -> float:
        signs = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=np.float64)
        corners = (signs * np.asarray(self.half)) @ _as_rot(self.rotation).T + np.asarray(self.center)
        return float(np.linalg.norm(corners, axis=1).max())

    def sample(self, rng: np.random.Generator, n: int):
        h = np.asarray(self.half, dtype=np.float64)
        face_areas = np.array([h[1] * h[2], h[0] * h[2], h[0] * h[1]] * 2)
        face = rng.choice(6, size=n, p=face_areas / face_areas.sum())
        axis, sign = face % 3, np.where(face < 3, 1.0, -1.0)
        p = rng.uniform(-1.0, 1.0, size=(n, 3)) * h
        p[np.arange(n), axis] = sign * h[axis]
        nrm = np.zeros((n, 3))
        nrm[np.arange(n), axis] = sign
        return self._from_local(p, nrm)


@dataclass(frozen=True)
class Cylinder(_Local):
    """A capped cylinder of ``radius`` along its local z axis (third column of ``rotation``), ±``half_height``."""

    center: tuple
    radius: float
    half_height: float
    rotation: np.ndarray | None = None
    part: int = 0

    @_quiet
    def intersect(self, o, d):
        ol, dl = self._to_local(o, d)
        r, hh = self.radius, self.half_height
        # Side: |(x, y)| = r with |z| <= hh.
        a = dl[..., 0] ** 2 + dl[..., 1] ** 2
        b = ol[..., 0] * dl[..., 0] + ol[..., 1] * dl[..., 1]
        c = ol[..., 0] ** 2 + ol[..., 1] ** 2 - r * r
        disc = b * b - a * c
        ok = (disc >= 0.0) & (a > 1e-300)
        sq = np.sqrt(np.where(ok, disc, 0.0))
        a_safe = np.where(a > 1e-300, a, 1.0)
        ts = []
        for t_side in ((-b - sq) / a_safe, (-b + sq) / a_safe):
            z = ol[..., 2] + t_side * dl[..., 2]
            ts.append(np.where(ok & (np.abs(z) <= hh) & (t_side > EPS), t_side, np.inf))
        # Caps: z = ±hh with |(x, y)| <= r.
        dz = np.where(np.abs(dl[..., 2]) < 1e-300, 1e-300, dl[..., 2])
        for zc in (-hh, hh):
            t_cap = (zc - ol[..., 2]) / dz
            x, y = ol[..., 0] + t_cap * dl[..., 0], ol[..., 1] + t_cap * dl[..., 1]
            ts.append(np.where((x * x + y * y <= r * r) & (t_cap > EPS), t_cap, np.inf))
        cand = np.stack(ts, axis=-1)
        which = np.argmin(cand, axis=-1)
        t = np.take_along_axis(cand, which[..., None], axis=-1)[..., 0]
        p = ol + np.where(np.isfinite(t), t, 0.0)[..., None] * dl
        side = np.stack([p[..., 0] / r, p[..., 1] / r, np.zeros_like(t)], axis=-1)
        cap = np.zeros_like(p)
        cap[..., 2] = np.where(which == 2, -1.0, 1.0)
        n = np.where((which < 2)[..., None], side, cap)
        return t, n @ _as_rot(self.rotation).T

    def contains(self, p, tol: float = 1e-6) -> np.ndarray:
        pl = (p - np.asarray(self.center)) @ _as_rot(self.rotation)
        return (np.hypot(pl[..., 0], pl[..., 1]) < self.radius - tol) & (np.abs(pl[..., 2]) < self.half_height - tol)

    def area(self) -> float:
        return 2.0 * np.pi * self.radius * (self.radius + 2.0 * self.half_height)

    def bound(self) -> float:
        return float(np.linalg.norm(self.center) + np.hypot(self.radius, self.half_height))

    def bsphere(self) -> tuple[np.ndarray, float]:
        return np.asarray(self.center, dtype=np.float64), float(np.hypot(self.radius, self.half_height))

    def sample(self, rng: np.random.Generator, n: int):
        r, hh = self.radius, self.half_height
        side_area, cap_area = 4.0 * np.pi * r * hh, np.pi * r * r
        kind = rng.choice(3, size=n, p=np.array([side_area, cap_area, cap_area]) / (side_area + 2 * cap_area))
        phi = rng.uniform(0.0, 2.0 * np.pi, size=n)
        rad = np.where(kind == 0, r, r * np.sqrt(rng.uniform(size=n)))
        z = np.where(kind == 0, rng.uniform(-hh, hh, size=n), np.where(kind == 1, hh, -hh))
        p = np.stack([rad * np.cos(phi), rad * np.sin(phi), z], axis=1)
        nrm = np.stack([np.cos(phi), np.sin(phi), np.zeros(n)], axis=1)
        nrm[kind == 1] = (0.0, 0.0, 1.0)
        nrm[kind == 2] = (0.0, 0.0, -1.0)
        return self._from_local(p, nrm)


Primitive = Sphere | Box | Cylinder


@dataclass
class Hit:
    """Nearest hits of a batch of rays: distance, unit normal, hit point, primitive ``part`` and object id."""

    t: np.ndarray
    normal: np.ndarray
    point: np.ndarray
    part: np.ndarray
    obj: np.ndarray

    @property
    def mask(self) -> np.ndarray:
        return np.isfinite(self.t)


def _reaching(o, d, dd, center, radius) -> np.ndarray:
    """Indices of rays that reach the sphere (``center``, ``radius``): the cheap test before an exact one.

    ``o`` is one shared origin [3] or [N, 3]; ``dd`` holds the squared lengths of the directions ``d`` [N, 3].
    """
    oc = o - center
    radius = radius * (1.0 + 1e-9) + 1e-12  # never cull a ray that grazes the primitive
    if oc.ndim == 1:
        b, cc = d @ oc, float(oc @ oc) - radius * radius
    else:
        b = np.einsum("ij,ij->i", d, oc)
        cc = np.einsum("ij,ij->i", oc, oc) - radius * radius
    disc = b * b - dd * cc
    return np.flatnonzero((disc >= 0.0) & (np.sqrt(np.maximum(disc, 0.0)) - b > EPS * dd))


def cast(o, d, prims, obj: int = 1) -> Hit:
    """Nearest hit of rays with the union of ``prims`` (one object ``obj``).

    ``d`` is [N, 3]; ``o`` is [N, 3] or one shared origin [3] (a pinhole camera: much cheaper). Each primitive is
    tested exactly only on the rays that reach its bounding sphere.
    """
    d = np.asarray(d, dtype=np.float64).reshape(-1, 3)
    o = np.asarray(o, dtype=np.float64)
    shared = o.ndim == 1
    dd = np.einsum("ij,ij->i", d, d)
    best = np.full(len(d), np.inf)
    normal = np.zeros(d.shape)
    part = np.full(len(d), -1, dtype=np.int64)
    for prim in prims:
        center, radius = prim.bsphere()
        idx = _reaching(o, d, dd, center, radius)
        if not len(idx):
            continue
        t, n = prim.intersect(o if shared else o[idx], d[idx])
        closer = t < best[idx]
        sel = idx[closer]
        best[sel], normal[sel], part[sel] = t[closer], n[closer], prim.part
    hit = np.isfinite(best)
    point = o + np.where(hit, best, 0.0)[:, None] * d
    return Hit(best, normal, point, part, np.where(hit, obj, 0))


@dataclass
class RigidBody:
    """Primitives in a body frame; cast with a pose (``R``, ``c``: body-to-world, x_world = R x_body + c)."""

    prims: list
    obj: int = 1
    radius: float = field(init=False)

    def __post_init__(self):
        # Bounding sphere about the body origin: rays that miss it skip the per-primitive tests.
        self.radius = max(p.bound() for p in self.prims)

    def cast(self, o, d, R, c) -> Hit:
        """Hits of world rays; ``point`` is in BODY coordinates (for solid textures), ``normal`` in WORLD ones.

        ``d`` is [..., 3]; ``o`` is one shared origin [3] or broadcasts with ``d``. Rays are culled against the
        bounding sphere in the world frame (it does not turn with the body); only the survivors are moved into the
        body frame and tested against the primitives.
        """
        R = np.asarray(R, dtype=np.float64)
        c = np.asarray(c, dtype=np.float64)
        d = np.asarray(d, dtype=np.float64)
        shape = d.shape[:-1]
        dw = d.reshape(-1, 3)
        o = np.asarray(o, dtype=np.float64)
        shared = o.ndim == 1
        if not shared:
            o = np.broadcast_to(o, d.shape).reshape(-1, 3)
        idx = _reaching(o, dw, np.einsum("ij,ij->i", dw, dw), c, self.radius)
        t = np.full(len(dw), np.inf)
        normal, point = np.zeros((len(dw), 3)), np.zeros((len(dw), 3))
        part, obj = np.full(len(dw), -1, dtype=np.int64), np.zeros(len(dw), dtype=np.int64)
        if len(idx):
            ob = (o - c) @ R if shared else (o[idx] - c) @ R  # R^T x for row vectors
            h = cast(ob, dw[idx] @ R, self.prims, self.obj)
            t[idx], normal[idx], point[idx], part[idx], obj[idx] = h.t, h.normal @ R.T, h.point, h.part, h.obj
        return Hit(
            t.reshape(shape),
            normal.reshape(*shape, 3),
            point.reshape(*shape, 3),
            part.reshape(shape),
            obj.reshape(shape),
        )

    def contains(self, p, tol: float = 1e-6) -> np.ndarray:
        """Whether body-frame points lie strictly inside any primitive."""
        inside = np.zeros(np.asarray(p).shape[:-1], dtype=bool)
        for prim in self.prims:
            inside |= prim.contains(p, tol)
        return inside

    def sample_surface(self, rng: np.random.Generator, n: int):
        """``n`` points (body frame) uniform on the visible surface of the union, with normals and part ids.

        Each primitive is oversampled in proportion to its area and points buried inside another primitive are
        dropped, so the samples lie on the outer surface that a camera can see.
        """
        areas = np.array([p.area() for p in self.prims])
        pts, nrms, parts = [], [], []
        for k, prim in enumerate(self.prims):
            m = int(np.ceil(3.0 * n * areas[k] / areas.sum())) + 8
            p, nrm = prim.sample(rng, m)
            others = [q for j, q in enumerate(self.prims) if j != k]
            keep = ~RigidBody(others, self.obj).contains(p) if others else np.ones(m, dtype=bool)
            pts.append(p[keep])
            nrms.append(nrm[keep])
            parts.append(np.full(int(keep.sum()), prim.part))
        p, nrm, part = np.concatenate(pts), np.concatenate(nrms), np.concatenate(parts)
        pick = np.sort(rng.permutation(len(p))[: min(n, len(p))])
        return p[pick], nrm[pick], part[pick]
