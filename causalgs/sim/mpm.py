"""The MLS-MPM simulator over a ParticleStore: configuration, time stepping and blow-up checks.

:class:`Simulator` moves the first ``store.n`` particles of a :class:`~causalgs.store.ParticleStore`. It registers
the substep-indexed state it needs in the store (``x_seg, v_seg, C_seg, F_seg`` with ``segment + 1`` slots per row),
reads materials from the store's ``mass, vol, E, nu, density`` rows and owns only grid fields and effect parameters.

A frame of ``m`` substeps runs as segments of at most ``segment`` substeps: substep ``s`` reads slot ``s`` and writes
slot ``s + 1``; at the end of a segment the last slot is copied into slot 0. That copy is the checkpoint boundary of
the (later) checkpointed backward: it stores slot 0 of every segment and replays one segment at a time.

The time step follows the CFL condition dt ≤ cfl · dx / max(c, |v|max) with c = sqrt((λ + 2μ)/ρ) the fastest
elastic (P-)wave, chosen per frame so the frame splits into equal substeps. Blow-ups (NaN, particles leaving the
grid) are detected after every frame and raised as one-line :class:`~causalgs.errors.CausalGSError`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields

import numpy as np
import torch

from causalgs import _ti
from causalgs.errors import CausalGSError
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
    )


@dataclass
class SimConfig:
    """Simulator settings. ``res``: grid cells along the longest axis of the box [lo, hi]. ``segment``: substeps per
    checkpoint segment (a field shape: changing it recompiles). ``cfl``: fraction of a cell a wave or particle may
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
        known = {f.name for f in fields(cls) if f.init}
        unknown = sorted(set(d) - known)
        if unknown:
            raise CausalGSError(
                f"unknown simulator setting(s): {', '.join(unknown)} (settings: {', '.join(sorted(known))})"
            )
        return cls(**d)

    def to_dict(self) -> dict:
        return {f.name: getattr(self, f.name) for f in fields(self) if f.init}


class Simulator:
    """MLS-MPM over the first ``store.n`` rows of ``store``. Call :meth:`reset` (or :meth:`set_state`) first."""

    def __init__(self, store: ParticleStore, config: SimConfig | None = None):
        self.config = config or SimConfig()
        self.store = store
        self.geo = self.config.geometry
        self.k = self.config.segment
        store.add_fields(segment_specs(self.k))
        self.grid = grid_fields(self.geo.shape)
        self.effects = Effects.from_spec(self.config.effects)
        self.frame = 0
        self.time = 0.0
        self.schedule: list[tuple[int, float]] = []  # (substeps, dt) of every frame since the last reset

    # -- state --------------------------------------------------------------------------------------------------
    def _seg(self):
        s = self.store
        return s.x_seg, s.v_seg, s.C_seg, s.F_seg

    def reset(self) -> None:
        """Start from the store's x, v, C, F rows (the canonical state) at time 0."""
        s = self.store
        kernels.rows_to_slot(s.x, s.v, s.C, s.F, *self._seg(), 0, s.n)
        self.frame, self.time, self.schedule = 0, 0.0, []

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
        for k in STATE:
            self.store.from_torch(f"{k}_seg", vals[k], slot=0)
        self.frame, self.time, self.schedule = 0, 0.0, []

    def state(self) -> dict[str, torch.Tensor]:
        """The current x, v, C, F (CPU tensors, copies)."""
        return {k: self.store.to_torch(f"{k}_seg", slot=0) for k in STATE}

    def write_to_store(self) -> None:
        """Copy the current state into the store's x, v, C, F rows (e.g. to render the simulated particles)."""
        s = self.store
        kernels.slot_to_rows(*self._seg(), s.x, s.v, s.C, s.F, 0, s.n)

    # -- time stepping --------------------------------------------------------------------------------------------
    def substep(self, s: int, dt: float) -> None:
        """One MLS-MPM substep from slot ``s`` to slot ``s + 1`` (0 ≤ s < segment)."""
        st, g, geo = self.store, self.grid, self.geo
        x, v, C, F = self._seg()
        kernels.clear_grid(g.v_in, g.m, g.v_out)
        kernels.p2g(x, v, C, F, st.mass, st.vol, st.E, st.nu, g.v_in, g.m, s, st.n, dt, geo.lo, geo.inv_dx,
                    self.config.material)  # fmt: skip
        kernels.grid_update(g.v_in, g.m, g.v_out, dt, geo.lo, geo.dx, self.effects)
        kernels.g2p(x, v, C, g.v_out, s, st.n, dt, geo.lo, geo.inv_dx)

    def step(self, substeps: int, dt: float | None = None, check=None) -> None:
        """Advance ``substeps`` substeps of ``dt`` (default: the CFL time step of the current state), in segments.

        ``check(dt)``, if given, runs after every segment (particles leaving the grid are caught before the clamped
        stencils turn them into NaN)."""
        dt = self.stable_dt() if dt is None else float(dt)
        done = 0
        while done < substeps:
            m = min(self.k, substeps - done)
            for s in range(m):
                self.substep(s, dt)
            kernels.copy_slot(*self._seg(), m, 0, self.store.n)
            done += m
            self.time += m * dt
            if check is not None:
                check(dt)

    def check_materials(self) -> None:
        """One-line error for the first particle with a non-physical mass, volume, density, E or nu."""
        rules = {
            "mass": (lambda a: a > 0, "> 0"),
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
        kernels.frame_stats(x, v, F, 0, st.n, geo.lo, geo.inv_dx, geo.shape, g.stats)
        return g.stats.to_numpy().astype(np.float64)

    def stable_dt(self, c: float | None = None) -> float:
        """cfl · dx / max(c, |v|max): the largest substep the CFL condition allows for the current state."""
        c = self.wave_speed() if c is None else c
        vmax = float(self._stats()[1])
        speed = max(c, vmax if math.isfinite(vmax) else 0.0, 1e-12)
        return self.config.cfl * self.geo.dx / speed

    def advance(self, frames: int, fps: float) -> dict[str, torch.Tensor]:
        """Simulate ``frames`` frames of 1/``fps`` s; checks the state after every frame. Returns :meth:`state`."""
        if not (fps > 0 and math.isfinite(fps)):
            raise CausalGSError(f"fps = {fps} must be a positive number")
        frame_dt = 1.0 / fps
        self.check_materials()
        c = self.wave_speed()
        for _ in range(int(frames)):
            dt_max = self.config.dt if self.config.dt is not None else self.stable_dt(c)
            m = max(1, math.ceil(frame_dt / dt_max - 1e-9))
            if m > self.config.max_substeps:
                raise CausalGSError(
                    f"frame {self.frame + 1} needs {m} substeps (dt = {dt_max:.3g} s for wave speed {c:.3g} m/s), "
                    f"more than max_substeps = {self.config.max_substeps}: lower the stiffness or raise max_substeps"
                )
            dt = frame_dt / m
            self.step(m, dt, check=lambda dt: self._check(self.frame + 1, dt, c))
            self.frame += 1
            self.schedule.append((m, dt))
        return self.state()

    def _check(self, f: int, dt: float, c: float) -> None:
        total, vmax, outside, _ = self._stats()
        t = self.time
        if outside > 0:
            nan = "" if math.isfinite(total) else ", state non-finite"
            raise CausalGSError(
                f"simulation blew up in frame {f} (t = {t:.4g} s): {int(outside)} particle(s) left the grid "
                f"(max speed {vmax:.3g} m/s{nan}); enlarge the domain, enable 'walls', or lower the time step"
            )
        if not math.isfinite(total):
            limit = self.config.cfl * self.geo.dx / max(c, 1e-12)
            raise CausalGSError(
                f"simulation blew up in frame {f} (t = {t:.4g} s): non-finite particle state; the time step "
                f"dt = {dt:.3g} s is likely too large for the stiffness (CFL limit {limit:.3g} s at wave speed "
                f"{c:.3g} m/s)"
            )


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
