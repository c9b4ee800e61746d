"""``causalgs render``: PLY or run folder, camera file or dataset camera, image or turntable, one-line errors."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
import torch
from click.testing import CliRunner

from causalgs.cameras import Camera, look_at
from causalgs.ply import write_gaussians_ply
from causalgs.render import rasterize
from causalgs.render.views import to_uint8
from cli.main import cli

W, H = 32, 24
BG = (0.1, 0.2, 0.3)


def _camera() -> Camera:
    return Camera.from_blender(look_at([0.0, -4.0, 1.5], [0.0, 0.0, 0.0]), W, H, fov_x=0.9)


@pytest.fixture
def scene(tmp_path, make_gaussians):
    """A 50-Gaussian PLY and a 32x24 camera file with a background."""
    g = make_gaussians()
    write_gaussians_ply(tmp_path / "scene.ply", **g)
    (tmp_path / "cam.json").write_text(json.dumps({**_camera().to_json(), "background": list(BG)}))
    return g, tmp_path


def _invoke(*args):
    return CliRunner().invoke(cli, ["render", *map(str, args)])


def _read_png(path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert img is not None, f"{path} does not decode"
    return img[..., ::-1]


def _reference(g, cam: Camera, bg) -> np.ndarray:
    t = {k: torch.from_numpy(v) for k, v in g.items()}
    img, _, _ = rasterize(
        t["means"], t["quats"], t["scales"], t["opacities"], t["sh"], torch.tensor(cam.viewmat),
        torch.tensor(cam.K), cam.width, cam.height, background=bg,
    )  # fmt: skip
    return to_uint8(img)


def _one_line_error(result, expected: str) -> str:
    assert result.exit_code != 0, result.output
    assert "Traceback" not in result.output
    assert result.exception is None or isinstance(result.exception, SystemExit), repr(result.exception)
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("Error:") and expected in lines[0], result.output
    return lines[0]


def test_renders_a_ply_to_png_like_rasterize(ti32, scene):
    g, d = scene
    out = d / "img.png"
    result = _invoke("--ply", d / "scene.ply", "--camera", d / "cam.json", "--out", out)
    assert result.exit_code == 0, result.output
    img = _read_png(out)
    assert img.shape == (H, W, 3) and img.dtype == np.uint8
    assert img.std() > 5, "the image should not be uniform"
    np.testing.assert_array_equal(img, _reference(g, _camera(), BG))  # background from the camera file
    # --background overrides it
    result = _invoke("--ply", d / "scene.ply", "--camera", d / "cam.json", "--out", out, "--background", "1,0,0")
    assert result.exit_code == 0, result.output
    np.testing.assert_array_equal(_read_png(out), _reference(g, _camera(), (1.0, 0.0, 0.0)))


def test_renders_a_run_folder_and_notes_time(ti32, scene):
    g, d = scene
    run = d / "run"
    write_gaussians_ply(run / "gaussians.ply", **g)
    result = _invoke(run, "--camera", d / "cam.json", "--out", d / "run.png", "--time", "0.5")
    assert result.exit_code == 0, result.output
    assert "issue #6" in result.output and "canonical (t = 0)" in result.output
    np.testing.assert_array_equal(_read_png(d / "run.png"), _reference(g, _camera(), BG))


def test_camera_from_a_dataset(ti32, scene, tmp_path):
    from causalgs.dataset import load_dataset
    from causalgs.synth import generate

    g, d = scene
    data = tmp_path / "spin"
    generate("spin", data, views=3, frames=3, resolution=24, progress=False)
    out = d / "view.png"
    result = _invoke("--ply", d / "scene.ply", "--data", data, "--view", 1, "--split", "val", "--out", out)
    assert result.exit_code == 0, result.output
    frame = load_dataset(data, splits=("val",)).val[1]
    img = _read_png(out)
    assert img.shape == (24, 24, 3)
    np.testing.assert_array_equal(img, _reference(g, frame.camera, tuple(frame.background.tolist())))
    bad = _invoke("--ply", d / "scene.ply", "--data", data, "--view", 99, "--out", out)
    _one_line_error(bad, "--view 99")


def test_turntable_writes_a_readable_mp4(ti32, scene, read_video):
    _, d = scene
    out = d / "orbit.mp4"
    result = _invoke("--ply", d / "scene.ply", "--camera", d / "cam.json", "--turntable", 3, "--out", out, "--fps", 12)
    assert result.exit_code == 0, result.output
    frames = read_video(out)
    assert len(frames) == 3 and frames[0].shape == (H, W, 3)
    assert frames[0].std() > 5
    assert sorted(p.name for p in d.iterdir()) == ["cam.json", "orbit.mp4", "scene.ply"]


@pytest.mark.parametrize(
    ("args", "expected"),
    [
        (["--ply", "{d}/missing.ply", "--camera", "{d}/cam.json", "--out", "{d}/x.png"], "not found"),
        (["--ply", "{d}/scene.ply", "--camera", "{d}/bad.json", "--out", "{d}/x.png"], "malformed JSON"),
        (["--ply", "{d}/scene.ply", "--camera", "{d}/missing.json", "--out", "{d}/x.png"], "camera file not found"),
        (["--ply", "{d}/scene.ply", "--camera", "{d}/cam.json", "--out", "{d}/x.gif"], ".png"),
        (["--ply", "{d}/scene.ply", "--camera", "{d}/cam.json", "--out", "{d}/x.mp4"], "--turntable"),
        (["--ply", "{d}/scene.ply", "--camera", "{d}/cam.json", "--out", "{d}/x.png", "--turntable", "3"], ".mp4"),
        (["--camera", "{d}/cam.json", "--out", "{d}/x.png"], "give a RUN folder or --ply"),
        (["{d}", "--camera", "{d}/cam.json", "--out", "{d}/x.png"], "no gaussians.ply"),
        (["{d}/scene.ply", "--camera", "{d}/cam.json", "--out", "{d}/x.png"], "use --ply"),
        (["--ply", "{d}/scene.ply", "--out", "{d}/x.png"], "no camera"),
        (["--ply", "{d}/scene.ply", "--camera", "{d}/cam.json", "--view", "2", "--out", "{d}/x.png"], "need --data"),
        (["--ply", "{d}/scene.ply", "--camera", "{d}/cam.json", "--out", "{d}/x.png", "--background", "2"], "r,g,b"),
        (["--ply", "{d}/cam.json", "--camera", "{d}/cam.json", "--out", "{d}/x.png"], "not a readable PLY"),
        (["--ply", "{d}/scene.ply", "--data", "{d}/nodata", "--out", "{d}/x.png"], "dataset folder not found"),
    ],
    ids=[
        "missing-ply", "malformed-camera", "missing-camera", "gif", "mp4-without-turntable", "turntable-png",
        "no-input", "not-a-run", "ply-as-run", "no-camera", "view-without-data", "bad-background", "not-ply",
        "missing-data",
    ],
)  # fmt: skip
def test_bad_input_is_one_line_error(scene, args, expected):
    _, d = scene
    (d / "bad.json").write_text("{not json")
    result = _invoke(*[a.format(d=d) for a in args])
    _one_line_error(result, expected)
    assert not (d / "x.png").exists()


def test_help():
    result = CliRunner().invoke(cli, ["render", "--help"])
    assert result.exit_code == 0
    for option in ("--ply", "--camera", "--data", "--view", "--turntable", "--device", "--precision", "--out"):
        assert option in result.output
