"""Constitutive models: the Newton polar iteration of fixed-corotated against numpy's SVD polar factor."""

from __future__ import annotations

import numpy as np

from causalgs.sim.materials import polar


def _svd_rotation(F: np.ndarray) -> np.ndarray:
    U, _, Vt = np.linalg.svd(F)
    return U @ Vt


def test_newton_polar_is_the_svd_rotation(ti64):
    rng = np.random.default_rng(0)
    # Moderate deformations: a random rotation times a stretch with singular values in [0.6, 1.7], det > 0.
    Q, _ = np.linalg.qr(rng.normal(size=(32, 3, 3)))
    Q *= np.sign(np.linalg.det(Q))[:, None, None]
    U, _ = np.linalg.qr(rng.normal(size=(32, 3, 3)))
    S = U @ (rng.uniform(0.6, 1.7, size=(32, 3))[:, :, None] * U.transpose(0, 2, 1))
    F = Q @ S
    R = polar(F)
    np.testing.assert_allclose(R, _svd_rotation(F), atol=1e-12)
    np.testing.assert_allclose(R.transpose(0, 2, 1) @ R, np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)
    np.testing.assert_allclose(R, Q, atol=1e-12)  # F = Q S with S symmetric positive definite
