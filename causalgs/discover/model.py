"""The model that discovery calibrates: the observed points as MPM particles, a few parameters per body, and effects.

Parameters (one flat float64 vector θ, so that least squares, sensitivities and bootstraps see one object):

- per body b: Young's modulus (log-space inside ``E_range``), Poisson ratio (inside ``nu_range``), and the initial
  velocity as a rigid twist, v0(x) = u_b + ω_b × (x − c_b) about the body's rest centroid c_b;
- the *learned* effect parameters, by name (``"ground.mu"``, ``"linear_drag.c"``, ``"force.b[2]"``): each in
  internal units, value = lower + scale·softplus(a) for a parameter with a lower bound (drag, friction, viscosity
  never go negative) and value = offset + scale·a otherwise. Every other effect parameter keeps its spec value.
  A parameter whose growth shortens the simulator's stable substep (viscosity: explicit diffusion needs
  dt ≤ dx²ρ/(6η)) is bounded above too, value = lower + (upper − lower)·sigmoid(a), at the value whose substep is
  :data:`SUBSTEP_COST` times shorter than the elastic one of the stiffest material the model allows (about 650 Pa·s
  on a 5 cm grid, where a 10 cm block of 30 kPa relaxes within half a frame at 24 fps). Unbounded, a calibration
  chasing a wobble it cannot explain drove the viscosity to thousands of Pa·s, where every rollout took tens of
  times longer (5000 Pa·s on that grid: about 1200 substeps a frame) and one refit ran for over half an hour.

The rollout is :func:`causalgs.sim.autograd.simulate` on the model's own grid (``res`` cells across the box): one
forward and one checkpointed backward give the loss and its gradient in every entry of θ. Where the observation
carries its measurement's lens (``Observation.mix``: tracks that move each motion pattern rigidly), the rollout is
returned through it (:func:`~causalgs.discover.observation.rigid_projection`), so that simulation and measurement
are compared in what the measurement can see. Density is fixed (video
and trajectories only constrain E/ρ).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from causalgs import _ti
from causalgs.discover.observation import LENSES, Observation, affine_projection, noise_floor
from causalgs.discover.residuals import twist_basis
from causalgs.errors import CausalGSError
from causalgs.sim import SimConfig, Simulator
from causalgs.sim.autograd import simulate
from causalgs.sim.effects import REGISTRY, Effects

CAPACITY, SEGMENT = 8192, 16  # the fitted model's store (causalgs.model.config.PhysicsConfig): one set of kernels
TWIST_FRAMES = 5  # the fewest first frames the initial twist is fitted to
TWIST_FIT = 1.5  # ... and more while a parabola per point follows them within this many times the noise
PINNED = 1e-3  # a bounded parameter whose sigmoid is this close to 0 or 1 is held at its bound
SUBSTEP_COST = 2.0  # a learned effect parameter may shorten the substep this many times below the elastic one


_UNPICKLED: dict = {}  # (runtime generation, config) -> the simulator every unpickled model of that config shares


def _unpickled_simulator(config: SimConfig) -> Simulator:
    """One simulator per config for the models unpickled in this process (a worker receives one state of a model
    after another, :mod:`causalgs.discover.workers`): a model's rollouts pass it all they depend on (materials,
    effect parameters, schedule), and every new simulator allocates its grid again."""
    from causalgs.model.scene import _sim_store

    key = (_ti.generation(), repr(config))
    if key not in _UNPICKLED:
        _UNPICKLED[key] = Simulator(_sim_store(CAPACITY, SEGMENT), config)
    return _UNPICKLED[key]


@dataclass(frozen=True)
class Knob:
    """One entry of θ: its name, what it sets, and the map from internal units to its value."""

    name: str
    kind: str  # "E", "nu", "u", "w" (per body) or "effect"
    body: int = -1
    index: int = 0  # axis (u, w) or position in Effects.flat() (effect)
    scale: float = 1.0
    lower: float | None = None
    offset: float = 0.0
    upper: float | None = None  # with ``lower``: a bounded parameter (sigmoid)

    def value(self, a: torch.Tensor) -> torch.Tensor:
        if self.kind == "effect" and self.lower is not None and self.upper is not None:
            return self.lower + (self.upper - self.lower) * torch.sigmoid(torch.as_tensor(a))
        if self.kind == "effect" and self.lower is not None:
            return self.lower + self.scale * torch.nn.functional.softplus(a)
        return self.offset + self.scale * a

    def internal(self, v: float) -> float:
        if self.kind == "effect" and self.lower is not None and self.upper is not None:
            s = min(max((v - self.lower) / (self.upper - self.lower), 1e-6), 1 - 1e-6)
            return math.log(s / (1 - s))
        if self.kind == "effect" and self.lower is not None:
            y = max((v - self.lower) / self.scale, 1e-9)
            return y + math.log(-math.expm1(-y)) if y < 30 else y  # softplus⁻¹
        return (v - self.offset) / self.scale


# Typical magnitudes of effect parameters (internal unit = one scale): a step of one unit is a visible change.
SCALES = {"g": 1.0, "b": 1.0, "c": 0.3, "k": 0.3, "mu": 0.3, "d": 0.01, "n": 0.1, "eta": 30.0, "yield_stress": 2e3}


def _expand(names, effects: Effects) -> list[str]:
    """``"force.b"`` → ``force.b[0..2]``; every name checked against the effects' parameters."""
    all_names = effects.param_names()
    out = []
    for n in names:
        hits = [a for a in all_names if a == n or a.startswith(n + "[")]
        if not hits:
            raise CausalGSError(f"'{n}' is not a parameter of the effects ({', '.join(all_names) or 'none'})")
        out += [h for h in hits if h not in out]
    return out


class PhysicsModel:
    """The observed points of ``obs`` as particles under the effects ``spec``, with the per-body parameters above and
    the effect parameters named in ``learn`` fitted; see the module docstring."""

    def __init__(self, obs: Observation, spec: str, learn=(), *, res: int = 24, E_range=(2e3, 4e5),
                 nu_range=(0.1, 0.45), cfl: float = 0.4, max_substeps: int = 4000):  # fmt: skip
        from causalgs.model.scene import _OWNER, _sim_store

        self.obs, self.spec, self.res = obs, spec, int(res)
        self.E_range, self.nu_range = tuple(map(float, E_range)), tuple(map(float, nu_range))
        self.effects = Effects.from_spec(spec)
        self.learn = _expand(learn, self.effects)
        store = _sim_store(CAPACITY, SEGMENT)
        if obs.points > CAPACITY:
            raise CausalGSError(f"{obs.points} points exceed the simulator's capacity of {CAPACITY}")
        cfg = SimConfig(res=self.res, lo=obs.lo, hi=obs.hi, segment=SEGMENT, cfl=cfl, max_substeps=max_substeps,
                        material="neo_hookean", effects=self.effects.spec())  # fmt: skip
        self.sim = Simulator(store, cfg)
        self.plan_of = None  # (θ, frames, substeps per interval) of the last rollout
        self._owner = _OWNER
        dt = _ti.torch_dtype()
        self.x0 = torch.as_tensor(obs.x[0], dtype=dt)  # where the simulated material starts
        # where the measured points start: the lens carries the material's fitted motions to them
        self.points0 = self.x0
        self.centroids = torch.stack([self.x0[torch.as_tensor(obs.body == b)].mean(0) for b in range(obs.bodies)])
        self.body = torch.as_tensor(obs.body)
        self._mix = None if obs.mix is None else torch.as_tensor(obs.mix, dtype=torch.float64)
        self._vol = torch.as_tensor(obs.vol, dtype=torch.float64)
        self._bend = None if obs.bend is None else torch.as_tensor(obs.bend, dtype=torch.long)
        knobs = []
        for b in range(obs.bodies):
            knobs += [Knob(f"{obs.names[b]}.E", "E", b), Knob(f"{obs.names[b]}.nu", "nu", b)]
            knobs += [Knob(f"{obs.names[b]}.v0[{i}]", "u", b, i) for i in range(3)]
            knobs += [Knob(f"{obs.names[b]}.omega0[{i}]", "w", b, i) for i in range(3)]
        flat = self.effects.flat()
        names = self.effects.param_names()
        for n in self.learn:
            i = names.index(n)
            effect, param = n.split("[")[0].split(".")
            prm = REGISTRY[effect].param(param)
            scale = SCALES.get(param, 1.0)
            upper = self._substep_cap(effect, param)
            if prm.lower is not None:
                knobs.append(Knob(n, "effect", index=i, scale=scale, lower=prm.lower, upper=upper))
            else:
                knobs.append(Knob(n, "effect", index=i, scale=scale, offset=float(flat[i])))
        self.knobs = knobs
        self.names = [k.name for k in knobs]

    def __getstate__(self) -> dict:
        """Everything but the simulator, which holds Taichi fields of this process: its config instead (a model sent
        to a worker process, :mod:`causalgs.discover.workers`, builds its own there)."""
        state = {k: v for k, v in self.__dict__.items() if k not in ("sim", "_owner", "plan_of")}
        state["sim"] = self.sim.config
        return state

    def __setstate__(self, state: dict) -> None:
        from causalgs.model.scene import _OWNER

        state = dict(state)
        config = state.pop("sim")
        self.__dict__.update(state)
        self.sim = _unpickled_simulator(config)
        self.plan_of = None
        self._owner = _OWNER

    def _substep_cap(self, effect: str, param: str) -> float | None:
        """The largest value of ``effect.param`` whose stable substep is no shorter than the elastic substep of the
        stiffest allowed material over :data:`SUBSTEP_COST` (None: the effect does not limit the substep)."""
        definition = REGISTRY[effect]
        if definition.dt_limit is None:
            return None
        E, nu, rho = self.E_range[1], self.nu_range[1], float(self.obs.density)
        c = math.sqrt(E * (1 - nu) / ((1 + nu) * (1 - 2 * nu)) / rho)  # the fastest pressure wave
        dx = self.sim.geo.dx
        target = dx / c / SUBSTEP_COST
        values = {k: np.array(v, dtype=np.float64) for k, v in self.effects.values(effect).items()}

        def dt(v: float) -> float:
            values[param] = np.array([v])
            return definition.dt_limit(values, dx, rho)

        lo, hi = 1e-6, 1.0
        while dt(hi) >= target:  # bracket, then bisect in log space (dt_limit falls as the parameter grows)
            lo, hi = hi, hi * 10.0
            if hi > 1e12:
                return None
        for _ in range(60):
            mid = math.sqrt(lo * hi)
            lo, hi = (mid, hi) if dt(mid) >= target else (lo, mid)
        return lo

    # -- θ ----------------------------------------------------------------------------------------------------------
    def index(self, name: str) -> int:
        if name not in self.names:
            raise CausalGSError(f"'{name}' is not a parameter of the model ({', '.join(self.names)})")
        return self.names.index(name)

    def pinned(self, theta: torch.Tensor, names=None) -> dict[str, str]:
        """The bounded parameters among ``names`` (default: all) that ``theta`` holds at a bound ("upper" or
        "lower": the sigmoid within :data:`PINNED` of 0 or 1): a stiffness or Poisson ratio at an end of its range,
        a bounded effect parameter. There the rollout no longer moves with the parameter, so its linearised standard
        error collapses to nothing and says nothing: the data asks for more than the model allows."""
        out = {}
        for name in self.names if names is None else names:
            k = self.knobs[self.index(name)]
            if k.kind in ("E", "nu") or (k.kind == "effect" and k.lower is not None and k.upper is not None):
                s = float(torch.sigmoid(torch.as_tensor(theta[self.index(name)], dtype=torch.float64)))
                if s > 1 - PINNED:
                    out[name] = "upper"
                elif s < PINNED:
                    out[name] = "lower"
        return out

    def base_indices(self) -> list[int]:
        """Entries of θ that are per-body (materials and initial velocities)."""
        return [i for i, k in enumerate(self.knobs) if k.kind != "effect"]

    def initial(self, E: float = 5e4, nu: float = 0.3, effects: dict | None = None) -> torch.Tensor:
        """θ at the stiffness ``E``, ratio ``nu``, the initial velocity fitted to the first observed frames (a rigid
        twist per body, least squares on the first differences) and the spec's effect values (or ``effects``)."""
        twist = self.fitted_twists()
        flat = self.effects.flat()
        out = []
        for k in self.knobs:
            if k.kind == "E":
                out.append(self.E_internal(E))
            elif k.kind == "nu":
                out.append(self.nu_internal(nu))
            elif k.kind in ("u", "w"):
                out.append(float(twist[k.body, (0 if k.kind == "u" else 3) + k.index]))
            else:
                v = (effects or {}).get(k.name, float(flat[k.index]))
                out.append(k.internal(v))
        return torch.tensor(out, dtype=torch.float64)

    def E_internal(self, E: float) -> float:
        """A stiffness (Pa) in θ's units: log-space inside ``E_range``, kept off its ends."""
        lo, hi = (math.log(a) for a in self.E_range)
        s = min(max((math.log(E) - lo) / (hi - lo), 1e-4), 1 - 1e-4)
        return math.log(s / (1 - s))

    def nu_internal(self, nu: float) -> float:
        """A Poisson ratio in θ's units, inside ``nu_range``, kept off its ends."""
        t = min(max((nu - self.nu_range[0]) / (self.nu_range[1] - self.nu_range[0]), 1e-4), 1 - 1e-4)
        return math.log(t / (1 - t))

    def fitted_twists(self, frames: int | None = None) -> np.ndarray:
        """[B, 6] (u, ω) per body: the rigid velocity field that best fits the initial velocities of the points
        (the slope at t = 0 of a least-squares parabola through each point's first ``frames`` positions, so gravity
        does not bias it), u at the body's rest centroid.

        ``frames`` None: the most first frames (at least :data:`TWIST_FRAMES`) that the parabolas follow within
        :data:`TWIST_FIT` times the noise on every frame: the whole free flight before a first contact, a drag or
        a spin bends them. Five frames leave the spin to the tracks' noise: on the landing control from video
        (seed 1, no spin) they gave ω = 0.36 rad/s about x where the flight before the impact (32 frames) gives
        0.01; calibrated from there, the base stayed in a tilted landing whose weak bounce it made up for with
        the ground 2 cm high."""
        obs = self.obs
        k = self.flight_frames() if frames is None else max(3, min(frames, obs.observed))
        v = self._parabolas(k)[0][1].reshape(-1, 3)
        out = np.zeros((obs.bodies, 6))
        c = self.centroids.double().numpy()
        for b in range(obs.bodies):
            sel = obs.body == b
            A = twist_basis(obs.x[0][sel] - c[b])
            sol, *_ = np.linalg.lstsq(A, v[sel].reshape(-1), rcond=None)
            out[b] = sol
        return out

    def _parabolas(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """The least-squares parabola of every coordinate's first ``k`` positions: its coefficients [3, P·3] (the
        position, the velocity at t = 0, the acceleration) and the RMS over the points of what it leaves per frame
        [k]."""
        obs = self.obs
        t = obs.times[:k] - obs.times[0]
        A = np.stack([np.ones_like(t), t, 0.5 * t**2], axis=1)
        y = obs.x[:k].reshape(k, -1)
        coef, *_ = np.linalg.lstsq(A, y, rcond=None)
        return coef, np.sqrt(((A @ coef - y) ** 2).mean(1))

    def flight_frames(self) -> int:
        """The most first frames of the fit window over which a parabola per point stays within ``TWIST_FIT``
        times the noise of every point's path, frame by frame (RMS over the points); at least ``TWIST_FRAMES``."""
        obs = self.obs
        sigma = obs.noise if obs.noise is not None else noise_floor(obs)
        best = min(TWIST_FRAMES, obs.observed)
        for k in range(best + 1, obs.observed + 1):
            if self._parabolas(k)[1].max() > TWIST_FIT * max(sigma, 1e-9):
                break
            best = k
        return best

    def unpack(self, theta: torch.Tensor) -> dict[str, torch.Tensor]:
        """Per-particle E, nu, v0 [P, 3] and the full effect vector from θ (differentiable)."""
        B = self.obs.bodies
        lo, hi = (math.log(a) for a in self.E_range)
        logE = [None] * B
        nu = [None] * B
        uw = [[None] * 6 for _ in range(B)]
        params = list(torch.as_tensor(self.effects.flat(), dtype=torch.float64).unbind()) or []
        for i, k in enumerate(self.knobs):
            a = theta[i]
            if k.kind == "E":
                logE[k.body] = lo + (hi - lo) * torch.sigmoid(a)
            elif k.kind == "nu":
                nu[k.body] = self.nu_range[0] + (self.nu_range[1] - self.nu_range[0]) * torch.sigmoid(a)
            elif k.kind == "u":
                uw[k.body][k.index] = a
            elif k.kind == "w":
                uw[k.body][3 + k.index] = a
            else:
                params[k.index] = k.value(a)
        E_b = torch.exp(torch.stack(logE))
        nu_b = torch.stack(nu)
        tw = torch.stack([torch.stack(r) for r in uw])  # [B, 6]
        r = self.x0.double() - self.centroids.double()[self.body]
        v0 = tw[self.body, :3] + torch.cross(tw[self.body, 3:], r, dim=1)
        p = torch.stack(params) if params else torch.zeros(0, dtype=torch.float64)
        return {"E": E_b[self.body], "nu": nu_b[self.body], "v0": v0, "params": p, "E_body": E_b, "nu_body": nu_b,
                "twist": tw}  # fmt: skip

    def values(self, theta: torch.Tensor) -> dict[str, float]:
        """Every knob's value in physical units (E in Pa, velocities in m/s and rad/s, effect parameters)."""
        with torch.no_grad():
            u = self.unpack(theta)
        out = {}
        for _i, k in enumerate(self.knobs):
            if k.kind == "E":
                out[k.name] = float(u["E_body"][k.body])
            elif k.kind == "nu":
                out[k.name] = float(u["nu_body"][k.body])
            elif k.kind in ("u", "w"):
                out[k.name] = float(u["twist"][k.body, (0 if k.kind == "u" else 3) + k.index])
            else:
                out[k.name] = float(u["params"][k.index])
        return out

    def spec_at(self, theta: torch.Tensor) -> str:
        """The effects spec with the fitted values of θ (what a refit run's config would say)."""
        with torch.no_grad():
            p = self.unpack(theta)["params"].numpy()
        eff = Effects.from_spec(self.spec)
        if len(p):
            eff.set_flat(p)
        return eff.spec()

    # -- rollout ----------------------------------------------------------------------------------------------------
    def rollout(self, theta: torch.Tensor, frames=None, *, lensed: bool = True) -> torch.Tensor:
        """Positions [len(frames), P, 3] (float64) at the observation's ``frames`` (default all after the first), seen
        through the observation's lens (:meth:`see`) unless ``lensed`` is False (the simulated material itself)."""
        obs = self.obs
        frames = list(range(1, len(obs.times))) if frames is None else [int(f) for f in frames]
        if not frames or min(frames) < 1:
            raise CausalGSError("rollout frames must be >= 1 (frame 0 is the start)")
        store = self.sim.store
        if self._owner.get(id(store)) is not self:
            store.resize(obs.points)
            store.from_torch("vol", torch.as_tensor(obs.vol, dtype=_ti.torch_dtype()))
            self._owner[id(store)] = self
        dt = _ti.torch_dtype()
        u = self.unpack(theta)
        density = torch.full((obs.points,), float(obs.density), dtype=dt)
        times = [float(obs.times[f] - obs.times[0]) for f in frames]
        x, _, _ = simulate(self.sim, self.x0, u["v0"].to(dt), u["E"].to(dt), u["nu"].to(dt), density, times,
                           u["params"].to(dt))  # fmt: skip
        self.plan_of = (theta.detach().double().clone(), tuple(frames), list(self.sim.last_plan))
        return self.see(x.double(), frames) if lensed else x.double()

    def see(self, x: torch.Tensor, frames=None) -> torch.Tensor:
        """Simulated positions [F, P, 3] at the observation's ``frames`` (default: every frame after the first) as
        the measurement sees them: through its lens where it has one
        (:func:`~causalgs.discover.observation.rigid_projection` or, for tracks that stretch each pattern,
        :func:`~causalgs.discover.observation.affine_projection`; the latter at the frames the observation's
        rigid tracks stretch, ``Observation.stretch``), else as they are."""
        if self.obs.mix is None:
            return x
        project = LENSES[self.obs.lens_kind]
        args = (self.x0.double(), self._mix, self._vol)
        if self._bend is not None:  # affine tracks that also bend each body
            return project(x, *args, at=self.points0.double(), bend=self._bend)
        out = project(x, *args, at=self.points0.double())
        if self.obs.stretch is not None:
            frames = range(1, len(self.obs.times)) if frames is None else frames
            rows = torch.as_tensor(np.nonzero(self.obs.stretch[list(frames)])[0])
            if len(rows):
                out = out.index_put((rows,), affine_projection(x[rows], *args, at=self.points0.double()))
        return out
