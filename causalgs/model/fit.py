"""``causalgs fit``: learn a scene from multi-view video, in three stages, with checkpoints and resume.

1. **canonical**: 3DGS on the t = 0 training images (densification, pruning; :mod:`causalgs.model.canonical`);
2. **kinematic**: the inverse-physics fields learn the velocity field through renders of the RK2-integrated
   Gaussians, on a time window that widens from ``window_start`` frames to every observed frame (slowly at first;
   every other image from the window's newest frames; the loss includes blurred copies of both images, so a small
   fast body that no longer overlaps its image is still pulled towards it). At the end the fit is kept as the model's
   *tracked* copy of the fields, Gaussians that never move are frozen as static background (so are patches of the
   floor that the fit moved, :func:`~causalgs.model.scene.floor_patches`, when the physics has a ground, and a few
   Gaussians far from every body, :func:`~causalgs.model.scene.stray_gaussians`). Each motion pattern's motion is
   then refined frame by frame against that frame's images (``kinematic.track``), gravity's magnitude measured
   again from those tracks' free flight (:meth:`Trainer._regravitate`), the velocity field fitted to them
   (``kinematic.distil``), and the model as it stands is kept as ``kinematic.pt``, the kinematic-only model that
   evaluation compares against;
3. **physics**: the dynamic Gaussians become MPM particles; renders of the simulated state and the distance between
   simulated and tracked positions at frame times train f_mat (materials), the fields through the initial velocity,
   and the learned effect parameters, through the checkpointed Taichi backward. Even iterations roll out from t = 0
   over a widening window (the causes); odd ones are shooting segments of ``shooting`` frames from the tracked state
   at a random observed frame (materials and effects from short rollouts that start where the bodies were seen).
   The stage ends with the stiffness calibration (:meth:`Trainer._calibrate`): one factor on every particle's E,
   chosen by how well the replay from t = 0 fits the training images.

Run folder: ``config.toml`` (resolved), ``run.json`` (data path, stage times), ``log.jsonl`` (one line per
iteration), ``losses.png``, ``checkpoint.pt`` (rewritten atomically at least every ``checkpoint_seconds`` and
at every stage end), ``kinematic.pt``, ``gaussians.ply`` (canonical 3DGS PLY) and ``physics.npz``.
"""

from __future__ import annotations

import io
import json
import math
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from causalgs import _ti
from causalgs.dataset import Dataset, Frame, load_dataset
from causalgs.errors import CausalGSError
from causalgs.io import read_json, write_bytes, write_json
from causalgs.metrics import ssim
from causalgs.model.appearance import JointAppearance
from causalgs.model.canonical import train_canonical
from causalgs.model.config import FitConfig
from causalgs.model.gaussians import Gaussians
from causalgs.model.kinematic import blend, pattern_motion
from causalgs.model.refine import refine_tracks
from causalgs.model.scene import FORECAST_SOURCES, CausalGS, floor_patches, scene_bounds, stray_gaussians
from causalgs.model.timeline import Timeline
from causalgs.model.upright import GRAVITY, FrameConfig, Upright, flight_along, free_flight, infer_upright, normalising
from causalgs.sim.effects import REGISTRY, Effects
from causalgs.similarity import Similarity

GRAVITY_Z = "gravity.g[2]"  # gravity's vertical component in the physics frame
DISTIL_SAMPLE = 4096  # moving Gaussians whose positions the field is fitted to the refined tracks by
REST_SAMPLE = 2048  # material points whose speed the rest penalty of the unstructured field (VFD off) averages
UPRIGHT_GROUP = 20  # a motion pattern tracked by fewer solid Gaussians gives no centroid for free flight

STAGES = ("canonical", "kinematic", "physics", "assimilate", "done")
LENGTHS = ("d",)  # effect parameters measured in metres (their steps are scaled by LENGTH_STEP)
LENGTH_STEP = 0.05


def image_loss(pred: torch.Tensor, gt: torch.Tensor, lambda_dssim: float) -> torch.Tensor:
    """L1 + λ·(1 − SSIM), the 3DGS photometric loss."""
    return (1 - lambda_dssim) * (pred - gt).abs().mean() + lambda_dssim * (1 - ssim(pred, gt))


def blur(img: torch.Tensor, sigma: float) -> torch.Tensor:
    """An image [H, W, C] smoothed by a separable Gaussian of ``sigma`` pixels (edges replicated)."""
    r = max(1, math.ceil(3 * sigma))
    x = torch.arange(-r, r + 1, dtype=img.dtype)
    g = torch.exp(-0.5 * (x / sigma) ** 2)
    g = g / g.sum()
    c = img.shape[-1]
    t = torch.nn.functional.pad(img.permute(2, 0, 1)[None], (r, r, r, r), mode="replicate")
    t = torch.nn.functional.conv2d(t, g.view(1, 1, 1, -1).expand(c, 1, 1, -1), groups=c)
    t = torch.nn.functional.conv2d(t, g.view(1, 1, -1, 1).expand(c, 1, -1, 1), groups=c)
    return t[0].permute(1, 2, 0)


def tracking_loss(pred: torch.Tensor, gt: torch.Tensor, lambda_dssim: float, blurs=()) -> torch.Tensor:
    """The photometric loss plus L1 between blurred copies of both images (``blurs``: σ as fractions of the image
    size). A small fast body moves by about its own size between frames; once its render no longer overlaps its image
    the sharp loss has no gradient left to pull it back, while the blurred terms still do (coarse to fine)."""
    loss = image_loss(pred, gt, lambda_dssim)
    size = max(pred.shape[0], pred.shape[1])
    for s in blurs:
        loss = loss + (blur(pred, s * size) - blur(gt, s * size)).abs().mean()
    return loss


def _finite(loss: torch.Tensor, stage: str, it: int) -> None:
    if not bool(torch.isfinite(loss)):
        raise CausalGSError(f"{stage} stage: the loss became {float(loss)} at iteration {it}; lower the learning rate")


class Run:
    """A run folder: paths, the JSONL log and checkpoints."""

    def __init__(self, out: Path):
        self.out = Path(out)
        self.config_path = self.out / "config.toml"
        self.info_path = self.out / "run.json"
        self.log_path = self.out / "log.jsonl"
        self.checkpoint_path = self.out / "checkpoint.pt"

    def log(self, record: dict) -> None:
        with open(self.log_path, "a") as f:
            f.write(json.dumps(record) + "\n")

    def truncate_log(self, stage: str, it: int) -> None:
        """Drop log lines written after the checkpoint being resumed (they will be written again)."""
        if not self.log_path.exists():
            return
        order = STAGES.index(stage)
        keep = []
        for line in self.log_path.read_text().splitlines():
            r = json.loads(line)
            s = STAGES.index(r["stage"])
            if s < order or (s == order and r["it"] <= it):
                keep.append(line)
        write_bytes(self.log_path, ("\n".join(keep) + "\n" if keep else "").encode())

    def save(self, payload: dict, path: Path | None = None) -> None:
        buf = io.BytesIO()
        torch.save(payload, buf)
        write_bytes(path or self.checkpoint_path, buf.getvalue())

    def load(self, path: Path | None = None) -> dict:
        p = path or self.checkpoint_path
        try:
            return torch.load(p, weights_only=False)
        except FileNotFoundError:
            raise CausalGSError(f"{p}: no checkpoint to resume from") from None
        except Exception as e:  # a truncated or foreign file
            raise CausalGSError(f"{p}: not a readable causalgs checkpoint ({type(e).__name__})") from None


def initial_gaussians(data: Dataset, config: FitConfig) -> Gaussians:
    deg = config.canonical.sh_degree
    if data.points is not None and len(data.points) > 0:
        return Gaussians.from_points(data.points, data.point_colors, sh_degree=deg)
    centres = np.stack([f.camera.center for f in data.train])
    lo, hi = centres.min(0), centres.max(0)
    mid, half = (lo + hi) / 2, 0.35 * float((hi - lo).max())
    return Gaussians.random(config.init_points, mid - half, mid + half, seed=config.seed, sh_degree=deg)


class Optimizers:
    """Several optimisers saved and restored as one (a stage's checkpoint holds one optimiser state); ``None``
    members are skipped."""

    def __init__(self, **members):
        self.members = {k: v for k, v in members.items() if v is not None}

    def state_dict(self) -> dict:
        return {k: v.state_dict() for k, v in self.members.items()}

    def load_state_dict(self, state: dict) -> None:
        if set(state) != set(self.members):
            raise CausalGSError(f"the checkpoint's optimiser state holds {sorted(state)}, this stage trains "
                                f"{sorted(self.members)}: resume with the run's own config")  # fmt: skip
        for k, v in self.members.items():
            v.load_state_dict(state[k])


class Trainer:
    """Runs the stages of a fit; every stage can be resumed from the checkpoint it last wrote."""

    def __init__(self, data: Dataset, run: Run, config: FitConfig, progress: Callable | None = None):
        self.data, self.run, self.config = data, run, config
        self.source = data  # the dataset in its own frame; ``data`` is re-posed into the model's (_adopt_frame)
        self.upright: Upright | None = None  # the inferred physics frame (_upright)
        self.upright_json: dict | None = None  # ... as a resumed checkpoint recorded it
        self.timeline = Timeline.of(data)
        self.train = self.timeline.by_frame(data.train)
        self.bg = tuple(float(b) for b in data.background)
        self.progress = progress or (lambda *a, **k: None)
        self.rng = np.random.default_rng(config.seed)
        self.model: CausalGS | None = None
        self.stage_seconds: dict[str, float] = {}
        self.forecast_choice: dict | None = None  # the assimilation stage's scores of the forecast's starts
        self.calibration: dict | None = None  # the stiffness calibration's scores and factor
        self.frame_loss: dict[int, float] = {}  # a running mean of each frame's tracking loss (kinematic.focus)
        self._last_save = time.monotonic()

    # -- shared -----------------------------------------------------------------------------------------------------
    def _gt(self, frame: Frame) -> torch.Tensor:
        return torch.from_numpy(frame.image).to(_ti.torch_dtype())

    def _sample(self, window: int, count: int, lowest: int = 0, newest: int = 0,
                focus: float = 0.0) -> list[tuple[int, Frame]]:  # fmt: skip
        """``count`` training images of frames in [lowest, window); with ``newest`` > 0 every other one is drawn from
        the newest ``newest`` frames of the window (where the curriculum has just extended it). With ``focus`` > 0
        the others are drawn with a probability ∝ (the frame's recent loss)^focus (:attr:`frame_loss`; a frame not
        yet seen counts as the worst): the fit spends its images where it tracks worst."""
        keys = [k for k in self.train if lowest <= k < window]
        front = [k for k in keys if k >= window - newest] if newest > 0 else []
        weights = None
        if focus > 0 and self.frame_loss:
            worst = max(self.frame_loss.values())
            w = np.array([self.frame_loss.get(k, worst) for k in keys]) ** focus
            weights = w / w.sum()
        out = []
        for i in range(count):
            pool = front if front and i % 2 == 0 else keys
            if pool is keys and weights is not None:
                k = keys[int(self.rng.choice(len(keys), p=weights))]
            else:
                k = pool[int(self.rng.integers(len(pool)))]
            frames = self.train[k]
            out.append((k, frames[int(self.rng.integers(len(frames)))]))
        return out

    def _window(self, it: int, iterations: int, start: int, ramp: float, power: float = 1.0) -> int:
        n = self.timeline.train_frames
        frac = min(1.0, it / max(1.0, ramp * iterations)) ** power
        return int(min(n, max(2, round(start + frac * (n - start)))))

    def _payload(self, stage: str, it: int, optimizer=None) -> dict:
        return {
            "stage": stage,
            "it": it,
            "model": self.model.state_dict() if self.model is not None else None,
            "gaussians": self.gaussians.state_dict() if stage == "canonical" else None,
            "optimizer": optimizer.state_dict() if optimizer is not None else None,
            "rng": self.rng.bit_generator.state,
            "torch_rng": torch.get_rng_state(),
            "stage_seconds": self.stage_seconds,
            "forecast_choice": self.forecast_choice,
            "calibration": self.calibration,
            "upright": self.frame_json(),
        }

    def _maybe_save(self, stage: str, it: int, optimizer, force: bool = False) -> None:
        if force or time.monotonic() - self._last_save > self.config.checkpoint_seconds:
            self.run.save(self._payload(stage, it, optimizer))
            self._last_save = time.monotonic()

    def _new_model(self) -> CausalGS:
        means = self.gaussians.means.detach().double().numpy()
        lo, hi = scene_bounds(means)
        for p in self.gaussians.parameters():
            p.requires_grad_(False)
        return CausalGS(self.config, self.gaussians, lo, hi, self.timeline.fps, self.timeline.train_frames)

    def frame_json(self) -> dict | None:
        """The inferred physics frame as run.json records it (None when not inferred): up and gravity's magnitude in
        the data's frame and units, with their evidence, and ``similarity``, the model's map from the data's frame."""
        if self.upright is None:
            out = self.upright_json
        else:
            out = {**self.upright.to_json(), "similarity": self.model.similarity().to_json()}
        m = self.model
        if self._learns_gravity(out) and m is not None and m.particles is not None:
            names = m.simulator().effects.param_names()
            if GRAVITY_Z in names:  # the physical stage's factor on the measured magnitude
                factor = -float(m.effect_params[names.index(GRAVITY_Z)].detach()) / GRAVITY
                out = {**out, "gravity_learned": out["gravity"] * factor}
        return out

    def _learns_gravity(self, frame: dict | None) -> bool:
        """Whether the physical stage refines gravity's magnitude: when the fit measured it from free flight
        (``frame.learn_gravity``; not when it was given, nor when nothing flew)."""
        fc = self.config.frame
        return bool(fc.infer and fc.learn_gravity and fc.gravity == 0 and frame and frame.get("flight") is not None)

    # -- entry ------------------------------------------------------------------------------------------------------
    def fit(self, resume: dict | None = None) -> CausalGS:
        start_stage, start_it, opt_state = "canonical", 0, None
        if resume is not None:
            start_stage, start_it, opt_state = resume["stage"], resume["it"], resume["optimizer"]
            self.rng.bit_generator.state = resume["rng"]
            torch.set_rng_state(resume["torch_rng"])
            self.stage_seconds = dict(resume.get("stage_seconds", {}))
            self.forecast_choice = resume.get("forecast_choice")
            self.calibration = resume.get("calibration")
            self.upright_json = resume.get("upright")
            self.run.truncate_log(start_stage, start_it)
        order = STAGES.index(start_stage)
        if order == 0:
            self.gaussians = initial_gaussians(self.data, self.config)
            self._canonical()
            start_it, opt_state = 0, None
        else:
            self.gaussians = Gaussians.from_points(np.zeros((1, 3)), sh_degree=self.config.canonical.sh_degree)
            self.model = self._new_model()
            _restore(self.model, resume["model"], self.run.checkpoint_path)
            self.gaussians = self.model.gaussians
            self._adopt_frame()
        if self.model is None:
            self.model = self._new_model()
        if order <= 1:
            self._kinematic(start_it if order == 1 else 0, opt_state if order == 1 else None)
            start_it, opt_state = 0, None
        if order <= 2 and self.config.physics.enabled:
            self._physics(start_it if order == 2 else 0, opt_state if order == 2 else None)
            start_it, opt_state = 0, None
        if order <= 3 and self.config.physics.enabled and self.config.physics.assimilate > 0:
            self._assimilate(start_it if order == 3 else 0, opt_state if order == 3 else None)
        self.run.save(self._payload("done", 0))
        return self.model

    # -- stages -----------------------------------------------------------------------------------------------------
    def _canonical(self) -> None:
        t0 = time.monotonic()
        frames = self.train.get(0)
        if not frames:
            raise CausalGSError(f"{self.data.root}: no training image at the first frame time (t = 0)")
        cfg = self.config.canonical

        def log(rec: dict) -> None:
            self.run.log({"stage": "canonical", "it": rec.get("step", 0), **rec})

        def progress(step, total, losses):
            self.progress("canonical", step, total, losses)

        self.gaussians = train_canonical(self.gaussians, frames, cfg, progress=progress, log=log)
        self.stage_seconds["canonical"] = time.monotonic() - t0
        self.model = self._new_model()
        self._normalise()
        self.run.save(self._payload("kinematic", 0))

    def _kinematic(self, start: int, opt_state) -> None:
        t0 = time.monotonic() - self.stage_seconds.get("kinematic", 0.0)
        m, kc = self.model, self.config.kinematic
        f = m.fields
        nets = f.motion_parameters()
        opt = torch.optim.Adam([{"params": nets, "lr": kc.lr}, {"params": [f.centres], "lr": kc.lr_centres},
                                {"params": [f.frame_twists], "lr": kc.lr_frame_twists}])  # fmt: skip
        reach = kc.rest_reach * float((m.hi - m.lo).max())  # a rotation rate times this is a speed
        joint = None
        if kc.appearance.enabled:
            joint = JointAppearance(m, self.config.canonical, kc.appearance, self.train[0], kc.iterations)
        rc = kc.residual
        residual_opt = torch.optim.Adam(m.residual.parameters(), lr=rc.lr) if m.residual is not None else None
        residual_from = int(rc.start * kc.iterations)
        optimizers = Optimizers(fields=opt, gaussians=joint, residual=residual_opt)
        if opt_state is not None:
            optimizers.load_state_dict(opt_state)
        for it in range(start, kc.iterations):
            window = self._window(it, kc.iterations, kc.window_start, kc.window_ramp, kc.window_power)
            picks = self._sample(window, kc.views_per_iter, newest=kc.newest_frames, focus=kc.focus)
            z = m.codes()  # once per iteration: the centres, the motion and the residual all read them
            lever = reach
            if kc.lr_centres == 0:  # the patterns turn about their mass centres as the mixtures stand now; a spin
                # costs the speed it gives the pattern's points (its radius of gyration): a floor turning in place
                # is dear, a small ball's spin is cheap
                gyration = f.place_centres(m.gaussians.means.detach()[m.dynamic], f.mixture(z.detach()))
                lever = gyration.clamp_min(0.01 * float((m.hi - m.lo).max()))
            states = m.observed([k for k, _ in picks], residual=it >= residual_from, codes=z)
            loss, metas = 0.0, []
            for state, (_, frame) in zip(states, picks, strict=True):
                img, _, meta = m.gaussians.render(frame.camera, self.bg, **state.overrides())
                metas.append((meta, frame.camera))
                term = tracking_loss(img, self._gt(frame), kc.lambda_dssim, kc.blur)
                k = self.timeline.index(frame)
                value = float(term.detach())
                self.frame_loss[k] = 0.7 * self.frame_loss.get(k, value) + 0.3 * value
                loss = loss + term / len(picks)
                if state.offset is not None and rc.lambda_size > 0:  # the smallest residual that explains the images
                    loss = loss + rc.lambda_size * (state.offset / m.residual.bound()).square().mean() / len(picks)
            if kc.lambda_rest > 0:  # bodies at rest unless the images say otherwise: L1 on the patterns' twists
                times = torch.arange(window, dtype=torch.float64).to(f.centres.dtype) / self.timeline.fps
                if f.structured:
                    W = f.twists(times)
                    rest = (W[..., :3].norm(dim=-1) + lever * W[..., 3:].norm(dim=-1)).mean()
                else:  # the unstructured field: the mean speed of a sample of the material points
                    x0 = m.gaussians.means.detach()[m.dynamic]
                    x0 = x0[torch.as_tensor(self.rng.permutation(len(x0))[:REST_SAMPLE])]
                    rest = f.flow_velocity(x0, times).norm(dim=-1).mean()
                loss = loss + kc.lambda_rest * rest
            _finite(loss, "kinematic", it)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            with torch.no_grad():  # the proximal L1 step on the per-frame twists (kinematic.frame_twists_shrink)
                T = f.frame_twists
                T.copy_(T.sign() * (T.abs() - kc.frame_twists_shrink * kc.lr_frame_twists).clamp_min(0.0))
            if residual_opt is not None:
                residual_opt.step()
                residual_opt.zero_grad(set_to_none=True)
            rec = {"stage": "kinematic", "it": it + 1, "loss": float(loss.detach()), "window": window}
            if joint is not None:
                for meta, camera in metas:
                    joint.observe(meta, camera)
                rec.update(joint.step(it + 1))
            self.run.log(rec)
            self.stage_seconds["kinematic"] = time.monotonic() - t0
            self._maybe_save("kinematic", it + 1, optimizers, force=it + 1 == kc.iterations)
            self.progress("kinematic", it + 1, kc.iterations, rec)
        if joint is not None:
            joint.finish()
        m.keep_track()
        self._split_static()
        partial = self.run.out / "track-partial.npz"
        self._track(partial)
        self._regravitate()
        self._distil()
        self.stage_seconds["kinematic"] = time.monotonic() - t0
        self.run.save(self._payload("physics", 0))
        self.run.save(self._payload("physics", 0), self.run.out / "kinematic.pt")
        partial.unlink(missing_ok=True)

    def _distil(self) -> None:
        """Fit the velocity field's twists to the refined tracks in 3D (``kinematic.distil`` steps) and keep it as the
        tracked copy: the positions of a sample of the moving Gaussians by the patterns' motion against the tracks'."""
        m, kc = self.model, self.config.kinematic
        if kc.distil == 0 or len(m.track_A) == 0:
            return
        f, n = m.fields, len(m.track_A)
        x0 = m.gaussians.means.detach()[m.dynamic]
        x0 = x0[torch.as_tensor(self.rng.permutation(len(x0))[:DISTIL_SAMPLE])]
        size = float((m.hi - m.lo).max())
        with torch.no_grad():
            h = f.mixture(f.code(x0))
            target = m.tracked_positions(x0, range(n))
        opt = torch.optim.Adam([{"params": list(f.f_weight.parameters()), "lr": kc.lr},
                                {"params": [f.frame_twists], "lr": kc.lr_frame_twists}])  # fmt: skip

        def error() -> torch.Tensor:  # RMS distance to the tracks over the window, in scene sizes
            R, t, q = pattern_motion(f, n - 1, 1.0 / self.timeline.fps, kc.substeps)
            xs = torch.stack([blend(h, x0, None, R[k], t[k], q[k])[0] for k in range(n)])
            return ((xs - target) ** 2).sum(-1).mean().sqrt() / size

        with torch.no_grad():
            before = float(error())
        for _ in range(kc.distil):
            loss = error()
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
        m.keep_track()
        with torch.no_grad():
            after = float(error())
        self.run.log({"stage": "kinematic", "it": kc.iterations, "distil": {"rms_before": before, "rms_after": after,
                      "scene_size": size}})  # fmt: skip

    def _track(self, partial: Path) -> None:
        """The per-frame refinement of the tracked motion (``kinematic.track``; :mod:`causalgs.model.refine`), kept in
        the model; an interrupted one goes on from ``partial``. Its scores of the motion before and after, on
        held-out cameras, are logged, never used to choose."""
        m, cfg = self.model, self.config.kinematic.track
        if cfg.iterations == 0 or not m.kinematic_fields.structured or not bool(m.dynamic.any()):
            return
        t0 = time.monotonic()

        def progress(done, total):
            self.progress("track", done, total, {})

        tracks = refine_tracks(m, self.data, self.timeline, cfg, progress=progress, checkpoint=partial)
        m.set_tracks(torch.from_numpy(tracks.A), torch.from_numpy(tracks.b))
        self.run.log({"stage": "kinematic", "it": self.config.kinematic.iterations, "track": {
            "frames": len(tracks.A), "scored_on": tracks.scored_on, "seconds": time.monotonic() - t0,
            "psnr_before": [round(float(v), 3) for v in tracks.psnr_before],
            "psnr_after": [round(float(v), 3) for v in tracks.psnr_after]}})  # fmt: skip

    def _split_static(self) -> None:
        """Static and dynamic Gaussians; in between, the physics frame is inferred and the model re-posed into it
        (:meth:`_upright`), since the floor's patches are found along its up."""
        m = self.model
        with torch.no_grad():
            m.dynamic.fill_(True)
            traj, _ = m.kinematic(self.timeline.train_frames - 1, rotations=False)
            disp = (traj - traj[:1]).norm(dim=-1).max(0).values
            size = float((m.hi - m.lo).max())
            dynamic = disp > self.config.kinematic.static_threshold * size
        sim = self._upright(traj, dynamic, size)
        with torch.no_grad():
            traj = torch.as_tensor(sim.points(traj.double().numpy()), dtype=traj.dtype)
            size = float((m.hi - m.lo).max())
            reach = self.config.kinematic.static_threshold * size
            floor = torch.zeros_like(dynamic)
            if "ground" in Effects.from_spec(self.config.physics.effects).names():
                floor = floor_patches(traj[0], dynamic, size, reach)  # the floor under a body that stays on it
            stray = stray_gaussians(traj[0], dynamic & ~floor, reach)  # a few Gaussians far from every body
            m.dynamic.copy_(dynamic & ~floor & ~stray)
        self.run.log({"stage": "kinematic", "it": self.config.kinematic.iterations, "dynamic": int(m.dynamic.sum()),
                      "static": int((~m.dynamic).sum()), "floor": int(floor.sum()),
                      "stray": int(stray.sum())})  # fmt: skip

    def _normalise(self) -> None:
        """Re-pose the new model into the normalising frame (:func:`~causalgs.model.upright.normalising`) for the
        kinematic stage; nothing when ``frame.infer`` is off."""
        if not self.config.frame.infer:
            return
        g = self.model.gaussians
        with torch.no_grad():
            points = g.means.detach()[torch.sigmoid(g.opacities.detach()) >= 0.5].double().numpy()
        cams = np.stack([f.camera.center for f in self.data.train])
        sim = normalising(points if len(points) >= 50 else g.means.detach().double().numpy(), cams, self.config.seed)
        self.model.reframe(sim)
        self._adopt_frame()
        self.run.log({"stage": "canonical", "it": self.config.canonical.iterations, "normalised": sim.to_json()})

    def _upright(self, traj: torch.Tensor, dynamic: torch.Tensor, size: float) -> Similarity:
        """Infer the physics frame (:func:`~causalgs.model.upright.infer_upright`) from the static Gaussians, the
        tracked centroids of the dynamic ones' motion patterns and the cameras, and re-pose the model and the
        cameras into it; the identity when ``frame.infer`` is off."""
        fc = self.config.frame
        if not fc.infer:
            return Similarity.identity()
        m, g = self.model, self.model.gaussians
        with torch.no_grad():
            alpha = torch.sigmoid(g.opacities.detach())
            static = g.means.detach()[~dynamic & (alpha >= 0.5)].double().numpy()
        tracks = self._centroids(traj[:, dynamic], dynamic)
        cams = np.stack([f.camera.center for f in self.data.train])
        before = m.similarity()  # the data's frame to the normalising one
        # what the config gives is in the data's frame and units; the evidence is in the normalising frame
        given = FrameConfig(True, tuple(before.directions(fc.up)) if fc.up else (), fc.gravity * before.scale)
        found = infer_upright(static, tracks, self.timeline.fps, cams, size, given, self.config.seed)
        if found.gravity is None:  # not measured: the data's units taken as metres
            found.gravity = GRAVITY * before.scale
        sim = found.similarity()
        m.reframe(sim)
        self._adopt_frame()
        self.upright = found.mapped(before.inverse())  # up and gravity in the data's own frame and units
        self.run.log({"stage": "kinematic", "it": self.config.kinematic.iterations, "frame": self.frame_json()})
        return sim

    def _centroids(self, moving: torch.Tensor, dynamic: torch.Tensor) -> np.ndarray:
        """Tracked centroids [F, G, 3] of the motion patterns from positions ``moving`` [F, n, 3] of the ``dynamic``
        Gaussians (a mask of all of them): the solid ones grouped by their strongest pattern (groups of at least
        :data:`UPRIGHT_GROUP`)."""
        m, g = self.model, self.model.gaussians
        with torch.no_grad():
            solid = torch.sigmoid(g.opacities.detach()[dynamic]) >= self.config.physics.min_opacity
            label = m.mixtures(g.means.detach()[dynamic][solid]).argmax(1)
            moving = moving[:, solid].double()
            groups = [k for k in torch.unique(label).tolist() if int((label == k).sum()) >= UPRIGHT_GROUP]
            return np.stack([moving[:, label == k].mean(1).numpy() for k in groups], 1) if groups else np.zeros(0)

    def _regravitate(self) -> None:
        """Gravity's magnitude measured again, from the refined tracks' free flight, and the model re-scaled so that
        it is :data:`GRAVITY` in the model's units. The velocity field's smooth motion rounds every contact off and
        its flights' acceleration with it (a bouncing ball's read 0.60 of the truth from the field, 1.004 from its
        tracks); the tracks follow each frame's images. Skipped when gravity was given or the tracks show no flight."""
        fc, m = self.config.frame, self.model
        if not fc.infer or fc.gravity > 0 or self.upright is None or len(m.track_A) == 0:
            return
        with torch.no_grad():
            moving = m.tracked_positions(m.gaussians.means.detach()[m.dynamic], range(len(m.track_A)))
        centroids = self._centroids(moving, m.dynamic)
        if not centroids.size:
            return
        size = float((m.hi - m.lo).max())
        flight = free_flight(centroids, self.timeline.fps, size, np.array([0.0, 0.0, 1.0]))
        if flight is None and self.upright.flight is not None:  # over the flights the velocity field showed
            flight = flight_along(centroids, self.upright.flight.segments, self.timeline.fps)
        if flight is None or -flight.g[2] <= 0:
            return
        before = self.upright.gravity
        to_data = m.similarity().inverse()
        self.upright = replace(self.upright, gravity=before * float(-flight.g[2]) / GRAVITY,
                               flight=flight.mapped(to_data),
                               notes=[*self.upright.notes, f"gravity from the refined tracks (the velocity field's "
                                      f"flight gave {before:.4g})"])  # fmt: skip
        m.reframe(Similarity.make(np.eye(3), GRAVITY / float(-flight.g[2]), what="gravity from the refined tracks"))
        self._adopt_frame()
        self.run.log({"stage": "kinematic", "it": self.config.kinematic.iterations, "frame": self.frame_json()})

    def _adopt_frame(self) -> None:
        """The cameras re-posed into the model's frame (the dataset as loaded is in the data's own)."""
        self.data = self.source.reframed(self.model.similarity())
        self.train = self.timeline.by_frame(self.data.train)

    def _physics(self, start: int, opt_state) -> None:
        t0 = time.monotonic() - self.stage_seconds.get("physics", 0.0)
        m, pc = self.model, self.config.physics
        if m.particles is None:
            m.build_physics(seed=self.config.seed)
            names = m.simulator().effects.param_names()
            effects = dict(zip(names, m.effect_params.tolist(), strict=True))
            self.run.log({"stage": "physics", "it": 0, "particles": len(m.particles), "box": m.box.tolist(),
                          "effects": effects})  # fmt: skip
        f = m.fields
        mask = m.learn_mask()
        names = m.simulator().effects.param_names()
        if self._learns_gravity(self.frame_json()) and GRAVITY_Z in names:
            mask[names.index(GRAVITY_Z)] = True
        # Per-parameter step sizes: plane offsets (metres) move at a twentieth of the rate of dimensionless parameters
        # such as friction coefficients, so one Adam step shifts a ground plane by about a millimetre.
        step_scale = torch.tensor([LENGTH_STEP if n.split("[")[0].split(".")[1] in LENGTHS else 1.0 for n in names],
                                  dtype=torch.float64)  # fmt: skip
        nets = f.motion_parameters()
        opt = torch.optim.Adam([
            {"params": list(f.f_mat.parameters()), "lr": pc.lr_mat},
            {"params": [f.pattern_materials], "lr": pc.lr_pattern_mat},
            {"params": nets, "lr": pc.lr_vel},
            {"params": [m.effect_params], "lr": pc.lr_effects},
        ])  # fmt: skip
        if opt_state is not None:
            opt.load_state_dict(opt_state)
        dx = m.cell
        n = self.timeline.train_frames
        for it in range(start, pc.iterations):
            window = self._window(it, pc.iterations, pc.window_start, pc.window_ramp)
            begin = 0
            if pc.shooting > 0 and it % 2 == 1 and n > 2:  # a segment from the tracked state at a random frame
                begin = int(self.rng.integers(1, n - 1))
                window = min(n, begin + pc.shooting + 1)
            frames = list(range(begin + 1, window))
            out = m.simulate(frames, start=begin)
            with torch.no_grad():
                x0 = out["x0"].detach()
                target = m.tracked_positions(x0, frames)
            # Charbonnier distance in grid cells: a robust pull towards the kinematic fit, which may have lost track
            # of a body late in the window (a squared loss would let those frames dominate).
            d2 = ((out["x"] - target.to(out["x"].dtype)) ** 2).sum(-1) / dx**2
            cons = (torch.sqrt(d2 + 1.0) - 1.0).mean()
            picks = self._sample(window, pc.views_per_iter, lowest=begin + 1)
            img_loss = 0.0
            for k, frame in picks:
                i = k - begin - 1
                (state,) = m.physical_states(out["x"][i : i + 1], out["F"][i : i + 1])
                img, _, _ = m.render(state, frame.camera, self.bg)
                img_loss = img_loss + image_loss(img, self._gt(frame), self.config.kinematic.lambda_dssim) / len(picks)
            loss = pc.lambda_image * img_loss + pc.lambda_consistency * cons
            _finite(loss, "physics", it)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            if m.effect_params.grad is not None:
                m.effect_params.grad[~mask] = 0.0
            before = m.effect_params.detach().clone()
            opt.step()
            with torch.no_grad():  # scaled steps; the friction coefficient and the like kept inside their bounds
                stepped = before + step_scale * (m.effect_params.detach() - before)
                m.effect_params.copy_(torch.as_tensor(_clamped(m, stepped.numpy())))
            rec = {"stage": "physics", "it": it + 1, "loss": float(loss.detach()), "image": float(img_loss.detach()),
                   "consistency": float(cons.detach()), "start": begin, "window": window,
                   "E_median": float(out["E"].detach().median()),
                   "nu_median": float(out["nu"].detach().median()),
                   **{n: float(v) for n, v, k in zip(m.simulator().effects.param_names(), m.effect_params.tolist(),
                                                     mask.tolist(), strict=True) if k}}  # fmt: skip
            self.run.log(rec)
            self.stage_seconds["physics"] = time.monotonic() - t0
            self._maybe_save("physics", it + 1, opt, force=it + 1 == pc.iterations)
            self.progress("physics", it + 1, pc.iterations, rec)
        if pc.calibrate:
            self._calibrate()
        self.stage_seconds["physics"] = time.monotonic() - t0

    def _calibrate(self) -> None:
        """The stiffness calibration: one factor on every particle's E, chosen among ``physics.calibrate`` by the
        image loss (L1 + D-SSIM) of the replay from t = 0 on every training view of ``calibrate_frames`` observed
        frames. The factor 1 (the trained materials) is always among the candidates, so the replay never fits the
        images worse than before. Scores go to the log and to ``run.json`` (``stiffness_calibration``)."""
        m, pc = self.model, self.config.physics
        n = self.timeline.train_frames
        keys = [k for k in sorted(self.train) if k >= 1]
        frames = sorted({keys[round(i * (len(keys) - 1) / max(1, pc.calibrate_frames - 1))]
                         for i in range(min(pc.calibrate_frames, len(keys)))})  # fmt: skip
        if not frames or n < 2:
            return
        base = float(m.log_stiffness)
        scores = {}
        for factor in sorted({1.0, *(float(a) for a in pc.calibrate)}):
            with torch.no_grad():
                m.log_stiffness.fill_(base + math.log(factor))
                scores[factor] = self._simulated_score(m.simulate(frames), frames)
        best = min(scores, key=scores.get)
        with torch.no_grad():
            m.log_stiffness.fill_(base + math.log(best))
        self.calibration = {"frames": frames, "scores": {f"{a:g}": v for a, v in scores.items()}, "factor": best}
        self.run.log({"stage": "physics", "it": pc.iterations, "calibration": self.calibration})

    def _assimilate(self, start: int, opt_state) -> None:
        """Where the forecast starts (data assimilation): a state at one of several frames near the end of the
        observed window, chosen by how well the simulation from it forecasts the window's newest frames.

        The candidate starts are the frames ``physics.assimilate``, then every ``physics.assimilate_scored`` fewer,
        down to ``assimilate_scored`` frames before the window's end, each with two states: the kinematic fit's
        (smooth in time, so its velocity, the slope of the tracked positions over the frames up to the start, is
        wrong for a few frames after a bounce or an impact) and the replay from t = 0's (the contacts where the
        simulator put them, but any drift of the replay included). Every candidate is scored on the same newest
        ``assimilate_scored`` frames, which none of them starts after: the image loss on every training view of the
        simulation from it. A later start has less time to drift and an earlier one may avoid a state corrupted by a
        contact; the scores decide, as the future's forecast is the same simulation continued.

        With ``physics.assimilate_iterations`` > 0 the chosen start also gets a rigid velocity correction per motion
        pattern, fitted to all but the newest third of the frames after it (:func:`_held_out`) and kept only if it
        forecasts the held-out frames better than the uncorrected start (a correction scored on the frames it was
        fitted to wins by fitting them, whether or not it carries on into the future)."""
        t0 = time.monotonic() - self.stage_seconds.get("assimilate", 0.0)
        m, pc = self.model, self.config.physics
        n = self.timeline.train_frames
        iters = pc.assimilate_iterations
        if start == 0:
            with torch.no_grad():
                m.forecast_twists.zero_()
                m.assimilated.zero_()
        begins, scored = _forecast_starts(n, pc.assimilate, pc.assimilate_scored)
        if not begins:  # too short a window, or off: the forecast starts at the last observed frame
            m.forecast_start.fill_(-1)
            self.stage_seconds["assimilate"] = time.monotonic() - t0
            return
        scores: dict[str, dict[str, float]] = {s: {} for s in FORECAST_SOURCES}
        with torch.no_grad():  # constants, each computed once (a replayed one is a whole replay)
            starts = {(s, b): m.restart_state(b, source=s) for b in begins for s in FORECAST_SOURCES}
        for (source, b), restart in starts.items():
            scores[source][str(b)] = self._forecast_score(b, restart, None, list(range(b + 1, n)), scored)
        source, begin = min(starts, key=lambda sb: scores[sb[0]][str(sb[1])])
        m.forecast_start.fill_(begin)
        m.forecast_source.fill_(FORECAST_SOURCES.index(source))
        choice = {"frame": begin, "source": source, "scored": scored, "scores": scores, "correction": None}
        window = list(range(begin + 1, n))
        held = _held_out(begin, n)
        if iters > 0 and held > 0:
            row = FORECAST_SOURCES.index(source)
            fit_frames, test_frames = window[:-held], window[-held:]
            opt = torch.optim.Adam([m.forecast_twists], lr=pc.lr_assimilate)
            if opt_state is not None:
                opt.load_state_dict(opt_state)
            restart = starts[(source, begin)]  # the same start every iteration
            for it in range(start, iters):
                out = m.simulate(fit_frames, start=begin, twists=m.forecast_twists, restart=restart)
                picks = self._sample(fit_frames[-1] + 1, pc.views_per_iter, lowest=begin + 1)
                img_loss = 0.0
                for k, frame in picks:
                    i = k - begin - 1
                    (state,) = m.physical_states(out["x"][i : i + 1], out["F"][i : i + 1])
                    img, _, _ = m.render(state, frame.camera, self.bg)
                    img_loss = img_loss + image_loss(img, self._gt(frame), self.config.kinematic.lambda_dssim) / len(
                        picks
                    )
                _finite(img_loss, "assimilate", it)
                opt.zero_grad(set_to_none=True)
                img_loss.backward()
                opt.step()
                tw = m.forecast_twists.detach()
                with torch.no_grad():
                    m.assimilated[row].copy_(tw)
                rec = {"stage": "assimilate", "it": it + 1, "loss": float(img_loss.detach()), "start": begin,
                       "source": source, "linear": float(tw[:, :3].norm(dim=1).max()),
                       "angular": float(tw[:, 3:].norm(dim=1).max())}  # fmt: skip
                self.run.log(rec)
                self.stage_seconds["assimilate"] = time.monotonic() - t0
                self._maybe_save("assimilate", it + 1, opt, force=it + 1 == iters)
                self.progress("assimilate", it + 1, iters, rec)
            plain = self._forecast_score(begin, restart, None, test_frames)
            corrected = self._forecast_score(begin, restart, m.assimilated[row], test_frames)
            keep = corrected < plain
            with torch.no_grad():
                m.forecast_twists.copy_(m.assimilated[row] if keep else torch.zeros_like(m.assimilated[row]))
            choice["correction"] = {"fitted_to": fit_frames, "held_out": test_frames, "uncorrected": plain,
                                    "corrected": corrected, "kept": bool(keep)}  # fmt: skip
        self.forecast_choice = choice
        self.stage_seconds["assimilate"] = time.monotonic() - t0

    def _forecast_score(self, begin: int, restart: dict, twists, frames: list[int],
                        scored: list[int] | None = None) -> float:  # fmt: skip
        """The mean image loss (L1 + D-SSIM) over every training view of ``scored`` (default: all of ``frames``)
        of the simulation from frame ``begin`` through ``frames`` from the state ``restart``
        (:meth:`CausalGS.restart_state`) with the velocity correction ``twists`` (None: uncorrected); no gradient."""
        scored = frames if scored is None else scored
        with torch.no_grad():
            out = self.model.simulate(frames, start=begin, twists=twists, restart=restart)
            rows = [frames.index(k) for k in scored]
            return self._simulated_score({"x": out["x"][rows], "F": out["F"][rows]}, scored)

    def _simulated_score(self, out: dict, frames: list[int]) -> float:
        """The mean image loss (L1 + D-SSIM) over every training view of ``frames`` of simulated particle states
        ``out`` (x, F at those frames, as :meth:`CausalGS.simulate` returns them); call without gradients."""
        m = self.model
        states = m.physical_states(out["x"], out["F"])
        losses = [image_loss(m.render(st, f.camera, self.bg)[0], self._gt(f), self.config.kinematic.lambda_dssim)
                  for st, k in zip(states, frames, strict=True) for f in self.train[k]]  # fmt: skip
        return float(torch.stack(losses).mean())


def _forecast_starts(n: int, earliest: int, every: int) -> tuple[list[int], list[int]]:
    """The assimilation's candidate start frames (``earliest`` frames before the last of ``n`` observed frames,
    then every ``every`` frames later, the latest ``every`` before the end; all ≥ 1, as a restart is after t = 0)
    and the newest frames that score them all. None when ``earliest`` ≤ 0 (off) or the window is too short."""
    last = n - 1
    every = min(every, last - 1)
    if earliest <= 0 or every < 1:
        return [], []
    begins = sorted({max(1, last - a) for a in range(max(earliest, every), every - 1, -every)})
    return begins, list(range(last - every + 1, n))


def _held_out(begin: int, n: int) -> int:
    """The newest frames of the window (a third of those after ``begin``, at least one) that the forecast-start
    correction is not fitted to and that decide whether it is kept; it keeps at least one frame of its own."""
    after = n - 1 - begin
    return max(1, min(after - 1, round(after / 3))) if after >= 2 else 0


def _clamped(m: CausalGS, values: np.ndarray) -> np.ndarray:
    """Effect parameters raised to their registry lower bounds (a friction coefficient never goes negative)."""
    out = values.copy()
    for i, name in enumerate(m.simulator().effects.param_names()):
        effect, param = name.split("[")[0].split(".")
        lower = REGISTRY[effect].param(param).lower
        if lower is not None:
            out[i] = max(out[i], lower)
    return out


def fit(data_dir, out, config: FitConfig | None = None, *, resume: bool = False, progress=None) -> CausalGS:
    """Fit a scene (see the module docstring). With ``resume`` the run folder's config and checkpoint are used (a
    ``config`` given with ``resume`` replaces the saved one: the CLI allows only its frame settings to change)."""
    out = Path(out)
    run = Run(out)
    state = None
    if resume:
        if config is not None:  # frame settings changed on resume (they act where the kinematic stage ends)
            config.save(run.config_path)
        config = FitConfig.load(run.config_path)
        info = read_json(run.info_path, "run info")
        data_dir = info["data"]
        state = run.load()
    elif config is None:
        config = FitConfig.preset_config("quick")
    data = load_dataset(data_dir)
    out.mkdir(parents=True, exist_ok=True)
    if not resume:
        if run.checkpoint_path.exists():
            raise CausalGSError(f"{out} already holds a run: use --resume to continue it or choose another --out")
        run.log_path.unlink(missing_ok=True)
        config.save(run.config_path)
    torch.manual_seed(config.seed)
    trainer = Trainer(data, run, config, progress)
    write_json(run.info_path, {"data": str(Path(data_dir).resolve()), "status": "running",
                               "fps": trainer.timeline.fps, "train_frames": trainer.timeline.train_frames})  # fmt: skip
    if state is not None and state["stage"] == "done":
        model = _load_model(trainer, state, run.checkpoint_path)
        trainer.forecast_choice = state.get("forecast_choice")
        trainer.calibration = state.get("calibration")
    else:
        model = trainer.fit(state)
    from causalgs.model.export import export_run
    from causalgs.model.plots import plot_losses

    export_run(model, out)
    plot_losses(run.log_path, out / "losses.png")
    write_json(run.info_path, {"data": str(Path(data_dir).resolve()), "status": "done",
                               "fps": trainer.timeline.fps, "train_frames": trainer.timeline.train_frames,
                               "stage_seconds": trainer.stage_seconds,
                               "total_seconds": sum(trainer.stage_seconds.values()),
                               "forecast_start": trainer.forecast_choice,
                               "stiffness_calibration": trainer.calibration,
                               "frame": trainer.frame_json()})  # fmt: skip
    return model


def _restore(model: CausalGS, weights: dict, path: Path) -> None:
    """Load a checkpoint's model weights; a checkpoint of another model (another version, another config's sizes)
    is a one-line error naming the file and what differs."""
    try:
        model.load_state_dict(weights)
    except RuntimeError as e:
        lines = [ln.strip() for ln in str(e).splitlines()[1:] if ln.strip()]
        what = lines[0] if lines else "its weights do not fit"
        raise CausalGSError(f"{path}: a checkpoint of another model than this config and version make ({what})") \
            from None


def _load_model(trainer: Trainer, state: dict, path: Path) -> CausalGS:
    trainer.gaussians = Gaussians.from_points(np.zeros((1, 3)), sh_degree=trainer.config.canonical.sh_degree)
    trainer.model = trainer._new_model()
    _restore(trainer.model, state["model"], path)
    trainer._adopt_frame()
    trainer.stage_seconds = dict(state.get("stage_seconds", {}))
    trainer.upright_json = state.get("upright")
    return trainer.model


def run_frame(run_dir) -> Similarity:
    """A finished run's map from its data's world frame to the model's (run.json ``frame``; identity without one)."""
    frame = read_json(Path(run_dir) / "run.json", "run info").get("frame")
    return Similarity.identity() if not frame else Similarity.from_json(frame["similarity"], f"{run_dir}/run.json")


def load_model(run_dir, which: str = "checkpoint.pt") -> tuple[CausalGS, Dataset, Timeline]:
    """The trained model of a run folder (``which``: checkpoint.pt or kinematic.pt), its dataset (the cameras in the
    model's frame) and timeline."""
    run = Run(Path(run_dir))
    config = FitConfig.load(run.config_path)
    info = read_json(run.info_path, "run info")
    data = load_dataset(info["data"])
    state = run.load(run.out / which)
    if state.get("model") is None:
        raise CausalGSError(f"{run.out / which}: the fit has not reached the dynamic stages yet")
    trainer = Trainer(data, run, config)
    model = _load_model(trainer, state, run.out / which)
    model.eval()
    return model, trainer.data, trainer.timeline
