"""Image metrics: PSNR (per image and pooled), SSIM, LPIPS (AlexNet and VGG16), and the report the eval writes.

Published numbers for novel-view synthesis differ mostly by convention (RGB or luma, 'valid' or padded SSIM, mean of
per-image PSNR or PSNR of the pooled MSE), so :func:`image_metrics` names the conventions it used next to the values.
The implementations reproduce the original implementations' values on the IQA-PyTorch calibration pairs
(``tests/data/metrics-calibration``): PSNR on RGB (scikit-image), SSIM on MATLAB ``rgb2gray`` (ssim_index.m), LPIPS
alex v0.1.
"""

from __future__ import annotations

import math

import torch

from causalgs.errors import CausalGSError
from causalgs.metrics.lpips_net import NETS, lpips, lpips_available, lpips_between, lpips_embedding, lpips_network
from causalgs.metrics.pixel import CHANNELS, SSIM_SIGMA, SSIM_WINDOW, _mse, _pairs, psnr, psnr_pooled, ssim, ssim_map

__all__ = [
    "CHANNELS",
    "NETS",
    "PSNR_CAP_DB",
    "image_metrics",
    "lpips",
    "lpips_available",
    "lpips_network",
    "psnr",
    "psnr_pooled",
    "ssim",
    "ssim_map",
]

LPIPS_BATCH = 16  # images whose LPIPS features are computed together (lpips_embedding: batches are 3-6x faster)
# metrics.json is strict JSON (no Infinity): a PSNR of identical images (+inf) is reported as this many dB.
PSNR_CAP_DB = 100.0


def _psnr_db(mse: float) -> float:
    return PSNR_CAP_DB if mse <= 0 else min(PSNR_CAP_DB, -10.0 * math.log10(mse))


def image_metrics(preds, gts, *, lpips_nets=("alex", "vgg")) -> dict:
    """Metrics of predicted images against ground truth, as a JSON-serialisable dict (plain floats).

    ``preds``, ``gts``: sequences of ``[H, W, 3]`` float images (tensors or arrays) in [0, 1], or ``[B, H, W, 3]``
    batches. Keys: ``psnr`` (mean of per-image PSNR), ``psnr_pooled`` (PSNR of the mean per-image MSE), ``ssim``
    (mean of per-image SSIM), ``lpips_alex`` and ``lpips_vgg`` (mean of per-image LPIPS, ``None`` when the weights are
    missing or the net was not asked for; ``lpips_unavailable`` then says why), ``lpips_vgg_unscaled`` (FreeGave's
    convention), ``n_images``, ``per_image`` (the per-image values) and ``conventions``. PSNR and SSIM are computed in
    float64, LPIPS in float32.
    """
    return image_metrics_many({"": preds}, gts, lpips_nets=lpips_nets)[""]


# LPIPS variants scored: (key, net, inputs scaled to [-1, 1])
_LPIPS_KEYS = (("lpips_alex", "alex", True), ("lpips_vgg", "vgg", True), ("lpips_vgg_unscaled", "vgg", False))


def image_metrics_many(preds: dict, gts, *, lpips_nets=("alex", "vgg")) -> dict:
    """:func:`image_metrics` of several predictions of the same ground truth (``preds``: name → images), each
    ground-truth image's LPIPS features computed once for all of them, and predictions identical to an earlier one's
    (two dynamics that render the same states) scored once."""
    nets = tuple(lpips_nets)
    for net in nets:
        if net not in NETS:
            raise CausalGSError(f"unknown LPIPS network {net!r} (expected one of {', '.join(NETS)})")
    pairs = {name: _pairs(images, gts) for name, images in preds.items()}
    same: dict[str, str] = {}  # name → the earlier name whose images are the same, bit for bit
    names = list(pairs)
    for i, name in enumerate(names):
        twin = next((o for o in names[:i] if o not in same and _identical(pairs[o][0], pairs[name][0])), None)
        if twin is not None:
            same[name] = twin
    pairs = {name: v for name, v in pairs.items() if name not in same}
    gts = next(iter(pairs.values()))[1] if pairs else []
    lpips_state = {net: lpips_available(net) if net in nets else (False, "not requested") for net in NETS}
    scored = [(key, net, norm) for key, net, norm in _LPIPS_KEYS if lpips_state[net][0]]
    per = {name: {"psnr": [], "ssim": [], **{key: [] for key, _, _ in scored}} for name in pairs}
    mses: dict[str, list[float]] = {name: [] for name in pairs}
    with torch.no_grad():
        for chunk in _chunks(gts):
            i = chunk[0]  # the image an error names
            try:
                g64 = torch.stack([torch.as_tensor(gts[j]).to(torch.float64) for j in chunk])
                truth = {key: lpips_embedding(g64.float(), net=net, normalize=norm) for key, net, norm in scored}
                for name, (ps, _) in pairs.items():
                    p64 = []
                    for i, g in zip(chunk, g64, strict=True):
                        p = torch.as_tensor(ps[i]).to(torch.float64)
                        mse = float(_mse(p, g, "rgb", 1.0)[0][0])
                        mses[name].append(mse)
                        per[name]["psnr"].append(_psnr_db(mse))
                        per[name]["ssim"].append(float(ssim(p, g)))
                        p64.append(p)
                    i = chunk[0]
                    batch = torch.stack(p64).float()
                    for key, net, norm in scored:
                        e = lpips_embedding(batch, net=net, normalize=norm)
                        per[name][key].extend(lpips_between(e, truth[key], net=net))
            except CausalGSError as e:
                raise CausalGSError(f"image {i}: {e}") from None
    out = {name: _report(per[name], mses[name], lpips_state) for name in pairs}
    return {name: dict(out[same.get(name, name)]) for name in preds}


def _chunks(images: list) -> list[list[int]]:
    """Runs of at most LPIPS_BATCH consecutive indices of images of one shape: a conv net's batch."""
    out: list[list[int]] = []
    for i, img in enumerate(images):
        if out and len(out[-1]) < LPIPS_BATCH and tuple(img.shape) == tuple(images[out[-1][0]].shape):
            out[-1].append(i)
        else:
            out.append([i])
    return out


def _identical(a: list, b: list) -> bool:
    """Whether two lists of images are the same, bit for bit."""
    if len(a) != len(b):
        return False
    return all(torch.equal(torch.as_tensor(x), torch.as_tensor(y)) for x, y in zip(a, b, strict=True))


def _report(per: dict[str, list[float]], mses: list[float], lpips_state: dict) -> dict:
    def mean(values: list[float]) -> float:
        return math.fsum(values) / len(values)

    out = {
        "psnr": mean(per["psnr"]),
        "psnr_pooled": _psnr_db(mean(mses)),
        "ssim": mean(per["ssim"]),
    }
    for net in NETS:
        out[f"lpips_{net}"] = mean(per[f"lpips_{net}"]) if lpips_state[net][0] else None
    out["lpips_vgg_unscaled"] = mean(per["lpips_vgg_unscaled"]) if lpips_state["vgg"][0] else None
    unavailable = {f"lpips_{net}": why for net, (ok, why) in lpips_state.items() if not ok}
    if unavailable:
        out["lpips_unavailable"] = unavailable
    out["n_images"] = len(mses)
    out["per_image"] = per
    out["conventions"] = {
        "images": "RGB, float values in [0, 1] (data range 1.0)",
        "psnr": f"10 log10(1 / MSE) over RGB pixels of each image, then averaged; capped at {PSNR_CAP_DB:g} dB "
        "(identical images)",
        "psnr_pooled": "10 log10(1 / mean of the per-image RGB MSEs)",
        "ssim": f"RGB channels averaged, {SSIM_WINDOW}x{SSIM_WINDOW} Gaussian window sigma {SSIM_SIGMA}, K1 0.01, "
        "K2 0.03, 'valid' filtering (no padding), no downsampling, mean over images",
        "lpips": "v0.1 linear heads, inputs scaled to [-1, 1], mean over images; weights: "
        + "; ".join(f"{net}: {why}" for net, (ok, why) in lpips_state.items() if ok),
        "lpips_vgg_unscaled": "LPIPS VGG on the [0, 1] images fed unscaled (as FreeGave's metrics.py computes it)",
        "freegave": "psnr (mean of per-image PSNR), ssim, lpips_vgg_unscaled",
        "nvfi": "psnr_pooled (PSNR of the pooled MSE), ssim, lpips_alex and lpips_vgg (inputs scaled to [-1, 1])",
    }
    return out
