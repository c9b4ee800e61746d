"""F Σ Fᵀ, the covariance handed from the simulator to the rasterizer."""

from __future__ import annotations

import torch

from causalgs.render.reference import quat_scale_to_cov
from causalgs.sim.autograd import deformed_covariance


def _quat_mul(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack([aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                        aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw], -1)  # fmt: skip


def test_rotation_turns_the_gaussian_and_stretch_scales_it():
    g = torch.Generator().manual_seed(0)
    d = torch.float64
    n = 32
    quats = torch.randn(n, 4, generator=g, dtype=d)
    quats = quats / quats.norm(dim=1, keepdim=True)
    scales = torch.rand(n, 3, generator=g, dtype=d) + 0.1
    rest = quat_scale_to_cov(quats, scales)
    # F = I leaves Σ alone.
    eye = torch.eye(3, dtype=d).expand(n, 3, 3)
    assert torch.allclose(deformed_covariance(eye, quats, scales), rest, atol=1e-14)
    # F = R (a rotation with quaternion r) is the Gaussian with quaternion r·q and the same scales.
    r = torch.randn(n, 4, generator=g, dtype=d)
    r = r / r.norm(dim=1, keepdim=True)
    w, x, y, z = r.unbind(-1)
    R = torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
                     2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
                     2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)  # fmt: skip
    R = R.reshape(n, 3, 3)
    got = deformed_covariance(R, quats, scales)
    assert torch.allclose(got, quat_scale_to_cov(_quat_mul(r, quats), scales), atol=1e-12)
    # A uniform stretch by s scales Σ by s², with time-batched F [T, n, 3, 3].
    F = torch.stack([eye, 2.0 * eye])
    out = deformed_covariance(F, quats, scales)
    assert out.shape == (2, n, 3, 3)
    assert torch.allclose(out[1], 4.0 * rest, atol=1e-12)
    # det Σ_t = det(F)² det Σ (volume change).
    A = eye + 0.1 * torch.randn(n, 3, 3, generator=g, dtype=d)
    dets = torch.linalg.det(deformed_covariance(A, quats, scales))
    assert torch.allclose(dets, torch.linalg.det(A) ** 2 * torch.linalg.det(rest), rtol=1e-10)
