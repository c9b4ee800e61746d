"""``causalgs reframe``: parse the transform, call :func:`causalgs.reframe.reframe_dataset`."""

from __future__ import annotations

import math
from pathlib import Path

import click

from causalgs.errors import CausalGSError
from cli.options import out_option, seed_option


def _translation(text: str):
    try:
        vals = [float(s) for s in text.split(",")]
    except ValueError:
        vals = []
    if len(vals) != 3 or not all(math.isfinite(v) for v in vals):
        raise CausalGSError(f"--translate {text!r} must be three finite numbers 'x,y,z'")
    return vals


@click.command()
@click.argument("data", type=click.Path(path_type=Path))
@out_option()
@click.option("--rotate", default="z:0", show_default=True, metavar="AXIS:DEG|random|M",
              help="Rotation: AXIS:DEG about x, y, z or an axis 'a,b,c' (e.g. 'x:90', '1,1,0:30'), 'random' "
              "(drawn from --seed), or nine numbers of a row-major rotation matrix.")  # fmt: skip
@click.option("--scale", type=float, default=1.0, show_default=True,
              help="Length scale: the new scene units per old unit (> 0).")  # fmt: skip
@click.option("--translate", default="0,0,0", show_default=True, metavar="X,Y,Z",
              help="Translation after rotating and scaling, in the new units.")  # fmt: skip
@seed_option
@click.option("--force", is_flag=True, help="Overwrite an existing folder in --out.")
def reframe(data, out, rotate, scale, translate, seed, force):
    """Write the dataset DATA re-posed in another world frame into --out: x' = scale · R x + t.

    Cameras, points3d.ply and the ground truth in gt/ are transformed; the images are the same (the same cameras
    see the same scene). gt/meta.json records the transform from the original frame. A fit of the copy should
    forecast what a fit of the original does: causalgs infers up and gravity from the video, not from the frame.
    """
    from causalgs.reframe import reframe_dataset
    from causalgs.similarity import Similarity, parse_rotation

    sim = Similarity.make(parse_rotation(rotate, seed), scale, _translation(translate), what="--rotate/--scale")
    click.echo(reframe_dataset(data, out, sim, overwrite=force))
