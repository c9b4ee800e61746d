"""Similarity transforms: composition and inverse, every kind of quantity, rotations parsed from the command line,
and one-line errors for what is not a similarity."""

from __future__ import annotations

import math

import numpy as np
import pytest

from causalgs.errors import CausalGSError
from causalgs.similarity import Similarity, parse_rotation, random_rotation, rotation_between


def test_inverse_and_composition():
    a = Similarity.make(random_rotation(1), 0.3, [1.0, 2.0, 3.0])
    b = Similarity.make(random_rotation(2), 4.0, [0.0, -1.0, 0.5])
    x = np.random.default_rng(0).normal(size=(10, 3))
    assert np.allclose(a.inverse().points(a.points(x)), x)
    assert np.allclose(a.then(b).points(x), b.points(a.points(x)))
    assert np.allclose(a.then(b).matrix(), b.matrix() @ a.matrix())
    assert Similarity.from_json(a.to_json()).to_json() == a.to_json()


def test_quantities_transform_consistently():
    """A rigid body's motion x(t) = c + Q(t) r + v t re-posed: positions, velocities (finite differences of the
    positions), spins, orientations, deformation gradients and planes all follow the one map."""
    s = Similarity.make(random_rotation(3), 2.5, [0.1, 0.2, 0.3])
    w = np.array([0.3, -1.0, 2.0])
    v = np.array([1.0, 0.0, -0.5])
    r = np.array([0.2, 0.1, 0.0])

    def x(t):
        th = np.linalg.norm(w) * t
        from causalgs.similarity import axis_angle

        return axis_angle(w, th) @ r + v * t

    dt = 1e-6
    vel = (s.points(x(dt)) - s.points(x(-dt))) / (2 * dt)
    assert np.allclose(vel, s.vectors(v + np.cross(w, r)), atol=1e-6)
    assert np.allclose(s.vectors(np.cross(w, r)), np.cross(s.directions(w), s.vectors(r)))
    Q = random_rotation(5)
    assert np.allclose(s.orientations(Q), s.R @ Q)
    F = np.diag([1.1, 0.9, 1.0])
    dx = np.array([0.01, 0.02, -0.01])
    assert np.allclose(s.deformations(F) @ s.vectors(dx), s.vectors(F @ dx))
    n, d = s.plane([0.0, 0.0, 2.0], 0.4)  # z = 0.2
    p = s.points([0.7, -0.3, 0.2])
    assert math.isclose(float(n @ p), d, abs_tol=1e-12) and math.isclose(float(np.linalg.norm(n)), 1.0)
    c2w = np.eye(4)
    c2w[:3, :3], c2w[:3, 3] = Q, [1.0, 2.0, 3.0]
    out = s.camera_to_world(c2w)
    assert np.allclose(out[:3, :3] @ out[:3, :3].T, np.eye(3)) and np.allclose(out[:3, 3], s.points(c2w[:3, 3]))
    assert np.allclose(s.quaternion(), Similarity.make(s.R).quaternion())
    q = Similarity.make(Q).quaternion()  # the body's orientation, turned as a quaternion and as a matrix
    assert np.allclose(Similarity.make(s.orientations(Q)).quaternion(), s.quaternions(q))


def test_rotation_between_and_parse():
    for a, b in (([0, 0, 1], [0, 0, 1]), ([0, 0, 1], [0, 0, -1]), ([1, 2, 3], [-3, 0, 1])):
        R = rotation_between(a, b)
        assert np.allclose(R @ (np.asarray(a) / np.linalg.norm(a)), np.asarray(b) / np.linalg.norm(b))
        assert np.allclose(R @ R.T, np.eye(3)) and np.isclose(np.linalg.det(R), 1.0)
    assert np.allclose(parse_rotation("z:90") @ [1, 0, 0], [0, 1, 0])
    assert np.allclose(parse_rotation("1,1,0:180") @ [1, 0, 0], [0, 1, 0])
    assert np.allclose(parse_rotation("random", seed=3), random_rotation(3))
    assert np.allclose(parse_rotation("0,-1,0,1,0,0,0,0,1"), parse_rotation("z:90"))


@pytest.mark.parametrize("text", ["q:90", "z:ninety", "0,0,0:30", "1,2"])
def test_a_malformed_rotation_is_a_one_line_error(text):
    with pytest.raises(CausalGSError, match="--rotate"):
        parse_rotation(text)


@pytest.mark.parametrize(("R", "scale", "match"), [
    (np.diag([1.0, 1.0, 2.0]), 1.0, "not a rotation"),
    (np.diag([1.0, 1.0, -1.0]), 1.0, "not a rotation"),
    (np.eye(3), 0.0, "scale = 0.0"),
    (np.eye(3), -2.0, "scale = -2.0"),
    (np.eye(3), float("nan"), "scale = nan"),
])  # fmt: skip
def test_what_is_not_a_similarity_is_refused(R, scale, match):
    with pytest.raises(CausalGSError, match=match):
        Similarity.make(R, scale)
