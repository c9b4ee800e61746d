"""The fit configuration: one dataclass per stage, nested, with documented defaults; unknown keys are refused.

``FitConfig.preset("quick" | "full")`` gives the two presets; ``from_dict`` / ``to_dict`` round-trip through TOML
(the resolved config is saved as ``config.toml`` in every run folder and read back by ``--resume``, ``predict``,
``eval`` and ``render``).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, get_type_hints

import tomli_w
import tomllib

from causalgs.errors import CausalGSError
from causalgs.io import write_text
from causalgs.model.appearance import AppearanceConfig
from causalgs.model.canonical import CanonicalConfig
from causalgs.model.fields import FieldsConfig
from causalgs.model.particles import FILLS
from causalgs.model.refine import RefineConfig
from causalgs.model.residual import ResidualConfig
from causalgs.model.upright import FrameConfig
from causalgs.settings import check_keys

TRACK_RESTART = 4  # training images a frame's two starts are compared on (kinematic.track.restart)
TRACK_SHIFT = 4e-3  # m per step, the per-frame refinement's translation step in the fit (kinematic.track.lr_shift)


@dataclass
class KinematicConfig:
    """Training of the velocity field through renders of the RK2-integrated Gaussians."""

    iterations: int = 1500
    lr: float = 2e-3  # Adam, f_vel / f_neck / f_weight
    # The pattern centres: 0 puts each at its pattern's mass centre every iteration (a spin then turns a body in
    # place; learned centres had drifted half the scene from the ball they turn, and its spin stayed 8x too slow);
    # > 0 learns them at this Adam rate (metres per step).
    lr_centres: float = 0.0
    lr_frame_twists: float = 0.02  # the per-frame twists T (m/s and rad/s per step; causalgs.model.fields)
    # After each Adam step the per-frame twists shrink towards zero by this share of a step (the proximal step of an
    # L1 penalty): a twist that the images do not push the same way step after step stays at zero. Adam moves every
    # entry by about a step whatever its gradient's size, and without the shrink the floor's pattern drifted away.
    frame_twists_shrink: float = 0.5
    window_start: int = 2  # frames in the trained window at the start of the curriculum
    window_ramp: float = 0.6  # fraction of the iterations after which the window covers every training frame
    window_power: float = 2.0  # the window grows as (iteration / ramp)^power: slowly over the first frames
    views_per_iter: int = 2  # images rendered (and averaged in the loss) per iteration
    newest_frames: int = 3  # every other image is drawn from this many newest frames of the window (0: uniform)
    focus: float = 0.0  # the other images drawn ∝ (frame's recent loss)^focus: more where tracking is worst (0: off)
    blur: tuple[float, ...] = (0.02, 0.05, 0.12)  # σ of the blurred loss terms, as fractions of the image size
    # Weight of the mean twist size |u_k| + reach·|ω_k| over patterns and window frames (m/s): a body is at rest
    # unless the images say otherwise, so a body that has landed stops rather than drifting at the window's end.
    lambda_rest: float = 0.01
    rest_reach: float = 0.2  # with learned centres: a rotation costs its speed at this fraction of the scene size
    substeps: int = 1  # RK2 steps per frame interval
    lambda_dssim: float = 0.2
    static_threshold: float = 0.01  # a Gaussian that moves less than this fraction of the scene size is static
    # the Gaussians trained with the motion on every observed frame (causalgs.model.appearance)
    appearance: AppearanceConfig = field(default_factory=AppearanceConfig)
    # the deformation residual inside the observed window (causalgs.model.residual)
    residual: ResidualConfig = field(default_factory=ResidualConfig)
    # After the stage, each pattern's motion refined frame by frame against that frame's images, each frame from the
    # last one's correction (causalgs.model.refine): the tracked state that interpolation renders, the physical
    # stage is held to and the forecast starts from. The velocity field smooths an impact over several frames; a
    # frame's own correction does not (track.iterations = 0: off). A correction may move TRACK_SHIFT m per step: at
    # 1e-3 the tracks of a ball bouncing at 30 fps fell behind at every impact (bounce, val 29.5 dB against 32.9).
    track: RefineConfig = field(default_factory=lambda: RefineConfig(lr_shift=TRACK_SHIFT, restart=TRACK_RESTART))
    # Then the velocity field's twists (f_weight and the per-frame table) are fitted to those tracks in 3D, this many
    # Adam steps on the positions of a sample of the moving Gaussians (no rendering; 0: off): the initial velocity
    # and spin the simulator starts from, and the field's extrapolation, are the refined motion's, not the smoothed.
    distil: int = 300


@dataclass
class PhysicsConfig:
    """The physical path: differentiable MPM from the inferred causes, trained through renders and consistency."""

    enabled: bool = True
    iterations: int = 60
    res: int = 32  # grid cells along the side of the (cubic) simulation box
    # What the box covers: "moving": the bodies' tracked paths plus a margin (an axis whose paths come near the edge
    # of the static floor or room extends to that edge, so the box's walls stand at the room's); "scene": the whole
    # static footprint too. A small body on a large floor gets cells half the size with "moving" at the same cost
    # per cell (MPM contact and impacts change with the cell size).
    box: str = "moving"
    segment: int = 16  # substeps per checkpoint segment
    # How the bodies become particles (causalgs.model.particles): "surface" fills the solid the Gaussians enclose,
    # a boundary voxel with only its part inside the surface; "gaussians" makes the Gaussians particles themselves
    # (``budget`` of them; the rest follow their nearest particle) plus whole-voxel fill, which makes a body about a
    # quarter of a cell thicker on every side.
    fill: str = "surface"
    budget: int = 1500
    capacity: int = 8192  # particle rows of the simulator's store (fixed, so kernels compile once)
    # Most particles simulated (8 per cell, plus the Gaussian particles with fill "gaussians"): a large body on a
    # fine grid gets coarser cells (a larger box) rather than a thinner fill, so one iteration's cost stays bounded.
    max_particles: int = 4096
    effects: str = "gravity;ground;walls"  # the model's physics (a spec of causalgs.sim.effects)
    # Effect parameters trained (names as in Effects.param_names). The ground's offset is learned from its "auto"
    # start: the simulated contact of particles a few centimetres apart sits a fraction of a cell off the plane.
    learn: tuple[str, ...] = ("ground.mu", "ground.d")
    ground: str = "auto"  # "auto": the ground plane's offset from the static Gaussians; "spec": as in effects
    min_opacity: float = 0.3  # dynamic Gaussians fainter than this are carried, not simulated as matter
    cfl: float = 0.4
    max_substeps: int = 400  # per frame
    lr_mat: float = 5e-3  # f_mat
    lr_pattern_mat: float = 2e-2  # Θ, the per-pattern material offsets
    lr_vel: float = 1e-3  # f_vel / f_neck / f_weight through the initial velocity
    lr_effects: float = 2e-2
    window_start: int = 8
    window_ramp: float = 0.5
    preload: int = 12  # frames of settling that give bodies at rest their weight-bearing stress at a restart
    shooting: int = 12  # every other iteration: a segment of this many frames from the kinematic fit's state at a
    # random observed frame (multiple shooting: materials and effects from short, well-conditioned rollouts; 0: off)
    views_per_iter: int = 2
    lambda_image: float = 1.0
    lambda_consistency: float = 0.02  # on the mean Charbonnier distance to the kinematic positions, in grid cells
    # Stiffness calibration at the end of the stage (Trainer._calibrate): every particle's E is multiplied by each of
    # these factors in turn, the simulation replayed from t = 0, and the factor whose replay fits the training images
    # best is kept (empty: off). Gradients through a bounce or an impact are unreliable (on the fallingball benchmark
    # the trained E was 1.2x the truth and its replay bounced 8 cm short, while 0.35x of it fitted the images best and
    # replayed the bounce within 1.5 cm); a line search over one factor is not.
    calibrate: tuple[float, ...] = (0.25, 0.35, 0.5, 0.7, 1.0, 1.4, 2.0, 2.8, 4.0)
    calibrate_frames: int = 12  # observed frames scored (evenly spaced), every training view of each
    # The forecast's start (Trainer._assimilate): candidate start frames from `assimilate` frames before the end of
    # the window, then every `assimilate_scored` frames later (0: off, start at the last observed frame with the
    # tracked velocity), each from the tracked and from the replayed state; the one whose simulation forecasts the
    # newest `assimilate_scored` frames best is kept. One start frame is not enough: on the fallingball benchmark
    # the tracked velocity 12 frames before the end still averaged over the bounce (0.9 m/s up, truly 1.5), and the
    # tracked state 6 frames before the end forecast the 22 future frames at 30.7 dB PSNR against 19.8; on jelly
    # the tracked state 12 frames before the end won and forecast best (22.2 dB; a candidate 18 frames before the
    # end scored better on the newest frames and forecast at 21.6). Iterations > 0 also fit a
    # velocity correction to the frames after the start, kept only if it forecasts the newest third of them better
    # (Adam; rate in m/s, rad/s per step). Off by default: on the fallingball and jelly benchmarks it passed that
    # test and still forecast the future frames worse.
    assimilate: int = 12
    assimilate_scored: int = 6
    # The simulation from the chosen start gives the velocities at the last observed frame, the refined tracks the
    # positions and rotations there, and the forecast goes on from both (off: the simulation from the start goes on):
    # where the simulation had drifted from the tracks by the window's end, the forecast no longer carries the drift
    # (the same four fits of fallingball and bounce forecast 0.1–2.6 dB better anchored).
    anchor: bool = True
    assimilate_iterations: int = 0
    lr_assimilate: float = 0.02

    def __post_init__(self):
        if self.box not in ("moving", "scene"):
            raise CausalGSError(f"physics.box = {self.box!r} must be 'moving' or 'scene'")
        if self.fill not in FILLS:
            raise CausalGSError(f"physics.fill = {self.fill!r}: expected one of {', '.join(FILLS)}")
        if not all(a > 0 for a in self.calibrate):
            raise CausalGSError(f"physics.calibrate = {list(self.calibrate)}: every factor must be positive")
        if self.assimilate_scored < 1:
            raise CausalGSError(f"physics.assimilate_scored = {self.assimilate_scored} must be at least 1")


@dataclass
class FitConfig:
    """Everything ``causalgs fit`` does; saved as ``config.toml`` with the run."""

    preset: str = "quick"
    seed: int = 0
    precision: str = "float32"
    init_points: int = 6000  # random initial cloud when the dataset has no points3d.ply
    canonical: CanonicalConfig = field(default_factory=CanonicalConfig)
    fields: FieldsConfig = field(default_factory=FieldsConfig)
    kinematic: KinematicConfig = field(default_factory=KinematicConfig)
    frame: FrameConfig = field(default_factory=FrameConfig)  # up and gravity's magnitude (causalgs.model.upright)
    physics: PhysicsConfig = field(default_factory=PhysicsConfig)
    checkpoint_seconds: float = 60.0  # a checkpoint at least this often within a stage, and at every stage end

    @classmethod
    def preset_config(cls, name: str) -> FitConfig:
        """``quick``: a few minutes per scene on 2 CPU cores; ``full``: longer schedules for better numbers."""
        if name not in PRESETS:
            raise CausalGSError(f"unknown preset '{name}' (presets: {', '.join(PRESETS)})")
        return from_dict(cls, {"preset": name, **PRESETS[name]})

    def to_dict(self) -> dict:
        return to_dict(self)

    def save(self, path: str | Path) -> None:
        write_text(path, tomli_w.dumps(to_dict(self)))

    @classmethod
    def load(cls, path: str | Path) -> FitConfig:
        p = Path(path)
        try:
            d = tomllib.loads(p.read_text())
        except FileNotFoundError:
            raise CausalGSError(f"{p}: no such config file") from None
        except tomllib.TOMLDecodeError as e:
            raise CausalGSError(f"{p}: not valid TOML ({e})") from None
        return from_dict(cls, d, where=str(p))


PRESETS: dict[str, dict] = {
    "quick": {
        "canonical": {"iterations": 1500, "densify_from": 200, "densify_until": 1200, "densify_every": 100,
                      "opacity_reset_every": 0, "max_gaussians": 20_000, "sh_degree": 1,
                      "sh_degree_every": 500},
        "kinematic": {"iterations": 1200, "track": {"iterations": 20, "lr_shift": TRACK_SHIFT,
                                                          "restart": TRACK_RESTART}},
        "physics": {"iterations": 60},
    },
    "full": {
        "canonical": {"iterations": 5000, "densify_from": 300, "densify_until": 3500, "densify_every": 100,
                      "opacity_reset_every": 2000, "max_gaussians": 40_000, "sh_degree": 2, "sh_degree_every": 1000},
        "kinematic": {"iterations": 3000, "track": {"lr_shift": TRACK_SHIFT, "restart": TRACK_RESTART}},
        "physics": {"iterations": 160, "budget": 3000},
    },
}


def to_dict(obj) -> dict:
    out = {}
    for f in dataclasses.fields(obj):
        if not f.init:
            continue
        v = getattr(obj, f.name)
        if dataclasses.is_dataclass(v):
            v = to_dict(v)
        elif isinstance(v, tuple):
            v = list(v)
        if v is not None:
            out[f.name] = v
    return out


def from_dict(cls, d: dict, where: str = "config"):
    """Build dataclass ``cls`` from a nested dict, starting from its defaults; unknown keys are one-line errors."""
    if not isinstance(d, dict):
        raise CausalGSError(f"{where}: expected a table of settings, got {d!r}")
    hints = get_type_hints(cls)
    check_keys(cls, d, where)
    kwargs: dict[str, Any] = {}
    for k, v in d.items():
        t = hints[k]
        if dataclasses.is_dataclass(t):
            kwargs[k] = from_dict(t, v, f"{where}.{k}")
        elif isinstance(v, list):
            kwargs[k] = tuple(v)
        else:
            kwargs[k] = v
    try:
        obj = cls(**kwargs)
    except TypeError as e:
        raise CausalGSError(f"{where}: {e}") from None
    _check_types(obj, hints, where)
    return obj


def _check_types(obj, hints: dict, where: str) -> None:
    for f in dataclasses.fields(obj):
        v, t = getattr(obj, f.name), hints[f.name]
        if t is bool and not isinstance(v, bool):
            raise CausalGSError(f"{where}.{f.name} = {v!r} must be true or false")
        if t is int and (isinstance(v, bool) or not isinstance(v, int)):
            raise CausalGSError(f"{where}.{f.name} = {v!r} must be an integer")
        if t is float and (isinstance(v, bool) or not isinstance(v, (int, float))):
            raise CausalGSError(f"{where}.{f.name} = {v!r} must be a number")
        if t is str and not isinstance(v, str):
            raise CausalGSError(f"{where}.{f.name} = {v!r} must be a string")


def apply_override(d: dict, item: str) -> None:
    """Set ``KEY=VALUE`` (``causalgs fit --set``: a dotted key, a TOML value or a bare string) in the config
    dict ``d``; an unknown group or a missing '=' is a one-line error."""
    key, eq, value = item.partition("=")
    if not eq:
        raise CausalGSError(f"--set {item}: expected KEY=VALUE")
    try:
        parsed = tomllib.loads(f"v = {value}")["v"]
    except tomllib.TOMLDecodeError:
        parsed = value  # a bare string
    *path, last = key.strip().split(".")
    node = d
    for p in path:
        if not isinstance(node.get(p), dict):
            raise CausalGSError(f"--set {item}: no settings group '{p}'")
        node = node[p]
    node[last] = parsed
