"""The cheap screen: how much each candidate could explain, from one sensitivity rollout per parameter.

At the base fit θ_b the residual is r = x_obs − x(θ_b) over the fit frames. The base parameters' sensitivities J_b
(one finite-difference rollout each) span what recalibrating the base could still absorb; a candidate's sensitivity
J_c (one rollout at its probe value) is what the new effect adds. The joint linear least-squares step on [J_b, J_c]
predicts the candidate's gain *beyond* a recalibration of the base, i.e. with J_c projected off J_b: a candidate
whose signature the base parameters can mimic (a stiffness change, a different throw) scores nothing here.
An effect that acts only past a threshold (a yield stress) is probed at several values, a rollout each, and scored
by the probe that explains most: one probe above every stress of the rollout sees no flow at all, and one far
below it flows so much that its secant points elsewhere. On the plastic landing from video (seed 0, 144 frames)
the single probe of 2 kPa put plasticity last of six (gain 0.083), and it was never refitted.
Structural candidates (a sticky ground in place of a Coulomb one) have no "off" value; their screen compares the
base-projected residuals with and without the change.
A candidate's step stays within its parameter's range (a drag coefficient is not negative): where the free step
leaves it, the step is solved again with that bound (bounded least squares), so what a candidate cannot do counts
for nothing. On the pull towards a point from video (seed 2), the free step put both drags at −2.4 (the pull
speeds the block up) and screened them at gains of 0.91 and 0.90, second and third of six; their refits stayed at
zero drag and changed nothing.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy.optimize import lsq_linear

from causalgs.discover.calibrate import change, jacobian, positions, targets
from causalgs.discover.candidates import Candidate
from causalgs.discover.model import PhysicsModel
from causalgs.errors import CausalGSError

STEP = 0.05  # finite-difference step of θ in internal units (a twentieth of a visible change)


def transfer(src: PhysicsModel, theta: torch.Tensor, dst: PhysicsModel, extra: dict | None = None) -> torch.Tensor:
    """θ of ``dst`` with every knob that ``src`` also has copied over; the others at ``dst``'s start values, or at
    the physical values given in ``extra`` (by name)."""
    out = dst.initial()
    for i, k in enumerate(dst.knobs):
        if k.name in src.names:
            out[i] = theta[src.index(k.name)]
        elif extra and k.name in extra:
            out[i] = k.internal(float(extra[k.name]))
        elif k.kind == "effect":
            out[i] = k.internal(float(dst.effects.flat()[k.index]))
    return out


def sensitivities(model: PhysicsModel, theta: torch.Tensor, frames, indices=None, base=None) -> np.ndarray:
    """[N, k] finite-difference derivatives of the flattened positions (cm) over ``frames`` with respect to the
    entries ``indices`` of θ (internal units) at the screen's step; ``base`` is the rollout at θ when known."""
    return jacobian(model, theta, frames, indices, base, step=STEP)


def _residual_after(J: np.ndarray, r: np.ndarray) -> tuple[float, np.ndarray]:
    if J.shape[1] == 0:
        return float(r @ r), np.zeros(0)
    sol, *_ = np.linalg.lstsq(J, r, rcond=None)
    e = r - J @ sol
    return float(e @ e), sol


def _bounded_residual_after(J: np.ndarray, r: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> tuple[float, np.ndarray]:
    """:func:`_residual_after` with the solution held within [lo, hi] per column (±inf: free)."""
    e, sol = _residual_after(J, r)
    if np.all(sol >= lo) and np.all(sol <= hi):
        return e, sol
    norm = np.linalg.norm(J, axis=0)
    norm[norm == 0] = 1.0  # a column that moves nothing: its bound is kept as it is
    fit = lsq_linear(J / norm, r, bounds=(lo * norm, hi * norm), method="bvls")
    sol = np.clip(fit.x / norm, lo, hi)
    res = r - J @ sol
    return float(res @ res), sol


@dataclass
class Screened:
    candidate: Candidate
    gain: float  # predicted fraction of the base residual (sum of squares) removed beyond base recalibration
    step: dict  # predicted parameter values
    model: PhysicsModel
    theta: torch.Tensor  # the candidate model's θ at the base fit (the refit's start)
    probe: tuple[float, ...] | None = None  # the probe values that scored ``gain`` (None: a structural change)


def _step_bounds(model: PhysicsModel, c: Candidate, theta: torch.Tensor, Jb: np.ndarray):
    """The bounds of the joint step on [J_b, J_c]: the base's columns free, each candidate parameter's within its
    range from its value at ``theta``."""
    start = model.values(theta)
    lo, hi = np.full(Jb.shape[1] + len(c.params), -np.inf), np.full(Jb.shape[1] + len(c.params), np.inf)
    for j, p in enumerate(c.params):
        knob = model.knobs[model.index(p)]
        if knob.kind == "effect" and knob.lower is not None:
            lo[Jb.shape[1] + j] = knob.lower - start[p]
            if knob.upper is not None:
                hi[Jb.shape[1] + j] = knob.upper - start[p]
    return lo, hi


def candidate_model(base: PhysicsModel, c: Candidate, models: dict | None = None) -> PhysicsModel:
    """The model of ``base`` with candidate ``c`` added (from ``models``, a cache by key, where it is there)."""
    model = (models or {}).get(c.key) or PhysicsModel(base.obs, c.spec(base.effects), c.learn(base.learn),
                                                      res=base.res, E_range=base.E_range, nu_range=base.nu_range)
    if models is not None:
        models[c.key] = model
    return model


def screen(base: PhysicsModel, theta: torch.Tensor, candidates: list[Candidate], frames,
           models: dict | None = None) -> list[Screened]:  # fmt: skip
    """Score every candidate (see the module docstring); best first. ``models`` caches candidate models by key."""
    frames = list(frames)
    target = targets(base.obs, frames)
    xb = positions(base, theta, frames)
    r = target - xb
    Jb = sensitivities(base, theta, frames, base.base_indices(), base=xb)
    rb, _ = _residual_after(Jb, r)
    out = []
    for c in candidates:
        model = candidate_model(base, c, models)
        th = transfer(base, theta, model)
        xc = positions(model, th, frames)
        plan = model.plan_of[2]
        rc = target - xc
        idx = [model.index(p) for p in c.params]
        if c.replaces is not None:  # structural: compare the base-projected residuals with and without the change
            rr, _ = _residual_after(Jb, rc)
            gain = (rb - rr) / max(rb, 1e-300)
            out.append(Screened(c, gain, {p: model.values(th)[p] for p in c.params}, model, th))
            continue
        best, bounds = None, _step_bounds(model, c, th, Jb)
        for probes in c.screen_probes():  # a threshold's probes: the one that explains most counts
            cols = []
            for p, i, probe in zip(c.params, idx, probes, strict=True):
                knob = model.knobs[i]
                th2 = th.clone()
                th2[i] = knob.internal(probe)
                start = model.values(th)[p]
                try:
                    cols.append(change(model, th, th2, frames, xc, plan) / (probe - start))
                except CausalGSError:
                    cols.append(np.zeros_like(xc))
            Jc = np.stack(cols, axis=1)
            rr, sol = _bounded_residual_after(np.concatenate([Jb, Jc], axis=1), rc, *bounds)
            gain = (rb - rr) / max(rb, 1e-300)
            if best is None or gain > best[0]:
                best = (gain, sol, probes)
        gain, sol, probes = best
        start = model.values(th)
        step = {p: start[p] + float(s) for p, s in zip(c.params, sol[Jb.shape[1] :], strict=True)}
        out.append(Screened(c, gain, step, model, th, probes))
    return sorted(out, key=lambda s: -s.gain)


def screen_rows(screened: list[Screened]) -> list[dict]:
    """What a screen found, as JSON: per candidate its key, gain, predicted step and probe (see :func:`restore`)."""
    return [{"effect": s.candidate.key, "gain": float(s.gain), "step": {p: float(v) for p, v in s.step.items()},
             "probe": None if s.probe is None else [float(v) for v in s.probe]} for s in screened]  # fmt: skip


def restore(base: PhysicsModel, theta: torch.Tensor, candidates: list[Candidate], rows: list[dict]) -> list[Screened]:
    """The screen of ``candidates`` from ``base`` at ``theta`` as :func:`screen_rows` kept it, without a rollout:
    each candidate's model and start θ are made again (:func:`transfer` is exact), its scores taken from ``rows``.
    Best first, as :func:`screen` orders them."""
    by_key = {r["effect"]: r for r in rows}
    if sorted(by_key) != sorted(c.key for c in candidates):
        raise CausalGSError(f"a kept screen holds {sorted(by_key)}, not the candidates {[c.key for c in candidates]}")
    out = []
    for c in candidates:
        r = by_key[c.key]
        model = candidate_model(base, c)
        probe = None if r["probe"] is None else tuple(float(v) for v in r["probe"])
        out.append(Screened(c, float(r["gain"]), {p: float(v) for p, v in r["step"].items()}, model,
                            transfer(base, theta, model), probe))  # fmt: skip
    return sorted(out, key=lambda s: -s.gain)
