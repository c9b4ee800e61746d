"""``causalgs render``: render a saved run or a 3DGS PLY from a camera file or a dataset camera (image or turntable)."""

from __future__ import annotations

from pathlib import Path

import click

from causalgs.errors import CausalGSError
from cli.options import device_option, parse_rgb, precision_option

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
VIDEO_SUFFIXES = (".mp4",)
RUN_GAUSSIANS = "gaussians.ply"
WHITE = (1.0, 1.0, 1.0)


@click.command()
@click.argument("run", required=False, type=click.Path(path_type=Path))
@click.option("--ply", type=click.Path(dir_okay=False, path_type=Path), help="A 3DGS PLY to render instead of RUN.")
@click.option(
    "--camera",
    type=click.Path(dir_okay=False, path_type=Path),
    help="Camera JSON in the dataset's form: camera_angle_x or fl_x, w, h, OpenGL transform_matrix, [background].",
)
@click.option("--data", type=click.Path(path_type=Path), help="Take the camera from this dataset instead (see --view).")
@click.option(
    "--view", type=click.IntRange(min=0), help="With --data: index (0-based) of the frame in the split.  [default: 0]"
)
@click.option(
    "--split", type=click.Choice(["test", "val", "train"]), default="test", show_default=True, help="With --data."
)
@click.option("--time", "time_", type=float,
              help="Dataset time of a fitted RUN (0 = first frame, 1 = last frame of the video).")
@click.option("--dynamics", type=click.Choice(["auto", "mpm", "mpm-open", "velocity", "frozen"]), default="auto",
              show_default=True,
              help="Fitted RUN with --time: auto = kinematic inside the observed window, the simulator beyond it.")
@click.option(
    "--out",
    "out",
    type=click.Path(dir_okay=False, path_type=Path),
    required=True,
    help="Output file: .png/.jpg image, or .mp4 with --turntable (written atomically).",
)
@click.option(
    "--background",
    help="Background 'r,g,b' in [0, 1].  [default: the camera file's or dataset's background, else 1,1,1]",
)
@click.option("--turntable", type=click.IntRange(min=1), help="Render an orbit of this many frames to an MP4.")
@click.option(
    "--fps", type=click.FloatRange(min=0.0, min_open=True), default=24.0, show_default=True, help="Video fps."
)
@click.option(
    "--orbit-center",
    type=click.Choice(["lookat", "centroid"]),
    default="lookat",
    show_default=True,
    help="Turntable centre: the camera axis point nearest the Gaussians' centroid, or the centroid.",
)
@device_option
@precision_option
def render(
    run, ply, camera, data, view, split, time_, dynamics, out, background, turntable, fps, orbit_center, device,
    precision,
):
    """Render a fitted RUN at any time from any of its dataset's cameras, or the canonical Gaussians of a run
    folder or of a 3DGS PLY.

    A fitted RUN with --view N (a camera of its dataset, by view id) and optional --time T renders the moving scene
    (the kinematic path inside the observed window, the simulator beyond it; see --dynamics).

    The camera comes from --camera CAM.json or from frame --view of a dataset's --split (--data DIR). With
    --turntable N the camera orbits the scene (same distance and elevation, up = +z) and an MP4 is written.

    \b
    Examples:
      causalgs render runs/jelly --view 3 --time 0.9 --out future.png
      causalgs render --ply scene.ply --camera cam.json --out img.png
      causalgs render runs/spin --data data/spin --view 3 --split test --out view3.png
      causalgs render --ply scene.ply --data data/spin --turntable 120 --out orbit.mp4
    """
    from causalgs import _ti
    from causalgs.io import write_image
    from causalgs.ply import read_gaussians_ply
    from causalgs.render.views import load_camera_json, render_camera, render_turntable

    _check_out(out, turntable)
    if run is not None and (run / "checkpoint.pt").is_file() and data is None and camera is None and not turntable:
        _render_run(run, view or 0, time_, dynamics, out, device)
        return
    ply_path = _gaussians_path(run, ply)
    if camera is not None and data is not None:
        raise CausalGSError("give either --camera or --data, not both")
    if data is None and (view is not None or split != "test"):
        raise CausalGSError("--view and --split choose a dataset camera: they need --data DIR")
    if time_ is not None and not 0.0 <= time_ <= 1.0:
        raise CausalGSError(f"--time {time_:g} must be in [0, 1]")
    if data is None and camera is None and view is not None and run is not None:
        raise CausalGSError(f"{run}: not a fitted run (no checkpoint.pt); --view needs --data DIR for a PLY")
    if camera is not None:
        cam, bg = load_camera_json(camera)
    elif data is not None:
        cam, bg = _dataset_camera(data, split, 0 if view is None else view)
    else:
        raise CausalGSError("no camera: give --camera CAM.json or --data DIR --view N")
    if background is not None:
        bg = parse_rgb(background, "--background")
    bg = WHITE if bg is None else bg

    gaussians = read_gaussians_ply(ply_path)
    if time_ is not None:
        click.echo(
            f"Note: --time {time_:g}: time-dependent rendering of runs comes with `causalgs fit` (issue #6); "
            "rendering the canonical (t = 0) state.",
            err=True,
        )
    _ti.init(device, precision)
    n = len(gaussians["means"])
    if turntable:
        render_turntable(gaussians, cam, turntable, out, background=bg, fps=fps, center=orbit_center)
        click.echo(f"Wrote {out}: {turntable} frames at {cam.width}x{cam.height}, {fps:g} fps ({n} Gaussians)")
    else:
        write_image(out, render_camera(gaussians, cam, bg))
        click.echo(f"Wrote {out}: {cam.width}x{cam.height} ({n} Gaussians)")


def _render_run(run: Path, view: int, time_: float | None, dynamics: str, out: Path, device: str) -> None:
    from causalgs import _ti
    from causalgs.model.config import FitConfig
    from causalgs.model.evaluate import render_view

    _ti.init(device, FitConfig.load(run / "config.toml").precision)
    image = render_view(run, view, time_, dynamics, out)
    click.echo(f"Wrote {out}: view {view} at time {time_ or 0.0:g} ({image.shape[1]}x{image.shape[0]})")


def _check_out(out: Path, turntable: int | None) -> None:
    suffix = out.suffix.lower()
    if turntable:
        if suffix not in VIDEO_SUFFIXES:
            raise CausalGSError(f"--out {out}: a turntable is written as a video; use a .mp4 file name")
    elif suffix not in IMAGE_SUFFIXES:
        hint = " (or add --turntable N for a video)" if suffix in VIDEO_SUFFIXES else ""
        raise CausalGSError(f"--out {out}: use a {'/'.join(IMAGE_SUFFIXES)} file name for an image{hint}")
    if out.is_dir():
        raise CausalGSError(f"--out {out} is a folder; give a file name")


def _gaussians_path(run: Path | None, ply: Path | None) -> Path:
    if run is not None and ply is not None:
        raise CausalGSError("give either a RUN folder or --ply, not both")
    if ply is not None:
        return ply
    if run is None:
        raise CausalGSError("nothing to render: give a RUN folder or --ply FILE")
    if not run.exists():
        raise CausalGSError(f"run folder not found: {run}")
    if not run.is_dir():
        hint = " (use --ply for a PLY file)" if run.suffix.lower() == ".ply" else ""
        raise CausalGSError(f"{run}: not a run folder{hint}")
    path = run / RUN_GAUSSIANS
    if not path.is_file():
        raise CausalGSError(f"{run}: no {RUN_GAUSSIANS} (not a saved run folder)")
    return path


def _dataset_camera(root: Path, split: str, index: int):
    from causalgs.dataset import load_dataset

    ds = load_dataset(root, splits=(split,))
    frames = ds.splits[split]
    if not frames:
        raise CausalGSError(f"{root}: no {split} split (transforms_{split}.json); choose another --split")
    if index >= len(frames):
        raise CausalGSError(
            f"--view {index}: the {split} split of {root} has {len(frames)} frames (0..{len(frames) - 1})"
        )
    bg = ds.background
    return frames[index].camera, (float(bg[0]), float(bg[1]), float(bg[2]))
