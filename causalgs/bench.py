"""Benchmarks: machine-readable speed figures (one JSON object per line), medians of repeated runs.

Speed is measured here, never asserted in tests: these machines are shared and noisy, so figures that are compared
(the Taichi rasterizer against the dense torch reference) are taken side by side in one process on the same inputs.
"""

from __future__ import annotations

import math
import statistics
import time
from collections.abc import Callable, Iterable

import numpy as np
import torch

from causalgs.cameras import Camera, look_at


def bench_scene(n: int, kind: str = "surface", seed: int = 0, dtype=torch.float32) -> dict[str, torch.Tensor]:
    """``n`` Gaussians with degree-3 SH, in one of two layouts.

    - ``surface``: like a trained object: splats on the unit sphere, flattened along the normal, mostly opaque
      (opacity logits ~ N(2, 1)), sized so the splats cover the surface about four times over.
    - ``volume``: a stress case: splats filling the cube [-1, 1]³ at opacity ~0.5, so that every ray crosses dozens
      (~35 per pixel at 10k Gaussians, 256²) before its transmittance runs out.
    """
    g = torch.Generator().manual_seed(seed)
    if kind == "surface":
        normal = torch.randn(n, 3, generator=g, dtype=torch.float64)
        normal /= normal.norm(dim=1, keepdim=True)
        means = normal.to(dtype)
        # Rotation taking z to the normal: the flat (z) axis of each splat lies along the sphere's normal.
        z = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand(n, 3)
        axis = torch.cross(z, normal, dim=1)
        w = 1.0 + normal[:, 2:3]
        quats = torch.cat([w, axis], dim=1)
        quats[w[:, 0] < 1e-6] = torch.tensor([0.0, 1.0, 0.0, 0.0], dtype=torch.float64)
        # Four-fold cover: n · π (2σ)² = 4 · 4π  =>  σ = sqrt(4 / n).
        sigma = math.sqrt(4.0 / n)
        scales = torch.log(torch.tensor([sigma, sigma, 0.1 * sigma])) + 0.2 * torch.randn(n, 3, generator=g)
        opacities = 2.0 + torch.randn(n, generator=g)
        return {
            "means": means,
            "quats": quats.to(dtype),
            "scales": scales.to(dtype),
            "opacities": opacities.to(dtype),
            "sh": (torch.randn(n, 16, 3, generator=g) * 0.2).to(dtype),
        }
    if kind != "volume":
        raise ValueError(f"unknown benchmark scene '{kind}' (surface or volume)")
    base = math.log(0.03 * (1e4 / n) ** (1.0 / 3.0))
    return {
        "means": (torch.rand(n, 3, generator=g, dtype=dtype) - 0.5) * 2.0,
        "quats": torch.randn(n, 4, generator=g, dtype=dtype),
        "scales": base + 0.3 * torch.randn(n, 3, generator=g, dtype=dtype),
        "opacities": torch.randn(n, generator=g, dtype=dtype),
        "sh": torch.randn(n, 16, 3, generator=g, dtype=dtype) * 0.2,
    }


def bench_camera(size: int) -> Camera:
    return Camera.from_blender(look_at([0.0, -3.5, 1.5], [0.0, 0.0, 0.0]), size, size, fov_x=0.8)


KEYS = ("means", "quats", "scales", "opacities", "sh")


def _median_ms(fn: Callable[[], object], repeats: int) -> tuple[float, float]:
    """(first call ms, median ms of the next ``repeats`` calls)."""
    t = time.perf_counter()
    fn()
    first = (time.perf_counter() - t) * 1e3
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t) * 1e3)
    return first, statistics.median(times)


def _forward_backward(render: Callable, leaves: dict[str, torch.Tensor]) -> None:
    """One forward+backward pass of ``render(leaves)`` (loss = Σ image + Σ alpha), the leaves' gradients fresh."""
    for t in leaves.values():
        t.grad = None
    img, alpha = render(leaves)[:2]
    (img.sum() + alpha.sum()).backward()


def _timings(render: Callable, scene: dict[str, torch.Tensor], repeats: int) -> dict[str, float]:
    """Forward (no grad) and forward+backward (loss = Σ image + Σ alpha) timings of ``render(scene)``."""
    leaves = {k: t.clone().requires_grad_(True) for k, t in scene.items()}

    def forward():
        with torch.no_grad():
            return render(scene)

    first_f, fwd = _median_ms(forward, repeats)
    first_fb, fb = _median_ms(lambda: _forward_backward(render, leaves), repeats)
    return {"forward_ms": fwd, "forward_backward_ms": fb, "first_forward_ms": first_f, "first_fb_ms": first_fb}


def render_benchmark(
    sizes: Iterable[int] = (128, 256, 512),
    counts: Iterable[int] = (1_000, 10_000, 100_000),
    repeats: int = 5,
    scene: str = "surface",
    reference_limit: float = 1e8,
) -> Iterable[dict]:
    """One record per (size, count): forward and forward+backward ms (medians) of the Taichi rasterizer and, where
    its compute stays under ``reference_limit`` Gaussian-pixel pairs, of the dense torch reference on the same
    inputs in the same process (pixel-chunked, checkpointed backward, so memory is not the limit)."""
    from causalgs import _ti
    from causalgs.render import rasterize
    from causalgs.render.reference import rasterize_reference

    dtype = _ti.torch_dtype()
    for size in sizes:
        cam = bench_camera(size)
        vm, K = torch.tensor(cam.viewmat, dtype=dtype), torch.tensor(cam.K, dtype=dtype)
        bg = torch.ones(3, dtype=dtype)
        for n in counts:
            p = bench_scene(n, scene, dtype=dtype)

            def ours(q, size=size, vm=vm, K=K, bg=bg):
                return rasterize(*(q[k] for k in KEYS), vm, K, size, size, background=bg)

            def ref(q, size=size, vm=vm, K=K, bg=bg, n=n):
                chunk = max(1, int(2e7 // n))  # ~2e7 pairs per chunk
                return rasterize_reference(*(q[k] for k in KEYS), vm, K, size, size, bg, chunk=chunk)

            t = _timings(ours, p, repeats)
            with torch.no_grad():
                _, alpha, meta = ours(p)
            rec = {
                "bench": "render",
                "scene": scene,
                "precision": _ti.runtime().precision,
                "arch": _ti.runtime().arch,
                "size": size,
                "gaussians": n,
                "tile_entries": meta["n_isect"],
                "coverage": round(float(alpha.mean()), 3),
                "forward_ms": round(t["forward_ms"], 2),
                "forward_backward_ms": round(t["forward_backward_ms"], 2),
                "first_forward_ms": round(t["first_forward_ms"], 1),
                "first_forward_backward_ms": round(t["first_fb_ms"], 1),
                "repeats": repeats,
            }
            if size * size * n <= reference_limit:
                r = _timings(ref, p, max(1, min(3, repeats)))
                rec.update(
                    reference_forward_ms=round(r["forward_ms"], 1),
                    reference_forward_backward_ms=round(r["forward_backward_ms"], 1),
                    speedup_forward=round(r["forward_ms"] / t["forward_ms"], 1),
                    speedup_forward_backward=round(r["forward_backward_ms"] / t["forward_backward_ms"], 1),
                )
            else:
                rec["reference"] = f"skipped: {size * size * n:.1e} Gaussian-pixel pairs"
            yield rec


# -- simulator ------------------------------------------------------------------------------------------------------

SIM_EFFECTS = "gravity;ground:d=0.1:mu=0.3;walls"
SIM_CAPACITY = 32768  # one store for every particle count: one compile per grid resolution


def sim_block(n: int, res: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor, float]:
    """A cube of about ``n`` particles at 8 per cell (spacing dx/2) above the ground plane of the unit box, moving
    down and sideways with a little noise. Returns x [m, 3], v [m, 3] (m = round(n^(1/3))³) and the spacing."""
    import itertools

    side = max(2, round(n ** (1.0 / 3.0)))
    spacing = 0.5 / res
    idx = torch.tensor(list(itertools.product(range(side), repeat=3)), dtype=torch.float64)
    x = torch.tensor([0.5, 0.5, 0.5]) + (idx - (side - 1) / 2) * spacing
    g = torch.Generator().manual_seed(seed)
    v = torch.tensor([0.5, 0.0, -1.0]) + 0.1 * torch.randn(len(x), 3, generator=g, dtype=torch.float64)
    return x, v, spacing


def _sim_setup(store, res: int, n: int, segment: int, effects: str = SIM_EFFECTS):
    from causalgs.sim import SimConfig, Simulator

    x, v, spacing = sim_block(n, res)
    m = len(x)
    store.resize(m)
    store.from_torch("vol", torch.full((m,), spacing**3))
    store.from_torch("density", torch.full((m,), 1.0e3))
    store.from_torch("mass", torch.full((m,), 1.0e3 * spacing**3))
    store.from_torch("E", torch.full((m,), 1.0e5))
    store.from_torch("nu", torch.full((m,), 0.3))
    sim = Simulator(store, SimConfig(res=res, segment=segment, effects=effects))
    sim.set_state(x, v)
    return sim, x, v


def sim_benchmark(
    counts: Iterable[int] = (1_000, 8_000, 32_000),
    resolutions: Iterable[int] = (32, 64),
    repeats: int = 5,
    segment: int = 8,
    segments: int = 2,
) -> Iterable[dict]:
    """One record per (grid resolution, particle count): forward and forward+backward ms per substep (medians over
    ``repeats`` runs of ``segments`` checkpoint segments), the forward with one kernel launch per phase instead of
    the fused substep (``fused_speedup`` = phased / fused, measured in the same process), and the memory the
    differentiable state takes for one simulated second with checkpoints (one segment of slots + a checkpoint per
    segment) and without (a slot per substep), from the field sizes allocated."""
    from causalgs import _ti
    from causalgs.store import ParticleStore

    dtype_bytes = 8 if _ti.runtime().precision == "float64" else 4
    for res in resolutions:
        store = ParticleStore(SIM_CAPACITY, sh_degree=0)
        for n in counts:
            if n > SIM_CAPACITY:
                raise ValueError(f"at most {SIM_CAPACITY} particles in the simulator benchmark, got {n}")
            sim, x, v = _sim_setup(store, res, n, segment)
            dt = sim.stable_dt()
            steps = segment * segments

            def forward(sim=sim, x=x, v=v, dt=dt, steps=steps, phased=False):
                sim.set_state(x, v)
                sim.step(steps, dt, phased=phased)

            def forward_backward(sim=sim, x=x, v=v, dt=dt, steps=steps):
                sim.set_state(x, v)
                out, tape = sim.rollout([steps * dt * (1 - 1e-12)], outputs=("x",))
                sim.backward(tape, {"x": torch.ones_like(out["x"])})

            sim.config.dt = dt  # the rollout plans with the same substep
            first_f, fwd = _median_ms(forward, repeats)
            _, phased = _median_ms(lambda f=forward: f(phased=True), repeats)
            first_fb, fb = _median_ms(forward_backward, repeats)
            sim.config.dt = None
            m = store.n
            per_slot = 2 * 24 * m * dtype_bytes  # x, v, C, F and their adjoints
            grid_nodes = math.prod(sim.geo.shape)
            grid = 2 * 7 * grid_nodes * dtype_bytes
            per_second = math.ceil(1.0 / dt)
            n_seg = math.ceil(per_second / segment)
            yield {
                "bench": "sim",
                "precision": _ti.runtime().precision,
                "arch": _ti.runtime().arch,
                "grid": res,
                "grid_nodes": grid_nodes,
                "particles": m,
                "dt_s": dt,
                "segment": segment,
                "forward_ms_per_substep": round(fwd / steps, 3),
                "forward_backward_ms_per_substep": round(fb / steps, 3),
                "forward_phased_ms_per_substep": round(phased / steps, 3),
                "fused_speedup": round(phased / fwd, 2),
                "backward_over_forward": round(fb / fwd, 2),
                "first_forward_ms": round(first_f, 1),
                "first_forward_backward_ms": round(first_fb, 1),
                "substeps_per_second": per_second,
                "memory_checkpointed_mb": round(((segment + 1) * per_slot + n_seg * per_slot / 2 + grid) / 2**20, 1),
                "memory_full_tape_mb": round(((per_second + 1) * per_slot + grid) / 2**20, 1),
                "repeats": repeats,
            }


def sim_compile_probe(res: int = 32, segment: int = 8, effects: str = SIM_EFFECTS) -> dict:
    """Seconds until the first forward substep and the first backward complete in this process (compile or cache
    load of every MPM kernel and gradient kernel). Run it in a fresh process, with an empty or a filled cache."""
    from causalgs.store import ParticleStore

    store = ParticleStore(SIM_CAPACITY, sh_degree=0)
    t0 = time.perf_counter()
    sim, x, v = _sim_setup(store, res, 1000, segment, effects)
    dt = sim.stable_dt()
    sim.step(1, dt)
    t1 = time.perf_counter()
    sim.set_state(x, v)
    out, tape = sim.rollout([dt * (1 - 1e-12)], outputs=("x",))
    t2 = time.perf_counter()
    sim.backward(tape, {"x": torch.ones_like(out["x"])})
    t3 = time.perf_counter()
    return {"forward_s": round(t1 - t0, 2), "backward_s": round(t3 - t2, 2), "total_s": round(t3 - t0, 2)}


def sim_compile_benchmark(precision: str = "float32", res: int = 32, effects: str = SIM_EFFECTS) -> dict:
    """Cold (empty offline cache) and warm (the cache the cold run filled) compile times of the simulator's forward
    and differentiable step, each in a fresh process."""
    import json
    import os
    import subprocess
    import sys
    import tempfile

    code = (
        "import json, sys\n"
        "from causalgs import _ti\n"
        f"_ti.init('cpu', {precision!r}, quiet=True)\n"
        "from causalgs.bench import sim_compile_probe\n"
        f"print(json.dumps(sim_compile_probe({res}, effects={effects!r})))\n"
    )
    rec = {"bench": "sim_compile", "precision": precision, "grid": res, "effects": effects}
    with tempfile.TemporaryDirectory(prefix="causalgs-compile-") as cache:
        env = dict(os.environ, CAUSALGS_TI_CACHE=cache)
        for label in ("cold", "warm"):
            out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=False)
            if out.returncode != 0:
                raise RuntimeError(f"compile probe failed: {out.stderr.strip().splitlines()[-1:]}")
            probe = json.loads(out.stdout.strip().splitlines()[-1])
            rec.update({f"{label}_{k}": v for k, v in probe.items()})
    return rec


LANDING_EFFECTS = "gravity;ground:mu=0.3;walls"  # the hidden-effect table's base physics (discover.table.BASE)


def _landing(effects: str, res: int, frames: int, fps: float):
    """The hidden-effect table's tossed block (seed 0), its landing simulated on a grid of ``res`` cells: the
    observation the discover benchmarks roll out."""
    from causalgs.discover.observation import synthesize

    return synthesize("toss", effects, seed=0, points=1_000_000, frames=frames, fps=fps, reference_res=res)


def discover_benchmark(resolutions: Iterable[int] = (20, 43), repeats: int = 5, frames: int = 30,
                       fps: float = 24.0, effects: str = LANDING_EFFECTS) -> Iterable[dict]:
    """One record per grid resolution: the seconds of one discovery rollout (``PhysicsModel.rollout``, no
    gradient) of the hidden-effect table's ``toss`` landing, the truth's particles on the truth's grid, and the
    milliseconds per MPM substep it took. Calibrations are hundreds of these (a forward-difference Jacobian is one
    per parameter), so this is what a discovery's time scales with."""
    from causalgs.discover.model import PhysicsModel

    for res in resolutions:
        obs = _landing(effects, res, frames, fps)
        model = PhysicsModel(obs, effects, (), res=res)
        theta = model.initial()
        with torch.no_grad():
            first, median = _median_ms(lambda: model.rollout(theta), repeats)  # noqa: B023
            before = model.sim.counter
            model.rollout(theta)
        substeps = model.sim.counter - before - 1  # the counter moves once per substep and once for the start state
        yield {"bench": "discover", "grid": res, "points": obs.points, "frames": frames, "fps": fps,
               "substeps": substeps, "rollout_ms": round(median, 2), "first_rollout_ms": round(first, 1),
               "ms_per_substep": round(median / max(substeps, 1), 4), "repeats": repeats}  # fmt: skip


def discover_workers_benchmark(res: int = 43, workers: Iterable[int] = (2,), repeats: int = 3, frames: int = 30,
                               fps: float = 24.0, effects: str = LANDING_EFFECTS) -> Iterable[dict]:
    """One record per worker count: the seconds of one Levenberg–Marquardt Jacobian (a rollout per parameter of the
    ``toss`` landing's model, :func:`~causalgs.discover.calibrate.jacobian`) here and with that many worker
    processes (:mod:`causalgs.discover.workers`), timed in turn in one run, their medians and ratio, and the largest
    difference between the two (cm per unit step)."""
    from causalgs.discover import workers as W
    from causalgs.discover.calibrate import fit_frames, jacobian, positions
    from causalgs.discover.model import PhysicsModel

    obs = _landing(effects, res, frames, fps)
    model = PhysicsModel(obs, effects, ("ground.mu", "ground.d"), res=res)
    theta = model.initial(E=3e4)
    fr = fit_frames(model)
    x = positions(model, theta, fr)
    for n in workers:
        with W.rollout_workers(n) as pool:
            started = time.perf_counter()
            jacobian(model, theta, fr, base=x)  # the workers start and build their kernels
            warm_up = time.perf_counter() - started
            here, there, diff = [], [], 0.0
            for _ in range(repeats):
                W._active = None
                t0 = time.perf_counter()
                serial = jacobian(model, theta, fr, base=x)
                here.append(time.perf_counter() - t0)
                W._active = pool
                t0 = time.perf_counter()
                par = jacobian(model, theta, fr, base=x)
                there.append(time.perf_counter() - t0)
                diff = max(diff, float(np.abs(par - serial).max()))
        a, b = float(np.median(here)), float(np.median(there))
        yield {"bench": "discover-workers", "grid": res, "points": obs.points, "frames": frames, "fps": fps,
               "params": len(theta), "workers": n, "serial_s": round(a, 3), "workers_s": round(b, 3),
               "speedup": round(a / b, 3), "first_call_s": round(warm_up, 2), "max_difference_cm": diff,
               "repeats": repeats}  # fmt: skip


# -- runs side by side ------------------------------------------------------------------------------------------------

_JOBS_WORK: dict[tuple, Callable[[], object]] = {}


def _jobs_work(work: str, res: int, frames: int, fps: float) -> Callable[[], object]:
    """This process's copy of a piece's unit of work, built (and compiled) once: ``rollout``, one discovery rollout
    of the ``toss`` landing on a grid of ``res`` cells (as in :func:`discover_benchmark`), or ``render``, one
    forward+backward pass of the rasterizer over 20k Gaussians at 128² (a fit's step is made of these)."""
    key = (work, res, frames, fps)
    if key in _JOBS_WORK:
        return _JOBS_WORK[key]
    if work == "rollout":
        from causalgs.discover.model import PhysicsModel

        obs = _landing(LANDING_EFFECTS, res, frames, fps)
        model = PhysicsModel(obs, LANDING_EFFECTS, (), res=res)
        theta = model.initial()

        def fn():
            with torch.no_grad():
                return model.rollout(theta)
    elif work == "render":
        from causalgs import _ti
        from causalgs.render import rasterize

        dtype = _ti.torch_dtype()
        cam = bench_camera(128)
        vm, K = torch.tensor(cam.viewmat, dtype=dtype), torch.tensor(cam.K, dtype=dtype)
        leaves = {k: t.requires_grad_(True) for k, t in bench_scene(20_000, dtype=dtype).items()}
        bg = torch.ones(3, dtype=dtype)

        def fn():
            _forward_backward(lambda q: rasterize(*(q[k] for k in KEYS), vm, K, 128, 128, background=bg), leaves)
    else:
        raise ValueError(f"unknown work '{work}' (rollout or render)")
    fn()  # its kernels compiled (or loaded from the offline cache)
    _JOBS_WORK[key] = fn
    return fn


def jobs_piece(name: str, index: int, work: str, res: int, units: int, frames: int, fps: float) -> dict:
    """One piece of a :func:`jobs_benchmark`: ``units`` units of ``work`` (see :func:`_jobs_work`), run where the
    table runs a row (here, or in a process of :func:`causalgs.discover.table.execute`); the seconds they took, the
    seconds this process first spent building them, and the CPUs and Taichi threads it ran on."""
    import os

    from causalgs import _ti

    t0 = time.perf_counter()
    fn = _jobs_work(work, res, frames, fps)
    setup = time.perf_counter() - t0
    t0 = time.perf_counter()
    for _ in range(units):
        fn()
    cpus = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None
    return {"case": name, "seed": index, "piece_s": time.perf_counter() - t0, "setup_s": setup, "cpus": cpus,
            "threads": _ti.runtime().threads, "pid": os.getpid()}  # fmt: skip


def jobs_benchmark(jobs: int = 2, pieces: int = 4, work: str = "rollout", res: int = 20, units: int = 5,
                   cycles: int = 3, frames: int = 30, fps: float = 24.0, log=None) -> dict:
    """What ``discover-table --jobs`` buys: ``pieces`` equal pieces of work (each ``units`` units of ``work``, see
    :func:`_jobs_work`) run as a table runs its rows, one after the other in this process on all its CPUs
    (``--jobs 1``) and ``jobs`` at once, each in a spawned process pinned to its own share of the CPUs
    (:func:`causalgs.discover.table.execute`, the table's own code), the two in turn ``cycles`` times in one run.

    The record: the median seconds of a piece either way; ``throughput_ratio``, pieces finished per second side by
    side over one after the other, from those medians (a long row's gain: the processes' start is left out); and
    ``wall_ratio``, the median wall seconds of all the pieces one after the other over side by side, the processes'
    start and their loading of the compiled kernels included (they are spawned afresh every cycle)."""
    from causalgs import _ti
    from causalgs.discover import table

    log = log or (lambda msg: None)
    if jobs < 2:
        raise ValueError(f"jobs = {jobs}: side by side needs at least 2")
    args = (work, res, units, frames, fps)
    todo = [("piece", i) for i in range(pieces)]

    def failed(name, index, why):
        raise RuntimeError(f"piece {index} failed: {why}")

    jobs_piece("warm-up", -1, *args)  # this process's kernels built before its first timed piece
    serial, side, serial_wall, side_wall = [], [], [], []
    for cycle in range(cycles):
        for mode, n, rows, walls in (("one after the other", 1, serial, serial_wall),
                                     (f"{jobs} at once", jobs, side, side_wall)):  # fmt: skip
            t0 = time.perf_counter()
            table.execute(todo, n, lambda name, i: jobs_piece(name, i, *args), jobs_piece, args, failed, rows.append,
                          lambda msg: None)  # fmt: skip
            walls.append(time.perf_counter() - t0)
            log(f"cycle {cycle + 1}/{cycles}, {mode}: {walls[-1]:.1f} s")
    a, b = statistics.median(r["piece_s"] for r in serial), statistics.median(r["piece_s"] for r in side)
    wa, wb = statistics.median(serial_wall), statistics.median(side_wall)
    return {"bench": "jobs", "work": work, "grid": res if work == "rollout" else None, "jobs": jobs,
            "pieces": pieces, "units": units, "cycles": cycles, "cpus": _ti.allowed_cpus(),
            "serial_piece_s": round(a, 3), "jobs_piece_s": round(b, 3), "throughput_ratio": round(jobs * a / b, 3),
            "serial_wall_s": round(wa, 2), "jobs_wall_s": round(wb, 2), "wall_ratio": round(wa / wb, 3),
            "jobs_setup_s": round(statistics.median(r["setup_s"] for r in side), 2),
            "serial_threads": serial[0]["threads"], "jobs_threads": side[0]["threads"],
            "jobs_cpus": sorted({tuple(r["cpus"] or ()) for r in side})}  # fmt: skip
