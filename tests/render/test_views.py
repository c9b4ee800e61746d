"""Orbit cameras, rendering a camera to uint8, camera files and turntable videos."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from causalgs.cameras import Camera, look_at
from causalgs.errors import CausalGSError, DataError
from causalgs.render import rasterize
from causalgs.render.views import (
    load_camera_json,
    orbit_cameras,
    orbit_center,
    render_camera,
    render_turntable,
    to_uint8,
    write_video,
)

W, H = 32, 24


def _camera(eye=(0.0, -4.0, 1.5), target=(0.0, 0.0, 0.0)) -> Camera:
    return Camera.from_blender(look_at(eye, target), W, H, fov_x=0.9)


def test_orbit_keeps_distance_elevation_and_intrinsics():
    cam, center = _camera(), np.array([0.1, 0.2, -0.1])
    cams = orbit_cameras(cam, center, 4)
    assert len(cams) == 4
    d0 = cam.center - center
    azimuths = []
    for c in cams:
        d = c.center - center
        assert np.linalg.norm(d) == pytest.approx(np.linalg.norm(d0))
        assert d[2] == pytest.approx(d0[2])  # same elevation (up = +z)
        np.testing.assert_array_equal(c.K, cam.K)
        assert (c.width, c.height) == (W, H)
        uv, depth = c.project(center)  # every camera looks at the centre
        np.testing.assert_allclose(uv, [W / 2, H / 2], atol=1e-9)
        assert depth > 0
        up_in_image = c.project(center + np.array([0.0, 0.0, 0.1]))[0]
        assert up_in_image[1] < H / 2  # +z points up in the image: no roll, not upside down
        azimuths.append(math.atan2(d[1], d[0]))
    steps = np.mod(np.diff(azimuths), 2 * math.pi)
    np.testing.assert_allclose(steps, math.pi / 2, atol=1e-9)  # evenly spaced, counter-clockwise from above
    np.testing.assert_allclose(cams[0].center, cam.center, atol=1e-12)


def test_first_orbit_camera_is_the_camera_when_it_looks_at_the_centre():
    cam = _camera(target=(0.2, 0.0, 0.1))
    first = orbit_cameras(cam, [0.2, 0.0, 0.1], 3)[0]
    np.testing.assert_allclose(first.viewmat, cam.viewmat, atol=1e-12)


def test_orbit_center_modes():
    cam = _camera(target=(0.0, 0.0, 0.0))
    means = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    np.testing.assert_allclose(orbit_center(cam, means, "centroid"), [0.0, 0.0, 1.0])
    c = orbit_center(cam, means, "lookat")
    forward = cam.c2w[:3, 2]
    off = c - cam.center
    np.testing.assert_allclose(np.cross(off, forward), 0.0, atol=1e-12)  # on the viewing axis
    assert np.dot(off, forward) > 0
    behind = orbit_center(cam, np.array([[0.0, -9.0, 1.5]]), "lookat")  # the centroid behind the camera
    np.testing.assert_allclose(behind, [0.0, -9.0, 1.5])
    with pytest.raises(CausalGSError, match="not one of"):
        orbit_center(cam, means, "middle")


def test_orbit_refuses_degenerate_cameras():
    cam = _camera(eye=(0.0, -4.0, 1.5))
    with pytest.raises(CausalGSError, match="straight above"):
        orbit_cameras(cam, cam.center - [0.0, 0.0, 3.0], 4)
    with pytest.raises(CausalGSError, match="orbit centre"):
        orbit_cameras(cam, cam.center, 4)
    with pytest.raises(CausalGSError, match="at least 1"):
        orbit_cameras(cam, [0.0, 0.0, 0.0], 0)


def test_render_camera_is_rasterize_in_uint8(ti32, make_gaussians):
    g, cam, bg = make_gaussians(), _camera(), (0.1, 0.2, 0.3)
    img = render_camera(g, cam, bg)
    assert img.dtype == np.uint8 and img.shape == (H, W, 3)
    assert img.std() > 5, "the Gaussians should show"
    t = {k: torch.from_numpy(v) for k, v in g.items()}
    ref, _, _ = rasterize(
        t["means"], t["quats"], t["scales"], t["opacities"], t["sh"], torch.tensor(cam.viewmat),
        torch.tensor(cam.K), W, H, background=bg,
    )  # fmt: skip
    np.testing.assert_array_equal(img, to_uint8(ref))
    # torch inputs with gradients give the same image and no graph
    img2 = render_camera({k: v.clone().requires_grad_() for k, v in t.items()}, cam, bg)
    np.testing.assert_array_equal(img2, img)


def test_render_camera_needs_every_parameter(ti32, make_gaussians):
    g = make_gaussians(5)
    del g["sh"]
    with pytest.raises(CausalGSError, match="missing sh"):
        render_camera(g, _camera())


def test_to_uint8_rounds_and_clips():
    np.testing.assert_array_equal(to_uint8(np.array([-1.0, 0.0, 0.5, 1.0, 2.0, np.nan])), [0, 0, 128, 255, 255, 0])


def test_turntable_writes_an_mp4(ti32, tmp_path, make_gaussians, read_video):
    g, cam = make_gaussians(), _camera()
    seen = []
    out = tmp_path / "videos" / "orbit.mp4"
    cams = render_turntable(g, cam, 3, out, fps=10, progress=lambda i, n: seen.append((i, n)))
    assert seen == [(1, 3), (2, 3), (3, 3)]
    frames = read_video(out)
    assert len(frames) == 3 and frames[0].shape == (H, W, 3)
    assert [p.name for p in out.parent.iterdir()] == ["orbit.mp4"]  # no temporary file left
    # the first frame looks like the camera's own image (lossy codec: compare loosely)
    first = render_camera(g, cams[0])
    assert np.abs(frames[0][..., ::-1].astype(float) - first).mean() < 12


def test_write_video_pads_odd_sizes_and_cleans_up_on_error(tmp_path, read_video):
    frames = [np.full((7, 9, 3), 40 * i, np.uint8) for i in range(2)]
    assert write_video(tmp_path / "odd.mp4", frames, fps=5) == 2
    read = read_video(tmp_path / "odd.mp4")
    assert len(read) == 2 and read[0].shape == (8, 10, 3)
    with pytest.raises(CausalGSError, match="first was"):
        write_video(tmp_path / "bad.mp4", [frames[0], np.zeros((8, 9, 3), np.uint8)])
    with pytest.raises(CausalGSError, match="no frames"):
        write_video(tmp_path / "none.mp4", [])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["odd.mp4"]


def test_load_camera_json(tmp_path):
    cam = _camera()
    path = tmp_path / "cam.json"
    path.write_text(json.dumps({**cam.to_json(), "background": [0, 0.5, 1]}))
    back, bg = load_camera_json(path)
    np.testing.assert_allclose(back.viewmat, cam.viewmat, atol=1e-12)
    np.testing.assert_allclose(back.K, cam.K)
    assert bg == (0.0, 0.5, 1.0)
    path.write_text(json.dumps({"camera_angle_x": 0.9, "w": 8, "h": 6, "transform_matrix": np.eye(4).tolist()}))
    assert load_camera_json(path)[1] is None


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        (None, "camera file not found"),
        ("{not json", "malformed JSON"),
        ("[1, 2]", "must be a JSON object"),
        ('{"w": 8, "h": 6, "camera_angle_x": 0.9}', "missing key 'transform_matrix'"),
        ('{"w": 8, "h": 6, "camera_angle_x": 0.9, "transform_matrix": [[1]]}', "4x4"),
        ('{"w": 8, "h": 6, "fl_x": 9, "transform_matrix": %s, "background": [2, 0, 0]}', "background"),
    ],
    ids=["missing", "malformed", "not-object", "no-matrix", "bad-matrix", "bad-background"],
)
def test_bad_camera_files_are_one_line_errors(tmp_path, text, expected):
    path = tmp_path / "bad_cam.json"
    if text is not None:
        path.write_text(text.replace("%s", json.dumps(np.eye(4).tolist())))
    with pytest.raises(DataError) as info:
        load_camera_json(path)
    msg = str(info.value)
    assert "bad_cam.json" in msg and expected in msg and "\n" not in msg, msg
