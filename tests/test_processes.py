"""causalgs.processes: stopping a pool of worker processes."""

import multiprocessing
import time
from concurrent.futures import CancelledError, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool

import pytest

from causalgs.processes import stop


def test_stop_terminates_the_pools_own_workers_at_once_and_leaves_other_children_running(tmp_path):
    """A pool stopped while its worker runs a minute-long task ends in seconds, the task never finishes and the
    pending one never starts, while another child process of the caller (here a plain process; in discovery, the
    workers of another pool) keeps running."""
    ctx = multiprocessing.get_context("spawn")
    other = ctx.Process(target=time.sleep, args=(120,), daemon=True)
    other.start()
    mark = tmp_path / "mark"
    # a task that says it started, runs a minute and says it finished (exec: a builtin the spawned worker
    # unpickles, where a function of this test module would not import)
    task = (f"import pathlib, time\np = pathlib.Path({str(mark)!r})\np.write_text('started')\n"
            "time.sleep(60)\np.write_text('finished')\n")  # fmt: skip
    try:
        pool = ProcessPoolExecutor(1, mp_context=ctx)
        running = pool.submit(exec, task, {})
        pending = pool.submit(exec, task.replace("started", "second"), {})
        t0 = time.monotonic()
        while not mark.exists():
            assert time.monotonic() - t0 < 60, "the worker never started its task"
            time.sleep(0.05)
        workers = list(pool._processes.values())
        t0 = time.monotonic()
        stop(pool)
        assert time.monotonic() - t0 < 30  # the task would have taken a minute
        for p in workers:
            p.join(10)
            assert not p.is_alive()
        assert mark.read_text() == "started"
        with pytest.raises((BrokenProcessPool, CancelledError)):
            running.result(timeout=10)
        assert pending.cancelled() or pending.exception(timeout=10) is not None
        assert other.is_alive()
    finally:
        other.terminate()
        other.join(10)
