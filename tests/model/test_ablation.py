"""The ablation rows as config switches, their errors and their table (the fits themselves: tests/model/test_fit.py
scores a finished run through :func:`run_ablation`)."""

from __future__ import annotations

from pathlib import Path

import pytest

from causalgs.errors import CausalGSError
from causalgs.model.ablation import ABLATIONS, AblationResult, ablation_config, ablation_table, run_ablation


def test_rows_switch_one_part_each():
    full = ablation_config("quick", ABLATIONS["full"])
    assert full.fields.materials == "field" and full.fields.patterns == 16
    assert full.fields.velocity == "basis"
    assert ablation_config("quick", ABLATIONS["VFD off"]).fields.velocity == "mlp"
    assert ablation_config("quick", ABLATIONS["IPI off"]).fields.materials == "global"
    assert ablation_config("quick", ABLATIONS["K=4"]).fields.patterns == 4
    assert ablation_config("quick", ABLATIONS["K=32"]).fields.patterns == 32
    assert ABLATIONS["no simulator"].run == "full" and ABLATIONS["no simulator"].dynamics == "kinematic-only"
    assert ablation_config("full", ABLATIONS["K=4"]).kinematic.iterations == full.kinematic.iterations * 5 // 2


def test_unknown_rows_and_scenes_are_one_line_errors(tmp_path):
    with pytest.raises(CausalGSError, match="unknown ablation row"):
        run_ablation(tmp_path, tmp_path / "out", ["jelly"], ["VFD on"])
    with pytest.raises(CausalGSError, match="no such scene folder"):
        run_ablation(tmp_path, tmp_path / "out", ["jelly"], ["full"])


def test_table_has_a_line_per_scene_and_row():
    rows = [AblationResult("jelly", "full", Path("r"), {"psnr": 25.5, "ssim": 0.91, "lpips_vgg": 0.2,
                                                         "lpips_alex": 0.1}),
            AblationResult("jelly", "K=4", Path("r"), {})]  # fmt: skip
    text = ablation_table(rows)
    assert "| jelly | full | 25.50 | 0.9100 | 0.2000 | 0.1000 |" in text
    assert "| jelly | K=4 | n/a | n/a | n/a | n/a |" in text
