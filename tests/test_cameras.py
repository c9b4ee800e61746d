from __future__ import annotations

import math

import numpy as np
import pytest

from causalgs.cameras import Camera, check_rigid, focal_to_fov, fov_to_focal, look_at, opengl_to_opencv
from causalgs.errors import DataError

# A 100x80 camera with a 90° horizontal field of view: fx = fy = 50, principal point (50, 40).
FOV = math.pi / 2


def gl_identity_camera() -> Camera:
    """OpenGL camera at the origin looking down -z, y up (Blender's default pose)."""
    return Camera.from_blender(np.eye(4), 100, 80, fov_x=FOV)


def test_focal_and_fov():
    assert fov_to_focal(FOV, 100) == pytest.approx(50.0)
    assert focal_to_fov(50.0, 100) == pytest.approx(FOV)


def test_opengl_to_opencv_flips_camera_y_and_z():
    c2w = look_at([3.0, 1.0, 2.0], [0.0, 0.0, 0.0])
    cv = opengl_to_opencv(c2w)
    np.testing.assert_allclose(cv[:3, 0], c2w[:3, 0])
    np.testing.assert_allclose(cv[:3, 1], -c2w[:3, 1])
    np.testing.assert_allclose(cv[:3, 2], -c2w[:3, 2])
    np.testing.assert_allclose(cv[:3, 3], c2w[:3, 3])
    np.testing.assert_allclose(opengl_to_opencv(cv), c2w)  # its own inverse


def test_intrinsics_by_hand():
    cam = gl_identity_camera()
    np.testing.assert_allclose(cam.K, [[50, 0, 50], [0, 50, 40], [0, 0, 1]])
    assert cam.fov_x == pytest.approx(FOV)
    np.testing.assert_allclose(cam.center, 0.0, atol=1e-15)


def test_projection_by_hand():
    cam = gl_identity_camera()
    pts = np.array([[0.0, 0.0, -2.0], [1.0, 0.0, -2.0], [0.0, 1.0, -2.0], [0.0, 0.0, 3.0]])
    uv, depth = cam.project(pts)
    np.testing.assert_allclose(depth, [2.0, 2.0, 2.0, -3.0])
    np.testing.assert_allclose(uv[0], [50.0, 40.0])  # on the optical axis: the principal point
    np.testing.assert_allclose(uv[1], [75.0, 40.0])  # right: u = cx + fx * 1/2
    np.testing.assert_allclose(uv[2], [50.0, 15.0])  # world up is image up: v = cy - fy * 1/2
    assert np.isnan(uv[3]).all()  # behind the camera


def test_world_to_camera_of_a_translated_camera():
    c2w = np.eye(4)
    c2w[:3, 3] = [1.0, 2.0, 3.0]
    cam = Camera.from_blender(c2w, 100, 80, fov_x=FOV)
    np.testing.assert_allclose(cam.world_to_camera([1.0, 2.0, 0.0]), [0.0, 0.0, 3.0])
    np.testing.assert_allclose(cam.world_to_camera([2.0, 3.0, 3.0]), [1.0, -1.0, 0.0])
    np.testing.assert_allclose(cam.center, [1.0, 2.0, 3.0])


def test_look_at_sees_its_target_at_the_principal_point():
    cam = Camera.from_blender(look_at([4.0, -3.0, 2.0], [0.5, 0.5, 0.0]), 64, 48, fov_x=0.8)
    uv, depth = cam.project(np.array([0.5, 0.5, 0.0]))
    np.testing.assert_allclose(uv, [32.0, 24.0], atol=1e-9)
    assert depth == pytest.approx(np.linalg.norm([3.5, -3.5, 2.0]))
    # The world's +z (the up vector) projects upwards in the image.
    uv_up, _ = cam.project(np.array([0.5, 0.5, 0.3]))
    assert uv_up[1] < 24.0


def test_rays_round_trip_to_pixel_centres():
    cam = Camera.from_blender(look_at([2.0, 2.0, 1.0], [0.0, 0.0, 0.0]), 16, 12, fov_x=0.9)
    o, d = cam.rays()
    assert o.shape == d.shape == (12, 16, 3)
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0)
    uv, _depth = cam.project(o + 2.5 * d)
    np.testing.assert_allclose(uv, cam.pixel_centers(), atol=1e-9)
    assert uv[0, 0].tolist() == pytest.approx([0.5, 0.5])
    # The ray through the principal point is the viewing direction.
    _, d0 = cam.rays(np.array([cam.cx, cam.cy]))
    np.testing.assert_allclose(d0, cam.c2w[:3, 2])


def test_scaled_camera_matches_resized_image():
    cam = gl_identity_camera()
    half = cam.scaled(0.5)
    assert (half.width, half.height) == (50, 40)
    np.testing.assert_allclose(half.K, [[25, 0, 25], [0, 25, 20], [0, 0, 1]])
    p = np.array([0.3, -0.2, -1.7])
    np.testing.assert_allclose(half.project(p)[0], 0.5 * cam.project(p)[0])


def test_json_round_trip():
    cam = Camera.from_blender(look_at([1.0, 2.0, 3.0], [0.0, 0.0, 0.0]), 64, 48, fl_x=70.0, fl_y=72.0, cx=30.0)
    back = Camera.from_json(cam.to_json())
    np.testing.assert_allclose(back.K, cam.K)
    np.testing.assert_allclose(back.viewmat, cam.viewmat, atol=1e-12)
    only_fov = {k: v for k, v in cam.to_json().items() if k in ("camera_angle_x", "w", "h", "transform_matrix")}
    assert Camera.from_json(only_fov).fx == pytest.approx(70.0)


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda d: d.pop("w"), "missing key 'w'"),
        (lambda d: d.pop("camera_angle_x"), "missing key 'camera_angle_x'"),
        (lambda d: d.update(camera_angle_x=4.0), "below pi"),
        (lambda d: d.update(w=0), "must be positive"),
        (lambda d: d.update(transform_matrix=[[1, 0], [0, 1]]), "expected a 4x4 matrix"),
    ],
)
def test_json_errors(edit, message):
    d = {"camera_angle_x": 0.8, "w": 32, "h": 32, "transform_matrix": np.eye(4).tolist()}
    edit(d)
    with pytest.raises(DataError, match=message):
        Camera.from_json(d, "cam.json")


def test_check_rigid_errors():
    m = np.eye(4)
    assert check_rigid(m, "m") is not None
    bad_last = m.copy()
    bad_last[3, 0] = 1.0
    scaled = np.diag([2.0, 1.0, 1.0, 1.0])
    mirror = np.diag([-1.0, 1.0, 1.0, 1.0])
    nan = m.copy()
    nan[0, 3] = np.nan
    cases = [
        (nan, "non-finite"),
        (bad_last, "last row"),
        (scaled, "not orthonormal"),
        (mirror, "reflection"),
        ("abc", "not a 4x4 matrix"),
        (np.eye(3), "shape"),
    ]
    for matrix, message in cases:
        with pytest.raises(DataError, match=message):
            check_rigid(matrix, "frame 0 transform_matrix")
