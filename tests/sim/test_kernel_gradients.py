"""Taichi's autodiff through one substep of the forward kernels against float64 finite differences.

This is a design check for the checkpointed backward (built on top of these kernels): p2g, grid_update and g2p obey
the global data access rule and differentiate exactly. Slow cold: the gradient kernels take ~2.5 minutes to compile
on 2 cores, seconds from the offline cache.
"""

from __future__ import annotations

import pytest
import torch

from causalgs.sim import SimConfig, Simulator, kernels

pytestmark = [pytest.mark.slow, pytest.mark.gradcheck]


def test_one_substep_gradients_match_finite_differences(ti64, mk):
    x0 = mk.block((0.5, 0.5, 0.5), count=4)
    n = len(x0)
    store = mk.store(n)
    mk.fill(store, x0)
    g = torch.Generator().manual_seed(0)
    d = torch.float64
    v = torch.randn(n, 3, generator=g, dtype=d)
    C = 0.5 * torch.randn(n, 3, 3, generator=g, dtype=d)
    F = torch.eye(3, dtype=d) + 0.05 * torch.randn(n, 3, 3, generator=g, dtype=d)
    wt = torch.randn(n, 3, generator=g, dtype=d)
    sim = Simulator(store, SimConfig(res=16, effects="gravity:g=0.1,0.2,-9.8;linear_drag:c=0.3;walls"))
    dt = 1e-3

    def loss() -> float:
        sim.set_state(x0, v, C, F)
        sim.substep(0, dt)
        x1 = store.to_torch("x_seg")[:, 1]
        return float((x1 * wt).sum())

    # Forward, then the three gradient kernels in reverse, seeded with dL/dx[:, 1] = wt.
    loss()
    store.zero_grad()
    seed = torch.zeros(n, sim.k + 1, 3, dtype=d)
    seed[:, 1] = wt
    store.from_torch("x_seg", seed, grad=True)
    st, gr, geo = store, sim.grid, sim.geo
    x, vs, Cs, Fs = st.x_seg, st.v_seg, st.C_seg, st.F_seg
    kernels.g2p.grad(x, vs, Cs, gr.v_out, 0, n, dt, geo.lo, geo.inv_dx)
    kernels.grid_update.grad(gr.v_in, gr.m, gr.v_out, dt, geo.lo, geo.dx, sim.effects)
    kernels.p2g.grad(x, vs, Cs, Fs, st.mass, st.vol, st.E, st.nu, gr.v_in, gr.m, 0, n, dt, geo.lo, geo.inv_dx,
                     sim.config.material)  # fmt: skip

    def fd(set_value, base, h):
        set_value(base + h)
        lp = loss()
        set_value(base - h)
        lm = loss()
        set_value(base)
        return (lp - lm) / (2 * h)

    # d L / d log E (all particles scaled together).
    E = store.to_torch("E")
    ad = float((store.to_torch("E", grad=True) * E).sum())
    num = fd(lambda s: store.from_torch("E", E * s), 1.0, 1e-5)
    assert abs(ad - num) <= 1e-6 * abs(num)
    # d L / d g (an effect parameter).
    g_ad = sim.effects.term("gravity").p.grad.to_numpy()
    g0 = sim.effects.get("gravity", "g")
    for i in range(3):
        e = torch.zeros(3, dtype=d).numpy()
        e[i] = 1.0
        num = fd(lambda s, e=e: sim.effects.set("gravity", g=g0 + s * e), 0.0, 1e-4)
        assert abs(g_ad[i] - num) <= 1e-5 * abs(num) + 1e-12
    # d L / d v[0, 0] (a particle's initial state).
    v_ad = float(store.to_torch("v_seg", grad=True)[0, 0, 0])

    def set_v(s):
        v[0, 0] = s

    num = fd(set_v, float(v[0, 0]), 1e-5)
    assert abs(v_ad - num) <= 1e-6 * abs(num)
