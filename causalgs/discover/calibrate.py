"""Least-squares calibration of a :class:`~causalgs.discover.model.PhysicsModel` through the MPM.

The objective is the mean squared distance between simulated and measured positions over chosen frames, in cm².
It is a small nonlinear least-squares problem (a dozen parameters against thousands of residuals) whose parameters
compensate for one another along long, narrow valleys (a lower throw against a drag, a friction against a push).
Levenberg–Marquardt is made for exactly that: each iteration takes the Jacobian of the residuals by forward
differences (one rollout per free parameter) and solves the damped Gauss–Newton step. Measured on a hidden
quadratic drag (``causalgs discover-table``): L-BFGS (strong-Wolfe line search, autodiff gradients through the
checkpointed backward) crawled along the valley and stopped at 0.1438 cm² with the drag 36% low after 75 iterations;
Levenberg–Marquardt reached 0.1246 cm² with it 7% off in 3 iterations. Its Jacobian costs one rollout per free
parameter, so a model with many bodies (a fitted run's motion patterns) is calibrated by L-BFGS, whose cost does not
grow with the number of parameters (``method="auto"``).

A trial point where the simulation blows up (a one-line :class:`~causalgs.errors.CausalGSError`) is a rejected
step. Several starting stiffnesses guard against the local minima of elastic fits (a soft and a stiff fit of one
bounce).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np
import torch

from causalgs.discover import workers
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


class Resume:
    """Where a calibration keeps its state as it goes, so that one stopped part-way goes on from there: the scan's
    grid points rolled out so far and its best, the warm-up's result, and Levenberg–Marquardt's θ and damping after
    every accepted iteration. ``states`` (a dict, name → JSON-ready state) is updated in place and ``save()``
    called after every change; a calibration finds its own states under ``prefix``. L-BFGS keeps none (its history
    is not worth a file; a model with that many bodies calibrates once per start)."""

    def __init__(self, states: dict | None = None, save=None, prefix: str = ""):
        self.states = {} if states is None else states
        self.save = save
        self.prefix = prefix

    def get(self, stage: str) -> dict | None:
        return self.states.get(self.prefix + stage)

    def put(self, stage: str, state: dict) -> None:
        self.states[self.prefix + stage] = state
        if self.save is not None:
            self.save()

    def sub(self, name: str) -> Resume:
        return Resume(self.states, self.save, f"{self.prefix}{name}/")


def _vector(theta: torch.Tensor) -> list[float]:
    return [float(v) for v in theta.detach().double()]


def scale(obs, frames) -> np.ndarray | None:
    """[F, P, 1] the residual weights of ``frames`` (:meth:`~causalgs.discover.observation.Observation.residual_scale`;
    None: all 1)."""
    s = obs.residual_scale()
    return None if s is None else s[list(frames)][..., None]


def mse(model: PhysicsModel, theta: torch.Tensor, frames) -> torch.Tensor:
    """The weighted mean squared distance (cm²) of the rollout from the measurement over ``frames``."""
    x = model.rollout(theta, frames)
    target = torch.as_tensor(model.obs.x[list(frames)], dtype=torch.float64)
    d = (x - target) / UNIT
    s = scale(model.obs, frames)
    if s is not None:
        d = d * torch.as_tensor(s, dtype=d.dtype)
    return (d**2).mean()


def fit_frames(model: PhysicsModel) -> list[int]:
    """The frames a calibration may use: every observed frame after the first."""
    return list(range(1, model.obs.observed))


JAC_STEP = 0.01  # forward-difference step of θ (internal units) for the Levenberg–Marquardt Jacobian
# Levenberg–Marquardt pays one rollout per free parameter and iteration, L-BFGS a forward and a backward rollout per
# evaluation whatever their number: "auto" takes L-BFGS above this many (a fitted run with many bodies).
LM_MAX_PARAMS = 24


def positions(model: PhysicsModel, theta: torch.Tensor, frames) -> np.ndarray:
    """The simulated positions at ``frames``, flattened, in cm, times their residual weights (:func:`scale`): with
    :func:`targets`, every linearised least squares over them is the weighted one."""
    with torch.no_grad():
        x = model.rollout(theta, frames).numpy()
    s = scale(model.obs, frames)
    return (x if s is None else x * s).reshape(-1) / UNIT


def targets(obs, frames) -> np.ndarray:
    """The measured positions at ``frames`` as :func:`positions` gives the simulated ones (flattened, cm, weighted)."""
    x = np.asarray(obs.x[list(frames)], dtype=np.float64)
    s = scale(obs, frames)
    return (x if s is None else x * s).reshape(-1) / UNIT


def change(model: PhysicsModel, theta: torch.Tensor, moved: torch.Tensor, frames, x0: np.ndarray,
           plan: list[int]) -> np.ndarray:  # fmt: skip
    """:func:`positions` at ``moved`` minus those at ``theta`` (``x0``, rolled out at the substep schedule ``plan``),
    both at one schedule. The CFL limit follows the parameters (a stiffness through the wave speed, a viscosity
    through its own limit), and a count of substeps that jumps changes symplectic Euler's O(dt) gravity bias, which
    a difference would read as a sensitivity (:meth:`~causalgs.sim.mpm.Simulator.holding`). So ``moved`` is rolled
    out holding ``plan``; where it needs more substeps than the hold allows, θ is rolled out again at ``moved``'s
    finer schedule. The model's ``plan_of`` is ``moved``'s afterwards either way."""
    with model.sim.holding(plan):
        x = positions(model, moved, frames)
    finer = list(model.sim.last_plan)
    if finer != list(plan):
        kept = model.plan_of
        with model.sim.holding(finer):
            x0 = positions(model, theta, frames)
        model.plan_of = kept
    return x - x0


def jacobian(model: PhysicsModel, theta: torch.Tensor, frames, indices=None, base=None,
             step: float = JAC_STEP) -> np.ndarray:  # fmt: skip
    """[N, k] forward-difference derivatives of :func:`positions` with respect to the entries ``indices`` of θ, each
    at one substep schedule (:func:`change`). ``base``: the positions at θ when already known (used where the
    model's last rollout was at θ over ``frames``, whose schedule it keeps; otherwise θ is rolled out again for its
    schedule). A step that blows the simulation up is taken backwards."""
    indices = list(range(len(theta))) if indices is None else list(indices)
    last = model.plan_of  # (θ, frames, plan) of the model's last rollout
    known = (base is not None and last is not None and frames is not None and last[1] == tuple(int(f) for f in frames)
             and torch.equal(last[0], theta.detach().double()))  # fmt: skip
    x0 = base if known else positions(model, theta, frames)
    plan = model.plan_of[2]  # θ's, either way
    if workers.active() is not None and len(indices) > 1:
        return _parallel_jacobian(model, theta, frames, indices, x0, plan, step)
    cols = []
    for i in indices:
        th = theta.clone()
        th[i] += step
        try:
            cols.append(change(model, theta, th, frames, x0, plan) / step)
        except CausalGSError:
            th[i] -= 2 * step
            cols.append(-change(model, theta, th, frames, x0, plan) / step)
    return np.stack(cols, axis=1) if cols else np.zeros((len(x0), 0))


def _parallel_jacobian(model: PhysicsModel, theta: torch.Tensor, frames, indices: list[int], x0: np.ndarray,
                       plan: list[int], step: float) -> np.ndarray:  # fmt: skip
    """:func:`jacobian`'s columns rolled out by the active worker pool (:mod:`causalgs.discover.workers`), each as
    :func:`change` takes it: forwards, and backwards where the forward step blew the simulation up."""

    def stepped(sign: float, which) -> list:
        out = []
        for i in which:
            th = theta.detach().clone()
            th[i] += sign * step
            out.append(th)
        return workers.moved(model, theta, out, frames, plan)

    results = dict(zip(indices, stepped(1.0, indices), strict=True))
    blown = [i for i in indices if isinstance(results[i], str)]
    sign = dict.fromkeys(indices, 1.0)
    for i, r in zip(blown, stepped(-1.0, blown) if blown else [], strict=True):
        if isinstance(r, str):
            raise CausalGSError(r)
        results[i], sign[i] = r, -1.0
    cols = [sign[i] * (results[i][0] - (x0 if results[i][1] is None else results[i][1])) / step for i in indices]
    return np.stack(cols, axis=1)


def calibrate(model: PhysicsModel, theta0: torch.Tensor, frames=None, *, iterations: int = 25,
              free=None, warm: float = 0.0, method: str = "auto", scan: int = 0,
              resume: Resume | None = None) -> Fit:  # fmt: skip
    """Levenberg–Marquardt (``method="lm"``) or L-BFGS (``"lbfgs"``; ``"auto"``: Levenberg–Marquardt for at most
    ``LM_MAX_PARAMS`` free parameters) from ``theta0`` on ``frames`` (default: the fit window), at most
    ``iterations`` iterations. ``free``: indices of θ to fit (default all); the rest stay at ``theta0``. ``warm``
    > 0: first fit the leading ``warm`` fraction of the frames (half the iterations), then all of them: a short
    horizon is nearly convex in the throw and the forces, so the long one starts in the right basin rather than
    where parameters compensate for one another (a friction that mimics a forward push, a throw that mimics drag).
    ``scan`` ≥ 1 (True: 1): start instead from the best point of a coarse grid of materials and learned effect
    parameters (:func:`scanned_start`, its planes' heights ``scan`` units either side; 0: no scan). ``resume``: where
    the calibration keeps its state as it goes and goes on from (:class:`Resume`; None: nowhere)."""
    if method not in ("auto", "lm", "lbfgs"):
        raise CausalGSError(f"calibration method '{method}' is not one of auto, lm, lbfgs")
    if method == "auto":
        method = "lm" if (len(theta0) if free is None else len(list(free))) <= LM_MAX_PARAMS else "lbfgs"
    frames = fit_frames(model) if frames is None else list(frames)
    if scan:
        theta0 = scanned_start(model, theta0, frames, resume=resume, reach=int(scan))
    if warm > 0 and len(frames) >= 6:
        head = frames[: max(3, round(warm * len(frames)))]
        done = None if resume is None else resume.get("warm")
        if done is not None:
            theta0 = torch.tensor(done["theta"], dtype=torch.float64)
        else:
            theta0 = calibrate(model, theta0, head, iterations=max(5, iterations // 2), free=free, method=method,
                               resume=None if resume is None else resume.sub("warm")).theta  # fmt: skip
            if resume is not None:
                resume.put("warm", {"theta": _vector(theta0)})
    if method == "lm":
        return _levenberg_marquardt(model, theta0, frames, iterations, free, resume)
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
    E0 = _start_stiffness(model, theta0)
    return Fit(theta, final, count[0], E0)


SCAN_E = (5e3, 1e4, 3e4, 1e5, 3e5)  # Pa: the stiffnesses of the scan (inside the model's range)
SCAN_NU = (0.2, 0.3, 0.4)
SCAN_MAX = 250  # rollouts at most: beyond, the learned effect parameters keep their start


def scanned_start(model: PhysicsModel, theta0: torch.Tensor, frames, resume: Resume | None = None,
                  reach: int = 1) -> torch.Tensor:  # fmt: skip
    """``theta0`` moved to the best point (lowest error over ``frames``, one rollout each) of a coarse grid: every
    body at each stiffness of ``SCAN_E`` and ratio of ``SCAN_NU``, each learned effect parameter at its start and
    one unit (:data:`~causalgs.discover.model.SCALES`) either side, a plane's height (``ground.d``) ``reach`` units
    either side. The throw keeps its start.

    A contact makes the window's error a rough function of the materials, the friction and the ground: from a start
    by the flight alone, a bounce goes to the basin nearest it. On the landing control from video (seed 1, 81
    frames, the first contact at frame 41) both starting stiffnesses ended at 0.173 cm² with the ground 1.9 cm high
    and E = 7.8 kPa (truth 28.5 kPa); the scan's best point (E = 30 kPa, ν = 0.3, the ground a centimetre under the
    fit's, μ = 0.4; 0.267 cm² before any step) calibrated to 0.037 cm² at E = 29.6 kPa, ν = 0.29, μ = 0.29 (truth
    0.3) and the ground 1.2 mm low, as a start at the truth did; the scan's second best went back to 0.173.

    ``resume``: kept after every grid point (the points done and the best so far) and gone on from
    (:class:`Resume`)."""
    frames = list(frames)
    mats = [(E, nu) for E in SCAN_E for nu in SCAN_NU if model.E_range[0] <= E <= model.E_range[1]
            and model.nu_range[0] <= nu <= model.nu_range[1]]  # fmt: skip
    start = model.values(theta0)
    effects, levels = [], []
    for i, k in enumerate(model.knobs):
        if k.kind == "effect":  # its start, and a unit (or more) either side where that stays inside its bounds
            v = start[k.name]
            effects.append(i)
            steps = range(1, (reach if k.name.endswith(".d") else 1) + 1)
            levels.append([v] + [w for j in steps for w in (v - j * k.scale, v + j * k.scale)
                                 if (k.lower is None or w > k.lower) and (k.upper is None or w < k.upper)])  # fmt: skip
    grid = list(itertools.product(*levels))
    if len(mats) * len(grid) > SCAN_MAX:
        grid = grid[:1]
    E_idx = [i for i, k in enumerate(model.knobs) if k.kind == "E"]
    nu_idx = [i for i, k in enumerate(model.knobs) if k.kind == "nu"]
    best, best_loss, done = theta0, math.inf, 0
    kept = None if resume is None else resume.get("scan")
    if kept is not None:  # (a loss of 1e300 at θ0: no grid point rolled out yet)
        done, best_loss, best = int(kept["done"]), float(kept["loss"]), torch.tensor(kept["theta"], dtype=torch.float64)

    def keep(i):
        if resume is not None:  # JSON has no infinity
            resume.put("scan", {"done": i, "loss": min(best_loss, 1e300), "theta": _vector(best)})

    def at(E: float, nu: float, point) -> torch.Tensor:
        th = theta0.detach().clone()
        th[E_idx] = model.E_internal(E)
        th[nu_idx] = model.nu_internal(nu)
        for j, v in zip(effects, point, strict=True):
            th[j] = model.knobs[j].internal(v)
        return th

    todo = list(enumerate(itertools.product(mats, grid)))[done:]
    pool = workers.active()
    batch = 1 if pool is None else 2 * pool.jobs  # a batch of grid points at once, kept after each
    for b in range(0, len(todo), batch):
        chunk = todo[b : b + batch]
        if chunk[0][0] > done:
            keep(chunk[0][0])
        thetas = [at(E, nu, point) for _, ((E, nu), point) in chunk]
        found = workers.losses(model, thetas, frames) if pool is not None else [_loss(model, thetas[0], frames)]
        for th, loss in zip(thetas, found, strict=True):
            if loss is not None and loss < best_loss:
                best, best_loss = th, loss
    keep(len(mats) * len(grid))
    return best


def _loss(model: PhysicsModel, theta: torch.Tensor, frames) -> float | None:
    """:func:`mse` at ``theta``, or None where the simulation blows up or the error is not finite."""
    try:
        with torch.no_grad():
            loss = float(mse(model, theta, frames))
    except CausalGSError:
        return None
    return loss if math.isfinite(loss) else None


def _start_stiffness(model: PhysicsModel, theta0: torch.Tensor) -> float:
    """The first body's E at the start (Pa): what a fit is labelled by."""
    return float(model.values(theta0)[model.names[model.base_indices()[0]]]) if model.base_indices() else 0.0


INERT = 0.1  # of the measurement noise: a parameter whose unit step moves no point further is not fitted here


def inert_step(model: PhysicsModel) -> float:
    """The largest displacement (m) a unit step of a parameter may cause and still be held by a Levenberg–Marquardt
    iteration: :data:`INERT` of the measurement noise (at least 1 µm). Marquardt's scaling by the Jacobian's own
    diagonal makes steps scale-free, so a column that is only the float32 rollout's rounding noise (a stiffness
    during a rigid flight, which does not depend on it: 5 µm per unit step on the toss landing's first 40%, against
    4 cm over the whole window) gets a step of any size. Unheld, the warm-up fit of the flight sent the stiffness
    to a bound of its range from every start, and the full window then settled in a poor minimum (0.233 cm² against
    0.098 near the middle of the range)."""
    from causalgs.discover.observation import noise_floor

    noise = model.obs.noise if model.obs.noise else noise_floor(model.obs)
    return max(INERT * float(noise), 1e-6)


def live(model: PhysicsModel, J: np.ndarray) -> np.ndarray:
    """[k] bool: the columns of ``J`` (cm per unit step, as :func:`jacobian` returns) whose unit step moves some point
    further than :func:`inert_step`."""
    return np.abs(J).max(0) * UNIT > inert_step(model)


def _levenberg_marquardt(model: PhysicsModel, theta0: torch.Tensor, frames, iterations: int, free,
                         resume: Resume | None = None) -> Fit:  # fmt: skip
    """Damped Gauss–Newton steps (J^T J + λ diag(J^T J)) δ = J^T r; λ shrinks after an accepted step and grows
    after a rejected one (a worse or blown-up trial). Stops when an accepted step gains less than 1e-5 of the loss,
    or when no damping finds a better point. ``resume``: θ, λ and the count kept after every accepted iteration,
    and gone on from (:class:`Resume`)."""
    idx = list(range(len(theta0))) if free is None else list(free)
    E0 = _start_stiffness(model, theta0)
    target = targets(model.obs, frames)
    theta = theta0.detach().clone()
    kept = None if resume is None else resume.get("lm")
    first, lam, count = 0, 1e-2, 1
    if kept is not None:
        theta = torch.tensor(kept["theta"], dtype=torch.float64)
        first, lam, count = int(kept["iteration"]), float(kept["lam"]), int(kept["evaluations"])
    try:
        x = positions(model, theta, frames)
    except CausalGSError:
        return Fit(theta, BLOWN, 1, E0)
    if not np.isfinite(x).all():
        return Fit(theta, BLOWN, 1, E0)
    r = target - x
    loss = float(r @ r) / len(r)
    for it in range(first, iterations):
        J = jacobian(model, theta, frames, idx, base=x)
        count += len(idx)
        moving = live(model, J)  # the rest of θ is held where it is
        if not moving.any():
            break
        J = J[:, moving]
        A, g = J.T @ J, J.T @ r
        D = np.diag(A) + 1e-9 * max(float(np.diag(A).max()), 1e-12)
        before = loss
        accepted = False
        for x2, trial in _trials(model, theta, frames, A, D, g, np.asarray(idx)[moving], lam):
            count += 1
            if x2 is None:  # the simulation blew up
                lam *= 10.0
                continue
            r2 = target - x2
            l2 = float(r2 @ r2) / len(r2) if np.isfinite(x2).all() else math.inf
            if l2 < loss:
                theta, x, r, loss = trial, x2, r2, l2
                lam = max(lam / 3.0, 1e-7)
                accepted = True
                break
            lam *= 10.0
        if not accepted or before - loss < 1e-5 * before:
            break
        if resume is not None:
            resume.put("lm", {"theta": _vector(theta), "lam": lam, "evaluations": count, "iteration": it + 1})
    return Fit(theta, loss, count, E0)


TRIALS = 10  # damping factors an iteration tries, each ten times the last, before it stops


def _trials(model: PhysicsModel, theta: torch.Tensor, frames, A: np.ndarray, D: np.ndarray, g: np.ndarray,
            where: np.ndarray, lam: float):  # fmt: skip
    """(positions or None where the simulation blew up, θ) of the damped steps from ``theta`` at λ, 10λ, 100λ, …
    (:data:`TRIALS` at most), lazily: the caller stops at the first it accepts. With a worker pool
    (:mod:`causalgs.discover.workers`) they are rolled out a pool's worth at once, the later ones on cores that
    would otherwise wait; the model's ``plan_of`` is then each one's as it is handed out, as a rollout here leaves
    it (:func:`jacobian` finds the accepted one's schedule there)."""
    def step(k: int) -> torch.Tensor:
        delta = np.linalg.solve(A + lam * 10.0**k * np.diag(D), g)
        trial = theta.clone()
        trial[where] += torch.as_tensor(delta, dtype=trial.dtype)
        return trial

    pool = workers.active()
    if pool is None:
        for k in range(TRIALS):
            trial = step(k)
            try:
                yield positions(model, trial, frames), trial
            except CausalGSError:
                yield None, trial
        return
    frames = [int(f) for f in frames]
    for first in range(0, TRIALS, pool.jobs):
        batch = [step(k) for k in range(first, min(first + pool.jobs, TRIALS))]
        for trial, got in zip(batch, workers.rollouts(model, batch, frames), strict=True):
            if isinstance(got, str):
                yield None, trial
                continue
            model.plan_of = (trial.detach().double().clone(), tuple(frames), got[1])
            yield got[0], trial


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
