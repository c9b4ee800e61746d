"""The CausalGS scene model: canonical Gaussians + inverse-physics fields + (once built) the simulated particles.

It answers one question for the rest of the program: *where is every Gaussian at frame k*, by either dynamics path:

- ``kinematic(steps)``: RK2 integration of the inferred velocity field (all Gaussians that are not static);
- ``simulate(frames)``: the differentiable MPM from the inferred causes (initial velocity from the kinematic field at
  t = 0, materials from f_mat, the configured effects with their learned parameters); dynamic Gaussians follow the
  particles' displacement and deformation (Σ = F Σ Fᵀ).

and renders a state from a camera. Time is in frames of the dataset (seconds = frame / fps).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from causalgs import _ti
from causalgs.errors import CausalGSError
from causalgs.model.config import FitConfig
from causalgs.model.fields import InversePhysics
from causalgs.model.gaussians import Gaussians
from causalgs.model.kinematic import blend, flow_paths, pattern_motion, quat_mul, rotvec_quat
from causalgs.model.particles import Particles, TooManyParticles, build_particles
from causalgs.model.refine import jacobian, place
from causalgs.model.residual import Residual, remove_rigid
from causalgs.render.reference import quat_scale_to_cov
from causalgs.sim.autograd import deformed_covariance, simulate
from causalgs.sim.effects import WALL_BAND, Effects
from causalgs.sim.mpm import SimConfig, Simulator, segment_specs
from causalgs.similarity import Similarity
from causalgs.store import ParticleStore


@dataclass
class State:
    """Gaussians at one time: means [N, 3] and either quats [N, 4] and optionally log-scales [N, 3] (tracked) or
    covs [N, 3, 3] (simulated); ``offset``: the deformation residual's displacement of the dynamic rows, if any."""

    means: torch.Tensor
    quats: torch.Tensor | None = None
    covs: torch.Tensor | None = None
    scales: torch.Tensor | None = None
    offset: torch.Tensor | None = None

    def overrides(self) -> dict:
        out = {"means": self.means}
        if self.covs is not None:
            out["covs"] = self.covs
        elif self.quats is not None:
            out["quats"] = self.quats
            if self.scales is not None:
                out["scales"] = self.scales
        return out


_STORES: dict = {}
_OWNER: dict = {}  # id(store) -> the model whose particles (count, volumes) the store holds


def _sim_store(capacity: int, segment: int) -> ParticleStore:
    """One simulator store per (runtime, capacity): every new store is a new compile of every MPM kernel."""
    key = (_ti.generation(), capacity, segment)
    if key not in _STORES:
        _STORES.clear()
        store = ParticleStore(capacity, sh_degree=0)
        store.add_fields(segment_specs(segment))
        _STORES[key] = store
    return _STORES[key]


class CausalGS(torch.nn.Module):
    """See the module docstring. ``fps`` converts frames to seconds; ``lo, hi`` bound the scene."""

    def __init__(self, config: FitConfig, gaussians: Gaussians, lo, hi, fps: float, train_frames: int):
        super().__init__()
        self.config = config
        self.gaussians = gaussians
        self.fps = float(fps)
        self.train_frames = int(train_frames)  # frames 0..train_frames-1 are observed
        window = dict(duration=(train_frames - 1) / fps, frames=train_frames)
        self.fields = InversePhysics(config.fields, lo, hi, **window)
        # The kinematic fit of the observed frames, kept as it stood at the end of the kinematic stage: the physical
        # stage trains ``fields`` further (through the initial velocity), which may move its later frames.
        self.tracked = InversePhysics(config.fields, lo, hi, **window)
        self.tracked.requires_grad_(False)
        rc = config.kinematic.residual
        size = float(np.max(np.asarray(hi, dtype=np.float64) - np.asarray(lo, dtype=np.float64)))
        self.residual = Residual(rc, config.fields.code_dim, window["duration"], size) if rc.enabled else None
        self.register_buffer("has_tracked", torch.zeros((), dtype=torch.bool))
        # The per-frame refinement of the tracked motion (kinematic.track, causalgs.model.refine): every pattern's
        # motion x = A x0 + b at observed frames 0..n-1, fitted frame by frame to that frame's images (n = 0: none).
        K = config.fields.patterns
        self.register_buffer("track_A", torch.zeros(0, K, 3, 3, dtype=torch.float64))
        self.register_buffer("track_b", torch.zeros(0, K, 3, dtype=torch.float64))
        self.register_buffer("lo", torch.as_tensor(lo, dtype=torch.float64))
        self.register_buffer("hi", torch.as_tensor(hi, dtype=torch.float64))
        self.register_buffer("dynamic", torch.ones(gaussians.n, dtype=torch.bool))
        self.register_buffer("box", torch.zeros(2, 3, dtype=torch.float64))  # simulation box lo, hi (0 = unset)
        self.effect_params = torch.nn.Parameter(torch.zeros(0, dtype=torch.float64))
        # The forecast's start (the assimilation stage, see Trainer._assimilate): a per-pattern twist added to the
        # velocities of the state at frame ``forecast_start`` (-1: none; the forecast starts at the last observed
        # frame), that state taken from FORECAST_SOURCES[forecast_source]: the kinematic fit or the replay from t = 0.
        self.forecast_twists = torch.nn.Parameter(torch.zeros(config.fields.patterns, 6))
        self.register_buffer("forecast_start", torch.tensor(-1, dtype=torch.int64))
        self.register_buffer("forecast_source", torch.tensor(0, dtype=torch.int64))
        # each source's fitted correction (the stage chooses between them and none; kept to resume and inspect)
        self.register_buffer("assimilated", torch.zeros(len(FORECAST_SOURCES), config.fields.patterns, 6))
        # log of the factor on every particle's Young's modulus chosen by the stiffness calibration (Trainer._calibrate)
        self.register_buffer("log_stiffness", torch.zeros((), dtype=torch.float64))
        # The similarity from the data's world frame to the model's (x_model = s R x_data + t, 4×4): the physics
        # frame that the fit inferred (z up, gravity 9.8 in its units; causalgs.model.upright). Identity until then.
        self.register_buffer("frame", torch.eye(4, dtype=torch.float64))
        self.particles: Particles | None = None
        self._sim: Simulator | None = None

    # -- persistence ------------------------------------------------------------------------------------------------
    def get_extra_state(self) -> dict:
        return {"particles": None if self.particles is None else self.particles.state_dict()}

    def set_extra_state(self, state: dict) -> None:
        p = state.get("particles")
        self.particles = None if p is None else Particles.from_state_dict(p)
        self._sim = None

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        # Buffers and parameters whose size depends on the data (Gaussian count, effect count): take the saved size.
        state_dict.setdefault(prefix + "track_A", self.track_A[:0])  # saved before the per-frame refinement
        state_dict.setdefault(prefix + "track_b", self.track_b[:0])
        for name in ("dynamic", "effect_params", "track_A", "track_b"):
            key = prefix + name
            if key in state_dict and state_dict[key].shape != getattr(self, name).shape:
                old = getattr(self, name)
                new = torch.empty_like(state_dict[key], dtype=old.dtype)
                if isinstance(old, torch.nn.Parameter):
                    self.effect_params = torch.nn.Parameter(new)
                else:
                    self.register_buffer(name, new)
        if prefix + "forecast_start" not in state_dict:  # saved before the assimilation stage existed
            state_dict[prefix + "forecast_start"] = torch.tensor(-1, dtype=torch.int64)
            state_dict[prefix + "forecast_twists"] = torch.zeros_like(self.forecast_twists)
        if prefix + "forecast_source" not in state_dict:  # saved before the replayed start existed: observed
            state_dict[prefix + "forecast_source"] = torch.tensor(0, dtype=torch.int64)
            state_dict[prefix + "assimilated"] = torch.zeros_like(self.assimilated)
        if prefix + "log_stiffness" not in state_dict:  # saved before the stiffness calibration existed
            state_dict[prefix + "log_stiffness"] = torch.zeros((), dtype=torch.float64)
        state_dict.setdefault(prefix + "frame", torch.eye(4, dtype=torch.float64))  # saved before re-posing existed
        if self.residual is not None and prefix + "residual.size" not in state_dict:  # saved before the residual
            state_dict.update({prefix + "residual." + k: v for k, v in self.residual.state_dict().items()})
        if prefix + "has_tracked" not in state_dict:  # a model saved before the tracked copy existed
            for k in [k for k in state_dict if k.startswith(prefix + "fields.")]:
                state_dict[prefix + "tracked." + k[len(prefix + "fields.") :]] = state_dict[k]
            state_dict[prefix + "has_tracked"] = torch.zeros((), dtype=torch.bool)
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def keep_track(self) -> None:
        """Freeze the kinematic fit as it stands (the end of the kinematic stage): from now on the kinematic path,
        the consistency targets and the forecast's starting state use this copy."""
        with torch.no_grad():
            self.tracked.load_state_dict(self.fields.state_dict())
            self.has_tracked.fill_(True)

    def similarity(self) -> Similarity:
        """:attr:`frame` as a :class:`~causalgs.similarity.Similarity` (data's world → the model's)."""
        m = self.frame.double().numpy()
        s = float(np.cbrt(np.linalg.det(m[:3, :3])))
        return Similarity.make(m[:3, :3] / s, s, m[:3, 3], what="the model's frame")

    def reframe(self, sim: Similarity) -> None:
        """Re-pose the whole model by ``sim`` (before the physical stage): Gaussians, both copies of the fields, the
        scene bounds; :attr:`frame` composes it. Renders from cameras re-posed by the same ``sim`` are unchanged."""
        if self.particles is not None:
            raise CausalGSError("a model is re-posed before its physical stage, not after")
        self.gaussians.reframe(sim)
        self.fields.reframe(sim)
        self.tracked.reframe(sim)
        if self.residual is not None:
            self.residual.reframe(sim)
        if len(self.track_A):  # x' = s R x + t: A' = R A Rᵀ, b' = s R b + t − A' t
            R = torch.as_tensor(sim.R, dtype=torch.float64)
            t = torch.as_tensor(sim.t, dtype=torch.float64)
            A = R @ self.track_A @ R.T
            b = sim.scale * self.track_b @ R.T + t - (A @ t[:, None])[..., 0]
            self.set_tracks(A, b)
        lo, hi = scene_bounds(self.gaussians.means.detach().double().numpy())
        with torch.no_grad():
            self.lo.copy_(torch.as_tensor(lo))
            self.hi.copy_(torch.as_tensor(hi))
            self.frame.copy_(torch.as_tensor(self.similarity().then(sim).matrix()))

    def set_tracks(self, A: torch.Tensor, b: torch.Tensor) -> None:
        """Keep the refined motion of the observed frames (:class:`~causalgs.model.refine.Tracks`' A [n, K, 3, 3],
        b [n, K, 3]); from now on the tracked state of those frames is theirs."""
        self.register_buffer("track_A", torch.as_tensor(A, dtype=torch.float64).clone())
        self.register_buffer("track_b", torch.as_tensor(b, dtype=torch.float64).clone())

    @property
    def kinematic_fields(self) -> InversePhysics:
        return self.tracked if bool(self.has_tracked) else self.fields

    # -- kinematic path ---------------------------------------------------------------------------------------------
    def mixtures(self, x: torch.Tensor) -> torch.Tensor:
        """h of the kinematic path (the tracked fit once it exists); the causes use ``fields`` directly."""
        f = self.kinematic_fields
        return f.mixture(f.code(x))

    def codes(self) -> torch.Tensor:
        """z [n, C] of the dynamic Gaussians at their canonical positions, by the kinematic path's fields."""
        return self.kinematic_fields.code(self.gaussians.means[self.dynamic].detach())

    def kinematic(self, steps: int, *, rotations: bool = True, index: torch.Tensor | None = None, frames=None,
                  mixtures: torch.Tensor | None = None):  # fmt: skip
        """Means [F, N, 3] and quats [F, N, 4] at ``frames`` (default 0..steps, all ≤ steps). Gaussians not in
        ``index`` (default: the dynamic ones) stay at their canonical state. ``mixtures``: their h when the caller
        has it already."""
        g = self.gaussians
        idx = torch.nonzero(self.dynamic).flatten() if index is None else index
        frames = list(range(steps + 1)) if frames is None else [int(k) for k in frames]
        h = self.mixtures(g.means[idx].detach()) if mixtures is None else mixtures
        xs, qs = self.trajectories(h, g.means[idx],
                                   g.quats[idx] if rotations else None, steps, frames)  # fmt: skip
        means = g.means[None].expand(len(frames), -1, -1).clone()
        means[:, idx] = xs.to(means.dtype)
        quats = None
        if qs is not None:
            quats = g.quats[None].expand(len(frames), -1, -1).clone()
            quats[:, idx] = qs.to(quats.dtype)
        return means, quats

    def trajectories(self, h, x0, q0, steps: int, frames):
        """Positions [F, n, 3] (and rotations [F, n, 4] if q0 is given) at ``frames`` of particles with mixtures h
        starting at x0: the patterns' rigid motions integrated by RK2 at dt = 1/fps, blended by h (see
        :func:`causalgs.model.kinematic.blend`)."""
        f = self.kinematic_fields
        if not f.structured:  # the ablation without VFD: one velocity per material point, rotations held
            xs = flow_paths(f, x0, steps, 1.0 / self.fps, self.config.kinematic.substeps)[list(frames)]
            return xs, (q0[None].expand(len(frames), -1, -1) if q0 is not None else None)
        R, t, q = pattern_motion(f, steps, 1.0 / self.fps, self.config.kinematic.substeps)
        out = [blend(h, x0, q0, R[k], t[k], q[k]) for k in frames]
        xs = torch.stack([x for x, _ in out])
        return xs, (torch.stack([r for _, r in out]) if q0 is not None else None)

    def tracked_positions(self, x0: torch.Tensor, frames) -> torch.Tensor:
        """Positions [F, n, 3] at ``frames`` of the material points at canonical ``x0``: the refined tracks where
        they exist (every frame of ``frames``), else the velocity field's motion (:meth:`trajectories`)."""
        frames = [int(k) for k in frames]
        h = self.mixtures(x0)
        if frames and max(frames) < len(self.track_A):
            A, b = self.track_A.to(x0.dtype), self.track_b.to(x0.dtype)
            return torch.stack([place(h, x0, A[k], b[k]) for k in frames])
        return self.trajectories(h, x0, None, max(frames, default=0), frames)[0]

    def kinematic_state(self, frame: int) -> State:
        means, quats = self.kinematic(int(frame), frames=[int(frame)])
        return State(means[0], quats[0])

    def observed(self, frames, *, residual: bool = True, codes: torch.Tensor | None = None) -> list[State]:
        """The tracked state at ``frames``: the refined tracks at the observed frames they cover, else the velocity
        field's motion (:meth:`kinematic`), plus, at observed frames, the deformation residual
        (:mod:`causalgs.model.residual`; ``residual=False`` leaves it out). The model's best reconstruction of what
        was seen: what interpolation renders and the kinematic stage trains. ``codes``: :meth:`codes` when the
        caller has them already."""
        frames = [int(k) for k in frames]
        z = self.codes() if codes is None else codes
        h = self.kinematic_fields.mixture(z)
        g = self.gaussians
        idx = torch.nonzero(self.dynamic).flatten()
        by_field = [k for k in frames if k >= len(self.track_A)]  # the refined tracks place the others
        moved = {}
        if by_field:
            means, quats = self.kinematic(max(by_field), frames=by_field, mixtures=h)
            moved = {k: (means[i], quats[i]) for i, k in enumerate(by_field)}
        out = []
        for k in frames:
            refined = k not in moved
            if refined:  # each pattern's refined motion; the covariances follow its Jacobian
                A, b = self.track_A[k].to(g.means.dtype), self.track_b[k].to(g.means.dtype)
                m, q = g.means.clone(), g.quats
                m[idx] = place(h.to(m.dtype), g.means[idx], A, b)
            else:
                m, q = moved[k]
            s = g.scales
            dx = None
            if residual and self.residual is not None and k < self.train_frames:
                d = self.residual(z, k / self.fps)
                dx = remove_rigid(d.dx, m[idx].detach(), h).to(m.dtype)
                m, q, s = m.clone(), q.clone(), s.clone()
                m[idx] = m[idx] + dx
                q[idx] = quat_mul(rotvec_quat(d.drot.to(q.dtype)), q[idx])
                s[idx] = s[idx] + d.dlog_scale.to(s.dtype)
            if refined:
                covs = quat_scale_to_cov(q, torch.exp(s))
                J = jacobian(h.to(m.dtype), A)
                covs = covs.index_put((idx,), J @ covs[idx] @ J.transpose(1, 2))
                out.append(State(m, covs=covs, offset=dx))
            else:
                out.append(State(m, q, scales=s if dx is not None else None, offset=dx))
        return out

    # -- physical path ----------------------------------------------------------------------------------------------
    def simulator(self) -> Simulator:
        if self.particles is None:
            raise CausalGSError("this model has no simulated particles yet (the physical stage has not run)")
        if self._sim is None:
            pc = self.config.physics
            lo, hi = self.box.tolist()
            store = _sim_store(pc.capacity, pc.segment)
            cfg = SimConfig(res=pc.res, lo=tuple(lo), hi=tuple(hi), segment=pc.segment, cfl=pc.cfl,
                            max_substeps=pc.max_substeps * 64, material="neo_hookean", effects=pc.effects)  # fmt: skip
            sim = Simulator(store, cfg)
            if len(self.effect_params) != len(sim.effects.param_names()):
                raise CausalGSError("the model's effect parameters do not match its effects spec")
            self._sim = sim
        store = self._sim.store
        if _OWNER.get(id(store)) is not self:  # the store is shared: another model may have used it since
            store.resize(len(self.particles))
            store.from_torch("vol", self.particles.vol.to(_ti.torch_dtype()))
            _OWNER[id(store)] = self
        return self._sim

    def build_physics(self, seed: int = 0) -> None:
        """Choose the simulation box, the ground plane and the particles (after the kinematic stage, which decides
        which Gaussians are dynamic and how far they travel).

        Particles come from the *solid* dynamic Gaussians (opacity ≥ ``physics.min_opacity``): faint floaters that
        the kinematic fit happened to move are carried along but are not matter. Bounds use robust percentiles for
        the same reason. The ground ("auto") is the densest level of the static Gaussians below the moving ones
        (a floor is a plane full of Gaussians), else the lowest point of the bodies at rest."""
        pc = self.config.physics
        g = self.gaussians
        means = g.means.detach().double()
        dyn = self.dynamic
        solid = dyn & (torch.sigmoid(g.opacities.detach()) >= pc.min_opacity)
        if not bool(solid.any()):
            raise CausalGSError("no dynamic Gaussians: the kinematic stage found nothing solid that moves")
        with torch.no_grad():
            traj, _ = self.kinematic(self.train_frames - 1, rotations=False, index=torch.nonzero(solid).flatten())
        moving = traj[:, solid].double().reshape(-1, 3)
        static = means[~dyn]
        size = float((self.hi - self.lo).max())
        effects = Effects.from_spec(pc.effects)
        names = effects.param_names()
        flat = effects.flat()
        m_lo, m_hi = _quantile(moving, 0.005), _quantile(moving, 0.995)
        ground_z = None
        if "ground.d" in names and pc.ground == "auto":
            # Below where the bodies start (their fitted paths may dip through the floor; their rest state does not).
            start_low = float(_quantile(means[solid], 0.001)[2])
            ground_z = _ground_level(static[:, 2], start_low, size)
            flat[names.index("ground.d")] = ground_z
        lo, hi = m_lo.clone(), m_hi.clone()
        if ground_z is not None:  # nothing moves below the ground
            lo[2] = ground_z
            hi[2] = max(float(hi[2]), ground_z + 0.1 * size)
        # The margin around the moving region is a fixed share of it (an eighth of the grid at any resolution), so
        # a finer grid resolves the same box more finely instead of hugging the bodies' paths more tightly.
        margin = max(WALL_BAND + 1, math.ceil(pc.res / 8))
        if len(static) > 100:  # the static scene's footprint in x, y (the floor, the room)
            f_lo, f_hi = _quantile(static[:, :2], 0.01), _quantile(static[:, :2], 0.99)
            if pc.box == "scene":
                lo[:2], hi[:2] = torch.minimum(lo[:2], f_lo), torch.maximum(hi[:2], f_hi)
            else:  # "moving": the paths, and the footprint's edge along an axis where a path comes within the
                # margin of it (a body that reaches the room's walls), so that the box's walls stand at the room's
                reach = margin * float((hi - lo).max()) / (pc.res - 2 * margin)
                lo[:2] = torch.where(lo[:2] - reach <= f_lo, torch.minimum(lo[:2], f_lo), lo[:2])
                hi[:2] = torch.where(hi[:2] + reach >= f_hi, torch.maximum(hi[:2], f_hi), hi[:2])
        side = float((hi - lo).max())
        dx = side / (pc.res - 2 * margin)
        centre = (lo + hi) / 2
        limit = min(pc.max_particles, pc.capacity)
        for _ in range(16):  # a large body on a fine grid: coarser cells (a larger box), never a thinner fill
            box_lo = centre - 0.5 * pc.res * dx
            box_lo[2] = lo[2] - (WALL_BAND + 0.5) * dx  # the ground plane just above the bottom wall band
            # Solid Gaussians off the grid (outliers beyond the paths' robust bounds) are carried like floaters, not
            # simulated: a particle whose stencil leaves the grid is not matter the grid can move.
            inner_lo, inner_hi = box_lo + dx, box_lo + (pc.res - 2) * dx
            inside = solid & ((means >= inner_lo) & (means <= inner_hi)).all(-1)
            if not bool(inside.any()):
                raise CausalGSError("no solid dynamic Gaussian lies inside the simulation box")
            try:
                particles = build_particles(means.numpy(), dyn.numpy(), box_lo.numpy(), dx, pc.budget, limit, seed,
                                            solid=inside.numpy(), coarse_fill=False, fill=pc.fill)  # fmt: skip
                break
            except TooManyParticles as e:
                # The count follows the volume (dx⁻³) only roughly: the surface's partial voxels and the closing
                # change with the cell, so every try grows it by a tenth at least.
                dx *= max(1.03 * (e.count / limit) ** (1.0 / 3.0), 1.1)
        else:
            fewer = f" or lower physics.budget (Gaussian particles, {pc.budget})" if pc.fill == "gaussians" else ""
            raise CausalGSError(f"no grid spacing keeps the particles within physics.max_particles = {limit}: raise "
                                f"it{fewer}")
        self.box.copy_(torch.stack([box_lo, box_lo + pc.res * dx]))
        self.effect_params = torch.nn.Parameter(torch.as_tensor(flat, dtype=torch.float64))
        self.particles = particles
        self._sim = None

    @property
    def cell(self) -> float:
        """The simulation grid's cell size (m)."""
        return float((self.box[1] - self.box[0]).max()) / self.config.physics.res

    def learn_mask(self) -> torch.Tensor:
        """Which entries of the effect parameters are trained (``physics.learn``)."""
        names = Effects.from_spec(self.config.physics.effects).param_names()
        unknown = [n for n in self.config.physics.learn if n not in names]
        if unknown:
            raise CausalGSError(f"physics.learn names {', '.join(unknown)}; the effects have {', '.join(names)}")
        return torch.tensor([n in self.config.physics.learn for n in names], dtype=torch.bool)

    def causes(self) -> dict[str, torch.Tensor]:
        """Initial velocity and materials of every particle (differentiable in the fields)."""
        p = self.particles
        f = self.fields
        x0 = p.x0.to(f.centres.dtype)
        h = f.mixture(f.code(x0))
        v0 = f.velocity(x0, 0.0, h)
        return {"x0": x0, "v0": v0, "h": h, **self.materials(x0)}

    def materials(self, x: torch.Tensor) -> dict[str, torch.Tensor]:
        """E, nu, density at canonical positions ``x``: f_mat plus the per-pattern offsets, weighted by the tracked
        fit's mixtures (the motion segmentation is a constant here: materials are learned for the bodies it found)."""
        with torch.no_grad():
            h = self.mixtures(x)
        out = self.fields.materials(x, h)
        if float(self.log_stiffness) != 0.0:  # the calibrated factor, kept inside the configured range
            lo, hi = self.config.fields.E_range
            out["E"] = (out["E"] * torch.exp(self.log_stiffness).to(out["E"].dtype)).clamp(lo, hi)
        return out

    def simulate(self, frames, start: int = 0, twists: torch.Tensor | None = None,
                 restart: dict | None = None) -> dict[str, torch.Tensor]:  # fmt: skip
        """Particle x, v, F [T, P, ...] at the given frame indices (sorted, > ``start``, or ≥ 0 from the start)
        through the differentiable MPM, with the inferred materials and effects. From ``start`` = 0 the particles
        start from the inferred causes (canonical positions, the initial velocity field); from a later frame they start
        from the kinematic fit's state there (:meth:`observed_state`, a constant): a shooting segment in training, the
        forecast after the observed window. ``twists`` [K, 6] (later starts only) adds a rigid velocity per motion
        pattern, blended by the tracked mixtures: the assimilation stage's correction of the observed velocity.
        ``restart``: :meth:`restart_state` of ``start`` when the caller already has it (it is a constant)."""
        sim = self.simulator()
        c = self.causes()
        dt = _ti.torch_dtype()
        start = int(start)
        if start == 0:
            x0, v0, C0, F0 = c["x0"], c["v0"], None, None
        else:
            s = restart if restart is not None else self.restart_state(start, c)
            x0, v0, C0, F0 = s["x"], s["v"], s["C"], s["F"]
            if twists is not None:
                v0 = v0 + self.pattern_velocity(twists, x0)
        times = [(float(f) - start) / self.fps for f in frames]
        x, v, F = simulate(sim, x0.to(dt), v0.to(dt), c["E"].to(dt), c["nu"].to(dt), c["density"].to(dt), times,
                           self.effect_params.to(dt), C0=C0, F0=F0)  # fmt: skip
        return {"x": x, "v": v, "F": F, **c}

    def restart_state(self, start: int, causes: dict | None = None,
                      source: str = "observed") -> dict[str, torch.Tensor]:  # fmt: skip
        """The constant state a simulation from frame ``start`` > 0 begins with, in the simulator's dtype.

        - ``source="observed"``: :meth:`observed_state` (the kinematic fit there), with the preloaded F of bodies at
          rest (``physics.preload``);
        - ``source="simulated"``: the replay from t = 0's particles at ``start`` (x, v, F; C = 0). The kinematic fit
          is smooth in time and lags a bounce by centimetres; the replay has the bounce where the contact put it."""
        dt = _ti.torch_dtype()
        if source == "simulated":
            with torch.no_grad():
                out = self.simulate([int(start)])
            F = out["F"][0].detach()
            return {"x": out["x"][0].detach(), "v": out["v"][0].detach(), "C": torch.zeros_like(F), "F": F}
        if source != "observed":
            raise CausalGSError(f"unknown forecast start source '{source}' (choose from {', '.join(FORECAST_SOURCES)})")
        s = self.observed_state(start)
        F = s["F"]
        if self.config.physics.preload > 0:
            F = self._preload(s, self.causes() if causes is None else causes)
        return {"x": s["x"], "v": s["v"], "C": s["C"].to(dt), "F": F.to(dt)}

    def _preload(self, s: dict, c: dict) -> torch.Tensor:
        """F for a restart from the observed state ``s`` with the bodies seen at rest already carrying their weight.

        A body at rest on the ground is compressed by gravity; restarted stress-free it would first sag (a soft one
        by centimetres). So: simulate the observed state with zero velocity for ``physics.preload`` frames (no
        gradient), and give the particles that are (nearly) at rest, those whose observed velocity would carry them
        less than half a cell over that time, the deformation they settled into; faster ones keep the observed
        rotation."""
        sim = self.simulator()
        dt = _ti.torch_dtype()
        with torch.no_grad():
            _, _, F = simulate(sim, s["x"].to(dt), torch.zeros_like(s["v"]).to(dt), c["E"].detach().to(dt),
                               c["nu"].detach().to(dt), c["density"].detach().to(dt),
                               [self.config.physics.preload / self.fps], self.effect_params.detach().to(dt),
                               F0=s["F"].to(dt))  # fmt: skip
        seconds = self.config.physics.preload / self.fps
        dx = self.cell
        rest = s["v"].norm(dim=1) * seconds < 0.5 * dx  # would move less than half a cell while settling
        return torch.where(rest[:, None, None], F[-1].to(s["F"].dtype), s["F"])

    def observed_state(self, frame: int) -> dict[str, torch.Tensor]:
        """The particles' state at ``frame`` by the kinematic fit (the tracked copy).

        - x: the tracked positions, kept inside the simulation domain (off the wall bands; not onto the ground plane,
          which simulated bodies rest a fraction of a cell into);
        - F: the rotation of ∂x/∂x0 (forward-mode autodiff through the mixtures and the patterns' motion). Its
          stretch is dropped: a blend of rigid motions shears or even inverts a neighbourhood where the mixtures
          change quickly, which says nothing about the material's strain, and would start the body vibrating;
        - v: the slope at ``frame`` of a least-squares parabola through the tracked positions of the last
          ``VELOCITY_FRAMES`` frames, zero where not significant (:func:`_resting`). The field's own velocity at the
          end of the fitted window is its least constrained value; a parabola is exact for free fall;
        - C = 0: the particle velocities carry any rotation."""
        p = self.particles
        f = self.kinematic_fields
        x0 = p.x0.to(f.centres.dtype)
        k = int(frame)

        def at_k(x):
            return self.tracked_positions(x, [k])[0]

        with torch.enable_grad():
            cols = [torch.func.jvp(at_k, (x0,), (torch.zeros_like(x0).index_fill_(1, torch.tensor([i]), 1.0),))
                    for i in range(3)]  # fmt: skip
        x = cols[0][0].detach()
        F = _rotation(torch.stack([c[1].detach() for c in cols], dim=-1))
        with torch.no_grad():
            if k >= 2:  # the slope at k of a least-squares parabola through the last VELOCITY_FRAMES tracked positions
                ks = list(range(max(0, k - VELOCITY_FRAMES + 1), k + 1))
                v = _resting(self.tracked_positions(x0, ks), self.fps)
            elif not f.structured:
                v = f.velocity(x0, k / self.fps)
            else:
                R, t, _ = pattern_motion(f, k, 1.0 / self.fps, self.config.kinematic.substeps)
                c = (R[k] @ f.centres[..., None])[..., 0] + t[k] if bool(f.moving_centres) else f.centres
                a, w = f.affine(self.mixtures(x0), torch.tensor([k / self.fps], dtype=x0.dtype), c)
                v = a[0] + torch.linalg.cross(w[0], x)
        dx = self.cell
        band = WALL_BAND * dx
        x = torch.minimum(torch.maximum(x, self.box[0].to(x.dtype) + band), self.box[1].to(x.dtype) - band)
        return {"x": x, "F": F, "v": v, "C": torch.zeros_like(F)}

    def pattern_velocity(self, twists: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        """v_i = Σ_k h_ik (u_k + ω_k × (x_i − c_k)) [P, 3] for twists [K, 6] (u, ω) at particle positions ``x``, with
        the tracked mixtures h of the particles and c_k each pattern's h-weighted centroid of ``x``."""
        with torch.no_grad():
            h = self.mixtures(self.particles.x0.to(self.kinematic_fields.centres.dtype)).to(x.dtype)
            c = (h.T @ x) / h.sum(0).clamp_min(1e-12)[:, None]  # [K, 3]
        tw = twists.to(x.dtype)
        lin = h @ (tw[:, :3] - torch.linalg.cross(tw[:, 3:], c))
        return lin + torch.linalg.cross(h @ tw[:, 3:], x)

    def forecast(self, frames) -> dict[str, torch.Tensor]:
        """Particle x, v, F [T, P, ...] at frame indices after the observed window, simulated with the inferred
        materials and effects from the observed state: the prediction of the future from what has been seen, rather
        than a replay of the whole sequence from t = 0. After the assimilation stage it starts a few frames before
        the end of the window, from the state (tracked, or replayed from t = 0) and the velocity correction that
        made the simulation match those frames' images best; otherwise at the last observed frame's tracked state.
        With ``physics.anchor`` the simulation from the chosen start gives only the velocities at the last observed
        frame, and the forecast goes on from there with the tracked positions and rotations of that frame."""
        last = self.train_frames - 1
        frames = [int(k) for k in frames]
        if not frames or min(frames) <= last:
            raise CausalGSError(f"forecast frames must come after the last observed frame {last}")
        start = int(self.forecast_start)
        if start < 0:
            return self.simulate(frames, start=last)
        source = FORECAST_SOURCES[int(self.forecast_source)]
        restart = self.restart_state(start, source=source)
        twists = self.forecast_twists.detach()
        if start >= last or not self.config.physics.anchor:
            return self.simulate(frames, start=start, twists=twists, restart=restart)
        end = self.simulate([last], start=start, twists=twists, restart=restart)
        seen = self.restart_state(last, source="observed")
        return self.simulate(frames, start=last, restart={**seen, "v": end["v"][0].detach()})

    def physical_states(self, x: torch.Tensor, F: torch.Tensor) -> list[State]:
        """Gaussian states (means, covariances) for simulated particle states x [T, P, 3], F [T, P, 3, 3]."""
        g, p = self.gaussians, self.particles
        scales = torch.exp(g.scales)
        cov0 = quat_scale_to_cov(g.quats, scales)
        dyn = p.dynamic
        out = []
        for k in range(len(x)):
            means = g.means.clone()
            covs = cov0.clone()
            Fc = F[k][p.carrier].to(means.dtype)
            means[dyn] = p.carry(x[k], F[k]).to(means.dtype)
            covs[dyn] = deformed_covariance(Fc, g.quats[dyn], scales[dyn])
            out.append(State(means, covs=covs))
        return out

    # -- rendering --------------------------------------------------------------------------------------------------
    def render(self, state: State, camera, background):
        return self.gaussians.render(camera, tuple(float(b) for b in background), **state.overrides())


VELOCITY_FRAMES = 6
# where a forecast's starting state comes from (the buffer ``forecast_source`` indexes this)
FORECAST_SOURCES = ("observed", "simulated")


def _resting(xs: torch.Tensor, fps: float) -> torch.Tensor:
    """Velocities [n, 3] at the last of the positions xs [m, n, 3] (frames 1/fps apart): the slope of a least-squares
    parabola, set to zero where it is not significant, i.e. below twice its standard error from the fit's residual
    scatter (for m > 3; a tracked body at rest jitters by a fraction of a millimetre, which the slope magnifies)."""
    m = len(xs)
    w = _slope_weights(m, fps).to(xs.dtype)
    v = torch.einsum("t,tnd->nd", w, xs)
    if m <= 3:
        return v
    t = torch.arange(m, dtype=xs.dtype) - (m - 1)
    A = torch.stack([torch.ones_like(t), t, t * t], dim=1)
    fit = A @ torch.linalg.pinv(A)  # [m, m] the projection onto parabolas
    resid = xs - torch.einsum("st,tnd->snd", fit, xs)
    sigma = torch.sqrt((resid**2).sum(0) / (m - 3))  # [n, 3] per-axis scatter
    return torch.where(v.abs() > 2.0 * sigma * w.norm(), v, torch.zeros_like(v))


def _slope_weights(m: int, fps: float) -> torch.Tensor:
    """w [m] with Σ_t w_t x_t the derivative at the last sample of the least-squares parabola (a line for m = 2)
    through samples x_t at frames spaced 1/fps apart."""
    t = torch.arange(m, dtype=torch.float64) - (m - 1)  # frames before the last, last at 0
    A = torch.stack([torch.ones_like(t), t, t * t], dim=1)[:, : min(3, m)]
    coef = torch.linalg.pinv(A)  # [terms, m]
    return coef[1] * fps


def _rotation(F: torch.Tensor) -> torch.Tensor:
    """The rotation of the polar decomposition of F [n, 3, 3] (a reflection turned into the nearest rotation)."""
    U, _, Vh = torch.linalg.svd(F.double())
    flip = torch.linalg.det(U @ Vh) < 0
    U = torch.where(flip[:, None, None], U * torch.tensor([1.0, 1.0, -1.0], dtype=U.dtype), U)
    return (U @ Vh).to(F.dtype)


def _quantile(x: torch.Tensor, q: float) -> torch.Tensor:
    return torch.quantile(x, q, dim=0) if len(x) <= 5_000_000 else x.min(0).values if q < 0.5 else x.max(0).values


def _ground_level(z_static: torch.Tensor, z_low: float, size: float) -> float:
    """The most populated 1%-of-the-scene-size slab of static Gaussians at or below the bodies' low point."""
    level = floor_level(z_static, z_low, size, dominance=0.0)
    return z_low if level is None else level


FLOOR_DOMINANCE = 5.0  # a floor's slab holds this many times its share of an even spread, or more


def floor_level(z_static: torch.Tensor, z_low: float, size: float, dominance: float = FLOOR_DOMINANCE) -> float | None:
    """The height of the floor under the bodies: the median height of the most populated 1%-of-the-scene-size slab
    of static Gaussians at or below ``z_low`` (+ 2% of the scene), if that slab holds at least ``dominance`` times
    what an even spread of them over those heights would put in one slab (a floor is a plane full of Gaussians; a
    wall spreads its own evenly). None if there are fewer than 50 such Gaussians or no slab stands out."""
    z = z_static[z_static <= z_low + 0.02 * size]
    if len(z) < 50:
        return None
    width = 0.01 * size
    bins = torch.floor((z - z.min()) / width).long()
    counts = torch.bincount(bins)
    peak = int(counts.argmax())
    span = max(1.0, float(z_low + 0.02 * size - z.min()) / width)  # slabs over the heights searched
    if float(counts[peak]) < dominance * len(z) / span:
        return None
    return float(z[bins == peak].median())


def floor_patches(start: torch.Tensor, dynamic: torch.Tensor, size: float, reach: float) -> torch.Tensor:
    """[G] bool: the dynamic Gaussians that are the floor's own: groups of them (within ``reach`` of each other at
    t = 0, transitively) lying no higher than ``reach`` above the floor (:func:`floor_level`, under the dynamic
    Gaussians' median start), 95% of each group. A body standing on the floor is one group with its bottom
    layer, so it is kept; a patch of floor has nothing of a body above it.

    Why: where a body lands and stays (a sticky ground), the kinematic fit moved the floor's Gaussians under and
    around it, sinking them into the ground by a median of 7 mm before the impact and 20 mm after it (up to 9 cm),
    rather than letting the body cover them. They moved more than the static threshold, and the physical stage
    then simulated a slab of floor 7 cm thick as a second body."""
    found = torch.zeros_like(dynamic)
    if int(dynamic.sum()) == 0 or bool(dynamic.all()):
        return found
    z0 = start[:, 2].double()
    level = floor_level(z0[~dynamic], float(z0[dynamic].median()), size)
    if level is None:
        return found
    idx = torch.nonzero(dynamic).flatten()
    x = start[idx].double().numpy()
    label = linked_groups(x, reach)
    z = x[:, 2]
    for g in np.unique(label):
        mine = label == g
        if np.quantile(z[mine], 0.95) <= level + reach:
            found[idx[torch.from_numpy(mine)]] = True
    return found


STRAY_GROUP = 8  # a linked group of fewer dynamic Gaussians than this is too small to be a body


def stray_gaussians(start: torch.Tensor, dynamic: torch.Tensor, reach: float, smallest: int = STRAY_GROUP,
                    near: float = 2.0) -> torch.Tensor:  # fmt: skip
    """[G] bool: the dynamic Gaussians that belong to no body: groups of them (within a link of each other at t = 0,
    transitively) of fewer than ``smallest`` that start outside every larger group's bounds grown by ``near`` links.
    The link is ``reach``, or three times the dynamic Gaussians' median spacing where that is more (a sparse fit,
    whose bodies' own Gaussians lie that far apart). Nothing when no group is that large: the rule cannot tell
    bodies from strays there. A small group near a body is its fringe, and one within its bounds is inside it (3DGS
    puts a body's Gaussians on its surface, and a few in the hollow are far from all of them): both stay dynamic.

    Why: where a plastic block lands and stays, the kinematic fit moved single Gaussians of the floor as well as
    whole patches of it (:func:`floor_patches`). On the plastic landing of ``causalgs synth toss`` (seed 0), 72 of
    them were left once the patches were static, 0 to 86 mm above the floor in groups of 1 to 6, 5 cm or more
    below the block at t = 0. The physical stage filled them as a second body of 120 particles spread over
    35 × 21 cm of floor, which discovery then simulated and tracked as a body."""
    found = torch.zeros_like(dynamic)
    idx = torch.nonzero(dynamic).flatten()
    if len(idx) < smallest:
        return found
    from scipy.spatial import cKDTree

    x = start[idx].double().numpy()
    link = max(reach, 3.0 * float(np.median(cKDTree(x).query(x, k=2)[0][:, 1])))
    label = linked_groups(x, link)
    small = np.bincount(label)[label] < smallest
    if small.all() or not small.any():
        return found
    far = small.copy()
    for g in np.unique(label[~small]):
        body = x[label == g]
        far &= ~((x >= body.min(0) - near * link) & (x <= body.max(0) + near * link)).all(1)
    found[idx[torch.from_numpy(far)]] = True
    return found


def linked_groups(x: np.ndarray, reach: float) -> np.ndarray:
    """[N] int: the group of each point, points within ``reach`` of each other being in one group, transitively."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    pairs = cKDTree(x).query_pairs(reach, output_type="ndarray")
    n = len(x)
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    return connected_components(graph, directed=False)[1]


def scene_bounds(points: np.ndarray, margin: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    lo, hi = points.min(0), points.max(0)
    pad = margin * float((hi - lo).max())
    return lo - pad, hi + pad
