"""Worker processes for independent pieces of Taichi work, each on a CPU of its own.

On the CPU backend a Taichi process runs best pinned to one CPU (:mod:`causalgs._ti`: every parallel loop is a
handoff to Taichi's pool, and unpinned each wakes a thread on another CPU). So the processes of :func:`pinned_pool`
are spawned (Taichi's runtime must not be forked), start Taichi with the caller's device and precision and one
thread, and each takes the next CPU of those the caller started with. Where the caller keeps working while they
run (``caller_busy``), the CPUs it is not pinned to come first, so that it keeps one of its own.

A caller that is stopped (Ctrl-C, SIGTERM, which the command line turns into an exit, or an error) ends its pool
with :func:`stop`: the workers are terminated rather than waited for, and only the pool's own.
"""

from __future__ import annotations

import itertools
import multiprocessing
import os


def worker_cpus(caller_busy: bool) -> list[int] | None:
    """The CPUs the workers of :func:`pinned_pool` take in turn (None: the system does not say)."""
    from causalgs import _ti

    allowed = _ti.allowed_cpus()
    if not allowed:
        return None
    if not caller_busy or not hasattr(os, "sched_getaffinity"):
        return allowed
    mine = os.sched_getaffinity(0)
    return [c for c in allowed if c not in mine] + [c for c in allowed if c in mine]


def shares(cpus: list[int] | None, jobs: int) -> list[list[int]] | None:
    """``cpus`` split into ``jobs`` shares as even as they can be, in order (``[0, 1, 2, 3]`` over 2: ``[[0, 1],
    [2, 3]]``); with more jobs than CPUs each job has one CPU and the CPUs are taken in turn. None (the system
    does not say) stays None."""
    if not cpus:
        return None
    n = len(cpus)
    if jobs >= n:
        return [[cpus[j % n]] for j in range(jobs)]
    bounds = [j * n // jobs for j in range(jobs + 1)]
    return [cpus[a:b] for a, b in itertools.pairwise(bounds)]


def pinned_pool(jobs: int, *, caller_busy: bool = False):
    """A ``ProcessPoolExecutor`` of ``jobs`` spawned processes, Taichi started in each as in this one, one thread
    and one CPU each (see the module docstring)."""
    from concurrent.futures import ProcessPoolExecutor

    from causalgs import _ti

    rt = _ti.runtime()
    ctx = multiprocessing.get_context("spawn")
    slots = ctx.Value("i", 0)  # each worker takes the next and runs on that CPU
    args = (rt.device, rt.precision, rt.debug, slots, worker_cpus(caller_busy))
    return ProcessPoolExecutor(int(jobs), mp_context=ctx, initializer=_init, initargs=args)


def stop(pool) -> None:
    """Terminate the worker processes of ``pool`` (a ``ProcessPoolExecutor``) now, rather than wait for the work
    under way, and shut it down; pending work is cancelled. Other child processes of the caller are left alone.

    The pool's own management thread sees its workers end and reaps them; they are not joined here as well, or a
    worker could be reaped twice and then read as alive ever after."""
    for p in list((getattr(pool, "_processes", None) or {}).values()):
        p.terminate()
    pool.shutdown(wait=True, cancel_futures=True)


def _init(device: str, precision: str, debug: bool, slots, cpus: list[int] | None) -> None:
    from causalgs import _ti

    os.environ[_ti.TI_THREADS_ENV] = "1"  # a worker is one CPU's share of the work ...
    os.environ.pop(_ti.CPUS_ENV, None)  # ... not the caller's CPUs ...
    with slots.get_lock():
        slot = slots.value
        slots.value += 1
    if cpus:  # ... but one of them, of its own
        _ti.pin([cpus[slot % len(cpus)]])
    _ti.init(device, precision, debug=debug, quiet=True)
