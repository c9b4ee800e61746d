"""The Taichi rasterizer against the dense torch reference (forward and backward) and float64 finite differences."""

from __future__ import annotations

import math

import pytest
import torch

from causalgs.cameras import Camera, look_at
from causalgs.errors import CausalGSError
from causalgs.render import rasterize
from causalgs.render.reference import quat_scale_to_cov, rasterize_reference

W, H = 40, 32
BG = (0.1, 0.2, 0.3)


def _camera() -> Camera:
    return Camera.from_blender(look_at([0.0, -4.0, 1.0], [0.0, 0.0, 0.0]), W, H, fov_x=0.9)


def _scene(n: int, seed: int, n_sh: int = 16, dtype=torch.float64) -> dict[str, torch.Tensor]:
    """Random overlapping Gaussians around the origin, plus some behind the camera and some far off-screen."""
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g, dtype=dtype) - 0.5) * 2.0
    if n >= 8:
        means[0] = torch.tensor([0.0, -6.0, 1.0])  # behind the camera (which sits at y = -4 looking at +y)
        means[1] = torch.tensor([0.0, -4.0, 1.0])  # at the camera centre
        means[2] = torch.tensor([9.0, 0.0, 0.0])  # far off-screen to the right
        means[3] = torch.tensor([0.0, 0.0, -7.0])  # far off-screen below
    return {
        "means": means,
        "quats": torch.randn(n, 4, generator=g, dtype=dtype),
        "scales": torch.log(torch.rand(n, 3, generator=g, dtype=dtype) * 0.25 + 0.03),
        "opacities": torch.randn(n, generator=g, dtype=dtype) + 0.5,
        "sh": torch.randn(n, n_sh, 3, generator=g, dtype=dtype) * 0.3,
    }


def _render(p, cam, covs=None):
    return rasterize(
        p["means"], p.get("quats"), p.get("scales"), p["opacities"], p["sh"], torch.tensor(cam.viewmat),
        torch.tensor(cam.K), cam.width, cam.height, background=BG, covs=covs,
    )  # fmt: skip


def _reference(p, cam, covs=None, probe=None):
    n_sh = p["sh"].shape[1]
    return rasterize_reference(
        p["means"], p.get("quats"), p.get("scales"), p["opacities"], p["sh"], torch.tensor(cam.viewmat),
        torch.tensor(cam.K), cam.width, cam.height, torch.tensor(BG, dtype=torch.float64),
        sh_degree=math.isqrt(n_sh) - 1, covs=covs, means2d_probe=probe,
    )  # fmt: skip


@pytest.mark.parametrize(("n", "n_sh", "seed"), [(60, 16, 0), (200, 16, 1), (40, 1, 2), (30, 4, 3), (25, 9, 4)])
def test_forward_matches_reference(ti64, n, n_sh, seed):
    p, cam = _scene(n, seed, n_sh), _camera()
    img, alpha, meta = _render(p, cam)
    ref_img, ref_alpha, ref_depth = _reference(p, cam)
    assert img.shape == (H, W, 3) and alpha.shape == (H, W)
    assert (alpha > 0.05).float().mean() > 0.2, "the scene should cover the image"
    torch.testing.assert_close(img, ref_img, atol=1e-10, rtol=0)
    torch.testing.assert_close(alpha, ref_alpha, atol=1e-10, rtol=0)
    torch.testing.assert_close(meta["depth"], ref_depth, atol=1e-9, rtol=0)
    if n >= 8:
        assert (meta["radii"][:4] == 0).all(), "behind-camera and off-screen Gaussians draw nothing"


def test_empty_and_culled_scenes_show_the_background(ti64):
    p = _scene(8, 5)
    p["means"][:] = torch.tensor([0.0, -6.0, 1.0])  # everything behind the camera
    img, alpha, meta = _render(p, _camera())
    torch.testing.assert_close(img, torch.tensor(BG, dtype=torch.float64).expand(H, W, 3))
    assert alpha.abs().max() == 0 and meta["n_isect"] == 0


def _loss_weights(seed: int):
    g = torch.Generator().manual_seed(seed)
    return torch.randn(H, W, 3, generator=g, dtype=torch.float64), torch.randn(H, W, generator=g, dtype=torch.float64)


@pytest.mark.parametrize("use_cov", [False, True])
def test_gradients_match_reference(ti64, use_cov):
    p, cam = _scene(50, 7), _camera()
    covs = None
    if use_cov:
        covs = quat_scale_to_cov(p.pop("quats"), torch.exp(p.pop("scales"))).detach()
        covs = covs + 0.002 * torch.eye(3, dtype=torch.float64)  # a generic (non scale/quat) covariance
        covs.requires_grad_(True)
    for t in p.values():
        t.requires_grad_(True)
    w_rgb, w_a = _loss_weights(11)
    img, alpha, meta = _render(p, cam, covs)
    ((img * w_rgb).sum() + (alpha * w_a).sum()).backward()
    ours = {k: t.grad.clone() for k, t in p.items()}
    ours_cov = covs.grad.clone() if use_cov else None
    for t in p.values():
        t.grad = None
    probe = torch.zeros(50, 2, dtype=torch.float64, requires_grad=True)
    ref_img, ref_alpha, _ = _reference(p, cam, covs if not use_cov else covs.detach().requires_grad_(True), probe)
    ref_covs = None
    if use_cov:
        # re-run so that the reference's cov leaf is the one we read
        ref_covs = covs.detach().clone().requires_grad_(True)
        ref_img, ref_alpha, _ = _reference(p, cam, ref_covs, probe)
    ((ref_img * w_rgb).sum() + (ref_alpha * w_a).sum()).backward()
    for k, t in p.items():
        assert t.grad.abs().max() > 0, k
        torch.testing.assert_close(ours[k], t.grad, atol=1e-9, rtol=1e-9, msg=k)
    if use_cov:
        torch.testing.assert_close(ours_cov, ref_covs.grad, atol=1e-9, rtol=1e-9)
    torch.testing.assert_close(meta["means2d"].grad, probe.grad, atol=1e-9, rtol=1e-9)


@pytest.mark.gradcheck
@pytest.mark.parametrize("use_cov", [False, True])
def test_gradients_match_finite_differences(ti64, use_cov):
    """Central differences in float64 for every coordinate of every input of a small scene."""
    p, cam = _scene(6, 21), _camera()
    p["means"] = p["means"] * 0.6
    p["scales"] = p["scales"] + 0.8  # large Gaussians: every pixel sees several
    if use_cov:
        p["covs"] = quat_scale_to_cov(p.pop("quats"), torch.exp(p.pop("scales")))
    w_rgb, w_a = _loss_weights(12)

    def loss(q):
        img, alpha, _ = _render(q, cam, q.get("covs"))
        return (img * w_rgb).sum() + (alpha * w_a).sum()

    leaves = {k: t.clone().requires_grad_(True) for k, t in p.items()}
    loss(leaves).backward()
    h = 1e-6
    for k, t in p.items():
        fd = torch.zeros_like(t)
        flat = fd.view(-1)
        for j in range(t.numel()):
            plus, minus = {**p, k: t.clone()}, {**p, k: t.clone()}
            plus[k].view(-1)[j] += h
            minus[k].view(-1)[j] -= h
            with torch.no_grad():
                flat[j] = (loss(plus) - loss(minus)) / (2 * h)
        scale = fd.abs().max()
        assert scale > 0, k
        err = (leaves[k].grad - fd).abs().max() / scale
        assert err < 1e-5, f"{k}: relative error {err:.2e}"


def test_two_renders_then_one_backward(ti64):
    """Rendering another scene between forward and backward must not corrupt the first render's gradients."""
    cam = _camera()
    p1 = {k: t.requires_grad_(True) for k, t in _scene(30, 8).items()}
    p2 = {k: t.requires_grad_(True) for k, t in _scene(30, 9).items()}
    w_rgb, _ = _loss_weights(13)
    img1, _, _ = _render(p1, cam)
    (img1 * w_rgb).sum().backward()
    alone = p1["means"].grad.clone()
    p1["means"].grad = None
    img1, _, _ = _render(p1, cam)
    img2, _, _ = _render(p2, cam)
    ((img1 * w_rgb).sum() + (img2 * w_rgb).sum()).backward()
    torch.testing.assert_close(p1["means"].grad, alone, atol=1e-12, rtol=0)


def test_bad_inputs_give_one_line_errors(ti64):
    p, cam = _scene(5, 1), _camera()
    with pytest.raises(CausalGSError, match=r"means has shape \[5, 2\]"):
        rasterize(p["means"][:, :2], p["quats"], p["scales"], p["opacities"], p["sh"], cam.viewmat, cam.K, W, H)
    with pytest.raises(CausalGSError, match="sh has shape"):
        rasterize(p["means"], p["quats"], p["scales"], p["opacities"], p["sh"][:, :5], cam.viewmat, cam.K, W, H)
    bad = p["means"].clone()
    bad[3, 1] = float("nan")
    with pytest.raises(CausalGSError, match="field 'x': non-finite value in row 3"):
        rasterize(bad, p["quats"], p["scales"], p["opacities"], p["sh"], cam.viewmat, cam.K, W, H)


def _psnr(a, b):
    return float(-10 * torch.log10(((a - b) ** 2).mean()))


def test_fit_a_target_image(ti32):
    """From noise, gradient descent through the rasterizer reproduces a 300-Gaussian target to > 30 dB."""
    cam = Camera.from_blender(look_at([0.0, -3.0, 0.0], [0.0, 0.0, 0.0], up=(0, 0, 1)), 64, 64, fov_x=0.8)
    vm, K = torch.tensor(cam.viewmat), torch.tensor(cam.K)
    n = 300
    target = _scene(n, 30, n_sh=1, dtype=torch.float32)
    target["sh"] = target["sh"] * 4
    with torch.no_grad():
        goal, _, _ = rasterize(*(target[k] for k in ("means", "quats", "scales", "opacities", "sh")), vm, K, 64, 64)
    g = torch.Generator().manual_seed(31)
    params = {
        "means": (torch.rand(n, 3, generator=g) - 0.5) * 2.0,
        "quats": torch.randn(n, 4, generator=g),
        "scales": torch.full((n, 3), math.log(0.05)),
        "opacities": torch.zeros(n),
        "sh": torch.randn(n, 1, 3, generator=g) * 0.5,
    }
    for t in params.values():
        t.requires_grad_(True)
    opt = torch.optim.Adam(
        [{"params": [params["means"]], "lr": 3e-3}, {"params": [params["sh"]], "lr": 2e-2},
         {"params": [params["quats"], params["scales"], params["opacities"]], "lr": 2e-2}]
    )  # fmt: skip
    start = None
    for _ in range(400):
        img, _, _ = rasterize(*(params[k] for k in ("means", "quats", "scales", "opacities", "sh")), vm, K, 64, 64)
        loss = (img - goal).abs().mean()
        start = start if start is not None else _psnr(img.detach(), goal)
        opt.zero_grad()
        loss.backward()
        opt.step()
    final = _psnr(img.detach(), goal)
    assert start < 20
    assert final > 30, f"PSNR {final:.1f} dB after fitting (started at {start:.1f} dB)"


def test_taichi_binning_matches_torch_binning(ti64):
    """The count/fill kernels give the same depth-ordered tile lists as the plain torch binning."""
    from causalgs.render import composite, project
    from causalgs.render.rasterizer import View, _scratch_rasterizer, _upload
    from causalgs.render.reference import bin_gaussians

    p, cam = _scene(300, 17), _camera()
    rast = _scratch_rasterizer()
    _upload(rast, {"x": p["means"], "opacity_raw": p["opacities"], "quat": p["quats"], "scale_raw": p["scales"]},
            p["sh"])  # fmt: skip
    rast.forward(View.of(cam.viewmat, cam.K, W, H))
    frame = rast.last_pass
    box = torch.empty((300, 4), dtype=torch.int32)
    radii = torch.empty((300, 2), dtype=torch.float64)
    s = rast.store
    project.bounds(s.mean2d, s.conic, s.depth, s.opac, box, radii, W, H, s.n)
    gids, ranges = bin_gaussians(box, s.to_torch("depth"), W, H, composite.TILE)
    assert len(gids) > 300
    torch.testing.assert_close(frame.gids, gids)
    torch.testing.assert_close(frame.ranges, ranges)
    torch.testing.assert_close(frame.pbox, box[gids.long()])


def test_chunked_reference_equals_dense_reference(ti64):
    """The benchmark runs the reference in checkpointed pixel chunks; it must be the same function."""
    p, cam = _scene(40, 19), _camera()
    leaves = [{k: t.clone().requires_grad_(True) for k, t in p.items()} for _ in range(2)]
    w_rgb, w_a = _loss_weights(14)
    outs = []
    for q, chunk in zip(leaves, (None, 97), strict=True):
        img, alpha, depth = rasterize_reference(
            q["means"], q["quats"], q["scales"], q["opacities"], q["sh"], torch.tensor(cam.viewmat),
            torch.tensor(cam.K), W, H, torch.tensor(BG, dtype=torch.float64), chunk=chunk,
        )  # fmt: skip
        ((img * w_rgb).sum() + (alpha * w_a).sum()).backward()
        outs.append((img.detach(), alpha.detach(), depth.detach()))
    for a, b in zip(*outs, strict=True):
        torch.testing.assert_close(a, b, atol=1e-12, rtol=0)
    for k in p:
        torch.testing.assert_close(leaves[0][k].grad, leaves[1][k].grad, atol=1e-12, rtol=1e-10)
