"""The gate a candidate must pass to be called a discovery, and the uncertainty of what it found.

A refit candidate is accepted only if all of these hold (``../shared/DISCOVERY.md``):

1. the held-out future error (frames never fitted) drops by at least ``future_drop`` (15%);
2. the Bayesian information criterion improves with an *effective* sample size n_eff = frames × 3 × clusters
   (residuals of neighbouring points and frames are strongly correlated; counting every point would reward any
   addition);
3. every new parameter is at least ``sigmas`` (3) standard errors from its "off" value, the standard errors from a
   moving-block bootstrap over frames of the linearised refit (naive Gauss–Newton errors assume independent
   residuals and come out far too small), and none is held at a bound of its range (there the linearised error
   collapses to nothing: a viscosity pinned at its cap read as 10¹⁵ standard errors from zero); and its 95%
   interval from every source of error the report names (that bootstrap, the bodies' extent, the tracks' own
   smooth error) excludes the "off" value: at least ``every_sigmas`` (1.96) of their standard errors away. The
   bootstrap sees the noise about one fit; the tracks' and the shape's errors are smooth and systematic, and can
   stand in for an effect by themselves: on the video-level landing control (seed 1, stretched tracks) a uniform
   force b = (−0.093, −0.006, 0.005) m/s² lay 5.0 bootstrap errors from zero, dropped the held-out error by 17%
   (MSE) and improved the BIC by 74, while its interval from every source, b_x in [−0.198, 0.013], held zero
   (1.7 errors);
4. the refit reaches the floor: its fit-window RMS is below the base's, within ``floor_factor`` (1.1×) of the best
   any model reached on this data or of the noise floor measured from the data, whichever is larger
   (:func:`causalgs.discover.residuals.lens_floor`; below the noise, a better fit of the window is fitting the
   noise and tells candidates nothing), and within ``noise_factor`` (1.25×) of what a correct model would fit the
   window by (that noise floor and, through a lens, what the lens cannot show of the refit's own motion:
   :func:`causalgs.discover.search.window_floor`); otherwise the candidate explains only part of the discrepancy
   ("not converged", or an effect the catalogue does not name);
5. the refit predicts the held-out frames to within ``future_factor`` (3×) of what a correct model would miss
   them by (RMS, :func:`causalgs.discover.search.held_out_floor`): the tracks' own error as the refit's window
   shows it (at most the noise floor), the fit window's noise carried forward through the refit's own linearised
   least squares (:func:`causalgs.discover.search.predictive_rms`; a bounce extrapolated from a noisy window is
   uncertain by more than the noise, a free flight hardly) and the bodies' extent. An entry of the catalogue that
   matches the fit window by mimicking an effect it is not (a uniform force for a pull that grows with the
   distance from a point) extrapolates the fit window, and misses the future by far more than the missing
   effect's own refit does (on the video-level flights, seed 0: 0.7× for the true force, 3.8× for a uniform
   force standing in for that pull).

Intervals are the bootstrap's 2.5–97.5% percentiles around the fitted value.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np


@dataclass
class GateConfig:
    future_drop: float = 0.15
    sigmas: float = 3.0
    every_sigmas: float = 1.96  # the 95% interval from every source of error excludes the "off" value
    floor_factor: float = 1.1
    noise_factor: float = 1.25
    future_factor: float = 3.0
    clusters_per_body: int = 4
    block: int = 4  # frames per bootstrap block
    resamples: int = 400
    seed: int = 0


def effective_n(frames: int, bodies: int, points: int, clusters_per_body: int) -> int:
    """frames × 3 coordinates × independent point clusters (at most the number of points)."""
    return int(frames * 3 * min(points, bodies * clusters_per_body))


def bic(mse: float, n_eff: int, k: int) -> float:
    """n·ln(mse) + k·ln(n) (Gaussian residuals; ``mse`` in any fixed unit)."""
    return n_eff * math.log(max(mse, 1e-300)) + k * math.log(n_eff)


def block_bootstrap(J: np.ndarray, r: np.ndarray, frames: int, cfg: GateConfig) -> np.ndarray:
    """[resamples, k] parameter deviations of the linearised least squares J δ ≈ r* when the residual ``r``
    (flattened [frames, …]) is resampled in blocks of ``cfg.block`` whole frames (every point of a frame moves
    together, so spatial correlation is kept too)."""
    rng = np.random.default_rng(cfg.seed)
    R = r.reshape(frames, -1)
    nb = max(1, math.ceil(frames / cfg.block))
    starts_max = max(1, frames - cfg.block + 1)
    pinv = np.linalg.pinv(J)
    out = np.empty((cfg.resamples, J.shape[1]))
    for s in range(cfg.resamples):
        idx = np.concatenate([np.arange(a, a + cfg.block) for a in rng.integers(0, starts_max, size=nb)])[:frames]
        idx = np.minimum(idx, frames - 1)
        out[s] = pinv @ R[idx].reshape(-1)
    return out


@dataclass
class Verdict:
    passed: bool
    checks: dict = field(default_factory=dict)
    reasons: list = field(default_factory=list)
    # Every check of the evidence holds (the held-out drop, the BIC, each new parameter significant and free of its
    # bounds) and only the floor's do not (4, 5): the candidate explains part of the discrepancy, and something
    # else is missing beside it (:func:`causalgs.discover.search.pairs`).
    partial: bool = False


def judge(*, base_train: float, base_future: float, train: float, future: float, best_train: float,
          k_new: int, n_eff: int, k_base: int, z: dict, cfg: GateConfig,
          noise: float | None = None, future_noise: float | None = None, window_noise: float | None = None,
          pinned: dict | None = None, z_all: dict | None = None) -> Verdict:  # fmt: skip
    """Apply the checks of the module docstring. ``*_train``/``*_future``: mean squared errors (one unit);
    ``z``: new parameter → |value − off| / standard error (the residuals' bootstrap); ``z_all``: the same over
    every source of error (None: ``z``); ``noise``: the noise floor as a mean squared error in
    the same unit (None: not checked); ``future_noise``: what a correct model would miss the held-out frames by,
    likewise (None: ``noise``); ``window_noise``: what a correct model would fit the window by, likewise (None:
    ``noise``); ``pinned``: new parameter → "upper"/"lower", those held at a bound."""
    z_all = z if z_all is None else z_all
    drop = 1.0 - future / max(base_future, 1e-300)
    d_bic = bic(train, n_eff, k_base + k_new) - bic(base_train, n_eff, k_base)
    reached = max(best_train, noise) if noise is not None else best_train
    floor_ok = train <= (cfg.floor_factor**2) * reached and train < base_train
    if future_noise is None:
        future_noise = noise
    if window_noise is None:
        window_noise = noise
    noise_ok = window_noise is None or train <= (cfg.noise_factor**2) * window_noise
    future_ok = future_noise is None or future <= (cfg.future_factor**2) * future_noise
    checks = {
        "future_drop": drop,
        "delta_bic": d_bic,
        "z": z,
        "z_all": z_all,
        "train_rms_ratio_to_best": math.sqrt(train / max(best_train, 1e-300)),
        "train_rms_ratio_to_noise": None if noise is None else math.sqrt(train / max(noise, 1e-300)),
        "train_rms_ratio_to_window_floor": None if window_noise is None else
        math.sqrt(train / max(window_noise, 1e-300)),
        "future_rms_ratio_to_noise": None if noise is None else math.sqrt(future / max(noise, 1e-300)),
        "future_rms_ratio_to_floor": None if future_noise is None else math.sqrt(future / max(future_noise, 1e-300)),
    }
    reasons = []
    if drop <= -0.005:
        reasons.append(f"held-out error rises {-100 * drop:.0f}%")
    elif drop < 0.005:
        reasons.append("held-out error does not change")
    elif drop < cfg.future_drop:
        reasons.append(f"held-out error drops {100 * drop:.0f}% (< {100 * cfg.future_drop:.0f}%)")
    if d_bic >= 0:
        reasons.append(f"BIC does not improve (Δ = {d_bic:+.1f})")
    pinned = pinned or {}
    for p, side in pinned.items():
        reasons.append(f"{p} is held at the {side} bound of its range: the data asks for more than the model allows")
    weak = [p for p, v in z.items() if not v >= cfg.sigmas and p not in pinned]
    if weak:
        reasons.append(f"not significant: {', '.join(f'{p} ({z[p]:.1f} SE)' for p in weak)}")
    loose = [p for p, v in z_all.items() if not v >= cfg.every_sigmas and p not in pinned and p not in weak]
    if loose:
        reasons.append("its interval from every source of error holds the off value: "
                       f"{', '.join(f'{p} ({z_all[p]:.1f} SE)' for p in loose)}")  # fmt: skip
    evidence = not reasons
    if not floor_ok:
        reasons.append("the refit does not reach the floor (not converged)")
    elif not noise_ok:
        what = "the noise floor" if window_noise == noise else "the noise floor and what the lens cannot show"
        reasons.append(f"the refit stays {math.sqrt(train / window_noise):.2f}× above {what} (explains only part)")
    if not future_ok:
        what = "the noise floor" if future_noise == noise else "what a correct model would"
        reasons.append(f"the refit misses the held-out frames by {math.sqrt(future / future_noise):.1f}× {what} "
                       "(it fits the window, not the law)")
    return Verdict(not reasons, checks, reasons, partial=evidence and bool(reasons))
