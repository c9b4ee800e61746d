"""The video-level hidden-effect table: its plan, the tracking error it reports, and how it resumes each stage
(synth → fit → discover). The stages themselves are tested where they live (the synthetic scenes, the fit, discovery
on a run); here they are replaced by recorders that write what the real ones write, so that the table's bookkeeping
is checked in seconds. The real table is `causalgs discover-table --level video`."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

import causalgs.discover.video_table as V
from causalgs.errors import CausalGSError


def test_the_plan_covers_every_case_once_before_any_twice():
    cfg = V.VideoTableConfig(seeds=2, control_seeds=3)
    plan = V.plan(cfg)
    n = len(V.CASES)
    controls = [c.name for c in V.CASES if c.kind == "control"]
    assert plan[:n] == [(c.name, 0) for c in V.CASES]
    assert len(plan) == 2 * n + len(controls) and plan[-len(controls):] == [(c, 2) for c in controls]
    only = V.plan(V.VideoTableConfig(only=("linear_drag", "outside"), first_seed=5))
    assert only == [("linear_drag", 5), ("outside: attractor", 5)]
    # every effect of the catalogue is hidden in one case, with a control for each window and one outside it
    from causalgs.discover.candidates import select

    assert {c.expect for c in V.CASES if c.kind in ("hidden", "pair")} == {c.key for c in select(None)}
    assert {c.frames for c in V.CASES if c.kind == "control"} == {V.FLIGHT, V.LANDING}


def test_tracking_error_against_a_plain_reference(tmp_path):
    """RMS per coordinate of tracked minus true displacements, at tracked points within 1 cm of a true point (a
    point far from every true one, say on the ground, is left out)."""
    rng = np.random.default_rng(0)
    frames, n = 6, 40
    gt = rng.uniform(-0.2, 0.2, (1, n, 3)) + np.linspace(0, 0.3, frames)[:, None, None] * np.array([1.0, 0.0, 0.5])
    (tmp_path / "gt").mkdir()
    np.savez(tmp_path / "gt" / "motion.npz", particles=np.concatenate([gt, gt[-1:]]))  # one frame past the window
    pick = rng.choice(n, 15, replace=False)
    err = 0.002 * rng.standard_normal((frames, 15, 3))
    x = gt[:, pick] + 0.003 + err  # a constant offset does not count: displacements are compared
    stray = np.full((frames, 1, 3), 5.0)
    obs = SimpleNamespace(x=np.concatenate([x, stray], axis=1))
    e = (err - err[:1])[1:]
    assert V.tracking_error(obs, tmp_path) == pytest.approx(float(np.sqrt((e**2).mean())), rel=1e-12)
    assert V.tracking_error(SimpleNamespace(x=stray), tmp_path) is None


def test_predictions_against_the_truth_at_the_matched_particles(tmp_path):
    """The discovery's saved simulations against the truth's motion at the tracked particles matched to a true
    material point: displacement errors over the held-out frames, before and after (a plain reference)."""
    rng = np.random.default_rng(1)
    frames, n, observed = 7, 30, 5
    gt = rng.uniform(-0.2, 0.2, (1, n, 3)) + np.linspace(0, 0.2, frames)[:, None, None] * np.array([1.0, 0.2, 0.0])
    (tmp_path / "gt").mkdir()
    np.savez(tmp_path / "gt" / "motion.npz", particles=gt)
    disc = tmp_path / "discover"
    disc.mkdir()
    assert V.prediction_error(disc, tmp_path) is None  # nothing saved
    pick = rng.choice(n, 12, replace=False)
    x = np.concatenate([gt[:, pick] + 0.002, np.full((frames, 1, 3), 5.0)], axis=1)  # + one unmatched point
    before = x + rng.normal(0, 0.004, x.shape) * (np.arange(frames) >= 1)[:, None, None]
    after = x + rng.normal(0, 0.001, x.shape) * (np.arange(frames) >= 1)[:, None, None]
    np.savez(disc / "trajectories.npz", x=x, before=before, after=after, observed=np.int64(observed))
    got = V.prediction_error(disc, tmp_path)
    for name, sim in (("before", before), ("after", after)):
        e = (sim[:, :12] - sim[:1, :12]) - (gt[:, pick] - gt[:1, pick])
        assert got[f"future_rms_{name}_m"] == pytest.approx(float(np.sqrt((e[observed:] ** 2).mean())), rel=1e-12)
        assert got[f"fit_rms_{name}_m"] == pytest.approx(float(np.sqrt((e[1:observed] ** 2).mean())), rel=1e-12)
    assert got["future_rms_after_m"] < got["future_rms_before_m"]


def _recorders(monkeypatch, calls, *, fail=()):
    """Stand-ins for the three stages that write what the real ones leave behind."""

    def generate(name, data, **kw):
        calls.append(("synth", kw["effects"]))
        Path(data).mkdir(parents=True, exist_ok=True)
        (Path(data) / "transforms_train.json").write_text("{}")

    def fit(data, run, config=None, *, resume=False):
        calls.append(("fit-resume" if resume else "fit", str(run)))
        run = Path(run)
        run.mkdir(parents=True, exist_ok=True)
        if config is not None:
            (run / "config.toml").write_text(config.physics.effects)
        (run / "checkpoint.pt").write_text("")
        if "stop" in str(run) and not resume:
            raise KeyboardInterrupt  # the fit stops half-way: a checkpoint, no finished run.json
        (run / "run.json").write_text(json.dumps({"status": "done", "total_seconds": 700.0}))

    def discover(run, out, *, config, log, resume, grid, lens, stretch):
        calls.append(("discover", resume) + ((lens,) if lens != "auto" else ()) + (("stretch",) if stretch else ()))
        assert config.res == 0  # each run's own grid, unless the truth's is given (the default)
        assert grid == ((-0.5, -0.5, -0.1), (0.5, 0.5, 0.9), 43)  # the truth's: the synth box, its reference cells
        if "attractor" in str(run):
            raise CausalGSError("the simulation blew up at frame 3")
        found = [{"effect": "linear_drag", "params": {"linear_drag.c": 2.85},
                  "interval": {"linear_drag.c": [2.7, 3.1]}}] if "drag" in str(run) else []  # fmt: skip
        rep = {"verdict": "discovered" if found else "no missing effect", "discovered": found, "ambiguous": [],
               "error_before": {"future_rms_m": 0.012}, "error_after": {"future_rms_m": 0.001 if found else 0.012},
               "floor_rms_m": 0.0012, "seconds": 300.0, "noise": 0.0011,
               "images": {"psnr_before": 25.0, "psnr_after": 32.5}}  # fmt: skip
        return rep, SimpleNamespace(x=np.zeros((3, 2, 3))), SimpleNamespace(x=np.ones((3, 2, 3)))

    monkeypatch.setattr(V, "_generate", generate)
    monkeypatch.setattr(V, "_run_fit", fit)
    monkeypatch.setattr(V, "_discover", discover)
    monkeypatch.setattr(V, "tracking_error", lambda obs, data, frame=None: 0.0015 if obs.x.sum() == 0 else 0.008)


def test_the_table_resumes_each_stage_and_records_failures(tmp_path, monkeypatch):
    calls = []
    _recorders(monkeypatch, calls)
    cfg = V.VideoTableConfig(only=("linear_drag", "friction", "outside: attractor"))
    rows = V.run_video_table(tmp_path, cfg)
    assert [c[0] for c in calls].count("synth") == 3 and [c[0] for c in calls].count("fit") == 3
    # a stopped discovery goes on, the tracks stretched where the bodies deform (the default)
    assert all(c == ("discover", True, "stretch") for c in calls if c[0] == "discover")
    by = {r["case"]: r for r in rows}
    drag = by["linear_drag"]
    assert drag["first_ok"] and drag["param_error"] == pytest.approx(0.05) and drag["interval_covers"]
    assert drag["fit_seconds"] == 700.0 and drag["tracking_rms_m"] == 0.0015 and drag["psnr_after"] == 32.5
    assert drag["tracking_kinematic_rms_m"] == 0.008  # the measurement without the per-frame refinement
    assert by["outside: attractor"]["verdict"] == "failed: the simulation blew up at frame 3"
    assert not by["friction"]["first_ok"]  # the stand-in found nothing
    # the friction case's model lacks the friction: its fit is told so
    assert (tmp_path / "friction-s0" / "run" / "config.toml").read_text() == "gravity;ground:mu=0.0;walls"
    saved = json.loads((tmp_path / "table.json").read_text())
    assert saved["level"] == "video" and saved["summary"]["runs"] == 3
    assert "| linear_drag | 0 | ✓ discovered |" in (tmp_path / "table.md").read_text()
    assert "| 8.00 → 1.50 |" in (tmp_path / "table.md").read_text()
    n = len(calls)
    V.run_video_table(tmp_path, cfg)  # every row is there: nothing runs again
    assert len(calls) == n
    # a new seed of the same case reuses nothing of seed 0, and a stopped fit goes on from its checkpoint
    # (the tracks through the lens the table is told, not stretched when told so)
    cfg1 = V.VideoTableConfig(only=("linear_drag",), first_seed=1, lens="affine", stretch=False)
    (tmp_path / "table.json").unlink()
    rows = V.run_video_table(tmp_path, cfg1)
    assert calls[n:] == [("synth", V.BY_NAME["linear_drag"].scene), ("fit", str(tmp_path / "linear-drag-s1" / "run")),
                         ("discover", True, "affine")]  # fmt: skip
    # a row lost with its table: the finished dataset and run are kept, only discovery runs (and resumes)
    (tmp_path / "table.json").unlink()
    m = len(calls)
    V.run_video_table(tmp_path, cfg1)
    assert calls[m:] == [("discover", True, "affine")]


def test_a_stopped_fit_resumes_and_other_tables_are_refused(tmp_path, monkeypatch):
    calls = []
    _recorders(monkeypatch, calls)
    monkeypatch.setattr(V, "_slug", lambda name: "stop-" + name.replace(" ", "").replace(":", ""))
    cfg = V.VideoTableConfig(only=("control: flight",))
    with pytest.raises(KeyboardInterrupt):
        V.run_video_table(tmp_path, cfg)
    rows = V.run_video_table(tmp_path, cfg)
    assert [c[0] for c in calls] == ["synth", "fit", "fit-resume", "discover"]
    assert rows[0]["first_ok"]
    from causalgs.discover.table import TableConfig, run_table

    with pytest.raises(CausalGSError, match="of the video level, not of the trajectory level"):
        run_table(tmp_path, TableConfig(only=("control: clean",)))
    traj = tmp_path / "traj"
    traj.mkdir()
    (traj / "table.json").write_text(json.dumps({"rows": []}))
    with pytest.raises(CausalGSError, match="of the trajectory level, not of the video level"):
        V.run_video_table(traj, cfg)


def test_tables_run_in_pieces_merge_into_one(tmp_path, monkeypatch):
    """`--merge`: the rows of several tables in one, each taken only where its video is the case's current scene,
    a later table's row replacing an earlier one of the same case and seed; nothing runs."""
    calls = []
    _recorders(monkeypatch, calls)
    a, b, merged = tmp_path / "a", tmp_path / "b", tmp_path / "all"
    V.run_video_table(a, V.VideoTableConfig(only=("linear_drag", "control: flight", "friction")))
    V.run_video_table(b, V.VideoTableConfig(only=("linear_drag", "control: flight"), first_seed=1))
    V.run_video_table(b, V.VideoTableConfig(only=("control: flight",)))
    for folder in (a / "linear-drag-s0", a / "friction-s0", b / "linear-drag-s1", b / "control-flight-s1"):
        assert (folder / "data" / "synth.json").is_file()  # the stamp every rendered case leaves
    # a case since rendered otherwise (here: a landing of 96 frames) is left out, and one without a stamp
    stamp = a / "friction-s0" / "data" / "synth.json"
    stamp.write_text(json.dumps({**json.loads(stamp.read_text()), "frames": 96}))
    (a / "linear-drag-s0" / "data" / "synth.json").unlink()
    # the row of control: flight, seed 0 in b replaces a's
    saved = json.loads((b / "table.json").read_text())
    for r in saved["rows"]:
        if (r["case"], r["seed"]) == ("control: flight", 0):
            r["seconds"] = 123.0
    (b / "table.json").write_text(json.dumps(saved))
    said = []
    n = len(calls)
    rows = V.merge(merged, [a, b], log=said.append)
    assert len(calls) == n  # nothing ran
    got = {(r["case"], r["seed"]): r for r in rows}
    assert set(got) == {("control: flight", 0), ("linear_drag", 1), ("control: flight", 1)}
    assert got[("control: flight", 0)]["seconds"] == 123.0
    assert got[("control: flight", 0)]["folder"] == str(b / "control-flight-s0")
    assert any("friction, seed 0" in m and "96 frames" in m for m in said)
    assert any("linear_drag, seed 0" in m and "no " in m for m in said)
    table = json.loads((merged / "table.json").read_text())
    assert table["level"] == "video" and table["summary"]["runs"] == 3
    assert table["config"]["merged_from"] == [str(a), str(b)]
    assert table["summary"]["controls_no_effect"] == 1.0
    assert "| linear_drag | 1 | ✓ discovered |" in (merged / "table.md").read_text()
    traj = tmp_path / "traj"
    traj.mkdir()
    (traj / "table.json").write_text(json.dumps({"rows": []}))
    with pytest.raises(CausalGSError, match="of the trajectory level, not of the video level"):
        V.merge(merged, [traj])
