"""``causalgs reframe``: a dataset re-posed by a similarity, its images unchanged, its cameras, points and truth
moved, the transform recorded; degenerate transforms and occupied folders refused without writing anything."""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner

from causalgs.dataset import load_dataset
from causalgs.errors import CausalGSError
from causalgs.reframe import reframe_dataset
from causalgs.similarity import Similarity, random_rotation


@pytest.fixture(scope="module")
def spin(tmp_path_factory):
    from causalgs.synth import generate

    out = tmp_path_factory.mktemp("spin") / "data"
    generate("spin", out, views=4, frames=6, resolution=24, progress=False)
    return out


def test_a_reframed_copy_is_the_same_scene_in_another_frame(spin, tmp_path):
    sim = Similarity.make(random_rotation(0), 0.3, [1.0, 2.0, 3.0])
    reframe_dataset(spin, tmp_path / "a", sim)
    a, b = load_dataset(spin), load_dataset(tmp_path / "a")
    for fa, fb in zip(a.frames(), b.frames(), strict=True):
        assert fa.path.read_bytes() == fb.path.read_bytes()
        assert np.allclose(sim.points(fa.camera.center), fb.camera.center)
    assert np.allclose(sim.points(a.points), b.points, atol=1e-5)
    # a point projects to the same pixel through the re-posed camera
    p = a.points[:5]
    for fa, fb in zip(a.train[:3], b.train[:3], strict=True):
        assert np.allclose(fa.camera.project(p)[0], fb.camera.project(sim.points(p))[0], atol=1e-6)
    with np.load(spin / "gt" / "motion.npz") as za, np.load(tmp_path / "a" / "gt" / "motion.npz") as zb:
        assert np.allclose(sim.points(za["trajectories"]), zb["trajectories"], atol=1e-5)
        assert np.allclose(sim.orientations(za["R"]), zb["R"], atol=1e-6)
        assert np.allclose(sim.directions(za["omega"]), zb["omega"])
        assert np.array_equal(za["body_points"], zb["body_points"])  # body frame: unchanged
    meta = json.loads((tmp_path / "a" / "gt" / "meta.json").read_text())
    assert np.allclose(meta["frame"]["matrix"], sim.matrix()) and meta["frame"]["unchanged"] == []
    # re-posed again: the transform from the original composes
    again = Similarity.make(random_rotation(1), 2.0)
    reframe_dataset(tmp_path / "a", tmp_path / "b", again)
    meta = json.loads((tmp_path / "b" / "gt" / "meta.json").read_text())
    assert np.allclose(meta["frame"]["matrix"], again.matrix() @ sim.matrix())


def test_motion_of_a_simulated_scene_transforms_by_kind():
    from causalgs.reframe import transform_motion

    sim = Similarity.make(random_rotation(2), 2.0, [0.0, 0.0, 1.0])
    rng = np.random.default_rng(0)
    F = np.eye(3) + 0.1 * rng.normal(size=(2, 5, 3, 3))
    arrays = {"particles": rng.normal(size=(2, 5, 3)).astype(np.float32), "F": F, "particle_object": np.ones(5),
              "vertices_2": rng.normal(size=(2, 4, 3)), "triangles_2": np.array([[0, 1, 2]]), "mystery": np.ones(3)}
    out, unknown = transform_motion(arrays, sim)
    assert out["particles"].dtype == np.float32 and np.allclose(out["particles"], sim.points(arrays["particles"]),
                                                                atol=1e-5)  # fmt: skip
    assert np.allclose(out["F"], sim.deformations(F))
    assert np.allclose(out["vertices_2"], sim.points(arrays["vertices_2"]))
    assert out["triangles_2"] is arrays["triangles_2"] and unknown == ["mystery"]


def _cli(*args):
    from cli.main import cli

    r = CliRunner().invoke(cli, ["reframe", *map(str, args)])
    return r.exit_code, r.output


@pytest.mark.parametrize(("args", "match"), [
    (["--scale", "0"], "scale = 0.0 must be a positive number"),
    (["--scale", "-3"], "scale = -3.0 must be a positive number"),
    (["--rotate", "1,0,0,0,1,0,0,0,2"], "is not a rotation"),
    (["--rotate", "w:30"], "--rotate 'w:30'"),
    (["--translate", "1,2"], "--translate '1,2'"),
])  # fmt: skip
def test_degenerate_transforms_are_one_line_errors_and_write_nothing(spin, tmp_path, args, match):
    code, out = _cli(spin, "--out", tmp_path / "x", *args)
    assert code == 1 and match in out and len(out.strip().splitlines()) == 1
    assert not (tmp_path / "x").exists() and not [p for p in tmp_path.iterdir() if p.name.startswith(".x")]


def test_an_occupied_folder_needs_force_and_a_failure_leaves_it_whole(spin, tmp_path, monkeypatch):
    code, _ = _cli(spin, "--out", tmp_path / "x", "--rotate", "x:90")
    assert code == 0
    code, out = _cli(spin, "--out", tmp_path / "x")
    assert code == 1 and "--force" in out
    before = sorted(p.relative_to(tmp_path) for p in (tmp_path / "x").rglob("*"))

    def broken(*a, **k):
        raise CausalGSError("disk full")

    monkeypatch.setattr("causalgs.reframe.write_points_ply", broken)
    with pytest.raises(CausalGSError, match="disk full"):
        reframe_dataset(spin, tmp_path / "x", Similarity.identity(), overwrite=True)
    assert sorted(p.relative_to(tmp_path) for p in (tmp_path / "x").rglob("*")) == before
    assert [p.name for p in tmp_path.iterdir()] == ["x"]
    code, out = _cli(tmp_path / "missing", "--out", tmp_path / "y")
    assert code == 1 and "missing" in out and not (tmp_path / "y").exists()
