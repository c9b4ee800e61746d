"""Inverse physics: the neural fields that infer, for every particle, its physics code, motion and material.

All of it is plain torch (no Taichi field is touched here; DESIGN.md "One path for the data"):

- γ(p): positional encoding of a position normalised to the scene box, [u, sin(2^k π u), cos(2^k π u)];
- z = f_vel(γ(p)): the latent physics code of the particle at canonical position p;
- h = f_neck(z) ∈ Δ^K: a softmax over K motion patterns (a particle belongs to a mixture of patterns, so the patterns
  act as soft objects and the clustering reads them directly);
- W_t = f_weight(γ_t(t)) + T(t) ∈ R^{K×6}: what each pattern does at time t, as a 6-DoF twist (3 linear + 3
  angular). T is a table of one twist per observed frame, interpolated linearly and held at its last value after
  the window: the MLP's spectral bias smooths a bounce over several frames, while a frame's own twist can turn the
  velocity within that frame (shrunk towards zero, it stays small on the bounce benchmark, whose tracked ball still
  stops 11–19 cm short of the floor at each bounce);
- v(p, t) = Σ_k h_k [u_k(t) + ω_k(t) × (p − c_k)]: the divergence-free 6-DoF basis B(p), with every pattern rotating
  about its own learned centre c_k (not only the world origin);
- m = f_mat(γ(p)) + h·Θ: Young's modulus (log-space, bounded), Poisson ratio and density (bounded). Θ ∈ R^{K×3}
  holds one material offset per motion pattern (zero at the start). A body is what moves together, and its particles
  share a material: through Θ the evidence about one body (a soft block squashed by an impact) moves that body's
  material and not its neighbour's. Through f_mat alone, whose weights every particle shares, the strongest signal
  in the scene drags every body's material along with it.

The code z and the mixture h are computed once per particle at its canonical position (the particle carries its
physics code, as a Lagrangian label), so integrating the motion costs O(N·K) per step and needs no network call:
for particle i, v_i(x, t) = a_i(t) + ω_i(t) × x with a_i = Σ_k h_ik (u_k − ω_k × c_k) and ω_i = Σ_k h_ik ω_k.
This is an exact rigid motion per pattern; the velocity Jacobian is [ω_i]×, which rotates the Gaussians.

Bounds: E ∈ [E_min, E_max] in log space keeps the CFL step of the simulator within a known budget; nu ∈
[nu_min, nu_max] stays away from the incompressible limit 0.5. Density defaults to a fixed value: with elastic
forces, gravity and friction, video only constrains E/ρ, so learning both would be a flat direction.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import nn

from causalgs.errors import CausalGSError


@dataclass
class FieldsConfig:
    """Sizes and bounds of the inverse-physics fields (all documented in the module docstring)."""

    patterns: int = 16  # K motion patterns
    code_dim: int = 32  # size of the physics code z
    width: int = 64  # hidden width of every MLP
    depth: int = 2  # hidden layers of every MLP
    pos_freqs: int = 4  # frequencies of γ(p)
    frame_twists: bool = True  # T(t): a learned twist per observed frame on top of f_weight's
    # "field": every particle's material from f_mat(γ(p)) + h·Θ; "global": one material for the whole scene (f_mat's
    # last bias alone), the paper's ablation without inverse-physics inference of intrinsic properties (IPI)
    materials: str = "field"
    # "basis": v = h·W_t·B(p), the velocity field decomposition (VFD) above; "mlp": one unstructured velocity per
    # material point, v(x0, t) = MLP(γ(x0), γ_t(t)), with no code, bottleneck or basis (the paper's ablation without
    # VFD; rotations of the Gaussians are held, having no velocity Jacobian)
    velocity: str = "basis"
    time_freqs: int = 6  # frequencies of γ_t(t): the shortest period is 1/16 of the window (4 frames of 67), so a
    # bounce or an impact, which turns the velocity within a frame or two, is not smoothed over a dozen frames
    E_range: tuple[float, float] = (2.0e3, 4.0e5)  # Pa
    E_init: float = 1.0e5  # Pa, where f_mat starts (stiff: a soft start sags at rest, and the fit is slow to leave it)
    nu_range: tuple[float, float] = (0.1, 0.45)
    nu_init: float = 0.3
    density_range: tuple[float, float] = (1000.0, 1000.0)  # kg/m³; equal ends = fixed density

    def __post_init__(self):
        self.E_range = tuple(float(a) for a in self.E_range)
        self.nu_range = tuple(float(a) for a in self.nu_range)
        self.density_range = tuple(float(a) for a in self.density_range)
        lo, hi = self.E_range
        if not 0 < lo <= self.E_init <= hi:
            raise CausalGSError(f"E_init = {self.E_init:g} must lie in E_range = [{lo:g}, {hi:g}] (positive)")
        if not 0 <= self.nu_range[0] <= self.nu_init <= self.nu_range[1] < 0.5:
            raise CausalGSError(f"nu_init = {self.nu_init} must lie in nu_range = {self.nu_range} within [0, 0.5)")
        if not 0 < self.density_range[0] <= self.density_range[1]:
            raise CausalGSError(f"density_range = {self.density_range} must be positive and ordered")
        if self.velocity not in ("basis", "mlp"):
            raise CausalGSError(f"fields.velocity = {self.velocity!r} must be 'basis' or 'mlp'")
        if self.materials not in ("field", "global"):
            raise CausalGSError(f"fields.materials = {self.materials!r} must be 'field' or 'global'")
        if self.patterns < 1 or self.code_dim < 1 or self.width < 1 or self.depth < 0:
            raise CausalGSError("patterns, code_dim and width must be at least 1, depth at least 0")


class Encoding(nn.Module):
    """γ(p) = [u, sin(2^k π u), cos(2^k π u)]_{k<L} with u = axes · (p − centre) / half_extent (the scene box to
    [-1, 1]; ``axes`` is the identity until the world is re-posed, :meth:`reframe`)."""

    def __init__(self, freqs: int, dims: int, centre=None, half_extent=None):
        super().__init__()
        self.freqs, self.dims = int(freqs), int(dims)
        self.register_buffer("centre", torch.zeros(dims) if centre is None else torch.as_tensor(centre).float())
        half = torch.ones(dims) if half_extent is None else torch.as_tensor(half_extent).float()
        self.register_buffer("half_extent", half)
        self.register_buffer("scales", math.pi * 2.0 ** torch.arange(self.freqs, dtype=torch.float32))
        self.register_buffer("axes", torch.eye(dims))

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        state_dict.setdefault(prefix + "axes", torch.eye(self.dims))  # saved before re-posing existed
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def reframe(self, sim) -> None:
        """The same γ of the same material point after the world is re-posed by ``sim`` (x' = s R x + t): with
        x − c = Rᵀ (x' − c') / s and c' = s R c + t, u = axes D Rᵀ D⁻¹ / s · D (x' − c'), D = diag(1 / half)."""
        D = torch.diag(1.0 / self.half_extent.double())
        R = torch.tensor(sim.R, dtype=torch.float64)
        axes = self.axes.double() @ D @ R.T @ torch.linalg.inv(D) / sim.scale
        centre = torch.as_tensor(sim.points(self.centre.double().numpy()))
        with torch.no_grad():
            self.axes.copy_(axes.to(self.axes.dtype))
            self.centre.copy_(centre.to(self.centre.dtype))

    @property
    def out_dim(self) -> int:
        return self.dims * (1 + 2 * self.freqs)

    def forward(self, p: torch.Tensor) -> torch.Tensor:
        u = (p - self.centre.to(p.dtype)) / self.half_extent.to(p.dtype)
        u = u @ self.axes.to(p.dtype).T
        a = u[..., None] * self.scales.to(p.dtype)  # [..., D, L]
        return torch.cat([u, a.sin().flatten(-2), a.cos().flatten(-2)], dim=-1)


def mlp(n_in: int, n_out: int, width: int, depth: int) -> nn.Sequential:
    layers: list[nn.Module] = []
    d = n_in
    for _ in range(depth):
        layers += [nn.Linear(d, width), nn.SiLU()]
        d = width
    layers.append(nn.Linear(d, n_out))
    return nn.Sequential(*layers)


class Flow(nn.Module):
    """The unstructured velocity of the ablation without VFD: v(x0, t) = W₂ SiLU(A γ(x0) + B γ_t(t) + b) + c for the
    material point at canonical x0, zero at the start. The hidden layer is a sum of a position and a time term, so
    the velocities of N points at T times cost O((N + T)·width) for the first layer and O(N·T·width) after it, not a
    network call per point and time."""

    def __init__(self, n_pos: int, n_time: int, width: int):
        super().__init__()
        self.pos = nn.Linear(n_pos, width)
        self.time = nn.Linear(n_time, width, bias=False)
        self.out = nn.Linear(width, 3)
        with torch.no_grad():
            self.out.weight.mul_(0.01)
            self.out.bias.zero_()

    def forward(self, gx: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
        """Velocities [T, N, 3] from the encoded positions γ(x0) [N, ·] and times γ_t(t) [T, ·]."""
        return self.out(nn.functional.silu(self.pos(gx)[None] + self.time(gt)[:, None]))


def _logit(x: float) -> float:
    x = min(max(x, 1e-4), 1 - 1e-4)
    return math.log(x / (1 - x))


class InversePhysics(nn.Module):
    """f_vel, f_neck, f_weight, f_mat and the pattern centres c_k (see the module docstring).

    ``lo, hi``: the scene box, used to normalise positions for γ(p) and to place the initial centres; ``duration``:
    the observed window in seconds; ``frames``: its frame count, the knots of the per-frame twists T (fewer than 2,
    or ``frame_twists`` off: no table)."""

    def __init__(self, config: FieldsConfig, lo, hi, duration: float = 1.0, frames: int = 0):
        super().__init__()
        self.config = c = config
        lo, hi = torch.as_tensor(lo, dtype=torch.float32), torch.as_tensor(hi, dtype=torch.float32)
        centre, half = (lo + hi) / 2, ((hi - lo) / 2).clamp_min(1e-6)
        self.enc = Encoding(c.pos_freqs, 3, centre, half)
        # Time is normalised so the trained window maps to [0, 1]; extrapolation evaluates beyond it.
        self.enc_t = Encoding(c.time_freqs, 1, torch.zeros(1), torch.tensor([max(duration, 1e-6)]))
        self.f_vel = mlp(self.enc.out_dim, c.code_dim, c.width, c.depth)
        self.f_neck = mlp(c.code_dim, c.patterns, c.width, 0)
        self.f_weight = mlp(self.enc_t.out_dim, c.patterns * 6, c.width, c.depth)
        self.f_mat = mlp(self.enc.out_dim, 3, c.width, c.depth)
        self.flow = Flow(self.enc.out_dim, self.enc_t.out_dim, c.width) if c.velocity == "mlp" else None
        # Start at rest (zero twists) and at E_init / nu_init everywhere.
        with torch.no_grad():
            self.f_weight[-1].weight.mul_(0.01)
            self.f_weight[-1].bias.zero_()
            last = self.f_mat[-1]
            last.weight.mul_(0.01)
            logE = [math.log(a) for a in c.E_range]
            span = max(logE[1] - logE[0], 1e-12)
            nu_span = max(c.nu_range[1] - c.nu_range[0], 1e-12)
            last.bias.copy_(torch.tensor([
                _logit((math.log(c.E_init) - logE[0]) / span), _logit((c.nu_init - c.nu_range[0]) / nu_span), 0.0
            ]))  # fmt: skip
        self.pattern_materials = nn.Parameter(torch.zeros(c.patterns, 3))  # Θ: per-pattern material offsets
        knots = int(frames) if c.frame_twists and frames >= 2 else 0
        self.frame_twists = nn.Parameter(torch.zeros(knots, c.patterns, 6))  # T: one twist per observed frame
        self.duration = max(float(duration), 1e-6)
        g = torch.Generator().manual_seed(0)
        self.centres = nn.Parameter(centre + (torch.rand(c.patterns, 3, generator=g) - 0.5) * half)
        # Every pattern turns about a centre that it carries along (causalgs.model.kinematic.pattern_motion): then u_k
        # is the velocity of the body's centre and ω_k its spin. Models saved before hold fixed centres (False).
        self.register_buffer("moving_centres", torch.tensor(True))

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        if prefix + "f_mat.0.weight" in state_dict and prefix + "pattern_materials" not in state_dict:
            state_dict[prefix + "pattern_materials"] = torch.zeros_like(self.pattern_materials)  # an older model
        state_dict.setdefault(prefix + "frame_twists", torch.zeros_like(self.frame_twists))  # saved before T existed
        state_dict.setdefault(prefix + "moving_centres", torch.tensor(False))  # saved when centres stood still
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def reframe(self, sim) -> None:
        """The same fields after the world is re-posed by ``sim`` (x' = s R x + t): the codes, mixtures and materials
        of a material point do not change, and every pattern's twist (u, ω) about its centre c becomes
        (s R u, R ω) about s R c + t, so the velocity field moves with the world (v' = s R v)."""
        self.enc.reframe(sim)
        K = self.config.patterns
        B = torch.zeros(6, 6, dtype=torch.float64)
        R = torch.tensor(sim.R, dtype=torch.float64)
        B[:3, :3], B[3:, 3:] = sim.scale * R, R
        block = torch.block_diag(*([B] * K))  # rows of the last layer: pattern k's (u, ω) at 6k..6k+5
        last = self.f_weight[-1]
        with torch.no_grad():
            last.weight.copy_((block @ last.weight.double()).to(last.weight.dtype))
            last.bias.copy_((block @ last.bias.double()).to(last.bias.dtype))
            T = self.frame_twists.double().reshape(len(self.frame_twists), K * 6)
            self.frame_twists.copy_((T @ block.T).reshape(self.frame_twists.shape).to(self.frame_twists.dtype))
            self.centres.copy_(torch.as_tensor(sim.points(self.centres.double().numpy())).to(self.centres.dtype))
            if self.flow is not None:  # v' = s R v
                out = self.flow.out
                out.weight.copy_((B[:3, :3] @ out.weight.double()).to(out.weight.dtype))
                out.bias.copy_((B[:3, :3] @ out.bias.double()).to(out.bias.dtype))

    def motion_parameters(self) -> list[nn.Parameter]:
        """The weights of the motion: f_vel, f_neck, f_weight (and the unstructured :class:`Flow`, if any)."""
        nets = [*self.f_vel.parameters(), *self.f_neck.parameters(), *self.f_weight.parameters()]
        return nets + ([*self.flow.parameters()] if self.flow is not None else [])

    # -- per particle ----------------------------------------------------------------------------------------------
    def code(self, p: torch.Tensor) -> torch.Tensor:
        """z = f_vel(γ(p)) [N, code_dim]."""
        return self.f_vel(self.enc(p))

    def mixture(self, z: torch.Tensor) -> torch.Tensor:
        """h = softmax(f_neck(z)) [N, K]."""
        return torch.softmax(self.f_neck(z), dim=-1)

    def materials(self, p: torch.Tensor, h: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """E, nu, density [N] from f_mat(γ(p)) + h·Θ (``h``: the particles' motion mixtures [N, K]; None leaves out
        the per-pattern offsets), each inside its configured range."""
        c = self.config
        if c.materials == "global":
            a = self.f_mat[-1].bias.to(p.dtype).expand(len(p), 3)
        else:
            a = self.f_mat(self.enc(p))
            if h is not None:
                a = a + h.to(a.dtype) @ self.pattern_materials.to(a.dtype)
        s = torch.sigmoid(a)
        logE0, logE1 = math.log(c.E_range[0]), math.log(c.E_range[1])
        return {
            "E": torch.exp(logE0 + s[:, 0] * (logE1 - logE0)),
            "nu": c.nu_range[0] + s[:, 1] * (c.nu_range[1] - c.nu_range[0]),
            "density": c.density_range[0] + s[:, 2] * (c.density_range[1] - c.density_range[0]),
        }

    # -- per time ---------------------------------------------------------------------------------------------------
    def twists(self, t: torch.Tensor) -> torch.Tensor:
        """W_t = f_weight(γ_t(t)) + T(t) [T, K, 6]: linear (u) then angular (ω) velocity of every pattern."""
        t = torch.as_tensor(t, dtype=self.centres.dtype).reshape(-1, 1)
        W = self.f_weight(self.enc_t(t)).reshape(len(t), self.config.patterns, 6)
        n = len(self.frame_twists)
        if n == 0:
            return W
        s = (t[:, 0] / self.duration * (n - 1)).clamp(0.0, n - 1.0)  # in knots; held at the ends
        i = s.detach().floor().long().clamp(max=n - 2)
        w = (s - i.to(s.dtype))[:, None, None]
        T = self.frame_twists.to(W.dtype)
        return W + (1.0 - w) * T[i] + w * T[i + 1]

    def place_centres(self, x: torch.Tensor, h: torch.Tensor, least: float = 1e-3) -> torch.Tensor:
        """Put every pattern's centre at the h-weighted mean of the canonical positions ``x`` [N, 3] (``h`` [N, K]):
        a body turns about its centre of mass, so a spin does not move it. Patterns with less than ``least`` of a
        particle's weight keep their centre. Returns each pattern's radius of gyration about it [K] (the mean
        distance a unit spin moves its points by; 0 for those patterns)."""
        with torch.no_grad():
            w = h.detach().to(self.centres.dtype)
            x = x.detach().to(w.dtype)
            mass = w.sum(0)
            com = (w.T @ x) / mass.clamp_min(1e-12)[:, None]
            held = mass > least
            self.centres.copy_(torch.where(held[:, None], com, self.centres))
            spread = (w * ((x[:, None, :] - com[None]) ** 2).sum(-1)).sum(0) / mass.clamp_min(1e-12)
            return torch.where(held, spread.sqrt(), torch.zeros_like(spread))

    def affine(self, h: torch.Tensor, t: torch.Tensor, centres: torch.Tensor | None = None):
        """Per-particle velocity field at times t: v_i(x, t) = a[t, i] + ω[t, i] × x. Returns a, ω [T, N, 3].
        ``centres`` [K, 3] or [T, K, 3]: where the patterns' centres are at those times (default: where they start,
        exact at t = 0 and for fixed centres)."""
        W = self.twists(t)
        u, w = W[..., :3], W[..., 3:]
        c = self.centres if centres is None else centres.to(w.dtype)
        a_k = u - torch.linalg.cross(w, c.expand_as(w))  # u_k − ω_k × c_k
        return torch.einsum("nk,tkd->tnd", h, a_k), torch.einsum("nk,tkd->tnd", h, w)

    @property
    def structured(self) -> bool:
        """Whether the motion is the velocity field decomposition (patterns and basis), not :class:`Flow`."""
        return self.flow is None

    def flow_velocity(self, x0: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        """The unstructured velocities [T, N, 3] of the material points at canonical ``x0`` at times ``t`` [T]."""
        t = torch.as_tensor(t, dtype=x0.dtype).reshape(-1, 1)
        return self.flow(self.enc(x0), self.enc_t(t))

    def velocity(self, p: torch.Tensor, t: float, h: torch.Tensor | None = None) -> torch.Tensor:
        """v(p, t) [N, 3] for particles at p whose mixtures are h (default: computed at p, i.e. canonical p). With
        the unstructured field (:class:`Flow`), p is the particles' canonical position."""
        if self.flow is not None:
            return self.flow_velocity(p, torch.tensor([float(t)], dtype=torch.float64))[0]
        if h is None:
            h = self.mixture(self.code(p))
        a, w = self.affine(h, torch.tensor([float(t)]))
        return a[0] + torch.linalg.cross(w[0], p)


def basis(p: torch.Tensor, centre: torch.Tensor) -> torch.Tensor:
    """B(p) [N, 6, 3]: the six divergence-free velocity fields e_x, e_y, e_z (translations) and e_k × (p − c)
    (rotations about ``centre``). v = V · B(p) for a twist V ∈ R^6; used by tests and analysis, the integrator uses
    the equivalent affine form."""
    r = p - centre
    eye = torch.eye(3, dtype=p.dtype).expand(len(p), 3, 3)
    rot = torch.linalg.cross(torch.eye(3, dtype=p.dtype)[None].expand(len(p), 3, 3), r[:, None, :].expand(-1, 3, -1))
    return torch.cat([eye, rot], dim=1)
