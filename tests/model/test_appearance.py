"""Joint training of the Gaussians in the kinematic stage: their colours and positions learn from frames after t = 0,
density control goes on with the model's per-Gaussian buffers kept aligned, and the optimiser state round-trips."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from causalgs.cameras import Camera, look_at
from causalgs.errors import CausalGSError


def _camera(az: float) -> Camera:
    eye = 2.5 * np.array([math.cos(az), math.sin(az), 0.6])
    return Camera.from_blender(look_at(eye, np.zeros(3)), 32, 32, fov_x=0.8)


def _model(n: int = 200):
    from causalgs.model.config import FitConfig
    from causalgs.model.gaussians import Gaussians
    from causalgs.model.scene import CausalGS

    torch.manual_seed(0)
    g = Gaussians.random(n, [-0.3] * 3, [0.3] * 3, seed=2, sh_degree=0, opacity=0.8)
    m = CausalGS(FitConfig(), g, [-0.5] * 3, [0.5] * 3, fps=30.0, train_frames=6).double()
    for p in m.gaussians.parameters():
        p.requires_grad_(False)  # as the canonical stage leaves them
    return m


def test_the_gaussians_learn_from_later_frames_and_density_control_keeps_the_model_aligned(ti64):
    from causalgs.model.appearance import AppearanceConfig, JointAppearance
    from causalgs.model.canonical import CanonicalConfig

    m = _model()
    cams = [_camera(a) for a in (0.2, 1.9, 3.7)]
    with torch.no_grad():  # the truth: the same Gaussians, redder and moved up a little
        sh = m.gaussians.sh.detach().clone()
        sh[:, 0, 0] += 1.0
        target = [m.gaussians.render(c, (1.0, 1.0, 1.0), sh=sh, means=m.gaussians.means + 0.02)[0] for c in cams]
    frames = [SimpleNamespace(camera=c, background=np.ones(3)) for c in cams]
    cfg = AppearanceConfig(means_lr=1e-3, lr_scale=20.0, densify_every=5, densify_until=0.5)
    joint = JointAppearance(m, CanonicalConfig(grad_threshold=1e-7, max_gaussians=400), cfg, frames, iterations=20)
    first = None
    for it in range(20):
        loss = 0.0
        for c, t in zip(cams, target, strict=True):
            state = m.observed([3], residual=False)[0]
            img, _, meta = m.gaussians.render(c, (1.0, 1.0, 1.0), **state.overrides())
            err = (img - t).abs().mean()
            err.backward()
            joint.observe(meta, c)
            loss += float(err)
        first = loss if first is None else first
        record = joint.step(it + 1)
        assert len(m.dynamic) == m.gaussians.n  # every per-Gaussian buffer follows density control
        if record:
            assert record["n"] == m.gaussians.n
    assert m.gaussians.n > 200  # densified
    assert loss < 0.7 * first
    assert float(m.gaussians.sh.detach()[:, 0, 0].mean()) > float(sh[:, 0, 0].mean()) - 0.8  # redder (by > 0.2)
    state = joint.state_dict()
    joint.load_state_dict(state)
    joint.finish()
    assert not any(p.requires_grad for p in m.gaussians.parameters())


def test_bad_settings_are_one_line_errors():
    from causalgs.model.appearance import AppearanceConfig

    with pytest.raises(CausalGSError, match="densify_until"):
        AppearanceConfig(densify_until=2.0)
    with pytest.raises(CausalGSError, match="means_lr"):
        AppearanceConfig(means_lr=float("nan"))
