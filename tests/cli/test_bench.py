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


def test_the_benchmarks_landing_is_the_hidden_effect_tables():
    from causalgs.bench import LANDING_EFFECTS
    from causalgs.discover.table import BASE

    assert LANDING_EFFECTS == BASE


def test_bench_jobs_piece_times_its_units_where_it_runs(ti32):
    """A piece of `bench jobs` here: its units timed, and the CPUs and Taichi threads it ran on (the discover
    benchmark's landing, so its kernels are those already built)."""
    import os

    from causalgs import _ti
    from causalgs.bench import jobs_piece

    rec = jobs_piece("piece", 3, "rollout", 12, 2, 6, 24.0)
    assert rec["case"] == "piece" and rec["seed"] == 3 and rec["piece_s"] > 0 and rec["setup_s"] > 0
    assert rec["threads"] == _ti.runtime().threads and rec["pid"] == os.getpid()
    assert rec["cpus"] == sorted(os.sched_getaffinity(0))
    again = jobs_piece("piece", 4, "rollout", 12, 2, 6, 24.0)  # built once per process
    assert again["setup_s"] < rec["setup_s"]


def test_bench_jobs_refuses_one_job():
    result = CliRunner().invoke(cli, ["bench", "jobs", "--jobs", "1"])
    assert result.exit_code == 2 and "--jobs" in result.output


@pytest.mark.slow
def test_bench_jobs_runs_pieces_both_ways():
    """Pieces one after the other here and two at once in pinned processes, as the table runs rows: the record
    says each way's median piece and the ratios, and the pieces side by side ran on CPUs of their own."""
    args = ["bench", "jobs", "--pieces", "2", "--units", "1", "--cycles", "1", "--frames", "6", "--grid", "10"]
    result = CliRunner().invoke(cli, args)
    assert result.exit_code == 0, result.output
    (rec,) = [json.loads(line) for line in result.output.splitlines() if line.startswith("{")]
    assert rec["bench"] == "jobs" and rec["jobs"] == 2 and rec["pieces"] == 2
    assert rec["serial_piece_s"] > 0 and rec["jobs_piece_s"] > 0 and rec["serial_wall_s"] > 0
    assert rec["throughput_ratio"] == pytest.approx(2 * rec["serial_piece_s"] / rec["jobs_piece_s"], rel=0.02)
    assert rec["jobs_threads"] == 1 or len(rec["cpus"] or []) < 2
    if rec["cpus"] and len(rec["cpus"]) >= 2:
        assert len(rec["jobs_cpus"]) == 2 and all(len(c) == 1 for c in rec["jobs_cpus"])


def test_bench_fit_tables_show_metrics_recovery_and_frame():
    from cli.bench import fit_table

    row = {"scene": "bounce", "fit_seconds": 600.0,
           "interpolation": {"mpm": {"psnr": 33.1, "psnr_pooled": 32.0, "ssim": 0.98, "lpips_vgg": 0.03,
                                     "lpips_vgg_unscaled": 0.02}},
           "extrapolation": {"mpm": {"psnr": 30.5, "psnr_pooled": 29.9, "ssim": 0.97, "lpips_alex": 0.05,
                                     "lpips_vgg": 0.1, "lpips_vgg_unscaled": 0.07},
                             "frozen": {"psnr": 25.0, "ssim": 0.9}},
           "recovery": {"objects": [{"name": "ball", "velocity_true_mean": [1.0, 0.0, 2.0],
                                     "velocity_error_relative": 0.12, "omega_true": [0.0, 4.0, 0.0],
                                     "omega_model": [0.1, 3.5, 0.0]}]},
           "frame": {"up_error_deg": 0.42, "gravity_ratio": 1.031}}  # fmt: skip
    text = fit_table([row, {"scene": "spin", "fit_seconds": None}])
    freegave, nvfi = text.split("**NVFi's convention**")
    assert "| bounce | mpm | 33.10 | 0.9800 | 0.0200 | 30.50 | 0.9700 | 0.0700 | 600 |" in freegave
    assert "| bounce | frozen | n/a | n/a | n/a | 25.00 | 0.9000 | n/a | 600 |" in freegave
    assert "| bounce | mpm | 32.00 | 0.9800 | 0.0300 | 29.90 | 0.9700 | 0.1000 | 600 |" in nvfi
    ball = "| bounce | ball | (1.00, 0.00, 2.00) | 12% | (0.00, 4.00, 0.00) | (0.10, 3.50, 0.00) | 0.42° | 1.031 |"
    assert ball in text
    assert "| spin | n/a | n/a | n/a | n/a | n/a | n/a | n/a |" in text
