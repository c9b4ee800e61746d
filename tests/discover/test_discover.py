"""The discovery loop end to end on measurements from closed-form laws (never from the simulator being calibrated):
a throw under gravity with linear drag, which a gravity-only model must discover and name; the same throw without
drag, where it must find nothing; the report, the plots and the command line."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest
from click.testing import CliRunner

from causalgs.discover.observation import Observation, synthesize
from causalgs.discover.search import DiscoverConfig
from cli.main import cli

G = np.array([0.0, 0.0, -9.8])
C_TRUE = 1.5
NOISE = 5e-4


def _cube(n: int = 3, side: float = 0.12, centre=(-0.15, 0.0, 0.45)) -> np.ndarray:
    s = (np.arange(n) + 0.5) / n * side - side / 2
    return np.stack(np.meshgrid(s, s, s, indexing="ij"), -1).reshape(-1, 3) + np.asarray(centre)


def _throw(c: float, frames: int = 12, fps: float = 30.0, v0=(0.6, 0.0, 1.4), seed: int = 0,
           b=(0.0, 0.0, 0.0)) -> Observation:  # fmt: skip
    """x(t) = x0 + v∞ t + (v0 − v∞)(1 − e^{−ct})/c with v∞ = (g + b)/c (uniform acceleration when c = 0), plus
    noise; ``b``: a uniform force per unit mass besides gravity."""
    x0 = _cube()
    t = np.arange(frames) / fps
    v0, acc = np.asarray(v0), G + np.asarray(b)
    if c > 0:
        vinf = acc / c
        disp = vinf * t[:, None] + (v0 - vinf) * (1 - np.exp(-c * t))[:, None] / c
    else:
        disp = v0 * t[:, None] + 0.5 * acc * t[:, None] ** 2
    x = x0[None] + disp[:, None, :]
    x = x + NOISE * np.random.default_rng(seed).standard_normal(x.shape)
    vol = np.full(len(x0), 0.12**3 / len(x0))
    return Observation(times=t, x=x, vol=vol, body=np.zeros(len(x0)), observed=9, lo=(-0.5, -0.5, 0.0),
                       hi=(0.5, 0.5, 1.0), ground=None, noise=NOISE, names=["cube"])  # fmt: skip


CFG = DiscoverConfig(res=16, starts=(3e4,), iterations=12, finalists=2, max_effects=1)
CANDIDATES = ("linear_drag", "quadratic_drag", "force")


@pytest.fixture
def ti32_runtime():
    from causalgs import _ti

    _ti.init("cpu", "float32")


def test_a_hidden_drag_is_found_named_and_repaired(ti32_runtime, tmp_path):
    from causalgs.discover.run import run_discovery

    obs = _throw(C_TRUE)
    lines = []
    rep = run_discovery("throw.npz", tmp_path, spec="gravity;walls", learn=(), candidates=CANDIDATES, config=CFG,
                        obs=obs, log=lines.append)  # fmt: skip
    assert rep["verdict"] == "discovered", rep["rounds"]
    gate = [ln for ln in lines if ln.startswith("round 1: passed the gate: ")]  # said as it happens
    assert len(gate) == 1 and "linear_drag" in gate[0], lines
    found = rep["discovered"][0]
    assert found["effect"] == "linear_drag"
    c = found["params"]["linear_drag.c"]
    assert abs(c - C_TRUE) < 0.1 * C_TRUE, c
    lo, hi = found["interval"]["linear_drag.c"]
    assert lo < c < hi and hi - lo < 0.5 * C_TRUE
    assert found["law"].startswith("linear drag: a = −c·v, c = ")
    # the interval spans the profile likelihood, closed on both sides, around the value
    plo, phi = found["interval_sources"]["profile"]["linear_drag.c"]
    assert lo <= plo < c < phi <= hi and found["interval_sources"]["profile_closed"]["linear_drag.c"] == [True, True]
    assert rep["error_after"]["future_rms_m"] < 0.5 * rep["error_before"]["future_rms_m"]
    assert NOISE <= rep["floor_rms_m"] <= rep["floor_rms_base_m"]  # the repaired model's floor, when lower
    assert rep["disagreement"]["first_departure"] is not None
    # The signature that names it: the residual acceleration is explained by −v better than by a constant.
    sig = rep["disagreement"]["signatures"]
    assert sig["v"] > 0.5
    for name in ("report.json", "report.md", "error.png", "residuals.png", "paths.png", "discover.json"):
        assert (tmp_path / name).is_file(), name
    md = (tmp_path / "report.md").read_text()
    assert "linear drag" in md and "## Errors (RMS per coordinate" in md and "Round 1" in md
    assert "profile likelihood (every other parameter refitted with it held" in md
    # the errors are what the report's heading says: RMS per coordinate over every point and held-out frame
    z = np.load(tmp_path / "trajectories.npz")
    for k in ("before", "after"):
        held = slice(int(z["observed"]), None)
        per_coordinate = np.sqrt(((z[k][held] - z["x"][held]) ** 2).mean())
        assert per_coordinate == pytest.approx(rep[f"error_{k}"]["future_rms_m"], rel=1e-6)
    back = json.loads((tmp_path / "report.json").read_text())
    assert back["verdict"] == "discovered" and back["discovered"][0]["effect"] == "linear_drag"


def test_nothing_is_found_when_nothing_is_missing(ti32_runtime, tmp_path):
    from causalgs.discover.run import run_discovery

    lines = []
    rep = run_discovery("throw.npz", tmp_path, spec="gravity;walls", learn=(), candidates=CANDIDATES, config=CFG,
                        obs=_throw(0.0), log=lines.append)  # fmt: skip
    assert rep["verdict"] == "no missing effect", rep["rounds"]
    assert "round 1: nothing passed the gate" in lines, lines
    assert rep["discovered"] == [] and rep["ambiguous"] == []
    assert rep["error_before"]["fit_rms_m"] < 2 * math.sqrt(2) * NOISE
    assert "No missing effect" in (tmp_path / "report.md").read_text()


def test_two_effects_missing_at_once_are_found_together(ti32_runtime, tmp_path):
    """A throw with a sideways push (b along y, where the throw has no speed) and a linear drag: a force alone
    leaves the drag unexplained and the drag alone the push, so neither passes the gate by itself. The force
    explains part of the discrepancy (every check of the evidence but the floor's), the drag is refitted beside
    it, and the pair passes: both named, each with its parameter, the held-out error down to the noise."""
    import dataclasses

    from causalgs.discover.run import run_discovery

    b_true = 1.5
    cfg = dataclasses.replace(CFG, max_effects=2)
    rep = run_discovery("throw.npz", tmp_path, spec="gravity;walls", learn=(), candidates=("linear_drag", "force"),
                        config=cfg, obs=_throw(C_TRUE, b=(0.0, b_true, 0.0)))  # fmt: skip
    rnd = rep["rounds"][0]
    assert not any(r["passed"] for r in rnd["refits"]), rnd["refits"]  # neither passes alone
    assert rnd["joint"]["lead"] == "force" and [r["effect"] for r in rnd["joint"]["refits"]] == ["linear_drag"]
    assert rep["verdict"] == "discovered", rnd
    found = {d["effect"]: d for d in rep["discovered"]}
    assert sorted(found) == ["force", "linear_drag"]
    assert found["force"]["fitted_with"] == "linear_drag" and found["linear_drag"]["fitted_with"] == "force"
    assert found["linear_drag"]["evidence"]["against"] == "force" and found["force"]["evidence"]["against"] == "base"
    c, by = found["linear_drag"]["params"]["linear_drag.c"], found["force"]["params"]["force.b[1]"]
    assert abs(c - C_TRUE) < 0.1 * C_TRUE and abs(by - b_true) < 0.1 * b_true, (c, by)
    for d in found.values():  # each interval holds its value and each parameter is significant
        for p, (lo, hi) in d["interval"].items():
            assert lo <= d["params"][p] <= hi, (p, lo, hi)
        assert all(z >= 3 for z in d["evidence"]["z"].values()), d["evidence"]
    assert rep["error_after"]["future_rms_m"] < 0.1 * rep["error_before"]["future_rms_m"]
    assert len(rep["rounds"]) == 1  # the pair used both effects the run allows
    md = (tmp_path / "report.md").read_text()
    assert "found together with `linear_drag`, fitted jointly" in md and "| with force |" in md


def test_an_effect_found_earlier_is_quoted_as_the_repaired_model_holds_it(ti32_runtime):
    """A later round refits the earlier effects' parameters with its own: the report quotes them at the repaired
    model (with an interval there), keeps what their round found, and leaves the latest round's entry as it is."""
    from causalgs.discover.calibrate import Fit
    from causalgs.discover.model import PhysicsModel
    from causalgs.discover.search import _state, requote

    obs = _throw(C_TRUE, b=(0.0, 1.5, 0.0))
    model = PhysicsModel(obs, "gravity;walls;linear_drag:c=1.4;force:b=0.0,1.5,0.0",
                         ("linear_drag.c", "force.b[0]", "force.b[1]", "force.b[2]"), res=CFG.res)  # fmt: skip
    final = _state(model, Fit(model.initial(E=3e4), 0.0, 0, 3e4))
    spec = model.spec_at(final.fit.theta)
    old = {"effect": "linear_drag", "spec": "gravity;walls;linear_drag:c=2.9", "params": {"linear_drag.c": 2.9},
           "interval": {"linear_drag.c": [2.5, 3.3]}, "law": "linear drag: a = −c·v, c = 2.9 [2.5, 3.3]",
           "interval_sources": {"shape_resolution_m": 0.0}, "at_bounds": {}}  # fmt: skip
    new = {"effect": "force", "spec": spec, "params": {"force.b[1]": 1.5}, "law": "kept"}
    found = [old, dict(new)]
    requote(found, final, obs, CFG, NOISE, NOISE)
    c = found[0]["params"]["linear_drag.c"]
    assert c == pytest.approx(model.values(final.fit.theta)["linear_drag.c"]) and abs(c - 1.4) < 1e-4
    lo, hi = found[0]["interval"]["linear_drag.c"]
    assert lo < c < hi and [lo, hi] != [2.5, 3.3]  # the repaired model's interval, not the round's
    assert found[0]["found_as"]["params"] == {"linear_drag.c": 2.9} and found[0]["refitted_with"] == ["force"]
    assert found[0]["spec"] == spec and found[0]["law"].startswith("linear drag: a = −c·v, c = 1.4")
    assert found[1] == new  # the latest round's own entry is untouched


def test_command_line_writes_the_report_and_refuses_bad_input(ti32_runtime, tmp_path, monkeypatch):
    obs = _throw(C_TRUE)
    obs.save(tmp_path / "obs.npz")
    out = tmp_path / "d"
    args = ["discover", str(tmp_path / "obs.npz"), "--out", str(out), "--effects", "gravity;walls", "--learn", "",
            "--candidates", "linear_drag", "--res", "16", "--starts", "3e4", "--iterations", "12",
            "--max-effects", "1", "--json"]  # fmt: skip
    r = CliRunner().invoke(cli, args)
    assert r.exit_code == 0, r.output
    rep = json.loads(r.output)
    assert rep["verdict"] == "discovered" and rep["discovered"][0]["effect"] == "linear_drag"
    assert (out / "report.md").is_file() and (out / "error.png").stat().st_size > 1000
    saved = json.loads((out / "discover.json").read_text())
    assert saved["spec"] == "gravity;walls" and saved["candidates"] == ["linear_drag"]
    # Every calibration was kept as it finished; a second run into the same folder must say --resume, and resumed
    # it recomputes none of them and reaches the same report.
    done = json.loads((out / "progress.json").read_text())["entries"]
    assert "base/3e+04" in done and "round 1/linear_drag/start 1" in done and rep["calibrations_resumed"] == 0
    r = CliRunner().invoke(cli, args[:-1])
    assert r.exit_code == 1 and "already holds a discovery run: use --resume" in r.output, r.output
    # The screen of each round was kept too: resumed, none runs again, and the rounds read as they did.
    screens = json.loads((out / "progress.json").read_text())["screens"]
    assert list(screens) == [f"round {i + 1}/screen" for i in range(len(rep["rounds"]))] and rep["screens_resumed"] == 0
    assert screens["round 1/screen"]["keys"] == ["linear_drag"]

    def no_screen(*a, **k):
        raise AssertionError("a kept screen was run again")

    with monkeypatch.context() as m:
        m.setattr("causalgs.discover.search.screen", no_screen)
        r = CliRunner().invoke(cli, [*args, "--resume"])
    assert r.exit_code == 0, r.output
    again = json.loads(r.output)
    assert again["calibrations_resumed"] == len(done) and "calibrations_restarted" not in again  # the same starts
    assert again["screens_resumed"] == len(screens) and again["rounds"] == rep["rounds"]
    assert again["discovered"][0]["params"] == rep["discovered"][0]["params"]
    # Options that decide between calibrations (how many effects at most) reuse them; options that change a
    # calibration's result (its iteration budget) are not mixed in.
    r = CliRunner().invoke(cli, [*args[:-3], "--max-effects", "2", "--resume", "--json"])
    assert r.exit_code == 0, r.output
    assert json.loads(r.output)["calibrations_resumed"] >= len(done)
    r = CliRunner().invoke(cli, [*args[:-5], "--iterations", "13", "--max-effects", "1", "--resume"])
    assert r.exit_code == 1 and "made with other options" in r.output, r.output
    r = CliRunner().invoke(cli, [*args[:-1], "--weigh", "--resume"])  # the weights change what is calibrated
    assert r.exit_code == 1 and "made with other options" in r.output, r.output
    bad = [
        (["discover", str(tmp_path / "missing.npz"), "--out", str(out)], "no such observation file"),
        (["discover", str(tmp_path), "--out", str(out)], "not a fitted run"),
        (["discover", str(tmp_path / "obs.npz"), "--out", str(out), "--candidates", "magic"], "unknown candidate"),
        (["discover", str(tmp_path / "obs.npz"), "--out", str(out), "--effects", "gravity;warp"], "unknown effect"),
        (["discover", str(tmp_path / "obs.npz"), "--out", str(out), "--starts", "1e4,-3"], "--starts"),
        (["discover", str(tmp_path / "obs.npz"), "--out", str(out), "--res", "3"], "--res 3"),
        (["discover-table", "--out", str(out), "--only", "nonsense"], "unknown case"),
        (["discover-table", "--out", str(out), "--level", "video", "--rigid-tracks"], "is for --level trajectory"),
        (["discover-table", "--out", str(out), "--lens", "affine"], "is for --level video"),
        (["discover-table", "--out", str(out), "--weigh"], "--weigh is for --level video"),
        (["discover-table", "--out", str(out), "--stretch"], "--stretch is for --level video"),
    ]
    for argv, msg in bad:
        r = CliRunner().invoke(cli, argv)
        lines = r.output.strip().splitlines()
        assert r.exit_code != 0 and len(lines) == 1 and msg in lines[0], (argv, r.output)
        assert "Traceback" not in r.output


def test_discover_passes_split_and_lens_to_the_measurement(tmp_path, monkeypatch):
    """``--split/--no-split``, ``--lens`` and ``--stretch`` reach the measurement of a run (load_source, through
    run_discovery); ``--profile/--no-profile`` its config."""
    import causalgs.discover.run as R

    seen = []

    def fake(source, out, **kw):
        seen.append(kw)
        return _fake_report(None)

    monkeypatch.setattr(R, "run_discovery", fake)
    # the stretching tracks where the bodies deform are on unless --no-stretch
    for extra, split, lens, stretch in (([], True, "auto", True), (["--no-split", "--lens", "affine"], False, "affine",
                                                                   True), (["--no-stretch"], True, "auto", False)):
        r = CliRunner().invoke(cli, ["discover", str(tmp_path / "obs.npz"), "--out", str(tmp_path / "d"), *extra])
        assert r.exit_code == 0, r.output
        assert seen[-1]["split"] is split and seen[-1]["lens"] == lens and seen[-1]["stretch"] is stretch
    # the profile likelihood of the named parameters is on unless --no-profile
    assert seen[-1]["config"].profile is True
    r = CliRunner().invoke(cli, ["discover", str(tmp_path / "obs.npz"), "--out", str(tmp_path / "d"), "--no-profile"])
    assert r.exit_code == 0, r.output
    assert seen[-1]["config"].profile is False


def _fake_report(effect: str | None, value: float = 0.0, verdict: str | None = None) -> dict:
    found = [{"effect": effect, "params": {"linear_drag.c": value},
              "interval": {"linear_drag.c": [value - 0.02, value + 0.02]}}] if effect else []  # fmt: skip
    return {"verdict": verdict or ("discovered" if effect else "no missing effect"), "discovered": found,
            "ambiguous": [], "error_before": {"future_rms_m": 0.01, "fit_rms_m": 0.004},
            "error_after": {"future_rms_m": 0.004 if effect else 0.01, "fit_rms_m": 0.003}, "seconds": 1.0,
            "noise": 0.002, "floor_rms_m": 0.003, "rounds": [], "final_spec": "gravity;walls",
            "disagreement": {"floor": 0.003, "first_departure": None, "by_contact": {}, "signatures": {},
                             "residual_force_gain": 0.0}}  # fmt: skip


def test_table_rows_score_what_was_found_against_what_was_hidden():
    import causalgs.discover.table as T
    from causalgs.discover.table import BY_NAME, summary
    from causalgs.discover.table import score as score_row

    drag = BY_NAME["linear_drag"]
    row = score_row(drag, _fake_report("linear_drag", 0.63))
    assert row["first_ok"] and row["in_set"] and math.isclose(row["param_error"], 0.05)
    assert not row["interval_covers"]  # 0.63 ± 0.02 misses the true 0.6
    assert score_row(drag, _fake_report("linear_drag", 0.61))["interval_covers"]
    assert math.isclose(row["future_drop"], 0.6)
    wrong = score_row(drag, _fake_report("quadratic_drag"))
    assert not wrong["first_ok"] and wrong["param_error"] is None
    control = BY_NAME["control: clean"]
    assert score_row(control, _fake_report(None))["first_ok"]
    assert not score_row(control, _fake_report("linear_drag", 0.1))["first_ok"]
    outside = BY_NAME["outside: attractor"]
    assert score_row(outside, _fake_report(None, verdict="unexplained discrepancy"))["first_ok"]
    rows = [{**row, "seed": 0}, {**wrong, "seed": 1}, {**score_row(control, _fake_report(None)), "seed": 0}]
    s = summary(rows)
    assert s["hidden_first"] == 0.5 and s["controls_no_effect"] == 1.0 and s["param_within_10pct"] == 1.0
    assert s["interval_covers_truth"] == 0.0
    assert row["future_truth_before_m"] is None and s["future_drop_vs_truth_ge_50pct"] is None  # no truth given
    truth = {"future_rms_before_m": 0.004, "future_rms_after_m": 0.0008}
    scored = score_row(drag, {**_fake_report("linear_drag", 0.63), "truth_error": truth})
    assert math.isclose(scored["future_truth_drop"], 0.8)
    assert summary([{**scored, "seed": 0}])["future_drop_vs_truth_ge_50pct"] == 1.0
    assert "| 4.0 → 0.8 mm (−80%) |" in T.markdown([{**scored, "seed": 0}])
    assert [T.change(d) for d in (0.8, -0.12, 0.001, -0.004)] == ["−80%", "+12%", "±0%", "±0%"]


def test_a_row_with_two_hidden_effects_needs_both_named_each_with_its_parameter():
    from causalgs.discover.table import BASE, BY_NAME, Case, summary
    from causalgs.discover.table import score as score_row

    case = Case("force+linear_drag", "hidden", BASE + ";force:b=0.8,0,0;linear_drag:c=0.6", BASE, expect="force",
                also=("linear_drag",), truth={"force.b[0]": 0.8, "linear_drag.c": 0.6})  # fmt: skip
    force = {"effect": "force", "params": {"force.b[0]": 0.82}, "interval": {"force.b[0]": [0.75, 0.9]}}
    drag = _fake_report("linear_drag", 0.57)["discovered"][0]  # interval 0.55..0.59 misses 0.6
    both = score_row(case, {**_fake_report("linear_drag", 0.57), "discovered": [drag, force]})
    assert both["expected"] == "force+linear_drag" and both["first_ok"] and both["in_set"]
    assert math.isclose(both["param_error"], 0.05) and both["interval_covers"] is False  # the drag's 5%, its miss
    one = score_row(case, {**_fake_report("linear_drag", 0.6), "discovered": [force]})
    assert not one["first_ok"] and not one["in_set"] and one["param_error"] is None  # the drag not named
    wrong = score_row(case, {**_fake_report("quadratic_drag", 0.6), "discovered": [
        _fake_report("quadratic_drag", 0.6)["discovered"][0], force, drag]})  # fmt: skip
    assert not wrong["first_ok"] and wrong["in_set"] and wrong["param_error"] is None  # first named wrong
    s = summary([{**both, "seed": 0}, {**one, "seed": 1}])
    assert s["hidden_first"] == 0.5 and s["hidden_in_set"] == 0.5 and s["param_within_10pct"] == 1.0
    # the table's own such case: a zero component of the force is scored against the force's size, not η's
    table_case = BY_NAME["force + damping"]
    f = {"effect": "force", "params": {"force.b[0]": 0.8, "force.b[1]": 0.04, "force.b[2]": 0.0},
         "interval": {f"force.b[{i}]": [-1.0, 1.0] for i in range(3)}}  # fmt: skip
    d = {"effect": "damping", "params": {"damping.eta": 200.0}, "interval": {"damping.eta": [150.0, 250.0]}}
    row = score_row(table_case, {**_fake_report("force"), "discovered": [d, f]})
    assert row["first_ok"] and math.isclose(row["param_error"], 0.05) and row["interval_covers"]
    # an ambiguity set of pairs fitted jointly: each pair's effects count by name, the top pair's lead first
    amb = [{"effect": "damping+force", "effects": ["damping", "force"]},
           {"effect": "damping+linear_drag", "effects": ["damping", "linear_drag"]}]  # fmt: skip
    row = score_row(table_case, {**_fake_report(None, verdict="ambiguous"), "ambiguous": amb})
    assert row["found"] == ["damping", "force", "damping", "linear_drag"] and row["first_ok"] and row["in_set"]


def test_table_resumes_and_records_failures(tmp_path, monkeypatch):
    import causalgs.discover.table as T
    from causalgs.errors import CausalGSError

    calls = []

    def fake_discover(obs, spec, learn, config=None, log=None, start=None, journal=None):
        calls.append(spec)
        assert journal.path.name == "progress.json" and journal.path.parent.parent == tmp_path
        if "attractor" in obs.truth["scene_spec"]:
            raise CausalGSError("the simulation blew up at frame 3")
        return _fake_report(None), {"before": obs.x[1:], "after": obs.x[1:]}

    def fake_observe(case, seed, cfg):
        obs = _throw(0.0)
        obs.truth = {"scene_spec": case.scene, "bodies": [{"E": 3e4, "velocity": [0.6, 0, 1.4], "omega": [0, 0, 0]}]}
        obs.clean = obs.x + 0.001  # the stand-in predicts the measurement: 1 mm off the truth, in displacement none
        return obs

    monkeypatch.setattr(T, "discover", fake_discover)
    monkeypatch.setattr(T, "observe", fake_observe)
    cfg = T.TableConfig(only=("control", "outside"))
    rows = T.run_table(tmp_path, cfg)
    assert len(rows) == 6 and len(calls) == 6
    failed = [r for r in rows if r["verdict"].startswith("failed")]
    assert len(failed) == 1 and "blew up" in failed[0]["verdict"]
    assert (tmp_path / "table.md").is_file() and (tmp_path / "control-clean-s0" / "report.md").is_file()
    with np.load(tmp_path / "control-clean-s0" / "trajectories.npz") as z:  # frame 0 + the simulated frames
        assert z["before"].shape == z["x"].shape == z["after"].shape and int(z["observed"]) == _throw(0.0).observed
        assert np.array_equal(z["before"], z["x"])
    clean = next(r for r in rows if r["case"] == "control: clean")
    assert clean["future_truth_before_m"] < 1e-15 and clean["future_truth_after_m"] < 1e-15
    again = T.run_table(tmp_path, cfg)  # every row is there: nothing runs again
    assert len(again) == 6 and len(calls) == 6
    retried = T.run_table(tmp_path, cfg, retry_failed=True)  # but the failed one when told to retry it
    assert len(retried) == 6 and len(calls) == 7
    assert [r["case"] for r in retried if r["verdict"].startswith("failed")] == [failed[0]["case"]]
    assert sorted((r["case"], r["seed"]) for r in retried) == sorted((r["case"], r["seed"]) for r in again)
    saved = json.loads((tmp_path / "table.json").read_text())
    assert saved["summary"]["controls_no_effect"] == 1.0 and saved["summary"]["runs"] == 6
    again = T.rescore(tmp_path)  # scored anew from the saved reports, nothing run
    assert len(again) == 6 and len(calls) == 7
    assert json.loads((tmp_path / "table.json").read_text())["rows"] == saved["rows"]
    r = CliRunner().invoke(cli, ["discover-table", "--out", str(tmp_path), "--rescore"])  # the same, from the CLI
    assert r.exit_code == 0, r.output
    assert "6 rows scored again" in r.output and json.loads(r.output.splitlines()[0])["runs"] == 6
    assert json.loads((tmp_path / "table.json").read_text())["rows"] == saved["rows"] and len(calls) == 7
    r = CliRunner().invoke(cli, ["discover-table", "--out", str(tmp_path / "none"), "--rescore"])
    assert r.exit_code != 0 and "no table in" in r.output and "Traceback" not in r.output
    (tmp_path / "v").mkdir()
    (tmp_path / "v" / "table.json").write_text(json.dumps({**saved, "level": "video"}))
    r = CliRunner().invoke(cli, ["discover-table", "--out", str(tmp_path / "v"), "--rescore"])
    assert r.exit_code != 0 and "holds a video table" in r.output
    assert saved["level"] == "trajectory"
    with pytest.raises(CausalGSError, match="of the trajectory level, not of the trajectory, rigid tracks level"):
        T.run_table(tmp_path, T.TableConfig(only=("control", "outside"), rigid=True))  # rows of two measurements
    assert len(calls) == 7


def test_predictions_are_scored_against_the_noise_free_truth(tmp_path):
    """A synthetic measurement keeps its positions before the noise (``clean``, saved with it); the tables score the
    predictions' displacements against them, so the noise of the first frame, where every rollout starts, costs
    nothing, and a held-out error can drop below the noise."""
    from causalgs.discover.observation import load_observation, synthesize
    from causalgs.discover.table import truth_error
    from causalgs.errors import CausalGSError

    obs = synthesize("toss", "gravity;ground:mu=0.3;walls", seed=0, points=150, frames=8, fps=24.0, noise=0.002,
                     rest_noise=0.003, reference_res=12)  # fmt: skip
    noise = obs.x - obs.clean
    assert np.std(noise[1:]) == pytest.approx(0.002, rel=0.1)
    assert np.std(noise[0]) == pytest.approx(math.hypot(0.002, 0.003), rel=0.1)
    obs.save(tmp_path / "obs.npz")
    assert np.array_equal(load_observation(tmp_path / "obs.npz").clean, obs.clean)
    k = obs.observed
    exact = obs.clean - obs.clean[:1] + obs.x[:1]  # the truth's motion, started from the measured first frame
    off = exact.copy()
    off[k:] += np.array([0.003, 0.0, 0.0])
    off[k:, :10] += np.array([0.0, 0.0, -0.004])
    e = truth_error(exact, off, obs.clean, k)
    assert max(e["fit_rms_before_m"], e["future_rms_before_m"], e["fit_rms_after_m"]) < 1e-12
    ref = 0.0  # a plain reference: the mean square over every held-out frame, point and coordinate
    for t in range(k, len(obs.times)):
        for p in range(obs.points):
            for c in range(3):
                ref += ((off[t, p, c] - off[0, p, c]) - (obs.clean[t, p, c] - obs.clean[0, p, c])) ** 2
    assert e["future_rms_after_m"] == pytest.approx(math.sqrt(ref / ((len(obs.times) - k) * obs.points * 3)))
    with pytest.raises(CausalGSError, match="'clean' has shape") as bad:
        Observation(times=obs.times, x=obs.x, vol=obs.vol, body=obs.body, observed=k, lo=obs.lo, hi=obs.hi,
                    clean=obs.clean[:, :5])  # fmt: skip
    assert "\n" not in str(bad.value)


def test_the_truths_own_physics_calibrated_from_the_measurement_is_the_floor_a_repair_can_reach(tmp_path):
    """From the clean first frame the truth's physics reproduces the clean motion (a floor of zero); from a noisy
    one it misses the held-out truth by what the rest shape's noise moved, which the table then reports beside the
    repair's error (kept in the case's journal, not computed again on a resumed table)."""
    import causalgs.discover.table as T
    from causalgs.discover.journal import Journal

    spec = "gravity;linear_drag:c=0.6;ground:mu=0.3;walls"
    clean = synthesize("toss", spec, seed=0, points=150, frames=8, fps=24.0, reference_res=12)
    assert T.truth_floor(clean, 12, iterations=2) < 1e-6
    noisy = synthesize("toss", spec, seed=0, points=150, frames=8, fps=24.0, noise=0.002, rest_noise=0.004,
                       reference_res=12)  # fmt: skip
    journal = Journal(tmp_path / "progress.json", "k", resume=True)
    floor = T.truth_floor(noisy, 12, iterations=2, journal=journal)
    assert 1e-4 < floor < 0.02 and "truth floor" in journal.entries
    again = Journal(tmp_path / "progress.json", "k", resume=True)
    assert T.truth_floor(noisy, 12, iterations=2, journal=again) == floor and again.reused == 1
    # no truth, no floor
    assert T.truth_floor(dataclasses.replace(noisy, clean=None), 12) is None
    # the row: the share of the error above the floor the repair removed, and the table's cell
    truth = {"future_rms_before_m": 0.004, "future_rms_after_m": 0.0021, "future_rms_floor_m": 0.0025}
    row = T.score(T.BY_NAME["linear_drag"], {**_fake_report("linear_drag", 0.6), "truth_error": truth})
    assert row["future_truth_drop"] < 0.5 and row["truth_excess_removed"] == 1.0
    assert T.summary([{**row, "seed": 1}])["excess_over_truth_floor_removed_ge_50pct"] == 1.0
    assert "| 4.0 → 2.1 mm (−48%); the truth's physics 2.5 mm |" in T.markdown([{**row, "seed": 1}])


def test_the_repair_is_judged_on_the_error_above_the_noise_floor():
    from causalgs.discover.table import excess_removed

    assert excess_removed(5e-3, 3e-3, 3e-3) == 1.0
    assert excess_removed(5e-3, 4e-3, 3e-3) == pytest.approx(1 - 7 / 16)
    assert excess_removed(5e-3, 6e-3, 3e-3) < 0  # worse than before
    assert excess_removed(3e-3, 3e-3, 3.5e-3) is None  # the base is at the floor already
    assert excess_removed(5e-3, 4e-3, None) is None


def test_reports_hold_only_json_numbers():
    from causalgs.discover.report import finite

    out = finite({"z": math.inf, "v": [1.0, float("nan"), np.float64(2.0)], "a": np.array([np.inf, 3.0]), "s": "x"})
    assert out == {"z": None, "v": [1.0, None, 2.0], "a": [None, 3.0], "s": "x"}
    json.dumps(out, allow_nan=False)


@pytest.mark.slow
def test_table_runs_cases_in_parallel_processes(tmp_path):
    """--jobs 2: two real (tiny) runs, each in its own spawned process with its own Taichi runtime; their rows and
    folders land in one table."""
    import causalgs.discover.table as T

    tiny = DiscoverConfig(res=10, starts=(3e4,), iterations=2, finalists=1, max_effects=1)
    cfg = T.TableConfig(only=("control: clean",), seeds=2, frames=6, res=10, jobs=2, discover=tiny)
    rows = T.run_table(tmp_path, cfg)
    assert sorted(r["seed"] for r in rows) == [0, 1]
    assert all(not r["verdict"].startswith("failed") for r in rows), [r["verdict"] for r in rows]
    assert (tmp_path / "control-clean-s0" / "report.json").is_file()
    assert (tmp_path / "control-clean-s1" / "report.json").is_file()
    assert json.loads((tmp_path / "table.json").read_text())["summary"]["runs"] == 2


def test_the_report_says_how_each_other_passer_was_told_apart():
    from causalgs.discover.report import markdown

    rep = _fake_report("linear_drag", 2.5)
    d = rep["discovered"][0]
    d.update(law="linear drag: a = −c·v, c = 2.5 [2.3, 2.7]",
             evidence={"signature": "v", "signature_share": 0.04, "future_drop": 0.97, "delta_bic": -690.4,
                       "z": {"linear_drag.c": 30.2}},
             runners_up=[{"effect": "force", "passed": True, "future_mse_cm2": 0.278, "delta_bic": -760.3,
                          "future_gap_cm2": [0.06, 0.51], "told_apart_by": "held-out frames"},
                         {"effect": "quadratic_drag", "passed": True, "future_mse_cm2": 0.0381, "delta_bic": -582.4,
                          "future_gap_cm2": [-0.08, 0.02], "told_apart_by": "fit window"},
                         {"effect": "damping", "passed": False, "future_mse_cm2": 0.5, "delta_bic": 3.0}],
             base_before={"body 0.E": 4e5}, base_after={"body 0.E": 2.6e4})  # fmt: skip
    text = markdown(rep)
    # what decided comes first; a signature that hardly shows the effect is said to be so
    assert "evidence: held-out RMS −83%; ΔBIC −690.4; linear_drag.c at 30.2 SE; its signature `v` explains 4%" in text
    assert "(the smoothed accelerations do not show it; the refit does)" in text
    assert "Held-out error change: −" in text and "by contact state" not in text  # no contact states: no line
    rep["disagreement"]["by_contact"] = {"ground contact": None, "flight": 0.0123}
    assert "- error by contact state over every frame (RMS distance, as the plots): flight 12.30 mm\n" in markdown(rep)
    d["evidence"]["signature_share"] = 0.9
    assert "explains 90% of the residual acceleration\n" in markdown(rep)
    # where the tracks' and the shape's errors widen the spread, the z over every source is said too
    d["evidence"]["z_all"] = {"linear_drag.c": 30.2}
    assert "linear_drag.c at 30.2 SE; its" in markdown(rep)
    d["evidence"]["z_all"] = {"linear_drag.c": 6.1}
    assert "linear_drag.c at 30.2 SE (6.1 of every source); its" in markdown(rep)
    assert "also passed, told apart on the held-out frames: `force`" in text
    assert "also passed, as good on the held-out frames, told apart by BIC on the fit window: `quadratic_drag`" in text
    assert "damping" not in text
    assert "held at an end of its range" not in text
    d["at_bounds"] = {"body 0.E": "lower"}
    assert "held at an end of its range in the refit: body 0.E = 2.6e+04 (lower)" in markdown(rep)
    # the interval's sources, each with its standard error: the residuals, the rest shape, the tracks' drift
    d["params"] = {"linear_drag.c": 2.5}
    d["interval_sources"] = {"se_noise": {"linear_drag.c": 0.05}, "se_rest_shape": {"linear_drag.c": 0.07},
                             "se_tracking": {"linear_drag.c": 0.11}, "rest_shape_error_m": 0.001,
                             "shape_resolution_m": 0.0127, "starts_within": 1}  # fmt: skip
    text = markdown(rep)
    assert "interval (95%) from three sources, standard errors: c 0.05 and 0.07 and 0.11" in text
    assert "the tracks' own smooth error, one for the whole window at the noise credited to them" in text
    assert "the rest shape's error of 1.00 mm and the bodies' extent known to ± 6.35 mm a face carried" in text
    # a run's rest shape is its particles: no error of its own, only the extent (not "an error of 0.00 mm")
    d["interval_sources"].update(rest_shape_error_m=0.0)
    text = markdown(rep)
    assert "error of 0.00 mm" not in text
    assert "(the residuals' block bootstrap; the bodies' extent known to ± 6.35 mm a face carried" in text
    d["interval_sources"].update(rest_shape_error_m=2e-6)  # nonzero, but shown as 0.00 mm: left out too
    assert "error of 0.00 mm" not in markdown(rep)
    d["interval_sources"].update(rest_shape_error_m=0.001)
    d["interval_sources"].update(se_rest_shape={"linear_drag.c": None})
    text = markdown(rep)
    assert "from two sources, standard errors: c 0.05 and 0.11 (the residuals' block bootstrap; the tracks' own " \
           "smooth error" in text
    d["interval_sources"].update(se_tracking={"linear_drag.c": None})
    # where and when: frame, time, the body by name, its contact state, where
    rep["disagreement"]["first_departure"] = {"frame": 6, "time": 0.05, "body": "body 0", "contact": "flight",
                                              "centroid": [-0.292, -0.049, 0.3]}  # fmt: skip
    assert "- first departure: frame 6 (t = 0.050 s), in **body 0**, flight, around (-0.292, -0.049, 0.300) m\n" \
        in markdown(rep)
    rep["disagreement"]["first_departure"] = None
    assert "interval (95%)" not in markdown(rep)
    # the base's parameters before and after: the effect's own added, a replaced term's shown as gone, no "nan"
    d["base_after"] = {"body 0.E": 2.6e4, "linear_drag.c": 2.5}
    text = markdown(rep)
    assert "| body 0.E | 4e+05 | 2.6e+04 |" in text and "| linear_drag.c | — | 2.5 |" in text
    assert "nan" not in text and "The repaired model has no" not in text
    d.update(base_before={"body 0.E": 4e5, "ground.mu": 8.4, "ground.d": -0.004},
             base_after={"body 0.E": 4e4, "ground_sticky.d": 3e-4})
    text = markdown(rep)
    assert "| ground.mu | 8.4 | — |" in text and "| ground_sticky.d | — | 0.0003 |" in text and "nan" not in text
    assert "The repaired model has no `ground.mu` or `ground.d`: a discovered effect replaced" in text


def test_the_report_says_the_measurement_was_refined_and_what_it_gained():
    from causalgs.discover.report import markdown
    from causalgs.discover.video import refined_quality
    from causalgs.model.refine import Tracks

    before = np.array([30.0, 29.0, 28.5, 22.0, 21.0, 27.0])
    after = np.array([30.0, 31.0, 31.5, 30.5, 26.0, 31.0])
    eye = np.tile(np.eye(3), (6, 2, 1, 1))
    tr = refined_quality(Tracks(eye, np.zeros((6, 2, 3)), before, after, "val", "k"))
    assert tr["median"] == pytest.approx(30.75) and tr["median_kinematic"] == pytest.approx(27.75)
    assert tr["poor"] == [4] and tr["frames"] == list(range(6)) and tr["cameras"] == "val"
    rep = _fake_report(None)
    rep["tracking"] = {**tr, "pixel_m": 0.0046, "stray_particles": 0}
    text = markdown(rep)
    assert "refined frame by frame" in text and "median PSNR of 30.8 dB" in text and "alone: 27.8 dB" in text
    assert "worst frame 26.0 dB against 21.0" in text and "frames 4: a disagreement there" in text
    assert "longer kinematic fit" not in text  # that advice is for the kinematic fit's own tracks
    assert "same lens" not in text  # compared point by point
    rep["tracking"]["lens_patterns"] = 2
    assert "each of the run's 2 motion pattern(s) rigidly" in markdown(rep)
    assert "stretching tracks are the measurement" not in markdown(rep)
    rep["tracking"]["stretched_frames"] = [3, 4, 5, 9]  # where the two refinements part: the impact's frames
    assert "At frames 3–5, 9 the tracks refined with a stretch" in markdown(rep)
    del rep["tracking"]["stretched_frames"]
    # where the base model's bodies deform, the rigid tracks cannot follow them: said with the frames
    assert "depart from their rigid motion" not in markdown(rep)
    rep["disagreement"]["blind"] = [0.0, 0.0, 0.0004, 0.0051, 0.003, 0.0012]
    text = markdown(rep)
    assert "depart from their rigid motion by up to 5.10 mm per coordinate (frame 4; above half of that at frames " \
           "4–5)" in text, text
    rep["tracking"]["lens"] = "affine"  # tracks that stretch each pattern: the departure is from the affine motion
    text = markdown(rep)
    assert "move and stretch each of the run's 2 motion pattern(s)" in text
    assert "depart from their affine motion by up to 5.10 mm" in text and "affine tracks cannot follow" in text
    del rep["tracking"]["lens"]
    assert "weigh a residual" not in text
    rep["weights"] = {"min_weight": 0.12, "per_frame_min": [1.0, 1.0, 0.8, 0.12, 0.3, 0.6]}
    assert "weigh a residual by σ/√(σ² + e²)" in markdown(rep)
    assert "(weights down to 0.12; below one half at frames 3–4)" in markdown(rep)


def test_the_error_plot_shows_the_deformation_the_tracks_cannot_follow(monkeypatch, tmp_path):
    """error.png draws the base model's departure from rigid motion (per point, as the error curves) where the
    observation has a lens and the departure shows against the floor."""
    from causalgs.discover import report as rp

    figs = []
    monkeypatch.setattr(rp, "_save", lambda fig, path: figs.append(fig))
    obs = Observation(times=np.arange(5) / 60.0, x=np.zeros((5, 2, 3)), vol=np.ones(2), body=np.zeros(2),
                      observed=3, lo=(-1, -1, -1), hi=(1, 1, 1))  # fmt: skip
    rep = _fake_report(None)
    traj = {"before": np.full((4, 2, 3), 0.01), "after": np.full((4, 2, 3), 0.01)}
    for blind in (None, [0.0, 0.0, 0.0001, 0.0001], [0.0, 0.0, 0.004, 0.001]):
        rep["disagreement"]["blind"] = blind
        rp.plot_error(rep, traj, obs, tmp_path / "error.png")
    lines = [[ln for ln in fig.axes[0].get_lines() if "departure" in ln.get_label()] for fig in figs]
    assert not lines[0] and not lines[1]  # none, or far below the floor
    (curve,) = lines[2]
    assert np.allclose(curve.get_ydata(), 1000 * np.sqrt(3) * np.array([1e-6, 1e-6, 0.004, 0.001]))
    assert list(curve.get_xdata()) == [1, 2, 3, 4]


def test_a_synthetic_scenes_report_puts_its_truth_beside_what_was_found():
    """Where the observation carries its truth (a synthetic scene), report.md says the true value of each found
    parameter and a truth column beside the base parameters before and after; without a truth, neither."""
    from causalgs.discover.report import markdown, true_value

    truth = {"effects": {"gravity": {"g": [0.0, 0.0, -9.8]}, "ground": {"mu": [0.3]},
                         "linear_drag": {"c": [0.6]}},
             "bodies": [{"name": "block", "E": 38255.1, "nu": 0.3, "velocity": [0.82, 0.02, 1.16],
                         "omega": [0.0, 0.0, 0.0]}]}  # fmt: skip
    assert true_value(truth, "block.E") == 38255.1 and true_value(truth, "block.v0[2]") == 1.16
    assert true_value(truth, "block.omega0[1]") == 0.0 and true_value(truth, "ground.mu") == 0.3
    assert true_value(truth, "linear_drag.c") == 0.6
    assert true_value(truth, "force.b[0]") == 0.0  # an effect the truth has not: its parameters are zero
    assert true_value(truth, "block.density_scale") is None and true_value(None, "block.E") is None
    rep = _fake_report("linear_drag", 0.6032)
    d = rep["discovered"][0]
    d.update(law="linear drag: a = −c·v, c = 0.6032 [0.548, 0.66]",
             evidence={"signature": "v", "signature_share": 0.99, "future_drop": 0.7, "delta_bic": -114.6,
                       "z": {"linear_drag.c": 30.0}},
             base_before={"block.E": 3.5e4, "ground.mu": 0.43}, base_after={"block.E": 3.8e4, "ground.mu": 0.29,
                                                                           "linear_drag.c": 0.6032})  # fmt: skip
    plain = markdown(rep)
    assert "| parameter | before | after |\n" in plain and "truth" not in plain
    text = markdown({**rep, "truth": truth})
    assert "  - the scene's truth (a synthetic scene): c = 0.6\n" in text
    assert "| parameter | before | after | truth |" in text
    assert "| block.E | 3.5e+04 | 3.8e+04 | 3.826e+04 |" in text and "| linear_drag.c | — | 0.6032 | 0.6 |" in text
    d["evidence"].update(signature="plastic", signature_share=None)  # a driver the accelerations do not measure
    text = markdown(rep)
    assert "its signature `plastic` is not one the residual accelerations measure" in text and "n/a" not in text


def test_the_error_plot_names_the_model_it_draws_and_labels_millimetres_plainly(monkeypatch, tmp_path):
    """The repaired curve of an ambiguity set is its first candidate's model (the one the repair keeps), said to be
    not told apart from the others, not their sum; the log axis reads in plain millimetres."""
    from causalgs.discover import report as rp

    figs = []
    monkeypatch.setattr(rp, "_save", lambda fig, path: figs.append(fig))
    obs = Observation(times=np.arange(5) / 60.0, x=np.zeros((5, 2, 3)), vol=np.ones(2), body=np.zeros(2),
                      observed=3, lo=(-1, -1, -1), hi=(1, 1, 1))  # fmt: skip
    traj = {"before": np.full((4, 2, 3), 0.006), "after": np.full((4, 2, 3), 0.004)}
    amb = {**_fake_report(None, verdict="ambiguous"),
           "ambiguous": [{"effect": "linear_drag"}, {"effect": "quadratic_drag"}]}  # fmt: skip
    found = _fake_report("linear_drag", 0.6)
    found["discovered"].append({"effect": "force"})
    for rep in (amb, found):
        rp.plot_error(rep, traj, obs, tmp_path / "error.png")
    labels = [[ln.get_label() for ln in fig.axes[0].get_lines()] for fig in figs]
    assert "after: linear_drag (not told apart from quadratic_drag)" in labels[0]
    assert "after: linear_drag + force" in labels[1]
    ax = figs[0].axes[0]
    ax.figure.canvas.draw()
    shown = [t.get_text() for t in ax.yaxis.get_ticklabels(which="both") if t.get_text()]
    assert shown and all("10^" not in t and "times" not in t for t in shown), shown
    assert all(float(t) > 0 for t in shown)


def test_the_report_says_when_the_base_was_recalibrated_from_a_refit():
    from causalgs.discover.report import markdown

    rep = _fake_report(None)
    rep["rounds"] = [{"screen": [{"effect": "plasticity", "gain": 0.03}],
                      "refits": [{"effect": "plasticity", "future_mse_cm2": 0.2, "passed": False,
                                  "reasons": ["held-out error drop 2% < 15%"]}],
                      "rebased": {"from": "plasticity", "train_before_cm2": 0.042, "train_after_cm2": 0.019,
                                  "future_before_cm2": 0.5, "future_after_cm2": 0.21}}]  # fmt: skip
    text = markdown(rep)
    assert "recalibrated from where the `plasticity` refit went" in text and "0.042 → 0.019 cm²" in text
    del rep["rounds"][0]["rebased"]
    assert "recalibrated" not in markdown(rep)


def test_the_report_weighs_the_held_out_error_against_what_a_correct_model_would_miss():
    from causalgs.discover.report import markdown

    rep = _fake_report(None)
    rep["error_before"] = rep["error_after"] = {"fit_rms_m": 0.0015, "future_rms_m": 0.0053}
    rep.update(future_floor_rms_m=0.0025, predictive_rms_m=0.0020, floor_rms_m=0.0015)
    text = markdown(rep)
    assert "misses by 5.30 mm, 2.1× what a correct model would miss them by (2.50 mm" in text
    assert "fit window's noise carried forward 2.00 mm" in text
    rep["verdict"] = "unexplained discrepancy"
    assert "3.5× on the held-out frames" not in markdown(rep) and "2.1× on the held-out frames" in markdown(rep)
    assert "in rigid motion of the bodies that a free force would remove" in markdown(rep)
    from causalgs.discover.video import refined_quality
    from causalgs.model.refine import Tracks

    psnr = np.array([30.0, 31.0, 31.5])
    tracks = Tracks(np.tile(np.eye(3), (3, 1, 1, 1)), np.zeros((3, 1, 3)), psnr, psnr, "val", "k", stretch=True)
    rep["tracking"] = {**refined_quality(tracks), "lens": "affine", "lens_patterns": 1, "pixel_m": 0.0046}
    # through an affine lens the excess over the floor is motion and strain
    text = markdown(rep)
    assert "in the bodies' motion and strain, which a free force and a free strain" in text
    assert "the affine tracks' error" not in text and "rigid motion of the bodies" not in text
    assert "(`tracks-affine.npz` in the run)" in text and "bend each of" not in text
    rep["tracking"]["bend_bodies"] = 1  # tracks that also bend the body: saved and named as such
    text = markdown(rep)
    assert "(`tracks-bent.npz` in the run)" in text and "They also bend each of 1 body(ies)" in text, text
    del rep["tracking"]
    # weighted residuals: the floors compare with the weighted errors, and both are shown
    rep["verdict"] = "no missing effect"
    rep["error_before"] = rep["error_after"] = {"fit_rms_m": 0.0030, "future_rms_m": 0.0080,
                                                "fit_rms_weighted_m": 0.0015, "future_rms_weighted_m": 0.0053}
    text = markdown(rep)
    assert "misses by 5.30 mm (weighted), 2.1× what a correct model would miss them by" in text, text
    assert "within 1.00× of the noise floor" in text
    assert "fit window 1.50 mm → 1.50 mm, held-out future 5.30 mm → 5.30 mm" in text


def test_a_dead_worker_leaves_its_runs_for_the_resumed_table():
    """A worker process that dies (here: ``os._exit(3)``, as a killed one) breaks the pool; the runs it broke get no
    row (a resumed table runs them again) and the log names them, instead of a "failed" row for every run in it."""
    import operator
    import os

    import causalgs.discover.table as T

    rows, logs = [], []
    T.execute([(os._exit, 3)], 2, None, operator.call, (), lambda *a: pytest.fail("a failed row"), rows.append,
              logs.append)  # fmt: skip
    assert rows == [] and "a worker process died" in logs[-1] and "(seed 3)" in logs[-1], logs


def test_cpu_shares_split_the_cpus_in_order():
    from causalgs.processes import shares

    assert shares([0, 1], 2) == [[0], [1]] and shares([0, 1, 2, 3], 2) == [[0, 1], [2, 3]]
    assert shares([0, 1, 2], 2) == [[0], [1, 2]] and shares([4, 5], 1) == [[4, 5]]
    assert shares([0, 1], 3) == [[0], [1], [0]] and shares([3], 2) == [[3], [3]]
    assert shares(None, 2) is None


# run in a table's worker process: where it runs, what its workers may take, its Taichi pool and its process
_WHERE = ("(__import__('time').sleep(2), sorted(__import__('os').sched_getaffinity(0)), "
          "__import__('causalgs._ti', fromlist=['_']).allowed_cpus(), "
          "__import__('causalgs._ti', fromlist=['_']).runtime().threads, __import__('os').getpid())[1:]")  # fmt: skip


@pytest.mark.parametrize("env", [None, "last"])
def test_runs_side_by_side_each_run_on_a_share_of_the_cpus_of_their_own(monkeypatch, env):
    """A table's runs in worker processes are pinned to their own shares of the CPUs (all those this process may
    use, or ``$CAUSALGS_TI_CPUS``), with one Taichi thread per CPU of it, and their own rollout workers inside it:
    unpinned, each ran several times slower."""
    import os

    import causalgs.discover.table as T
    from causalgs import _ti
    from causalgs.processes import shares

    cpus = _ti.allowed_cpus()
    if env is None:
        monkeypatch.delenv(_ti.CPUS_ENV, raising=False)
    else:
        cpus = [cpus[-1]]
        monkeypatch.setenv(_ti.CPUS_ENV, str(cpus[0]))
    rows = []
    T.execute([(_WHERE, {}), (_WHERE, {})], 2, None, eval, (), lambda *a: pytest.fail(f"a failed row {a}"),
              rows.append, lambda line: None)  # fmt: skip
    assert len(rows) == 2 and len({pid for *_, pid in rows}) == 2, rows  # one run in each process
    for where, allowed, threads, pid in rows:
        assert pid != os.getpid() and where == allowed and threads == len(where), rows
    assert sorted(where for where, *_ in rows) == sorted(shares(cpus, 2)), rows


def test_a_stopped_table_stops_its_workers_instead_of_waiting_for_their_runs():
    """Stopped while runs are under way in worker processes (Ctrl-C, or SIGTERM, which the command line turns into an
    exit), the table stops its workers and ends at once: the stop propagates, and no worker is left running the
    minute-long run it was given."""
    import multiprocessing
    import operator
    import time

    import causalgs.discover.table as T

    def stop(line):
        raise KeyboardInterrupt

    before = multiprocessing.active_children()  # an earlier test's pool may still be winding down
    t0 = time.monotonic()
    with pytest.raises(KeyboardInterrupt):
        T.execute([(time.sleep, 60), (time.sleep, 61)], 2, None, operator.call, (), lambda *a: pytest.fail("a row"),
                  lambda row: pytest.fail("a row"), stop)  # fmt: skip
    assert [p for p in multiprocessing.active_children() if p not in before] == []
    assert time.monotonic() - t0 < 45  # the runs would have taken a minute; spawning two workers takes seconds


def test_a_stopped_discovery_stops_its_rollout_workers_instead_of_waiting_for_their_rollouts(ti32_runtime,
                                                                                             tmp_path):
    """Stopped while its rollout workers are busy (Ctrl-C here; SIGTERM is an exit, handled alike), discovery
    terminates them: the half-minute task under way never finishes, and no worker is left running."""
    import contextlib
    import multiprocessing
    import signal
    import threading
    import time

    from causalgs.discover import workers

    assert workers.active() is None
    mark = tmp_path / "mark"
    main = threading.main_thread().ident

    def stop_once_started():
        while not mark.exists():
            time.sleep(0.05)
        signal.pthread_kill(main, signal.SIGINT)

    before = multiprocessing.active_children()
    # Ctrl-C as at a terminal: a job started in the background of a non-interactive shell inherits SIGINT ignored
    # (and Python then installs no KeyboardInterrupt for it), which is not what this test is about
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    with pytest.raises(KeyboardInterrupt), contextlib.ExitStack() as restore:
        restore.callback(signal.signal, signal.SIGINT, previous)
        with workers.rollout_workers(2) as pool:
            threading.Thread(target=stop_once_started, daemon=True).start()
            # a task that says it started, runs half a minute and says it finished (exec: a builtin the spawned
            # workers unpickle, where a function of this test module would not import)
            task = (f"import pathlib, time\np = pathlib.Path({str(mark)!r})\np.write_text('started')\n"
                    "time.sleep(30)\np.write_text('finished')\n")
            pool.map(exec, [(task, {})])
    assert workers.active() is None
    assert mark.read_text() == "started"
    assert [p for p in multiprocessing.active_children() if p not in before] == []


def test_no_further_round_once_the_repaired_model_agrees_within_the_noise(ti32_runtime, tmp_path):
    """After the drag is found, the repaired model fits the window at the noise and the held-out frames within what
    a correct model misses them by: a second round would only fit the noise, and is not run."""
    import dataclasses

    from causalgs.discover.run import run_discovery

    cfg = dataclasses.replace(CFG, max_effects=2)
    rep = run_discovery("throw.npz", tmp_path, spec="gravity;walls", learn=(), candidates=CANDIDATES, config=cfg,
                        obs=_throw(C_TRUE))  # fmt: skip
    assert [d["effect"] for d in rep["discovered"]] == ["linear_drag"]
    assert len(rep["rounds"]) == 1 and rep["settled"]["round"] == 2
    assert rep["settled"]["train_rms_ratio_to_window_floor"] <= 1 and rep["settled"]["future_rms_ratio_to_floor"] <= 1
    assert "Round 2 was not run" in (tmp_path / "report.md").read_text()


def test_discover_table_stretches_video_tracks_unless_told_not_to(tmp_path, monkeypatch):
    """``discover-table --level video`` runs with the stretching tracks where the bodies deform unless
    ``--no-stretch``; at trajectory level only an explicit ``--stretch`` is refused (above)."""
    import causalgs.discover.video_table as V

    seen = []
    monkeypatch.setattr(V, "run_video_table", lambda out, cfg, **kw: seen.append(cfg) or [])
    for extra, stretch in (([], True), (["--no-stretch"], False), (["--stretch"], True)):
        r = CliRunner().invoke(cli, ["discover-table", "--level", "video", "--only", "linear_drag", "--out",
                                     str(tmp_path / "t"), *extra])  # fmt: skip
        assert r.exit_code == 0, r.output
        assert seen[-1].stretch is stretch
    import causalgs.discover.table as T

    monkeypatch.setattr(T, "run_table", lambda out, cfg, **kw: seen.append(cfg) or [])
    r = CliRunner().invoke(cli, ["discover-table", "--only", "linear_drag", "--out", str(tmp_path / "u")])
    assert r.exit_code == 0 and isinstance(seen[-1], T.TableConfig), r.output
