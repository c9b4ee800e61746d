"""Dense plain-torch reference of the rasterizer's maths: every Gaussian against every pixel.

Used only by tests and the benchmark, to hold the Taichi kernels to the same numbers forward and backward (torch
autograd differentiates this file). It follows gsplat's conventions, as the kernels do:

- covariance Σ = R S Sᵀ Rᵀ with R from the normalised quaternion (w, x, y, z) and S = diag(exp(scale_raw));
- EWA projection with the perspective Jacobian evaluated at a position clamped to 1.3× the field of view (so far
  off-screen Gaussians do not blow up), plus a 0.3 px² low-pass dilation;
- Gaussians closer than ``NEAR`` to the camera plane are dropped;
- colour = SH(view direction) + 0.5, clamped at 0;
- alpha = min(0.99, opacity · exp(−σ)), σ = ½ dᵀ Σ₂D⁻¹ d with d = mean2d − pixel centre (centres at +0.5);
  alpha < 1/255 is skipped; compositing front to back stops *before* a Gaussian that would bring the transmittance
  to ≤ 1e-4.
"""

from __future__ import annotations

import torch

from causalgs.render.sh import eval_sh_torch

NEAR = 0.01
EPS2D = 0.3
ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.99
T_MIN = 1e-4


def quat_scale_to_cov(quats: torch.Tensor, scales: torch.Tensor) -> torch.Tensor:
    """Covariances [N, 3, 3] from quaternions [N, 4] (w, x, y, z; any norm) and scales [N, 3] (activated)."""
    w, x, y, z = (quats / quats.norm(dim=-1, keepdim=True)).unbind(-1)
    R = torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(-1, 3, 3)  # fmt: skip
    M = R * scales[:, None, :]
    return M @ M.transpose(1, 2)


def project(means, covs, viewmat, K, width: int, height: int):
    """EWA projection. Returns mean2d [N, 2], cov2d [N, 2, 2] (dilated), depth [N] and a validity mask [N]."""
    R, t = viewmat[:3, :3], viewmat[:3, 3]
    p = means @ R.T + t
    cov_c = R @ covs @ R.T
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    x, y, z = p.unbind(-1)
    valid = z > NEAR
    zs = torch.where(valid, z, torch.ones_like(z))
    tan_x, tan_y = 0.5 * width / fx, 0.5 * height / fy
    tx = zs * torch.clamp(x / zs, -(cx / fx + 0.3 * tan_x), (width - cx) / fx + 0.3 * tan_x)
    ty = zs * torch.clamp(y / zs, -(cy / fy + 0.3 * tan_y), (height - cy) / fy + 0.3 * tan_y)
    zero = torch.zeros_like(zs)
    J = torch.stack([fx / zs, zero, -fx * tx / zs**2, zero, fy / zs, -fy * ty / zs**2], dim=-1).reshape(-1, 2, 3)
    cov2d = J @ cov_c @ J.transpose(1, 2) + EPS2D * torch.eye(2, dtype=means.dtype)
    mean2d = torch.stack([fx * x / zs + cx, fy * y / zs + cy], dim=-1)
    det = cov2d[:, 0, 0] * cov2d[:, 1, 1] - cov2d[:, 0, 1] ** 2
    return mean2d, cov2d, z, valid & (det > 0)


def _composite(pix, mean2d, conic, opac, colors, depth, background):
    """Front-to-back compositing of depth-sorted splats at pixel centres ``pix`` [P, 2]: colour, alpha, Σ w·depth."""
    dx = mean2d[:, 0][None, :] - pix[:, :1]  # [P, M]
    dy = mean2d[:, 1][None, :] - pix[:, 1:]
    sigma = 0.5 * (conic[:, 0] * dx * dx + conic[:, 2] * dy * dy) + conic[:, 1] * dx * dy
    alpha = torch.clamp(opac * torch.exp(-sigma), max=ALPHA_MAX)
    alpha = torch.where((alpha >= ALPHA_MIN) & (sigma >= 0), alpha, torch.zeros_like(alpha))
    one_minus = 1.0 - alpha
    T = torch.cumprod(torch.cat([torch.ones_like(alpha[:, :1]), one_minus[:, :-1]], dim=1), dim=1)
    included = (T * one_minus > T_MIN).detach()  # non-increasing along depth: a prefix, as in the kernel's loop
    w = alpha * T * included
    T_final = 1.0 - w.sum(dim=1)
    return w @ colors + T_final[:, None] * background[None, :], 1.0 - T_final, w @ depth


def rasterize_reference(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales_raw: torch.Tensor,
    opacities_raw: torch.Tensor,
    sh: torch.Tensor,
    viewmat: torch.Tensor,
    K: torch.Tensor,
    width: int,
    height: int,
    background: torch.Tensor,
    sh_degree: int = 3,
    covs: torch.Tensor | None = None,
    means2d_probe: torch.Tensor | None = None,
    chunk: int | None = None,
):
    """Render [H, W, 3] colour, [H, W] alpha and [H, W] expected depth by brute force (memory O(H·W·N)).

    Arguments have the shapes of :func:`causalgs.render.rasterize`; ``covs`` [N, 3, 3] replaces quats and scales.
    ``means2d_probe`` [N, 2] (zeros) is added to the projected means, so its gradient is ∂L/∂mean2d.
    ``chunk``: pixels per chunk (checkpointed under autograd), to fit large images in memory.
    """
    if covs is None:
        covs = quat_scale_to_cov(quats, torch.exp(scales_raw))
    mean2d, cov2d, depth, valid = project(means, covs, viewmat, K, width, height)
    if means2d_probe is not None:
        mean2d = mean2d + means2d_probe
    campos = torch.linalg.inv(viewmat)[:3, 3]
    colors = torch.clamp(eval_sh_torch(sh, means - campos, sh_degree) + 0.5, min=0.0)
    opac = torch.sigmoid(opacities_raw)

    idx = torch.nonzero(valid).flatten()
    idx = idx[torch.argsort(depth[idx], stable=True)]
    a, b, c = cov2d[idx, 0, 0], cov2d[idx, 0, 1], cov2d[idx, 1, 1]
    det = a * c - b * b
    conic = torch.stack([c / det, -b / det, a / det], dim=-1)  # [M, 3]

    v, u = torch.meshgrid(
        torch.arange(height, dtype=means.dtype) + 0.5, torch.arange(width, dtype=means.dtype) + 0.5, indexing="ij"
    )
    pix = torch.stack([u.reshape(-1), v.reshape(-1)], dim=1)
    args = (mean2d[idx], conic, opac[idx], colors[idx], depth[idx], background)
    if chunk is None or chunk >= len(pix):
        rgb, acc, d_acc = _composite(pix, *args)
    else:
        # Pixel chunks bound the [P, M] working set; under autograd each chunk is recomputed in the backward.
        from torch.utils.checkpoint import checkpoint

        parts = [
            checkpoint(_composite, pix[i : i + chunk], *args, use_reentrant=False)
            if torch.is_grad_enabled()
            else _composite(pix[i : i + chunk], *args)
            for i in range(0, len(pix), chunk)
        ]
        rgb, acc, d_acc = (torch.cat(t) for t in zip(*parts, strict=True))
    exp_depth = torch.where(acc > 0, d_acc / torch.clamp(acc, min=1e-12), torch.zeros_like(acc))
    return rgb.reshape(height, width, 3), acc.reshape(height, width), exp_depth.reshape(height, width)


def bin_gaussians(box: torch.Tensor, depth: torch.Tensor, width: int, height: int, tile: int = 16):
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
