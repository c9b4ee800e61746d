"""The paper's ablation (its Table 4): the full model against itself without one part, as config switches.

Each row is a fit of the same scene with a few settings changed (``--set`` overrides of the preset) and the dynamics
whose extrapolation is scored:

- ``full``: the model as configured (K = 16 motion patterns), forecasting with the simulator;
- ``no simulator``: the same fit's kinematic-only model (``kinematic.pt``), its velocity field extrapolated;
- ``VFD off``: an unstructured velocity v(x0, t) per material point instead of code, bottleneck and basis
  (``fields.velocity=mlp``, :class:`~causalgs.model.fields.Flow`);
- ``IPI off``: one material for the whole scene instead of f_mat's per-particle inference (``fields.materials``);
- ``K=4``, ``K=32``: other numbers of motion patterns.

Fits that already finished in the output folder are scored again, not refitted; an interrupted one resumes.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

from causalgs.errors import CausalGSError
from causalgs.model.config import FitConfig, apply_override, from_dict, to_dict


@dataclass(frozen=True)
class Ablation:
    """One row: ``overrides`` (``KEY=VALUE`` as ``fit --set`` takes them), the dynamics scored, and the run it
    reads (its own unless ``run`` names another row's)."""

    overrides: tuple[str, ...] = ()
    dynamics: str = "mpm"
    run: str | None = None


ABLATIONS: dict[str, Ablation] = {
    "full": Ablation(),
    "no simulator": Ablation(dynamics="kinematic-only", run="full"),
    "VFD off": Ablation(("fields.velocity=mlp",)),
    "IPI off": Ablation(("fields.materials=global",)),
    "K=4": Ablation(("fields.patterns=4",)),
    "K=32": Ablation(("fields.patterns=32",)),
}


@dataclass
class AblationResult:
    """One scored row: the scene, the row's name, its run folder and its extrapolation metrics."""

    scene: str
    row: str
    run: Path
    metrics: dict


def _slug(name: str) -> str:
    return "".join(c if c.isalnum() else "-" for c in name.lower()).strip("-")


def ablation_config(preset: str, ablation: Ablation) -> FitConfig:
    d = to_dict(FitConfig.preset_config(preset))
    for item in ablation.overrides:
        apply_override(d, item)
    return from_dict(FitConfig, d)


def run_ablation(data_root, out_root, scenes: Sequence[str], rows: Sequence[str], *, preset: str = "quick",
                 lpips_nets=("alex", "vgg"), log: Callable[[str], None] | None = None) -> list[AblationResult]:
    """Fit (or resume, or reuse) and score every (scene, row): extrapolation metrics of the row's dynamics."""
    from causalgs.model.evaluate import evaluate
    from causalgs.model.fit import fit

    unknown = [r for r in rows if r not in ABLATIONS]
    if unknown:
        raise CausalGSError(f"unknown ablation row(s) {', '.join(unknown)} (rows: {', '.join(ABLATIONS)})")
    out = []
    for scene in scenes:
        data = Path(data_root) / scene
        if not data.is_dir():
            raise CausalGSError(f"{data}: no such scene folder")
        for row in rows:
            ab = ABLATIONS[row]
            source = ab.run or row
            run = Path(out_root) / scene / _slug(source)
            if not (run / "physics.npz").is_file():
                resume = (run / "checkpoint.pt").is_file()
                if log:
                    log(f"{scene}: fitting '{source}' into {run}")
                fit(data, run, None if resume else ablation_config(preset, ABLATIONS[source]), resume=resume)
            metrics = evaluate(run, dynamics=(ab.dynamics,), lpips_nets=lpips_nets)
            out.append(AblationResult(scene, row, run, metrics["extrapolation"].get(ab.dynamics, {})))
    return out


def ablation_table(results: Sequence[AblationResult]) -> str:
    """Markdown: one line per scene and row, extrapolation PSNR (mean per image) / SSIM / LPIPS (VGG, AlexNet)."""

    def f(v, fmt):
        return "n/a" if v is None else format(v, fmt)

    lines = ["| scene | model | PSNR | SSIM | LPIPS vgg | LPIPS alex |", "|---" * 6 + "|"]
    for r in results:
        m = r.metrics
        lines.append(f"| {r.scene} | {r.row} | {f(m.get('psnr'), '.2f')} | {f(m.get('ssim'), '.4f')} | "
                     f"{f(m.get('lpips_vgg'), '.4f')} | {f(m.get('lpips_alex'), '.4f')} |")  # fmt: skip
    return "\n".join(lines)
