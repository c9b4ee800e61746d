"""Training of the canonical (t = 0) Gaussians: 3D Gaussian Splatting on the first frames of every view.

This follows the reference implementation (graphdeco-inria/gaussian-splatting, ``train.py`` and
``scene/gaussian_model.py``): Adam with one parameter group per parameter, the position learning rate scaled by the
scene extent and decayed exponentially, loss (1 − λ)·L1 + λ·(1 − SSIM), the SH degree raised every 1000 iterations,
and adaptive density control — clone small Gaussians and split large ones where the screen-space gradient is large,
prune transparent and oversized ones, and reset opacities now and then.

Deviations, each on purpose:
- The densification gradient threshold is in 3DGS's NDC units. ``meta["means2d"].grad`` of our rasterizer is in
  pixels; the NDC gradient is the pixel gradient times (W/2, H/2) (x_pix = (x_ndc + 1)·W/2 − 0.5), so the stats
  accumulate ``‖(g_x·W/2, g_y·H/2)‖`` and the 3DGS default 2e-4 applies unchanged, independently of the image size.
- The optimizer steps before densification (3DGS densifies first and then steps, which silently skips the update of
  every parameter on densification iterations because the new tensors have no gradient yet).
- The screen-size prune uses the 2D radii collected since the last densification. 3DGS resets them to zero inside
  ``densification_postfix`` just before it tests them, so its screen-size prune never fires.
- ``max_gaussians`` caps the count: when clones and splits would exceed it, only the highest-gradient candidates are
  densified.
- The SH "rest" coefficients share one tensor with the DC term (the rasterizer's raw form) but have their own learning
  rate: Adam's step is linear in the learning rate, so scaling the step of those rows by rest_lr / dc_lr after
  ``Adam.step`` is exactly a separate parameter group.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, fields

import numpy as np
import torch

from causalgs import _ti
from causalgs.errors import CausalGSError
from causalgs.metrics import ssim
from causalgs.model.gaussians import PARAMS, Gaussians, quat_to_rotmat
from causalgs.settings import check_keys

__all__ = [
    "CanonicalConfig",
    "CanonicalTrainer",
    "DensifyStats",
    "GaussianOptimizer",
    "expon_lr",
    "scene_extent",
    "train_canonical",
]

SPLIT_SAMPLES = 2  # children per split Gaussian (3DGS's N = 2); their scales are divided by 0.8 N = 1.6


@dataclass
class CanonicalConfig:
    """Settings of :func:`train_canonical`; the defaults are the reference 3DGS ones unless noted.

    - ``iterations``: optimisation steps, one random training view each (views are drawn without replacement).
    - ``seed``: view order, split samples and random backgrounds.
    - ``sh_degree``: largest SH degree trained (for new Gaussians and the schedule; capped by the Gaussians' own);
      the active degree starts at 0 and rises by one every ``sh_degree_every`` iterations.
    - learning rates: ``means_lr`` → ``means_lr_final`` (both times the scene extent, exponential decay over
      ``iterations``), ``sh_dc_lr``, ``sh_rest_lr`` (= DC / 20), ``opacities_lr`` (0.05, the 3DGS release value; later
      versions use 0.025), ``scales_lr``, ``quats_lr``. Adam with eps 1e-15 as in 3DGS.
    - ``lambda_dssim``: weight of (1 − SSIM) in the loss.
    - densification runs at iterations ``densify_from`` < it < ``densify_until`` that are multiples of
      ``densify_every``; ``grad_threshold`` is on the mean NDC-space gradient norm of the projected mean (see the
      module docstring); ``percent_dense`` × extent separates clone (smaller) from split (larger).
    - ``opacity_reset_every``: iterations between opacity resets to at most 0.01 (0 = never); on a white background
      also at ``densify_from``, as 3DGS does.
    - pruning: opacity below ``prune_opacity``; after the first opacity reset (from the start when resets are off)
      also a 2D radius above ``prune_screen_size`` pixels (0 = off) or a largest scale above ``prune_world_size`` ×
      extent.
    - ``max_gaussians``: cap on the count (0 = none). Not in 3DGS; sized for CPU training.
    - ``random_background``: render and composite the target on a random colour each step (needs the frames'
      alpha), which stops the model from explaining the background with Gaussians.
    - ``extent``: the scene radius that scales the position learning rate and the size thresholds; ``None`` = 1.1 ×
      the largest distance of a camera centre from their mean (3DGS's ``getNerfppNorm``).
    - ``log_every``: iterations between records passed to ``log`` (densification events are always logged).
    """

    iterations: int = 30_000
    seed: int = 0
    sh_degree: int = 3
    sh_degree_every: int = 1000
    means_lr: float = 1.6e-4
    means_lr_final: float = 1.6e-6
    sh_dc_lr: float = 2.5e-3
    sh_rest_lr: float = 2.5e-3 / 20.0
    opacities_lr: float = 0.05
    scales_lr: float = 5e-3
    quats_lr: float = 1e-3
    lambda_dssim: float = 0.2
    densify_from: int = 500
    densify_until: int = 15_000
    densify_every: int = 100
    grad_threshold: float = 2e-4
    percent_dense: float = 0.01
    opacity_reset_every: int = 3000
    prune_opacity: float = 0.005
    prune_screen_size: float = 20.0
    prune_world_size: float = 0.1
    max_gaussians: int = 500_000
    random_background: bool = False
    extent: float | None = None
    log_every: int = 100

    def __post_init__(self):
        positive = ("iterations", "sh_degree_every", "densify_every", "sh_dc_lr", "log_every")
        for name in positive:
            if not getattr(self, name) > 0:
                raise CausalGSError(f"canonical setting {name} = {getattr(self, name)} must be positive")
        non_negative = (
            *("means_lr", "means_lr_final", "sh_rest_lr", "opacities_lr", "scales_lr", "quats_lr", "grad_threshold"),
            *("percent_dense", "opacity_reset_every", "prune_opacity", "prune_screen_size", "prune_world_size"),
            *("max_gaussians", "densify_from", "densify_until"),
        )
        for name in non_negative:
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise CausalGSError(f"canonical setting {name} = {value} must be a non-negative number")
        if not 0 <= self.sh_degree <= 3:
            raise CausalGSError(f"canonical setting sh_degree = {self.sh_degree} must be in 0..3")
        if not 0 <= self.lambda_dssim <= 1:
            raise CausalGSError(f"canonical setting lambda_dssim = {self.lambda_dssim} must be in [0, 1]")
        if self.extent is not None and not (math.isfinite(self.extent) and self.extent > 0):
            raise CausalGSError(f"canonical setting extent = {self.extent} must be a positive number (or None)")

    @classmethod
    def from_dict(cls, d: dict) -> CanonicalConfig:
        check_keys(cls, d, "canonical")
        return cls(**d)

    def to_dict(self) -> dict:
        return {f.name: getattr(self, f.name) for f in fields(self)}


def scene_extent(cameras: Sequence) -> float:
    """3DGS's scene radius: 1.1 × the largest distance of a camera centre from the mean centre. A single camera (or
    coincident ones) gives no scale; 1.0 then, so that the learning rates stay usable."""
    centres = np.stack([np.asarray(c.center, dtype=np.float64) for c in cameras])
    radius = 1.1 * float(np.linalg.norm(centres - centres.mean(axis=0), axis=1).max())
    return radius if radius > 1e-9 else 1.0


def expon_lr(step: int, lr_init: float, lr_final: float, max_steps: int) -> float:
    """Log-linear interpolation from ``lr_init`` at step 0 to ``lr_final`` at ``max_steps`` (3DGS's
    ``get_expon_lr_func`` without the delay, which its defaults leave off)."""
    if lr_init == 0.0 or lr_final == 0.0:
        return lr_init if lr_final == lr_init else 0.0
    t = min(max(step / max(max_steps, 1), 0.0), 1.0)
    return math.exp(math.log(lr_init) * (1.0 - t) + math.log(lr_final) * t)


class GaussianOptimizer:
    """Adam over a :class:`Gaussians`' parameters, one group per parameter, and the row surgery that keeps its
    moments aligned when densification adds, removes or reorders Gaussians (each kept Gaussian keeps its moments,
    new ones start at zero, as in 3DGS's ``cat_tensors_to_optimizer`` and ``_prune_optimizer``)."""

    def __init__(self, gaussians: Gaussians, config: CanonicalConfig, extent: float):
        self.gaussians, self.config, self.extent = gaussians, config, extent
        lrs = {"means": config.means_lr * extent, "quats": config.quats_lr, "scales": config.scales_lr,
               "opacities": config.opacities_lr, "sh": config.sh_dc_lr}  # fmt: skip
        groups = [{"params": [p], "lr": lrs[name], "name": name} for name, p in gaussians.params().items()]
        self.adam = torch.optim.Adam(groups, lr=0.0, eps=1e-15)
        self.rest_scale = config.sh_rest_lr / config.sh_dc_lr

    def group(self, name: str) -> dict:
        return next(g for g in self.adam.param_groups if g["name"] == name)

    def state(self, name: str) -> dict:
        """Adam's state of one parameter (``exp_avg``, ``exp_avg_sq``, ``step``; empty before the first step)."""
        return self.adam.state.get(self.group(name)["params"][0], {})

    def set_iteration(self, iteration: int) -> float:
        """Set the decayed position learning rate for ``iteration``; returns it."""
        c = self.config
        lr = expon_lr(iteration, c.means_lr * self.extent, c.means_lr_final * self.extent, c.iterations)
        self.group("means")["lr"] = lr
        return lr

    def step(self) -> None:
        sh = self.gaussians.sh
        old_rest = sh.detach()[:, 1:].clone() if sh.shape[1] > 1 else None
        self.adam.step()
        if old_rest is not None:  # the SH rest learning rate: see the module docstring
            with torch.no_grad():
                sh[:, 1:] = old_rest + (sh[:, 1:] - old_rest) * self.rest_scale

    def zero_grad(self) -> None:
        self.adam.zero_grad(set_to_none=True)

    def replace_rows(self, index: torch.Tensor, new: dict[str, torch.Tensor] | None = None) -> None:
        """Keep the rows ``index`` (in that order) of every parameter and its Adam moments, then append the rows
        ``new`` (a tensor per parameter) with zero moments. The parameters become new tensors; the groups follow."""
        tensors = {}
        for name, p in self.gaussians.params().items():
            rows = p.detach()[index]
            tensors[name] = rows if new is None else torch.cat([rows, new[name].to(rows.dtype)])
        params = self.gaussians.set_params(tensors)
        n_new = 0 if new is None else len(new["means"])
        for group in self.adam.param_groups:
            old, fresh = group["params"][0], params[group["name"]]
            state = self.adam.state.pop(old, None)
            if state:
                for key in ("exp_avg", "exp_avg_sq"):
                    kept = state[key][index]
                    state[key] = torch.cat([kept, kept.new_zeros((n_new, *kept.shape[1:]))])
                self.adam.state[fresh] = state
            group["params"][0] = fresh

    def reset_values(self, name: str, values: torch.Tensor) -> None:
        """Overwrite one parameter's values in place and zero its moments (3DGS's ``replace_tensor_to_optimizer``)."""
        with torch.no_grad():
            getattr(self.gaussians, name).copy_(values)
        for key in ("exp_avg", "exp_avg_sq"):
            if key in self.state(name):
                self.state(name)[key].zero_()


@dataclass
class DensifyStats:
    """Per-Gaussian statistics between densifications: the summed NDC-space gradient norm of the projected mean,
    the number of views that drew the Gaussian, and its largest 2D radius (pixels)."""

    grad_sum: torch.Tensor
    count: torch.Tensor
    max_radii: torch.Tensor

    @classmethod
    def zeros(cls, n: int) -> DensifyStats:
        return cls(torch.zeros(n, dtype=torch.float64), torch.zeros(n, dtype=torch.int64), torch.zeros(n))

    def add(self, meta: dict, width: int, height: int) -> None:
        """Accumulate one render's ``meta`` (after backward) for the Gaussians it drew (radius > 0)."""
        grad = meta["means2d"].grad
        radii = meta["radii"].detach().amax(dim=-1).to(self.max_radii.dtype)
        drawn = radii > 0
        if grad is None or not drawn.any():
            return
        ndc = grad.detach()[drawn].double() * grad.new_tensor([0.5 * width, 0.5 * height]).double()
        self.grad_sum[drawn] += ndc.norm(dim=-1)
        self.count[drawn] += 1
        self.max_radii[drawn] = torch.maximum(self.max_radii[drawn], radii[drawn])

    def mean_grad(self) -> torch.Tensor:
        return torch.where(self.count > 0, self.grad_sum / self.count.clamp(min=1), torch.zeros_like(self.grad_sum))

    def rows(self, index: torch.Tensor, n_new: int = 0) -> DensifyStats:
        """The statistics of rows ``index`` followed by ``n_new`` zero rows (new Gaussians have no history)."""
        return DensifyStats(*(torch.cat([t[index], t.new_zeros(n_new)]) for t in (self.grad_sum, self.count,
                                                                                  self.max_radii)))  # fmt: skip


class CanonicalTrainer:
    """One canonical training run: the Gaussians (trained in place), the optimizer state, the densification
    statistics and the schedules. :func:`train_canonical` drives it; tests call its steps one by one."""

    def __init__(self, gaussians: Gaussians, frames: Sequence, config: CanonicalConfig | None = None,
                 keep_sh_degree: bool = False):  # fmt: skip
        if not frames:
            raise CausalGSError("canonical training needs at least one frame")
        self.gaussians, self.frames = gaussians, list(frames)
        self.config = config or CanonicalConfig()
        self.extent = self.config.extent or scene_extent([f.camera for f in self.frames])
        self.optimizer = GaussianOptimizer(gaussians, self.config, self.extent)
        self.stats = DensifyStats.zeros(gaussians.n)
        self.rng = np.random.default_rng(self.config.seed)
        self.generator = torch.Generator().manual_seed(self.config.seed)
        self.max_degree = min(self.config.sh_degree, gaussians.sh_degree)
        self.white = all(np.all(np.asarray(f.background) == 1.0) for f in self.frames)
        self.iteration = 0
        self._order: list[int] = []
        if not keep_sh_degree:  # a fresh fit raises the degree on its schedule; a continued one keeps it
            gaussians.active_sh_degree = 0

    # -- one iteration --------------------------------------------------------------------------------------------
    def step(self) -> dict:
        """Run the next iteration; returns its record (losses, count, and what densification did)."""
        c, g = self.config, self.gaussians
        self.iteration = it = self.iteration + 1
        lr = self.optimizer.set_iteration(it)
        if it % c.sh_degree_every == 0:
            g.active_sh_degree = min(g.active_sh_degree + 1, self.max_degree)
        frame = self._next_frame()
        background = self.rng.random(3) if c.random_background else np.asarray(frame.background, dtype=np.float64)
        image, _, meta = g.render(frame.camera, tuple(background.tolist()))
        losses = self._loss(image, self._target(frame, background), frame)
        losses["loss"].backward()
        record = {"step": it, **{k: float(v.detach()) for k, v in losses.items()}}
        with torch.no_grad():
            densifying = it < c.densify_until
            if densifying:
                self.stats.add(meta, frame.camera.width, frame.camera.height)
            self.optimizer.step()
            self.optimizer.zero_grad()
            if densifying and it > c.densify_from and it % c.densify_every == 0:
                # The size prune starts after the first opacity reset, as in 3DGS.
                record.update(self.densify_and_prune(prune_big=it > c.opacity_reset_every))
            if densifying and self._reset_due(it):
                self.reset_opacity()
                record["opacity_reset"] = True
        record.update(n=g.n, sh_degree=g.active_sh_degree, lr_means=lr)
        return record

    def _reset_due(self, it: int) -> bool:
        every = self.config.opacity_reset_every
        return (every > 0 and it % every == 0) or (self.white and it == self.config.densify_from)

    def _next_frame(self):
        """Views in a random order without replacement, refilled when used up (as 3DGS does)."""
        if not self._order:
            self._order = self.rng.permutation(len(self.frames)).tolist()
        return self.frames[self._order.pop()]

    def _target(self, frame, background: np.ndarray) -> torch.Tensor:
        """The frame's image as a tensor, recomposited on ``background`` when that differs from the dataset's."""
        image = np.asarray(frame.image, dtype=np.float64)
        cam = frame.camera
        if image.shape != (cam.height, cam.width, 3):
            raise CausalGSError(
                f"frame image has shape {list(image.shape)}, its camera is {cam.width}x{cam.height}: expected "
                f"[{cam.height}, {cam.width}, 3]"
            )
        own = np.asarray(frame.background, dtype=np.float64)
        if not np.array_equal(background, own):
            alpha = np.asarray(frame.alpha, dtype=np.float64)[..., None]
            image = image + (1.0 - alpha) * (background - own)  # un-composite from the old colour onto the new
        return torch.from_numpy(image).to(_ti.torch_dtype())

    def _loss(self, image: torch.Tensor, target: torch.Tensor, frame) -> dict[str, torch.Tensor]:
        lam = self.config.lambda_dssim
        l1 = (image - target).abs().mean()
        s = ssim(image, target)
        loss = (1.0 - lam) * l1 + lam * (1.0 - s)
        if not torch.isfinite(loss):
            where = getattr(frame, "path", None) or f"view {getattr(frame, 'view', '?')}"
            raise CausalGSError(
                f"canonical training: the loss is {float(loss.detach())} at iteration {self.iteration} ({where}); "
                "check the images and lower the learning rates"
            )
        return {"loss": loss, "l1": l1.detach(), "ssim": s.detach()}

    # -- adaptive density control ---------------------------------------------------------------------------------
    def densify_and_prune(self, prune_big: bool = True) -> dict:
        """Clone and split where the mean gradient passes the threshold, then prune; the statistics restart."""
        cloned, split = self.densify()
        pruned = self.prune(self.prune_mask(prune_big))
        self.stats = DensifyStats.zeros(self.gaussians.n)
        return {"cloned": cloned, "split": split, "pruned": pruned}

    def densify_masks(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Which Gaussians to clone (small ones) and to split (large ones), within the ``max_gaussians`` cap."""
        c, g = self.config, self.gaussians
        grads = self.stats.mean_grad()
        hot = grads >= c.grad_threshold
        small = torch.exp(g.scales.detach()).amax(dim=1) <= c.percent_dense * self.extent
        clone, split = hot & small, hot & ~small
        # Each clone and each split adds one Gaussian (a split replaces one by two).
        budget = max(c.max_gaussians - g.n, 0) if c.max_gaussians else None
        if budget is not None and int(hot.sum()) > budget:
            chosen = torch.zeros_like(hot)
            chosen[grads.masked_fill(~hot, -math.inf).topk(budget).indices] = True
            clone, split = clone & chosen, split & chosen
        return clone, split

    def densify(self) -> tuple[int, int]:
        """Clone and split (3DGS ``densify_and_clone`` / ``densify_and_split``): a clone is an exact copy that the
        optimizer then pulls apart; a split replaces a Gaussian by 2 samples from it with scales / 1.6. Returns the
        numbers of cloned and split Gaussians."""
        clone, split = self.densify_masks()
        if not (clone.any() or split.any()):
            return 0, 0
        p = {k: v.detach() for k, v in self.gaussians.params().items()}
        children = {k: v[split].repeat(SPLIT_SAMPLES, *([1] * (v.dim() - 1))) for k, v in p.items()}
        stds = torch.exp(children["scales"])
        samples = torch.normal(torch.zeros_like(stds), stds, generator=self.generator)
        children["means"] = children["means"] + (quat_to_rotmat(children["quats"]) @ samples[..., None])[..., 0]
        children["scales"] = children["scales"] - math.log(0.8 * SPLIT_SAMPLES)
        new = {k: torch.cat([p[k][clone], children[k]]) for k in PARAMS}
        keep = torch.nonzero(~split).squeeze(1)
        self.optimizer.replace_rows(keep, new)
        self.stats = self.stats.rows(keep, len(new["means"]))
        return int(clone.sum()), int(split.sum())

    def prune_mask(self, prune_big: bool = True) -> torch.Tensor:
        """Gaussians to remove: nearly transparent ones; with ``prune_big`` also those too large on screen (radius
        since the last densification) or in the world (largest scale against the extent)."""
        c, g = self.config, self.gaussians
        mask = torch.sigmoid(g.opacities.detach()) < c.prune_opacity
        if prune_big:
            if c.prune_screen_size > 0:
                mask |= self.stats.max_radii > c.prune_screen_size
            if c.prune_world_size > 0:
                mask |= torch.exp(g.scales.detach()).amax(dim=1) > c.prune_world_size * self.extent
        return mask

    def prune(self, mask: torch.Tensor) -> int:
        """Remove the Gaussians where ``mask`` is true (with their optimizer moments and statistics)."""
        if not mask.any():
            return 0
        keep = torch.nonzero(~mask).squeeze(1)
        self.optimizer.replace_rows(keep)
        self.stats = self.stats.rows(keep)
        return int(mask.sum())

    def reset_opacity(self, ceiling: float = 0.01) -> None:
        """Clamp every opacity to at most ``ceiling`` and forget its moments, so that Gaussians that the images do
        not need fall below the prune threshold (3DGS ``reset_opacity``)."""
        op = self.gaussians.opacities.detach()
        self.optimizer.reset_values("opacities", torch.minimum(op, torch.logit(op.new_tensor(ceiling))))


def train_canonical(
    gaussians: Gaussians,
    frames: Sequence,
    config: CanonicalConfig | None = None,
    *,
    progress: Callable[[int, int, dict], None] | None = None,
    log: Callable[[dict], None] | None = None,
) -> Gaussians:
    """Fit ``gaussians`` to ``frames`` (the t = 0 images: objects with ``camera``, ``image`` [H, W, 3] composited on
    ``background``, and ``alpha`` for random backgrounds) and return them.

    The Gaussians are trained in place and returned: the same object, whose parameters are new tensors whenever
    densification changed the count (so re-read ``gaussians.means`` rather than keeping an old reference).
    ``progress(step, total, losses)`` is called every iteration; ``log(record)`` every ``log_every`` iterations, at
    every densification or opacity reset and at the end, with ``stage = "canonical"``. A non-finite loss stops with
    a one-line :class:`CausalGSError` naming the iteration.
    """
    config = config or CanonicalConfig()
    trainer = CanonicalTrainer(gaussians, frames, config)
    for _ in range(config.iterations):
        record = trainer.step()
        it = record["step"]
        if progress is not None:
            progress(it, config.iterations, {k: record[k] for k in ("loss", "l1", "ssim")})
        eventful = "cloned" in record or "opacity_reset" in record
        if log is not None and (eventful or it % config.log_every == 0 or it == config.iterations):
            log({"stage": "canonical", **record})
    return gaussians
