"""The physics frame from a scene's evidence: free flight (a parabola's acceleration), the static scene's dominant
plane, both, neither; in any frame and scale."""

from __future__ import annotations

import math

import numpy as np
import pytest

from causalgs.errors import CausalGSError
from causalgs.model.upright import FrameConfig, dominant_plane, free_flight, infer_upright
from causalgs.similarity import Similarity, random_rotation

FPS = 30.0


def bouncing(frames: int = 67, restitution: float = 0.8, g: float = 9.8, noise: float = 0.0, seed: int = 0):
    """A ball's centre (z up, metres): thrown up and sideways from 0.5 m, bouncing on z = 0.1 with ``restitution``,
    plus Gaussian noise of ``noise`` metres."""
    rng = np.random.default_rng(seed)
    x, v = np.array([0.0, 0.0, 0.5]), np.array([0.4, -0.2, 1.0])
    dt, sub = 1.0 / FPS, 100
    out = []
    for _ in range(frames):
        out.append(x.copy())
        for _ in range(sub):
            v = v + np.array([0.0, 0.0, -g]) * dt / sub
            x = x + v * dt / sub
            if x[2] < 0.1 and v[2] < 0:
                v[2] = -restitution * v[2]
    return np.asarray(out) + noise * rng.normal(size=(frames, 3))


def sliding(frames: int = 67, decel: float = 3.0):
    """A box's centre sliding on the floor to rest under friction (z up)."""
    t = np.arange(frames) / FPS
    v0 = 2.0
    s = np.where(t < v0 / decel, v0 * t - 0.5 * decel * t * t, v0 * v0 / (2 * decel))
    return np.stack([s, 0.2 * np.ones_like(s), 0.1 * np.ones_like(s)], 1)


def floor_points(n: int = 3000, seed: int = 0):
    rng = np.random.default_rng(seed)
    floor = np.c_[rng.uniform(-1, 1, (n, 2)), 0.002 * rng.normal(size=n)]
    clutter = rng.uniform(-1, 1, (n // 5, 3)) * [1, 1, 0.5] + [0, 0, 0.5]
    return np.concatenate([floor, clutter])


CAMERAS = np.array([[2.0, 0.0, 1.0], [-2.0, 0.5, 1.2], [0.0, 2.0, 0.8]])


@pytest.mark.parametrize("seed", [0, 1])
def test_free_flight_finds_gravity_between_bounces_in_any_frame(seed):
    sim = Similarity.make(random_rotation(seed), 0.3 if seed else 3.0, [1.0, -2.0, 0.5])
    track = sim.points(bouncing(noise=0.0005))
    f = free_flight(track[:, None], FPS, size=3.0 * sim.scale)
    assert f is not None and f.flights >= 2
    g_true = sim.vectors([0.0, 0.0, -9.8])
    assert np.linalg.norm(f.g - g_true) < 0.01 * np.linalg.norm(g_true)


def test_no_free_flight_at_rest_or_in_a_slow_drift():
    rest = np.tile([0.1, 0.2, 0.3], (67, 1)) + 1e-4 * np.random.default_rng(0).normal(size=(67, 3))
    t = np.arange(67)[:, None] / FPS
    drift = np.array([0.0, 0.0, 0.5]) + 0.005 * t**2 * np.array([1.0, 0.0, 0.0])  # 0.01 m/s²: 2.4 cm in 2.2 s
    assert free_flight(np.stack([rest, drift], 1), FPS, size=1.5) is None


def test_a_floor_plane_is_found_and_faces_the_cameras():
    sim = Similarity.make(random_rotation(4), 2.0, [0.3, 0.0, -1.0])
    p = dominant_plane(sim.points(floor_points()), sim.points(CAMERAS).mean(0))
    assert p is not None and p.share > 0.7
    up = sim.directions([0.0, 0.0, 1.0])
    assert math.degrees(math.acos(min(1.0, p.normal @ up))) < 0.3
    assert dominant_plane(np.random.default_rng(0).uniform(-1, 1, (2000, 3)), np.zeros(3)) is None


def test_up_from_the_plane_and_gravity_from_free_flight():
    sim = Similarity.make(random_rotation(7), 0.3, [0.0, 1.0, 0.0])
    tracks = np.stack([sim.points(bouncing(noise=0.0005)), sim.points(sliding())], 1)
    u = infer_upright(sim.points(floor_points()), tracks, FPS, sim.points(CAMERAS), 3.0 * sim.scale, FrameConfig())
    up = sim.directions([0.0, 0.0, 1.0])
    assert u.source == "plane+flight"
    assert math.degrees(math.acos(min(1.0, u.up @ up))) < 0.5
    assert abs(u.gravity - 9.8 * sim.scale) < 0.01 * 9.8 * sim.scale
    # the inferred similarity takes the data back to z up, 9.8 units/s² (the original frame, up to a turn about z)
    back = sim.then(u.similarity())
    assert np.allclose(back.directions([0.0, 0.0, 1.0]), [0.0, 0.0, 1.0], atol=0.01) and abs(back.scale - 1) < 0.01


def test_flight_alone_plane_alone_given_and_neither():
    sim = Similarity.make(random_rotation(2), 1.5)
    ball = sim.points(bouncing(noise=0.0005))[:, None]
    noise = np.random.default_rng(1).uniform(-1, 1, (500, 3))
    up = sim.directions([0.0, 0.0, 1.0])
    u = infer_upright(noise, ball, FPS, CAMERAS, 3.0, FrameConfig())
    assert u.source == "flight" and u.up @ up > math.cos(math.radians(1.0))
    u = infer_upright(sim.points(floor_points()), np.zeros(0), FPS, sim.points(CAMERAS), 3.0, FrameConfig())
    assert u.source == "plane" and u.gravity is None and u.similarity().scale == 1.0 and u.notes
    u = infer_upright(noise, ball, FPS, CAMERAS, 3.0, FrameConfig(up=(0.0, 1.0, 0.0), gravity=4.0))
    assert u.source == "given" and np.allclose(u.up, [0, 1, 0]) and u.gravity == 4.0
    with pytest.raises(CausalGSError, match="cannot infer the up direction.*frame.up"):
        infer_upright(noise, np.zeros(0), FPS, CAMERAS, 3.0, FrameConfig())


def test_sliding_on_the_floor_is_not_taken_for_gravity():
    """More frames of sliding than of flight: with the floor found, only accelerations along its normal count."""
    tracks = np.stack([bouncing(frames=140), sliding(frames=140), sliding(frames=140) + np.array([0, 0.3, 0])], 1)
    u = infer_upright(floor_points(), tracks, FPS, CAMERAS, 3.0, FrameConfig())
    assert u.source == "plane+flight" and abs(u.gravity - 9.8) < 0.1
    assert free_flight(tracks[:, 1:], FPS, 3.0) is not None  # without the floor, sliding alone would pass


@pytest.mark.parametrize("bad", [{"up": (0.0, 0.0, 0.0)}, {"up": (1.0, 2.0)}, {"gravity": -1.0}])
def test_bad_frame_settings_are_one_line_errors(bad):
    with pytest.raises(CausalGSError, match="frame"):
        FrameConfig(**bad)


def test_with_a_floor_and_only_sliding_up_is_the_floors():
    """A steady acceleration across the floor (a box sliding to rest) is never taken for gravity: up comes from the
    floor, gravity's magnitude is not measured."""
    tracks = np.stack([sliding(frames=140), sliding(frames=140) + np.array([0, 0.3, 0])], 1)
    assert free_flight(tracks, FPS, 3.0) is not None  # alone, the sliding would pass for a flight
    u = infer_upright(floor_points(), tracks, FPS, CAMERAS, 3.0, FrameConfig())
    assert u.source == "plane" and u.up @ [0, 0, 1] > 0.999 and u.gravity is None
    assert any("sliding or rolling" in n for n in u.notes)


def test_flight_along_joins_the_pieces_of_one_flight_and_not_two_flights():
    """Segments found on smoother tracks: the pieces of one parabola (split by a wobble, a few frames apart) are
    joined and give g exactly; two flights with a bounce between them stay two (one parabola through both would
    bend at the contact) and give g exactly as well; with noise, the joined flight gives g within 3%."""
    from causalgs.model.upright import flight_along

    fps, g = 60.0, np.array([0.0, 0.0, -9.8])
    t = np.arange(40) / fps
    one = (np.array([0.1, 0.2, 0.3]) + np.outer(t, [0.5, 0.0, 3.0]) + 0.5 * np.outer(t * t, g))[:, None]
    f = flight_along(one, [(0, 2, 8), (0, 11, 16), (0, 17, 23), (0, 22, 30)], fps)
    assert f.segments == [(0, 2, 30)] and np.allclose(f.g, g, atol=1e-6)
    b = t - 0.3  # a bounce at t = 0.3 s (z = 0.659): the vertical velocity turns from -0.94 to +2 m/s
    z = np.where(t < 0.3, 0.5 + 2.0 * t - 4.9 * t * t, 0.659 + 2.0 * b - 4.9 * b * b)
    two = np.stack([0.2 * t, 0.0 * t, z], 1)[:, None]
    f = flight_along(two, [(0, 0, 16), (0, 20, 39)], fps)
    assert f.segments == [(0, 0, 16), (0, 20, 39)] and np.allclose(f.g, g, atol=1e-6)
    noisy = one + np.random.default_rng(0).normal(0.0, 0.004, one.shape)
    f = flight_along(noisy, [(0, 2, 8), (0, 11, 16), (0, 17, 23), (0, 22, 30)], fps)
    assert f.segments == [(0, 2, 30)] and abs(-f.g[2] / 9.8 - 1) < 0.03
    assert flight_along(one, [], fps) is None
