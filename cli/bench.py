"""``causalgs bench``: machine-readable speed figures."""

from __future__ import annotations

import json
import time

import click

from cli.options import device_option, precision_option


def _ints(text: str, what: str) -> tuple[int, ...]:
    try:
        vals = tuple(int(float(s)) for s in text.split(","))
    except ValueError:
        raise click.BadParameter(f"'{text}' must be comma-separated integers", param_hint=what) from None
    if not vals or min(vals) < 1:
        raise click.BadParameter(f"'{text}' must be positive integers", param_hint=what)
    return vals


@click.group()
def bench():
    """Benchmarks printing one JSON object per measurement (medians of repeated runs).

    Figures compared with each other (e.g. the rasterizer against the dense torch reference) are measured side by
    side in one process on the same inputs; these machines are shared and noisy, so compare ratios, not absolutes
    across runs.
    """


@bench.command()
@click.option("--sizes", default="128,256,512", show_default=True, help="Image sides (px), comma-separated.")
@click.option("--counts", default="1000,10000,100000", show_default=True, help="Gaussian counts, comma-separated.")
@click.option("--repeats", type=click.IntRange(1, 1000), default=5, show_default=True, help="Timed runs per case.")
@click.option(
    "--scene",
    type=click.Choice(["surface", "volume"]),
    default="surface",
    show_default=True,
    help="surface: opaque splats on a sphere, like a trained object; volume: a cube of half-transparent splats.",
)
@click.option("--reference-limit", type=float, default=1e8, show_default=True,
              help="Skip the dense torch reference above this many Gaussian-pixel pairs.")  # fmt: skip
@click.option("--json", "as_json", is_flag=True, help="Print JSON lines only (default: JSON lines plus a table).")
@device_option
@precision_option
def render(sizes, counts, repeats, scene, reference_limit, as_json, device, precision):
    """Rasterizer forward and forward+backward milliseconds, first-call (compile or cache load) time, and the
    dense torch reference on the same inputs where it is affordable."""
    from causalgs import _ti
    from causalgs.bench import render_benchmark

    _ti.init(device, precision)
    rows = []
    for rec in render_benchmark(_ints(sizes, "--sizes"), _ints(counts, "--counts"), repeats, scene, reference_limit):
        click.echo(json.dumps(rec))
        rows.append(rec)
    if not as_json:
        from rich.console import Console
        from rich.table import Table

        table = Table(title=f"render ({scene}, {precision}, {rows[0]['arch'] if rows else device})")
        for col in ("size", "gaussians", "forward_ms", "forward_backward_ms", "speedup_forward_backward"):
            table.add_column(col, justify="right")
        for r in rows:
            table.add_row(*(str(r.get(c, "-")) for c in ("size", "gaussians", "forward_ms", "forward_backward_ms",
                                                         "speedup_forward_backward")))  # fmt: skip
        Console(stderr=True).print(table)


@bench.command()
@click.option("--counts", default="1000,8000,32000", show_default=True, help="Particle counts, comma-separated.")
@click.option("--grids", default="32,64", show_default=True, help="Grid resolutions (cells per side), comma-separated.")
@click.option("--repeats", type=click.IntRange(1, 1000), default=5, show_default=True, help="Timed runs per case.")
@click.option("--segment", type=click.IntRange(1, 256), default=8, show_default=True,
              help="Substeps per checkpoint segment.")  # fmt: skip
@click.option("--compile/--no-compile", "compile_", default=True, show_default=True,
              help="Also measure cold and warm compile time of the differentiable step (fresh processes, an empty "
              "then a filled kernel cache; minutes when cold).")  # fmt: skip
@click.option("--json", "as_json", is_flag=True, help="Print JSON lines only (default: JSON lines plus a table).")
@device_option
@precision_option
def sim(counts, grids, repeats, segment, compile_, as_json, device, precision):
    """MPM forward and forward+backward milliseconds per substep (a falling elastic block, gravity, Coulomb ground,
    walls), the fused substep's speed-up over one kernel per phase, the memory of the differentiable state for one
    simulated second with and without checkpoints, and the cold/warm compile time of the differentiable step."""
    from causalgs import _ti
    from causalgs.bench import sim_benchmark, sim_compile_benchmark

    _ti.init(device, precision)
    rows = []
    for rec in sim_benchmark(_ints(counts, "--counts"), _ints(grids, "--grids"), repeats, segment):
        click.echo(json.dumps(rec))
        rows.append(rec)
    if compile_:
        click.echo(json.dumps(sim_compile_benchmark(precision)))
    if not as_json:
        from rich.console import Console
        from rich.table import Table

        cols = ("grid", "particles", "forward_ms_per_substep", "fused_speedup", "forward_backward_ms_per_substep",
                "backward_over_forward", "memory_checkpointed_mb", "memory_full_tape_mb")  # fmt: skip
        table = Table(title=f"sim ({precision}, {rows[0]['arch'] if rows else device})")
        for col in cols:
            table.add_column(col, justify="right")
        for r in rows:
            table.add_row(*(str(r.get(c, "-")) for c in cols))
        Console(stderr=True).print(table)


@bench.command(name="discover")
@click.option("--grids", default="20,43", show_default=True,
              help="Grid resolutions (cells over the scene's box), comma-separated: 20 is the trajectory table's, "
              "43 the video table's.")  # fmt: skip
@click.option("--repeats", type=click.IntRange(1, 1000), default=5, show_default=True, help="Timed runs per case.")
@click.option("--frames", type=click.IntRange(2, 1000), default=30, show_default=True,
              help="Frames of the landing (at 24 fps: the trajectory table's window).")  # fmt: skip
@click.option("--fps", type=click.FloatRange(1.0, 1000.0), default=24.0, show_default=True,
              help="Frame rate of the landing (the video table's is 120).")  # fmt: skip
@click.option("--workers", default=None,
              help="Also time one calibration Jacobian (a rollout per parameter) here and with each of these "
                   "counts of worker processes, comma-separated (`causalgs discover --workers`), on the first grid "
                   "of --grids.")  # fmt: skip
@device_option
@precision_option
def discover_bench(grids, repeats, frames, fps, workers, device, precision):
    """Seconds of one discovery rollout of the hidden-effect table's tossed block (its landing, the truth's
    particles on the truth's grid) and milliseconds per MPM substep: a discovery runs hundreds of these. With
    --workers, the seconds of a Jacobian here and in worker processes, timed in turn, and their ratio."""
    from causalgs import _ti
    from causalgs.bench import discover_benchmark, discover_workers_benchmark

    _ti.init(device, precision)
    resolutions = _ints(grids, "--grids")
    for rec in discover_benchmark(resolutions, repeats, frames, fps):
        click.echo(json.dumps(rec))
    if workers:
        for rec in discover_workers_benchmark(resolutions[0], _ints(workers, "--workers"), repeats, frames, fps):
            click.echo(json.dumps(rec))


@bench.command(name="jobs")
@click.option("--jobs", type=click.IntRange(2, 64), default=2, show_default=True,
              help="Pieces at once, each in a process pinned to its own share of the CPUs "
                   "($CAUSALGS_TI_CPUS, else all this process may use), as `discover-table --jobs`.")  # fmt: skip
@click.option("--pieces", type=click.IntRange(1, 256), default=4, show_default=True,
              help="Equal pieces of work, the table's rows.")  # fmt: skip
@click.option("--work", type=click.Choice(["rollout", "render"]), default="rollout", show_default=True,
              help="A piece's unit: rollout, one discovery rollout of the tossed block's landing (on --grid); "
                   "render, one forward+backward pass of the rasterizer (20k Gaussians, 128²), of which a fit's "
                   "steps are made.")  # fmt: skip
@click.option("--grid", type=click.IntRange(8, 64), default=20, show_default=True,
              help="Rollout work: cells over the scene's box (20: the trajectory table's, 43: the video table's).")
@click.option("--units", type=click.IntRange(1, 10000), default=5, show_default=True, help="Units per piece.")
@click.option("--cycles", type=click.IntRange(1, 100), default=3, show_default=True,
              help="Times the two ways are run, in turn.")  # fmt: skip
@click.option("--frames", type=click.IntRange(2, 1000), default=30, show_default=True,
              help="Rollout work: frames of the landing.")  # fmt: skip
def jobs_bench(jobs, pieces, work, grid, units, cycles, frames):
    """What `discover-table --jobs` buys on this machine: equal pieces of work run as the table runs its rows, one
    after the other in this process on all its CPUs and --jobs at once in pinned processes (the table's own code),
    in turn in one run. Prints one JSON record: the median seconds of a piece either way, throughput_ratio (pieces
    per second side by side over one after the other, the processes' start left out, as for rows hours long) and
    wall_ratio (all pieces' wall seconds, the start included). CPU, float32, as the table runs."""
    from rich.console import Console

    from causalgs import _ti
    from causalgs.bench import jobs_benchmark

    _ti.init("cpu", "float32")
    console = Console(stderr=True)
    rec = jobs_benchmark(jobs, pieces, work, grid, units, cycles, frames, log=console.log)
    click.echo(json.dumps(rec))


@bench.command(name="fit")
@click.option("--data", "data_root", type=click.Path(file_okay=False), required=True,
              help="Folder with one dataset per scene (e.g. the output of `causalgs synth all`).")  # fmt: skip
@click.option("--out", "out_root", type=click.Path(file_okay=False), required=True, help="Folder for the runs.")
@click.option("--scenes", default="fallingball,jelly,collide,room,spin,bounce,tumble,knock,soft", show_default=True,
              help="Scenes (sub-folders of --data), comma-separated: MPM-made and MuJoCo-made.")  # fmt: skip
@click.option("--preset", type=click.Choice(["quick", "full"]), default="quick", show_default=True)
@click.option("--lpips", "lpips_nets", default="alex,vgg", show_default=True, help="LPIPS networks: alex, vgg, none.")
@click.option("--json", "as_json", is_flag=True, help="Print JSON lines only.")
@device_option
def fit_(data_root, out_root, scenes, preset, lpips_nets, as_json, device):
    """Fit, then evaluate, every scene: one JSON line per scene (fit seconds per stage, interpolation and
    extrapolation metrics of the simulator and its baselines, the recovered initial velocity and spin and the
    inferred up and gravity against the truth), then two tables. Runs already fitted in --out are evaluated again,
    not refitted."""
    from pathlib import Path

    from causalgs import _ti
    from causalgs.model.config import FitConfig
    from causalgs.model.evaluate import DYNAMICS, evaluate
    from causalgs.model.fit import fit as run_fit
    from cli.model import _nets

    _ti.init(device, "float32")
    rows = []
    for scene in [s.strip() for s in scenes.split(",") if s.strip()]:
        run = Path(out_root) / scene
        if not (run / "physics.npz").is_file():
            resume = (run / "checkpoint.pt").is_file()
            run_fit(Path(data_root) / scene, run, None if resume else FitConfig.preset_config(preset), resume=resume)
        info = json.loads((run / "run.json").read_text())
        t0 = time.monotonic()
        metrics = evaluate(run, dynamics=DYNAMICS, lpips_nets=_nets(lpips_nets))
        row = {"scene": scene, "preset": preset, "fit_seconds": info.get("total_seconds"),
               "stage_seconds": info.get("stage_seconds"), "eval_seconds": time.monotonic() - t0,
               **metrics}  # fmt: skip
        rows.append(row)
        click.echo(json.dumps(row))
    if not as_json:
        click.echo(fit_table(rows))


# Table 1's two conventions: which PSNR and LPIPS each paper reports (SSIM: 11×11 Gaussian window, RGB, both)
CONVENTIONS = {
    "FreeGave": ("psnr", "lpips_vgg_unscaled", "PSNR: mean of per-image PSNR; LPIPS: VGG on the [0, 1] images "
                 "unscaled, as FreeGave's metrics.py"),
    "NVFi": ("psnr_pooled", "lpips_vgg", "PSNR: of the pooled MSE; LPIPS: VGG on images scaled to [-1, 1]"),
}


def fit_table(rows: list[dict]) -> str:
    """Markdown tables, one per convention (:data:`CONVENTIONS`): per scene and dynamics, interpolation and
    extrapolation PSNR / SSIM / LPIPS and the fit's seconds; then :func:`recovery_table`."""

    def f(v, fmt):
        return "n/a" if v is None else format(v, fmt)

    parts = []
    for name, (pk, lk, what) in CONVENTIONS.items():
        lines = [f"**{name}'s convention** ({what}; SSIM: mean per image, 11×11 Gaussian window, RGB)", "",
                 "| scene | dynamics | interp. PSNR | SSIM | LPIPS | extrap. PSNR | SSIM | LPIPS | fit s |",
                 "|---" * 9 + "|"]  # fmt: skip
        for r in rows:
            splits = [r.get("interpolation", {}), r.get("extrapolation", {})]
            for dyn in dict.fromkeys([d for sp in splits for d in sp]):
                cells = []
                for sp in splits:
                    m = sp.get(dyn) or {}
                    cells += [f(m.get(pk), ".2f"), f(m.get("ssim"), ".4f"), f(m.get(lk), ".4f")]
                lines.append(f"| {r['scene']} | {dyn} | {' | '.join(cells)} | {f(r['fit_seconds'], '.0f')} |")
        parts.append("\n".join(lines))
    return "\n\n".join(parts) + "\n\n" + recovery_table(rows)


def recovery_table(rows: list[dict]) -> str:
    """A markdown table: per scene and body, the learned initial velocity and spin against the truth, and the
    inferred frame (up's error, gravity's magnitude over the truth's)."""
    lines = ["| scene | body | velocity true (m/s) | velocity error | spin true (rad/s) | spin learned | up error | "
             "gravity / truth |", "|---" * 8 + "|"]  # fmt: skip

    def vec(v):
        return "n/a" if v is None else "(" + ", ".join(f"{a:.2f}" for a in v) + ")"

    for r in rows:
        fr = r.get("frame") or {}
        up = "n/a" if fr.get("up_error_deg") is None else f"{fr['up_error_deg']:.2f}°"
        g = "n/a" if fr.get("gravity_ratio") is None else f"{fr['gravity_ratio']:.3f}"
        for o in (r.get("recovery") or {}).get("objects", []) or [{}]:
            rel = o.get("velocity_error_relative")
            lines.append(f"| {r['scene']} | {o.get('name', 'n/a')} | {vec(o.get('velocity_true_mean'))} | "
                         f"{'n/a' if rel is None else f'{100 * rel:.0f}%'} | {vec(o.get('omega_true'))} | "
                         f"{vec(o.get('omega_model'))} | {up} | {g} |")  # fmt: skip
    return "\n".join(lines)


@bench.command(name="ablate")
@click.option("--data", "data_root", type=click.Path(file_okay=False), required=True,
              help="Folder with one dataset per scene (e.g. the output of `causalgs synth all`).")  # fmt: skip
@click.option("--out", "out_root", type=click.Path(file_okay=False), required=True,
              help="Folder for the runs (SCENE/ROW); finished runs are scored again, not refitted.")  # fmt: skip
@click.option("--scenes", default="jelly,fallingball,bounce", show_default=True, help="Scenes, comma-separated.")
@click.option("--rows", default="full,no simulator,VFD off,IPI off,K=4,K=32", show_default=True,
              help="Ablation rows, comma-separated: full, no simulator, VFD off, IPI off, K=4, K=32.")  # fmt: skip
@click.option("--preset", type=click.Choice(["quick", "full"]), default="quick", show_default=True)
@click.option("--lpips", "lpips_nets", default="alex,vgg", show_default=True, help="LPIPS networks: alex, vgg, none.")
@device_option
def ablate(data_root, out_root, scenes, rows, preset, lpips_nets, device):
    """The paper's ablation table: every scene fitted with one part of the model switched off or resized, the
    extrapolation scored (PSNR, SSIM, LPIPS). One JSON line per row, then a markdown table."""
    from rich.console import Console

    from causalgs import _ti
    from causalgs.model.ablation import ablation_table, run_ablation
    from cli.model import _nets

    _ti.init(device, "float32")
    console = Console(stderr=True)
    results = run_ablation(data_root, out_root, [s.strip() for s in scenes.split(",") if s.strip()],
                           [r.strip() for r in rows.split(",") if r.strip()], preset=preset,
                           lpips_nets=_nets(lpips_nets), log=console.log)  # fmt: skip
    for r in results:
        click.echo(json.dumps({"scene": r.scene, "row": r.row, "run": str(r.run), "extrapolation": r.metrics}))
    click.echo(ablation_table(results))
