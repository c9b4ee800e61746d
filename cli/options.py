"""Options shared by every command, so that ``--device``, ``--seed`` and ``--out`` mean the same everywhere."""

from __future__ import annotations

from pathlib import Path

import click

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
