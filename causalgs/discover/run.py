"""One discovery run, as ``causalgs discover`` does it: read the measurement, run the loop, write the outputs.

The measurement is an observation file (:meth:`~causalgs.discover.observation.Observation.save`: trajectories of
material points, for example from a simulated scene or a tracker). The model's effects and the effect parameters
calibrated with the base are given as a spec (the physics a fitted run was trained with, or what the user believes).
Everything a person needs to redo the run is saved next to the report as ``discover.json``, and every calibration
as it finishes in ``progress.json`` (:mod:`causalgs.discover.journal`): a stopped run is resumed with ``resume``.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from causalgs.discover.journal import Journal, calibration_options, fingerprint
from causalgs.discover.observation import Observation, load_observation
from causalgs.discover.report import write_outputs
from causalgs.discover.search import DiscoverConfig, discover
from causalgs.errors import CausalGSError
from causalgs.io import write_json
from causalgs.sim.effects import Effects

DEFAULT_SPEC = "gravity;ground:mu=0.3;walls"
DEFAULT_LEARN = ("ground.mu",)


def load_source(source, *, refine: bool = True, lens: str = "auto", split: bool = True, stretch: bool = True,
                progress=None, workers: int = 1) -> tuple[Observation, dict]:  # fmt: skip
    """The observation at ``source`` and the base model it implies: an ``.npz`` observation file (no base: the
    defaults), or a fitted run folder (:func:`causalgs.discover.video.observation_from_run`: the run's physics; its
    tracked motion refined frame by frame unless ``refine`` is False, with the tracks' ``lens`` ("auto", "rigid" or
    "affine"), refined from each half of the cameras too where ``split``, the stretching tracks at the frames where
    the bodies deform where ``stretch``, ``progress(done, total)`` following it, refinements that do not depend on
    one another in ``workers`` processes at once). Anything else is a one-line error."""
    source = Path(source)
    if source.is_dir():
        if not (source / "config.toml").is_file() or not (source / "checkpoint.pt").is_file():
            raise CausalGSError(f"{source}: a folder but not a fitted run (no config.toml / checkpoint.pt); give a "
                                "run folder or an observation file (.npz)")  # fmt: skip
        from causalgs.discover.video import REFINE, observation_from_run

        return observation_from_run(source, refine=REFINE if refine else None, lens_kind=lens, split=split,
                                    stretch=stretch, progress=progress, workers=workers)  # fmt: skip
    return load_observation(source), {}


def run_discovery(source, out, *, spec: str | None = None, learn=None, candidates=None,
                  config: DiscoverConfig | None = None, log=None, obs: Observation | None = None,
                  base: dict | None = None, resume: bool = False, refine: bool = True, lens: str = "auto",
                  split: bool = True, stretch: bool = True, progress=None) -> dict:  # fmt: skip
    """Discover on ``source`` (or the given ``obs``) with the base model ``spec``/``learn`` (None: the run's own
    physics for a run folder, else :data:`DEFAULT_SPEC` / :data:`DEFAULT_LEARN`; ``obs`` with ``base``: what
    :func:`load_source` returned for ``source``, already loaded; ``refine``, ``lens``, ``split``, ``stretch`` and
    ``progress`` as there);
    writes ``report.json``, ``report.md``, the plots, ``discover.json`` (the options) and ``progress.json`` (the
    finished calibrations) into ``out`` and returns the report. An ``out`` that already holds a discovery run is an
    error unless ``resume``, which continues it (same options and measurement) from its finished calibrations."""
    cfg = config or DiscoverConfig()
    if spec is not None:
        Effects.from_spec(spec)  # a malformed spec is a one-line error before any work
    base = dict(base or {})
    if obs is None:
        obs, base = load_source(source, refine=refine, lens=lens, split=split, stretch=stretch, progress=progress,
                                workers=cfg.workers)  # fmt: skip
    spec = spec if spec is not None else base.get("spec", DEFAULT_SPEC)
    learn = tuple(learn) if learn is not None else tuple(base.get("learn", DEFAULT_LEARN))
    if cfg.res <= 0:  # the run's grid, else the default
        cfg = dataclasses.replace(cfg, res=int(base.get("res", DiscoverConfig.res)))
    out = Path(out)
    options = {"source": str(source), "spec": spec, "learn": list(learn),
               "candidates": None if candidates is None else list(candidates),
               "tracking": ("refined" if base.get("tracking", {}).get("refined") else "kinematic") if "run" in base
               else None,
               "lens": None if obs.mix is None else f"{obs.lens_kind} per motion pattern ({obs.mix.shape[1]})" + (
                   "" if obs.stretch is None else f", stretching at {int(obs.stretch.sum())} frames where the bodies "
                   "deform"),
               "shape_resolution_m": obs.shape_resolution, "noise_m": obs.noise,
               "config": dataclasses.asdict(cfg), "box": [list(obs.lo), list(obs.hi)]}  # fmt: skip
    if (out / "report.json").is_file() and not (out / "progress.json").is_file() and not resume:
        raise CausalGSError(f"{out} already holds a discovery report: choose another --out")
    key = fingerprint({**calibration_options(spec, learn, cfg), "box": [obs.lo, obs.hi], "noise": obs.noise}, obs.x,
                      obs.mix, obs.lens_kind, obs.bend, obs.stretch)  # fmt: skip
    journal = Journal(out / "progress.json", key, resume=resume)
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "discover.json", options)
    tracking = base.get("tracking")  # refined tracks come scored on held-out cameras
    if "run" in base and tracking is None:  # how well the run's tracked motion matches its own images, per frame
        from causalgs.discover.video import tracking_quality

        if log:
            log("scoring the tracked motion against the training images")
        tracking = tracking_quality(base["run"])
    report, traj = discover(obs, spec, learn, candidates=candidates, config=cfg, log=log, journal=journal)
    if tracking is not None:
        report["tracking"] = {**tracking, "stray_particles": base.get("stray", 0), "pixel_m": base.get("pixel_m"),
                              "lens_patterns": None if obs.mix is None else int(obs.mix.shape[1]),
                              "lens": None if obs.mix is None else obs.lens_kind,
                              "bend_bodies": None if obs.bend is None else int(obs.bend.max()) + 1,
                              "stretched_frames": None if obs.stretch is None
                              else [int(f) for f in np.nonzero(obs.stretch)[0]]}  # fmt: skip
    report["source"] = str(source)
    report["config"] = options
    if obs.truth is not None:
        report["truth"] = obs.truth
    if "run" in base:  # a fitted run: the disagreement on images of held-out cameras, before and after
        from causalgs.discover.video import image_residuals

        if log:
            log("rendering the held-out views before and after")
        report["images"] = image_residuals(base["run"], obs, traj, out / "images.png")
        if report["discovered"]:
            report["refit_config"] = str(_repaired_config(Path(base["run"]), report, out / "config.toml"))
    write_outputs(out, report, traj, obs)
    return report


def _repaired_config(run: Path, report: dict, path: Path) -> Path:
    """The run's config with the discovered effects added to its physics (their parameters learned, starting at
    the discovered values): ``causalgs fit DATA --config PATH`` refits the scene with them."""
    from causalgs.model.config import FitConfig

    cfg = FitConfig.load(run / "config.toml")
    final = Effects.from_spec(report["final_spec"])
    cfg.physics.effects = final.spec()
    new = [p for d in report["discovered"] for p in d["params"]]
    keep = [n for n in cfg.physics.learn if n in final.param_names()]
    cfg.physics.learn = tuple(dict.fromkeys([*keep, *[n for n in new if n in final.param_names()]]))
    cfg.save(path)
    return path
