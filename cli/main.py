"""The ``causalgs`` command line.

Commands only parse options, build a config, call one library function and save what it returns; the work lives in
the ``causalgs`` package. Errors caused by the input are printed as one line and exit with status 1, never with a
traceback.
"""

from __future__ import annotations

import signal
import sys
from pathlib import Path

import click

from causalgs import __version__
from causalgs.errors import CausalGSError
from cli.model import cluster, eval_, fit, predict
from cli.options import out_option, parse_rgb, seed_option
from cli.reframe import reframe
from cli.render import render


class _Group(click.Group):
    """Click group that turns :class:`CausalGSError` into a one-line message and a non-zero exit."""

    def invoke(self, ctx):
        try:
            return super().invoke(ctx)
        except CausalGSError as e:
            click.echo(f"Error: {e}", err=True)
            sys.exit(1)
        except KeyboardInterrupt:
            click.echo("Interrupted.", err=True)
            sys.exit(130)


@click.group(cls=_Group, context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 110})
@click.version_option(__version__, prog_name="causalgs")
def cli():
    """CausalGS: learn the physics of a dynamic 3D scene from multi-view video and predict its future.

    Every 3D Gaussian of the scene is also a physical particle. An inverse-physics model infers each particle's
    initial velocity and material (Young's modulus, Poisson ratio, density), and a differentiable MPM simulator moves
    the particles from those causes, trained end to end through the rendering loss.

    \b
    Typical session:
      causalgs synth bounce --out data/bounce       # a built-in scene with ground truth
      causalgs info data/bounce                     # check a dataset and print its summary
      causalgs fit data/bounce --out runs/bounce    # learn the scene (--preset quick|full)
      causalgs predict runs/bounce --frames 22      # extrapolate the future with the simulator
      causalgs eval runs/bounce                     # interpolation and extrapolation metrics
      causalgs render runs/bounce --view 3 --time 0.9 --out v3.png
    """


# ---------------------------------------------------------------------------------------------------------------------
# Built commands
# ---------------------------------------------------------------------------------------------------------------------
@cli.command()
@click.argument("name", type=click.Choice(["spin", "fallingball", "jelly", "collide", "room", "toss", "bounce",
                                           "tumble", "knock", "soft", "all"]))  # fmt: skip
@out_option()
@click.option("--views", type=click.IntRange(2, 200), default=20, show_default=True, help="Cameras on the ring.")
@click.option("--frames", type=click.IntRange(2, 1000), default=89, show_default=True, help="Frames in time.")
@click.option("--resolution", type=click.IntRange(8, 2048), default=128, show_default=True, help="Image side (px).")
@click.option(
    "--background",
    default="1,1,1",
    show_default=True,
    help="Background colour as 'r,g,b' in [0, 1]; images are RGBA and the reader composites them on it.",
)
@seed_option
@click.option(
    "--effects",
    default=None,
    help="Simulated scenes only: the external effects of the true motion, replacing the scene's default, as a spec "
    "of the simulator's effects, e.g. 'gravity;ground:mu=0.4;linear_drag:c=0.3;walls' (effects: gravity, force, "
    "linear_drag, quadratic_drag, ground, ground_sticky, walls, damping, plasticity).",
)
@click.option(
    "--fps",
    type=click.FloatRange(1.0, 10000.0),
    default=None,
    help="Capture rate in frames per second [default: 120 for the MPM scenes, 30 for bounce, 60 for tumble, knock "
    "and soft, whose future frames then still hold motion; 24 for spin].",
)
@click.option(
    "--reference-res",
    type=click.IntRange(8, 256),
    default=None,
    help="Simulated scenes only: grid cells along the longest side of the true motion's simulation box [default: 64, "
    "finer than a model's]. A model's own spacing gives a scene whose contacts and impacts its grid can reproduce "
    "(MPM contact depends on the grid), e.g. to test `causalgs discover` on an effect alone.",
)
@click.option("--force", is_flag=True, help="Overwrite an existing dataset in --out.")
def synth(name, out, views, frames, resolution, background, seed, effects, fps, reference_res, force):
    """Write the built-in scene NAME as a dataset in --out.

    The layout is the D-NeRF / NVFi one (transforms_{train,val,test}.json, RGBA PNGs, points3d.ply) plus gt/ with
    per-view per-frame object-id masks and the true motion.

    \b
    spin         a rigid fan spinning and drifting (analytic motion, ray-cast images)
    fallingball  a stiff ball thrown up, falling and bouncing on the ground
    jelly        a soft cube dropped on the ground, wobbling
    collide      a stiff ball thrown into a soft block
    room         a static room with three objects of different materials running into each other
    toss         an elastic block tossed without spin, landing and sliding (the scene of `causalgs discover`)
    bounce       a ball thrown with spin, bouncing (restitution 0.8) and rolling (MuJoCo)
    tumble       a box tossed with spin, tumbling and sliding to rest (MuJoCo)
    knock        a ball thrown into a standing box, both moving after the impact (MuJoCo)
    soft         a soft ball (MuJoCo flex) dropped with a roll, squashing and wobbling
    all          the benchmark scenes above (all but toss), each into --out/NAME

    fallingball to toss are simulated by the project's MPM on a fine reference grid (--effects sets their external
    effects), bounce to soft by MuJoCo, an independent engine; all are rendered from surface meshes by a z-buffer
    rasterizer, never by the model's rasterizer.

    train = the first 3/4 of the frames from all but the held-out views; val = the same frames from the held-out
    views (interpolation); test = the remaining future frames from every view (extrapolation).
    """
    from causalgs.synth import BENCHMARK, generate

    bg = parse_rgb(background, "--background")
    if name == "all" and effects is not None:
        raise CausalGSError("--effects applies to one simulated scene, not to 'all'")
    for n in BENCHMARK if name == "all" else [name]:
        target = Path(out) / n if name == "all" else out
        opts = {"views": views, "frames": frames, "resolution": resolution, "background": bg, "seed": seed}
        click.echo(generate(n, target, **opts, overwrite=force, effects=effects, fps=fps, reference_res=reference_res))


@cli.command()
@click.argument("data", type=click.Path(path_type=Path))
@click.option("--downscale", type=float, default=1.0, show_default=True, help="Image scale factor in (0, 1].")
def info(data, downscale):
    """Check the dataset in DATA and print its summary (splits, frames, views, times, image size).

    Every problem found (missing files, malformed JSON, non-rigid cameras, times outside [0, 1], images of
    inconsistent size, empty splits) is reported as one line naming the file and the value.
    """
    from causalgs.dataset import load_dataset

    ds = load_dataset(data, downscale=downscale)
    click.echo(ds.summary())


cli.add_command(render)
cli.add_command(fit)
cli.add_command(predict)
cli.add_command(eval_)
cli.add_command(cluster)
cli.add_command(reframe)


from cli.bench import bench  # noqa: E402
from cli.discover import discover, discover_table  # noqa: E402

cli.add_command(bench)
cli.add_command(discover)
cli.add_command(discover_table)


def stop_cleanly_on_sigterm() -> None:
    """Make SIGTERM end the command as an exit does (status 143) rather than killing it outright, so that what runs at
    exit still runs: Taichi writes the kernels the process compiled to its offline cache (minutes of compiling for
    a gradient kernel), which a killed process loses. Every output is written atomically, so a stop between two
    kernels leaves no partial file. A run started in the background of a script ignores SIGINT (the shell makes
    every such job do), so SIGTERM is how such a run is stopped. A handler someone else installed is kept."""
    if signal.getsignal(signal.SIGTERM) is signal.SIG_DFL:
        signal.signal(signal.SIGTERM, _exit_on_sigterm)


def _exit_on_sigterm(signum, frame) -> None:
    click.echo("Terminated.", err=True)
    sys.exit(128 + signal.SIGTERM)


def main():
    stop_cleanly_on_sigterm()
    cli(prog_name="causalgs")


if __name__ == "__main__":
    main()
