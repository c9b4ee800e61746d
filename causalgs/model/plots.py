"""Plots people look at instead of reading logs: the training losses of a run, per stage (PNG, matplotlib Agg)."""

from __future__ import annotations

import io
import json
from pathlib import Path

from causalgs.io import write_bytes

_CURVES = {"canonical": ("loss",), "kinematic": ("loss",), "physics": ("image", "consistency"),
           "assimilate": ("loss",)}


def plot_losses(log_path, out_path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    series: dict[str, dict[str, tuple[list, list]]] = {}
    for line in Path(log_path).read_text().splitlines():
        r = json.loads(line)
        for key in _CURVES.get(r.get("stage"), ()):
            if isinstance(r.get(key), (int, float)):
                xs, ys = series.setdefault(r["stage"], {}).setdefault(key, ([], []))
                xs.append(r["it"])
                ys.append(r[key])
    stages = [s for s in _CURVES if s in series]
    if not stages:
        return
    fig, axes = plt.subplots(1, len(stages), figsize=(4.5 * len(stages), 3.4), squeeze=False)
    for ax, stage in zip(axes[0], stages, strict=True):
        for key, (xs, ys) in series[stage].items():
            ax.plot(xs, ys, label=key, lw=1)
        ax.set_yscale("log")
        ax.set_title(stage)
        ax.set_xlabel("iteration")
        ax.legend()
        ax.grid(alpha=0.3)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    write_bytes(out_path, buf.getvalue())
