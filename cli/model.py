"""``causalgs fit``, ``predict`` and ``eval``: parse options, build the config, call the library, report."""

from __future__ import annotations

import json
import math
from pathlib import Path

import click

from causalgs.errors import CausalGSError
from cli.options import device_option, seed_option

# causalgs.model.evaluate.DYNAMICS, spelled out so that --help does not import torch (a test holds them equal)
DYNAMICS = ("mpm", "mpm-open", "velocity", "frozen", "kinematic-only")


def _progress_callbacks(enabled: bool = True):
    """A rich progress bar with one task per stage; returns (callback, context manager)."""
    from causalgs.progress import progress_bar

    bar = progress_bar(enabled)
    tasks: dict[str, int] = {}

    def update(stage: str, step: int, total: int, losses: dict) -> None:
        if stage not in tasks:
            tasks[stage] = bar.add_task(stage, total=total)
        loss = losses.get("loss")
        desc = f"{stage} loss {loss:.4f}" if isinstance(loss, float) else stage
        bar.update(tasks[stage], completed=step, total=total, description=desc)

    return update, bar


@click.command()
@click.argument("data", type=click.Path(path_type=Path))
@click.option("--out", "out", type=click.Path(file_okay=False, path_type=Path), required=True,
              help="Run folder: config.toml, log.jsonl, losses.png, checkpoints, gaussians.ply, physics.npz.")
@click.option("--preset", type=click.Choice(["quick", "full"]), default="quick", show_default=True,
              help="quick: minutes per scene on a laptop CPU; full: longer schedules.")
@click.option("--config", "config_path", type=click.Path(dir_okay=False, path_type=Path),
              help="A config.toml (e.g. a previous run's) used instead of the preset.")
@click.option("--set", "overrides", multiple=True, metavar="KEY=VALUE",
              help="Override one setting, e.g. --set physics.iterations=20 --set physics.effects='gravity;ground'.")
@click.option("--no-physics", is_flag=True, help="Skip the physical stage (a kinematic-only model).")
@click.option("--resume", is_flag=True, help="Continue the run in --out from its last checkpoint.")
@seed_option
@device_option
def fit(data, out, preset, config_path, overrides, no_physics, resume, seed, device):
    """Learn the scene in DATA (a D-NeRF / NVFi layout folder) into the run folder --out.

    \b
    Stages (each with a progress bar; losses go to log.jsonl and losses.png):
      canonical  3D Gaussians at t = 0 (densified and pruned)
      kinematic  physics codes and velocity field through renders of the moving Gaussians
      track      each motion pattern's motion refined frame by frame against that frame's images
      physics    MPM particles from the dynamic Gaussians; materials, initial velocity and effect
                 parameters trained through the differentiable simulator; then one factor on every
                 E chosen by how well the replay fits the images (physics.calibrate; [] for off)
      assimilate where the forecast starts: 12 or 6 frames before the window's end
                 (physics.assimilate, physics.assimilate_scored), from the tracked or the replayed state,
                 whichever forecasts the newest 6 observed frames best (assimilate=0: off); the
                 forecast goes on from the last observed frame's tracked positions with the velocities
                 that simulation reaches there (physics.anchor)
    An interrupted fit continues with --resume. The resolved config is saved as config.toml.
    """
    from causalgs import _ti
    from causalgs.model.config import FitConfig, apply_override, from_dict, to_dict
    from causalgs.model.fit import fit as run_fit

    if resume:
        if config_path or no_physics or any(not o.strip().startswith("frame.") for o in overrides):
            raise CausalGSError("--resume continues with the run's saved config.toml; drop --config, --no-physics and "
                                "every --set but frame.* (the physics frame is found where the kinematic stage ends)")
        config = None
        if overrides:
            d = to_dict(FitConfig.load(Path(out) / "config.toml"))
            for item in overrides:
                apply_override(d, item)
            config = from_dict(FitConfig, d)
    else:
        config = FitConfig.load(config_path) if config_path else FitConfig.preset_config(preset)
        d = to_dict(config)
        d["seed"] = seed
        if no_physics:
            d["physics"]["enabled"] = False
        for item in overrides:
            apply_override(d, item)
        config = from_dict(FitConfig, d)
    precision = config.precision if config else FitConfig.load(Path(out) / "config.toml").precision
    _ti.init(device, precision)
    update, bar = _progress_callbacks()
    with bar:
        model = run_fit(data, out, config, resume=resume, progress=update)
    info = json.loads((Path(out) / "run.json").read_text())
    click.echo(f"Fitted {info['data']} -> {out}: {int(model.dynamic.sum())} dynamic / {model.gaussians.n} Gaussians, "
               f"{len(model.particles) if model.particles is not None else 0} particles, "
               f"{info['total_seconds']:.0f} s")  # fmt: skip


@click.command()
@click.argument("run", type=click.Path(file_okay=False, path_type=Path))
@click.option("--frames", type=click.IntRange(min=1), default=22, show_default=True, help="Future frames to predict.")
@click.option("--dynamics", type=click.Choice(DYNAMICS), default="mpm", show_default=True,
              help="mpm: the tracked state, then the simulator continuing from it; mpm-open: the simulator replaying "
              "everything from t = 0; velocity: the kinematic field extrapolated; frozen: the last observed frame; "
              "kinematic-only: the model before its physical stage.")
@click.option("--out", "out", type=click.Path(file_okay=False, path_type=Path),
              help="Output folder.  [default: RUN/predict/DYNAMICS]")
@click.option("--no-video", is_flag=True, help="Write PNGs only.")
@click.option("--lpips", "lpips_nets", default="alex", show_default=True,
              help="LPIPS networks to score with: 'alex', 'vgg', 'alex,vgg' or 'none' (VGG is ~20x slower on a CPU).")
@device_option
def predict(run, frames, dynamics, out, no_video, lpips_nets, device):
    """Render the future: the FRAMES frames after the observed window, from every test camera of RUN's dataset.

    Writes view_NNN/FFFF.png and view_NNN.mp4 per camera and metrics.json (PSNR, SSIM, LPIPS) where the dataset
    has ground truth for those frames.
    """
    from causalgs import _ti
    from causalgs.model.config import FitConfig
    from causalgs.model.evaluate import predict as run_predict

    _check_run(run)
    _ti.init(device, FitConfig.load(run / "config.toml").precision)
    update, bar = _progress_callbacks()
    with bar:
        summary = run_predict(run, frames, dynamics, out, video=not no_video, lpips_nets=_nets(lpips_nets),
                              progress=lambda i, n: update("predict", i, n, {}))  # fmt: skip
    line = f"Predicted frames {summary['frames'][0]}..{summary['frames'][-1]} from {len(summary['views'])} views "
    line += f"({dynamics}) -> {summary['out']}"
    m = summary.get("metrics")
    if m:
        line += f"; PSNR {m['psnr']:.2f} dB, SSIM {m['ssim']:.4f}"
        if m.get("lpips_alex") is not None:
            line += f", LPIPS(alex) {m['lpips_alex']:.4f}"
    click.echo(line)


@click.command(name="eval")
@click.argument("run", type=click.Path(file_okay=False, path_type=Path))
@click.option("--dynamics", multiple=True, type=click.Choice(DYNAMICS),
              help="Dynamics to score (repeatable).  [default: mpm, mpm-open, frozen, kinematic-only]")
@click.option("--lpips", "lpips_nets", default="alex,vgg", show_default=True,
              help="LPIPS networks: 'alex', 'vgg', 'alex,vgg' or 'none' (VGG is ~20x slower on a CPU).")
@click.option("--json", "as_json", is_flag=True, help="Print metrics.json to stdout.")
@device_option
def eval_(run, dynamics, lpips_nets, as_json, device):
    """Score RUN: interpolation (val: held-out views at observed times) and extrapolation (test: future frames) by
    every dynamics; PSNR (per-image mean and pooled), SSIM, LPIPS (AlexNet, VGG). Writes RUN/metrics.json."""
    from causalgs import _ti
    from causalgs.model.config import FitConfig
    from causalgs.model.evaluate import EVAL_DYNAMICS, evaluate

    _check_run(run)
    _ti.init(device, FitConfig.load(run / "config.toml").precision)
    result = evaluate(run, dynamics=dynamics or EVAL_DYNAMICS, lpips_nets=_nets(lpips_nets))
    if as_json:
        click.echo(json.dumps(result, indent=2))
        return
    for key in ("interpolation", "extrapolation"):
        for dyn, m in result[key].items():
            lp = m.get("lpips_alex")
            lp = f"{lp:.4f}" if lp is not None else "n/a"
            click.echo(f"{key:14s} {dyn:15s} PSNR {m['psnr']:6.2f}  SSIM {m['ssim']:.4f}  LPIPS(alex) {lp}  "
                       f"({m['images']} images)")  # fmt: skip
    rec = result.get("recovery")
    if rec:
        for o in rec["objects"]:
            if o.get("gaussians"):
                rel = o["velocity_error_relative"]
                spin = ""
                if o.get("omega_model") is not None:
                    spin = (f", spin {math.hypot(*o['omega_model']):.2f} rad/s "
                            f"(true {math.hypot(*o['omega_true']):.2f})")  # fmt: skip
                click.echo(f"object {o['id']} {o['name']}: E {o['E_model']:.3g} (true {o['E_true']:.3g}), initial "
                           f"velocity error {o['velocity_error_mean']:.3f} m/s"
                           + (f" ({100 * rel:.0f}% of its speed)" if rel is not None else "") + spin)  # fmt: skip
        if rec["stiffness_order_ok"] is not None:
            click.echo(f"stiffness order of the objects: {'right' if rec['stiffness_order_ok'] else 'wrong'}")
    click.echo(f"Wrote {run / 'metrics.json'}")


def _nets(text: str) -> tuple[str, ...]:
    nets = tuple(n.strip() for n in text.split(",") if n.strip() and n.strip() != "none")
    bad = [n for n in nets if n not in ("alex", "vgg")]
    if bad:
        raise CausalGSError(f"--lpips {text}: unknown network(s) {', '.join(bad)} (alex, vgg or none)")
    return nets


def _check_run(run: Path) -> None:
    if not run.is_dir():
        raise CausalGSError(f"run folder not found: {run}")
    for name in ("config.toml", "run.json", "checkpoint.pt"):
        if not (run / name).is_file():
            raise CausalGSError(f"{run}: no {name} (not a fitted run folder; run `causalgs fit DATA --out {run}`)")


@click.command()
@click.argument("run", type=click.Path(file_okay=False, path_type=Path))
@click.option("--k", type=click.IntRange(min=1), help="Number of dynamic clusters.  [default: by silhouette score]")
@click.option("--k-max", type=click.IntRange(min=2), default=6, show_default=True, help="Largest K tried.")
@click.option("--masks/--no-masks", default=True, show_default=True,
              help="Render the labels into masks/r_VVV_FFF.png for every test camera at --times frames and score them "
                   "against the dataset's gt/masks: AP, PQ, F1, precision, recall, mIoU.")  # fmt: skip
@click.option("--times", type=click.IntRange(min=1), default=10, show_default=True,
              help="Evenly spaced frames of the video the masks are rendered at.")  # fmt: skip
@seed_option
@device_option
def cluster(run, k, k_max, masks, times, seed, device):
    """Segment RUN into objects by learned physics: K-means on each dynamic Gaussian's physics code, log E and nu.

    Writes RUN/cluster/labels.npy (0 = static), clusters.ply (the Gaussians coloured by cluster, for any 3DGS viewer),
    clusters.png (a dataset view of it), masks/ (label masks) and cluster.json (sizes, median materials, and, with
    ground truth, the Hungarian-matched accuracy and per-object IoU, and the masks' segmentation scores).
    """
    from causalgs import _ti
    from causalgs.dataset import load_dataset
    from causalgs.io import read_json, write_image
    from causalgs.model.cluster import cluster_run
    from causalgs.ply import read_gaussians_ply
    from causalgs.render.views import render_camera

    _check_run(run)
    _ti.init(device, "float32")
    report = cluster_run(run, k, k_max, seed, masks=times if masks else 0)
    data = load_dataset(read_json(run / "run.json", "run info")["data"], splits=("train",))
    cam = data.train[0].camera
    write_image(run / "cluster" / "clusters.png", render_camera(read_gaussians_ply(run / "cluster" / "clusters.ply"),
                                                                cam, tuple(data.background)))  # fmt: skip
    line = f"{report['k']} dynamic cluster(s): " + ", ".join(
        f"#{c['id']} {c['gaussians']} Gaussians, E {c['E_median']:.3g}" for c in report["clusters"]
    )
    gt = report.get("ground_truth")
    if gt and gt.get("matched_accuracy") is not None:
        line += f"; matched accuracy vs true objects {100 * gt['matched_accuracy']:.1f}%"
    sc = (report.get("segmentation") or {}).get("scores")
    if sc:
        line += (f"; masks AP {sc['ap']:.3f} PQ {sc['pq']:.3f} F1 {sc['f1']:.3f} P {sc['precision']:.3f} "
                 f"R {sc['recall']:.3f} mIoU {sc['miou']:.3f}")  # fmt: skip
    click.echo(line)
    click.echo(f"Wrote {run / 'cluster'}")
