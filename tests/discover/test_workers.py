"""Rollouts in worker processes (:mod:`causalgs.discover.workers`) agree with the same rollouts here: a Jacobian, a
scan and a whole calibration come out as the serial ones do, and a model changed in place is rolled out as it is
now, not as the workers first saw it."""

from __future__ import annotations

import pickle

import numpy as np
import pytest
import torch

from causalgs.errors import CausalGSError
from tests.discover.test_core import _thrown_cube

SPEC = "gravity;ground:mu=0.3;walls"


@pytest.fixture(scope="module")
def bounce():
    """A cube thrown onto a frictional ground (a contact: stiffness and ratio move the points), and its model."""
    from causalgs.discover.model import PhysicsModel

    # A worker runs its kernels on one thread, this process on a pool of them: atomic sums add in another order.
    # In float32 a rollout then differs by rounding (6e-8 cm measured), which a forward-difference Jacobian or a
    # calibration amplifies past these tests' tolerances; in float64 the workers' rollouts are this process's.
    obs, _, _ = _thrown_cube(SPEC, (0.0, 0.0, 0.1), (0.4, 0.0, -1.0), 10, frames=14, precision="float64")
    m = PhysicsModel(obs, SPEC, ("ground.mu", "ground.d"), res=16)
    return m, m.initial(E=1e5, nu=0.35, effects={"ground.mu": 0.5, "ground.d": 0.005})


@pytest.fixture(scope="module")
def pool(bounce):
    """Two workers, started on the runtime ``bounce`` made (they take its precision)."""
    from causalgs.discover.workers import rollout_workers

    with rollout_workers(2) as p:
        yield p


def test_a_model_pickles_without_its_simulator_and_rolls_out_the_same(bounce):
    m, start = bounce
    x = m.rollout(start).numpy()
    state = m.__getstate__()
    assert "plan_of" not in state and "_owner" not in state and state["sim"] is m.sim.config
    back = pickle.loads(pickle.dumps(m))
    assert back.sim is not m.sim and back.names == m.names
    assert np.array_equal(back.rollout(start).numpy(), x)
    assert np.array_equal(m.rollout(start).numpy(), x)  # the shared store went back to the original
    assert pickle.loads(pickle.dumps(m)).sim is back.sim  # unpickled models of one config share one simulator


def test_a_jacobian_from_the_workers_is_the_serial_one(bounce, pool):
    from causalgs.discover import workers
    from causalgs.discover.calibrate import fit_frames, jacobian, positions

    m, start = bounce
    fr = fit_frames(m)
    x = positions(m, start, fr)
    with workers_off():
        serial = jacobian(m, start, fr, base=x)
    assert workers.active() is pool
    par = jacobian(m, start, fr, base=x)
    assert serial.shape == par.shape == (len(x), len(start))
    assert np.abs(serial).max() > 1.0  # cm per unit: every column moves the bounce
    np.testing.assert_allclose(par, serial, rtol=0, atol=1e-6 * np.abs(serial).max())
    # changed in place (the rest shape of a bootstrap draw): the workers roll out the model as it is now
    x0 = m.x0
    try:
        m.x0 = x0 + 0.01
        m.points0 = m.x0
        with workers_off():
            moved_serial = jacobian(m, start, fr)
        moved_par = jacobian(m, start, fr)
    finally:
        m.x0 = m.points0 = x0
    assert np.abs(moved_serial - serial).max() > 1e-3
    np.testing.assert_allclose(moved_par, moved_serial, rtol=0, atol=1e-6 * np.abs(serial).max())


def test_a_scan_and_a_calibration_from_the_workers_are_the_serial_ones(bounce, pool):
    from causalgs.discover.calibrate import calibrate, fit_frames, scanned_start

    m, start = bounce
    fr = fit_frames(m)
    with workers_off():
        scan = scanned_start(m, start, fr)
        fit = calibrate(m, start, iterations=4)
    assert torch.equal(scanned_start(m, start, fr), scan)
    par = calibrate(m, start, iterations=4)
    assert fit.loss < 0.5 * calibrate(m, start, iterations=1).loss or fit.loss < 1e-6
    assert par.evaluations == fit.evaluations
    np.testing.assert_allclose(par.theta.numpy(), fit.theta.numpy(), rtol=0, atol=1e-5)
    assert abs(par.loss - fit.loss) <= 1e-6 * max(fit.loss, 1e-9)


def test_a_step_that_blows_up_is_taken_backwards_and_one_that_blows_up_both_ways_is_the_error(bounce, pool,
                                                                                               monkeypatch):
    """As :func:`~causalgs.discover.calibrate.jacobian` here: the column of a forward step that blows the
    simulation up is the backward difference; where both blow up, the simulator's one line is the error."""
    from causalgs.discover import workers
    from causalgs.discover.calibrate import JAC_STEP, change, fit_frames, jacobian, positions

    m, start = bounce
    fr = fit_frames(m)
    x = positions(m, start, fr)
    plan = m.plan_of[2]
    real = workers.moved

    def forward_blows_up(model, theta, steps, *a):  # the stiffness's forward step
        got = real(model, theta, steps, *a)
        return ["frame 3 blew up" if s[0] > theta[0] else g for s, g in zip(steps, got, strict=True)]

    monkeypatch.setattr(workers, "moved", forward_blows_up)
    J = jacobian(m, start, fr, [0, 1], base=x)
    back = start.clone()
    back[0] -= JAC_STEP
    with workers_off():
        expect = -change(m, start, back, fr, x, plan) / JAC_STEP
    np.testing.assert_allclose(J[:, 0], expect, rtol=0, atol=1e-6 * np.abs(expect).max())
    monkeypatch.setattr(workers, "moved", lambda model, theta, steps, *a: ["frame 3 blew up"] * len(steps))
    with pytest.raises(CausalGSError, match="frame 3 blew up"):
        jacobian(m, start, fr, [0, 1], base=x)


class workers_off:
    """Rollouts here inside, whatever pool is open outside."""

    def __enter__(self):
        from causalgs.discover import workers

        self.kept, workers._active = workers._active, None

    def __exit__(self, *exc):
        from causalgs.discover import workers

        workers._active = self.kept



def test_each_worker_runs_on_a_cpu_of_its_own(bounce, pool):
    import multiprocessing
    import os

    from causalgs import _ti
    from causalgs.discover import workers
    from causalgs.discover.calibrate import fit_frames

    m, start = bounce
    workers.losses(m, [start] * 4, fit_frames(m))  # every worker has started
    cpus = [sorted(os.sched_getaffinity(p.pid)) for p in multiprocessing.active_children()]
    allowed = _ti.allowed_cpus()
    assert len(cpus) == 2 and all(len(c) == 1 and c[0] in allowed for c in cpus), cpus
    if len(allowed) >= 2:
        assert cpus[0] != cpus[1], cpus


def test_rest_shape_draws_from_the_workers_are_the_serial_ones(bounce, pool):
    """Each draw starts the simulation from another rest shape: the workers roll out the same draws, in the same
    order, and the model keeps its own rest shape."""
    from causalgs.discover.calibrate import fit_frames, jacobian
    from causalgs.discover.search import rest_shape_draws

    m, start = bounce
    fr = fit_frames(m)
    fut = list(range(m.obs.observed, len(m.obs.times)))
    J = jacobian(m, start, fr)
    J_fut = jacobian(m, start, fut)
    x0 = m.x0.clone()
    with workers_off():
        serial = rest_shape_draws(m, start, J, 0.002, fut, J_fut, samples=4)
    par = rest_shape_draws(m, start, J, 0.002, fut, J_fut, samples=4)
    assert serial[0].shape == (4, len(start)) and np.abs(serial[1]).max() > 0
    for a, b in zip(serial, par, strict=True):
        np.testing.assert_allclose(b, a, rtol=0, atol=1e-6 * np.abs(a).max())
    assert torch.equal(m.x0, x0) and torch.equal(m.points0, x0)
