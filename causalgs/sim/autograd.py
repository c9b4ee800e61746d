"""The torch boundary of the simulator: one ``torch.autograd.Function`` around a recorded rollout.

``simulate(sim, x0, v0, E, nu, density, times, params)`` runs the MPM from (x0, v0) with per-particle materials and
the effect parameters ``params`` (the vector of :meth:`~causalgs.sim.effects.Effects.flat`, names in
:meth:`~causalgs.sim.effects.Effects.param_names`) and returns positions, velocities and deformation gradients at the
output ``times``. torch's backward drives the checkpointed Taichi backward (:meth:`Simulator.backward`), so a loss on
any of the outputs reaches x0, v0, E, nu, density and every effect parameter.

The substep schedule (how many substeps between outputs, of what size) is chosen in the forward from the CFL limit
and held fixed in the backward: it is a discretisation choice, not a function of the inputs. Particle volumes come
from the store (rest volumes are geometry, not inferred).

Gradients never pass through Taichi's own torch integration: values are copied into the store and adjoints copied
out, so no leaf tensor's ``.grad`` is touched by Taichi (which would double gradients).
"""

from __future__ import annotations

import torch

from causalgs import _ti
from causalgs.errors import CausalGSError
from causalgs.render.reference import quat_scale_to_cov
from causalgs.sim.mpm import Simulator


def _load(sim: Simulator, E, nu, density, params) -> None:
    st = sim.store
    for name, t in (("E", E), ("nu", nu), ("density", density)):
        if tuple(t.shape) != (st.n,):
            raise CausalGSError(f"material '{name}' has shape {list(t.shape)}, expected [{st.n}]")
        st.from_torch(name, t.detach())
    sim.effects.set_flat(params.detach().cpu().double().numpy())


class _Rollout(torch.autograd.Function):
    @staticmethod
    def forward(ctx, sim: Simulator, times: tuple, x0, v0, E, nu, density, params, C0=None, F0=None):
        _load(sim, E, nu, density, params)
        sim.set_state(x0, v0, C0, F0)
        out, tape = sim.rollout(times, outputs=("x", "v", "F"))
        ctx.sim, ctx.tape = sim, tape
        ctx.save_for_backward(E, nu, density, params)
        dt = x0.dtype
        return out["x"].to(dt), out["v"].to(dt), out["F"].to(dt)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, gx, gv, gF):
        sim, tape = ctx.sim, ctx.tape
        E, nu, density, params = ctx.saved_tensors
        # Other rollouts may have run since the forward: restore this one's materials and parameters (the state is
        # restored from the tape's checkpoints).
        _load(sim, E, nu, density, params)
        g = sim.backward(tape, {"x": gx, "v": gv, "F": gF})

        def cast(t, like):
            return t.to(dtype=like.dtype, device=like.device)

        return (None, None, cast(g["x0"], gx), cast(g["v0"], gv), cast(g["E"], E), cast(g["nu"], nu),
                cast(g["density"], density), cast(g["params"], params), None, None)  # fmt: skip


def simulate(
    sim: Simulator,
    x0: torch.Tensor,
    v0: torch.Tensor,
    E: torch.Tensor,
    nu: torch.Tensor,
    density: torch.Tensor,
    times,
    params: torch.Tensor | None = None,
    *,
    C0: torch.Tensor | None = None,
    F0: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Differentiable rollout: x [T, n, 3], v [T, n, 3], F [T, n, 3, 3] at ``times`` (sorted seconds from 0).

    ``x0, v0`` [n, 3]; ``E, nu, density`` [n]; ``params`` [P] the effect parameters (default: the simulator's
    current values, without gradient). ``n`` must equal ``sim.store.n``; volumes are the store's ``vol``.
    ``C0, F0`` [n, 3, 3]: a starting affine velocity and deformation (default 0 and I; constants, no gradient)."""
    n = sim.store.n
    for name, t, shape in (("x0", x0, (n, 3)), ("v0", v0, (n, 3))):
        if tuple(t.shape) != shape:
            raise CausalGSError(f"simulate: {name} has shape {list(t.shape)}, expected {list(shape)}")
    if params is None:
        params = torch.as_tensor(sim.effects.flat(), dtype=_ti.torch_dtype())
    times = tuple(float(t) for t in torch.as_tensor(times, dtype=torch.float64).reshape(-1).tolist())
    for name, t in (("C0", C0), ("F0", F0)):
        if t is not None and tuple(t.shape) != (n, 3, 3):
            raise CausalGSError(f"simulate: {name} has shape {list(t.shape)}, expected [{n}, 3, 3]")
    C0 = None if C0 is None else C0.detach()
    F0 = None if F0 is None else F0.detach()
    return _Rollout.apply(sim, times, x0, v0, E, nu, density, params, C0, F0)


def deformed_covariance(F: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor) -> torch.Tensor:
    """Σ_t = F Σ Fᵀ [..., n, 3, 3]: the rest covariance of each Gaussian (from quaternion [n, 4] and activated scale
    [n, 3]) carried by its particle's deformation gradient F [..., n, 3, 3]; the rasterizer's ``covs`` input."""
    cov = quat_scale_to_cov(quats, scales)
    return F @ cov @ F.transpose(-1, -2)
