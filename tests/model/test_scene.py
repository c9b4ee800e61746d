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


def test_the_observed_state_adds_the_residual_inside_the_window_only_and_reposes_with_the_world(ti64):
    """``observed``: the velocity field's state plus the deformation residual at observed frames (rigid part
    removed), the velocity field's alone after the window; a re-posed model
    renders the same observed images from the re-posed cameras. A residual that translates everything moves
    nothing."""
    from causalgs.model.config import FitConfig
    from causalgs.model.gaussians import Gaussians
    from causalgs.model.scene import CausalGS

    torch.manual_seed(0)
    g = Gaussians.random(300, [-0.4] * 3, [0.4] * 3, seed=1, sh_degree=1)
    with torch.no_grad():
        g.opacities.fill_(1.0)
    m = CausalGS(FitConfig(), g, [-0.5] * 3, [0.5] * 3, fps=30.0, train_frames=10).double()
    with torch.no_grad():
        for p in (*m.fields.f_weight.parameters(), *m.residual.parameters()):
            p.add_(0.3 * torch.randn_like(p))
    m.keep_track()
    frames = [0, 6, 9, 12]
    plain = m.observed(frames, residual=False)
    states = m.observed(frames)
    means, quats = m.kinematic(12, frames=frames)
    for i, k in enumerate(frames):
        assert torch.equal(plain[i].means, means[i]) and torch.equal(plain[i].quats, quats[i])
        if k < m.train_frames:
            off = states[i].means - means[i]
            assert 0 < float(off.abs().max()) <= m.residual.bound() * 1.01
            assert states[i].scales is not None and not torch.equal(states[i].quats, quats[i])
        else:
            assert torch.equal(states[i].means, means[i]) and states[i].offset is None
    last = m.residual.net[-1]
    saved = [t.detach().clone() for t in (last.weight, last.bias)]
    with torch.no_grad():  # a residual that would carry the whole scene along: it moves nothing
        last.weight.zero_()
        last.bias.copy_(torch.tensor([3.0, -2.0, 1.0, *([0.0] * 6)]))
    shifted = m.observed([6])[0]
    assert float((shifted.means - means[1]).abs().max()) < 1e-9
    with torch.no_grad():
        last.weight.copy_(saved[0])
        last.bias.copy_(saved[1])
    cams = [_camera(a) for a in (0.3, 2.0)]
    before = [m.render(s, c, (1.0, 1.0, 1.0))[0].detach() for s in m.observed([6]) for c in cams]
    sim = Similarity.make(random_rotation(5), 2.0, [0.2, -1.0, 4.0])
    m.reframe(sim)
    after = [m.render(s, c, (1.0, 1.0, 1.0))[0].detach() for s in m.observed([6]) for c in
             [_reposed(c, sim) for c in cams]]  # fmt: skip
    for a, b in zip(before, after, strict=True):
        assert float((a - b).abs().max()) < 1e-9
