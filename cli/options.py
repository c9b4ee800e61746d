"""Options shared by every command, so that ``--device``, ``--seed`` and ``--out`` mean the same everywhere."""

from __future__ import annotations

from pathlib import Path

import click

from causalgs.errors import CausalGSError

device_option = click.option(
    "--device",
    type=click.Choice(["cpu", "gpu"]),
    default="cpu",
    show_default=True,
    help="Where Taichi kernels run. 'gpu' tries CUDA, then Vulkan, and falls back to the CPU with a message.",
)

precision_option = click.option(
    "--precision",
    type=click.Choice(["float32", "float64"]),
    default="float32",
    show_default=True,
    help="Floating-point precision of the Taichi fields and kernels.",
)

seed_option = click.option(
    "--seed", type=int, default=0, show_default=True, help="Random seed; the same seed gives the same result."
)


def out_option(required: bool = True, help: str = "Output folder (created if missing; files are written atomically)."):
    return click.option(
        "--out",
        "out",
        type=click.Path(file_okay=False, path_type=Path),
        required=required,
        help=help,
    )


def parse_rgb(text: str, what: str) -> tuple[float, float, float]:
    """An 'r,g,b' option value in [0, 1], or a one-line error naming the option."""
    try:
        vals = tuple(float(s) for s in text.split(","))
    except ValueError:
        raise CausalGSError(f"{what} '{text}' must be three numbers 'r,g,b' in [0, 1]") from None
    if len(vals) != 3 or not all(0.0 <= v <= 1.0 for v in vals):
        raise CausalGSError(f"{what} '{text}' must be three numbers 'r,g,b' in [0, 1]")
    return vals
