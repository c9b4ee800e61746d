"""Least-squares calibration of a :class:`~causalgs.discover.model.PhysicsModel` through the differentiable MPM.

The objective is the mean squared distance between simulated and measured positions over chosen frames, in cm²
(so its scale suits L-BFGS's tolerances). L-BFGS with a strong-Wolfe line search takes one forward and one
checkpointed backward rollout per evaluation. A trial point where the simulation blows up (a one-line
:class:`~causalgs.errors.CausalGSError`) scores a large loss with no gradient, which makes the line search step back.
Several starting stiffnesses guard against the local minima of elastic fits (a soft and a stiff fit of one bounce).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from causalgs.discover.model import PhysicsModel
from causalgs.errors import CausalGSError

UNIT = 0.01  # m: losses are mean squared distances in cm²
BLOWN = 1e6


@dataclass
class Fit:
    theta: torch.Tensor
    loss: float  # mean squared distance over the fitted frames, cm²
    evaluations: int
    start: float  # the starting stiffness (Pa)

    @property
    def rms(self) -> float:
        """RMS distance per coordinate (m)."""
        return float(np.sqrt(self.loss)) * UNIT


def mse(model: PhysicsModel, theta: torch.Tensor, frames) -> torch.Tensor:
    x = model.rollout(theta, frames)
    target = torch.as_tensor(model.obs.x[list(frames)], dtype=torch.float64)
    return (((x - target) / UNIT) ** 2).mean()


def fit_frames(model: PhysicsModel) -> list[int]:
    """The frames a calibration may use: every observed frame after the first."""
    return list(range(1, model.obs.observed))


def calibrate(model: PhysicsModel, theta0: torch.Tensor, frames=None, *, iterations: int = 25,
              free=None, warm: float = 0.0) -> Fit:  # fmt: skip
    """L-BFGS from ``theta0`` on ``frames`` (default: the fit window). ``free``: indices of θ to fit (default all);
    the rest stay at ``theta0``. ``warm`` > 0: first fit the leading ``warm`` fraction of the frames (half the
    iterations), then all of them: a short horizon is nearly convex in the throw and the forces, so the long one
    starts in the right basin rather than where parameters compensate for one another (a friction that mimics a
    forward push, a throw that mimics drag)."""
    frames = fit_frames(model) if frames is None else list(frames)
    if warm > 0 and len(frames) >= 6:
        head = frames[: max(3, round(warm * len(frames)))]
        theta0 = calibrate(model, theta0, head, iterations=max(5, iterations // 2), free=free).theta
    mask = torch.zeros(len(theta0), dtype=torch.bool)
    mask[list(range(len(theta0))) if free is None else list(free)] = True
    fixed = theta0.detach().clone()
    a = fixed[mask].clone().requires_grad_(True)
    opt = torch.optim.LBFGS([a], lr=1.0, max_iter=iterations, history_size=20, line_search_fn="strong_wolfe",
                            tolerance_grad=1e-9, tolerance_change=1e-12)  # fmt: skip
    count = [0]

    def full(v):
        th = fixed.clone()
        th[mask] = v
        return th

    def closure():
        opt.zero_grad()
        count[0] += 1
        try:
            loss = mse(model, full(a), frames)
        except CausalGSError:
            a.grad = torch.zeros_like(a)
            return torch.tensor(BLOWN, dtype=torch.float64)
        if not torch.isfinite(loss):
            a.grad = torch.zeros_like(a)
            return torch.tensor(BLOWN, dtype=torch.float64)
        loss.backward()
        return loss.detach()

    opt.step(closure)
    theta = full(a.detach())
    with torch.no_grad():
        try:
            final = float(mse(model, theta, frames))
        except CausalGSError:
            final = BLOWN
    E0 = float(model.values(theta0)[model.names[model.base_indices()[0]]]) if model.base_indices() else 0.0
    return Fit(theta, final, count[0], E0)


def multistart(model: PhysicsModel, starts=(1e4, 1e5), frames=None, *, iterations: int = 25,
               effects: dict | None = None, theta=None) -> tuple[Fit, list[Fit]]:  # fmt: skip
    """Calibrate from every starting stiffness in ``starts`` (the other entries from the data's first frames, or
    from ``theta`` where given); the best fit and all of them."""
    fits = []
    for E in starts:
        th = model.initial(E=E, effects=effects)
        if theta is not None:  # keep everything of a previous fit but the stiffness
            keep = [i for i, k in enumerate(model.knobs) if k.kind != "E"]
            th[keep] = theta[keep]
        fits.append(calibrate(model, th, frames, iterations=iterations))
    best = min(fits, key=lambda f: f.loss)
    return best, fits
