"""The kinematic stage's tracking loss: the blur against a plain reference (OpenCV), and the property it exists for —
a blob rendered away from where the image has it, with no overlap left, still gets a gradient towards it."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import torch

from causalgs import _ti
from causalgs.cameras import Camera, look_at, opengl_to_opencv
from causalgs.model.fit import blur, image_loss, tracking_loss
from causalgs.model.gaussians import Gaussians

SIZE = 48


@pytest.mark.parametrize("sigma", [0.8, 2.5, 6.0])
def test_blur_matches_opencv(sigma):
    rng = np.random.default_rng(0)
    img = rng.random((SIZE, SIZE + 5, 3))
    ours = blur(torch.from_numpy(img), sigma).numpy()
    r = max(1, math.ceil(3 * sigma))
    ref = cv2.GaussianBlur(img, (2 * r + 1, 2 * r + 1), sigma, borderType=cv2.BORDER_REPLICATE)
    assert np.abs(ours - ref).max() < 1e-6


def test_blur_gradcheck_float64():
    x = torch.rand(9, 7, 2, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda t: blur(t, 1.3), (x,))


def _blob(x: float) -> tuple[Gaussians, Camera]:
    g = Gaussians.from_points(np.array([[x, 0.0, 0.0]]), np.array([[0.9, 0.1, 0.1]]), sh_degree=0)
    with torch.no_grad():
        g.scales.fill_(math.log(0.05))
        g.opacities.fill_(4.0)
    c2w = opengl_to_opencv(look_at(np.array([0.0, -3.0, 0.0]), [0.0, 0.0, 0.0], up=(0.0, 0.0, 1.0)))
    f = 0.5 * SIZE / math.tan(0.5 * 0.8)
    return g, Camera.from_intrinsics(f, f, SIZE / 2, SIZE / 2, SIZE, SIZE, c2w)


def test_blurred_terms_pull_a_blob_that_no_longer_overlaps_its_image():
    _ti.init("cpu", "float64")
    target, cam = _blob(0.5)
    with torch.no_grad():
        gt, _, _ = target.render(cam, (1.0, 1.0, 1.0))
    g, _ = _blob(-0.45)  # 18 px from the target, 6 blob radii: neither the images nor SSIM windows overlap
    grads = {}
    for name, fn in (("sharp", lambda a, b: image_loss(a, b, 0.2)),
                     ("tracking", lambda a, b: tracking_loss(a, b, 0.2, (0.02, 0.05, 0.12)))):  # fmt: skip
        g.zero_grad()
        img, _, _ = g.render(cam, (1.0, 1.0, 1.0))
        fn(img, gt).backward()
        grads[name] = g.means.grad[0, 0].item()
    # Gradient descent moves x by −grad, towards the target (+x); the sharp loss has (almost) nothing left to say.
    assert abs(grads["sharp"]) < 0.1 * abs(grads["tracking"])
    assert grads["tracking"] < 0
