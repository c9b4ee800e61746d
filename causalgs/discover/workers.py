"""Independent rollouts of a discovery run spread over worker processes.

A Levenberg–Marquardt iteration rolls the model out once per free parameter (the columns of its forward-difference
Jacobian), the screen once per parameter, a scan once per grid point: rollouts that do not depend on one another,
and each holds a single core (on the CPU backend the particles scatter to the grid serially,
:func:`causalgs._ti.serial_scatter`, and most of a rollout is kernel launches). Inside ``with rollout_workers(n):``
(``DiscoverConfig.workers``, ``causalgs discover --workers``) they run in ``n`` spawned processes, each with its own
Taichi runtime of the caller's precision, one thread and one CPU of those the caller started with
(:mod:`causalgs._ti`: pinned, a rollout runs several times faster), while the calling process waits; everything
else stays where it was. The results are the same rollouts: in float64 to the last bit, in float32 to rounding (a
worker's one thread adds its atomic sums in another order than the caller's pool; 6e-8 cm a rollout measured), so
a calibration takes the same steps up to that rounding: only the clock changes.

A model goes to the workers as a file: pickled without its simulator (which a worker builds once on its own runtime,
its kernels from the offline cache) and named by the digest of everything else. A model changed in place (the
residual weights of a weighted base) is a new digest and goes again, so a worker never rolls out a stale one; the
rest shapes of the rest-shape draws go with each rollout instead (:func:`displaced`).
"""

from __future__ import annotations

import contextlib
import hashlib
import pickle
import shutil
import tempfile
from collections import OrderedDict
from pathlib import Path

import torch

from causalgs.errors import CausalGSError

_active: RolloutPool | None = None
KEEP_MODELS = 4  # models a worker keeps built (a round's base and candidates in turn)


class RolloutPool:
    """``jobs`` worker processes for :func:`moved`, :func:`rollouts`, :func:`displaced` and :func:`losses` (see the
    module docstring)."""

    def __init__(self, jobs: int):
        from causalgs.processes import pinned_pool

        self.jobs = int(jobs)
        self.dir = Path(tempfile.mkdtemp(prefix="causalgs-rollouts-"))
        self._files: OrderedDict[str, Path] = OrderedDict()
        self._pool = pinned_pool(self.jobs)  # the caller waits while they roll out: every CPU is theirs

    def model_file(self, model) -> str:
        """The file the workers read ``model`` from, written where its state is new."""
        blob = pickle.dumps(model, protocol=pickle.HIGHEST_PROTOCOL)
        digest = hashlib.sha1(blob).hexdigest()
        path = self._files.get(digest)
        if path is None:
            path = self.dir / f"{digest}.pkl"
            tmp = path.with_suffix(".tmp")
            tmp.write_bytes(blob)
            tmp.replace(path)
            self._files[digest] = path
            while len(self._files) > 4 * KEEP_MODELS:  # old states: no worker asks for them again
                self._files.popitem(last=False)[1].unlink(missing_ok=True)
        self._files.move_to_end(digest)
        return str(path)

    def map(self, fn, calls: list[tuple]) -> list:
        """``fn(*call)`` for every call, in the workers; the results in order."""
        from concurrent.futures.process import BrokenProcessPool

        futures = [self._pool.submit(fn, *call) for call in calls]
        try:
            return [f.result() for f in futures]
        except BrokenProcessPool:
            raise CausalGSError("a rollout worker process died (killed, or out of memory); run again with "
                                "--resume") from None  # fmt: skip
        finally:
            for f in futures:
                f.cancel()

    def close(self, stop: bool = False) -> None:
        """Shut the workers down once their rollouts end; ``stop`` (the caller was stopped: Ctrl-C, SIGTERM, an
        error): terminate them instead, rather than wait for the rollouts under way. What the caller finished is in
        its journal and resumes."""
        from causalgs import processes

        if stop:
            processes.stop(self._pool)
        else:
            self._pool.shutdown(wait=True, cancel_futures=True)
        shutil.rmtree(self.dir, ignore_errors=True)


@contextlib.contextmanager
def rollout_workers(jobs: int):
    """Independent rollouts inside run in ``jobs`` worker processes (1: here, as everywhere outside). Left by an
    exception (Ctrl-C, SIGTERM, which the command line turns into an exit, or an error), the workers are terminated
    at once instead of finishing what they were given."""
    global _active
    if jobs <= 1 or _active is not None:  # nested: the outer pool serves
        yield _active
        return
    pool = RolloutPool(jobs)
    _active = pool
    try:
        yield pool
    except BaseException:
        _active = None
        pool.close(stop=True)
        raise
    _active = None
    pool.close()


def active() -> RolloutPool | None:
    """The pool of the enclosing :func:`rollout_workers`, or None (rollouts run here)."""
    return _active


def moved(model, theta: torch.Tensor, steps: list[torch.Tensor], frames, plan: list[int]) -> list:
    """For every θ of ``steps``, what :func:`~causalgs.discover.calibrate.change` needs: (its positions at
    ``plan``'s substep schedule, or at its own finer one; then also ``theta``'s positions at that one, else None),
    or the simulator's one-line error where the step blew it up. Run by the workers of the active pool."""
    path = _active.model_file(model)
    th = theta.detach().double().clone()
    frames = [int(f) for f in frames]
    return _active.map(_moved, [(path, th, s.detach().double().clone(), frames, list(plan)) for s in steps])


def rollouts(model, thetas: list[torch.Tensor], frames) -> list:
    """For every θ of ``thetas``, (:func:`~causalgs.discover.calibrate.positions` over ``frames``, the substep
    schedule it took) or the simulator's one-line error, in the workers of the active pool."""
    path = _active.model_file(model)
    frames = [int(f) for f in frames]
    return _active.map(_positions, [(path, t.detach().double().clone(), frames) for t in thetas])


def displaced(model, theta: torch.Tensor, frames, plan: list[int], starts) -> list:
    """For every (material, measured points) start of ``starts``: the positions over ``frames`` at ``theta`` and the
    substep schedule ``plan`` from there in place of the model's rest shape
    (:func:`~causalgs.discover.search.displaced_rollouts`), or the simulator's one-line error, in the workers of the
    active pool. The model goes once; each start goes with its own rollout."""
    path = _active.model_file(model)
    th = theta.detach().double().clone()
    frames = [int(f) for f in frames]
    return _active.map(_displaced, [(path, th, frames, list(plan), m.detach().clone(), p.detach().clone())
                                    for m, p in starts])  # fmt: skip


def losses(model, thetas: list[torch.Tensor], frames) -> list[float | None]:
    """:func:`~causalgs.discover.calibrate.mse` at every θ of ``thetas`` (None where the simulation blew up), in
    the workers of the active pool."""
    path = _active.model_file(model)
    frames = [int(f) for f in frames]
    return _active.map(_loss, [(path, t.detach().double().clone(), frames) for t in thetas])


# -- in a worker ---------------------------------------------------------------------------------------------------
_models: OrderedDict[str, object] = OrderedDict()


def _model(path: str):
    m = _models.get(path)
    if m is None:
        with open(path, "rb") as f:
            m = _models[path] = pickle.load(f)
        while len(_models) > KEEP_MODELS:
            _models.popitem(last=False)
    _models.move_to_end(path)
    return m


def _moved(path: str, theta: torch.Tensor, step: torch.Tensor, frames: list[int], plan: list[int]):
    from causalgs.discover.calibrate import positions

    model = _model(path)
    try:
        with model.sim.holding(plan):
            x = positions(model, step, frames)
    except CausalGSError as e:
        return str(e)
    finer = list(model.sim.last_plan)
    if finer == list(plan):
        return x, None
    with model.sim.holding(finer):
        return x, positions(model, theta, frames)


def _positions(path: str, theta: torch.Tensor, frames: list[int]):
    from causalgs.discover.calibrate import positions

    model = _model(path)
    try:
        return positions(model, theta, frames), list(model.sim.last_plan)
    except CausalGSError as e:
        return str(e)


def _displaced(path: str, theta: torch.Tensor, frames: list[int], plan: list[int], material: torch.Tensor,
               points: torch.Tensor):  # fmt: skip
    from causalgs.discover.calibrate import positions

    model = _model(path)
    x0, points0 = model.x0, model.points0
    model.x0, model.points0 = material, points
    try:
        with model.sim.holding(plan):
            return positions(model, theta, frames)
    except CausalGSError as e:
        return str(e)
    finally:
        model.x0, model.points0 = x0, points0


def _loss(path: str, theta: torch.Tensor, frames: list[int]) -> float | None:
    from causalgs.discover.calibrate import _loss as loss

    return loss(_model(path), theta, frames)
