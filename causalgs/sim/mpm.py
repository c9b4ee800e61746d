"""The MLS-MPM simulator over a ParticleStore: configuration, time stepping, blow-up checks, checkpointed backward.

:class:`Simulator` moves the first ``store.n`` particles of a :class:`~causalgs.store.ParticleStore`. It registers
the substep-indexed state it needs in the store (``x_seg, v_seg, C_seg, F_seg`` with ``segment + 1`` slots per row),
reads materials from the store's ``vol, density, E, nu`` rows (mass = density · volume) and owns only grid fields
and effect parameters.

Substeps run in segments of ``segment`` substeps: substep ``s`` reads slot ``s`` and writes slot ``s + 1``; when a
segment is full its last slot is copied into slot 0 before the next substep. That copy is the checkpoint boundary.

**Checkpointed backward** (:meth:`Simulator.rollout` then :meth:`Simulator.backward`). The forward keeps slot 0 of
every segment (a copy of x, v, C, F) and which slot every requested output time ended in. The backward walks the
segments from last to first: restore the segment's start, replay its substeps (the last segment's slots are still
intact and are not replayed), seed the end slot with the adjoint carried from the later segment plus the loss
gradients of outputs in this segment, then for each substep in reverse recompute its grid and run the gradient
kernels g2p_adjoint → grid_update.grad → p2g_adjoint → stress.grad (as difftaichi's diffmpm does; the grid is scratch
of one substep). Parameter adjoints (E, nu, density, effect parameters) accumulate across all segments because the
gradient kernels only ever add to them; ``ti.ad.Tape`` is not used since it clears every adjoint when entered.
Memory: one segment of slots plus one checkpoint per segment, instead of one slot per substep for a full tape
(``segment`` ≥ all substeps is the full tape: a single segment, never replayed).

The time step follows the CFL condition dt ≤ cfl · dx / max(c, |v|max) with c = sqrt((λ + 2μ)/ρ) the fastest
elastic (P-)wave, chosen per frame so the frame splits into equal substeps. Blow-ups (NaN, particles leaving the
grid) are detected after every frame and raised as one-line :class:`~causalgs.errors.CausalGSError`.
"""

from __future__ import annotations

import contextlib
import itertools
import math
from dataclasses import dataclass, field, fields

import numpy as np
import torch

from causalgs import _ti
from causalgs.errors import CausalGSError
from causalgs.settings import check_keys
from causalgs.sim import kernels
from causalgs.sim.effects import Effects
from causalgs.sim.grid import GridGeometry, grid_fields
from causalgs.sim.materials import DEFAULT_MODEL, check_model, lame
from causalgs.store import FieldSpec, ParticleStore

STATE = ("x", "v", "C", "F")


def segment_specs(segment: int) -> tuple[FieldSpec, ...]:
    """Substep-indexed particle state for segments of ``segment`` substeps (slots 0..segment)."""
    k = (segment + 1,)
    return (
        FieldSpec("x_seg", (3,), per_row=k, doc="position per substep slot of the current segment"),
        FieldSpec("v_seg", (3,), per_row=k, doc="velocity per substep slot"),
        FieldSpec("C_seg", (3, 3), per_row=k, doc="APIC affine matrix per substep slot"),
        FieldSpec("F_seg", (3, 3), per_row=k, fill="identity", doc="deformation gradient per substep slot"),
        FieldSpec("vc_seg", (3,), per_row=k, doc="velocity after the particle-stage effects per substep slot (what "
                  "P2G scatters when there are such effects)"),
    )


SCRATCH = (FieldSpec("mpm_affine", (3, 3), doc="MPM scratch: stress and APIC momentum term of the current substep"),)


HOLD_SLACK = 1.25  # a held substep count may stand for up to this many more than the CFL limit asks for


@dataclass
class SimConfig:
    """Simulator settings. ``res``: grid cells along the longest axis of the box [lo, hi]. ``segment``: substeps per
    checkpoint segment (the first simulator on a store sizes its slot fields from it; later ones may use any segment
    up to that without recompiling). ``cfl``: fraction of a cell a wave or particle may
    cross per substep. ``dt``: a fixed substep (s) instead of the CFL one. ``max_substeps``: per frame; a frame that
    needs more is an error. ``material``: one of ``materials.MODELS``. ``effects``: an effects spec string."""

    res: int = 32
    lo: tuple[float, float, float] = (0.0, 0.0, 0.0)
    hi: tuple[float, float, float] = (1.0, 1.0, 1.0)
    segment: int = 8
    cfl: float = 0.4
    dt: float | None = None
    max_substeps: int = 1000
    material: str = DEFAULT_MODEL
    effects: str = "gravity:g=0,0,-9.8;walls"
    geometry: GridGeometry = field(init=False, repr=False)

    def __post_init__(self):
        check_model(self.material)
        if self.segment < 1:
            raise CausalGSError(f"segment = {self.segment} substeps must be at least 1")
        if not 0 < self.cfl <= 1:
            raise CausalGSError(f"cfl = {self.cfl} must be in (0, 1]")
        if self.dt is not None and not (math.isfinite(self.dt) and self.dt > 0):
            raise CausalGSError(f"dt = {self.dt} must be a positive number")
        if self.max_substeps < 1:
            raise CausalGSError(f"max_substeps = {self.max_substeps} must be at least 1")
        self.lo, self.hi = tuple(float(a) for a in self.lo), tuple(float(a) for a in self.hi)
        self.geometry = GridGeometry.from_box(self.lo, self.hi, int(self.res))

    @classmethod
    def from_dict(cls, d: dict) -> SimConfig:
        check_keys(cls, d, "simulator")
        return cls(**d)

    def to_dict(self) -> dict:
        return {f.name: getattr(self, f.name) for f in fields(self) if f.init}


@dataclass
class Segment:
    """A recorded segment: its start state (the checkpoint: x, v, C, F), its substep sizes and the outputs that ended
    in it as ``(slot, output index)``."""

    start: dict[str, torch.Tensor]
    dts: list[float] = field(default_factory=list)
    outputs: list[tuple[int, int]] = field(default_factory=list)


@dataclass
class Tape:
    """What :meth:`Simulator.backward` needs from a :meth:`Simulator.rollout`."""

    segments: list[Segment]
    times: list[float]
    stamp: int  # the simulator's substep counter when the rollout ended (the last segment's slots are intact if equal)


class Simulator:
    """MLS-MPM over the first ``store.n`` rows of ``store``. Call :meth:`reset` (or :meth:`set_state`) first."""

    def __init__(self, store: ParticleStore, config: SimConfig | None = None):
        self.config = config or SimConfig()
        self.store = store
        self.geo = self.config.geometry
        self.k = self.config.segment
        have = store.specs.get("x_seg")
        if have is None:
            store.add_fields(segment_specs(self.k))
        elif have.per_row[0] - 1 < self.k:
            raise CausalGSError(
                f"this particle store holds simulator segments of at most {have.per_row[0] - 1} substeps, the "
                f"config asks for segment = {self.k}: use a new store or a shorter segment"
            )
        store.add_fields(SCRATCH)
        self.grid = grid_fields(self.geo.shape)
        self.effects = Effects.from_spec(self.config.effects)
        self.frame = 0
        self.time = 0.0
        self.slot = 0  # slot of the current state within the live segment
        self.counter = 0  # substeps run by this simulator (any state change bumps it)
        self.schedule: list[tuple[int, float]] = []  # (substeps, dt) of every frame since the last reset
        self._recording: list[Segment] | None = None
        self.last_plan: list[int] = []  # the substeps of each interval of the last rollout
        self._held_plan: list[int] | None = None

    # -- state --------------------------------------------------------------------------------------------------
    def _seg(self):
        s = self.store
        return s.x_seg, s.v_seg, s.C_seg, s.F_seg

    def _restart(self) -> None:
        self.frame, self.time, self.slot, self.schedule = 0, 0.0, 0, []
        self.counter += 1

    def reset(self) -> None:
        """Start from the store's x, v, C, F rows (the canonical state) at time 0."""
        s = self.store
        kernels.rows_to_slot(s.x, s.v, s.C, s.F, *self._seg(), 0, s.n)
        self._restart()

    def set_state(self, x, v, C=None, F=None) -> None:
        """Start from tensors x [n, 3], v [n, 3], C [n, 3, 3] (default 0), F [n, 3, 3] (default I) at time 0."""
        n = self.store.n
        dt = _ti.torch_dtype()
        vals = {
            "x": torch.as_tensor(x),
            "v": torch.as_tensor(v),
            "C": torch.zeros(n, 3, 3) if C is None else torch.as_tensor(C),
            "F": torch.eye(3).expand(n, 3, 3) if F is None else torch.as_tensor(F),
        }
        for name, t in vals.items():
            shape = (n, 3) if name in ("x", "v") else (n, 3, 3)
            if tuple(t.shape) != shape:
                raise CausalGSError(f"simulator state '{name}' has shape {list(t.shape)}, expected {list(shape)}")
            if not bool(torch.isfinite(t).all()):
                raise CausalGSError(f"simulator state '{name}' has non-finite values")
            vals[name] = t.detach().to(device="cpu", dtype=dt).contiguous()
        self._write_slot(vals, 0)
        self._restart()

    def _write_slot(self, vals: dict[str, torch.Tensor], slot: int) -> None:
        for k in STATE:
            self.store.from_torch(f"{k}_seg", vals[k], slot=slot)

    def _read_slot(self, slot: int, names=STATE) -> dict[str, torch.Tensor]:
        return {k: self.store.to_torch(f"{k}_seg", slot=slot) for k in names}

    def state(self) -> dict[str, torch.Tensor]:
        """The current x, v, C, F (CPU tensors, copies)."""
        return self._read_slot(self.slot)

    def write_to_store(self) -> None:
        """Copy the current state into the store's x, v, C, F rows (e.g. to render the simulated particles)."""
        s = self.store
        kernels.slot_to_rows(*self._seg(), s.x, s.v, s.C, s.F, self.slot, s.n)

    # -- time stepping --------------------------------------------------------------------------------------------
    def substep(self, s: int, dt: float) -> None:
        """One MLS-MPM substep from slot ``s`` to slot ``s + 1`` (0 ≤ s < segment), in one kernel launch. Low
        level: :meth:`step` keeps the slot bookkeeping and uploads the effect parameters."""
        st, g, geo = self.store, self.grid, self.geo
        scatter = st.vc_seg if self.effects.kernel.has_particle else st.v_seg
        kernels.substep(st.x_seg, st.v_seg, st.vc_seg, scatter, st.C_seg, st.F_seg, st.vol, st.density, st.E, st.nu,
                        st.mpm_affine, g.v_in, g.m, g.v_out, g.box, s, st.n, dt, self._lo(), geo.inv_dx, geo.dx,
                        self.config.material, self.effects.kernel)  # fmt: skip

    def substep_phased(self, s: int, dt: float) -> None:
        """:meth:`substep` as one kernel per phase (six or seven launches): the same arithmetic, the reference the
        fused kernel is tested and benchmarked against."""
        st, g, geo = self.store, self.grid, self.geo
        kernels.particle_box(st.x_seg, s, st.n, self._lo(), geo.inv_dx, geo.shape, g.box)
        kernels.clear_grid(g.v_in, g.m, g.v_out, g.box)
        kernels.stress(*self._stress_args(s, dt))
        if self.effects.kernel.has_particle:
            kernels.particle_terms(*self._particle_args(s, dt))
        kernels.p2g(*self._p2g_args(s))
        kernels.grid_update(g.v_in, g.m, g.v_out, dt, self._lo(), geo.dx, self.effects.kernel, g.box)
        kernels.g2p(st.x_seg, st.v_seg, st.C_seg, g.v_out, s, st.n, dt, self._lo(), geo.inv_dx)

    def _lo(self):
        """The grid's origin field, holding this simulator's ``lo`` (grid fields are shared by shape)."""
        return self.grid.origin(self.geo.lo)

    def _stress_args(self, s: int, dt: float) -> tuple:
        st = self.store
        return (st.v_seg, st.C_seg, st.F_seg, st.vol, st.density, st.E, st.nu, st.mpm_affine, s, st.n, dt,
                self.geo.inv_dx, self.config.material, self.effects.kernel)  # fmt: skip

    def _p2g_args(self, s: int) -> tuple:
        st, g, geo = self.store, self.grid, self.geo
        v = st.vc_seg if self.effects.kernel.has_particle else st.v_seg
        return (st.x_seg, v, st.vol, st.density, st.mpm_affine, g.v_in, g.m, s, st.n, self._lo(), geo.inv_dx)

    def _particle_args(self, s: int, dt: float) -> tuple:
        st = self.store
        return (st.x_seg, st.v_seg, st.vc_seg, s, st.n, dt, self.effects.kernel)

    def _boundary(self) -> None:
        """Start a new segment if the live one is full: copy its last slot into slot 0 (and checkpoint it)."""
        if self.slot < self.k:
            return
        kernels.copy_slot(*self._seg(), self.k, 0, self.store.n)
        self.slot = 0
        if self._recording is not None:
            self._recording.append(Segment(start=self._read_slot(0)))

    def step(self, substeps: int, dt: float | None = None, check=None, phased: bool = False) -> None:
        """Advance ``substeps`` substeps of ``dt`` (default: the CFL time step of the current state).

        ``check(dt)``, if given, runs whenever a segment fills up (particles leaving the grid are caught before the
        clamped stencils turn them into NaN). ``phased``: one kernel per phase (:meth:`substep_phased`)."""
        dt = self.stable_dt() if dt is None else float(dt)
        self.effects.upload()
        advance = self.substep_phased if phased else self.substep
        for _ in range(int(substeps)):
            self._boundary()
            advance(self.slot, dt)
            self.slot += 1
            self.counter += 1
            self.time += dt
            if self._recording is not None:
                self._recording[-1].dts.append(dt)
            if check is not None and self.slot == self.k:
                check(dt)

    def check_materials(self) -> None:
        """One-line error for the first particle with a non-physical volume, density, E or nu."""
        rules = {
            "vol": (lambda a: a > 0, "> 0"),
            "density": (lambda a: a > 0, "> 0"),
            "E": (lambda a: a > 0, "> 0"),
            "nu": (lambda a: (a > -1) & (a < 0.5), "in (-1, 0.5)"),
        }
        for name, (ok, text) in rules.items():
            vals = self.store.to_torch(name)
            bad = torch.nonzero(~ok(vals)).flatten()
            if len(bad):
                i = int(bad[0])
                raise CausalGSError(
                    f"particle {i} has {name} = {float(vals[i]):.4g}; the simulator needs {name} {text}"
                )

    def wave_speed(self) -> float:
        """Fastest P-wave speed sqrt((λ + 2μ)/ρ) over the particles (m/s)."""
        if self.store.n == 0:
            return 0.0
        E, nu, rho = (self.store.to_torch(k).double() for k in ("E", "nu", "density"))
        mu, lam = lame(E, nu)
        return float(torch.sqrt((lam + 2.0 * mu) / rho).max())

    def _stats(self) -> np.ndarray:
        st, g, geo = self.store, self.grid, self.geo
        x, v, _, F = self._seg()
        kernels.frame_stats(x, v, F, self.slot, st.n, self._lo(), geo.inv_dx, geo.shape, g.stats)
        return g.stats.to_numpy().astype(np.float64)

    def stable_dt(self, c: float | None = None) -> float:
        """The largest substep allowed for the current state: cfl · dx / max(c, |v|max), and cfl times the limit of
        any effect (e.g. viscosity's dx² ρ / 6η)."""
        c = self.wave_speed() if c is None else c
        vmax = float(self._stats()[1])
        speed = max(c, vmax if math.isfinite(vmax) else 0.0, 1e-12)
        dt = self.config.cfl * self.geo.dx / speed
        if self.store.n:
            rho_min = float(self.store.to_torch("density").min())
            dt = min(dt, self.config.cfl * self.effects.dt_limit(self.geo.dx, rho_min))
        return dt

    def _plan(self, duration: float, c: float, label: str) -> tuple[int, float]:
        """Equal substeps covering ``duration`` seconds, each at most the stable (or configured) dt."""
        dt_max = self.config.dt if self.config.dt is not None else self.stable_dt(c)
        m = max(1, math.ceil(duration / dt_max - 1e-9))
        if m > self.config.max_substeps:
            raise CausalGSError(
                f"{label} needs {m} substeps (dt = {dt_max:.3g} s for wave speed {c:.3g} m/s), more than "
                f"max_substeps = {self.config.max_substeps}: lower the stiffness or raise max_substeps"
            )
        return m, duration / m

    def advance(self, frames: int, fps: float) -> dict[str, torch.Tensor]:
        """Simulate ``frames`` frames of 1/``fps`` s; checks the state after every frame. Returns :meth:`state`."""
        if not (fps > 0 and math.isfinite(fps)):
            raise CausalGSError(f"fps = {fps} must be a positive number")
        self.check_materials()
        c = self.wave_speed()
        for _ in range(int(frames)):
            m, dt = self._plan(1.0 / fps, c, f"frame {self.frame + 1}")
            self.step(m, dt, check=lambda dt: self._check(f"frame {self.frame + 1}", dt, c))
            self._check(f"frame {self.frame + 1}", dt, c)
            self.frame += 1
            self.schedule.append((m, dt))
        return self.state()

    def _check(self, where: str, dt: float, c: float) -> None:
        total, vmax, outside, _ = self._stats()
        t = self.time
        if outside > 0:
            nan = "" if math.isfinite(total) else ", state non-finite"
            raise CausalGSError(
                f"simulation blew up in {where} (t = {t:.4g} s): {int(outside)} particle(s) left the grid "
                f"(max speed {vmax:.3g} m/s{nan}); enlarge the domain, enable 'walls', or lower the time step"
            )
        if not math.isfinite(total):
            limit = self.config.cfl * self.geo.dx / max(c, 1e-12)
            raise CausalGSError(
                f"simulation blew up in {where} (t = {t:.4g} s): non-finite particle state; the time step "
                f"dt = {dt:.3g} s is likely too large for the stiffness (CFL limit {limit:.3g} s at wave speed "
                f"{c:.3g} m/s)"
            )

    # -- differentiable rollout -------------------------------------------------------------------------------------
    def rollout(self, times, outputs=("x", "v", "F")) -> tuple[dict[str, torch.Tensor], Tape]:
        """Simulate from the current state (time 0, see :meth:`set_state`) through the sorted ``times`` (s, ≥ 0),
        recording what :meth:`backward` needs. Returns the state at every time, ``{name: [T, n, ...]}``, and the tape.

        Each interval between consecutive times is split into equal substeps under the CFL limit; the state is
        checked at every output time and segment boundary."""
        times = [float(t) for t in times]
        if not times:
            raise CausalGSError("rollout needs at least one output time")
        if not all(math.isfinite(t) for t in times) or times[0] < 0 or any(b < a for a, b in itertools.pairwise(times)):
            raise CausalGSError(f"output times must be finite, non-negative and sorted, got {times}")
        if self.time != 0.0 or self.slot != 0:
            raise CausalGSError("rollout starts from time 0: call set_state() or reset() first")
        self.check_materials()
        c = self.wave_speed()
        self._recording = [Segment(start=self._read_slot(0))]
        out: dict[str, list[torch.Tensor]] = {k: [] for k in outputs}
        plan: list[int] = []
        try:
            for i, t in enumerate(times):
                if t > self.time:
                    m, dt = self._plan(t - self.time, c, f"output {i} (t = {t:.4g} s)")
                    held = self._held_plan[len(plan)] if len(plan) < len(self._held_plan or ()) else None
                    if held is not None and held * HOLD_SLACK >= m:
                        m = held  # a held schedule, within HOLD_SLACK of the CFL limit
                        dt = (t - self.time) / m
                    plan.append(m)
                    self.step(m, dt, check=lambda dt, i=i: self._check(f"the interval before output {i}", dt, c))
                    self._check(f"the interval before output {i}", dt, c)
                    self.time = t  # no drift from summing dt
                self._recording[-1].outputs.append((self.slot, i))
                for k, val in self._read_slot(self.slot, outputs).items():
                    out[k].append(val)
        finally:
            segments, self._recording = self._recording, None
            self.last_plan = plan
        return {k: torch.stack(v) for k, v in out.items()}, Tape(segments, times, self.counter)

    @contextlib.contextmanager
    def holding(self, plan: list[int]):
        """Rollouts inside take ``plan``'s substeps per interval (a :attr:`last_plan`) wherever the CFL limit
        allows within :data:`HOLD_SLACK`. For finite differences: the substep count jumps where a parameter moves
        the CFL limit across an integer, and with it symplectic Euler's O(dt) gravity bias (g T²/2 · (1/m − 1/(m+1))
        per interval of T seconds: 94.5 µm at 24 fps from 9 to 10 substeps), which a difference would read as a
        sensitivity to the parameter; the autodiff path holds its schedule the same way."""
        prev, self._held_plan = self._held_plan, list(plan)
        try:
            yield
        finally:
            self._held_plan = prev

    def backward(self, tape: Tape, grads: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """Adjoints of a rollout. ``grads``: dL/d(output) as ``{name: [T, n, ...]}`` for any of x, v, C, F (missing
        or None = zero). Returns dL/d of x0, v0, C0, F0 [n, ...], E, nu, density [n] and ``params`` (the effect
        parameters in :meth:`Effects.flat` order).

        The store's materials and the effect parameters must be those of the rollout (the torch boundary restores
        them when other work ran in between)."""
        st = self.store
        n = st.n
        seg_names = [f"{k}_seg" for k in STATE]
        st.zero_grad([*seg_names, "vc_seg", "E", "nu", "density"])
        self.effects.upload()
        self.effects.zero_grad()
        seeds = {k: v for k, v in grads.items() if v is not None}
        for k, v in seeds.items():
            if k not in STATE or tuple(v.shape[:2]) != (len(tape.times), n):
                raise CausalGSError(f"gradient '{k}' has shape {list(v.shape)}; expected [{len(tape.times)}, {n}, ...]")

        def seed(slot: int, index: int) -> None:
            for k, gk in seeds.items():
                cur = st.to_torch(f"{k}_seg", grad=True, slot=slot)
                st.from_torch(f"{k}_seg", cur + gk[index].to(cur.dtype), grad=True, slot=slot)

        intact = tape.stamp == self.counter
        last = len(tape.segments) - 1
        for j in range(last, -1, -1):
            seg = tape.segments[j]
            m = len(seg.dts)
            if j != last or not intact:
                self._write_slot(seg.start, 0)
                for s, dt in enumerate(seg.dts):
                    self.substep(s, dt)
                self.counter += 1  # the slots no longer hold the rollout's last segment
            if j != last:
                kernels.carry_adjoint(*self._seg(), m, n)
            by_slot: dict[int, list[int]] = {}
            for slot, index in seg.outputs:
                by_slot.setdefault(slot, []).append(index)
            for index in by_slot.get(m, ()):
                seed(m, index)
            for s in range(m - 1, -1, -1):
                self._substep_grad(s, seg.dts[s])
                for index in by_slot.get(s, ()):
                    seed(s, index)
        out = {f"{k}0": st.to_torch(f"{k}_seg", grad=True, slot=0) for k in STATE}
        for k in ("E", "nu", "density"):
            out[k] = st.to_torch(k, grad=True)
        out["params"] = torch.from_numpy(self.effects.flat_grad())
        return out

    def _substep_grad(self, s: int, dt: float) -> None:
        """Recompute the grid of substep ``s`` and run its gradient kernels in reverse order. The recompute is the
        whole substep (one launch; its G2P rewrites slot ``s + 1`` with the values it already holds)."""
        st, g, geo = self.store, self.grid, self.geo
        self.substep(s, dt)
        kernels.clear_grid_grad(g.v_in, g.m, g.v_out, g.box)
        st.zero_grad(["mpm_affine"])
        kernels.g2p_adjoint(st.x_seg, st.v_seg, st.C_seg, g.v_out, s, st.n, dt, self._lo(), geo.inv_dx)
        kernels.grid_update.grad(g.v_in, g.m, g.v_out, dt, self._lo(), geo.dx, self.effects.kernel, g.box)
        kernels.p2g_adjoint(*self._p2g_args(s))
        if self.effects.kernel.has_particle:
            kernels.particle_terms.grad(*self._particle_args(s, dt))
            kernels.zero_slot_grad(st.vc_seg, s, st.n)
        kernels.stress.grad(*self._stress_args(s, dt))


def momenta(state: dict[str, torch.Tensor], mass: torch.Tensor, dx: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Total linear momentum P = Σ m v and APIC angular momentum L = Σ m (x × v + dx²/4 ε:Cᵀ) about the origin.

    The affine term is the particle's share of the grid angular momentum (Jiang et al. 2015, sec. 5.3, with the
    quadratic B-spline's D = dx²/4 I); with it, L is what APIC transfers conserve exactly.
    """
    x, v, C = (state[k].double() for k in ("x", "v", "C"))
    m = mass.double()[:, None]
    P = (m * v).sum(0)
    skew = torch.stack([C[:, 2, 1] - C[:, 1, 2], C[:, 0, 2] - C[:, 2, 0], C[:, 1, 0] - C[:, 0, 1]], dim=1)
    L = (m * (torch.linalg.cross(x, v) + 0.25 * dx * dx * skew)).sum(0)
    return P, L
