"""Constitutive models for MLS-MPM, all behind one signature: ``model(F, mu, lam) -> tau``.

``tau`` is the Kirchhoff stress τ = P Fᵀ (P the first Piola–Kirchhoff stress), which is what the MLS-MPM P2G needs:
the grid force of particle p is −V_p τ_p ∇w (Hu et al. 2018, eq. 18, with ∇w ≈ 4/dx² w (x_i − x_p)). Every model
below gives a symmetric τ, so the grid forces carry no torque and APIC keeps angular momentum.

None of them calls an SVD: Taichi 1.7 cannot differentiate ``ti.svd`` / ``ti.polar_decompose`` in 3D (compile error,
measured here). Fixed-corotated takes its rotation from a fixed number of Newton polar iterations R ← ½(R + R⁻ᵀ),
unrolled with ``ti.static`` (a runtime loop carrying a local under autodiff overflows the AD stack).

Models are chosen by name (a static kernel argument): ``MODELS`` maps the name to its ``ti.func``. The same maths in
plain torch lives in :mod:`causalgs.sim.reference`.
"""

# No `from __future__ import annotations`: Taichi 1.7 reads kernel annotations as live objects.
import numpy as np
import torch

from causalgs._ti import ti
from causalgs.errors import CausalGSError

# Newton polar iterations. Singular values map σ → ½(σ + 1/σ): from σ = 2 (or 0.5) eight steps reach 1 to 1e-16.
# Larger stretches converge more slowly (σ = 10 needs ~10); fixed-corotated is meant for moderate deformation.
POLAR_ITERS = 8


def lame(E, nu):
    """Lamé parameters (μ, λ) from Young's modulus and Poisson ratio; works on floats, tensors and in Taichi scope."""
    return E / (2.0 * (1.0 + nu)), E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))


@ti.func
def lame_ti(E, nu):
    """:func:`lame` in Taichi scope (a plain Python call inside a kernel triggers Taichi's scope warning)."""
    return E / (2.0 * (1.0 + nu)), E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))


@ti.func
def polar_rotation(F):
    """Rotation factor R of F = R S by Newton's iteration R ← ½(R + R⁻ᵀ) (Higham 1986); needs det F > 0."""
    R = F
    for _ in ti.static(range(POLAR_ITERS)):
        R = 0.5 * (R + R.inverse().transpose())
    return R


@ti.func
def neo_hookean(F, mu, lam):
    """Compressible neo-Hookean: P = μ(F − F⁻ᵀ) + λ ln J F⁻ᵀ, so τ = μ(F Fᵀ − I) + λ ln J I (no inverse needed)."""
    J = F.determinant()
    I = ti.Matrix.identity(float, 3)
    return mu * (F @ F.transpose() - I) + lam * ti.log(J) * I


@ti.func
def stvk(F, mu, lam):
    """St. Venant–Kirchhoff: E = ½(FᵀF − I), S = 2μE + λ tr(E) I, P = F S, τ = F S Fᵀ."""
    I = ti.Matrix.identity(float, 3)
    G = 0.5 * (F.transpose() @ F - I)
    S = 2.0 * mu * G + lam * G.trace() * I
    return F @ S @ F.transpose()


@ti.func
def fixed_corotated(F, mu, lam):
    """Fixed-corotated (Stomakhin et al. 2012): P = 2μ(F − R) + λ(J − 1) J F⁻ᵀ, τ = 2μ(F − R)Fᵀ + λ(J − 1) J I."""
    J = F.determinant()
    R = polar_rotation(F)
    I = ti.Matrix.identity(float, 3)
    return 2.0 * mu * (F - R) @ F.transpose() + lam * (J - 1.0) * J * I


MODELS = {"neo_hookean": neo_hookean, "stvk": stvk, "fixed_corotated": fixed_corotated}
DEFAULT_MODEL = "neo_hookean"


def check_model(name: str) -> str:
    if name not in MODELS:
        raise CausalGSError(f"unknown material model '{name}' (models: {', '.join(MODELS)})")
    return name


@ti.func
def kirchhoff(F, mu, lam, model: ti.template()):
    """Kirchhoff stress of the model named ``model`` (a static string)."""
    return ti.static(MODELS[model])(F, mu, lam)


@ti.kernel
def _polar_batch(F: ti.types.ndarray(), R: ti.types.ndarray(), n: ti.i32):
    for p in range(n):
        A = ti.Matrix.zero(float, 3, 3)
        for a, b in ti.static(ti.ndrange(3, 3)):
            A[a, b] = F[p, a, b]
        Q = polar_rotation(A)
        for a, b in ti.static(ti.ndrange(3, 3)):
            R[p, a, b] = Q[a, b]


def polar(F) -> np.ndarray:
    """The Newton polar rotation of each F [n, 3, 3] as Taichi computes it (for tests and diagnostics)."""
    from causalgs import _ti

    Ft = torch.as_tensor(np.asarray(F)).to(_ti.torch_dtype()).reshape(-1, 3, 3).contiguous()
    R = torch.empty_like(Ft)
    if len(Ft):
        _polar_batch(Ft, R, len(Ft))
    return R.numpy()
