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


def _moving_model(train_frames: int = 10):
    from causalgs.model.config import FitConfig
    from causalgs.model.gaussians import Gaussians
    from causalgs.model.scene import CausalGS

    torch.manual_seed(0)
    g = Gaussians.random(300, [-0.4] * 3, [0.4] * 3, seed=1, sh_degree=1)
    with torch.no_grad():
        g.opacities.fill_(1.0)
    m = CausalGS(FitConfig(), g, [-0.5] * 3, [0.5] * 3, fps=30.0, train_frames=train_frames).double()
    with torch.no_grad():
        for p in m.fields.f_weight.parameters():
            p.add_(0.3 * torch.randn_like(p))
    m.keep_track()
    return m


def test_tracks_of_the_velocity_fields_motion_give_its_states(ti64):
    """Refined tracks equal to the patterns' own motion (A = R_k, b = t_k) give the velocity field's positions and
    (for Gaussians of one pattern) the covariances of its rotated Gaussians: the tracked state is one motion,
    whichever holds it. After the tracks' last frame the velocity field's state is used."""
    from causalgs.model.kinematic import pattern_motion
    from causalgs.render.reference import quat_scale_to_cov

    m = _moving_model()
    m.residual = None
    with torch.no_grad():  # one pattern per Gaussian: the blends of rotations (quaternions, matrices) then agree
        m.kinematic_fields.f_neck[-1].weight.mul_(1e6)
    R, t, _ = pattern_motion(m.kinematic_fields, 9, 1.0 / m.fps)
    m.set_tracks(R[:8], t[:8])
    frames = [0, 5, 7, 9]
    states = m.observed(frames)
    means, quats = m.kinematic(9, frames=frames)
    g = m.gaussians
    scales = torch.exp(g.scales)
    h = m.mixtures(g.means.detach())
    one, k_of = h.max(1).values > 1 - 1e-13, h.argmax(1)
    assert int(one.sum()) > 100
    cov0 = quat_scale_to_cov(g.quats, scales)
    for i, k in enumerate(frames):
        assert torch.allclose(states[i].means, means[i], atol=1e-12)
        if k < 8:  # Σ = R Σ0 Rᵀ with the pattern's RK2 map, whose rotation the quaternions integrate to O(ω dt)³
            Rk = R[k][k_of]
            assert torch.allclose(states[i].covs[one], (Rk @ cov0 @ Rk.transpose(1, 2))[one], atol=1e-12)
            drift = float((R[k].transpose(1, 2) @ R[k] - torch.eye(3, dtype=R.dtype)).abs().max())
            gap = (states[i].covs - quat_scale_to_cov(quats[i], scales)).abs().amax((1, 2)) / cov0.abs().amax((1, 2))
            assert float(gap[one].max()) <= 4 * drift + 1e-12
        else:
            assert states[i].covs is None and torch.equal(states[i].quats, quats[i])
    x0 = m.gaussians.means.detach()[:50]
    assert torch.allclose(m.tracked_positions(x0, [3, 7]), m.trajectories(m.mixtures(x0), x0, None, 7, [3, 7])[0],
                          atol=1e-12)  # fmt: skip


def test_refined_tracks_move_the_tracked_state_and_repose_with_the_world(ti64):
    """A track that shifts every pattern moves the tracked state (positions and the forecast's start) by that shift;
    re-posed by a similarity, the model renders the same tracked images from the re-posed cameras."""
    from causalgs.model.kinematic import pattern_motion

    m = _moving_model()
    m.residual = None
    R, t, _ = pattern_motion(m.kinematic_fields, 9, 1.0 / m.fps)
    shift = torch.tensor([0.05, -0.02, 0.03], dtype=torch.float64)
    m.set_tracks(R[:10], t[:10] + shift)
    plain, _ = m.kinematic(9, frames=[6])
    moved = m.observed([6])[0].means
    dyn = m.dynamic
    assert torch.allclose(moved[dyn] - plain[0][dyn], shift.expand(int(dyn.sum()), 3), atol=1e-12)
    cams = [_camera(a) for a in (0.3, 2.0)]
    before = [m.render(m.observed([6])[0], c, (1.0, 1.0, 1.0))[0].detach() for c in cams]
    sim = Similarity.make(random_rotation(6), 2.0, [0.2, -1.0, 4.0])
    m.reframe(sim)
    after = [m.render(m.observed([6])[0], _reposed(c, sim), (1.0, 1.0, 1.0))[0].detach() for c in cams]
    for a, b in zip(before, after, strict=True):
        assert float((a - b).abs().max()) < 1e-9
    state = m.state_dict()
    fresh = _moving_model()
    fresh.load_state_dict(state)
    assert torch.equal(fresh.track_A, m.track_A) and torch.equal(fresh.track_b, m.track_b)
    old = {k: v for k, v in state.items() if not k.startswith("track_")}  # a model saved before the tracks
    fresh = _moving_model()
    fresh.load_state_dict(old)
    assert len(fresh.track_A) == 0
