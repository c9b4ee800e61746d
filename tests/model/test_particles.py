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


def test_a_shell_of_gaussians_becomes_a_solid_ball_of_the_right_volume():
    dx = 0.05
    r = 0.2
    shell = _sphere_shell(4000, r, (0.5, 0.5, 0.5))
    static = np.random.default_rng(1).uniform(0, 1, (300, 3)) * [1, 1, 0.02]  # a floor, not simulated
    means = np.concatenate([shell, static])
    dynamic = np.arange(len(means)) < len(shell)
    p = build_particles(means, dynamic, lo=(0, 0, 0), dx=dx, budget=1000, capacity=100000)
    vol = float(p.vol.sum())
    true = 4 / 3 * math.pi * r**3
    # The voxelised shell covers the ball plus at most a voxel layer outside it.
    assert true * 0.95 < vol < true * 1.35, (vol, true)
    # Interior particles exist (the ball is solid, not a shell) and fill particles are not Gaussians.
    centre_dist = (p.x0 - torch.tensor([0.5, 0.5, 0.5], dtype=torch.float64)).norm(dim=1)
    assert int((centre_dist < 0.5 * r).sum()) > 50
    assert int((p.gaussian >= 0).sum()) == 1000 and bool((p.gaussian[p.gaussian >= 0] < len(shell)).all())
    assert len(p.carrier) == len(shell) and bool((p.dynamic == torch.arange(len(shell))).all())
    # A Gaussian that is a particle rides on itself with zero offset.
    own = p.gaussian[p.gaussian >= 0]
    rows = torch.nonzero(p.gaussian >= 0).flatten()
    assert bool((p.carrier[own] == rows).all())
    assert float(p.offset[own].abs().max()) == 0.0
    # Every offset is within a voxel diagonal or so (the nearest particle is close).
    assert float(p.offset.norm(dim=1).max()) < dx


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


def test_a_gappy_surface_is_sealed_before_it_is_filled():
    """A cube's surface sampled with holes wider than one closing (a flat face covered by a few large Gaussians) is
    filled whole; a notched solid that is closed at once keeps its notch; two bodies seal independently."""
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
    # Two bodies side by side, one gappy and one closed, each as it should be.
    two = np.concatenate([gappy, np.zeros((12, n, n), bool), ell], axis=0)
    out = seal_and_fill(np.pad(two, pad), 1)
    assert abs(int(out.sum()) - (n**3 + int(ell.sum()))) <= 0.02 * n**3
