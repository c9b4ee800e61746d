"""Which way is up, and how long is a metre: the physics frame of a scene, inferred from its video.

The simulator, the ground plane and the simulation box are written for a z-up world in which gravity is 9.8 units/s²
(:data:`GRAVITY`). A dataset posed by Blender or by structure-from-motion has its own up direction and scale, so the
fit infers them after the kinematic stage and re-poses the model into that frame (:meth:`CausalGS.reframe`):

- **free flight** (:func:`free_flight`): the tracked centroid of every motion pattern, in sliding windows of about a
  tenth of a second; a window's acceleration counts if it stands out of its fit's noise (4 standard errors, a
  scale-free test). The acceleration most windows share (within 15%) is gravity's candidate; the windows that agree
  with it are joined into flights, and one parabola per flight with a shared acceleration gives g in scene units.
  Long flights average out what a body's spin adds to the acceleration of a centroid off its centre of mass.
- **the static scene's dominant plane** (:func:`dominant_plane`): RANSAC on the static Gaussians (inliers within
  0.5% of the scene size), refined by least squares; it counts if it holds a quarter of them. Its normal points to
  the cameras' side (a floor is seen from above).

Up is the plane's normal, with gravity from free flight along it (within :data:`AGREE_DEG`; a plane of thousands of
Gaussians fixes a direction more precisely than a few flights); without a plane, the flight's −g. A steady
acceleration across the plane is a body sliding or rolling to rest, never taken for gravity.
Gravity's magnitude is the flight's acceleration along up; without free flight the scene is taken to be in metres.
Neither a plane nor free flight: a one-line error that says how to give up by hand.

Before the kinematic stage, whose settings have absolute units, the model is put into a *normalising* frame
(:func:`normalising`: the canonical Gaussians' dominant plane up, a fixed extent), so that the kinematic fit, and the
tracks the frame is then inferred from, do not depend on the data's own frame and scale.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from causalgs.errors import CausalGSError
from causalgs.similarity import Similarity, rotation_between

REFERENCE_SIZE = 1.2  # the extent the kinematic stage sees a scene at (the benchmark scenes' floors are 1.2 m)
GRAVITY = 9.8  # the simulator's gravity (causalgs.sim.effects "gravity" default), units/s² of the physics frame
AGREE_DEG = 15.0  # a plane whose normal is this close to −g is the floor gravity acts towards
WINDOW_SECONDS = 0.1  # sliding windows of free-flight detection (at least 5 frames)
SIGNIFICANT = 4.0  # a window's acceleration counts when it is this many standard errors from zero
CARRY = 0.05  # ... and would move a body by this fraction of the scene size over the observed time
WOBBLE = 0.6  # a window this close to gravity (a fraction of it) is a wobble of the track, not a contact
JOIN_RMS = 2.0  # two pieces of one flight are joined if one parabola fits both within this times their own RMS
OUTLIER = 4.0  # a flight's end frame this many times the parabolas' RMS residual off them is dropped
SHARED = 0.15  # windows whose accelerations differ by less than this fraction of the candidate's agree with it
PLANE_TOL = 0.005  # RANSAC inlier distance, as a fraction of the scene size
PLANE_SHARE = 0.25  # a dominant plane holds at least this share of the static Gaussians


@dataclass
class FrameConfig:
    """How the fit finds the physics frame (see :mod:`causalgs.model.upright`).

    - ``infer``: infer up and gravity's magnitude from the video; false: the data's frame is taken as z up, metres.
    - ``up``: the data's up direction, when known (three numbers; empty: inferred).
    - ``gravity``: gravity's magnitude in the data's units per s², when known (0: measured from free flight).
    - ``learn_gravity``: refine the measured magnitude in the physical stage (the simulator's gravity is trained with
      the materials; run.json ``frame.gravity_learned``). A flight tracked by the kinematic fit gives it within about
      5-10%; the simulation of the flight against the images narrows it.
    """

    infer: bool = True
    up: tuple[float, ...] = ()
    gravity: float = 0.0
    learn_gravity: bool = True

    def __post_init__(self):
        self.up = tuple(float(a) for a in self.up)
        if self.up and (len(self.up) != 3 or not np.linalg.norm(self.up) > 0 or not np.all(np.isfinite(self.up))):
            raise CausalGSError(f"frame.up = {list(self.up)} must be three numbers, not all zero")
        if not (math.isfinite(self.gravity) and self.gravity >= 0):
            raise CausalGSError(f"frame.gravity = {self.gravity} must be a positive number (0: measured)")


@dataclass
class Plane:
    normal: np.ndarray  # unit, towards the cameras
    offset: float  # normal · x = offset
    share: float  # of the static Gaussians within PLANE_TOL of it
    rms: float  # inliers' RMS distance (scene units)


@dataclass
class Flight:
    g: np.ndarray  # the shared acceleration of the flights (scene units/s²)
    flights: int  # how many flights (runs of agreeing windows) were joined
    frames: int  # frames in them
    rms: float  # the parabolas' RMS residual (scene units)
    segments: list[tuple[int, int, int]] = field(default_factory=list)  # (track, first frame, last frame) of each

    def mapped(self, sim: Similarity) -> Flight:
        """The same flight in another frame (``sim`` maps this one's coordinates to it)."""
        return Flight(sim.vectors(self.g), self.flights, self.frames, sim.scale * self.rms, list(self.segments))


@dataclass
class Upright:
    """The inferred frame: ``up`` and ``gravity`` (magnitude) in the data's units; :meth:`similarity` maps the data
    into the physics frame."""

    up: np.ndarray
    gravity: float | None  # None: not measured (no free flight), metres assumed
    source: str  # what gave up: "plane", "flight", "plane+flight" or "given"
    plane: Plane | None = None
    flight: Flight | None = None
    notes: list[str] = field(default_factory=list)

    def similarity(self) -> Similarity:
        """x_physics = s R x with R taking up to +z (the smallest such turn) and s = 9.8 / gravity."""
        s = 1.0 if self.gravity is None else GRAVITY / self.gravity
        return Similarity.make(rotation_between(self.up, [0.0, 0.0, 1.0]), s, what="the inferred frame")

    def mapped(self, sim: Similarity) -> Upright:
        """The same evidence expressed in another frame (``sim`` maps this one's coordinates to it)."""
        plane = None
        if self.plane is not None:
            n, d = sim.plane(self.plane.normal, self.plane.offset)
            plane = Plane(n, d, self.plane.share, sim.scale * self.plane.rms)
        flight = None if self.flight is None else self.flight.mapped(sim)
        gravity = None if self.gravity is None else self.gravity * sim.scale
        return Upright(sim.directions(self.up), gravity, self.source, plane, flight, list(self.notes))

    def to_json(self) -> dict:
        out = {"up": self.up.tolist(), "gravity": None if self.gravity is None else float(self.gravity),
               "source": self.source, "notes": self.notes, "similarity": self.similarity().to_json()}  # fmt: skip
        if self.plane is not None:
            p = self.plane
            out["plane"] = {"normal": p.normal.tolist(), "offset": float(p.offset), "share": float(p.share),
                            "rms": float(p.rms)}  # fmt: skip
        if self.flight is not None:
            f = self.flight
            out["flight"] = {"g": f.g.tolist(), "flights": int(f.flights), "frames": int(f.frames),
                             "rms": float(f.rms)}  # fmt: skip
        return out


# -- free flight -------------------------------------------------------------------------------------------------------
def _design(n: int, fps: float) -> np.ndarray:
    t = (np.arange(n) - (n - 1) / 2) / fps
    return np.stack([np.ones(n), t, 0.5 * t * t], axis=1)


def window_accelerations(track: np.ndarray, fps: float, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Accelerations [W, 3] of least-squares parabolas through ``width``-frame windows of ``track`` [F, 3], and each
    one's standard error [W] (from the window's residual scatter, pooled over the axes)."""
    A = _design(width, fps)
    pinv = np.linalg.pinv(A)
    wins = np.lib.stride_tricks.sliding_window_view(track, width, axis=0)  # [W, 3, width]
    coef = np.einsum("kt,wdt->wkd", pinv, wins)  # [W, 3 coefficients, 3 axes]
    resid = wins - np.einsum("tk,wkd->wdt", A, coef)
    sigma = np.sqrt((resid**2).sum((1, 2)) / (3 * (width - 3)))
    return coef[:, 2], sigma * np.sqrt((pinv[2] ** 2).sum())


def free_flight(tracks: np.ndarray, fps: float, size: float, axis: np.ndarray | None = None) -> Flight | None:
    """Gravity from tracked centroids ``tracks`` [F, G, 3] in a scene of ``size`` (see the module docstring); None
    without free flight. A window's acceleration counts if it stands out of its fit's noise and would carry a body
    over the whole observed time by at least :data:`CARRY` of the scene (a smooth fit's slow drift is not a force),
    and, with an ``axis`` (a floor's normal), if it is within :data:`AGREE_DEG` of it: a body sliding to rest on the
    floor decelerates as steadily as a falling one accelerates, but along the floor."""
    F = len(tracks)
    width = max(5, round(WINDOW_SECONDS * fps))
    if F < width + 1:
        return None
    duration = (F - 1) / fps
    least = 2 * CARRY * size / duration**2
    per_track, samples = [], []
    for g in range(tracks.shape[1]):
        acc, se = window_accelerations(tracks[:, g], fps, width)
        norm = np.linalg.norm(acc, axis=1)
        keep = (norm > SIGNIFICANT * se) & (norm > least)
        if axis is not None:
            keep &= np.abs(acc @ axis) >= math.cos(math.radians(AGREE_DEG)) * norm
        per_track.append((acc, keep))
        samples.extend(acc[keep])
    if len(samples) < 3:
        return None
    S = np.asarray(samples)
    norms = np.linalg.norm(S, axis=1)
    agree = np.linalg.norm(S[:, None] - S[None], axis=2) < SHARED * norms[:, None]
    best = int(np.argmax(agree.sum(1)))
    if agree[best].sum() < 3:
        return None
    g0 = np.median(S[agree[best]], axis=0)
    flights = []
    for g, (acc, keep) in enumerate(per_track):
        dev = np.linalg.norm(acc - g0, axis=1) / np.linalg.norm(g0)
        flights += _runs(g, keep & (dev < 2 * SHARED), dev < WOBBLE, width)
    return _joint_parabola(tracks, flights, fps, width)


def flight_along(tracks: np.ndarray, segments: list[tuple[int, int, int]], fps: float) -> Flight | None:
    """Gravity from tracked centroids ``tracks`` [F, G, 3] over flight ``segments`` (track, first, last frame) found
    on smoother tracks of the same bodies; None without a segment. A smooth track's wobble splits one flight into
    several: two segments of a track less than a window apart are joined where one parabola through both fits them
    within :data:`JOIN_RMS` times the RMS of a parabola each (a contact between them would bend the joined one).
    Noisy tracks, whose windows scatter too much to find a flight of their own, still give the acceleration over
    a long flight: a tumbling box's tracks gave gravity within 2% of the truth over one 29-frame flight, 18% off
    over its four pieces."""
    width = max(5, round(WINDOW_SECONDS * fps))
    kept = [(g, a, b) for g, a, b in sorted(segments) if g < tracks.shape[1] and b < len(tracks) and b > a]
    joined: list[tuple[int, int, int]] = []
    for g, a, b in kept:
        if joined and joined[-1][0] == g and a - joined[-1][2] <= width:
            last = joined[-1]
            whole = _parabolas(tracks, [(g, last[1], max(b, last[2]))], fps)
            parts = _parabolas(tracks, [last, (g, a, b)], fps)
            if whole is not None and parts is not None and whole[1].rms <= JOIN_RMS * parts[1].rms:
                joined[-1] = (g, last[1], max(b, last[2]))
                continue
        joined.append((g, a, b))
    return _joint_parabola(tracks, joined, fps, width) if joined else None


def _runs(track: int, agrees: np.ndarray, near: np.ndarray, width: int) -> list[tuple[int, int, int]]:
    """(track, first frame, last frame) of each flight: a run of consecutive windows near gravity (a smooth track's
    wobble), from its first to its last window that agrees with it. A contact's windows are far from gravity for as
    long as a window spans the contact, so they end a run."""
    out = []
    w = 0
    while w < len(near):
        if not near[w]:
            w += 1
            continue
        end = w
        while end + 1 < len(near) and near[end + 1]:
            end += 1
        ok = np.nonzero(agrees[w : end + 1])[0]
        if len(ok):
            out.append((track, w + int(ok[0]), w + int(ok[-1]) + width - 1))
        w = end + 1
    return out


def _joint_parabola(tracks: np.ndarray, flights: list[tuple[int, int, int]], fps: float,
                    width: int) -> Flight | None:  # fmt: skip
    """One parabola per flight, all with one acceleration (:func:`_parabolas`); a flight's end frame whose residual
    is more than :data:`OUTLIER` times the fit's RMS (a contact the windows half-spanned) is dropped and the fit
    repeated, a flight kept at least ``width`` frames long."""
    fit = _parabolas(tracks, flights, fps)
    for _ in range(width):
        if fit is None:
            return None
        resid, flight = fit
        trimmed = []
        for (g, a, b), r in zip(flights, resid, strict=True):
            limit = OUTLIER * flight.rms
            while b - a + 1 > width and max(r[0], r[-1]) > limit:
                if r[0] >= r[-1]:
                    a, r = a + 1, r[1:]
                else:
                    b, r = b - 1, r[:-1]
            trimmed.append((g, a, b))
        if trimmed == flights:
            return flight
        flights = trimmed
        fit = _parabolas(tracks, flights, fps)
    return None if fit is None else fit[1]


def _parabolas(tracks: np.ndarray, flights: list[tuple[int, int, int]],
               fps: float) -> tuple[list[np.ndarray], Flight] | None:  # fmt: skip
    """Linear least squares for one acceleration g [3] and each flight's start position and velocity; each flight's
    per-frame residual distances and the :class:`Flight`."""
    if not flights:
        return None
    rows = sum(b - a + 1 for _, a, b in flights)
    A = np.zeros((rows, 1 + 2 * len(flights)))
    Y = np.zeros((rows, 3))
    r = 0
    for i, (g, a, b) in enumerate(flights):
        t = (np.arange(a, b + 1) - a) / fps
        n = len(t)
        A[r : r + n, 0] = 0.5 * t * t
        A[r : r + n, 1 + 2 * i] = 1.0
        A[r : r + n, 2 + 2 * i] = t
        Y[r : r + n] = tracks[a : b + 1, g]
        r += n
    coef, *_ = np.linalg.lstsq(A, Y, rcond=None)
    dist = np.linalg.norm(A @ coef - Y, axis=1)
    rms = float(np.sqrt((dist**2).mean()))
    bounds = np.cumsum([0] + [b - a + 1 for _, a, b in flights])
    resid = [dist[bounds[i] : bounds[i + 1]] for i in range(len(flights))]
    return resid, Flight(coef[0], len(flights), int(rows), rms, [(int(g), int(a), int(b)) for g, a, b in flights])


# -- the dominant plane ------------------------------------------------------------------------------------------------
def dominant_plane(points: np.ndarray, towards: np.ndarray, seed: int = 0, tries: int = 400) -> Plane | None:
    """The plane holding the most ``points`` [N, 3] within PLANE_TOL of the scene size (RANSAC, then least squares on
    its inliers), its normal turned towards ``towards`` [3]; None if it holds less than PLANE_SHARE of them."""
    if len(points) < 50:
        return None
    lo, hi = np.quantile(points, 0.01, axis=0), np.quantile(points, 0.99, axis=0)
    tol = PLANE_TOL * float(np.linalg.norm(hi - lo))
    rng = np.random.default_rng(seed)
    best, best_count = None, 0
    for _ in range(tries):
        a, b, c = points[rng.choice(len(points), 3, replace=False)]
        n = np.cross(b - a, c - a)
        if np.linalg.norm(n) < 1e-12:
            continue
        n = n / np.linalg.norm(n)
        count = int((np.abs((points - a) @ n) < tol).sum())
        if count > best_count:
            best, best_count = (n, float(n @ a)), count
    if best is None or best_count < PLANE_SHARE * len(points):
        return None
    n, d = best
    inl = points[np.abs(points @ n - d) < tol]
    centre = inl.mean(0)
    n = np.linalg.svd(inl - centre, full_matrices=False)[2][-1]
    if n @ (towards - centre) < 0:
        n = -n
    dist = (inl - centre) @ n
    share = float((np.abs((points - centre) @ n) < tol).sum() / len(points))
    return Plane(n, float(n @ centre), share, float(np.sqrt((dist**2).mean())))


# -- before the kinematic stage ------------------------------------------------------------------------------------
def normalising(points: np.ndarray, cameras: np.ndarray, seed: int = 0) -> Similarity:
    """A first frame for the kinematic stage, from the canonical Gaussians [N, 3] alone: the dominant plane's normal
    turned to +z (none found: no turn) and the scene scaled to :data:`REFERENCE_SIZE` across (its robust extent).
    The kinematic stage has settings in absolute units (the pattern centres' step, the rest penalty on speeds, the
    velocity network's output scale); in this frame they mean the same for any data's units."""
    plane = dominant_plane(points, cameras.mean(0), seed)
    R = np.eye(3) if plane is None else rotation_between(plane.normal, [0.0, 0.0, 1.0])
    turned = points @ R.T
    extent = float((np.quantile(turned, 0.99, axis=0) - np.quantile(turned, 0.01, axis=0)).max())
    return Similarity.make(R, REFERENCE_SIZE / extent if extent > 0 else 1.0, what="the normalising frame")


# -- both --------------------------------------------------------------------------------------------------------------
def infer_upright(static: np.ndarray, tracks: np.ndarray, fps: float, cameras: np.ndarray, size: float,
                  config: FrameConfig, seed: int = 0) -> Upright:  # fmt: skip
    """The physics frame of a scene of ``size`` from its static Gaussians [N, 3], tracked pattern centroids
    [F, G, 3] at ``fps`` and camera centres [C, 3] (see the module docstring)."""
    given_g = config.gravity if config.gravity > 0 else None
    if config.up:
        up = np.asarray(config.up) / np.linalg.norm(config.up)
        flight = free_flight(tracks, fps, size, up) if tracks.size else None
        gravity = given_g or (float(-flight.g @ up) if flight is not None and -flight.g @ up > 0 else None)
        return Upright(up, gravity, "given", None, flight)
    plane = dominant_plane(static, cameras.mean(0), seed)
    notes = []
    if plane is not None and tracks.size:
        flight = free_flight(tracks, fps, size, plane.normal)
        if flight is not None:
            up = plane.normal if -flight.g @ plane.normal > 0 else -plane.normal
            return Upright(up, given_g or float(-flight.g @ up), "plane+flight", plane, flight)
    flight = free_flight(tracks, fps, size) if tracks.size else None
    if flight is not None and plane is None:
        up = -flight.g / np.linalg.norm(flight.g)
        return Upright(up, given_g or float(np.linalg.norm(flight.g)), "flight", None, flight, notes)
    if plane is not None:
        if flight is not None:  # steady, but across the floor: a body sliding or rolling to rest, not falling
            angle = math.degrees(math.acos(np.clip(abs(plane.normal @ flight.g) / np.linalg.norm(flight.g), -1, 1)))
            notes.append(f"the only steady acceleration seen is {angle:.0f}° off the floor's normal (sliding or "
                         f"rolling, not falling): up from the floor")  # fmt: skip
        if given_g is None:
            notes.append("no free flight: gravity's magnitude not measured, the scene taken to be in metres")
        return Upright(plane.normal, given_g, "plane", plane, None, notes)
    raise CausalGSError("cannot infer the up direction: the static scene has no dominant plane and nothing is seen in "
                        "free flight; give it with --set frame.up=[x,y,z] (or frame.infer=false for a z-up metric "
                        "frame), with --resume to continue this run")  # fmt: skip
