"""A deformation residual inside the observed window: (z, t) → (Δx, Δrotation, Δscale), on top of the velocity field.

The velocity field moves every particle by a blend of K rigid motions (:mod:`causalgs.model.kinematic`); a body that
bends, bulges or wobbles within a pattern is beyond it. As FreeGave does, a small network conditioned on the physics
code z (detached: the residual does not shape the codes) and on time refines the tracked state of the observed frames.
It must not carry the motion itself: the forecast and the simulator's initial state come from the velocity field.
So, by construction:

- every output is bounded (tanh): |Δx| ≤ ``max_offset`` × the scene size per axis, the rotation angle per axis ≤
  ``max_angle``, |Δlog s| ≤ ``max_log_scale``;
- Δx has its rigid part removed: per motion pattern k, the h_k-weighted least-squares twist (a_k, ω_k) of Δx about
  the pattern's centroid c_k (the translation the weighted mean, the rotation from the weighted inertia tensor) is
  subtracted, x ↦ Σ_k h_k (a_k + ω_k × (x − c_k)). For a particle in one pattern this is the orthogonal projection
  onto the complement of the pattern's infinitesimal rigid motions: a pattern's mean residual displacement and its
  residual angular moment are zero, so whatever moves a body as a whole has to be the velocity field's;
- it is zero at the start (last layer zeroed) and trained only late in the kinematic stage, after the velocity field.

Beyond the window it is zero: the future is the simulator's.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import nn

from causalgs.errors import CausalGSError
from causalgs.model.fields import Encoding, mlp

INERTIA_EPS = 1e-9  # relative ridge on a pattern's inertia tensor (a pattern on a line or a point has a null axis)


@dataclass
class ResidualConfig:
    """The deformation residual (``kinematic.residual``; see the module docstring)."""

    enabled: bool = True
    width: int = 64
    depth: int = 2
    time_freqs: int = 6
    max_offset: float = 0.01  # |Δx| per axis, as a fraction of the scene size
    max_angle: float = 0.1  # radians per axis
    max_log_scale: float = 0.2
    lr: float = 1e-3
    start: float = 0.6  # the fraction of the kinematic stage after which it trains (the velocity field first)
    lambda_size: float = 0.01  # weight of the mean squared Δx in units of its bound (the smallest residual wins)

    def __post_init__(self):
        for name in ("max_offset", "max_angle", "max_log_scale", "lr", "lambda_size"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise CausalGSError(f"kinematic.residual.{name} = {value} must be a non-negative number")
        if not 0.0 <= self.start <= 1.0:
            raise CausalGSError(f"kinematic.residual.start = {self.start} must lie in [0, 1]")
        if self.width < 1 or self.depth < 0 or self.time_freqs < 0:
            raise CausalGSError("kinematic.residual: width must be at least 1, depth and time_freqs at least 0")


@dataclass
class Deformation:
    """One frame's residual for n Gaussians: dx [n, 3], drot [n, 3] (rotation vector), dlog_scale [n, 3]."""

    dx: torch.Tensor
    drot: torch.Tensor
    dlog_scale: torch.Tensor


class Residual(nn.Module):
    """(z, t) → :class:`Deformation`; ``code_dim`` is z's size, ``duration`` the window in seconds, ``size`` the
    scene size that scales Δx."""

    def __init__(self, config: ResidualConfig, code_dim: int, duration: float, size: float):
        super().__init__()
        self.config = config
        self.enc_t = Encoding(config.time_freqs, 1, torch.zeros(1), torch.tensor([max(float(duration), 1e-6)]))
        self.net = mlp(code_dim + self.enc_t.out_dim, 9, config.width, config.depth)
        with torch.no_grad():
            self.net[-1].weight.zero_()
            self.net[-1].bias.zero_()
        self.register_buffer("size", torch.tensor(float(size), dtype=torch.float64))
        # The network's outputs live in the frame it was built in; a re-posed world (x' = s R x + t) turns its
        # displacements by s R and its rotation vectors by R (:meth:`reframe`).
        self.register_buffer("linear", torch.eye(3, dtype=torch.float64))
        self.register_buffer("turn", torch.eye(3, dtype=torch.float64))

    def reframe(self, sim) -> None:
        """The same residual of the same material point after the world is re-posed by ``sim``."""
        R = torch.tensor(sim.R, dtype=torch.float64)
        with torch.no_grad():
            self.linear.copy_(sim.scale * R @ self.linear)
            self.turn.copy_(R @ self.turn)

    def bound(self) -> float:
        """The largest |Δx| per axis, in the current world's units."""
        return self.config.max_offset * float(self.size) * float(torch.linalg.det(self.linear)) ** (1.0 / 3.0)

    def forward(self, z: torch.Tensor, t: float) -> Deformation:
        """The bounded (not yet projected) residual of Gaussians with codes z [n, C] at time t (seconds)."""
        c = self.config
        tt = self.enc_t(torch.full((len(z), 1), float(t), dtype=z.dtype))
        out = torch.tanh(self.net(torch.cat([z.detach(), tt], dim=-1)))
        scale = out.new_tensor([c.max_offset * float(self.size), c.max_angle, c.max_log_scale]).repeat_interleave(3)
        out = out * scale
        dx = out[:, :3] @ self.linear.to(out.dtype).T
        return Deformation(dx, out[:, 3:6] @ self.turn.to(out.dtype).T, out[:, 6:])


def remove_rigid(dx: torch.Tensor, x: torch.Tensor, h: torch.Tensor) -> torch.Tensor:
    """``dx`` [n, 3] less each pattern's h-weighted least-squares rigid twist of it about the pattern's centroid of
    ``x`` [n, 3] (h [n, K], the mixtures), blended back by h: see the module docstring."""
    w = h.to(dx.dtype)
    x = x.to(dx.dtype)
    mass = w.sum(0).clamp_min(1e-12)  # [K]
    c = (w.T @ x) / mass[:, None]  # [K, 3]
    a = (w.T @ dx) / mass[:, None]  # [K, 3]: the weighted mean displacement
    r = x[:, None, :] - c[None]  # [n, K, 3]
    moment = torch.einsum("nk,nkd->kd", w, torch.linalg.cross(r, dx[:, None, :].expand_as(r)))  # Σ h r × dx
    rr = torch.einsum("nk,nki,nkj->kij", w, r, r)  # Σ h r rᵀ
    eye = torch.eye(3, dtype=dx.dtype)
    inertia = rr.diagonal(dim1=-2, dim2=-1).sum(-1)[:, None, None] * eye - rr  # Σ h (|r|² I − r rᵀ)
    ridge = INERTIA_EPS * inertia.diagonal(dim1=-2, dim2=-1).sum(-1).clamp_min(1e-30)[:, None, None] * eye
    omega = torch.linalg.solve(inertia + ridge, moment[..., None])[..., 0]  # [K, 3]
    rigid = a[None] + torch.linalg.cross(omega[None].expand_as(r), r)  # [n, K, 3]
    return dx - torch.einsum("nk,nkd->nd", w, rigid)
