"""Joint training: the Gaussians learn their appearance and shape with the motion, on every observed frame.

The canonical stage fits the Gaussians to the t = 0 images only; that is a warm-up. Frozen after it, nothing seen
later (a face turning into view, a body's underside) would ever be reconstructed, and every error of the t = 0 fit
would be carried through time. As in FreeGave and the paper, the dynamic stage therefore trains the Gaussians'
positions, rotations, scales, opacities and colours together with the velocity field, through the same renders of the
moving Gaussians, and adaptive density control goes on: a clone or a split child takes the physics code of its
canonical position, its parent's (the code is a field of the canonical position, :mod:`causalgs.model.fields`).

The optimiser and the density control are the canonical stage's (:class:`~causalgs.model.canonical.CanonicalTrainer`),
with the positions at a fixed rate and no opacity resets (a reset in the middle of tracking would make every body
transparent to the motion's gradient for a hundred iterations).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch

from causalgs.errors import CausalGSError
from causalgs.model.canonical import CanonicalConfig, CanonicalTrainer


@dataclass
class AppearanceConfig:
    """The Gaussians' training in the kinematic stage (``kinematic.appearance``).

    - ``enabled``: train the Gaussians with the motion (off: they stay as the canonical stage left them);
    - ``means_lr``: the positions' Adam rate, times the scene extent (the canonical stage ends at a tenth of it);
    - ``lr_scale``: the canonical stage's rates of rotations, scales, opacities and colours times this;
    - ``densify_every``: iterations between densifications (0: none); ``densify_until``: the fraction of the stage
      after which the count stays fixed (the motion then settles on the final Gaussians).
    """

    enabled: bool = True
    means_lr: float = 1.6e-5
    lr_scale: float = 1.0
    densify_every: int = 100
    densify_until: float = 0.5

    def __post_init__(self):
        for name in ("means_lr", "lr_scale"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise CausalGSError(f"kinematic.appearance.{name} = {value} must be a non-negative number")
        if self.densify_every < 0:
            raise CausalGSError(f"kinematic.appearance.densify_every = {self.densify_every} must be 0 or more")
        if not 0.0 <= self.densify_until <= 1.0:
            raise CausalGSError(f"kinematic.appearance.densify_until = {self.densify_until} must lie in [0, 1]")


class JointAppearance:
    """The Gaussians' optimiser and density control during the kinematic stage of ``model`` (a CausalGS).

    ``frames``: the training frames at t = 0, whose cameras give the scene extent as in the canonical stage;
    ``iterations``: the stage's length. Per iteration: :meth:`observe` every render's ``meta`` after the backward
    pass, then :meth:`step`."""

    def __init__(self, model, canonical: CanonicalConfig, config: AppearanceConfig, frames: Sequence, iterations: int):
        self.model, self.config = model, config
        s = config.lr_scale
        until = int(config.densify_until * iterations) if config.densify_every > 0 else 0
        cc = dataclasses.replace(
            canonical, iterations=max(1, iterations), means_lr=config.means_lr, means_lr_final=config.means_lr,
            sh_dc_lr=max(canonical.sh_dc_lr * s, 1e-12), sh_rest_lr=canonical.sh_rest_lr * s,
            opacities_lr=canonical.opacities_lr * s, scales_lr=canonical.scales_lr * s,
            quats_lr=canonical.quats_lr * s, densify_from=0, densify_until=until,
            densify_every=max(1, config.densify_every), opacity_reset_every=0, extent=None,
        )  # fmt: skip
        g = model.gaussians
        for p in g.parameters():
            p.requires_grad_(True)
        self.trainer = CanonicalTrainer(g, frames, cc, keep_sh_degree=True)
        self.iteration = 0

    def observe(self, meta: dict, camera) -> None:
        """Accumulate one render's screen-space gradients for density control (after ``backward``)."""
        if self.iteration < self.trainer.config.densify_until:
            self.trainer.stats.add(meta, camera.width, camera.height)

    def step(self, iteration: int) -> dict:
        """Adam step of the Gaussians; density control when due. Returns what it did (for the log)."""
        self.iteration = iteration
        t, c = self.trainer, self.trainer.config
        with torch.no_grad():
            t.optimizer.step()
            t.optimizer.zero_grad()
            if iteration < c.densify_until and iteration > 0 and iteration % c.densify_every == 0:
                record = t.densify_and_prune(prune_big=True)
                m = self.model
                m.register_buffer("dynamic", torch.ones(m.gaussians.n, dtype=torch.bool))  # all move until split
                return {**record, "n": m.gaussians.n}
        return {}

    def finish(self) -> None:
        """The Gaussians' parameters stop taking gradients (the stage is over)."""
        for p in self.model.gaussians.parameters():
            p.requires_grad_(False)

    def state_dict(self) -> dict:
        return self.trainer.optimizer.adam.state_dict()

    def load_state_dict(self, state: dict) -> None:
        self.trainer.optimizer.adam.load_state_dict(state)
