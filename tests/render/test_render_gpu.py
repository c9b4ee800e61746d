"""The rasterizer on CUDA (float64) against the dense torch reference, forward and backward, on a scene of several
tiles with Gaussians behind the camera and off-screen. ``test_rasterizer.py`` holds the same kernels to the same
reference on the CPU; on the GPU the projection's gradients are accumulated by concurrent atomic adds. Skipped without
a CUDA device."""

from __future__ import annotations

import math

import pytest
import torch

from causalgs.cameras import Camera, look_at
from causalgs.render import rasterize
from causalgs.render.reference import rasterize_reference

pytestmark = [pytest.mark.gpu]

D = torch.float64
W, H = 96, 72
BG = (0.1, 0.2, 0.3)


def _scene(n: int, seed: int) -> tuple[dict[str, torch.Tensor], Camera]:
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g, dtype=D) - 0.5) * 2.0
    means[0] = torch.tensor([0.0, -6.0, 1.0])  # behind the camera
    means[1] = torch.tensor([9.0, 0.0, 0.0])  # off-screen
    p = {
        "means": means,
        "quats": torch.randn(n, 4, generator=g, dtype=D),
        "scales": torch.log(torch.rand(n, 3, generator=g, dtype=D) * 0.2 + 0.02),
        "opacities": torch.randn(n, generator=g, dtype=D) + 0.5,
        "sh": torch.randn(n, 16, 3, generator=g, dtype=D) * 0.3,
    }
    return p, Camera.from_blender(look_at([0.0, -4.0, 1.0], [0.0, 0.0, 0.0]), W, H, fov_x=0.9)


def _args(p, cam):
    return (p["means"], p["quats"], p["scales"], p["opacities"], p["sh"], torch.tensor(cam.viewmat),
            torch.tensor(cam.K), W, H)  # fmt: skip


def test_cuda_render_matches_reference(cuda64):
    p, cam = _scene(300, 3)
    leaves = {k: t.clone().requires_grad_(True) for k, t in p.items()}
    img, alpha, meta = rasterize(*_args(leaves, cam), background=BG)
    assert img.device.type == "cpu" and img.dtype == D and img.shape == (H, W, 3)
    assert (alpha > 0.05).float().mean() > 0.2, "the scene should cover the image"
    assert (meta["radii"][:2] == 0).all(), "behind-camera and off-screen Gaussians draw nothing"
    g = torch.Generator().manual_seed(4)
    w_rgb, w_a = torch.randn(H, W, 3, generator=g, dtype=D), torch.randn(H, W, generator=g, dtype=D)
    ((img * w_rgb).sum() + (alpha * w_a).sum()).backward()

    ref_leaves = {k: t.clone().requires_grad_(True) for k, t in p.items()}
    ref_img, ref_alpha, ref_depth = rasterize_reference(
        *_args(ref_leaves, cam), torch.tensor(BG, dtype=D), sh_degree=math.isqrt(16) - 1
    )
    torch.testing.assert_close(img.detach(), ref_img.detach(), atol=1e-10, rtol=0)
    torch.testing.assert_close(alpha.detach(), ref_alpha.detach(), atol=1e-10, rtol=0)
    torch.testing.assert_close(meta["depth"].detach(), ref_depth.detach(), atol=1e-9, rtol=0)
    ((ref_img * w_rgb).sum() + (ref_alpha * w_a).sum()).backward()
    for k in p:
        assert ref_leaves[k].grad.abs().max() > 0, k
        torch.testing.assert_close(leaves[k].grad, ref_leaves[k].grad, atol=1e-9, rtol=1e-9, msg=k)
