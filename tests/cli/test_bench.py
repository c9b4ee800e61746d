"""``causalgs bench sim`` prints parseable records with the figures it promises (slow: compiles the float32 MPM)."""

from __future__ import annotations

import json

import pytest
from click.testing import CliRunner

from cli.main import cli


@pytest.mark.slow
def test_bench_sim_json(ti32):
    args = ["bench", "sim", "--counts", "1000", "--grids", "16", "--repeats", "1", "--segment", "4", "--no-compile"]
    result = CliRunner().invoke(cli, [*args, "--json"])
    assert result.exit_code == 0, result.output
    (rec,) = [json.loads(line) for line in result.output.splitlines() if line.startswith("{")]
    assert rec["bench"] == "sim" and rec["particles"] == 1000 and rec["grid"] == 16
    assert rec["forward_ms_per_substep"] > 0 and rec["forward_backward_ms_per_substep"] > rec["forward_ms_per_substep"]
    assert rec["memory_full_tape_mb"] > rec["memory_checkpointed_mb"] > 0
    assert rec["forward_phased_ms_per_substep"] > 0
    assert rec["fused_speedup"] == pytest.approx(rec["forward_phased_ms_per_substep"] / rec["forward_ms_per_substep"],
                                                 rel=0.05)  # fmt: skip


def test_bench_sim_help():
    result = CliRunner().invoke(cli, ["bench", "sim", "--help"])
    assert result.exit_code == 0
    assert "checkpoints" in result.output and "--no-compile" in result.output


def test_bench_discover_json(ti32):
    """One record per grid, its rollout timed and its substeps counted (6 frames on a coarse grid)."""
    args = ["bench", "discover", "--grids", "12", "--repeats", "1", "--frames", "6"]
    result = CliRunner().invoke(cli, args)
    assert result.exit_code == 0, result.output
    (rec,) = [json.loads(line) for line in result.output.splitlines() if line.startswith("{")]
    assert rec["bench"] == "discover" and rec["grid"] == 12 and rec["frames"] == 6 and rec["points"] > 10
    assert rec["substeps"] >= 5 and rec["rollout_ms"] > 0
    assert rec["ms_per_substep"] == pytest.approx(rec["rollout_ms"] / rec["substeps"], rel=1e-2)
