"""Hand-computed hits of the analytic ray caster: the synthetic ground truth is only as good as these."""

from __future__ import annotations

import numpy as np
import pytest

from causalgs.synth.raycast import Box, Cylinder, RigidBody, Sphere, cast, rotation_exp


def test_sphere_hit_distance_and_normal():
    o, d = np.array([[0.0, 0.0, -5.0]]), np.array([[0.0, 0.0, 1.0]])
    h = cast(o, d, [Sphere((0.0, 0.0, 0.0), 1.0, part=3)])
    assert h.t[0] == pytest.approx(4.0)
    np.testing.assert_allclose(h.normal[0], [0.0, 0.0, -1.0], atol=1e-12)
    np.testing.assert_allclose(h.point[0], [0.0, 0.0, -1.0], atol=1e-12)
    assert h.part[0] == 3 and h.obj[0] == 1


def test_sphere_oblique_hit_and_miss():
    # A ray at height 0.6 grazes into the unit sphere at z = -0.8: t = 5 - 0.8.
    o = np.array([[0.0, 0.6, -5.0], [0.0, 1.2, -5.0], [0.0, 0.0, 5.0]])
    d = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])  # last: sphere behind the origin
    h = cast(o, d, [Sphere((0.0, 0.0, 0.0), 1.0)])
    assert h.t[0] == pytest.approx(4.2)
    np.testing.assert_allclose(h.normal[0], [0.0, 0.6, -0.8], atol=1e-12)
    assert np.isinf(h.t[1]) and np.isinf(h.t[2])
    assert h.part[1] == -1 and h.obj[1] == 0


def test_oriented_box_hit():
    # A box of half extents (2, 0.5, 0.5) turned 90 degrees about z: its long axis lies along world y.
    box = Box((1.0, 0.0, 0.0), (2.0, 0.5, 0.5), rotation_exp([0.0, 0.0, np.pi / 2]))
    o = np.array([[1.0, 1.5, 5.0], [5.0, 0.0, 0.0], [4.0, 0.0, 5.0]])
    d = np.array([[0.0, 0.0, -1.0], [-1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
    h = cast(o, d, [box])
    assert h.t[0] == pytest.approx(4.5)  # top face z = 0.5, inside the long axis (|y| = 1.5 < 2)
    np.testing.assert_allclose(h.normal[0], [0.0, 0.0, 1.0], atol=1e-12)
    assert h.t[1] == pytest.approx(3.5)  # side face x = 1.5
    np.testing.assert_allclose(h.normal[1], [1.0, 0.0, 0.0], atol=1e-12)
    assert np.isinf(h.t[2])  # x = 4 is beyond the turned box's half width 0.5


def test_axis_parallel_ray_on_box_does_not_give_nan():
    h = cast(np.array([[0.2, 0.3, -3.0]]), np.array([[0.0, 0.0, 1.0]]), [Box((0, 0, 0), (1.0, 1.0, 1.0))])
    assert h.t[0] == pytest.approx(2.0)
    assert np.all(np.isfinite(h.normal))


def test_cylinder_side_and_cap():
    cyl = Cylinder((0.0, 0.0, 0.0), 0.5, 1.0)  # axis z, |z| <= 1
    o = np.array([[3.0, 0.0, 0.3], [0.1, 0.0, 4.0], [3.0, 0.0, 1.5]])
    d = np.array([[-1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [-1.0, 0.0, 0.0]])
    h = cast(o, d, [cyl])
    assert h.t[0] == pytest.approx(2.5)
    np.testing.assert_allclose(h.normal[0], [1.0, 0.0, 0.0], atol=1e-12)
    assert h.t[1] == pytest.approx(3.0)
    np.testing.assert_allclose(h.normal[1], [0.0, 0.0, 1.0], atol=1e-12)
    assert np.isinf(h.t[2])


def test_union_takes_the_nearest_primitive():
    prims = [Sphere((0.0, 0.0, 0.0), 1.0, part=0), Box((0.0, 0.0, -1.5), (0.2, 0.2, 0.2), part=1)]
    h = cast(np.array([0.0, 0.0, -5.0]), np.array([[0.0, 0.0, 1.0], [0.0, 0.05, 1.0]]), prims)  # shared origin
    assert h.t[0] == pytest.approx(3.3)
    assert list(h.part) == [1, 1]


def test_rigid_body_pose():
    """Casting a posed body equals casting the primitives moved by hand; the hit point stays in body coordinates."""
    body = RigidBody([Box((0.5, 0.0, 0.0), (0.5, 0.1, 0.1))])
    R, c = rotation_exp([0.0, 0.0, np.pi / 2]), np.array([0.0, 0.0, 1.0])  # the box now lies along world +y
    o, d = np.array([0.0, 0.7, 5.0]), np.array([[0.0, 0.0, -1.0], [0.0, 0.0, 1.0]])
    h = body.cast(o, d, R, c)
    assert h.t[0] == pytest.approx(5.0 - 1.1)
    np.testing.assert_allclose(h.normal[0], [0.0, 0.0, 1.0], atol=1e-12)
    np.testing.assert_allclose(h.point[0], [0.7, 0.0, 0.1], atol=1e-12)
    assert np.isinf(h.t[1])


def test_rotation_exp_is_a_rotation_about_its_axis():
    w = np.array([0.3, -0.4, 1.2])
    R = rotation_exp(w)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(R @ w, w, atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)


def test_surface_samples_lie_on_the_visible_surface():
    body = RigidBody([Sphere((0.0, 0.0, 0.0), 0.5, part=0), Box((0.6, 0.0, 0.0), (0.5, 0.1, 0.1), part=1)])
    p, n, part = body.sample_surface(np.random.default_rng(0), 500)
    assert len(p) == 500 and set(part.tolist()) == {0, 1}
    assert not body.contains(p).any()
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-12)
