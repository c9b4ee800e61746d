"""Discovery on a fitted run: the measurement is what the video says about the particles' motion.

:func:`observation_from_run` turns a run of ``causalgs fit`` into an :class:`Observation`: the simulated particles'
positions over the observed window by the run's kinematic fit (the tracked motion, fitted to every training image),
their rest volumes, and bodies from the fit's motion segmentation (each particle's dominant motion pattern; patterns
holding less than ``min_share`` of the particles join the pattern they mix most with). Stray particles are left out
(:func:`stray_particles`: a few particles apart from every body, such as a Gaussian that floated below the floor,
are no material anyone measured, and one of them 18 cm off its body's path outweighed a whole drag). The last
``held_out`` fraction of the window is never fitted by discovery and only scored. The base model is the run's own
physics: its effects spec at the learned values and the effect parameters it learned; its grid is used where
``DiscoverConfig.res`` is 0 (``causalgs discover`` calibrates on ``--res`` cells, 20 by default).

The measurement's noise is not the jitter of the tracks alone. Tracked motion errs smoothly: a pattern's rigid
motion is a little off for many frames together, which neither the jitter estimate
(:func:`~causalgs.discover.observation.noise_floor`) nor the rigid floor sees. Measured on the flight of
``causalgs synth toss --fps 120 --frames 48`` (128² images, 4.6 mm a pixel at the block), the tracked displacements
missed the truth by 1–4 mm (median per frame), 1.45 mm RMS per coordinate, a third of a pixel, while the jitter
estimate said 0.52 mm; a model with the true effect then stopped 1.6× above that "floor" and the gate turned it away.
So a run's noise is at least :data:`RESOLVE` of a pixel's footprint at the bodies (the median over the training
cameras of depth / focal length): what tracking from these images can resolve. A body that deforms for good costs
the tracks more than that (on the dent of the video table they missed the truth by 2.89 mm, two quarter pixels), so
the noise is also measured from the images: the tracks refined again from each half of the cameras land apart by
what one half's tracks err, and :data:`SPLIT` times that (:func:`split_sigma`) is credited where it is more.
"""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from causalgs.discover.model import CAPACITY
from causalgs.discover.observation import Observation, lens, noise_floor
from causalgs.errors import CausalGSError
from causalgs.model.refine import RefineConfig, cached_tracks, tracks_kept
from causalgs.similarity import Similarity

REFINE = RefineConfig()  # the measurement: the kinematic fit refined frame by frame (causalgs.model.refine)
# The share of the particles a body needs: a motion pattern holding less joins the one it mixes with most, and a
# group of particles apart from every other (:func:`stray_particles`) holding less is left out. A linked group of
# 35 of 3409 particles (1.03%) resting on the floor 25-49 cm from a thrown block, moved rigidly with it by the
# tracks, was kept at a 1% share: as a clump lying on the ground in the simulation, it made stiffness, viscosity
# and the ground's friction and height live in what is a free flight, and the calibration ran them to their bounds.
STRAY_SHARE = 0.05

_LOADED: dict = {}  # the last run loaded, by folder and checkpoint state: one discovery reads its run once


def _load(run_dir):
    """``load_model(run_dir)`` (the trained model, its dataset with every image, its timeline), kept for the next call
    on the same run while its checkpoint is unchanged."""
    from causalgs.model.fit import load_model

    path = Path(run_dir).resolve()
    ckpt = path / "checkpoint.pt"
    st = ckpt.stat() if ckpt.is_file() else None
    key = (str(path), None if st is None else (st.st_mtime_ns, st.st_size))
    if key not in _LOADED:
        loaded = load_model(run_dir, "checkpoint.pt")
        _LOADED.clear()
        _LOADED[key] = loaded
    return _LOADED[key]


def synthetic_truth(root: Path, obs: Observation, reach: float = 0.03, frame=None) -> dict | None:
    """What a synthetic scene's dataset records of its truth (``causalgs synth``: ``gt/meta.json``), in the terms
    of a report (:func:`causalgs.discover.report.true_value`): the true effects, and each tracked body's material
    and throw where most of its first-frame points lie on one of the scene's objects
    (:func:`causalgs.model.recovery.true_objects`, as a fit's recovery report assigns its Gaussians) and no other
    body claims that object. None for a dataset without a truth (a user's own video) or with one that cannot be
    read: the report then goes without it. ``frame`` (a :class:`~causalgs.similarity.Similarity`, default none):
    the run's map from the data's frame to its own, in which ``obs`` and the truth returned are."""
    from causalgs.io import read_json
    from causalgs.model.recovery import true_objects

    path = root / "gt" / "meta.json"
    if not path.is_file():
        return None
    try:
        meta = read_json(path, "ground truth")
        effects = meta["motion"]["effects"]
        objects = {o["id"]: o for o in meta.get("objects", []) if "E" in o}
    except (CausalGSError, KeyError, TypeError):
        return None
    frame = frame or Similarity.identity()
    label = true_objects(frame.inverse().points(obs.x[0]), root, reach)
    bodies = []
    for b, name in enumerate(obs.names if label is not None else []):
        ids, counts = np.unique(label[obs.body == b], return_counts=True)
        top = int(np.argmax(counts))
        if int(ids[top]) in objects and 2 * counts[top] > counts.sum():
            o = dict(objects[int(ids[top])])
            for key, kind in (("velocity", "vectors"), ("omega", "directions")):
                if key in o:
                    o[key] = getattr(frame, kind)(o[key]).tolist()
            bodies.append({"name": name, "object": o.get("name"),
                           **{k: o[k] for k in ("E", "nu", "density", "velocity", "omega") if k in o}})  # fmt: skip
    if len({b["object"] for b in bodies}) < len(bodies):  # two bodies on one object: neither is that object
        bodies = []
    effects = {name: _reposed_effect(dict(params), frame) for name, params in effects.items()}
    return {"scene": meta.get("scene"), "effects_spec": meta["motion"].get("effects_spec"), "effects": effects,
            "bodies": bodies, "source": str(path)}


def _reposed_effect(params: dict, frame: Similarity) -> dict:
    """An effect's true parameters in a run's frame: accelerations (g, b) turned and scaled, planes (n, d) moved."""
    for key in ("g", "b"):
        if key in params:
            params[key] = frame.vectors(params[key]).tolist()
    if "n" in params and "d" in params:
        n, d = frame.plane(params["n"], float(np.ravel(params["d"])[0]))
        params["n"], params["d"] = n.tolist(), [d]
    return params


def refined_together(run_dir, model, data, tl, specs: list[tuple], workers: int, steps: list) -> list:
    """The tracks of every (config, half, frames) of ``specs`` (:func:`~causalgs.model.refine.cached_tracks`), in
    order. With ``workers`` > 1, of those the run does not hold yet all but the first are refined at once in worker
    processes (:func:`causalgs.processes.pinned_pool`; each loads the run itself and writes its tracks into it)
    while this process refines the first (its progress ``steps[i]``); each is then read from the run as it ends. A
    refinement takes one CPU: on the damping landing (seed 0, 144 frames) the rigid tracks took 29 minutes and the
    stretching ones 23, one after the other."""
    from causalgs.processes import pinned_pool, stop

    todo = [i for i, (cfg, half, frames) in enumerate(specs) if not tracks_kept(run_dir, model, cfg, half, frames)]
    pool, elsewhere = None, {}
    if workers > 1 and len(todo) > 1:
        pool = pinned_pool(min(workers - 1, len(todo) - 1), caller_busy=True)
        elsewhere = {i: pool.submit(_refine_here, str(run_dir), *specs[i]) for i in todo[1:]}
    try:
        out = []
        for i, (cfg, half, frames) in enumerate(specs):
            if i in elsewhere:
                elsewhere[i].result()
            out.append(cached_tracks(run_dir, model, data, tl, cfg, steps[i], half=half, frames=frames))
        return out
    finally:
        if pool is not None:
            for f in elsewhere.values():
                f.cancel()
            if any(not f.done() for f in elsewhere.values()):  # stopped: the refinements under way stop too
                stop(pool)
            else:
                pool.shutdown()


def _refine_here(run_dir: str, cfg: RefineConfig, half: int | None, frames: int | None) -> None:
    """In a worker of :func:`refined_together`: refine one set of tracks of the run and write it there."""
    model, data, tl = _load(run_dir)
    cached_tracks(run_dir, model, data, tl, cfg, None, half=half, frames=frames)


def observation_from_run(run_dir, *, held_out: float = 0.25, max_points: int = CAPACITY, min_share: float = STRAY_SHARE,
                         seed: int = 0, refine: RefineConfig | None = REFINE, lens_kind: str | None = "auto",
                         split: bool = True, stretch: bool = False, progress=None,
                         workers: int = 1) -> tuple[Observation, dict]:  # fmt: skip
    """The observation described in the module docstring and the run's base model: ``{"spec", "learn", "res"}``,
    with ``"tracking"`` (:func:`refined_quality`) where the motion was refined (``refine``; None measures the
    kinematic fit as it is). The tracks move every motion pattern as a whole, so the observation carries that lens
    (``Observation.mix``, the particles' pattern weights, and ``lens_kind``) and discovery compares the simulation
    through it. ``lens_kind``: "rigid" (tracks refined by a rigid correction per pattern), "affine" (by a
    correction that also stretches each pattern), "auto" (both, and the one :func:`choose_lens` picks from
    held-out cameras; the kinematic fit's tracks, with ``refine`` None, are rigid) or None (compare point by
    point, rigid tracks). ``split``: also refine the tracks from each half of the cameras over the fit window and
    credit the noise their disagreement shows (:func:`split_sigma`). ``stretch``: where rigid tracks are taken
    from "auto", take the stretching ones at the frames where the bodies deform (:func:`stretch_where_deforming`).
    ``progress(done, total)`` follows the refinements, frame by frame. ``workers`` > 1: refinements that do not
    depend on one another (the rigid and the stretching tracks; the two halves) run at once, all but the first in
    processes of their own (:func:`refined_together`).

    Discovery simulates every particle the run simulated (up to ``max_points``; beyond, a random subset of each
    body, its particles' volumes scaled to keep the body's). A thinner set is a coarser material: the MPM resolves
    a body with 8 particles a cell, and on the landing of ``causalgs synth toss`` a random 600 of the truth's own
    2380 particles, simulated with the truth's parameters, missed the truth's held-out bounce by 10.5–12.9 mm (all
    of them: 0)."""
    from causalgs.sim.effects import Effects

    run_dir = Path(run_dir)
    model, data, tl = _load(run_dir)
    if model.particles is None:
        raise CausalGSError(f"{run_dir}: the fit has no simulated particles (its physical stage has not run)")
    n = tl.train_frames
    if n < 8:
        raise CausalGSError(f"{run_dir}: {n} observed frames; discovery needs at least 8")
    if not 0.0 < held_out < 0.6:
        raise CausalGSError(f"held_out = {held_out} must be in (0, 0.6)")
    p = model.particles
    x0 = p.x0.to(model.fields.centres.dtype)
    if lens_kind not in (None, "auto", *TRACKS):
        raise CausalGSError(f"lens '{lens_kind}' is not one of auto, {', '.join(TRACKS)}")
    observed = max(3, n - round(held_out * n))
    tracks, choice, halves = None, None, None
    if refine is not None:
        kinds = ["rigid", "affine"] if lens_kind == "auto" else [lens_kind or "rigid"]
        total = [len(kinds) * n + (2 * observed if split else 0)]  # grows by a refinement where a bend is tried
        made = {}

        def step_at(done: int):
            return None if progress is None else (lambda d, t: progress(done + d, total[0]))

        def refined(kind):
            made[kind] = cached_tracks(run_dir, model, data, tl, lens_refinement(refine, kind), step_at(len(made) * n))
            return made[kind]

        specs = [(lens_refinement(refine, kind), None, None) for kind in kinds]
        made.update(zip(kinds, refined_together(run_dir, model, data, tl, specs, workers,
                                                [step_at(i * n) for i in range(len(kinds))]), strict=True))  # fmt: skip
        if lens_kind == "auto":
            choice = choose_lens(made["rigid"], made["affine"])
            if choice["lens"] == "affine":  # a body deformed for good: does it also taper or bulge?
                total[0] += n
                bend = choose_lens(made["affine"], refined("bent"), kinds=("affine", "bent"))
                choice = {**bend, "text": choice["text"] + " " + bend["text"]}
            tracks = made[choice["lens"]]
        else:
            tracks = made[kinds[0]]
        if split:
            again = lens_refinement(refine, tracks.kind)
            halves = refined_together(run_dir, model, data, tl, [(again, i, observed) for i in (0, 1)], workers,
                                      [step_at(len(made) * n + i * observed) for i in (0, 1)])  # fmt: skip
    kind = "rigid" if tracks is None else tracks.lens
    with torch.no_grad():
        h = model.mixtures(x0)
        if tracks is None:
            xs, _ = model.trajectories(h, x0, None, n - 1, list(range(n)))
        else:
            xs = tracks.positions(h.double(), x0.double())
        parts = None if halves is None else [t.positions(h.double(), x0.double()).double().numpy() for t in halves]
        # rigid tracks measured against the stretching ones refined from the same images (see :func:`disagreement`)
        rival = made.get("affine") if tracks is not None and kind == "rigid" else None
        xa = None if rival is None else rival.positions(h.double(), x0.double()).double().numpy()
    x = xs.double().numpy()
    bent = None if tracks is None else tracks.bodies(h)  # [P] the body each point's bend is of (None: no bend)
    h = h.double().numpy()
    body = _bodies(h, min_share)
    vol = p.vol.double().numpy()
    stray = stray_particles(x[0], float(model.cell), min_share)
    if stray.all():
        raise CausalGSError(f"{run_dir}: no group of particles large enough to be a body")
    x, h, body, vol = x[:, ~stray], h[~stray], body[~stray], vol[~stray]
    xa = None if xa is None else xa[:, ~stray]
    bent = None if bent is None else bent[~stray]
    split_m = None if parts is None else split_sigma(parts[0][:, ~stray], parts[1][:, ~stray])
    drift = np.ones(n) if parts is None else drift_profile(parts[0][:, ~stray], parts[1][:, ~stray], n)
    rng = np.random.default_rng(seed)
    if len(vol) > max_points:  # a volume-preserving subset, the same share of every body
        keep = []
        for b in np.unique(body):
            mine = np.nonzero(body == b)[0]
            k = max(3, round(max_points * len(mine) / len(vol)))
            pick = np.sort(rng.choice(mine, size=min(k, len(mine)), replace=False))
            # the picked particles' own volumes, scaled to the body's: a uniform share would give the surface
            # Gaussians (small voxel shares) the mass of the interior fill
            keep.append((pick, vol[pick] * vol[mine].sum() / vol[pick].sum()))
        idx = np.concatenate([k for k, _ in keep])
        new_vol = np.concatenate([v for _, v in keep])
        x, h, body, vol = x[:, idx], h[idx], body[idx], new_vol
        xa = None if xa is None else xa[:, idx]
        bent = None if bent is None else bent[idx]
    _, body = np.unique(body, return_inverse=True)
    lo, hi = (tuple(float(v) for v in row) for row in model.box.double().numpy())
    cfg = model.config.physics
    eff = Effects.from_spec(cfg.effects)
    eff.set_flat(model.effect_params.detach().double().numpy())
    ground = float(eff.get("ground", "d")[0]) if "ground" in eff.names() else None
    with torch.no_grad():
        rho = float(model.causes()["density"].double().median())
    obs = Observation(times=np.arange(n) / tl.fps, x=x, vol=vol, body=body, observed=observed, lo=lo, hi=hi,
                      density=rho, ground=ground, names=[f"body {b}" for b in range(int(body.max()) + 1)],
                      mix=lens(h) if lens_kind is not None else None, lens_kind=kind,
                      bend=None if bent is None or lens_kind is None else np.unique(bent, return_inverse=True)[1],
                      # the fit filled its bodies with particles at half a grid cell: a face is known to ± a quarter
                      shape_resolution=0.5 * float(model.cell),
                      # tracks err smoothly, more where the halves disagree more (without them: alike everywhere)
                      drift=drift, disagreement=None if xa is None else disagreement(x, xa, body))  # fmt: skip
    obs.truth = synthetic_truth(Path(data.root), obs, frame=model.similarity())
    pixel = pixel_footprint(data.train, x[0].mean(0))
    obs.noise = max(noise_floor(obs), RESOLVE * pixel, SPLIT * split_m if split_m is not None else 0.0)
    if stretch and xa is not None:  # rigid tracks: the stretching ones where the bodies deform (the rigid noise)
        obs = stretch_where_deforming(obs, xa)
    base = {"spec": eff.spec(), "learn": tuple(cfg.learn), "res": int(cfg.res), "run": str(run_dir),
            "stray": int(stray.sum()), "pixel_m": pixel}  # fmt: skip
    if tracks is not None:
        base["tracking"] = refined_quality(tracks)
        base["tracking"]["split_sigma_m"] = split_m
        base["tracking"]["noise_m"] = obs.noise
        if choice is not None:
            base["tracking"]["lens_choice"] = choice["text"]
            base["tracking"]["lens_gain_db"] = choice["gain_db"]
            base["tracking"]["lens_agree"] = choice["agree"]
    return obs, base


def disagreement(rigid: np.ndarray, affine: np.ndarray, body: np.ndarray) -> np.ndarray:
    """[T, B] how far stretching tracks stray from rigid ones refined from the same images, per frame and body: the
    RMS per coordinate (m) of their difference, less (in quadrature) its median over the frames, what the two
    refinements differ by anyway; 0 at the first frame, where both start from the fit. ``rigid``, ``affine``
    [T, P, 3] the points' positions by each; ``body`` [P] their bodies.

    Rigid tracks of a deforming body err by about its departure from rigid motion, and where a body deforms the
    stretch the images ask for pulls the stretching tracks away from the rigid ones. On the damping landing of the
    video table (seed 2) the two differed by 0.5–1.2 mm per coordinate before and after the impact and by 2.1–2.3 mm
    at it (frames 40–42), where the rigid tracks missed the truth's material, seen through the rigid lens, by
    2.6–3.1 mm (its departure from rigid: 2.8–3.1 mm); that error put the block 5 mm too low at frame 40. Unlike the
    base fit's departure (:func:`causalgs.discover.search.track_error`), which a stiff base calibrated without the
    missing effect barely shows, this measure comes from the images alone, the same for every model."""
    diff2 = (affine - rigid) ** 2
    d2 = np.stack([diff2[:, body == b].mean((1, 2)) for b in range(int(body.max()) + 1)], axis=1)  # [T, B]
    out = np.sqrt(np.maximum(0.0, d2 - np.median(d2, axis=0)))
    out[0] = 0.0
    return out


STRETCH_AT = 1.0  # (of the noise) the rigid and stretching tracks' disagreement beyond which a frame is stretched


def stretch_where_deforming(obs: Observation, affine: np.ndarray, at: float = STRETCH_AT) -> Observation:
    """``obs`` (rigid tracks, with their :attr:`~Observation.disagreement` from the stretching tracks ``affine``
    [T, P, 3] refined from the same images) with the stretching tracks, compared through the affine lens
    (:attr:`~Observation.stretch`), at every frame where the two disagree by more than ``at`` times the noise for
    some body; unchanged where no frame does.

    A rigid pose fitted to the images of a body that deforms for a moment (an elastic impact, a landing) is off by
    about the deformation, and the physics that fits those frames is bent to match: on the friction landing of the
    video table (seed 0, μ = 0.3) the rigid tracks of the second landing (frames 58–81, 2.5–3.3 mm low and up to
    31 mrad off in pitch) alone brought the friction refit to μ = 0.258, while the run's own particles moved by the
    truth's motion gave 0.291. The stretching tracks follow the squash, and the affine lens shows the simulated one:
    stretched at the 30 frames where the two tracks disagreed beyond the noise, the refit came to μ = 0.312 (E 37.3
    kPa, truth 38.3; the ground 0.1 mm from the truth's), and at seed 1 to 0.322 (E 26.9 kPa, truth 28.5). Stretching
    tracks everywhere were no substitute (seed 1: μ = 0.207 from the truth's physics): in flight and at rest their
    six more numbers per pattern and frame are noise. Which frames is decided from the images alone, the same for
    every model."""
    if obs.disagreement is None or obs.mix is None or obs.lens_kind != "rigid" or not obs.noise:
        return obs
    stretch = obs.disagreement.max(1) > at * obs.noise
    stretch[0] = False
    if not stretch.any():
        return obs
    return replace(obs, x=np.where(stretch[:, None, None], affine, obs.x), stretch=stretch)


SPLIT = 1.75  # the noise credited per unit of split_sigma: the least ratio measured of the tracks' error to it


def split_sigma(xa: np.ndarray, xb: np.ndarray) -> float:
    """The position error σ (m, per coordinate) of tracks fitted to half the cameras, from two such tracks of the
    same points fitted to disjoint halves (``xa``, ``xb`` [F, P, 3], frame 0 the shared start): RMS(xa − xb)/√2
    over frames 1.., the errors of the halves being independent. A misfit both halves share does not show, and on
    the table's runs most of the error was shared: :func:`observation_from_run` credits :data:`SPLIT` times this.

    Measured (seed 0, 144 frames, the fit window's 81 frames, its 17 training cameras split 9 and 8): on the dent
    (5 kPa, stretching tracks) split_sigma was 1.65 mm, and the whole tracks missed the truth's motion seen through
    their lens by 2.89 mm (each half's by 2.93 and 2.87), 1.75× it; on the elastic landing control (rigid tracks)
    0.76 mm against 1.51 mm (1.52 and 1.56), 1.97× (seed 1: 0.82 against 1.71 mm, 2.09×); on the damped landing
    (η = 200 Pa·s, rigid tracks) 0.53 mm against 0.93 mm (0.91 and 0.95), 1.75×. The quarter-pixel credit
    (:data:`RESOLVE`) was 1.49 and 1.41 mm on the dent and the control: right for the control, half the dent's. In
    free flight the halves tell the whole error: on the linear drag of the table (seed 1, 48 frames, its window's
    27) split_sigma was 0.44 mm and the tracks missed the truth by 0.40 mm, and the quarter pixel (1.16 mm) stays
    the credit. What a body that deforms for good costs the tracks shows in how far apart the halves land, and the
    credit follows it."""
    d = np.asarray(xa, dtype=np.float64)[1:] - np.asarray(xb, dtype=np.float64)[1:]
    if d.size == 0:
        return 0.0
    return float(np.sqrt((d**2).mean() / 2.0))


DRIFT_SMOOTH = 5  # frames: the running mean that smooths the halves' disagreement per frame into a drift profile


def drift_profile(xa: np.ndarray, xb: np.ndarray, frames: int) -> np.ndarray:
    """[frames] how the tracks' error varies in size over the frames, from tracks of the same points fitted to
    disjoint halves of the cameras (``xa``, ``xb`` [F, P, 3], F ≤ frames, frame 0 the shared start): their
    disagreement per frame (RMS over the points), a running mean over :data:`DRIFT_SMOOTH` frames, relative to its
    RMS over frames 1..F−1; frame 0 takes frame 1's value and frames past F the last one. Flat where the halves
    agree exactly. :func:`causalgs.discover.search.drift_draws` draws the tracks' smooth error with this profile.

    The halves show where tracking is hard, not how the error they share drifts: on the dent (5 kPa, seed 0,
    affine tracks, the 81-frame window) they disagreed by 0.6-0.8 mm a frame before the impact (frame 41) and
    1.8-2.6 mm after it, where the tracks' real error (against the truth's motion through the lens) was 0.7-0.9
    and 3.2-4.3 mm; but the direction of their disagreement changed from one frame to the next (correlated by less
    than e^(−1/2) one frame apart), while the shared error moved the refit as one error would."""
    d = np.asarray(xa, dtype=np.float64) - np.asarray(xb, dtype=np.float64)
    F = len(d)
    flat = np.ones(frames)
    if F < 2:
        return flat
    size = np.sqrt((d[1:] ** 2).mean(axis=(1, 2)))  # [F-1]
    if not (size > 0).any():
        return flat
    k = min(DRIFT_SMOOTH, F - 1)
    pad = np.pad(size, (k // 2, k - 1 - k // 2), mode="edge")
    smooth = np.convolve(pad, np.ones(k) / k, mode="valid")  # [F-1], frames 1..F-1
    prof = np.empty(frames)
    prof[0] = smooth[0]
    n = min(frames - 1, len(smooth))
    prof[1 : 1 + n] = smooth[:n]
    prof[1 + n :] = smooth[-1]
    return prof / math.sqrt((smooth**2).mean())


STRETCH_GROUND = 10.0  # per metre: the stretching tracks' weight on their depth under the floor (RefineConfig.ground)


TRACKS = ("rigid", "affine", "bent")  # the refined tracks' kinds: a rigid or an affine motion per pattern, or an
# affine one with a second-order bend per body (seen through the affine lens with ``Observation.bend``)


def lens_refinement(refine: RefineConfig, kind: str) -> RefineConfig:
    """The refinement that makes the ``kind`` tracks (:data:`TRACKS`): ``refine`` rigid, or with a stretch per
    pattern (and for "bent" a bend per body) and (unless ``refine`` sets one) :data:`STRETCH_GROUND` on the depth
    under the floor the cameras see (:func:`causalgs.model.refine.visible_floor`), where no camera sees a stretch
    grow. The rigid tracks go without it: a rigid block cannot flatten, and kept out of the floor it rides high. On
    the dent the term took the rigid tracks from 6.37 to 7.49 mm RMS from the truth, and their held-out PSNR from
    28.1 to 27.0 dB."""
    if kind not in ("affine", "bent"):
        return replace(refine, stretch=False, bend=False)
    return replace(refine, stretch=True, bend=kind == "bent", ground=refine.ground or STRETCH_GROUND)


AFFINE_GAIN_DB = 0.25  # median held-out PSNR the stretching tracks must gain over the rigid ones at the window's end
AFFINE_AGREE = 0.75  # ... on at least this share of those frames


def choose_lens(rigid, affine, gain_db: float = AFFINE_GAIN_DB, share: float = 0.25,
                agree: float = AFFINE_AGREE, kinds: tuple[str, str] = ("rigid", "affine")) -> dict:  # fmt: skip
    """Which tracks measure a run's motion: the rigid ones, unless the tracks that also stretch each pattern match
    the held-out cameras better where the bodies have come to their final shape, the last ``share`` of the observed
    frames (at least three): better on at least ``agree`` of them, by a median of ``gain_db`` or more (PSNR). That
    is a body deformed for good; a wobble, an elastic impact or a flight is not. Both are scored on cameras neither
    fitted, so the stretch's six more numbers per pattern and frame are taken only where the images show them.

    Measured (seed 0, 144 frames, each frame scored on two held-out cameras): over the last 27 frames the stretching
    tracks gained a median +2.55 dB on the splat (1.5 kPa; better on all), +0.40 dB on the dent (5 kPa; 89%),
    −0.03 dB on the elastic landing control (41%) and −0.25 dB on the damped landing (11%). Over all the frames the
    dent and the control were alike (+0.55 and +0.48 dB at the upper quartile, the dent's tracks kept above the
    learned ground): the stretch gains at an elastic impact too, and loses a little in flight.

    ``kinds`` ("affine", "bent"): the same rule between affine tracks and tracks that also bend each body (a foot
    spreading on the ground, :class:`~causalgs.model.refine.RefineConfig` ``bend``), taken only where the affine
    ones were. On the dent (seed 0) the bent tracks gained a median +2.7 dB over the stretching ones after the
    impact, and were 2.1 mm RMS from the truth against 4.3 mm.

    Returns ``{"lens", "gain_db", "agree", "text"}``: the median gain over those frames and the share of them
    where the stretching tracks were better."""
    plain, rich = kinds
    what = {"affine": "stretch each pattern", "bent": "bend each body"}[rich]
    ok = np.isfinite(rigid.psnr_after) & np.isfinite(affine.psnr_after)
    if not ok.any():
        return {"lens": plain, "gain_db": 0.0, "agree": 0.0, "text": f"No frame had cameras to compare {plain} "
                f"tracks and tracks that also {what} on; the tracks are {plain}."}  # fmt: skip
    gain = (affine.psnr_after - rigid.psnr_after)[ok]
    last = gain[-max(3, int(np.ceil(share * len(gain)))) :]
    med, better = float(np.median(last)), float(np.mean(last > 0))
    med_r, med_a = float(np.median(rigid.psnr_after[ok])), float(np.median(affine.psnr_after[ok]))
    kind = rich if med >= gain_db and better >= agree else plain
    text = (f"Tracks that also {what} matched the held-out cameras at a median {med_a:.1f} dB against "
            f"{med_r:.1f} dB for {plain} ones. Over the last {len(last)} frames they gained a median {med:+.2f} dB "
            f"and were better on {better:.0%} of them; taking them needs a median gain of at least {gain_db:.2f} dB "
            f"and a gain on at least {agree:.0%} of those frames, as where a body is deformed for good: the tracks "
            f"are {kind}.")  # fmt: skip
    return {"lens": kind, "gain_db": med, "agree": better, "text": text}


def image_residuals(run_dir, obs: Observation, traj: dict, out_png, *, views: int = 4) -> dict | None:
    """Per-pixel disagreement on images discovery never fitted: the run's Gaussians carried by the simulated
    particles before and after the repair (every particle follows the displacement of its nearest observed point),
    rendered from held-out cameras (the dataset's val split) at the held-out frames and compared with the images.
    Writes ``out_png`` (for the last held-out frame of the first view: image, before, after, and both absolute
    residuals ×4, each labelled) and returns PSNR before and after over up to ``views`` cameras × every held-out frame
    (None without held-out cameras at those frames)."""
    from scipy.spatial import cKDTree

    from causalgs.discover.report import plot_images
    from causalgs.metrics.pixel import psnr

    model, data, tl = _load(run_dir)
    held = set(range(obs.observed, len(obs.times)))
    frames = [f for f in data.val if tl.index(f) in held]
    cams = sorted({f.view for f in frames if f.view is not None})[:views]
    frames = [f for f in frames if f.view in cams] if cams else frames[:views]
    if not frames:
        return None
    p = model.particles
    x0 = p.x0.double().numpy()
    _, near = cKDTree(obs.x[0]).query(x0)
    eye = torch.eye(3, dtype=torch.float64).expand(len(x0), 3, 3)[None]
    bg = tuple(float(b) for b in data.background)
    scores = {"before": [], "after": []}
    last = max(frames, key=lambda f: (f.view == frames[0].view, tl.index(f)))
    shown = None
    for fr in frames:
        k = tl.index(fr)
        gt = torch.from_numpy(fr.image).double()
        row = {}
        for key in ("before", "after"):
            disp = traj[key][k - 1][near] - obs.x[0][near]
            x = torch.from_numpy(x0 + disp)[None]
            with torch.no_grad():
                (state,) = model.physical_states(x, eye)
                img, _, _ = model.render(state, fr.camera, bg)
            img = img.double().clamp(0, 1)
            scores[key].append(float(psnr(img, gt)))
            row[key] = img.numpy()
        if fr is last:
            shown = (fr, k, gt.numpy(), row, scores["before"][-1], scores["after"][-1])
    out = {"psnr_before": float(np.mean(scores["before"])), "psnr_after": float(np.mean(scores["after"])),
           "images": len(frames), "frames": sorted({tl.index(f) for f in frames}),
           "panel": "image | before | after | |before − image|×4 | |after − image|×4"}  # fmt: skip
    if shown is not None:
        fr, k, g, row, before, after = shown
        cam = f"camera {fr.view}, " if fr.view is not None else ""
        plot_images([(f"measured ({cam}frame {k})", g), (f"before: {before:.2f} dB", row["before"]),
                     (f"after: {after:.2f} dB", row["after"]),
                     ("|before − measured| × 4", np.clip(4 * np.abs(row["before"] - g), 0, 1)),
                     ("|after − measured| × 4", np.clip(4 * np.abs(row["after"] - g), 0, 1))],
                    f"a held-out camera at a held-out frame; over all {len(frames)} such images "
                    f"{out['psnr_before']:.2f} → {out['psnr_after']:.2f} dB", Path(out_png))  # fmt: skip
    return out


RESOLVE = 0.25  # of a pixel: the smallest position error a run's tracked motion is credited with (see above)


def stray_particles(x: np.ndarray, cell: float, share: float = STRAY_SHARE) -> np.ndarray:
    """[P] bool: particles of the groups (particles within one simulation cell of each other, transitively) that hold
    fewer than ``share`` of all the particles (or fewer than 8): floaters too few to be a body, whatever the tracks
    make of them (see ``STRAY_SHARE``)."""
    from causalgs.model.scene import linked_groups

    n = len(x)
    label = linked_groups(x, cell)
    size = np.bincount(label)
    return size[label] < max(8, share * n) if n >= 8 else np.zeros(n, dtype=bool)


TRACKING_DROP_DB = 3.0  # a frame this far below the median PSNR of the tracked motion has lost the images


def refined_quality(tracks, drop_db: float = TRACKING_DROP_DB) -> dict:
    """:func:`tracking_quality`'s answer for refined tracks (:class:`~causalgs.model.refine.Tracks`), from the PSNR
    the refinement measured on each frame's held-out cameras: ``psnr`` the refined motion's, ``psnr_kinematic`` the
    kinematic fit's, ``refined`` True."""
    ok = np.isfinite(tracks.psnr_after)
    frames = [int(k) for k in np.nonzero(ok)[0]]
    scores = [float(v) for v in tracks.psnr_after[ok]]
    med = float(np.median(scores)) if scores else float("nan")
    return {"frames": frames, "psnr": scores, "psnr_kinematic": [float(v) for v in tracks.psnr_before[ok]],
            "median": med, "median_kinematic": float(np.median(tracks.psnr_before[ok])) if scores else float("nan"),
            "poor": [k for k, v in zip(frames, scores, strict=True) if v < med - drop_db], "drop_db": drop_db,
            "views": REFINE.score_views, "cameras": tracks.scored_on, "refined": True}  # fmt: skip


def pixel_footprint(frames, point: np.ndarray) -> float:
    """The size (m) of one pixel at ``point``: depth over focal length, the median over the cameras of ``frames``."""
    sizes = []
    for cam in {id(f.camera): f.camera for f in frames}.values():
        depth = float((cam.viewmat @ np.append(point, 1.0))[2])
        if depth > 0:
            sizes.append(depth / float(np.sqrt(cam.K[0, 0] * cam.K[1, 1])))
    if not sizes:
        raise CausalGSError("no training camera sees the bodies (all of them behind it)")
    return float(np.median(sizes))


def tracking_quality(run_dir, *, views: int = 4, drop_db: float = TRACKING_DROP_DB) -> dict:
    """How well the measurement itself agrees with the video: the PSNR at every observed frame of the run's tracked
    motion (its kinematic fit, which :func:`observation_from_run` takes as the measured motion) rendered at up to
    ``views`` training cameras. Frames more than ``drop_db`` below the median are where the tracking has lost the
    images (an impact it smoothed over, say): a disagreement there may be the measurement's, not the physics'.
    Returns ``{"frames", "psnr", "median", "poor", "views"}``."""
    from causalgs.metrics.pixel import psnr

    model, data, tl = _load(run_dir)
    bg = tuple(float(b) for b in data.background)
    cams = sorted({f.view for f in data.train if f.view is not None})
    cams = set(cams[:: max(1, len(cams) // views)][:views]) if cams else None
    by_frame: dict[int, list] = {}
    for fr in data.train:
        if cams is None or fr.view in cams:
            by_frame.setdefault(tl.index(fr), []).append(fr)
    frames = sorted(k for k in by_frame if k < tl.train_frames)
    scores = []
    for k in frames:
        state = model.kinematic_state(k)
        vals = []
        for fr in by_frame[k][:views]:
            with torch.no_grad():
                img, _, _ = model.render(state, fr.camera, bg)
            vals.append(float(psnr(img.double().clamp(0, 1), torch.from_numpy(fr.image).double())))
        scores.append(float(np.mean(vals)))
    med = float(np.median(scores)) if scores else float("nan")
    poor = [k for k, v in zip(frames, scores, strict=True) if v < med - drop_db]
    return {"frames": frames, "psnr": scores, "median": med, "poor": poor, "drop_db": drop_db,
            "views": len(cams) if cams else views}  # fmt: skip


def _bodies(h: np.ndarray, min_share: float) -> np.ndarray:
    """Dominant pattern per particle; small patterns merged into the pattern they mix with most."""
    label = h.argmax(1)
    counts = np.bincount(label, minlength=h.shape[1])
    big = counts >= max(1, min_share * len(label))
    if not big.any():
        big[counts.argmax()] = True
    small = ~big[label]
    if small.any():
        hb = h[small][:, big]
        label[small] = np.nonzero(big)[0][hb.argmax(1)]
    return label
