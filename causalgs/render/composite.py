"""Tile binning (torch) and front-to-back alpha compositing (Taichi), forward and hand-written backward.

Design, for the CPU backend (no block shared memory, and Taichi's autodiff cannot handle the compositing loop):
- Binning: every Gaussian's exact pixel box (project.bounds) is cut into 16×16 tiles; (tile, depth) ordering comes
  from a depth argsort followed by a stable sort on the tile id (torch).
- The projected data of every tile entry is packed contiguously in tile order, so the compositing loops stream it.
- Compositing runs one tile per thread and is *entry-major*: for each Gaussian of the tile's list, only the pixels of
  its own box (clipped to the tile) are visited, instead of every pixel against every entry. Pixels that reach the
  transmittance floor are marked done (negative T); a tile stops when all its pixels are done.
- The backward walks each tile's list in reverse, recovering T_i from the final T by division by (1 − α_i), and
  sums each entry's gradient over its pixels in registers: a tile's entries belong to one thread, so no atomics.
"""

# No `from __future__ import annotations`: Taichi 1.7 reads kernel annotations as live objects.
import torch

from causalgs._ti import ti
from causalgs.render.reference import ALPHA_MAX, ALPHA_MIN, T_MIN

TILE = 16
PACK = 10  # mx, my, conic a, b, c, opacity, r, g, b, depth
VPACK = 9  # gradients of mx, my, a, b, c, opacity, r, g, b


def bin_gaussians(box: torch.Tensor, depth: torch.Tensor, width: int, height: int, tile: int = TILE):
    """Tile lists. ``box`` [N, 4] int32 inclusive pixel boxes (x0, x1, y0, y1), ``depth`` [N].

    Returns ``gids`` [M] int32 (Gaussian of every entry, by tile then depth) and ``ranges`` [T, 2] int32 (each
    tile's [start, end) in ``gids``), with T = ceil(W / tile) · ceil(H / tile) tiles in row-major order.
    """
    tiles_x = (width + tile - 1) // tile
    n_tiles = tiles_x * ((height + tile - 1) // tile)
    box = box.long()
    valid = (box[:, 0] <= box[:, 1]) & (box[:, 2] <= box[:, 3])
    ids = torch.nonzero(valid).flatten()
    ids = ids[torch.argsort(depth[ids], stable=True)]
    b = box[ids]
    tx0, ty0 = b[:, 0] // tile, b[:, 2] // tile
    nx = b[:, 1] // tile - tx0 + 1
    counts = nx * (b[:, 3] // tile - ty0 + 1)
    total = int(counts.sum())
    rep = torch.repeat_interleave(torch.arange(len(ids)), counts)
    first = torch.cumsum(counts, 0) - counts
    off = torch.arange(total) - first[rep]
    tile_id = (ty0[rep] + off // nx[rep]) * tiles_x + tx0[rep] + off % nx[rep]
    tile_sorted, perm = torch.sort(tile_id, stable=True)
    gids = ids[rep[perm]].to(torch.int32)
    ends = torch.cumsum(torch.bincount(tile_sorted, minlength=n_tiles), 0)
    ranges = torch.stack([ends - torch.bincount(tile_sorted, minlength=n_tiles), ends], dim=1).to(torch.int32)
    return gids.contiguous(), ranges.contiguous()


@ti.kernel
def pack(
    gids: ti.types.ndarray(),
    box: ti.types.ndarray(),
    mean2d: ti.template(),
    conic: ti.template(),
    opac: ti.template(),
    color: ti.template(),
    depth: ti.template(),
    packed: ti.types.ndarray(),
    pbox: ti.types.ndarray(),
    m: ti.i32,
):
    for k in range(m):
        g = gids[k]
        packed[k, 0] = mean2d[g][0]
        packed[k, 1] = mean2d[g][1]
        for j in ti.static(range(3)):
            packed[k, 2 + j] = conic[g][j]
            packed[k, 6 + j] = color[g][j]
        packed[k, 5] = opac[g]
        packed[k, 9] = depth[g]
        for j in ti.static(range(4)):
            pbox[k, j] = box[g, j]


@ti.kernel
def composite_forward(
    packed: ti.types.ndarray(),
    pbox: ti.types.ndarray(),
    ranges: ti.types.ndarray(),
    background: ti.math.vec3,
    rgb: ti.types.ndarray(),
    T_out: ti.types.ndarray(),
    last: ti.types.ndarray(),
    dacc: ti.types.ndarray(),
    width: ti.i32,
    height: ti.i32,
    tiles_x: ti.i32,
    n_tiles: ti.i32,
    tile: ti.template(),
):
    """Colour ``rgb`` [H, W, 3], final transmittance ``T_out`` [H, W], ``last`` [H, W] (end of the entries each
    pixel used) and weighted depth sum ``dacc`` [H, W]."""
    for t in range(n_tiles):
        tx0 = (t % tiles_x) * tile
        ty0 = (t // tiles_x) * tile
        tx1 = ti.min(tx0 + tile, width) - 1
        ty1 = ti.min(ty0 + tile, height) - 1
        start, end = ranges[t, 0], ranges[t, 1]
        for py, px in ti.ndrange((ty0, ty1 + 1), (tx0, tx1 + 1)):
            T_out[py, px] = 1.0
            last[py, px] = start
            dacc[py, px] = 0.0
            for ch in ti.static(range(3)):
                rgb[py, px, ch] = 0.0
        active = (tx1 - tx0 + 1) * (ty1 - ty0 + 1)
        k = start
        while k < end and active > 0:
            x0, x1 = ti.max(pbox[k, 0], tx0), ti.min(pbox[k, 1], tx1)
            y0, y1 = ti.max(pbox[k, 2], ty0), ti.min(pbox[k, 3], ty1)
            mx, my = packed[k, 0], packed[k, 1]
            a, b, c, o = packed[k, 2], packed[k, 3], packed[k, 4], packed[k, 5]
            for py, px in ti.ndrange((y0, y1 + 1), (x0, x1 + 1)):
                T = T_out[py, px]
                if T > 0:  # done pixels hold -T
                    dx = mx - (px + 0.5)
                    dy = my - (py + 0.5)
                    sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
                    alpha = ti.min(ALPHA_MAX, o * ti.exp(-sigma))
                    if sigma >= 0 and alpha >= ALPHA_MIN:
                        next_T = T * (1.0 - alpha)
                        if next_T <= T_MIN:
                            T_out[py, px] = -T
                            active -= 1
                        else:
                            w = alpha * T
                            for ch in ti.static(range(3)):
                                rgb[py, px, ch] += w * packed[k, 6 + ch]
                            dacc[py, px] += w * packed[k, 9]
                            T_out[py, px] = next_T
                            last[py, px] = k + 1
            k += 1
        for py, px in ti.ndrange((ty0, ty1 + 1), (tx0, tx1 + 1)):
            T = ti.abs(T_out[py, px])
            T_out[py, px] = T
            for ch in ti.static(range(3)):
                rgb[py, px, ch] += T * background[ch]


@ti.kernel
def composite_backward(
    packed: ti.types.ndarray(),
    pbox: ti.types.ndarray(),
    ranges: ti.types.ndarray(),
    background: ti.math.vec3,
    T_final: ti.types.ndarray(),
    last: ti.types.ndarray(),
    v_rgb: ti.types.ndarray(),
    v_alpha: ti.types.ndarray(),
    T_buf: ti.types.ndarray(),
    c_buf: ti.types.ndarray(),
    v_packed: ti.types.ndarray(),
    width: ti.i32,
    height: ti.i32,
    tiles_x: ti.i32,
    n_tiles: ti.i32,
    tile: ti.template(),
):
    """Gradients of every tile entry (``v_packed`` [M, 9]) from ∂L/∂rgb [H, W, 3] and ∂L/∂alpha [H, W].

    With T_i the transmittance before entry i, S_i = Σ_{j>i} c_j α_j T_j + T_N·bg the colour behind it and T_N the
    final transmittance: ∂C/∂c_i = α_i T_i, ∂C/∂α_i = c_i T_i − S_i / (1 − α_i), ∂(1 − T_N)/∂α_i = T_N / (1 − α_i).
    """
    for t in range(n_tiles):
        tx0 = (t % tiles_x) * tile
        ty0 = (t // tiles_x) * tile
        tx1 = ti.min(tx0 + tile, width) - 1
        ty1 = ti.min(ty0 + tile, height) - 1
        start, end = ranges[t, 0], ranges[t, 1]
        for py, px in ti.ndrange((ty0, ty1 + 1), (tx0, tx1 + 1)):
            T_buf[py, px] = T_final[py, px]
            for ch in ti.static(range(3)):
                c_buf[py, px, ch] = T_final[py, px] * background[ch]
        for kk in range(end - start):
            k = end - 1 - kk
            x0, x1 = ti.max(pbox[k, 0], tx0), ti.min(pbox[k, 1], tx1)
            y0, y1 = ti.max(pbox[k, 2], ty0), ti.min(pbox[k, 3], ty1)
            mx, my = packed[k, 0], packed[k, 1]
            a, b, c, o = packed[k, 2], packed[k, 3], packed[k, 4], packed[k, 5]
            col = ti.Vector([packed[k, 6], packed[k, 7], packed[k, 8]])
            g = ti.Vector([0.0] * VPACK)
            for py, px in ti.ndrange((y0, y1 + 1), (x0, x1 + 1)):
                if k < last[py, px]:
                    dx = mx - (px + 0.5)
                    dy = my - (py + 0.5)
                    sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
                    G = ti.exp(-sigma)
                    alpha = ti.min(ALPHA_MAX, o * G)
                    if sigma >= 0 and alpha >= ALPHA_MIN:
                        ra = 1.0 / (1.0 - alpha)
                        T = T_buf[py, px] * ra
                        T_buf[py, px] = T
                        fac = alpha * T
                        v_al = v_alpha[py, px] * T_final[py, px] * ra
                        for ch in ti.static(range(3)):
                            vc = v_rgb[py, px, ch]
                            g[6 + ch] += fac * vc
                            v_al += (col[ch] * T - c_buf[py, px, ch] * ra) * vc
                            c_buf[py, px, ch] += col[ch] * fac
                        if o * G <= ALPHA_MAX:  # clamped alpha has no gradient
                            v_sig = -o * G * v_al
                            g[0] += (a * dx + b * dy) * v_sig
                            g[1] += (b * dx + c * dy) * v_sig
                            g[2] += 0.5 * dx * dx * v_sig
                            g[3] += dx * dy * v_sig
                            g[4] += 0.5 * dy * dy * v_sig
                            g[5] += G * v_al
            for j in ti.static(range(VPACK)):
                v_packed[k, j] = g[j]
