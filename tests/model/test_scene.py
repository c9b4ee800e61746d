"""The scene model re-posed into another world frame (the physics frame a fit infers): the same images from the
same cameras re-posed, the kinematic states included, and the frame composed and saved."""

from __future__ import annotations

import math

import numpy as np
import torch

from causalgs.cameras import Camera, look_at
from causalgs.similarity import Similarity, random_rotation


def _camera(az: float) -> Camera:
    eye = 2.5 * np.array([math.cos(az), math.sin(az), 0.6])
    return Camera.from_blender(look_at(eye, np.zeros(3)), 32, 32, fov_x=0.8)


def _reposed(camera: Camera, sim: Similarity) -> Camera:
    return Camera(camera.K, np.linalg.inv(sim.camera_to_world(camera.c2w)), camera.width, camera.height)


def test_a_reposed_model_renders_the_same_images(ti64):
    from causalgs.model.config import FitConfig
    from causalgs.model.gaussians import Gaussians
    from causalgs.model.scene import CausalGS

    torch.manual_seed(0)
    g = Gaussians.random(300, [-0.4] * 3, [0.4] * 3, seed=1, sh_degree=2)
    with torch.no_grad():
        g.sh.normal_()
        g.opacities.fill_(1.0)
    m = CausalGS(FitConfig(), g, [-0.5] * 3, [0.5] * 3, fps=30.0, train_frames=10).double()
    with torch.no_grad():
        for p in m.fields.f_weight.parameters():
            p.add_(0.3 * torch.randn_like(p))
    m.keep_track()
    cams = [_camera(a) for a in (0.3, 2.0, 4.1)]

    def images(model, cameras):
        return [model.render(model.kinematic_state(k), c, (1.0, 1.0, 1.0))[0].detach() for k in (0, 6)
                for c in cameras]  # fmt: skip

    before = images(m, cams)
    assert float((before[0] - before[3]).abs().max()) > 0.01  # the patterns move something
    sim = Similarity.make(random_rotation(3), 3.0, [0.2, -1.0, 4.0])
    m.reframe(sim)
    after = images(m, [_reposed(c, sim) for c in cams])
    for a, b in zip(before, after, strict=True):
        assert float((a - b).abs().max()) < 1e-9
    assert np.allclose(m.frame.numpy(), sim.matrix())
    again = Similarity.make(random_rotation(4), 0.5)
    m.reframe(again)
    assert np.allclose(m.similarity().matrix(), again.matrix() @ sim.matrix())
    state = m.state_dict()
    fresh = CausalGS(FitConfig(), Gaussians.random(300, [-0.4] * 3, [0.4] * 3, seed=1, sh_degree=2), [-0.5] * 3,
                     [0.5] * 3, fps=30.0, train_frames=10)  # fmt: skip
    fresh.load_state_dict(state)
    assert np.allclose(fresh.similarity().matrix(), m.similarity().matrix())
