"""From dynamic Gaussians to MPM particles, and back from simulated particles to Gaussians.

3DGS puts its Gaussians on surfaces, so the dynamic Gaussians alone would simulate as hollow shells: wrong mass,
wrong inertia, contact that folds in. The particles fill the solid the surface encloses instead: the Gaussians'
centres are voxelised at spacing dx/2 (the usual 8 particles per cell), the occupancy is closed until each body's
surface seals and its enclosed holes are filled (scipy.ndimage; see :func:`seal_and_fill`), and then

- ``fill = "surface"`` (the default): every voxel inside gets one particle at its centre with the voxel's volume
  (dx/2)³; a voxel on the boundary gets only its part inside the surface the Gaussians sample (see
  :func:`inside_fraction`), with that part's volume, its particle at that part's centroid. A voxel that holds a
  surface Gaussian reaches on average half a voxel past the surface, so a fill of whole voxels makes a body about a
  quarter of a cell thicker on every side: on a 0.20 × 0.16 × 0.12 m box at 1.19 cm voxels, +6% to +56% volume and
  its lowest layer 3–12 mm low, which a contact fit then trades against the ground's height and friction.
  The surface is where the Gaussians' centres are: a 3DGS fit puts them a few millimetres inside a face (a median
  6 mm on the fitted toss scenes), but a face's Gaussians run on to its edges, so each face comes out sunk below a
  rim; a face is filled up to its rim (:func:`fill_recesses`), and on four fitted toss scenes a body comes out
  0.87–0.89 of the true volume (0.80–0.84 sunk), its bottom flat where it was a rim one voxel wide that alone met
  the ground.
- ``fill = "gaussians"`` (the construction before it): the dynamic Gaussians are particles themselves (a random
  subset of ``budget`` when there are more) and every filled voxel that holds none gets one at its centre; a voxel's
  volume is shared equally by its particles.

Total mass is the filled volume times density however the Gaussians are spread. Every dynamic Gaussian follows its
nearest particle p to first order: x_g(t) = x_p(t) + F_p(t)(x_g(0) − x_p(0)) and Σ_g(t) = F_p Σ_g Fᵀ_p (a Gaussian
that is a particle has zero offset).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy import ndimage
from scipy.spatial import cKDTree

from causalgs.errors import CausalGSError

FILLS = ("surface", "gaussians")


@dataclass
class Particles:
    """The simulated particles of a scene and how the dynamic Gaussians hang on them.

    ``x0`` [P, 3] rest positions, ``vol`` [P] rest volumes, ``gaussian`` [P] the Gaussian index a particle is (−1 for
    fill), ``carrier`` [G] the particle every dynamic Gaussian follows and ``offset`` [G, 3] its rest offset from it,
    ``dynamic`` [G] the indices of those Gaussians in the canonical set."""

    x0: torch.Tensor
    vol: torch.Tensor
    gaussian: torch.Tensor
    dynamic: torch.Tensor
    carrier: torch.Tensor
    offset: torch.Tensor

    def __len__(self) -> int:
        return len(self.x0)

    def state_dict(self) -> dict[str, torch.Tensor]:
        return {k: getattr(self, k) for k in ("x0", "vol", "gaussian", "dynamic", "carrier", "offset")}

    @classmethod
    def from_state_dict(cls, d: dict) -> Particles:
        return cls(**{k: d[k] for k in ("x0", "vol", "gaussian", "dynamic", "carrier", "offset")})

    def carry(self, x: torch.Tensor, F: torch.Tensor) -> torch.Tensor:
        """Dynamic Gaussians' positions [..., G, 3] from particle positions x [..., P, 3] and F [..., P, 3, 3]."""
        xp = x[..., self.carrier, :]
        Fp = F[..., self.carrier, :, :]
        return xp + (Fp @ self.offset.to(x.dtype)[..., None])[..., 0]


def build_particles(
    means: np.ndarray, dynamic: np.ndarray, lo, dx: float, budget: int, capacity: int, seed: int = 0,
    solid: np.ndarray | None = None, coarse_fill: bool = True, fill: str = "surface",
) -> Particles:
    """Particles for the Gaussians ``means[solid]`` (default: ``dynamic``) on a grid of cell ``dx`` whose box starts
    at ``lo``: 8 per cell, or 1 per cell when 8 would pass ``capacity`` (a large dynamic region on a fixed-capacity
    store). Every Gaussian of ``dynamic`` is carried by its nearest particle. With ``coarse_fill`` false, more than
    ``capacity`` particles at 8 per cell raise :class:`TooManyParticles` (with the count) instead. ``fill``:
    ``"surface"`` or ``"gaussians"`` (the module's docstring); ``budget`` counts Gaussian particles in the latter."""
    if fill not in FILLS:
        raise CausalGSError(f"physics.fill = {fill!r}: expected one of {', '.join(FILLS)}")
    solid = dynamic if solid is None else (np.asarray(solid, bool) & np.asarray(dynamic, bool))
    try:
        return _build(means, dynamic, solid, lo, dx / 2.0, budget, capacity, seed, fill)
    except _TooMany as e:
        if not coarse_fill:
            raise TooManyParticles(e.args[0]) from None
    try:
        return _build(means, dynamic, solid, lo, dx, budget, capacity, seed, fill)
    except _TooMany as e:
        raise CausalGSError(
            f"the dynamic region needs {e.args[0]} particles even at one per cell, more than the simulator's "
            f"capacity {capacity}: lower the grid resolution or the particle budget, or raise physics.capacity"
        ) from None


class _TooMany(Exception):
    pass


class TooManyParticles(Exception):
    """The particles at 8 per cell would pass the limit; ``count`` is how many they would be."""

    def __init__(self, count: int):
        super().__init__(count)
        self.count = int(count)


MAX_EXTRA_CLOSING = 8  # closing iterations tried beyond the first when a surface has not sealed
SEALED = 0.75  # a body is sealed once its filled volume reaches this share of its volume at the most closing
SEAL_JUMP = 0.05  # ... and no further closing grows it by more than this share at once (a cavity sealing)


def seal_and_fill(occ: np.ndarray, first: int) -> np.ndarray:
    """The solid bodies of a voxelised surface: closed, then their enclosed holes filled.

    A surface sampled by Gaussian centres has gaps (a flat face is covered by a few large Gaussians), and on a fine
    voxel grid one closing iteration does not seal them: the fill then leaves a hollow shell, whose mass and inertia
    are a fraction of the body's. So every body (a connected part of the once-closed occupancy), closed on its own so
    that no closing bridges two bodies, takes the fewest closing iterations, from ``first`` up to
    ``first + MAX_EXTRA_CLOSING``, whose filled volume reaches ``SEALED`` of the most-closed one: a hollow shell holds
    a small share of it, a solid body nearly all of it. A thick-walled body (a small block whose faces are two or
    three voxels deep, its unseen face gappy) holds most of its volume even hollow, so the fill also waits until no
    further closing grows it by more than ``SEAL_JUMP`` at once: a cavity sealing is a jump (a third of the volume
    on such a block), a concave notch filling grows it gradually. The fewest such iterations keep a concave shape's
    notch, unless the notch is more than a quarter of the closed volume and narrower than the closing (then it is
    filled). ``occ`` must be padded by ``first`` voxels (each body is padded further on its own)."""
    cube = np.ones((3, 3, 3), bool)
    most = first + MAX_EXTRA_CLOSING
    labels, _ = ndimage.label(ndimage.binary_closing(occ, structure=cube, iterations=first), structure=cube)
    out = np.zeros_like(occ)
    for k, sl in enumerate(ndimage.find_objects(labels), start=1):
        if sl is None:
            continue
        sl = tuple(slice(max(0, a.start - most), min(n, a.stop + most)) for a, n in zip(sl, occ.shape, strict=True))
        mine = np.pad(occ[sl] & (labels[sl] == k), most)
        filled = [ndimage.binary_fill_holes(ndimage.binary_closing(mine, structure=cube, iterations=c))
                  for c in range(first, most + 1)]  # fmt: skip
        vols = np.array([np.count_nonzero(f) for f in filled], dtype=np.float64)
        jumps = np.flatnonzero(vols[1:] > (1.0 + SEAL_JUMP) * vols[:-1])
        after = int(jumps[-1]) + 1 if len(jumps) else 0
        pick = max(after, int(np.argmax(vols >= SEALED * vols[-1])))
        inner = tuple(slice(most, most + (a.stop - a.start)) for a in sl)
        out[sl] |= filled[pick][inner]
    return out


SUB = 4  # sub-samples per voxel edge where the surface cuts a voxel (64 per voxel: its inside share to 1/64)
VOTERS = 8  # nearest surface Gaussians whose tangent planes decide whether a point is inside
REACH = 0.75  # (voxels) how far from the nearest Gaussian a point of a voxel outside the occupancy may be inside


def inside_fraction(occ: np.ndarray, origin: np.ndarray, h: float, pts: np.ndarray,
                    cells: np.ndarray) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """The share of each voxel ``cells`` [n, 3] (indices into ``occ``, whose voxel (0, 0, 0) has its corner at
    ``origin``, edge ``h``) inside the surface sampled by the Gaussian centres ``pts`` [m, 3], and that part's
    centroid: ([n], [n, 3]).

    A Gaussian's outward normal is the direction in which the filled occupancy ``occ`` falls fastest (down the
    gradient of its blur over one voxel): on a face that is the face's normal however the Gaussians on it are
    arranged (their own spread's least axis is not: a face seen from no camera holds a few Gaussians in rows). A
    point is inside where the tangent planes of its ``VOTERS`` nearest Gaussians, weighted by distance at the scale
    of half a voxel, put it on average behind the surface (Hoppe et al.'s signed distance to the nearest tangent
    plane, smoothed over a few so that one stray Gaussian does not cut a hole), and, in a voxel outside ``occ``,
    within ``REACH`` voxel of its nearest Gaussian: a tangent plane says nothing past its face's edge, and a face's last
    row of Gaussians above an unseen, sparsely sampled bottom otherwise hangs a lip of up to a voxel under the body.
    A face sunk below its rim is then filled up to it (:func:`fill_recesses`). A voxel's share is that of its
    ``SUB``³ sub-samples inside."""
    pts = np.asarray(pts, dtype=np.float64)
    blur = ndimage.gaussian_filter(occ.astype(np.float64), 1.0)
    grad = np.stack(np.gradient(blur), -1)
    vox = np.clip(np.floor((pts - origin) / h).astype(np.int64), 0, np.array(occ.shape) - 1)
    normal = -grad[tuple(vox.T)]
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)
    u = (np.arange(SUB) + 0.5) / SUB - 0.5
    sub = np.stack(np.meshgrid(u, u, u, indexing="ij"), -1).reshape(-1, 3) * h
    x = (origin + (cells + 0.5) * h)[:, None, :] + sub[None]  # [n, SUB³, 3]
    q = x.reshape(-1, 3)
    v = min(VOTERS, len(pts))
    dist, near = cKDTree(pts).query(q, k=v)
    dist, near = dist.reshape(len(q), v), near.reshape(len(q), v)
    w = np.exp(-0.5 * ((dist - dist[:, :1]) / (0.5 * h)) ** 2)
    side = ((q[:, None, :] - pts[near]) * normal[near]).sum(-1)
    beyond = np.repeat(~occ[tuple(cells.T)], SUB**3) & (dist[:, 0] >= REACH * h)  # past a face's edge
    inside = (((w * side).sum(1) < 0) & ~beyond).reshape(len(cells), -1)
    inside = fill_recesses(occ, cells, inside)
    share = inside.mean(1)
    centroid = (x * inside[..., None]).sum(1) / np.maximum(inside.sum(1), 1)[:, None]
    return share, centroid


def fill_recesses(occ: np.ndarray, cells: np.ndarray, inside: np.ndarray) -> np.ndarray:
    """``inside`` [n, SUB³] (the sub-samples of the voxels ``cells`` of ``occ`` inside the surface; every other voxel
    of ``occ`` is wholly inside, every other voxel outside it), with each outside sub-sample that has inside ones on
    both sides along two of the three axes made inside.

    A 3DGS fit puts a face's Gaussians a few millimetres inside it, but the neighbouring faces' Gaussians run on to
    the edge they share: each face of a box comes out sunk below a rim as deep as that inset, one voxel wide. Under
    a body the rim is all that touches the ground, and its contact is not the face's: on a fitted toss (friction
    μ = 0.3, the inset 6 mm) the filled block's rim made its simulated landing slide 16 mm further than the truth's
    at the truth's parameters, and a fit of the motion wanted μ ≈ 0.5. A point outside a convex solid has it on one
    side at most along any line, so a convex body gains nothing, and a recess is filled only within the voxels the
    surface cuts (a cavity deeper than that keeps its depth beyond them)."""
    n = len(cells)
    if n == 0:
        return inside
    fine = np.repeat(np.repeat(np.repeat(occ, SUB, 0), SUB, 1), SUB, 2)
    a, b, c = np.indices((SUB, SUB, SUB)).reshape(3, -1)  # sub-sample offsets, in inside_fraction's order
    idx = (cells[:, None, 0] * SUB + a, cells[:, None, 1] * SUB + b, cells[:, None, 2] * SUB + c)  # [n, SUB³] each
    fine[idx] = inside
    enclosed = np.zeros(fine.shape, dtype=np.int8)
    for axis in range(3):
        before = np.logical_or.accumulate(fine, axis=axis)
        after = np.flip(np.logical_or.accumulate(np.flip(fine, axis), axis=axis), axis)
        enclosed += before & after
    return inside | (enclosed[idx] >= 2)


def _build(means: np.ndarray, dynamic: np.ndarray, solid: np.ndarray, lo, h: float, budget: int, capacity: int,
           seed: int, fill: str) -> Particles:  # fmt: skip
    dyn = np.flatnonzero(dynamic)
    src = np.flatnonzero(solid)
    if len(src) == 0:
        raise CausalGSError("no dynamic Gaussians to simulate: every Gaussian was classed static")
    lo = np.asarray(lo, dtype=np.float64)
    pts = means[src].astype(np.float64)
    ijk = np.floor((pts - lo) / h).astype(np.int64)
    pad = 2
    base = ijk.min(0) - pad
    shape = ijk.max(0) - base + 1 + pad
    occ = np.zeros(shape, dtype=bool)
    occ[tuple((ijk - base).T)] = True
    # Close gaps as wide as the Gaussians' typical spacing so the surface seals before its inside is filled.
    spacing = float(np.median(cKDTree(pts).query(pts, k=2)[0][:, 1])) if len(pts) > 1 else h
    first = int(np.clip(np.ceil(2.0 * spacing / h), 1, 6))
    occ = np.pad(occ, first)
    base = base - first
    occ = seal_and_fill(occ, first)
    if fill == "gaussians":
        x0, vol, gaussian = _gaussian_particles(means, src, occ, base, lo, h, budget, capacity, seed)
    else:
        # The voxels the surface may cut: two layers in from the occupancy's boundary (surface Gaussians, and the
        # voxels just behind them) and one out (a face on a voxel's edge).
        cube = np.ones((3, 3, 3), bool)
        core = ndimage.binary_erosion(occ, structure=cube, iterations=2)
        band = ndimage.binary_dilation(occ, structure=cube) & ~core
        on_band = band[tuple((ijk - base).T)]
        if not on_band.any():
            on_band[:] = True
        if np.count_nonzero(occ) > capacity:  # the particles are about one per filled voxel
            raise _TooMany(np.count_nonzero(occ))
        cells = np.argwhere(band)
        share, centroid = inside_fraction(occ, lo + base * h, h, pts[on_band], cells)
        core = np.argwhere(core)
        x0 = np.concatenate([lo + (core + base + 0.5) * h, centroid[share > 0]])
        vol = np.concatenate([np.full(len(core), h**3), share[share > 0] * h**3])
        if len(x0) > capacity:
            raise _TooMany(len(x0))
        gaussian = -np.ones(len(x0), dtype=np.int64)
    tree = cKDTree(x0)
    _, carrier = tree.query(means[dyn].astype(np.float64))
    offset = means[dyn].astype(np.float64) - x0[carrier]
    return Particles(
        x0=torch.from_numpy(x0),
        vol=torch.from_numpy(vol),
        gaussian=torch.from_numpy(gaussian),
        dynamic=torch.from_numpy(dyn),
        carrier=torch.from_numpy(carrier.astype(np.int64)),
        offset=torch.from_numpy(offset),
    )


def _gaussian_particles(means, src, occ, base, lo, h, budget, capacity, seed):
    """``fill = "gaussians"``: the solid Gaussians (``budget`` of them at most) are particles, and every filled voxel
    that holds none gets one at its centre; each voxel's volume is shared by its particles."""
    rng = np.random.default_rng(seed)
    chosen = src if len(src) <= budget else np.sort(rng.choice(src, budget, replace=False))
    shape = np.array(occ.shape)
    g_ijk = np.floor((means[chosen].astype(np.float64) - lo) / h).astype(np.int64) - base
    occ[tuple(g_ijk.T)] = True
    holder = np.zeros(shape, dtype=bool)
    holder[tuple(g_ijk.T)] = True
    fill_ijk = np.argwhere(occ & ~holder)
    fill_x = lo + (fill_ijk + base + 0.5) * h
    x0 = np.concatenate([means[chosen].astype(np.float64), fill_x])
    if len(x0) > capacity:
        raise _TooMany(len(x0))
    all_ijk = np.concatenate([g_ijk, fill_ijk])
    flat = np.ravel_multi_index(tuple(all_ijk.T), shape)
    _, inverse, counts = np.unique(flat, return_inverse=True, return_counts=True)
    vol = h**3 / counts[inverse]
    return x0, vol, np.concatenate([chosen, -np.ones(len(fill_x), dtype=np.int64)])
