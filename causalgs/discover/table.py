"""The hidden-effect table: does ``discover`` find what was hidden, and only that?

Every case simulates the ``toss`` scene (:func:`causalgs.synth.physics.toss_setup`) with a set of effects, observes
its particles with measurement noise, and runs :func:`causalgs.discover.search.discover` with a model whose effects
lack one of them (or lack nothing, for the negative controls). The rows say what was found, how far its parameter
is from the truth, the held-out error before and after, and the time. ``causalgs discover-table`` runs it.
The held-out error is given three ways: against the noisy measurement (it cannot fall below the noise, the row's
``floor``), against the noise-free truth, and there beside the truth's own physics calibrated from the same
measurement (:func:`truth_floor`): every simulation starts from the measured first frame, and the noise of that
rest shape moves the bounces by millimetres that no model, however right, can take back.

- **hidden**: one effect of the catalogue present in the scene and missing in the model; the goal is that effect
  first, its parameter within 10%, the held-out error down by half or more;
- **control**: the model has every effect of the scene, with a nuisance of the base fit — a noisy reconstructed
  rest shape, an initial velocity started 10% off, a stiffness started at half or twice the truth; the goal is
  "no missing effect";
- **outside**: a position-dependent pull towards a point (``attractor``), not in the catalogue; the goal is
  "unexplained discrepancy", not a wrong name;
- **pair**: a confusable pair (sticky ground against a model that may learn its friction): told apart, or
  reported as ambiguous.

At this (trajectory) level the measurement is the project's own MPM at the model's grid with every particle
observed: the table tests the discovery logic — the screen, the refits, the gate, the uncertainty — on data whose
answer is known, with noise and nuisances as the only departures from the model. The departure of a real scene
from any grid (discretisation, tracking) is what a fitted run's discovery faces (``causalgs discover RUN``).
With ``rigid`` (``--rigid-tracks``) every body is seen through its best rigid motion, as tracks from video see it,
and discovered through that lens: what such tracks hide (an elastic wobble, a permanent squash) is tested on its
own, apart from the errors of tracking images.
"""

from __future__ import annotations

import dataclasses
import re
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from causalgs.discover.journal import Journal, calibration_options, fingerprint
from causalgs.discover.observation import Observation, synthesize
from causalgs.discover.report import finite
from causalgs.discover.search import DiscoverConfig, discover
from causalgs.errors import CausalGSError
from causalgs.io import write_json, write_text

BASE = "gravity;ground:mu=0.3;walls"
SLIP = "gravity;ground:mu=0.0;walls"


@dataclass(frozen=True)
class Case:
    name: str
    kind: str  # "hidden", "control", "outside", "pair"
    scene: str  # effects of the simulated scene
    model: str  # effects of the model discover starts from
    learn: tuple[str, ...] = ("ground.mu",)
    expect: str | None = None  # the candidate that should be named ("none": no missing effect; "unexplained")
    also: tuple[str, ...] = ()  # further hidden effects, each to be named (any order, any round)
    truth: dict = field(default_factory=dict)  # fitted parameter name -> true value
    rest_noise: float = 0.0  # m, on the first frame (a noisy reconstructed rest shape)
    velocity_start: float = 1.0  # the base calibration starts from this multiple of the true initial velocity
    stiffness_start: float | None = None  # the base calibration starts from this multiple of the true stiffness

    @property
    def expected(self) -> str | None:
        """What the row says was expected: the one effect, or every hidden one joined by "+"."""
        return "+".join((self.expect, *self.also)) if self.also else self.expect


CASES: tuple[Case, ...] = (
    Case("force", "hidden", BASE + ";force:b=0.8,0.0,0.0", BASE, expect="force",
         truth={"force.b[0]": 0.8, "force.b[1]": 0.0, "force.b[2]": 0.0}),
    Case("linear_drag", "hidden", BASE + ";linear_drag:c=0.6", BASE, expect="linear_drag",
         truth={"linear_drag.c": 0.6}),
    Case("quadratic_drag", "hidden", BASE + ";quadratic_drag:k=0.6", BASE, expect="quadratic_drag",
         truth={"quadratic_drag.k": 0.6}),
    # Viscosity matters where strain rates are high: the landing (η·v/L against E·strain needs η of a few hundred
    # Pa·s for this block; at 20 Pa·s the base stays within 1.1× of the noise floor and nothing is detectable).
    Case("damping", "hidden", BASE + ";damping:eta=200", BASE, expect="damping", truth={"damping.eta": 200.0}),
    Case("friction", "hidden", BASE, SLIP, learn=(), expect="friction", truth={"ground.mu": 0.3}),
    Case("sticky", "pair", "gravity;ground_sticky;walls", BASE, expect="sticky"),
    Case("plasticity", "hidden", BASE + ";plasticity:yield_stress=1500", BASE, expect="plasticity",
         truth={"plasticity.yield_stress": 1500.0}),
    # Two hidden at once: both must be named (the force shows in flight, the viscosity at the landing; in release
    # 74 neither alone reached the floor and nothing passed; since release 75 found together by the joint refit)
    Case("force + damping", "hidden", BASE + ";force:b=0.8,0.0,0.0;damping:eta=200", BASE, expect="force",
         also=("damping",), truth={"force.b[0]": 0.8, "force.b[1]": 0.0, "force.b[2]": 0.0, "damping.eta": 200.0}),
    Case("control: clean", "control", BASE, BASE, expect="none"),
    Case("control: noisy rest shape", "control", BASE, BASE, expect="none", rest_noise=0.004),
    Case("control: velocity 10% off", "control", BASE, BASE, expect="none", velocity_start=1.1),
    Case("control: stiffness ×0.5", "control", BASE, BASE, expect="none", stiffness_start=0.5),
    Case("control: stiffness ×2", "control", BASE, BASE, expect="none", stiffness_start=2.0),
    Case("outside: attractor", "outside", BASE + ";attractor:k=3.0:c=0.0,0.0,0.3", BASE, expect="unexplained"),
)  # fmt: skip
BY_NAME = {c.name: c for c in CASES}


@dataclass
class TableConfig:
    seeds: int = 1
    first_seed: int = 0  # seeds first_seed .. first_seed + seeds - 1 (to spread a table over machines or runs)
    res: int = 20  # the model's and the measurement's grid
    frames: int = 30
    fps: float = 24.0
    noise: float = 0.002  # m per coordinate
    rest_noise: float = 0.002  # m, on the first frame of every case (added to the case's own)
    only: tuple[str, ...] = ()  # case names (empty: all)
    control_seeds: int | None = None  # seeds per negative control (None: ``seeds``); 4 × 5 controls = 20
    jobs: int = 1  # runs at once, each in its own process
    # observe each body through its best rigid motion, as tracks from video do (``synthesize(rigid=True)``)
    rigid: bool = False
    discover: DiscoverConfig = field(default_factory=lambda: DiscoverConfig(res=20))


def observe(case: Case, seed: int, cfg: TableConfig) -> Observation:
    return synthesize("toss", case.scene, seed=seed, points=1_000_000, frames=cfg.frames, fps=cfg.fps,
                      noise=cfg.noise, rest_noise=cfg.rest_noise + case.rest_noise,
                      reference_res=cfg.res, rigid=cfg.rigid)  # fmt: skip


def _throw(obs: Observation, scale: float = 1.0) -> dict[str, float]:
    """Every body's true initial velocity and spin (times ``scale``) by the model's parameter names."""
    out = {}
    for name, body in zip(obs.names, obs.truth["bodies"], strict=True):
        out |= {f"{name}.v0[{i}]": scale * float(body["velocity"][i]) for i in range(3)}
        out |= {f"{name}.omega0[{i}]": scale * float(body["omega"][i]) for i in range(3)}
    return out


def _start(case: Case, obs: Observation) -> tuple[dict | None, tuple[float, ...] | None]:
    start = _throw(obs, case.velocity_start) if case.velocity_start != 1.0 else None
    E = float(obs.truth["bodies"][0]["E"])
    starts = None if case.stiffness_start is None else (case.stiffness_start * E,)
    return start, starts


def score(case: Case, report: dict) -> dict:
    """The row of one run: what was found against what was expected. Where several effects were hidden
    (``case.also``), the first named must be one of them and every one must be named (in any order, in rounds of
    their own or together, as a pair fitted jointly); the parameter error is the largest over all of them."""
    # an ambiguity set's entry may be a pair fitted jointly: its effects, each by name
    found = [d["effect"] for d in report["discovered"]] or [e for a in report["ambiguous"]
                                                            for e in a.get("effects", [a["effect"]])]  # fmt: skip
    verdict = report["verdict"]
    hidden = (case.expect, *case.also)
    if case.expect == "none":
        ok = verdict == "no missing effect"
    elif case.expect == "unexplained":
        ok = verdict == "unexplained discrepancy"
    else:
        ok = bool(found) and found[0] in hidden and set(hidden) <= set(found)
    in_set = set(hidden) <= set(found) if case.expect not in ("none", "unexplained") else ok
    err = covered = None
    named = {d["effect"]: d for d in report["discovered"]}
    if case.truth and report["discovered"] and report["discovered"][0]["effect"] in hidden:
        # each true parameter is scored where its effect was named (an effect not named scores none of them)
        got, interval = {}, {}
        for effect in hidden:
            if effect in named:
                got |= named[effect]["params"]
                interval |= named[effect]["interval"]
        if all(p in got for p in case.truth):
            rel = []
            for p, true in case.truth.items():
                # a zero component is scored against its vector's size (force.b[1] against |b|, not against η)
                same = [abs(v) for k, v in case.truth.items() if k.partition("[")[0] == p.partition("[")[0]]
                scale = abs(true) if true != 0 else max(same)
                rel.append(abs(got[p] - true) / scale)
            err = max(rel)
            covered = all(interval[p][0] <= true <= interval[p][1] for p, true in case.truth.items())
    before, after = report["error_before"]["future_rms_m"], report["error_after"]["future_rms_m"]
    truth = report.get("truth_error") or {}
    t_before, t_after = truth.get("future_rms_before_m"), truth.get("future_rms_after_m")
    t_floor = truth.get("future_rms_floor_m")
    return {
        "case": case.name, "kind": case.kind, "expected": case.expected, "verdict": verdict, "found": found,
        "first_ok": ok, "in_set": in_set, "param_error": err, "interval_covers": covered,
        "future_rms_before_m": before, "future_rms_after_m": after,
        "future_drop": 1.0 - after / before if before > 0 else 0.0,
        "floor_rms_m": report.get("floor_rms_m"),
        "excess_removed": excess_removed(before, after, report.get("floor_rms_m")),
        # the predictions against the noise-free truth (synthetic scenes): what a repair is for
        "future_truth_before_m": t_before, "future_truth_after_m": t_after,
        "future_truth_drop": 1.0 - t_after / t_before if t_before else None,
        # ... and the truth's own physics calibrated from this measurement (:func:`truth_floor`): what is left of
        # the error above it
        "future_truth_floor_m": t_floor, "truth_excess_removed": excess_removed(t_before, t_after, t_floor),
        "seconds": report["seconds"],
    }  # fmt: skip


def _run_one(case_name: str, seed: int, cfg: TableConfig, out: Path, log=None) -> dict:
    """One case × seed: its folder of outputs and its row (a failing run is a row too)."""
    from causalgs.discover.report import trajectories, write_outputs

    log = log or (lambda msg: None)
    case = BY_NAME[case_name]
    t0 = time.monotonic()
    obs = observe(case, seed, cfg)
    folder = out / f"{_slug(case.name)}-s{seed}"
    folder.mkdir(parents=True, exist_ok=True)
    obs.save(folder / "observation.npz")
    start, starts = _start(case, obs)
    dcfg = cfg.discover if starts is None else dataclasses.replace(cfg.discover, starts=starts)
    # Every calibration is kept as it finishes (the case's progress.json): a table re-run after a change of the
    # gate, or after a stop, recomputes only the calibrations that change.
    key = fingerprint(calibration_options(case.model, case.learn, dcfg, start), obs.x)
    try:
        journal = Journal(folder / "progress.json", key, resume=True)
        report, traj = discover(obs, case.model, case.learn, config=dcfg, log=log, start=start, journal=journal)
    except CausalGSError as e:  # one failing case is a row of the table, not the end of it
        return _failed(case, seed, str(e), time.monotonic() - t0)
    report["source"] = str(folder / "observation.npz")
    report["truth"] = obs.truth
    if obs.clean is not None:
        full = trajectories(traj, obs)
        report["truth_error"] = truth_error(full["before"], full["after"], obs.clean, obs.observed)
        if case.kind in ("hidden", "pair"):
            report["truth_error"]["future_rms_floor_m"] = truth_floor(obs, dcfg.res, dcfg.iterations, journal)
    write_outputs(folder, report, traj, obs)
    return {**score(case, report), "seed": seed, "seconds": time.monotonic() - t0}


def _failed(case: Case, seed: int, why: str, seconds: float) -> dict:
    return {"case": case.name, "kind": case.kind, "expected": case.expected, "seed": seed, "verdict": f"failed: {why}",
            "found": [], "first_ok": False, "in_set": False, "param_error": None, "future_rms_before_m": None,
            "future_rms_after_m": None, "future_drop": 0.0, "seconds": seconds}  # fmt: skip


def _worker_init(slots, cpu_shares: list[list[int]] | None, threads: int) -> None:
    """A table's run process: the next of ``cpu_shares`` is its own (pinned there, its Taichi pool and torch one
    thread per CPU of it, its rollout workers inside it), or, where the system does not say, ``threads``."""
    import os

    import torch

    from causalgs import _ti

    with slots.get_lock():
        slot = slots.value
        slots.value += 1
    os.environ.pop(_ti.CPUS_ENV, None)  # the share is the process's CPUs now, not the table's
    if cpu_shares:
        share = cpu_shares[slot % len(cpu_shares)]
        _ti.confine(share)
        threads = len(share)
    os.environ[_ti.TI_THREADS_ENV] = str(threads)
    torch.set_num_threads(threads)
    _ti.init("cpu", "float32", quiet=True)


def _worker(case_name: str, seed: int, cfg: TableConfig, out: str) -> dict:
    return _run_one(case_name, seed, cfg, Path(out))


def plan(cfg, cases=CASES) -> list[tuple[str, int]]:
    """The (case, seed) runs of a table (``cfg``: its seeds, control seeds and ``only``), seed by seed (every case
    once before any twice: an interrupted table covers every case)."""
    cases = [c for c in cases if not cfg.only or c.name in cfg.only or c.kind in cfg.only]
    counts = {c.name: cfg.control_seeds if c.kind == "control" and cfg.control_seeds is not None else cfg.seeds
              for c in cases}  # fmt: skip
    out = []
    for k in range(max(counts.values(), default=0)):
        out += [(c.name, cfg.first_seed + k) for c in cases if k < counts[c.name]]
    return out


def truth_error(before: np.ndarray, after: np.ndarray, true: np.ndarray, observed: int) -> dict:
    """How far the predictions before and after the repair are from the truth (``true``: [T, P, 3], the same
    points without the measurement's noise): RMS per coordinate (m) of the displacement from the first frame, over
    the fit window (frames 1..observed-1) and the held-out frames. Displacements, because every simulation starts
    from the measured first frame, whose noise no model can remove; against the noisy measurement the held-out
    RMS cannot drop below the noise (:func:`excess_removed`), against the truth it can."""
    true = np.asarray(true, dtype=np.float64)
    d_true = true - true[:1]
    out = {}
    for name, sim in (("before", before), ("after", after)):
        sim = np.asarray(sim, dtype=np.float64)
        e2 = ((sim - sim[:1]) - d_true) ** 2
        out[f"fit_rms_{name}_m"] = float(np.sqrt(e2[1:observed].mean()))
        out[f"future_rms_{name}_m"] = float(np.sqrt(e2[observed:].mean())) if observed < len(true) else None
    return out


def truth_floor(obs: Observation, res: int, iterations: int = 25, journal=None) -> float | None:
    """The held-out RMS against the truth (m, as :func:`truth_error`) of the truth's own physics calibrated from
    this measurement: the scene's effects spec with their true values, the materials and throw fitted from a start at
    the truth's, every simulation started from the measured (noisy) first frame. What a repair that named every
    effect with its exact parameters would reach: the rest shape's noise moves the contacts (at a bounce or a
    landing several millimetres), which no model can undo, so a drop to this floor is all a repair can give.
    None where the observation has no truth or no held-out frames. ``journal``: where the calibration is kept
    (a resumed table does not compute it again)."""
    from causalgs.discover.model import PhysicsModel

    truth = obs.truth or {}
    if obs.clean is None or "effects_spec" not in truth or obs.observed >= len(obs.times):
        return None
    model = PhysicsModel(obs, truth["effects_spec"], (), res=res)
    theta = model.initial()
    for name, body in zip(obs.names, truth["bodies"], strict=True):
        theta[model.index(f"{name}.E")] = model.E_internal(float(body["E"]))
        theta[model.index(f"{name}.nu")] = model.nu_internal(float(body["nu"]))
    for name, value in _throw(obs).items():
        k = model.index(name)
        theta[k] = model.knobs[k].internal(value)
    journal = journal if journal is not None else Journal(None, "")
    fit = journal.calibrate("truth floor", model, theta, iterations=iterations)
    x = np.concatenate([obs.x[:1], model.rollout(fit.theta).detach().numpy()])
    return truth_error(x, x, obs.clean, obs.observed)["future_rms_before_m"]


def excess_removed(before: float, after: float, floor: float | None) -> float | None:
    """The share of the held-out mean squared error *above the noise floor* that the repair removed. The RMS
    itself cannot drop below the floor (the measurement noise is in every held-out frame), so where the base is
    already within 1.5× of the floor a 50% drop of the RMS is out of reach however right the repair is."""
    if floor is None or before is None or after is None or before**2 <= floor**2:
        return None
    return 1.0 - max(after**2 - floor**2, 0.0) / (before**2 - floor**2)


def run_table(out, cfg: TableConfig | None = None, log=None, retry_failed: bool = False) -> list[dict]:
    """Every case × seed: writes ``out/CASE-sSEED/{observation.npz, report.json, report.md, plots}``, then
    ``out/table.json`` and ``out/table.md`` (updated after every run, so an interrupted table keeps its rows; rows
    already in ``table.json`` are not run again, failed ones too unless ``retry_failed``). ``cfg.jobs`` > 1 runs
    that many cases at once, each in a fresh process (Taichi and torch share the cores between them)."""

    cfg = cfg or TableConfig()
    log = log or (lambda msg: None)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    rows, todo = pending(out, measurement(cfg), plan(cfg), retry_failed)

    def finish(row: dict) -> None:
        rows.append(row)
        log(f"{row['case']}, seed {row['seed']} -> {row['verdict']} {row['found']} ({row['seconds']:.0f} s)")
        _write(out, rows, cfg)

    def local(name: str, seed: int) -> dict:
        log(f"{name}, seed {seed}")
        return _run_one(name, seed, cfg, out, log)

    execute(todo, cfg.jobs, local, _worker, (cfg, str(out)), lambda n, s, why: _failed(BY_NAME[n], s, why, 0.0),
            finish, log)  # fmt: skip
    return rows


def measurement(cfg: TableConfig | dict) -> str:
    """The name of a trajectory table's measurement, kept in ``table.json`` (a resumed table must not mix two)."""
    rigid = cfg.get("rigid", False) if isinstance(cfg, dict) else cfg.rigid
    return "trajectory, rigid tracks" if rigid else "trajectory"


def pending(out: Path, level: str, runs: list, retry_failed: bool = False) -> tuple[list[dict], list]:
    """(the rows ``out/table.json`` holds, the runs of ``runs`` it lacks); a table of another level there is a
    one-line error. ``retry_failed``: a failed row is dropped and its run is pending again (it resumes from its
    last finished stage)."""
    from causalgs.io import read_json

    done = {}
    if (out / "table.json").is_file():
        saved = read_json(out / "table.json", "table")
        if saved.get("level", "trajectory") != level:
            raise CausalGSError(f"{out / 'table.json'} holds a table of the {saved.get('level', 'trajectory')} level, "
                                f"not of the {level} level: choose another --out")  # fmt: skip
        done = {(r["case"], r["seed"]): r for r in saved.get("rows", [])
                if not (retry_failed and str(r.get("verdict", "")).startswith("failed"))}
    return list(done.values()), [k for k in runs if k not in done]


def execute(todo: list, jobs: int, local, worker, args: tuple, failed, finish, log) -> None:
    """Run every (case, seed) of ``todo`` and hand each row to ``finish`` as it ends: here, one after the other
    (``jobs`` 1: ``local(case, seed)``), or ``jobs`` at once, each in a fresh spawned process
    (``worker(case, seed, *args)``, a module-level function), each pinned to its own share of the CPUs
    (``$CAUSALGS_TI_CPUS``, else all this process may use: :func:`causalgs.processes.shares`). A
    run that raises is a row of the table (``failed(case, seed, why)``), not the end of it. A worker process that
    dies (killed, or crashed in native code) breaks the whole pool, and every run still in it then reports the
    break, not an outcome of its own: those get no row (a resumed table runs them again), and the log names them."""
    if jobs <= 1:
        for name, seed in todo:
            finish(local(name, seed))
        return
    import multiprocessing
    import os
    from concurrent.futures import ProcessPoolExecutor

    from causalgs import _ti
    from causalgs.processes import shares, stop

    # Each run on a share of the CPUs of its own: a Taichi process runs several times faster pinned than where the
    # system moves it and its pool's handoffs wake the other CPUs (measured: causalgs._ti).
    cpus = _ti.cpus_from_env() or _ti.allowed_cpus()
    threads = max(1, (os.cpu_count() or 1) // jobs)
    ctx = multiprocessing.get_context("spawn")  # Taichi's runtime must not be forked
    pool = ProcessPoolExecutor(jobs, mp_context=ctx, initializer=_worker_init,
                               initargs=(ctx.Value("i", 0), shares(cpus, jobs), threads))  # fmt: skip
    try:
        broken = _collect(pool, todo, worker, args, failed, finish, log, jobs)
    except BaseException:
        # Stopped (Ctrl-C, or SIGTERM, which the command line turns into an exit): the workers stop too, rather
        # than the exit waiting hours for the runs under way. Each run keeps what it finished and resumes.
        stop(pool)
        raise
    pool.shutdown()
    if broken:
        log(f"a worker process died (killed or crashed), so these runs have no row; run the table again to resume "
            f"them: {', '.join(broken)}")


def _collect(pool, todo: list, worker, args: tuple, failed, finish, log, jobs: int) -> list[str]:
    """Submit ``todo`` to ``pool`` and hand each row to ``finish`` as it ends (see :func:`execute`); the runs a
    broken pool took with it."""
    from concurrent.futures import as_completed
    from concurrent.futures.process import BrokenProcessPool

    futures = {pool.submit(worker, name, seed, *args): (name, seed) for name, seed in todo}
    log(f"{len(todo)} runs, {jobs} at once")
    broken = []
    for fut in as_completed(futures):
        name, seed = futures[fut]
        try:
            row = fut.result()
        except BrokenProcessPool:
            broken.append(f"{name} (seed {seed})")
            continue
        except Exception as e:
            row = failed(name, seed, f"{type(e).__name__}: {e}")
        finish(row)
    return broken


def _slug(name: str) -> str:
    return re.sub("-+", "-", "".join(ch if ch.isalnum() else "-" for ch in name.lower())).strip("-")


def summary(rows: list[dict]) -> dict:
    """The issue's goals, as fractions over the rows of each kind."""
    def frac(sel, key):
        sel = [r for r in rows if sel(r)]
        return (sum(bool(r[key]) for r in sel) / len(sel)) if sel else None

    hidden = lambda r: r["kind"] in ("hidden", "pair")  # noqa: E731
    errs = [r["param_error"] for r in rows if r["kind"] == "hidden" and r["param_error"] is not None]

    def halved(key):  # the share of the hidden rows named first whose ``key`` (where given) is 50% or more
        vals = [r.get(key) for r in rows if r["kind"] == "hidden" and r["first_ok"]]
        vals = [v for v in vals if v is not None]
        return (sum(v >= 0.5 for v in vals) / len(vals)) if vals else None

    return {
        "hidden_first": frac(hidden, "first_ok"),
        "hidden_in_set": frac(hidden, "in_set"),
        "param_within_10pct": (sum(e <= 0.1 for e in errs) / len(errs)) if errs else None,
        # how often the reported 95% interval holds the true value (honest intervals: about 95%)
        "interval_covers_truth": frac(lambda r: r["kind"] == "hidden" and r.get("interval_covers") is not None,
                                      "interval_covers"),
        "future_drop_ge_50pct": halved("future_drop"),
        "excess_over_floor_removed_ge_50pct": halved("excess_removed"),
        "future_drop_vs_truth_ge_50pct": halved("future_truth_drop"),
        "excess_over_truth_floor_removed_ge_50pct": halved("truth_excess_removed"),
        "controls_no_effect": frac(lambda r: r["kind"] == "control", "first_ok"),
        "outside_unexplained": frac(lambda r: r["kind"] == "outside", "first_ok"),
        "runs": len(rows),
    }


def markdown(rows: list[dict]) -> str:
    L = ["| case | seed | verdict | named | param error | interval holds truth | held-out RMS before → after | floor "
         "| excess removed | held-out vs truth | time |",
         "|---|---|---|---|---|---|---|---|---|---|---|"]  # fmt: skip
    for r in rows:
        pe = "—" if r["param_error"] is None else f"{100 * r['param_error']:.1f}%"
        mark = "✓" if r["first_ok"] else "✗"
        if r["future_rms_before_m"] is None:
            err = "—"
        else:
            err = (f"{1000 * r['future_rms_before_m']:.1f} → {1000 * r['future_rms_after_m']:.1f} mm "
                   f"({change(r['future_drop'])})")  # fmt: skip
        floor = "—" if r.get("floor_rms_m") is None else f"{1000 * r['floor_rms_m']:.1f} mm"
        ex = "—" if r.get("excess_removed") is None else f"{100 * r['excess_removed']:.0f}%"
        cov = {True: "yes", False: "no"}.get(r.get("interval_covers"), "—")
        L.append(f"| {r['case']} | {r['seed']} | {mark} {r['verdict']} | {', '.join(r['found']) or '—'} | {pe} | "
                 f"{cov} | {err} | {floor} | {ex} | {vs_truth(r)} | {r['seconds']:.0f} s |")  # fmt: skip
    return "\n".join(L + goals(rows)) + "\n"


def change(drop: float) -> str:
    """A drop of the error as the tables print its change: "−80%", "+12%", and "±0%" where it rounds to none
    (the minus the typographic one, as in the reports)."""
    text = f"{-100 * drop:+.0f}"
    return "±0%" if text in ("+0", "-0") else text.replace("-", "\u2212") + "%"


def vs_truth(r: dict) -> str:
    """A row's held-out error against the truth, before → after (mm), as the tables print it."""
    if r.get("future_truth_before_m") is None or r.get("future_truth_after_m") is None:
        return "—"
    drop = "" if r.get("future_truth_drop") is None else f" ({change(r['future_truth_drop'])})"
    t_floor = r.get("future_truth_floor_m")
    floor = "" if t_floor is None else f"; the truth's physics {1000 * t_floor:.1f} mm"
    return f"{1000 * r['future_truth_before_m']:.1f} → {1000 * r['future_truth_after_m']:.1f} mm{drop}{floor}"


def goals(rows: list[dict]) -> list[str]:
    """The markdown lines of the goals reached (:func:`summary`)."""
    L = ["", "| goal | reached |", "|---|---|"]
    for k, v in summary(rows).items():
        if k != "runs":
            L.append(f"| {k.replace('_', ' ')} | {'n/a' if v is None else f'{100 * v:.0f}%'} |")
    return L


def rescore(out) -> list[dict]:
    """Score every row of ``out/table.json`` again from its saved ``report.json`` (after a change of the scoring,
    without running anything) and rewrite the table."""
    from causalgs.io import read_json

    out = Path(out)
    if not (out / "table.json").is_file():
        raise CausalGSError(f"no table in {out} to score again (no {out / 'table.json'})")
    saved = read_json(out / "table.json", "table")
    if saved.get("level", "trajectory") == "video":
        raise CausalGSError(f"only trajectory tables are scored again; {out / 'table.json'} holds a video table, "
                            f"whose rows also carry its fits' and tracks' errors")  # fmt: skip
    rows = []
    for r in saved.get("rows", []):
        path = out / f"{_slug(r['case'])}-s{r['seed']}" / "report.json"
        if r["verdict"].startswith("failed") or not path.is_file():
            rows.append(r)
            continue
        rows.append({**score(BY_NAME[r["case"]], read_json(path, "report")), "seed": r["seed"],
                     "seconds": r["seconds"]})  # fmt: skip
    _write(out, rows, saved.get("config", {}))
    return rows


def _sorted(rows: list[dict]) -> list[dict]:
    return sorted(rows, key=lambda r: ([c.name for c in CASES].index(r["case"]), r["seed"]))


def _write(out: Path, rows: list[dict], cfg: TableConfig | dict) -> None:
    rows = _sorted(rows)
    config = cfg if isinstance(cfg, dict) else _cfg_dict(cfg)
    saved = {"level": measurement(config), "rows": rows, "summary": summary(rows), "config": config}
    write_json(out / "table.json", finite(saved))
    write_text(out / "table.md", markdown(rows))


def _cfg_dict(cfg: TableConfig) -> dict:
    d = dataclasses.asdict(cfg)
    d["only"] = list(cfg.only)
    return d
