"""Real spherical harmonics up to degree 3, in the basis and sign convention of 3DGS and gsplat.

A Taichi function for the projection kernel and a torch twin for the reference; both evaluate the same constants on
the unit direction from the camera centre to the Gaussian.
"""

# No `from __future__ import annotations`: Taichi 1.7 reads ti.func annotations as live objects.
import numpy as np
import torch

from causalgs._ti import ti

C0 = 0.28209479177387814
C1 = 0.4886025119029199
C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)


def sh_basis_torch(dirs: torch.Tensor, degree: int) -> torch.Tensor:
    """Basis values [N, (degree + 1)²] at unit directions [N, 3]."""
    x, y, z = dirs.unbind(-1)
    out = [torch.full_like(x, C0)]
    if degree >= 1:
        out += [-C1 * y, C1 * z, -C1 * x]
    if degree >= 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        out += [C2[0] * xy, C2[1] * yz, C2[2] * (2 * zz - xx - yy), C2[3] * xz, C2[4] * (xx - yy)]
    if degree >= 3:
        out += [
            C3[0] * y * (3 * xx - yy),
            C3[1] * xy * z,
            C3[2] * y * (4 * zz - xx - yy),
            C3[3] * z * (2 * zz - 3 * xx - 3 * yy),
            C3[4] * x * (4 * zz - xx - yy),
            C3[5] * z * (xx - yy),
            C3[6] * x * (xx - 3 * yy),
        ]
    return torch.stack(out, dim=-1)


def eval_sh_torch(sh: torch.Tensor, view: torch.Tensor, degree: int) -> torch.Tensor:
    """Colour [N, 3] = Σ_k basis_k(view/|view|) · sh[:, k] for the first (degree + 1)² coefficients of sh [N, S, 3]."""
    dirs = view / torch.sqrt((view * view).sum(dim=-1, keepdim=True) + 1e-20)  # finite at the camera centre
    basis = sh_basis_torch(dirs, degree)
    return (basis[..., None] * sh[:, : basis.shape[-1]]).sum(dim=1)


@ti.func
def eval_sh(S, d, degree: ti.template()):
    """Σ_k basis_k(d) · S[k, :] for a unit direction ``d`` and coefficients ``S`` ((degree+1)² × 3 or larger matrix);
    ``degree`` is static so unused terms are not compiled."""
    c = C0 * _row(S, 0)
    if ti.static(degree >= 1):
        x, y, z = d[0], d[1], d[2]
        c += -C1 * y * _row(S, 1) + C1 * z * _row(S, 2) - C1 * x * _row(S, 3)
        if ti.static(degree >= 2):
            xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
            c += (
                C2[0] * xy * _row(S, 4)
                + C2[1] * yz * _row(S, 5)
                + C2[2] * (2 * zz - xx - yy) * _row(S, 6)
                + C2[3] * xz * _row(S, 7)
                + C2[4] * (xx - yy) * _row(S, 8)
            )
            if ti.static(degree >= 3):
                c += (
                    C3[0] * y * (3 * xx - yy) * _row(S, 9)
                    + C3[1] * xy * z * _row(S, 10)
                    + C3[2] * y * (4 * zz - xx - yy) * _row(S, 11)
                    + C3[3] * z * (2 * zz - 3 * xx - 3 * yy) * _row(S, 12)
                    + C3[4] * x * (4 * zz - xx - yy) * _row(S, 13)
                    + C3[5] * z * (xx - yy) * _row(S, 14)
                    + C3[6] * x * (xx - 3 * yy) * _row(S, 15)
                )
    return c


@ti.func
def _row(S, k: ti.template()):
    return ti.Vector([S[k, 0], S[k, 1], S[k, 2]])


def rotate_sh(sh: torch.Tensor, R, degree: int) -> torch.Tensor:
    """SH coefficients [N, S, 3] of the same colour function in a world turned by the rotation ``R`` [3, 3]: the
    colour seen along R d after the turn is the colour seen along d before. Each band l mixes only within itself, by
    the (2l + 1)² matrix M with basis(Rᵀ d) = basis(d) M, solved exactly by least squares on directions that span
    the band."""
    R = torch.tensor(np.asarray(R), dtype=torch.float64)
    g = torch.Generator().manual_seed(0)
    dirs = torch.nn.functional.normalize(torch.randn(64, 3, generator=g, dtype=torch.float64), dim=-1)
    B = sh_basis_torch(dirs, degree)
    B_turned = sh_basis_torch(dirs @ R, degree)  # rows: basis at Rᵀ d
    out = sh.clone()
    for band in range(1, degree + 1):
        lo, hi = band * band, (band + 1) * (band + 1)
        M = torch.linalg.lstsq(B[:, lo:hi], B_turned[:, lo:hi]).solution  # [m, m]
        out[:, lo:hi] = torch.einsum("ij,njc->nic", M.to(sh.dtype), sh[:, lo:hi])
    return out
