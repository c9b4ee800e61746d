"""The disagreement map: where and when the calibrated simulation departs from the measurement, and what the
departure looks like.

- :func:`error_curve`: RMS distance per frame (over all points, and per body);
- :func:`point_errors`: RMS distance per point over chosen frames (the residual heat on the particles);
- :func:`contact`: which points touch the ground at each frame (within one model cell of the plane);
- :func:`first_departure`: the first frame where the error rises above a multiple of the fit window's floor and
  stays there, and the region it starts in (the body, contact or flight, and the worst points' centroid);
- :func:`residual_accelerations`: accelerations of the measured minus the simulated trajectories, from
  Savitzky–Golay derivatives of both (never raw second differences, which amplify noise by 1/dt²);
- :func:`signatures`: how much of the residual acceleration each candidate's driver explains (the fraction of its
  variance captured by a least-squares fit a = θ·driver, per body), the evidence quoted in reports.
"""

from __future__ import annotations

import numpy as np
from scipy.signal import savgol_filter

from causalgs.discover.observation import Observation


def error_curve(sim: np.ndarray, obs: Observation, frames) -> dict:
    """RMS distance (m) per frame: ``{"all": [F], "bodies": [B, F]}`` for ``sim`` [F, P, 3] at ``frames``."""
    d2 = ((sim - obs.x[list(frames)]) ** 2).sum(-1)  # [F, P]
    per_body = np.stack([np.sqrt(d2[:, obs.body == b].mean(1)) for b in range(obs.bodies)])
    return {"all": np.sqrt(d2.mean(1)), "bodies": per_body}


def point_errors(sim: np.ndarray, obs: Observation, frames) -> np.ndarray:
    """RMS distance (m) per point over ``frames``."""
    return np.sqrt(((sim - obs.x[list(frames)]) ** 2).sum(-1).mean(0))


def contact(obs: Observation, band: float) -> np.ndarray:
    """[T, P] bool: the point is within ``band`` of the ground plane (False everywhere without a ground)."""
    if obs.ground is None:
        return np.zeros(obs.x.shape[:2], dtype=bool)
    return obs.x[..., 2] - obs.ground < band


def first_departure(curve: np.ndarray, frames, floor: float, factor: float = 3.0, hold: int = 2) -> int | None:
    """The first of ``frames`` from which the error ``curve`` stays above ``factor``·``floor`` for ``hold`` frames."""
    frames = list(frames)
    above = curve > factor * max(floor, 1e-12)
    for i in range(len(frames)):
        if above[i : i + hold].all() and len(above[i : i + hold]) == min(hold, len(frames) - i):
            return frames[i]
    return None


def region(sim_frame: np.ndarray, obs: Observation, frame: int, band: float, top: float = 0.1) -> dict:
    """Where the error is at ``frame``: the body with the largest RMS, whether its worst points touch the ground,
    and the centroid of the worst ``top`` fraction of points."""
    d = np.sqrt(((sim_frame - obs.x[frame]) ** 2).sum(-1))
    per_body = [float(np.sqrt((d[obs.body == b] ** 2).mean())) for b in range(obs.bodies)]
    b = int(np.argmax(per_body))
    k = max(1, round(top * len(d)))
    worst = np.argsort(d)[-k:]
    touching = contact(obs, band)[frame][worst].mean() if obs.ground is not None else 0.0
    return {
        "body": obs.names[b],
        "body_errors": dict(zip(obs.names, per_body, strict=True)),
        "contact": "ground contact" if touching >= 0.5 else "flight",
        "centroid": obs.x[frame][worst].mean(0).round(4).tolist(),
    }


def derivatives(x: np.ndarray, dt: float, window: int = 7, order: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Smoothed velocity and acceleration of trajectories ``x`` [T, ...] (Savitzky–Golay, ``window`` frames)."""
    w = min(window, len(x) - (1 - len(x) % 2))
    if w <= order:
        z = np.zeros_like(x)
        return z, z
    v = savgol_filter(x, w, order, deriv=1, delta=dt, axis=0, mode="interp")
    a = savgol_filter(x, w, order, deriv=2, delta=dt, axis=0, mode="interp")
    return v, a


def residual_accelerations(sim: np.ndarray, obs: Observation, frames, window: int = 7) -> np.ndarray:
    """[F, P, 3] smoothed acceleration of (measured − simulated) over consecutive ``frames``."""
    frames = list(frames)
    dt = float(np.median(np.diff(obs.times)))
    _, a = derivatives(obs.x[frames] - sim, dt, window)
    return a


def drivers(obs: Observation, frames, band: float, window: int = 7) -> dict[str, np.ndarray]:
    """What each candidate's residual acceleration is proportional to, [F, P, 3] per driver, from the measured
    (smoothed) motion: ``const`` (a uniform field, one column per axis), ``v`` (linear drag), ``vv`` (|v|·v,
    quadratic drag), ``contact`` (the tangential velocity of points touching the ground: friction), ``internal``
    (velocity relative to the body's mean: material damping acts on internal motion only)."""
    frames = list(frames)
    dt = float(np.median(np.diff(obs.times)))
    v, _ = derivatives(obs.x[frames], dt, window)
    out = {"v": v, "vv": np.linalg.norm(v, axis=-1, keepdims=True) * v}
    touch = contact(obs, band)[frames][..., None]
    vt = v.copy()
    vt[..., 2] = 0.0
    out["contact"] = touch * vt
    internal = np.empty_like(v)
    for b in range(obs.bodies):
        sel = obs.body == b
        internal[:, sel] = v[:, sel] - v[:, sel].mean(1, keepdims=True)
    out["internal"] = internal
    return out


def signatures(a_res: np.ndarray, drv: dict[str, np.ndarray], body: np.ndarray) -> dict[str, float]:
    """Fraction of the residual acceleration's variance (over all points) that each driver explains, with one
    coefficient per body (``const``: one constant vector per body)."""
    out = {}
    total = float((a_res**2).sum())
    if total <= 0:
        return {k: 0.0 for k in [*drv, "const"]}
    for name in [*drv, "const"]:
        explained = 0.0
        for b in np.unique(body):
            r = a_res[:, body == b].reshape(-1, 3)
            if name == "const":
                explained += float((r.mean(0) ** 2).sum() * len(r))
                continue
            d = drv[name][:, body == b].reshape(-1, 3)
            den = float((d * d).sum())
            if den > 0:
                explained += float((r * d).sum()) ** 2 / den
        out[name] = explained / total
    return out
