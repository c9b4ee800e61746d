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


def test_sigterm_ends_a_command_as_an_exit_does_so_exit_handlers_run():
    """SIGTERM becomes an exit with status 143: what runs at exit (Taichi writing its offline cache of compiled
    kernels) still runs, where the default action would kill the process outright. A handler installed before is
    left alone."""
    import signal
    import subprocess
    import sys

    code = ("import atexit, os, signal, time\n"
            "from cli.main import stop_cleanly_on_sigterm\n"
            "stop_cleanly_on_sigterm()\n"
            "atexit.register(lambda: print('exit handlers ran', flush=True))\n"
            "os.kill(os.getpid(), signal.SIGTERM)\n"
            "time.sleep(30)\n"
            "print('not stopped')\n")  # fmt: skip
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert r.returncode == 128 + signal.SIGTERM, (r.returncode, r.stderr)
    assert r.stdout.strip() == "exit handlers ran" and r.stderr.strip() == "Terminated.", (r.stdout, r.stderr)

    from cli.main import stop_cleanly_on_sigterm

    def mine(signum, frame):
        pass

    before = signal.signal(signal.SIGTERM, mine)
    try:
        stop_cleanly_on_sigterm()
        assert signal.getsignal(signal.SIGTERM) is mine
    finally:
        signal.signal(signal.SIGTERM, before)
