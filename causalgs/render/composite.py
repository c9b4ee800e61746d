"""Tile binning (torch) and front-to-back alpha compositing (Taichi), forward and hand-written backward.

Design, for the CPU backend (no block shared memory, and Taichi's autodiff cannot handle the compositing loop):
- Binning: every Gaussian's exact pixel box (project.bounds) is cut into 16×16 tiles; tile counts and a prefix sum
  give each tile's slots, and a serial pass over the depth-sorted Gaussians fills them, so every list is
  depth-ordered. The projected data of every entry is packed into its slot, so the compositing loops stream it.
- Compositing runs one tile per thread and is *entry-major*: for each Gaussian of the tile's list, only the pixels of
  its own box (clipped to the tile) are visited, instead of every pixel against every entry. Pixels that reach the
  transmittance floor are marked done (negative T); a tile stops when all its pixels are done.
- Per-pixel state lives in plain arrays owned by the tile's thread and is updated with `x = x + v`, never `x += v`:
  Taichi turns augmented assignment to global memory into an atomic add, which cost a third of the forward time.
- The backward walks each tile's list in reverse, recovering T_i from the final T by division by (1 − α_i), and
  sums each entry's gradient over its pixels in registers: a tile's entries belong to one thread, so no atomics.
"""

# No `from __future__ import annotations`: Taichi 1.7 reads kernel annotations as live objects.
import torch

from causalgs import _ti
from causalgs._ti import ti
from causalgs.render.reference import ALPHA_MAX, ALPHA_MIN, T_MIN

TILE = 16
PACK = 11  # mx, my, conic a, b, c, opacity, r, g, b, depth, σ bound ln(255·opacity)
VPACK = 9  # gradients of mx, my, a, b, c, opacity, r, g, b


@ti.func
def _tile_rect(t, tiles_x, tile: ti.template(), width, height):
    """Inclusive pixel bounds (x0, y0, x1, y1) of tile ``t`` (row-major tiles), clipped to the image."""
    tx0 = (t % tiles_x) * tile
    ty0 = (t // tiles_x) * tile
    return tx0, ty0, ti.min(tx0 + tile, width) - 1, ti.min(ty0 + tile, height) - 1


@ti.func
def _row_span(mx, a, b, c, smax, dy, x0, x1):
    """Pixels [lo, hi] of row offset ``dy`` where σ = ½(a dx² + 2b dx dy + c dy²) ≤ ``smax``, within [x0, x1].

    Solving the quadratic in dx = mx − (px + 0.5) per row visits only the ellipse, not its bounding box (whose
    corners are ≥ 21% of its area, far more for thin rotated splats). ``smax`` carries the same safety margin as
    project.bounds, so no pixel the reference draws is skipped; the alpha test itself stays exact in the loop.
    """
    lo, hi = x0, x1
    disc = b * b * dy * dy - a * (c * dy * dy - 2.0 * smax)
    if disc < 0:
        lo, hi = 1, 0
    else:
        r = ti.sqrt(disc)
        dx_lo = (-b * dy - r) / a
        dx_hi = (-b * dy + r) / a
        lo = ti.max(x0, ti.cast(ti.max(ti.ceil(mx - dx_hi - 0.5), -1.0), ti.i32))
        hi = ti.min(x1, ti.cast(ti.min(ti.floor(mx - dx_lo - 0.5), 1e9), ti.i32))
    return lo, hi


@ti.func
def _row_exp(mx, a, b, c, dy, lo):
    """exp(−σ) at pixel ``lo`` of a row, and the ratio to the next pixel.

    Along a row σ is quadratic in px, so exp(−σ) follows G ← G·R, R ← R·e^(−a): two exps per row instead of one per
    pixel (the exp was most of the compositing time). The ratio stays below e^6 inside the ellipse because the 0.3 px²
    dilation bounds a by 1/0.3, and the recurrence's rounding (a few ulps per pixel) is far below the tests' 1e-10.
    """
    dx = mx - (lo + 0.5)
    sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
    return ti.exp(-sigma), ti.exp(a * dx + b * dy - 0.5 * a)


@ti.kernel
def count_tiles(box: ti.types.ndarray(), counts: ti.types.ndarray(), n: ti.i32, tiles_x: ti.i32, tile: ti.template()):
    """Number of Gaussians whose pixel box touches each tile (``counts`` [T] zeroed by the caller)."""
    for i in range(n):
        if box[i, 0] <= box[i, 1] and box[i, 2] <= box[i, 3]:
            for ty in range(box[i, 2] // tile, box[i, 3] // tile + 1):
                for tx in range(box[i, 0] // tile, box[i, 1] // tile + 1):
                    ti.atomic_add(counts[ty * tiles_x + tx], 1)


@ti.kernel
def fill_tiles(
    order: ti.types.ndarray(),
    box: ti.types.ndarray(),
    cursor: ti.types.ndarray(),
    mean2d: ti.template(),
    conic: ti.template(),
    opac: ti.template(),
    color: ti.template(),
    depth: ti.template(),
    gids: ti.types.ndarray(),
    packed: ti.types.ndarray(),
    pbox: ti.types.ndarray(),
    n: ti.i32,
    tiles_x: ti.i32,
    tile: ti.template(),
):
    """Append every Gaussian, in depth ``order``, to the lists of the tiles it touches (``cursor`` [T] starts at each
    tile's first slot), writing its packed data there. Serial, so that every tile list stays depth-sorted; it costs
    a fraction of a millisecond at 10k Gaussians."""
    ti.loop_config(serialize=True)
    for j in range(n):
        g = order[j]
        if box[g, 0] <= box[g, 1] and box[g, 2] <= box[g, 3]:
            m2, co, col = mean2d[g], conic[g], color[g]
            o = opac[g]
            smax = ti.log(255.0 * ti.max(o, ALPHA_MIN)) * (1.0 + 1e-4) + 1e-6
            for ty in range(box[g, 2] // tile, box[g, 3] // tile + 1):
                for tx in range(box[g, 0] // tile, box[g, 1] // tile + 1):
                    t = ty * tiles_x + tx
                    k = cursor[t]
                    cursor[t] = k + 1
                    gids[k] = g
                    packed[k, 0], packed[k, 1] = m2[0], m2[1]
                    packed[k, 2], packed[k, 3], packed[k, 4] = co[0], co[1], co[2]
                    packed[k, 5] = o
                    packed[k, 6], packed[k, 7], packed[k, 8] = col[0], col[1], col[2]
                    packed[k, 9] = depth[g]
                    packed[k, 10] = smax
                    for c in ti.static(range(4)):
                        pbox[k, c] = box[g, c]


def bin_and_pack(store, box: torch.Tensor, width: int, height: int, tile: int = TILE):
    """Tile lists of the projected Gaussians of ``store`` from their pixel boxes ``box`` [N, 4] int32.

    Returns ``gids`` [M] int32 (the Gaussian of every entry, by tile then depth), ``ranges`` [T, 2] int32 (each
    tile's [start, end) in the lists, row-major tiles), ``packed`` [M, PACK] and ``pbox`` [M, 4] (entry data).
    """
    n = store.n
    tiles_x = (width + tile - 1) // tile
    n_tiles = tiles_x * ((height + tile - 1) // tile)
    counts = torch.zeros(n_tiles, dtype=torch.int32)
    if n:
        count_tiles(box, counts, n, tiles_x, tile)
    ends = torch.cumsum(counts, 0, dtype=torch.int32)
    starts = ends - counts
    m = int(ends[-1]) if n_tiles else 0
    dt = _ti.torch_dtype()
    gids = torch.empty(m, dtype=torch.int32)
    packed = torch.empty((m, PACK), dtype=dt)
    pbox = torch.empty((m, 4), dtype=torch.int32)
    if m:
        order = torch.argsort(store.to_torch("depth"), stable=True).to(torch.int32)
        s = store
        fill_tiles(order, box, starts.clone(), s.mean2d, s.conic, s.opac, s.color, s.depth, gids, packed, pbox, n,
                   tiles_x, tile)  # fmt: skip
    return gids, torch.stack([starts, ends], dim=1).contiguous(), packed, pbox


@ti.kernel
def scatter_grads(
    gids: ti.types.ndarray(),
    v_packed: ti.types.ndarray(),
    mean2d: ti.template(),
    conic: ti.template(),
    opac: ti.template(),
    color: ti.template(),
    m: ti.i32,
):
    """Sum the entries' gradients into the Gaussians' adjoint fields (cleared by the caller)."""
    for k in range(m):
        g = gids[k]
        mean2d.grad[g] += ti.Vector([v_packed[k, 0], v_packed[k, 1]])
        conic.grad[g] += ti.Vector([v_packed[k, 2], v_packed[k, 3], v_packed[k, 4]])
        opac.grad[g] += v_packed[k, 5]
        color.grad[g] += ti.Vector([v_packed[k, 6], v_packed[k, 7], v_packed[k, 8]])


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
    ti.loop_config(block_dim=4)  # tiles differ widely in cost: hand them out one at a time
    for t in range(n_tiles):
        tx0, ty0, tx1, ty1 = _tile_rect(t, tiles_x, tile, width, height)
        start, end = ranges[t, 0], ranges[t, 1]
        for py in range(ty0, ty1 + 1):
            for px in range(tx0, tx1 + 1):
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
            col = ti.Vector([packed[k, 6], packed[k, 7], packed[k, 8]])
            z, smax = packed[k, 9], packed[k, 10]
            q = ti.exp(-a)
            for py in range(y0, y1 + 1):
                dy = my - (py + 0.5)
                lo, hi = _row_span(mx, a, b, c, smax, dy, x0, x1)
                G, R = _row_exp(mx, a, b, c, dy, lo)
                for px in range(lo, hi + 1):
                    T = T_out[py, px]
                    dx = mx - (px + 0.5)
                    sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
                    alpha = ti.min(ALPHA_MAX, o * G)
                    G *= R
                    R *= q
                    if T > 0:  # done pixels hold -T
                        if sigma >= 0 and alpha >= ALPHA_MIN:
                            next_T = T * (1.0 - alpha)
                            if next_T <= T_MIN:
                                T_out[py, px] = -T
                                active -= 1
                            else:
                                w = alpha * T
                                for ch in ti.static(range(3)):
                                    rgb[py, px, ch] = rgb[py, px, ch] + w * col[ch]
                                dacc[py, px] = dacc[py, px] + w * z
                                T_out[py, px] = next_T
                                last[py, px] = k + 1
            k += 1
        for py in range(ty0, ty1 + 1):
            for px in range(tx0, tx1 + 1):
                T = ti.abs(T_out[py, px])
                T_out[py, px] = T
                for ch in ti.static(range(3)):
                    rgb[py, px, ch] = rgb[py, px, ch] + T * background[ch]


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
    ti.loop_config(block_dim=4)
    for t in range(n_tiles):
        tx0, ty0, tx1, ty1 = _tile_rect(t, tiles_x, tile, width, height)
        start, end = ranges[t, 0], ranges[t, 1]
        for py in range(ty0, ty1 + 1):
            for px in range(tx0, tx1 + 1):
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
            smax = packed[k, 10]
            q = ti.exp(-a)
            g = ti.Vector([0.0] * VPACK)
            for py in range(y0, y1 + 1):
                dy = my - (py + 0.5)
                lo, hi = _row_span(mx, a, b, c, smax, dy, x0, x1)
                G_next, R = _row_exp(mx, a, b, c, dy, lo)
                for px in range(lo, hi + 1):
                    G = G_next
                    G_next *= R
                    R *= q
                    if k < last[py, px]:
                        dx = mx - (px + 0.5)
                        sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
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
                                c_buf[py, px, ch] = c_buf[py, px, ch] + col[ch] * fac
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
