"""The Taichi runtime: the only place in the project that calls ``ti.init``.

Import Taichi from here (``from causalgs._ti import ti``): this module silences Taichi's import banner and its
version-check network call before Taichi is loaded. Nothing initialises Taichi at import time; call :func:`init`.

- ``device="cpu"`` (default) runs on the CPU backend.
- ``device="gpu"`` tries CUDA, then Vulkan, and falls back to the CPU with a visible message. It never passes
  ``ti.gpu``: on a machine without a GPU that segfaults in Taichi 1.7.4 (measured here).
- ``precision`` is ``"float32"`` or ``"float64"``; :func:`real` gives the Taichi dtype every field should use and
  :func:`torch_dtype` the matching torch dtype. Finite-difference gradient checks need ``float64``.
- The offline kernel cache is on. Its folder is ``$CAUSALGS_TI_CACHE`` or ``~/.cache/causalgs/taichi``: a gradient
  kernel of the simulator takes minutes to compile cold and seconds from the cache. Its size limit is
  ``$CAUSALGS_TI_CACHE_MB`` (default 1024, at most 2047): Taichi's own default of 100 MB evicts a quarter of the
  cache (least recently used) whenever it is exceeded, and the project's kernels in both precisions, for several
  effect sets and grid shapes, pass 100 MB, so cached gradient kernels were recompiled cold.
- torch runs with ``$CAUSALGS_TORCH_THREADS`` threads (default 1): beside Taichi's own thread pool, one torch
  thread measured ~20× faster than the default for the small ops of this project on 2 cores. Taichi's CPU pool has
  ``$CAUSALGS_TI_THREADS`` threads (default: all cores).
- ``$CAUSALGS_TI_CPUS`` (a CPU list as ``taskset -c`` takes it: ``0``, ``0,2``, ``1-3``) pins the process to those
  CPUs when Taichi starts on the CPU backend. Taichi hands every parallel loop from the launching thread to its
  pool's threads and waits; with a second CPU idle, each handoff wakes a thread there, which on a virtual machine
  is an interrupt to another virtual CPU. Measured on this project's 2-core machines (``causalgs bench``): a
  discovery rollout of the toss landing took 1668 ms unpinned and 739 ms pinned to one CPU (2380 particles, 43
  cells; 240 particles on 20 cells: 220 and 58 ms), the MPM's forward+backward substep 6.21 → 3.58 ms (2197
  particles) and 18.0 → 12.5 ms (8000), the rasterizer's forward+backward 48.8 → 48.2 ms (a second CPU gave it
  nothing). Unset: the process runs where the
  system puts it. Discovery's rollout workers (:mod:`causalgs.discover.workers`) are pinned one CPU each.
"""

from __future__ import annotations

import atexit
import contextlib
import os
import sys
from dataclasses import dataclass
from pathlib import Path

os.environ.setdefault("TI_SKIP_VERSION_CHECK", "ON")  # no network call from ti.init
os.environ.setdefault("ENABLE_TAICHI_HEADER_PRINT", "False")  # no banner on import

import taichi as ti

from causalgs.errors import RuntimeConfigError

DEVICES = ("cpu", "gpu")
PRECISIONS = ("float32", "float64")
CACHE_ENV = "CAUSALGS_TI_CACHE"
THREADS_ENV = "CAUSALGS_TORCH_THREADS"
TI_THREADS_ENV = "CAUSALGS_TI_THREADS"
CACHE_MB_ENV = "CAUSALGS_TI_CACHE_MB"
CPUS_ENV = "CAUSALGS_TI_CPUS"
# the CPUs this process may run on, as it started (before any pinning; None where the system does not say)
_ALLOWED = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None


@dataclass(frozen=True)
class Runtime:
    """What :func:`init` set up. ``arch`` is the backend actually taken ("x64", "arm64", "cuda", "vulkan")."""

    device: str
    precision: str
    arch: str
    debug: bool
    cache_dir: str
    generation: int
    threads: int = 1  # Taichi's CPU pool (``cpu_max_num_threads``)

    @property
    def on_gpu(self) -> bool:
        return self.arch in ("cuda", "vulkan")


_runtime: Runtime | None = None
_generation = 0


def cache_dir() -> Path:
    """The offline kernel cache folder: ``$CAUSALGS_TI_CACHE`` if set, else ``~/.cache/causalgs/taichi``."""
    env = os.environ.get(CACHE_ENV)
    return Path(env).expanduser() if env else Path.home() / ".cache" / "causalgs" / "taichi"


def init(device: str = "cpu", precision: str = "float32", *, debug: bool = False, quiet: bool = False) -> Runtime:
    """Initialise Taichi once for the process and return the :class:`Runtime`.

    Calling it again with the same arguments does nothing. Calling it with different ones resets Taichi: every
    field allocated before (every :class:`~causalgs.store.ParticleStore`) becomes invalid, which the store detects.
    ``debug=True`` turns on Taichi's bounds checks and lets ``ti.ad.Tape(validation=True)`` check the global data
    access rule of differentiated kernels.
    """
    global _runtime, _generation
    if device not in DEVICES:
        raise RuntimeConfigError(f"device '{device}' is not one of {', '.join(DEVICES)}")
    if precision not in PRECISIONS:
        raise RuntimeConfigError(f"precision '{precision}' is not one of {', '.join(PRECISIONS)}")
    if (
        _runtime is not None
        and (_runtime.device, _runtime.precision, _runtime.debug) == (device, precision, debug)
        and _runtime.generation == _generation
    ):
        return _runtime

    if _runtime is not None:
        ti.reset()
    folder = cache_dir()
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise RuntimeConfigError(f"cannot create the Taichi kernel cache folder {folder} ({e.strerror})") from None

    if device == "cpu":  # before Taichi starts its thread pool: threads made later inherit the CPUs
        pin(cpus_from_env())
    fp = ti.f64 if precision == "float64" else ti.f32
    threads = _env_threads(TI_THREADS_ENV, os.cpu_count() or 1)
    # ti.gpu would segfault without a GPU; a list of archs makes Taichi fall back to the CPU cleanly.
    arch = [ti.cuda, ti.vulkan] if device == "gpu" else ti.cpu
    # Taichi prints its start line to stdout; keep stdout for results (JSON lines of `causalgs bench`).
    with contextlib.redirect_stdout(sys.stderr):
        ti.init(
            arch=arch,
            default_fp=fp,
            default_ip=ti.i32,
            debug=debug,
            offline_cache=True,
            offline_cache_file_path=str(folder),
            # Taichi holds the limit in a C int: at most 2047 MB.
            offline_cache_max_size_of_files=min(_env_threads(CACHE_MB_ENV, 1024), 2047) * 1024 * 1024,
            log_level=ti.WARN,
            unrolling_limit=64,  # the store copies unroll 16x3 SH matrices
            cpu_max_num_threads=threads,
        )
    taken = ti.lang.impl.current_cfg().arch.name
    if device == "gpu" and taken not in ("cuda", "vulkan") and not quiet:
        print("causalgs: no CUDA or Vulkan device found; running on the CPU.", file=sys.stderr)

    _set_torch_threads()
    if _generation == 0:
        atexit.register(_shutdown)
    _generation += 1
    _runtime = Runtime(device, precision, taken, debug, str(folder), _generation, threads)
    return _runtime


def _shutdown() -> None:
    """Finalise Taichi at exit: the offline kernel cache is written to disk only when the program is reset (Taichi
    1.7 does not do it at interpreter exit; without this, every process recompiled every kernel)."""
    if _runtime is not None:
        ti.reset()


def _env_threads(name: str, default: int) -> int:
    raw = os.environ.get(name)
    if raw is None:
        return default
    try:
        n = int(raw)
    except ValueError:
        n = 0
    if n < 1:
        raise RuntimeConfigError(f"{name}={raw!r} must be a positive integer")
    return n


def allowed_cpus() -> list[int] | None:
    """The CPUs the process could run on when it started (its affinity before :func:`pin`), or None where the
    system does not tell."""
    return None if _ALLOWED is None else list(_ALLOWED)


def confine(cpus: list[int]) -> None:
    """From now on this process, and every process it starts, uses ``cpus`` only: it runs there (:func:`pin`), and
    :func:`allowed_cpus`, which its worker processes take their CPUs from, is ``cpus``. A table's runs side by side
    each get their own share of the machine this way (:func:`causalgs.processes.shares`)."""
    global _ALLOWED
    pin(cpus)
    if _ALLOWED is not None:
        _ALLOWED = sorted(cpus)


def parse_cpus(text: str) -> list[int]:
    """``"0,2-3"`` → [0, 2, 3]; a malformed list is a one-line error naming ``$CAUSALGS_TI_CPUS``."""
    out: set[int] = set()
    try:
        for part in text.split(","):
            a, _, b = part.strip().partition("-")
            lo, hi = int(a), int(b or a)
            if lo < 0 or hi < lo:
                raise ValueError
            out.update(range(lo, hi + 1))
    except ValueError:
        raise RuntimeConfigError(f"{CPUS_ENV}={text!r} is not a CPU list (e.g. 0 or 0,2 or 1-3)") from None
    return sorted(out)


def cpus_from_env() -> list[int] | None:
    """The CPUs ``$CAUSALGS_TI_CPUS`` names (None: unset), each checked against :func:`allowed_cpus`."""
    raw = os.environ.get(CPUS_ENV)
    if raw is None or not raw.strip():
        return None
    cpus = parse_cpus(raw)
    allowed = allowed_cpus()
    if allowed is not None and not set(cpus) <= set(allowed):
        raise RuntimeConfigError(f"{CPUS_ENV}={raw!r}: this process may run on CPUs {allowed} only")
    return cpus


def pin(cpus: list[int] | None) -> None:
    """Run this thread, and every thread it starts from now on (Taichi's pool, torch's), on ``cpus`` only (None, or
    a system without affinities: nothing changes)."""
    if cpus and hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, cpus)


def _set_torch_threads() -> None:
    import torch

    torch.set_num_threads(_env_threads(THREADS_ENV, 1))


def serial_scatter() -> bool:
    """Whether particle loops that scatter with atomics run serially: on the CPU backend (measured here, 8k
    particles: P2G 2.2 ms with parallel atomics, 0.42 ms serial, where Taichi demotes the atomics; the gathers run as
    fast serially), never on a GPU."""
    return not runtime().on_gpu


def serial_loops() -> bool:
    """Whether every top-level loop of the simulator's kernels runs serially: on the CPU backend with a pool of one
    thread (``$CAUSALGS_TI_THREADS=1``, as in discovery's rollout workers). Taichi hands each parallel loop from the
    launching thread to its pool and waits, even to a single pool thread, which costs two context switches a loop;
    a serial loop runs on the launching thread itself, with the same results (tested: a throw's loss and gradients).
    Measured here, one CPU each, medians of three alternating runs: a discovery rollout of the toss landing took
    79.0 ms serial against 92.7 in the pool (240 particles, 20 cells) and 648 against 659 (2380, 43 cells)."""
    rt = runtime()
    return not rt.on_gpu and rt.threads == 1


def runtime() -> Runtime:
    """The current :class:`Runtime`; raises if :func:`init` has not been called."""
    if _runtime is None:
        raise RuntimeConfigError("Taichi is not initialised: call causalgs._ti.init() first")
    return _runtime


def is_initialized() -> bool:
    return _runtime is not None


def generation() -> int:
    """Increases at every (re)initialisation; objects holding Taichi fields compare it to detect a reset."""
    return _generation


def real():
    """The Taichi float dtype of the current precision."""
    return ti.f64 if runtime().precision == "float64" else ti.f32


def torch_dtype():
    """The torch float dtype of the current precision."""
    import torch

    return torch.float64 if runtime().precision == "float64" else torch.float32


def numpy_dtype():
    import numpy as np

    return np.float64 if runtime().precision == "float64" else np.float32
