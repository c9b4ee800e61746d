"""A plain-torch MLS-MPM substep with the same maths as :mod:`causalgs.sim.kernels` (tests only).

Dense and slow on purpose: a few hundred particles on a small grid. Effects are given as ``[(name, params), ...]``
with ``params`` a dict of float tuples (what :func:`causalgs.sim.effects.parse_spec` returns, defaults filled in).
"""

from __future__ import annotations

import itertools

import torch

from causalgs.sim.effects import EPS, GRID_STAGES, PARTICLE, REGISTRY, WALL_BAND, parse_spec
from causalgs.sim.materials import POLAR_ITERS, lame


def polar_rotation(F: torch.Tensor) -> torch.Tensor:
    R = F
    for _ in range(POLAR_ITERS):
        R = 0.5 * (R + torch.linalg.inv(R).transpose(-1, -2))
    return R


def kirchhoff(F: torch.Tensor, mu: torch.Tensor, lam: torch.Tensor, model: str) -> torch.Tensor:
    """τ = P Fᵀ of each F [n, 3, 3] (see :mod:`causalgs.sim.materials`)."""
    I = torch.eye(3, dtype=F.dtype).expand_as(F)
    mu, lam = mu[:, None, None], lam[:, None, None]
    Ft = F.transpose(-1, -2)
    J = torch.linalg.det(F)[:, None, None]
    if model == "neo_hookean":
        return mu * (F @ Ft - I) + lam * torch.log(J) * I
    if model == "stvk":
        G = 0.5 * (Ft @ F - I)
        tr = G.diagonal(dim1=-2, dim2=-1).sum(-1)[:, None, None]
        return F @ (2.0 * mu * G + lam * tr * I) @ Ft
    if model == "fixed_corotated":
        R = polar_rotation(F)
        return 2.0 * mu * (F - R) @ Ft + lam * (J - 1.0) * J * I
    raise ValueError(model)


def effects_list(spec: str) -> list[tuple[str, dict[str, tuple[float, ...]]]]:
    """Parse a spec and fill in defaults, in the kernels' application order: by stage (forces, then boundary
    conditions), and by name within a stage, whatever the order of the spec (forces such as a drag and an attractor
    do not commute within a substep)."""
    out = []
    for name, values in parse_spec(spec):
        d = REGISTRY[name]
        out.append((name, {p.name: tuple(values.get(p.name, p.default)) for p in d.params}))
    return sorted(out, key=lambda e: (REGISTRY[e[0]].order, e[0]))


def _vec(p, name, dtype):
    return torch.tensor(p[name], dtype=dtype)


def _norm(v: torch.Tensor) -> torch.Tensor:
    return torch.sqrt((v * v).sum(-1, keepdim=True) + EPS * EPS)


def _contact(v, x, p, dx):
    n = _vec(p, "n", v.dtype)
    n = n / torch.sqrt((n * n).sum() + EPS * EPS)
    phi = x @ n - p["d"][0]
    return n, torch.clamp(0.5 - phi / dx, 0.0, 1.0)[:, None]


def _apply_effects(v: torch.Tensor, x: torch.Tensor, I: torch.Tensor, dt: float, dx: float, shape, effects):
    for name, p in effects:
        if REGISTRY[name].order not in GRID_STAGES:
            continue
        if name in ("gravity", "force"):
            v = v + dt * _vec(p, "g" if name == "gravity" else "b", v.dtype)
        elif name == "linear_drag":
            v = v * torch.exp(torch.tensor(-p["c"][0] * dt, dtype=v.dtype))
        elif name == "quadratic_drag":
            v = v / (1.0 + p["k"][0] * dt * _norm(v))
        elif name == "attractor":
            v = v - dt * p["k"][0] * (x - _vec(p, "c", v.dtype))
        elif name == "ground":
            n, w = _contact(v, x, p, dx)
            vn = (v @ n)[:, None]
            vt = v - vn * n
            scale = torch.clamp(1.0 + p["mu"][0] * vn / _norm(vt), min=0.0)
            vc = torch.where(vn < 0, vt * scale, v)
            v = v + w * (vc - v)
        elif name == "ground_sticky":
            _, w = _contact(v, x, p, dx)
            v = (1.0 - w) * v
        elif name == "walls":
            hi = torch.tensor(shape) - WALL_BAND
            into = ((I < WALL_BAND) & (v < 0)) | ((I >= hi) & (v > 0))
            v = torch.where(into, torch.zeros_like(v), v)
        else:
            raise ValueError(f"no reference for effect '{name}'")
    return v


def _particle_effects(v: torch.Tensor, x: torch.Tensor, dt: float, effects) -> torch.Tensor:
    for name, p in effects:
        if REGISTRY[name].order != PARTICLE:
            continue
        if name == "floor":
            n = _vec(p, "n", v.dtype)
            n = n / torch.sqrt((n * n).sum() + EPS * EPS)
            vn = (v @ n)[:, None]
            push = torch.clamp((p["d"][0] - (x @ n)[:, None]) / dt - vn, min=0.0)
            vt = v - vn * n
            scale = torch.clamp(1.0 - p["mu"][0] * push / _norm(vt), min=0.0)
            v = scale * vt + (vn + push) * n
        else:
            raise ValueError(f"no reference for effect '{name}'")
    return v


def _project(F: torch.Tensor, mu: torch.Tensor, effects) -> torch.Tensor:
    for name, p in effects:
        if name == "plasticity":
            R = polar_rotation(F)
            S = R.transpose(-1, -2) @ F
            S = 0.5 * (S + S.transpose(-1, -2))
            I = torch.eye(3, dtype=F.dtype)
            m = S.diagonal(dim1=-2, dim2=-1).sum(-1)[:, None, None] / 3.0
            D = S - m * I
            q = 1.5**0.5 * 2.0 * mu[:, None, None] * torch.sqrt((D * D).sum((-1, -2), keepdim=True) + EPS * EPS)
            scale = torch.clamp(p["yield_stress"][0] / q, max=1.0)
            F = R @ (m * I + scale * D)
    return F


def _extra_stress(F: torch.Tensor, C: torch.Tensor, effects) -> torch.Tensor:
    tau = torch.zeros_like(F)
    for name, p in effects:
        if name == "damping":
            tau = tau + p["eta"][0] * torch.linalg.det(F)[:, None, None] * (C + C.transpose(-1, -2))
    return tau


def substep(state: dict, mat: dict, dt: float, lo, dx: float, shape, model: str, effects) -> dict:
    """One substep. ``state``: x [n,3], v [n,3], C [n,3,3], F [n,3,3]; ``mat``: vol, density, E, nu [n]."""
    x, v, C, F = state["x"], state["v"], state["C"], state["F"]
    dtype, n = x.dtype, len(x)
    inv_dx = 1.0 / dx
    lo = torch.tensor(lo, dtype=dtype)
    shape_t = torch.tensor(shape)
    Xp = (x - lo) * inv_dx
    base = torch.clamp(torch.floor(Xp - 0.5).long(), min=torch.zeros(3, dtype=torch.long), max=shape_t - 3)
    fx = Xp - base.to(dtype)
    w = [0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1.0) ** 2, 0.5 * (fx - 0.5) ** 2]

    I3 = torch.eye(3, dtype=dtype)
    mu, lam = lame(mat["E"], mat["nu"])
    F_new = _project((I3 + dt * C) @ F, mu, effects)
    tau = kirchhoff(F_new, mu, lam, model) + _extra_stress(F_new, C, effects)
    mass = mat["density"] * mat["vol"]
    affine = (-dt * mat["vol"] * 4.0 * inv_dx * inv_dx)[:, None, None] * tau + mass[:, None, None] * C
    mv = mass[:, None] * _particle_effects(v, x, dt, effects)

    ncell = int(shape[0] * shape[1] * shape[2])
    grid_p = torch.zeros(ncell, 3, dtype=dtype)
    grid_m = torch.zeros(ncell, dtype=dtype)
    stencil = list(itertools.product(range(3), repeat=3))

    def flat(idx):
        return (idx[:, 0] * shape[1] + idx[:, 1]) * shape[2] + idx[:, 2]

    for i, j, k in stencil:
        off = torch.tensor([i, j, k])
        dpos = (off.to(dtype) - fx) * dx
        weight = w[i][:, 0] * w[j][:, 1] * w[k][:, 2]
        node = flat(base + off)
        grid_p.index_add_(0, node, weight[:, None] * (mv + (affine @ dpos[:, :, None])[:, :, 0]))
        grid_m.index_add_(0, node, weight * mass)

    has = grid_m > 0
    gv = grid_p / torch.where(has, grid_m, torch.ones_like(grid_m))[:, None]
    idx = torch.stack(torch.meshgrid(*[torch.arange(s) for s in shape], indexing="ij"), -1).reshape(-1, 3)
    gv = _apply_effects(gv, lo + idx.to(dtype) * dx, idx, dt, dx, shape, effects)
    gv = torch.where(has[:, None], gv, torch.zeros_like(gv))

    new_v = torch.zeros(n, 3, dtype=dtype)
    new_C = torch.zeros(n, 3, 3, dtype=dtype)
    for i, j, k in stencil:
        off = torch.tensor([i, j, k])
        dpos = off.to(dtype) - fx
        weight = w[i][:, 0] * w[j][:, 1] * w[k][:, 2]
        g_v = gv[flat(base + off)]
        new_v = new_v + weight[:, None] * g_v
        new_C = new_C + (4.0 * inv_dx * weight)[:, None, None] * g_v[:, :, None] * dpos[:, None, :]
    return {"x": x + dt * new_v, "v": new_v, "C": new_C, "F": F_new}
