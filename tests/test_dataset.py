"""The dataset reader on tiny hand-made datasets: what loads, and every way a broken one is reported in one line."""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from causalgs.cameras import fov_to_focal, look_at
from causalgs.dataset import load_dataset
from causalgs.errors import DataError
from causalgs.io import write_image
from causalgs.ply import write_points_ply
from cli.main import cli

W, H = 8, 6
FOV = 0.8
RADIUS = 3.0
PIXEL = (200, 100, 50, 64)  # the hand-made RGBA value at pixel (0, 0) of every RGBA image
CLEAR = (10, 20, 30, 0)  # ... and a fully transparent one at pixel (0, 1)


def _eye(view: int) -> np.ndarray:
    a = 2.0 * math.pi * view / 3.0
    return np.array([RADIUS * math.cos(a), RADIUS * math.sin(a), 0.5])


def _pose(view: int) -> np.ndarray:
    return look_at(_eye(view), (0.0, 0.0, 0.0))


def _rgba(seed: int, w: int = W, h: int = H) -> np.ndarray:
    img = np.random.default_rng(seed).integers(0, 256, size=(h, w, 4), dtype=np.uint8)
    img[0, 0], img[0, 1] = PIXEL, CLEAR
    return img


def _frame(root: Path, split: str, k: int, view: int, time: float, ext: str = ".png") -> dict:
    """Write the image of one frame and return its JSON entry (``file_path`` without extension for even ``k``)."""
    name = f"r_{k:03d}"
    if ext == ".jpg":  # JPEG has no alpha: write RGB
        (root / split).mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(root / split / (name + ext)), _rgba(k)[..., :3])
    else:
        write_image(root / split / (name + ext), _rgba(100 * len(split) + k))
    file_path = f"./{split}/{name}" + ("" if k % 2 == 0 else ext)
    return {"file_path": file_path, "time": time, "view": view, "frame": k, "transform_matrix": _pose(view).tolist()}


def _write_json(root: Path, split: str, obj) -> None:
    (root / f"transforms_{split}.json").write_text(json.dumps(obj))


def _edit(root: Path, split: str, fn) -> None:
    path = root / f"transforms_{split}.json"
    data = json.loads(path.read_text())
    fn(data)
    path.write_text(json.dumps(data))


@pytest.fixture
def data_dir(tmp_path) -> Path:
    """train: views 0, 1 at times 0, .25, .5; val: view 2 at .25 (a JPEG); test: views 0-2 at 1; a 10-point cloud."""
    root = tmp_path / "scene"
    train = [_frame(root, "train", 2 * t + v, v, 0.25 * t) for t in range(3) for v in range(2)]
    _write_json(root, "train", {"camera_angle_x": FOV, "fps": 24.0, "frames": train})
    _write_json(root, "val", {"camera_angle_x": FOV, "frames": [_frame(root, "val", 0, 2, 0.25, ext=".jpg")]})
    _write_json(root, "test", {"camera_angle_x": FOV, "frames": [_frame(root, "test", v, v, 1.0) for v in range(3)]})
    xyz = np.arange(30, dtype=np.float32).reshape(10, 3)
    write_points_ply(root / "points3d.ply", xyz, np.linspace(0, 1, 30).reshape(10, 3))
    return root


# ---------------------------------------------------------------------------------------------------------------------
# What loads
# ---------------------------------------------------------------------------------------------------------------------
def test_counts_times_and_sizes(data_dir):
    ds = load_dataset(data_dir)
    assert (len(ds.train), len(ds.val), len(ds.test)) == (6, 1, 3)
    np.testing.assert_array_equal(ds.times("train"), [0.0, 0.25, 0.5])
    np.testing.assert_array_equal(ds.times(), [0.0, 0.25, 0.5, 1.0])
    assert ds.image_size == (W, H)
    assert ds.fps == 24.0
    f = ds.train[3]
    assert (f.split, f.index, f.view, f.frame, f.time) == ("train", 3, 1, 3, 0.25)
    assert f.rgba.dtype == np.uint8 and f.rgba.shape == (H, W, 4)
    assert f.image.dtype == np.float32 and f.image.shape == (H, W, 3)


def test_extension_less_paths_and_jpeg(data_dir):
    ds = load_dataset(data_dir)
    assert ds.train[0].path == data_dir / "train" / "r_000.png"  # file_path "./train/r_000"
    assert ds.train[1].path.name == "r_001.png"  # file_path with its extension
    val = ds.val[0]
    assert val.path.name == "r_000.jpg" and val.rgba.shape == (H, W, 3)
    np.testing.assert_array_equal(val.alpha, np.ones((H, W), np.float32))


def test_camera_pose_and_projection(data_dir):
    cam = load_dataset(data_dir).train[1].camera  # view 1
    np.testing.assert_allclose(cam.center, _eye(1), atol=1e-9)
    assert cam.fx == pytest.approx(fov_to_focal(FOV, W)) and cam.fy == pytest.approx(cam.fx)
    assert (cam.cx, cam.cy) == (W / 2, H / 2)
    # The look-at target projects to the image centre; a point to the camera's right / up moves right / up.
    gl = _pose(1)
    right, up = gl[:3, 0], gl[:3, 1]
    uv, depth = cam.project(np.array([[0.0, 0.0, 0.0], 0.2 * right, 0.2 * up]))
    dist = np.linalg.norm(_eye(1))
    np.testing.assert_allclose(depth, dist, rtol=1e-9)
    np.testing.assert_allclose(uv[0], [W / 2, H / 2], atol=1e-9)
    np.testing.assert_allclose(uv[1], [W / 2 + cam.fx * 0.2 / dist, H / 2], atol=1e-9)
    np.testing.assert_allclose(uv[2], [W / 2, H / 2 - cam.fy * 0.2 / dist], atol=1e-9)


def test_composited_colour_is_alpha_blend(data_dir):
    bg = (0.2, 0.4, 0.6)
    f = load_dataset(data_dir, background=bg).train[0]
    a = np.float32(PIXEL[3]) / np.float32(255)
    rgb = np.array(PIXEL[:3], np.float32) / np.float32(255)
    expected = a * rgb + (np.float32(1) - a) * np.array(bg, np.float32)
    np.testing.assert_allclose(f.image[0, 0], expected, rtol=0, atol=1e-7)
    assert f.alpha[0, 0] == pytest.approx(64 / 255)


@pytest.mark.parametrize(
    ("json_bg", "arg_bg", "expected"),
    [(None, None, (1, 1, 1)), ((0, 0, 1), None, (0, 0, 1)), ((0, 0, 1), (0, 1, 0), (0, 1, 0))],
    ids=["white-default", "json", "argument-wins"],
)
def test_background_precedence(data_dir, json_bg, arg_bg, expected):
    if json_bg is not None:
        _edit(data_dir, "train", lambda d: d.update(background=list(json_bg)))
    ds = load_dataset(data_dir, background=arg_bg)
    np.testing.assert_array_equal(ds.background, np.array(expected, np.float32))
    np.testing.assert_array_equal(ds.test[0].background, ds.background)
    np.testing.assert_array_equal(ds.train[0].image[0, 1], np.array(expected, np.float32))  # the CLEAR pixel


def test_fl_x_form_and_per_frame_override(data_dir):
    def to_fl(d):
        del d["camera_angle_x"]
        d.update(fl_x=10.0, fl_y=12.0, cx=4.5, cy=3.25, w=W, h=H)
        d["frames"][0]["fl_x"] = 20.0  # a frame's own focal replaces fl_x *and* fl_y

    _edit(data_dir, "train", to_fl)
    ds = load_dataset(data_dir)
    np.testing.assert_allclose(ds.train[1].camera.K, [[10, 0, 4.5], [0, 12, 3.25], [0, 0, 1]])
    np.testing.assert_allclose(ds.train[0].camera.K, [[20, 0, 4.5], [0, 20, 3.25], [0, 0, 1]])


def test_downscale_resizes_images_and_cameras(data_dir):
    full = load_dataset(data_dir).train[0]
    half = load_dataset(data_dir, downscale=0.5).train[0]
    assert half.rgba.shape == (3, 4, 4) and half.camera.width == 4 and half.camera.height == 3
    np.testing.assert_allclose(half.camera.K[:2], full.camera.K[:2] * 0.5)
    np.testing.assert_array_equal(half.camera.viewmat, full.camera.viewmat)
    block = full.rgba[:2, :2].astype(np.float64).mean(axis=(0, 1))  # INTER_AREA averages 2x2 blocks
    np.testing.assert_allclose(half.rgba[0, 0], block, atol=1.0)


def test_16_bit_and_grayscale_images(data_dir):
    img16 = np.zeros((H, W, 4), np.uint16)
    img16[0, 0] = (65535, 0, 32768, 65535)
    cv2.imwrite(str(data_dir / "train" / "r_000.png"), img16[..., [2, 1, 0, 3]])
    cv2.imwrite(str(data_dir / "train" / "r_001.png"), np.full((H, W), 77, np.uint8))
    ds = load_dataset(data_dir)
    f16, gray = ds.train[0], ds.train[1]
    assert f16.rgba.dtype == np.uint16
    np.testing.assert_allclose(f16.image[0, 0], [1.0, 0.0, 32768 / 65535], atol=1e-7)
    assert f16.alpha[0, 0] == 1.0 and f16.alpha[1, 1] == 0.0
    assert gray.rgba.shape == (H, W, 3)
    np.testing.assert_allclose(gray.image, 77 / 255, atol=1e-7)


def test_points_optional_splits_and_summary(data_dir):
    ds = load_dataset(data_dir)
    assert ds.points.shape == (10, 3) and ds.point_colors.shape == (10, 3)
    np.testing.assert_array_equal(ds.points[1], [3, 4, 5])
    text = ds.summary()
    for part in ("8x6", "train: 6 frames, 2 views", "val:   1 frames, 1 views", "10 points", "fps: 24"):
        assert part in text
    only_train = load_dataset(data_dir, splits=("train",))
    assert only_train.val == [] and only_train.test == [] and set(only_train.splits) == {"train", "val", "test"}
    (data_dir / "transforms_val.json").unlink()
    (data_dir / "points3d.ply").unlink()
    ds = load_dataset(data_dir)
    assert ds.val == [] and ds.points is None and ds.point_colors is None and "val:   none" in ds.summary()


# ---------------------------------------------------------------------------------------------------------------------
# Every broken dataset: DataError, one line, naming the file and the value
# ---------------------------------------------------------------------------------------------------------------------
def _frame1(key, value):
    return lambda d: d["frames"][1].__setitem__(key, value)


def _drop1(key):
    return lambda d: d["frames"][1].pop(key)


def _json(fn, split="train"):
    return lambda root: _edit(root, split, fn)


def _write(rel, data: bytes):
    return lambda root: (root / rel).write_bytes(data)


def _image(rel, img):
    return lambda root: write_image(root / rel, img)


def _scaled_pose(d):
    d["frames"][1]["transform_matrix"][0][0] = 2.0


def _nan_pose(d):
    d["frames"][1]["transform_matrix"][2][3] = float("nan")


def _ply_no_z(root):
    from plyfile import PlyData, PlyElement

    arr = np.zeros(2, dtype=[("x", "<f4"), ("y", "<f4")])
    PlyData([PlyElement.describe(arr, "vertex")]).write(str(root / "points3d.ply"))


def _ply_inf(root):
    xyz = np.zeros((4, 3), np.float32)
    xyz[2, 1] = np.inf
    arr = np.zeros(4, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4")])
    for i, k in enumerate("xyz"):
        arr[k] = xyz[:, i]
    from plyfile import PlyData, PlyElement

    PlyData([PlyElement.describe(arr, "vertex")]).write(str(root / "points3d.ply"))


TRAIN = "transforms_train.json"
ERROR_CASES = {
    # id: (change to the good dataset, load_dataset kwargs, substrings the message must contain)
    "missing-folder": (None, {}, ["dataset folder not found", "no_such_scene"]),
    "missing-train-json": (lambda r: (r / TRAIN).unlink(), {}, [TRAIN, "not found"]),
    "malformed-json": (_write(TRAIN, b'{"frames": [}'), {}, [TRAIN, "malformed JSON", "line 1"]),
    "top-level-list": (_write(TRAIN, b"[1, 2]"), {}, [TRAIN, "JSON object", "list"]),
    "frames-missing": (_json(lambda d: d.pop("frames")), {}, [TRAIN, "'frames'"]),
    "frames-not-list": (_json(lambda d: d.update(frames={"a": 1})), {}, [TRAIN, "'frames' must be a list"]),
    "frame-not-object": (_json(lambda d: d["frames"].__setitem__(1, 3)), {}, [TRAIN, "frame 1", "JSON object"]),
    "empty-split": (_json(lambda d: d.update(frames=[]), "val"), {}, ["transforms_val.json", "'frames' is empty"]),
    "missing-fov": (_json(lambda d: d.pop("camera_angle_x")), {}, [TRAIN, "'camera_angle_x'", "fl_x", "frame 0"]),
    "missing-file_path": (_json(_drop1("file_path")), {}, [TRAIN, "frame 1", "'file_path'"]),
    "missing-time": (_json(_drop1("time")), {}, [TRAIN, "frame 1", "'time'"]),
    "missing-matrix": (_json(_drop1("transform_matrix")), {}, [TRAIN, "frame 1", "'transform_matrix'"]),
    "time-not-number": (_json(_frame1("time", "soon")), {}, [TRAIN, "frame 1 time", "'soon'", "not a number"]),
    "time-bool": (_json(_frame1("time", True)), {}, [TRAIN, "frame 1 time", "True"]),
    "fov-not-number": (_json(lambda d: d.update(camera_angle_x="wide")), {}, [TRAIN, "camera_angle_x", "'wide'"]),
    "fov-negative": (_json(lambda d: d.update(camera_angle_x=-1)), {}, [TRAIN, "camera_angle_x = -1", "positive"]),
    "fl_x-nan": (_json(_frame1("fl_x", float("nan"))), {}, [TRAIN, "frame 1 fl_x", "not finite"]),
    "time-above-1": (_json(_frame1("time", 1.5)), {}, [TRAIN, "frame 1 time = 1.5", "[0, 1]"]),
    "time-negative-test": (_json(_frame1("time", -0.1), "test"), {}, ["transforms_test.json", "frame 1 time = -0.1"]),
    "time-nan": (_json(_frame1("time", float("nan"))), {}, [TRAIN, "frame 1 time", "not finite"]),
    "matrix-nan": (_json(_nan_pose), {}, [TRAIN, "frame 1 transform_matrix", "non-finite"]),
    "matrix-not-rigid": (_json(_scaled_pose), {}, [TRAIN, "frame 1 transform_matrix", "not rigid"]),
    "matrix-shape": (_json(_frame1("transform_matrix", [[1, 0], [0, 1]])), {}, [TRAIN, "frame 1", "[2, 2]"]),
    "view-negative": (_json(_frame1("view", -2)), {}, [TRAIN, "frame 1 view = -2"]),
    "file_path-not-str": (_json(_frame1("file_path", 7)), {}, [TRAIN, "frame 1 file_path = 7"]),
    "image-missing": (lambda r: (r / "train/r_001.png").unlink(), {}, [TRAIN, "frame 1", "r_001", "not found"]),
    "image-corrupt": (_write("train/r_001.png", b"\x89PNG garbage"), {}, ["r_001.png", "unreadable", "frame 1"]),
    "image-empty": (_write("train/r_002.png", b""), {}, ["r_002.png", "unreadable"]),
    "size-mismatch": (
        _image("test/r_002.png", _rgba(0, w=10)),
        {},
        ["r_002.png is 10x6 but the other images are 8x6"],
    ),
    "json-wh-mismatch": (_json(lambda d: d.update(w=16, h=6)), {}, ["r_000.png is 8x6", TRAIN, "w=16"]),
    "downscale-zero": (None, {"downscale": 0.0}, ["downscale = 0", "(0, 1]"]),
    "downscale-above-1": (None, {"downscale": 1.5}, ["downscale = 1.5"]),
    "downscale-nan": (None, {"downscale": float("nan")}, ["downscale = nan"]),
    "downscale-str": (None, {"downscale": "half"}, ["downscale = 'half'"]),
    "background-arg-range": (None, {"background": (2, 0, 0)}, ["background argument = (2, 0, 0)", "[0, 1]"]),
    "background-arg-str": (None, {"background": "red"}, ["background argument = 'red'"]),
    "background-json": (_json(lambda d: d.update(background=[1, 1])), {}, [TRAIN, "background = [1, 1]"]),
    "background-disagree": (
        _json(lambda d: d.update(background=[0, 0, 0]), "test"),
        {"background": None},
        ["transforms_test.json: background = [0.0, 0.0, 0.0] differs", "[1.0, 1.0, 1.0]"],
    ),
    "fps-negative": (_json(lambda d: d.update(fps=-3)), {}, [TRAIN, "fps = -3"]),
    "ply-not-ply": (_write("points3d.ply", b"not a ply at all\n"), {}, ["points3d.ply", "not a readable PLY"]),
    "ply-no-z": (_ply_no_z, {}, ["points3d.ply", "'z'"]),
    "ply-non-finite": (_ply_inf, {}, ["points3d.ply", "non-finite", "vertex 2"]),
}


def _break(root: Path, case: str) -> Path:
    change = ERROR_CASES[case][0]
    if case == "missing-folder":
        return root.parent / "no_such_scene"
    if case == "background-disagree":  # needs a background in train too, different from test's
        _edit(root, "train", lambda d: d.update(background=[1, 1, 1]))
    if change is not None:
        change(root)
    return root


@pytest.mark.parametrize("case", list(ERROR_CASES))
def test_broken_dataset_raises_one_line_data_error(data_dir, case):
    _, kwargs, expected = ERROR_CASES[case]
    root = _break(data_dir, case)
    with pytest.raises(DataError) as info:
        load_dataset(root, **kwargs)
    msg = str(info.value)
    assert "\n" not in msg and "Traceback" not in msg
    for part in expected:
        assert part in msg, f"{part!r} not in {msg!r}"


# ---------------------------------------------------------------------------------------------------------------------
# The command line
# ---------------------------------------------------------------------------------------------------------------------
def test_cli_info_on_broken_dataset_prints_one_error_line(data_dir):
    _edit(data_dir, "train", _frame1("time", 1.5))
    result = CliRunner().invoke(cli, ["info", str(data_dir)])
    assert result.exit_code != 0
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("Error:") and "Traceback" not in result.output
    assert "transforms_train.json: frame 1 time = 1.5" in lines[0]


def test_cli_info_on_good_dataset_prints_summary(data_dir):
    result = CliRunner().invoke(cli, ["info", str(data_dir), "--downscale", "0.5"])
    assert result.exit_code == 0, result.output
    assert "4x3" in result.output and "train: 6 frames" in result.output and "test:  3 frames" in result.output
