"""The checkpointed backward and its torch boundary against float64 finite differences and a full tape.

One scene exercises every registered effect at once (each with a parameter that matters): an elastoplastic block
thrown against a tilted Coulomb ground (on grid nodes), a tilted Coulomb floor (met by the particles) and a sticky
side plane, under gravity, a force field, linear and quadratic drag, an attractor and material damping. Its rollout
spans several checkpoint segments; a loss on positions, velocities and deformation gradients at three output times
is differentiated with respect to x0, v0, E, nu, density and every effect parameter. The substep is fixed
(``SimConfig.dt``) so that finite differences see the same schedule.
"""

from __future__ import annotations

import pytest
import torch

from causalgs.errors import CausalGSError
from causalgs.sim import REGISTRY
from causalgs.sim.autograd import simulate

pytestmark = [pytest.mark.gradcheck]

D = torch.float64


def test_every_effect_parameter_is_exercised(mk):
    names = {part.split(":")[0] for part in mk.ALL_EFFECTS.split(";")}
    assert names == set(REGISTRY), "the gradient scene must use every registered effect"


def test_gradients_match_finite_differences(ti64, mk):
    sim, inp, w = mk.throw(segment=2)
    assert sum(len(s.dts) for s in sim_tape_segments(sim, inp, mk.THROW_TIMES)) == 14
    mk.check_gradients(sim, inp, w)


def sim_tape_segments(sim, inp, times):
    """The segments of a fresh rollout of the scene (to check it spans several checkpoints)."""
    for name in ("E", "nu", "density"):
        sim.store.from_torch(name, inp[name])
    sim.set_state(inp["x0"], inp["v0"])
    _, tape = sim.rollout(times)
    return tape.segments


def test_checkpointed_equals_full_tape(ti64, mk):
    """Segments of 2 substeps (7 checkpoints, 6 replays) against one segment holding all 14 substeps."""
    grads = []
    for segment in (2, 16):
        sim, inp, w = mk.throw(segment=segment)
        leaves = {k: v.clone().requires_grad_(True) for k, v in inp.items()}
        mk.throw_loss(sim, leaves, w).backward()
        grads.append({k: v.grad for k, v in leaves.items()})
    for k in grads[0]:
        scale = float(grads[1][k].abs().max())
        err = float((grads[0][k] - grads[1][k]).abs().max())
        assert err <= 1e-10 * max(scale, 1.0), f"{k}: checkpointed and full-tape gradients differ by {err:.3g}"


def test_backward_after_another_rollout(ti64, mk):
    """A second forward between a forward and its backward does not change the first one's gradients."""
    sim, inp, w = mk.throw(segment=2)
    a = {k: v.clone().requires_grad_(True) for k, v in inp.items()}
    mk.throw_loss(sim, a, w).backward()
    b = {k: v.clone().requires_grad_(True) for k, v in inp.items()}
    loss_b = mk.throw_loss(sim, b, w)
    other = {**inp, "E": inp["E"] * 2, "v0": -inp["v0"]}
    with torch.no_grad():
        mk.throw_loss(sim, other, w)
    loss_b.backward()
    for k in a:
        assert torch.allclose(a[k].grad, b[k].grad, rtol=1e-10, atol=1e-12), k


def test_bad_inputs_are_one_line_errors(ti64, mk):
    sim, inp, _ = mk.throw(segment=2)
    times = mk.THROW_TIMES
    with pytest.raises(CausalGSError, match=r"x0 has shape \[3, 3\]"):
        simulate(sim, inp["x0"][:3], inp["v0"], inp["E"], inp["nu"], inp["density"], times)
    with pytest.raises(CausalGSError, match="sorted"):
        simulate(sim, inp["x0"], inp["v0"], inp["E"], inp["nu"], inp["density"], (0.02, 0.01))
    with pytest.raises(CausalGSError, match=r"effect parameters: got 2 values"):
        simulate(sim, inp["x0"], inp["v0"], inp["E"], inp["nu"], inp["density"], times, torch.zeros(2, dtype=D))
    with pytest.raises(CausalGSError, match=r"material 'nu' has shape"):
        simulate(sim, inp["x0"], inp["v0"], inp["E"], inp["nu"][:5], inp["density"], times)


@pytest.mark.slow
def test_hand_written_p2g_adjoint_equals_autodiff(ti64, mk):
    """p2g_adjoint against Taichi's own autodiff of p2g (slow: p2g.grad compiles for about a minute)."""
    from causalgs.sim import kernels

    sim, inp, _ = mk.throw(segment=2)
    st, g = sim.store, sim.grid
    n = st.n
    gen = torch.Generator().manual_seed(3)
    sim.set_state(inp["x0"] + 0.01 * torch.randn(n, 3, generator=gen, dtype=D), inp["v0"])
    st.from_torch("mpm_affine", torch.randn(n, 3, 3, generator=gen, dtype=D))
    kernels.particle_box(st.x_seg, 0, n, sim._lo(), sim.geo.inv_dx, sim.geo.shape, g.box)
    g.v_in.grad.from_torch(torch.randn(*g.v_in.shape, 3, generator=gen, dtype=D))
    g.m.grad.from_torch(torch.randn(*g.m.shape, generator=gen, dtype=D))
    out = []
    for kernel in (kernels.p2g.grad, kernels.p2g_adjoint):
        st.zero_grad(["x_seg", "v_seg", "mpm_affine", "density"])
        kernel(*sim._p2g_args(0))
        out.append([st.to_torch(k, grad=True) for k in ("x_seg", "v_seg", "mpm_affine", "density")])
    for a, b, name in zip(*out, ("x", "v", "affine", "density"), strict=True):
        assert torch.allclose(a, b, rtol=1e-12, atol=1e-12 * float(a.abs().max())), name


@pytest.mark.slow
def test_hand_written_g2p_adjoint_equals_autodiff(ti64, mk):
    """g2p_adjoint against Taichi's own autodiff of g2p (slow: g2p.grad compiles for tens of seconds)."""
    from causalgs.sim import kernels

    sim, inp, _ = mk.throw(segment=2)
    st, g, geo = sim.store, sim.grid, sim.geo
    n = st.n
    gen = torch.Generator().manual_seed(4)
    sim.set_state(inp["x0"] + 0.01 * torch.randn(n, 3, generator=gen, dtype=D), inp["v0"])
    kernels.particle_box(st.x_seg, 0, n, sim._lo(), geo.inv_dx, geo.shape, g.box)
    g.v_out.from_torch(torch.randn(*g.v_out.shape, 3, generator=gen, dtype=D))
    seeds = {"x_seg": (3,), "v_seg": (3,), "C_seg": (3, 3)}
    out = []
    for kernel in (kernels.g2p.grad, kernels.g2p_adjoint):
        st.zero_grad(list(seeds))
        g.v_out.grad.fill(0)
        for k, shape in seeds.items():
            st.from_torch(k, torch.randn(n, *shape, generator=torch.Generator().manual_seed(9), dtype=D), grad=True,
                          slot=1)  # fmt: skip
        kernel(st.x_seg, st.v_seg, st.C_seg, g.v_out, 0, n, 1e-3, sim._lo(), geo.inv_dx)
        out.append([st.to_torch("x_seg", grad=True, slot=0), g.v_out.grad.to_torch()])
    for a, b, name in zip(*out, ("x", "grid v_out"), strict=True):
        assert torch.allclose(a, b, rtol=1e-12, atol=1e-12 * float(a.abs().max())), name


_SERIAL = """
import sys, torch
sys.path.insert(0, {here!r})
import conftest
from causalgs import _ti
_ti.init("cpu", "float64")
assert _ti.serial_loops(), "one Taichi thread on the CPU runs every loop serially"
torch.save(conftest.throw_gradients(segment=2), {out!r})
"""


def test_serial_loops_give_the_pools_loss_and_gradients(ti64, mk, tmp_path):
    """With one Taichi thread on the CPU every top-level loop of the simulator runs on the launching thread
    (:func:`causalgs._ti.serial_loops`, as in discovery's rollout workers): a fresh process with
    ``$CAUSALGS_TI_THREADS=1`` gives the throw's loss and gradients of this process's pool (all cores: parallel
    loops wherever the machine has more than one)."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    from causalgs import _ti

    out = tmp_path / "serial.pt"
    code = _SERIAL.format(here=str(Path(__file__).parent), out=str(out))
    env = {**os.environ, _ti.TI_THREADS_ENV: "1"}
    env.pop(_ti.CPUS_ENV, None)
    done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=900)
    assert done.returncode == 0, done.stderr[-2000:]
    serial = torch.load(out)
    assert _ti.serial_loops() == (_ti.runtime().threads == 1)
    pooled = mk.throw_gradients(segment=2)
    assert set(serial) == set(pooled) and len(pooled) == 7, sorted(serial)  # the loss and 6 inputs' gradients
    loss = pooled.pop("loss")
    assert torch.allclose(serial["loss"], loss, rtol=1e-12, atol=0), (float(serial["loss"]), float(loss))
    for k, grad in pooled.items():
        scale = max(float(grad.abs().max()), 1.0)
        err = float((serial[k] - grad).abs().max())
        assert err <= 1e-10 * scale, f"{k}: serial and pooled gradients differ by {err:.3g}"
