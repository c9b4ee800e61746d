"""PSNR and SSIM in torch, with the conventions of the original implementations made explicit.

Images are ``[H, W, 3]`` or ``[B, H, W, 3]`` float tensors or arrays with values in ``[0, data_range]``. Three channel
conventions are offered, because published numbers differ mostly by which one they use:

- ``"rgb"``: the three channels as they are (scikit-image ``peak_signal_noise_ratio``, 3DGS/NeRF evaluation code).
- ``"y"``: luma of YCbCr, ITU-R BT.601 as in MATLAB ``rgb2ycbcr`` on 8-bit images, Y = 16 + 65.481 R + 128.553 G +
  24.966 B (R, G, B in [0, 1]), rounded to integers with a peak of 255 (super-resolution papers, BasicSR, pyiqa).
- ``"gray"``: MATLAB ``rgb2gray`` on 8-bit images (the first row of the inverse NTSC matrix, ≈ 0.2989 R + 0.5870 G
  + 0.1140 B), rounded to integers, peak 255. This is how the IQA-PyTorch calibration fed the original SSIM MATLAB
  script (``ResultsCalibra.md``, note 2), and the only one of the three that reproduces its SSIM values.

The rounding in ``"y"`` and ``"gray"`` mirrors MATLAB converting uint8 images to uint8; it is applied with a
straight-through gradient (the value is rounded, the gradient is that of the unrounded value) as pyiqa does, so those
modes stay usable in a loss, though only ``"rgb"`` is smooth enough for finite-difference gradient checks.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
import torch.nn.functional as F

from causalgs.errors import CausalGSError

CHANNELS = ("rgb", "y", "gray")

# SSIM constants of Wang et al. 2004 and their ssim_index.m: fspecial('gaussian', 11, 1.5), K = [0.01 0.03].
SSIM_WINDOW = 11
SSIM_SIGMA = 1.5
SSIM_K1 = 0.01
SSIM_K2 = 0.03

# MATLAB rgb2gray: the first row of inv([1 0.956 0.621; 1 -0.272 -0.647; 1 -1.106 1.703]), printed by MATLAB to 15
# digits. The rounded 0.299/0.587/0.114 give the same 8-bit values almost everywhere, but not everywhere.
_GRAY = (0.298936021293776, 0.587043074451121, 0.114020904255103)
# MATLAB rgb2ycbcr, Y row, for R, G, B in [0, 1] and Y in 8-bit range [16, 235].
_Y_OFFSET = 16.0
_Y = (65.481, 128.553, 24.966)


def as_images(x, what: str) -> torch.Tensor:
    """``x`` as a float tensor ``[B, H, W, 3]`` (numpy arrays are wrapped without a copy)."""
    if isinstance(x, np.ndarray):
        # torch.from_numpy refuses negative strides (e.g. img[..., ::-1], BGR → RGB) and warns on read-only arrays.
        x = torch.from_numpy(x if x.flags.writeable and min(x.strides, default=0) >= 0 else x.copy())
    if not isinstance(x, torch.Tensor):
        raise CausalGSError(f"{what}: expected a torch tensor or numpy array, got {type(x).__name__}")
    if not x.is_floating_point():
        raise CausalGSError(f"{what}: expected float values in [0, data_range], got dtype {x.dtype}")
    if x.ndim == 3:
        x = x[None]
    if x.ndim != 4 or x.shape[-1] != 3:
        raise CausalGSError(f"{what}: expected shape [H, W, 3] or [B, H, W, 3], got {list(x.shape)}")
    return x


def image_pair(pred, gt) -> tuple[torch.Tensor, torch.Tensor]:
    """``pred`` and ``gt`` as ``[B, H, W, 3]`` tensors of one shape, one dtype (the wider) and ``pred``'s device."""
    p, g = as_images(pred, "pred"), as_images(gt, "gt")
    if p.shape != g.shape:
        raise CausalGSError(f"pred and gt differ in shape: {list(p.shape)} vs {list(g.shape)}")
    dtype = torch.promote_types(p.dtype, g.dtype)
    return p.to(dtype), g.to(device=p.device, dtype=dtype)


def _check_channel(channel: str) -> None:
    if channel not in CHANNELS:
        raise CausalGSError(f"unknown channel mode {channel!r} (expected one of {', '.join(CHANNELS)})")


def _round_half_up(v: torch.Tensor) -> torch.Tensor:
    """MATLAB's uint8 conversion (round half away from zero; values here are >= 0), straight-through gradient."""
    return v + (torch.floor(v + 0.5) - v).detach()


def to_channels(x: torch.Tensor, channel: str, data_range: float) -> tuple[torch.Tensor, float]:
    """``[B, H, W, 3]`` images → ``([B, C, H, W], peak)`` in the convention of ``channel`` (see the module notes)."""
    _check_channel(channel)
    if channel == "rgb":
        return x.permute(0, 3, 1, 2), float(data_range)
    # The 8-bit conversions run in float64 so that float32 inputs round to the same integers as float64 ones.
    x64 = x.to(torch.float64) / data_range
    if channel == "y":
        v = _Y_OFFSET + x64 @ x64.new_tensor(_Y)
    else:
        v = (x64 * 255.0) @ x64.new_tensor(_GRAY)
    return _round_half_up(v).to(x.dtype)[:, None], 255.0


def _mse(pred, gt, channel: str, data_range: float) -> tuple[torch.Tensor, float]:
    """Per-image mean squared error ``[B]`` (float64) in the convention of ``channel``, and the peak value."""
    p, g = image_pair(pred, gt)
    pc, peak = to_channels(p, channel, data_range)
    gc, _ = to_channels(g, channel, data_range)
    d = pc.to(torch.float64) - gc.to(torch.float64)
    return (d * d).mean(dim=(1, 2, 3)), peak


def _psnr_from_mse(mse: torch.Tensor, peak: float) -> torch.Tensor:
    # mse == 0 gives +inf (log10(inf)), which is the true value; callers that need a finite number cap it.
    return 10.0 * torch.log10(peak**2 / mse)


def psnr(pred, gt, *, channel: str = "rgb", data_range: float = 1.0) -> torch.Tensor:
    """Peak signal-to-noise ratio in dB of each image: a float64 tensor ``[]`` for ``[H, W, 3]`` inputs, ``[B]`` for
    ``[B, H, W, 3]``.

    PSNR = 10 log10(peak² / MSE), the MSE over all pixels and channels of one image (as scikit-image does). Identical
    images give ``+inf`` (not capped here; :func:`causalgs.metrics.image_metrics` caps its JSON report). ``channel``:
    ``"rgb"`` (peak ``data_range``), ``"y"`` or ``"gray"`` (8-bit, peak 255), see the module notes.
    """
    single = _ndim(pred) == 3
    mse, peak = _mse(pred, gt, channel, data_range)
    out = _psnr_from_mse(mse, peak)
    return out[0] if single else out


def psnr_pooled(preds, gts, *, channel: str = "rgb", data_range: float = 1.0) -> torch.Tensor:
    """PSNR of the mean of the per-image MSEs over a set of images (a float64 scalar tensor).

    This is not the mean of the per-image PSNRs: the logarithm makes that mean favour the easy images (one perfect
    frame alone can make it infinite), while the pooled value is dominated by the worst ones. Both are reported,
    and papers differ in which they print. ``preds``/``gts``: sequences of ``[H, W, 3]`` images (sizes may differ
    between pairs; every image weighs the same) or ``[B, H, W, 3]`` batches.
    """
    preds, gts = _pairs(preds, gts)
    mses = []
    peak = 1.0
    for p, g in zip(preds, gts, strict=True):
        m, peak = _mse(p, g, channel, data_range)
        mses.append(m)
    return _psnr_from_mse(torch.cat(mses).mean(), peak)


def _ndim(x) -> int:
    return x.ndim if isinstance(x, (np.ndarray, torch.Tensor)) else -1


def _pairs(preds, gts) -> tuple[Sequence, Sequence]:
    """Sequences of images (or batches) → two lists of equal, non-zero length."""
    if _ndim(preds) == 4:
        preds = list(preds)
    if _ndim(gts) == 4:
        gts = list(gts)
    if _ndim(preds) == 3 or _ndim(gts) == 3:
        raise CausalGSError("expected sequences of images or [B, H, W, 3] batches, got a single image")
    preds, gts = list(preds), list(gts)
    if len(preds) != len(gts):
        raise CausalGSError(f"{len(preds)} predicted images but {len(gts)} ground-truth images")
    if not preds:
        raise CausalGSError("no images to evaluate")
    return preds, gts


def _gaussian_1d(dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """MATLAB fspecial('gaussian', 11, 1.5) is the outer product of this normalised 1D window with itself."""
    r = torch.arange(SSIM_WINDOW, dtype=torch.float64) - (SSIM_WINDOW - 1) / 2
    g = torch.exp(-(r * r) / (2 * SSIM_SIGMA**2))
    return (g / g.sum()).to(dtype=dtype, device=device)


def _filter_valid(x: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    """Separable Gaussian filter of ``[N, 1, H, W]`` with MATLAB filter2(..., 'valid') extent: ``[N, 1, H-10, W-10]``.

    'valid' (no padding) is what ssim_index.m and scikit-image's SSIM average over; with 'same' padding the border
    pixels see a reflected or zero image and the calibration values are not reproduced.
    """
    x = F.conv2d(x, g.view(1, 1, 1, -1))
    return F.conv2d(x, g.view(1, 1, -1, 1))


def ssim_map(pred, gt, *, channel: str = "rgb", data_range: float = 1.0) -> torch.Tensor:
    """The SSIM map ``[B, C, H-10, W-10]`` (C = 3 for ``"rgb"``, 1 otherwise); :func:`ssim` is its mean."""
    p, g = image_pair(pred, gt)
    h, w = p.shape[1:3]
    if min(h, w) < SSIM_WINDOW:
        raise CausalGSError(f"SSIM needs images of at least {SSIM_WINDOW}×{SSIM_WINDOW} pixels, got {h}×{w}")
    pc, peak = to_channels(p, channel, data_range)
    gc, _ = to_channels(g, channel, data_range)
    b, c = pc.shape[:2]
    x = pc.reshape(b * c, 1, h, w)
    y = gc.reshape(b * c, 1, h, w)
    win = _gaussian_1d(x.dtype, x.device)
    c1 = (SSIM_K1 * peak) ** 2
    c2 = (SSIM_K2 * peak) ** 2
    # One convolution call for the five filtered images.
    stats = _filter_valid(torch.cat([x, y, x * x, y * y, x * y]), win).split(b * c)
    mu_x, mu_y, xx, yy, xy = stats
    mu_xx, mu_yy, mu_xy = mu_x * mu_x, mu_y * mu_y, mu_x * mu_y
    s_xx, s_yy, s_xy = xx - mu_xx, yy - mu_yy, xy - mu_xy
    num = (2 * mu_xy + c1) * (2 * s_xy + c2)
    den = (mu_xx + mu_yy + c1) * (s_xx + s_yy + c2)
    return (num / den).reshape(b, c, h - SSIM_WINDOW + 1, w - SSIM_WINDOW + 1)


def ssim(pred, gt, *, channel: str = "rgb", data_range: float = 1.0) -> torch.Tensor:
    """Mean structural similarity (Wang et al. 2004) as a scalar tensor in the inputs' dtype; differentiable.

    11×11 Gaussian window with sigma 1.5, K1 = 0.01, K2 = 0.03, 'valid' filtering (no padding) as in the authors'
    ssim_index.m without its downsampling of images larger than 256 pixels, averaged over the window positions, the
    channels and the batch. ``1 - ssim(render, target)`` is the D-SSIM training loss; use ``channel="rgb"`` there.
    """
    return ssim_map(pred, gt, channel=channel, data_range=data_range).mean()
