from __future__ import annotations

import pytest
from click.testing import CliRunner

from cli.main import _PLANNED, cli

COMMANDS = ("synth", "fit", "predict", "eval", "render", "cluster", "discover", "bench")


def test_help_lists_every_command():
    result = CliRunner().invoke(cli, ["--help"])
    assert result.exit_code == 0
    for name in (*COMMANDS, "info"):
        assert f"\n  {name} " in result.output, name


@pytest.mark.parametrize("name", sorted(_PLANNED))
def test_planned_commands_say_so_and_fail(name):
    result = CliRunner().invoke(cli, [name, "some/run", "--frames", "22"])
    assert result.exit_code == 2
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("Error:") and "not built yet" in lines[0]
    assert "Traceback" not in result.output


@pytest.mark.parametrize("name", sorted(_PLANNED))
def test_planned_commands_have_help(name):
    result = CliRunner().invoke(cli, [name, "--help"])
    assert result.exit_code == 0 and "Not built yet" in " ".join(result.output.split())


def test_shared_options_mean_the_same(tmp_path):
    result = CliRunner().invoke(cli, ["synth", "spin", "--help"])
    assert "--out" in result.output and "--seed" in result.output
    bad = CliRunner().invoke(cli, ["synth", "spin", "--out", str(tmp_path / "d"), "--background", "2,0,0"])
    assert bad.exit_code != 0 and "Error:" in bad.output and "Traceback" not in bad.output


def test_version():
    result = CliRunner().invoke(cli, ["--version"])
    assert result.exit_code == 0 and "causalgs" in result.output
