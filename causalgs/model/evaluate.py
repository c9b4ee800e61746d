"""Prediction and evaluation of a fitted run: render any frame by either dynamics path, extrapolate, score.

Dynamics (``--dynamics``):

- ``mpm``: the model's prediction: inside the observed window its best reconstruction of what was seen, the tracked
  state (as FreeGave's and the paper's interpolation renders); after it the simulator with the inferred materials
  and effects continuing from the forecast's start (:meth:`CausalGS.forecast`: the state near the end of the
  window, tracked or replayed, that forecast the newest observed frames best), as a forecast starts from the latest
  measurement;
- ``mpm-open``: the simulator from t = 0 for every frame (open loop: the whole sequence replayed from the causes);
- ``velocity``: the kinematic field integrated past the observed window (f_weight(t) extrapolated);
- ``frozen``: the scene held at the last observed frame by the kinematic-only model (a baseline);
- ``kinematic-only``: ``velocity`` of the model saved at the end of the kinematic stage (``kinematic.pt``), trained
  without the physical path (the baseline the simulator has to beat).

``evaluate`` writes ``metrics.json``: interpolation (val: held-out views at observed times) and extrapolation (test:
future frames from every view), PSNR (mean of per-image values, and pooled), SSIM and LPIPS (AlexNet, VGG) for every
dynamics, plus the number of images and the conventions; on datasets with ground truth also ``recovery``
(:mod:`causalgs.model.recovery`: per-object stiffness and initial-velocity error).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from causalgs.dataset import Frame
from causalgs.errors import CausalGSError
from causalgs.io import read_json, write_image, write_json
from causalgs.metrics import image_metrics, image_metrics_many
from causalgs.model.fit import load_model
from causalgs.model.recovery import frame_report, recovery_report
from causalgs.model.scene import CausalGS, State
from causalgs.model.timeline import Timeline
from causalgs.render.views import to_uint8, write_video

DYNAMICS = ("mpm", "mpm-open", "velocity", "frozen", "kinematic-only")
# what `eval` scores unless asked: the model, its open-loop replay and the baselines
EVAL_DYNAMICS = ("mpm", "mpm-open", "frozen", "kinematic-only")


def states(model: CausalGS, frames, dynamics: str) -> dict[int, State]:
    """The Gaussians' state at each frame index in ``frames`` by the chosen dynamics (no autograd)."""
    frames = sorted({int(k) for k in frames})
    if not frames:
        return {}
    with torch.no_grad():
        if dynamics in ("mpm", "mpm-open"):
            if model.particles is None:
                raise CausalGSError(f"this run has no physical stage (fit with physics enabled to use '{dynamics}')")
            inside = frames if dynamics == "mpm-open" else [k for k in frames if k < model.train_frames]
            after = [k for k in frames if k not in inside]
            result = {}
            if inside and dynamics == "mpm":
                result.update(zip(inside, model.observed(inside), strict=True))
            elif inside:
                out = model.simulate(inside)
                result.update(zip(inside, model.physical_states(out["x"], out["F"]), strict=True))
            if after:
                out = model.forecast(after)
                result.update(zip(after, model.physical_states(out["x"], out["F"]), strict=True))
            return result
        if dynamics in ("velocity", "kinematic-only"):
            return dict(zip(frames, model.observed(frames), strict=True))
        if dynamics == "frozen":
            held = sorted({min(k, model.train_frames - 1) for k in frames})
            at = dict(zip(held, model.observed(held), strict=True))
            return {k: at[min(k, held[-1])] for k in frames}
    raise CausalGSError(f"unknown dynamics '{dynamics}' (choose from {', '.join(DYNAMICS)})")


def render_images(model: CausalGS, timeline: Timeline, frames: list[Frame], dynamics: str, background):
    """Render every dataset frame (its camera, its time) by ``dynamics``: float32 images [H, W, 3] in [0, 1]."""
    st = states(model, [timeline.index(f) for f in frames], dynamics)
    out = []
    with torch.no_grad():
        for f in frames:
            img, _, _ = model.render(st[timeline.index(f)], f.camera, background)
            out.append(img.clamp(0, 1).float().numpy())
    return out


def _model_for(run_dir, dynamics: str):
    # The frozen baseline holds the best fit of the last observed frame: the kinematic model before the physical
    # stage (which trains the velocity field only through the initial velocity, and so may move its later frames).
    which = "kinematic.pt" if dynamics in ("kinematic-only", "frozen") else "checkpoint.pt"
    return load_model(run_dir, which)


def evaluate(run_dir, *, dynamics=EVAL_DYNAMICS, lpips_nets=("alex", "vgg"), progress=None) -> dict:
    """Score interpolation and extrapolation of a run and write ``RUN/metrics.json`` (see the module docstring)."""
    run_dir = Path(run_dir)
    result: dict = {"interpolation": {}, "extrapolation": {}}
    previous = run_dir / "metrics.json"
    if previous.is_file():  # keep the rows of dynamics not scored this time
        old = read_json(previous, "metrics")
        for key in result:
            result[key].update({d: v for d, v in old.get(key, {}).items() if d not in dynamics})
    # Every dynamics is rendered first and scored together: each true image's LPIPS features are computed once.
    preds: dict[str, dict[str, list]] = {"val": {}, "test": {}}
    data = None
    for dyn in dynamics:
        model, data, tl = _model_for(run_dir, dyn)
        if dyn in ("mpm", "mpm-open") and model.particles is None:
            continue
        for split in preds:
            frames = data.splits[split]
            if frames and not (split == "val" and dyn == "frozen"):  # frozen = kinematic-only inside
                preds[split][dyn] = render_images(model, tl, frames, dyn, data.background)
    for split, key in (("val", "interpolation"), ("test", "extrapolation")):
        if not preds[split]:
            continue
        frames = data.splits[split]
        scores = image_metrics_many(preds[split], [f.image for f in frames], lpips_nets=lpips_nets)
        for dyn, m in scores.items():
            result[key][dyn] = {**m, "images": len(frames)}
            if progress:
                progress(dyn, split, result[key][dyn])
    info = read_json(run_dir / "run.json", "run info")
    recovered = recovery_report(run_dir / "physics.npz", info["data"]) if (run_dir / "physics.npz").is_file() else None
    if recovered is not None:
        result["recovery"] = recovered
    frame = frame_report(info.get("frame"), info["data"])
    if frame is not None:
        result["frame"] = frame
    write_json(run_dir / "metrics.json", result)
    return result


def predict(run_dir, frames: int = 22, dynamics: str = "mpm", out=None, *, video: bool = True,
            lpips_nets=("alex", "vgg"), progress=None) -> dict:  # fmt: skip
    """Render the ``frames`` frames after the observed window from every test camera (the training cameras when the
    dataset has no test split): PNGs per view and frame, an MP4 per view, and metrics where ground truth exists."""
    model, data, tl = _model_for(run_dir, dynamics)
    if frames < 1:
        raise CausalGSError(f"--frames {frames}: predict at least one frame")
    out = Path(out) if out is not None else Path(run_dir) / "predict" / dynamics
    cams = _cameras(data.test or data.train)
    future = list(range(tl.train_frames, tl.train_frames + frames))
    st = states(model, future, dynamics)
    gt = {(f.view, tl.index(f)): f for f in data.test}
    preds, gts = [], []
    n = 0
    with torch.no_grad():
        for view, cam in cams.items():
            images = []
            for k in future:
                img, _, _ = model.render(st[k], cam, data.background)
                img = img.clamp(0, 1).float().numpy()
                images.append(to_uint8(img))
                write_image(out / f"view_{view:03d}" / f"{k:04d}.png", images[-1])
                if (view, k) in gt:
                    preds.append(img)
                    gts.append(gt[(view, k)].image)
                n += 1
                if progress:
                    progress(n, len(cams) * len(future))
            if video:
                write_video(out / f"view_{view:03d}.mp4", images, fps=tl.fps)
    summary = {"dynamics": dynamics, "frames": future, "views": sorted(cams), "out": str(out)}
    if preds:
        summary["metrics"] = image_metrics(preds, gts, lpips_nets=lpips_nets)
        summary["metrics"]["images"] = len(preds)
    write_json(out / "metrics.json", summary)
    return summary


def _cameras(frames: list[Frame]) -> dict[int, object]:
    cams: dict[int, object] = {}
    for i, f in enumerate(frames):
        key = f.view if f.view is not None else i
        cams.setdefault(key, f.camera)
    return cams


def render_view(run_dir, view: int, time: float | None, dynamics: str = "auto", out=None) -> np.ndarray:
    """One image of camera ``view`` (a dataset view id) at dataset time ``time`` (default 0); ``auto`` uses the
    kinematic path inside the observed window and the simulator beyond it."""
    model, data, tl = load_model(run_dir)
    cams = _cameras(data.frames())
    if view not in cams:
        raise CausalGSError(f"--view {view}: the dataset has views {min(cams)}..{max(cams)}")
    t = 0.0 if time is None else float(time)
    if not 0.0 <= t:
        raise CausalGSError(f"--time {t}: must be >= 0 (dataset time, 1 = the last frame)")
    k = round(t * (len(tl.times) - 1))
    if dynamics == "auto":
        dynamics = "velocity" if k < tl.train_frames or model.particles is None else "mpm"
    st = states(model, [k], dynamics)[k]
    with torch.no_grad():
        img, _, _ = model.render(st, cams[view], data.background)
    image = to_uint8(img.clamp(0, 1).float().numpy())
    if out is not None:
        write_image(out, image)
    return image
