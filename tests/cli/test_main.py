from __future__ import annotations

from click.testing import CliRunner

from cli.main import cli

COMMANDS = ("synth", "fit", "predict", "eval", "render", "cluster", "discover", "discover-table", "bench")


def test_help_lists_every_command():
    result = CliRunner().invoke(cli, ["--help"])
    assert result.exit_code == 0
    for name in (*COMMANDS, "info"):
        assert f"\n  {name} " in result.output, name


def test_shared_options_mean_the_same(tmp_path):
    result = CliRunner().invoke(cli, ["synth", "spin", "--help"])
    assert "--out" in result.output and "--seed" in result.output
    bad = CliRunner().invoke(cli, ["synth", "spin", "--out", str(tmp_path / "d"), "--background", "2,0,0"])
    assert bad.exit_code != 0 and "Error:" in bad.output and "Traceback" not in bad.output


def test_version():
    result = CliRunner().invoke(cli, ["--version"])
    assert result.exit_code == 0 and "causalgs" in result.output
