"""Textured triangle meshes and a z-buffer rasterizer: the benchmark scenes' renderer, independent of the model's
Gaussian rasterizer.

A scene is a list of meshes. Each :class:`Mesh` has rest-pose vertices ``X`` (material coordinates), triangles, an
object id and a solid texture (a colour times a 3D checker evaluated at the *rest* coordinates, so the texture
moves and deforms with the material). Deformable meshes are carried by simulated particles (:class:`Embedding`).

Rendering (:func:`render_meshes`): vertices are projected with the OpenCV camera; a Taichi kernel walks each
triangle's pixel box at ``ss × ss`` subsamples per pixel and keeps, per subsample, the nearest triangle by an
atomic min over (depth, triangle index) packed into one 64-bit key (perspective-correct depth). Shading is a second
kernel over the hit subsamples: perspective-correct barycentrics → rest coordinates → checker albedo, times Lambert with
a fixed light and ambient term. Colour and coverage are the means over subsamples; object ids are read at the pixel
centre (``ss`` is odd).
"""

# No `from __future__ import annotations`: Taichi 1.7 reads kernel annotations as live objects.
import math
from dataclasses import dataclass

import numpy as np
import torch

from causalgs._ti import ti
from causalgs.cameras import Camera

LIGHT = np.array([0.35, -0.45, 0.82]) / np.linalg.norm([0.35, -0.45, 0.82])
AMBIENT = 0.35
SUPERSAMPLE = 3  # odd, so one subsample sits at the pixel centre (for the id masks)
DEPTH_BITS = 31
EMPTY = np.iinfo(np.int64).max


@dataclass
class Mesh:
    """A triangle mesh: rest vertices ``X`` [V, 3], triangles [T, 3] (counter-clockwise seen from outside), its
    object id (1..255), base colour and checker size (in rest coordinates)."""

    X: np.ndarray
    triangles: np.ndarray
    object_id: int
    color: tuple[float, float, float]
    checker: float = 0.1
    dark: float = 0.55  # albedo factor of the dark checker cells


def box_mesh(lo, hi, cells: int) -> tuple[np.ndarray, np.ndarray]:
    """The surface of the box [lo, hi] as a closed mesh with ``cells`` × ``cells`` quads per face (outward winding)."""
    lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
    verts, tris = [], []
    u = np.linspace(0.0, 1.0, cells + 1)
    for axis in range(3):
        a, b = (axis + 1) % 3, (axis + 2) % 3
        for side in (0, 1):
            uu, vv = np.meshgrid(u, u, indexing="ij")
            p = np.zeros((cells + 1, cells + 1, 3))
            p[..., axis] = hi[axis] if side else lo[axis]
            p[..., a] = lo[a] + uu * (hi[a] - lo[a])
            p[..., b] = lo[b] + vv * (hi[b] - lo[b])
            base = sum(len(v) for v in verts)
            idx = base + np.arange((cells + 1) ** 2).reshape(cells + 1, cells + 1)
            q = np.stack([idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]], -1).reshape(-1, 4)
            t = np.concatenate([q[:, [0, 1, 2]], q[:, [0, 2, 3]]])
            # (a, b, axis) is right-handed, so u×v points along +axis: flip the low side to face outward.
            if not side:
                t = t[:, [0, 2, 1]]
            verts.append(p.reshape(-1, 3))
            tris.append(t)
    return np.concatenate(verts), np.concatenate(tris).astype(np.int32)


def sphere_mesh(center, radius: float, subdivisions: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """An icosphere (outward winding)."""
    t = (1.0 + math.sqrt(5.0)) / 2.0
    v = [(-1, t, 0), (1, t, 0), (-1, -t, 0), (1, -t, 0), (0, -1, t), (0, 1, t), (0, -1, -t), (0, 1, -t),
         (t, 0, -1), (t, 0, 1), (-t, 0, -1), (-t, 0, 1)]  # fmt: skip
    f = [(0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11), (1, 5, 9), (5, 11, 4), (11, 10, 2), (10, 7, 6),
         (7, 1, 8), (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8), (3, 8, 9), (4, 9, 5), (2, 4, 11), (6, 2, 10),
         (8, 6, 7), (9, 8, 1)]  # fmt: skip
    verts = [np.asarray(p, dtype=np.float64) / np.linalg.norm(p) for p in v]
    faces = list(f)
    for _ in range(subdivisions):
        cache: dict[tuple[int, int], int] = {}

        def mid(i, j, cache=cache):
            key = (min(i, j), max(i, j))
            if key not in cache:
                m = verts[i] + verts[j]
                verts.append(m / np.linalg.norm(m))
                cache[key] = len(verts) - 1
            return cache[key]

        new = []
        for a, b, c in faces:
            ab, bc, ca = mid(a, b), mid(b, c), mid(c, a)
            new += [(a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca)]
        faces = new
    return np.asarray(center) + radius * np.stack(verts), np.asarray(faces, dtype=np.int32)


class Embedding:
    """Carries mesh vertices with simulated particles: each vertex follows its ``k`` nearest particles at rest,
    x_v = Σ w (x_p + F_p (X_v − X_p)) / Σ w with w = 1 / (d + ε) (first-order: the local affine motion of the
    material, so faces stretch, shear and rotate with it)."""

    def __init__(self, X_vertices: np.ndarray, X_particles: np.ndarray, k: int = 8, chunk: int = 512):
        Xv = torch.as_tensor(X_vertices, dtype=torch.float64)
        Xp = torch.as_tensor(X_particles, dtype=torch.float64)
        idx, wts = [], []
        for s in range(0, len(Xv), chunk):
            d = torch.cdist(Xv[s : s + chunk], Xp)
            dist, i = torch.topk(d, k=min(k, len(Xp)), largest=False)
            w = 1.0 / (dist + 1e-6)
            idx.append(i)
            wts.append(w / w.sum(1, keepdim=True))
        self.index = torch.cat(idx)
        self.weight = torch.cat(wts)
        self.offset = Xv[:, None, :] - Xp[self.index]  # [V, k, 3]: X_v − X_p

    def __call__(self, x: torch.Tensor, F: torch.Tensor) -> np.ndarray:
        """Deformed vertex positions for particle positions x [P, 3] and deformation gradients F [P, 3, 3]."""
        x, F = torch.as_tensor(x, dtype=torch.float64), torch.as_tensor(F, dtype=torch.float64)
        moved = x[self.index] + (F[self.index] @ self.offset[..., None])[..., 0]
        return (self.weight[..., None] * moved).sum(1).numpy()


@ti.kernel
def _raster(pix: ti.types.ndarray(), depth: ti.types.ndarray(), tris: ti.types.ndarray(), n_tris: ti.i32,
            width: ti.i32, height: ti.i32, near: float, depth_scale: float, zbuf: ti.types.ndarray()):  # fmt: skip
    """For every subsample centre inside a triangle, zbuf = min(zbuf, depth_key << 32 | triangle)."""
    for t in range(n_tris):
        a, b, c = tris[t, 0], tris[t, 1], tris[t, 2]
        za, zb, zc = depth[a], depth[b], depth[c]
        if za > near and zb > near and zc > near:
            ax, ay, bx, by, cx, cy = pix[a, 0], pix[a, 1], pix[b, 0], pix[b, 1], pix[c, 0], pix[c, 1]
            area = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)
            if ti.abs(area) > 1e-12:
                x0 = ti.max(ti.cast(ti.floor(ti.min(ax, bx, cx) - 0.5), ti.i32), 0)
                x1 = ti.min(ti.cast(ti.ceil(ti.max(ax, bx, cx) - 0.5), ti.i32), width - 1)
                y0 = ti.max(ti.cast(ti.floor(ti.min(ay, by, cy) - 0.5), ti.i32), 0)
                y1 = ti.min(ti.cast(ti.ceil(ti.max(ay, by, cy) - 0.5), ti.i32), height - 1)
                for y in range(y0, y1 + 1):
                    for x in range(x0, x1 + 1):
                        px, py = x + 0.5, y + 0.5
                        w0 = ((bx - px) * (cy - py) - (by - py) * (cx - px)) / area
                        w1 = ((cx - px) * (ay - py) - (cy - py) * (ax - px)) / area
                        w2 = 1.0 - w0 - w1
                        if w0 >= 0 and w1 >= 0 and w2 >= 0:
                            z = 1.0 / (w0 / za + w1 / zb + w2 / zc)  # perspective-correct depth
                            key = ti.cast(ti.min(z * depth_scale, 2.0**DEPTH_BITS - 1), ti.i64)
                            ti.atomic_min(zbuf[y * width + x], (key << 32) | ti.cast(t, ti.i64))


@ti.kernel
def _shade(zbuf: ti.types.ndarray(), pix: ti.types.ndarray(), depth: ti.types.ndarray(), tris: ti.types.ndarray(),
           rest: ti.types.ndarray(), verts: ti.types.ndarray(), tri_mesh: ti.types.ndarray(),
           color: ti.types.ndarray(), checker: ti.types.ndarray(), dark: ti.types.ndarray(),
           mesh_id: ti.types.ndarray(), width: ti.i32, light: ti.math.vec3, ambient: float,
           rgb: ti.types.ndarray(), ids: ti.types.ndarray()):  # fmt: skip
    """Per subsample with a hit: perspective-correct barycentrics at its centre → rest coordinates → checker albedo,
    times two-sided Lambert on the face normal; and the object id."""
    for i in range(zbuf.shape[0]):
        key = zbuf[i]
        if key != ti.i64(EMPTY):
            t = ti.cast(key & ti.i64(0xFFFFFFFF), ti.i32)
            a, b, c = tris[t, 0], tris[t, 1], tris[t, 2]
            px, py = ti.cast(i % width, float) + 0.5, ti.cast(i // width, float) + 0.5
            ax, ay, bx, by, cx, cy = pix[a, 0], pix[a, 1], pix[b, 0], pix[b, 1], pix[c, 0], pix[c, 1]
            area = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)
            w0 = ((bx - px) * (cy - py) - (by - py) * (cx - px)) / area
            w1 = ((cx - px) * (ay - py) - (cy - py) * (ax - px)) / area
            l0, l1, l2 = w0 / depth[a], w1 / depth[b], (1.0 - w0 - w1) / depth[c]
            s = l0 + l1 + l2
            l0, l1, l2 = l0 / s, l1 / s, l2 / s
            m = tri_mesh[t]
            cells = 0
            for d in ti.static(range(3)):
                X = l0 * rest[a, d] + l1 * rest[b, d] + l2 * rest[c, d]
                cells += ti.cast(ti.floor(X / checker[m]), ti.i32)
            e1 = ti.Vector([verts[b, d] - verts[a, d] for d in ti.static(range(3))])
            e2 = ti.Vector([verts[c, d] - verts[a, d] for d in ti.static(range(3))])
            n = e1.cross(e2)
            n = n / (n.norm() + 1e-30)
            shade = ambient + (1.0 - ambient) * ti.abs(n.dot(light))
            f = ti.select(cells % 2 == 0, 1.0, dark[m]) * shade
            for d in ti.static(range(3)):
                rgb[i, d] = ti.min(ti.max(color[m, d] * f, 0.0), 1.0)
            ids[i] = mesh_id[m]


def render_meshes(camera: Camera, meshes: list[Mesh], positions: list[np.ndarray], ss: int = SUPERSAMPLE,
                  background=(1.0, 1.0, 1.0)):  # fmt: skip
    """Render ``meshes`` (vertex ``positions`` per mesh, world) into ``(rgb [H, W, 3], alpha [H, W], ids [H, W])``:
    straight colour averaged over covered subsamples, coverage, uint8 object id at the pixel centre (0 = none)."""
    W, H = camera.width * ss, camera.height * ss
    cam = camera.scaled(ss) if ss != 1 else camera
    verts = np.concatenate(positions)
    offsets = np.cumsum([0] + [len(p) for p in positions])
    tris = np.concatenate([m.triangles + o for m, o in zip(meshes, offsets[:-1], strict=True)]).astype(np.int32)
    tri_mesh = np.concatenate([np.full(len(m.triangles), i) for i, m in enumerate(meshes)])
    R, tvec = cam.viewmat[:3, :3], cam.viewmat[:3, 3]
    pc = verts @ R.T + tvec
    z = pc[:, 2]
    K = cam.K
    zs = np.where(z > 1e-9, z, 1e-9)
    pix = np.stack([K[0, 0] * pc[:, 0] / zs + K[0, 2], K[1, 1] * pc[:, 1] / zs + K[1, 2]], -1)
    far = float(max(z.max(), 1e-6)) * 1.01
    zbuf = torch.full((H * W,), EMPTY, dtype=torch.int64)
    _raster(torch.from_numpy(np.ascontiguousarray(pix, dtype=np.float64)), torch.from_numpy(np.ascontiguousarray(z)),
            torch.from_numpy(tris), len(tris), W, H, 1e-4, (2.0**DEPTH_BITS - 2) / far, zbuf)  # fmt: skip
    hit = zbuf != EMPTY
    rgb = torch.zeros(H * W, 3, dtype=torch.float64)
    ids = torch.zeros(H * W, dtype=torch.int32)

    def t64(a):
        return torch.from_numpy(np.ascontiguousarray(a, dtype=np.float64))

    def t32(a):
        return torch.from_numpy(np.ascontiguousarray(a, dtype=np.int32))

    rest = np.concatenate([m.X for m in meshes])
    per_mesh = [t64([m.color for m in meshes]), t64([m.checker for m in meshes]), t64([m.dark for m in meshes]),
                t32([m.object_id for m in meshes])]  # fmt: skip
    _shade(zbuf, t64(pix), t64(z), t32(tris), t64(rest), t64(verts), t32(tri_mesh), *per_mesh, W, LIGHT.tolist(),
           AMBIENT, rgb, ids)  # fmt: skip
    hit_img = hit.reshape(camera.height, ss, camera.width, ss).double()
    cover = hit_img.mean((1, 3))
    rgb_img = rgb.reshape(camera.height, ss, camera.width, ss, 3).sum((1, 3))
    rgb_img = rgb_img / hit_img.sum((1, 3)).clamp(min=1.0)[..., None]
    rgb_img = torch.where(cover[..., None] > 0, rgb_img, torch.tensor(background, dtype=torch.float64))
    centre = ss // 2
    id_img = ids.reshape(camera.height, ss, camera.width, ss)[:, centre, :, centre]
    return rgb_img.numpy(), cover.numpy(), id_img.numpy().astype(np.uint8)
