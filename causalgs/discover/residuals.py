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
    """[T, P] bool: the point's body touches the ground at that frame (its lowest points within ``band`` of the
    plane; a body slides or rests as a whole, so its top is "in contact" too). False everywhere without a ground."""
    if obs.ground is None:
        return np.zeros(obs.x.shape[:2], dtype=bool)
    out = np.zeros(obs.x.shape[:2], dtype=bool)
    for b in range(obs.bodies):
        sel = obs.body == b
        low = np.quantile(obs.x[:, sel, 2], 0.05, axis=1) - obs.ground  # robust to a few noisy points
        out[:, sel] = (low < band)[:, None]
    return out


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
    """What each candidate's residual acceleration is proportional to, from the measured (smoothed) motion:
    per body centroid [F, B, 3] — ``v`` (linear drag), ``vv`` (|v|·v, quadratic drag), ``contact`` (the tangential
    velocity while the body touches the ground: friction) — and per point [F, P, 3] ``internal`` (velocity relative
    to the body's mean: material damping acts on internal motion only). ``const`` (a uniform field) needs none."""
    frames = list(frames)
    dt = float(np.median(np.diff(obs.times)))
    v, _ = derivatives(obs.x[frames], dt, window)
    vc = _centroids(v, obs)
    out = {"v": vc, "vv": np.linalg.norm(vc, axis=-1, keepdims=True) * vc}
    touch = contact(obs, band)[frames]
    tc = np.stack([touch[:, obs.body == b].any(1) for b in range(obs.bodies)], axis=1)[..., None]
    vt = vc.copy()
    vt[..., 2] = 0.0
    out["contact"] = tc * vt
    out["internal"] = v - vc[:, obs.body]
    return out


def _centroids(a: np.ndarray, obs: Observation) -> np.ndarray:
    """[F, P, 3] → [F, B, 3], the mean over each body's points."""
    return np.stack([a[:, obs.body == b].mean(1) for b in range(obs.bodies)], axis=1)


def smooth_frames(obs: Observation, frames, band: float, margin: int = 3) -> np.ndarray:
    """[F] bool: the frames more than ``margin`` frames away from any body touching down or lifting off. An impact
    a frame earlier or later in the model than in the measurement leaves a residual impulse there that no smooth
    law explains; signatures are read off the other frames."""
    frames = list(frames)
    touch = contact(obs, band)
    state = np.stack([touch[:, obs.body == b].any(1) for b in range(obs.bodies)], axis=1)  # [T, B]
    change = np.nonzero((state[1:] != state[:-1]).any(1))[0] + 1  # frames where some body's state flips
    far = np.ones(len(frames), dtype=bool)
    for i, f in enumerate(frames):
        if len(change) and np.abs(change - f).min() <= margin:
            far[i] = False
    return far


def signatures(a_res: np.ndarray, drv: dict[str, np.ndarray], obs: Observation) -> dict[str, float]:
    """How much of the residual acceleration each driver explains with one coefficient per body (``const``: one
    constant vector per body): for the body drivers, the fraction of the variance of the bodies' *centroid*
    residual accelerations (averaging over a body's points removes most of the measurement noise, which a second
    derivative amplifies); for ``internal``, the fraction of the residual relative to the centroid."""
    ac = _centroids(a_res, obs)
    rel = a_res - ac[:, obs.body]
    out = {}
    for name in [*[k for k in drv if k != "internal"], "const", "internal"]:
        r_all, d_all = (rel, drv.get("internal")) if name == "internal" else (ac, drv.get(name))
        total = float((r_all**2).sum())
        explained = 0.0
        for b in range(obs.bodies):
            sel = (obs.body == b) if name == "internal" else np.array([b])
            r = r_all[:, sel].reshape(-1, 3)
            if name == "const":
                explained += float((r.mean(0) ** 2).sum() * len(r))
                continue
            d = d_all[:, sel].reshape(-1, 3)
            den = float((d * d).sum())
            if den > 0:
                explained += float((r * d).sum()) ** 2 / den
        out[name] = explained / total if total > 0 else 0.0
    return out


def twist_basis(r: np.ndarray) -> np.ndarray:
    """[3n, 6]: the flattened velocities u + ω × r of points at offsets ``r`` [n, 3] per unit twist (u, ω)."""
    A = np.zeros((len(r), 3, 6))
    A[:, :, :3] = np.eye(3)
    A[:, 0, 4], A[:, 0, 5] = r[:, 2], -r[:, 1]
    A[:, 1, 3], A[:, 1, 5] = -r[:, 2], r[:, 0]
    A[:, 2, 3], A[:, 2, 4] = r[:, 1], -r[:, 0]
    return A.reshape(-1, 6)


def affine_basis(r: np.ndarray) -> np.ndarray:
    """[3n, 12]: the flattened displacements u + M r of points at offsets ``r`` [n, 3] per unit translation u and
    per unit entry of the matrix M (row-major)."""
    A = np.zeros((len(r), 3, 12))
    A[:, :, :3] = np.eye(3)
    for i in range(3):
        A[:, i, 3 + 3 * i : 6 + 3 * i] = r
    return A.reshape(-1, 12)


def quadratic_basis(r: np.ndarray) -> np.ndarray:
    """[3n, 30]: :func:`affine_basis` and, per coordinate, the six second-order monomials of the offsets ``r``
    (x², y², z², xy, xz, yz): a body bent or bulged as well as strained."""
    mono = np.stack([r[:, 0] ** 2, r[:, 1] ** 2, r[:, 2] ** 2, r[:, 0] * r[:, 1], r[:, 0] * r[:, 2],
                     r[:, 1] * r[:, 2]], axis=1)  # fmt: skip
    Q = np.zeros((len(r), 3, 18))
    for i in range(3):
        Q[:, i, 6 * i : 6 * i + 6] = mono
    return np.concatenate([affine_basis(r), Q.reshape(-1, 18)], axis=1)


def lens_floor(sim: np.ndarray, obs: Observation, frames) -> float:
    """Per-coordinate RMS (m) of what is left of the residual (measured − simulated, [F, P, 3] at ``frames``) once
    every body's best rigid motion is removed frame by frame (a translation and a small rotation, least squares);
    where the measurement's lens is affine (tracks that stretch each pattern, :attr:`Observation.lens_kind`), its
    best smooth deformation instead: a translation, any linear map and a second-order bend or bulge
    (:func:`quadratic_basis`), as at the frames where rigid tracks stretch (:attr:`Observation.stretch`).

    The part of a residual that no better dynamics of the bodies the lens can show could remove: measurement noise
    and the noise of the reconstructed rest shape (each point's start offset), which are independent from point to
    point. A missing force, drag or friction moves a body as a whole and is removed with the rigid part, so this is
    the floor a correct model reaches, estimated from the data and the base fit alone.

    Through an affine lens a missing effect that squashes a body for good (plastic flow) leaves a residual that is
    a deformation of the body, and the rigid part alone counted it as noise: on the plastic landing of ``causalgs
    synth toss`` (seed 0, from video) that floor came out at 18.2 mm per coordinate, 8.6× the noise credited to the
    tracks, and the base model, 23.7 mm off on the fit window, was read as within 1.3× of it. A body squashed on
    the ground is not strained uniformly either: its foot, held by the ground, spreads differently from its top, a
    bulge the tracks' patterns show and no single linear map follows. On a second fit of that landing (16
    patterns) the base's residual left 14.6 mm per coordinate without each body's rigid motion, 7.5 mm without its
    affine motion, 4.4 mm without this basis and 3.7 mm with third-order terms too (noise 1.9 mm). The deformation
    cannot be removed pattern by pattern instead: the tracks and the simulation seen through the same lens are both
    blends of the patterns' affine motions, so their difference is too, and removing those would leave nothing."""
    frames = list(frames)
    r = obs.x[frames] - sim
    smooth = obs.mix is not None and obs.lens_kind == "affine"
    stretched = [smooth or (obs.stretch is not None and bool(obs.stretch[f])) for f in frames]
    left, count = 0.0, 0
    for b in range(obs.bodies):
        sel = obs.body == b
        p = obs.x[frames][:, sel]
        q = p - p.mean(1, keepdims=True)
        for k in range(len(frames)):
            rk = r[k, sel]
            A = (quadratic_basis if stretched[k] else twist_basis)(q[k])
            sol, *_ = np.linalg.lstsq(A, rk.reshape(-1), rcond=None)
            e = rk.reshape(-1) - A @ sol
            left += float(e @ e)
            count += max(len(e) - A.shape[1], 1)
    return float(np.sqrt(left / max(count, 1)))

