"""Dynamic Gaussians to particles: interior fill gives the solid's volume, Gaussians ride on their particles."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from causalgs.errors import CausalGSError
from causalgs.model.particles import build_particles


def _sphere_shell(n: int, r: float, centre, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    return np.asarray(centre) + r * d / np.linalg.norm(d, axis=1, keepdims=True)


def _box_surface(rng, n: int, size, centre, noise: float = 0.0) -> np.ndarray:
    """``n`` points on the faces of an axis-aligned box (uniform by area), each moved by N(0, noise²) per axis."""
    size = np.asarray(size, dtype=np.float64)
    areas = np.array([size[1] * size[2], size[0] * size[2], size[0] * size[1]])
    axis = rng.choice(3, size=n, p=areas / areas.sum())
    p = (rng.random((n, 3)) - 0.5) * size
    p[np.arange(n), axis] = rng.choice([-0.5, 0.5], size=n) * size[axis]
    return p + np.asarray(centre) + rng.normal(0.0, noise, p.shape)


def _mass_stats(x: np.ndarray, vol: np.ndarray):
    """Volume, centroid, per-axis standard deviation and the mean height of the lowest 5% of the volume."""
    w = vol / vol.sum()
    mu = (w[:, None] * x).sum(0)
    sd = np.sqrt((w[:, None] * (x - mu) ** 2).sum(0))
    order = np.argsort(x[:, 2])
    low = np.cumsum(w[order]) <= 0.05
    return vol.sum(), mu, sd, float((x[order, 2][low] * w[order][low]).sum() / w[order][low].sum())


def test_a_shell_of_gaussians_becomes_a_solid_ball_of_the_right_volume():
    dx = 0.05
    r = 0.2
    shell = _sphere_shell(4000, r, (0.5, 0.5, 0.5))
    static = np.random.default_rng(1).uniform(0, 1, (300, 3)) * [1, 1, 0.02]  # a floor, not simulated
    means = np.concatenate([shell, static])
    dynamic = np.arange(len(means)) < len(shell)
    true = 4 / 3 * math.pi * r**3
    p = build_particles(means, dynamic, lo=(0, 0, 0), dx=dx, budget=1000, capacity=100000)
    # The boundary voxels keep only their part inside the sphere.
    assert abs(float(p.vol.sum()) / true - 1) < 0.04, (float(p.vol.sum()), true)
    assert float(p.vol.max()) == pytest.approx((dx / 2) ** 3) and float(p.vol.min()) > 0
    # Interior particles exist (the ball is solid, not a shell); no particle is a Gaussian, every Gaussian is carried.
    centre_dist = (p.x0 - torch.tensor([0.5, 0.5, 0.5], dtype=torch.float64)).norm(dim=1)
    assert int((centre_dist < 0.5 * r).sum()) > 50
    assert float(centre_dist.max()) < r + 0.25 * dx  # each boundary particle at its part's centroid, inside
    assert bool((p.gaussian == -1).all())
    assert len(p.carrier) == len(shell) and bool((p.dynamic == torch.arange(len(shell))).all())
    assert float(p.offset.norm(dim=1).max()) < dx  # the nearest particle is close

    # fill "gaussians": the Gaussians are particles (``budget`` of them, riding on themselves with zero offset) and
    # whole voxels fill the rest, so the body comes out larger by up to a voxel layer.
    p = build_particles(means, dynamic, lo=(0, 0, 0), dx=dx, budget=1000, capacity=100000, fill="gaussians")
    assert true * 1.1 < float(p.vol.sum()) < true * 1.35, (float(p.vol.sum()), true)
    assert int((p.gaussian >= 0).sum()) == 1000 and bool((p.gaussian[p.gaussian >= 0] < len(shell)).all())
    own = p.gaussian[p.gaussian >= 0]
    rows = torch.nonzero(p.gaussian >= 0).flatten()
    assert bool((p.carrier[own] == rows).all())
    assert float(p.offset[own].abs().max()) == 0.0


@pytest.mark.parametrize("noise", [0.0, 0.003])
def test_a_box_keeps_its_extent_wherever_the_voxels_cut_its_faces(noise):
    """Gaussians on a 0.20 × 0.16 × 0.12 m box's faces, on voxels of 1.19 cm placed at random against it: the
    particles' volume, spread along every axis, centroid and lowest layer are the solid box's; a fill of whole
    voxels is a quarter of a cell thicker on every side (+6% to +56% volume here). The faces come out a millimetre or
    two proud (+1% to +7% volume): a face is filled up to its edges, and the tangent planes of the faces that meet
    there reach a little past it (see :func:`causalgs.model.particles.fill_recesses`)."""
    rng = np.random.default_rng(0)
    size, centre, dx = np.array([0.2, 0.16, 0.12]), np.array([-0.33, 0.02, 0.218]), 0.0238
    true_sd = size / math.sqrt(12)
    true_low = centre[2] - size[2] / 2 + 0.025 * size[2]
    for n in (1500, 6000):
        for _ in range(2):
            lo = np.array([-0.5, -0.5, -0.1]) + rng.random(3) * dx / 2
            means = _box_surface(rng, n, size, centre, noise)
            p = build_particles(means, np.ones(n, bool), lo, dx, budget=n, capacity=100000)
            vol, mu, sd, low = _mass_stats(p.x0.numpy(), p.vol.numpy())
            assert -0.02 < vol / size.prod() - 1 < 0.08, vol / size.prod()
            assert np.abs(sd / true_sd - 1).max() < 0.04, sd / true_sd
            assert np.abs(mu - centre).max() < 0.0015, mu - centre
            assert abs(low - true_low) < 0.003, low - true_low
            whole = build_particles(means, np.ones(n, bool), lo, dx, budget=n, capacity=100000, fill="gaussians")
            assert float(whole.vol.sum()) / size.prod() - 1 > abs(vol / size.prod() - 1)


def test_a_plate_thinner_than_a_voxel_keeps_its_thickness():
    rng = np.random.default_rng(2)
    size, centre, dx = np.array([0.2, 0.16, 0.008]), np.array([0.0, 0.0, 0.2]), 0.0238
    means = _box_surface(rng, 4000, size, centre)
    p = build_particles(means, np.ones(len(means), bool), (-0.5, -0.5, -0.1), dx, budget=4000, capacity=100000)
    vol, mu, sd, _ = _mass_stats(p.x0.numpy(), p.vol.numpy())
    assert 0.8 < vol / size.prod() < 1.4, vol / size.prod()  # each face a millimetre or two proud of 8 mm
    assert abs(mu[2] - centre[2]) < 0.002 and sd[2] < 0.006, (mu, sd)


def test_carry_follows_translation_and_deformation():
    means = _sphere_shell(300, 0.1, (0.0, 0.0, 0.0))
    p = build_particles(means, np.ones(300, bool), lo=(-0.3, -0.3, -0.3), dx=0.04, budget=100, capacity=10000)
    P = len(p)
    A = torch.tensor([[1.2, 0.1, 0.0], [0.0, 0.9, 0.2], [0.0, 0.0, 1.1]], dtype=torch.float64)
    shift = torch.tensor([0.3, -0.1, 0.2], dtype=torch.float64)
    x = p.x0 @ A.T + shift  # an affine motion: the first-order carry reproduces it exactly
    F = A.expand(P, 3, 3)
    carried = p.carry(x, F)
    expect = torch.as_tensor(means) @ A.T + shift
    assert torch.allclose(carried, expect, atol=1e-12)


def test_too_many_particles_and_nothing_dynamic_are_clear_errors():
    means = _sphere_shell(20000, 0.2, (0.0, 0.0, 0.0))
    with pytest.raises(CausalGSError, match="capacity"):
        build_particles(means, np.ones(20000, bool), lo=(-1, -1, -1), dx=0.02, budget=200, capacity=5000)
    with pytest.raises(CausalGSError, match="no dynamic"):
        build_particles(means, np.zeros(20000, bool), lo=(-1, -1, -1), dx=0.05, budget=10, capacity=500)
    with pytest.raises(CausalGSError, match="physics.fill"):
        build_particles(means, np.ones(20000, bool), lo=(-1, -1, -1), dx=0.05, budget=10, capacity=500, fill="dense")
    from causalgs.model.config import FitConfig, from_dict, to_dict

    d = to_dict(FitConfig.preset_config("quick"))
    d["physics"]["fill"] = "dense"
    with pytest.raises(CausalGSError, match="physics.fill"):
        from_dict(FitConfig, d)


def test_a_gappy_surface_is_sealed_before_it_is_filled():
    """A cube's surface sampled with holes wider than one closing (a flat face covered by a few large Gaussians) is
    filled whole, and so is a thick-walled block whose hollow holds most of its volume; a notched solid that is
    closed at once keeps its notch; two bodies seal independently."""
    from causalgs.model.particles import MAX_EXTRA_CLOSING, seal_and_fill

    n, pad = 20, 1 + MAX_EXTRA_CLOSING
    shell = np.zeros((n, n, n), bool)
    shell[[0, -1], :, :] = shell[:, [0, -1], :] = shell[:, :, [0, -1]] = True
    gappy = shell.copy()
    gappy[0, 5:12, 5:12] = False  # a 7-voxel hole in one face: one closing does not seal it
    occ = np.pad(gappy, pad)
    from scipy import ndimage

    one = ndimage.binary_fill_holes(ndimage.binary_closing(occ, np.ones((3, 3, 3), bool)))
    assert one.sum() < 0.5 * n**3  # the old fill: a hollow shell
    out = seal_and_fill(occ, 1)
    assert abs(int(out.sum()) - n**3) <= 0.02 * n**3
    # A solid with a notch (already closed) keeps its notch.
    ell = np.ones((n, n, n), bool)
    ell[12:, :, 12:] = False
    out = seal_and_fill(np.pad(ell, pad), 1)
    assert int(out.sum()) == int(ell.sum())
    # A thick-walled block (faces three voxels deep, as on a small body at a fine voxel) whose unseen bottom has a
    # hole six voxels wide: hollow it still holds 78% of its volume; it is filled whole, not kept hollow.
    thick = np.ones((16, 14, 12), bool)
    thick[3:-3, 3:-3, 3:-3] = False
    thick[5:11, 4:10, :3] = False
    hollow = ndimage.binary_fill_holes(ndimage.binary_closing(np.pad(thick, pad), np.ones((3, 3, 3), bool)))
    assert 0.75 * thick.size < hollow.sum() < 0.8 * thick.size
    assert int(seal_and_fill(np.pad(thick, pad), 1).sum()) == thick.size
    # Two bodies side by side, one gappy and one closed, each as it should be.
    two = np.concatenate([gappy, np.zeros((12, n, n), bool), ell], axis=0)
    out = seal_and_fill(np.pad(two, pad), 1)
    assert abs(int(out.sum()) - (n**3 + int(ell.sum()))) <= 0.02 * n**3


def test_an_unseen_bottom_hangs_no_lip_under_the_body():
    """A box whose bottom no camera sees: its faces densely sampled, its bottom by a few Gaussians (8% of a seen
    face's density). The side faces' tangent planes reach past their last row; within the voxels outside the
    occupancy they are trusted only within reach of a Gaussian, so no particle hangs more than half a voxel under
    the bottom (the fill without the reach hung a lip of 9–17 mm here, a voxel being 11.9 mm)."""
    rng = np.random.default_rng(0)
    size, centre, dx = np.array([0.2, 0.16, 0.12]), np.array([-0.33, 0.02, 0.218]), 0.0238
    bottom = centre[2] - size[2] / 2
    for _ in range(4):
        lo = np.array([-0.5, -0.5, -0.1]) + rng.random(3) * dx / 2
        means = _box_surface(rng, 4000, size, centre)
        on_bottom = np.abs(means[:, 2] - bottom) < 1e-9
        means = means[~on_bottom | (rng.random(len(means)) < 0.08)]
        p = build_particles(means, np.ones(len(means), bool), lo, dx, budget=len(means), capacity=100000)
        x, vol = p.x0.numpy(), p.vol.numpy()
        assert float(x[:, 2].min()) > bottom - 0.5 * dx / 2, (float(x[:, 2].min()) - bottom)
        assert -0.02 < vol.sum() / size.prod() - 1 < 0.08, vol.sum() / size.prod()


def test_a_face_sunk_below_its_rim_is_filled_up_to_it():
    """As a 3DGS fit places them: every face's Gaussians 6 mm inside it but running on to its edges, the bottom
    (seen by no camera) sampled at 8% of a seen face's density, 1 mm of noise. Filled as the Gaussians sample it,
    each face is sunk 6 mm below a rim one voxel wide, and under the body only the rim meets the ground (its
    lowest half-cell carries 0.02–0.54 of the rim's mass per area over the middle of the bottom on these four
    placements, 0.41 on average). Filled up to the rim, the bottom is flat and the body nearer its volume."""
    rng = np.random.default_rng(0)
    size, centre, dx, inset = np.array([0.2, 0.16, 0.12]), np.array([-0.33, 0.02, 0.218]), 0.0196, 0.006
    ratios, vols = [], []
    for _ in range(4):
        lo = np.array([-0.5, -0.5, -0.1]) + rng.random(3) * dx / 2
        p = _box_surface(rng, 4000, size, centre) - centre
        on = np.isclose(np.abs(p), size / 2)
        keep = ~(on[:, 2] & (p[:, 2] < 0)) | (rng.random(len(p)) < 0.08)
        means = (p - np.sign(p) * on * inset)[keep] + centre + rng.normal(0, 0.001, (int(keep.sum()), 3))
        q = build_particles(means, np.ones(len(means), bool), lo, dx, budget=len(means), capacity=100000)
        x, vol = q.x0.numpy(), q.vol.numpy()
        middle = (np.abs(x[:, :2] - centre[:2]) < size[:2] / 2 - 0.02).all(1)
        a_mid = float(np.prod(size[:2] - 0.04))
        low = x[:, 2] < x[:, 2].min() + dx / 2
        ratios.append((vol[low & middle].sum() / a_mid) / (vol[low & ~middle].sum() / (size[0] * size[1] - a_mid)))
        vols.append(vol.sum() / size.prod())
    assert np.mean(ratios) > 0.8, ratios
    assert 0.84 < min(vols) and max(vols) < 0.95, vols  # the inset itself still takes about 10% (0.81–0.84 sunk)


def test_fill_recesses_fills_a_dish_and_keeps_a_step():
    """On the sub-sample grid: a slab whose top layer is a dish (a rim one sub-sample wide around a sunk middle)
    comes out whole; a step (material along one axis only) and a convex slab gain nothing."""
    from causalgs.model.particles import SUB, fill_recesses

    occ = np.zeros((6, 6, 4), bool)
    occ[1:5, 1:5, 1:3] = True  # a slab two voxels thick; its top layer (z = 2) is the one the surface cuts
    cells = np.argwhere(occ & (np.arange(4) == 2)[None, None, :])
    o = (np.arange(SUB) + 0.5) / SUB
    sub = np.stack(np.meshgrid(o, o, o, indexing="ij"), -1).reshape(-1, 3)
    pos = cells[:, None, :] + sub[None]  # [n, SUB³, 3] in voxels
    top = pos[..., 2] < 2.5  # the lower half of the layer inside: a flat face
    rim = ((pos[..., 0] < 1.25) | (pos[..., 0] > 4.75) | (pos[..., 1] < 1.25) | (pos[..., 1] > 4.75))
    flat = fill_recesses(occ, cells, top)
    assert (flat == top).all()  # convex: nothing added
    dish = top | (rim & (pos[..., 2] < 2.75))  # a rim a quarter voxel proud of the face
    out = fill_recesses(occ, cells, dish)
    assert (out == (pos[..., 2] < 2.75)).all()  # filled up to the rim, no higher
    step = top | ((pos[..., 0] < 1.25) & (pos[..., 2] < 2.75))  # a wall along one edge only
    assert (fill_recesses(occ, cells, step) == step).all()
