"""Built-in synthetic scenes with ground truth, written as D-NeRF / NVFi / FreeGave datasets.

Each scene is a builder ``build(views=, frames=, resolution=, seed=, fps=) -> SynthScene`` registered in :data:`SCENES`;
:func:`generate` validates the options, builds the scene and hands it to the one shared writer
(:mod:`causalgs.synth.writer`), so every scene has the same layout, split protocol and gt/ folder. Images come from
analytic ray casting (:mod:`causalgs.synth.raycast`) for rigid scenes, and from surface meshes carried by the
project's MPM at a reference resolution for deformable ones (:mod:`causalgs.synth.physics`, rendered by the z-buffer
rasterizer of :mod:`causalgs.synth.mesh`), and from meshes posed by MuJoCo, an independent rigid and soft body engine,
for the engine scenes (:mod:`causalgs.synth.engine_scenes`): never from the model's Gaussian rasterizer.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from pathlib import Path

from causalgs.errors import CausalGSError
from causalgs.synth import engine_scenes, physics, spin
from causalgs.synth.writer import SynthScene, check_out, protocol, write_dataset

__all__ = ["BENCHMARK", "ENGINE", "SCENES", "generate", "protocol"]

SCENES: dict[str, Callable[..., SynthScene]] = {
    "spin": spin.build,
    "jelly": physics.jelly,
    "fallingball": physics.fallingball,
    "collide": physics.collide,
    "room": physics.room,
    "toss": physics.toss,
    "bounce": engine_scenes.bounce,
    "tumble": engine_scenes.tumble,
    "knock": engine_scenes.knock,
    "soft": engine_scenes.soft,
}
# The benchmark of fit / predict / eval (``causalgs synth all``); ``toss`` is the scene of ``causalgs discover``.
BENCHMARK = ("spin", "jelly", "fallingball", "collide", "room", "bounce", "tumble", "knock", "soft")
# Scenes simulated by the MPM: they take an effects spec (any terms of the simulator's registry) and show progress.
SIMULATED = {"jelly", "fallingball", "collide", "room", "toss"}
# Scenes simulated by MuJoCo: their motion is the engine's, so they take neither an effects spec nor a reference grid.
ENGINE = set(engine_scenes.SETUPS)


# Frame rates of the scenes when --fps is not given: the spinning fan keeps turning at 24 fps; the MPM scenes are
# captured at 120 fps and the engine scenes at 30-60 fps, so that their future frames still hold motion (see
# causalgs.synth.physics.FPS and causalgs.synth.engine_scenes.FPS).
DEFAULT_FPS = {name: spin.FPS if name == "spin" else engine_scenes.FPS.get(name, physics.FPS) for name in SCENES}


def _check_options(name, views, frames, resolution, background, fps, reference_res=None) -> tuple[float, float, float]:
    if name not in SCENES:
        raise CausalGSError(f"unknown scene '{name}'; choose one of: {', '.join(sorted(SCENES))}")
    if fps is not None and (isinstance(fps, bool) or not isinstance(fps, (int, float)) or not math.isfinite(fps)
                            or not 1.0 <= fps <= 10000.0):  # fmt: skip
        raise CausalGSError(f"--fps = {fps!r} must be a number in [1, 10000]")
    if reference_res is not None and (isinstance(reference_res, bool) or not isinstance(reference_res, int)
                                      or not 8 <= reference_res <= 256):  # fmt: skip
        raise CausalGSError(f"--reference-res = {reference_res!r} must be an integer in [8, 256]")
    for what, value, low in (("views", views, 2), ("frames", frames, 2), ("resolution", resolution, 8)):
        if isinstance(value, bool) or not isinstance(value, int) or value < low:
            raise CausalGSError(f"--{what} = {value!r} must be an integer >= {low}")
    try:
        bg = tuple(float(v) for v in background)
    except (TypeError, ValueError):
        raise CausalGSError(f"--background {background!r} must be three numbers in [0, 1]") from None
    if len(bg) != 3 or not all(math.isfinite(v) and 0.0 <= v <= 1.0 for v in bg):
        raise CausalGSError(f"--background {background!r} must be three numbers in [0, 1]")
    return bg


def _motion_of(name: str) -> str:
    return "MuJoCo" if name in ENGINE else "analytic"


def generate(
    name: str,
    out,
    *,
    views: int = 20,
    frames: int = 89,
    resolution: int = 128,
    background=(1.0, 1.0, 1.0),
    seed: int = 0,
    overwrite: bool = False,
    progress: bool = True,
    effects: str | None = None,
    fps: float | None = None,
    reference_res: int | None = None,
) -> str:
    """Write the built-in scene ``name`` into ``out`` and return a short human summary.

    ``effects`` (simulated scenes only) replaces the scene's default effects spec, e.g.
    ``"gravity;ground:mu=0.4;linear_drag:c=0.3;walls"``. The result depends only on the arguments (same seed, same
    bytes). ``fps`` is the capture rate (None: the scene's default, :data:`DEFAULT_FPS`). ``reference_res``
    (simulated scenes only) is the truth's grid along the box's longest side (None: the fine default; a model's own
    spacing makes a scene whose contacts the model's grid can reproduce). Raises
    :class:`CausalGSError` with one line for bad options or when ``out`` already holds files and ``overwrite`` is
    false.
    """
    start = time.perf_counter()
    bg = _check_options(name, views, frames, resolution, background, fps, reference_res)
    fps = float(DEFAULT_FPS[name] if fps is None else fps)
    out = Path(out)
    check_out(out, overwrite)  # before minutes of simulation
    if name in SIMULATED:
        if effects is not None:
            from causalgs.sim.effects import parse_spec

            parse_spec(effects)  # one-line error for a bad spec before anything runs
        extra = {} if reference_res is None else {"reference_res": reference_res}
        scene = SCENES[name](views=views, frames=frames, resolution=resolution, seed=seed, effects=effects,
                             progress=progress, fps=fps, **extra)  # fmt: skip
    elif reference_res is not None:
        raise CausalGSError(f"scene '{name}' has {_motion_of(name)} motion and takes no --reference-res")
    elif effects is not None:
        raise CausalGSError(f"scene '{name}' has {_motion_of(name)} motion and takes no --effects (simulated: "
                            f"{', '.join(sorted(SIMULATED))})")  # fmt: skip
    else:
        scene = SCENES[name](views=views, frames=frames, resolution=resolution, seed=seed, fps=fps)
    options = {
        "seed": seed,
        "options": {
            "views": views,
            "frames": frames,
            "resolution": resolution,
            "background": list(bg),
            "seed": seed,
            "effects": effects,
            "fps": fps,
            "reference_res": reference_res,
        },
    }
    counts = write_dataset(out, scene, background=bg, overwrite=overwrite, progress=progress, options=options)
    elapsed = time.perf_counter() - start
    return (
        f"Wrote '{name}' to {out}: {views} views x {frames} frames at {resolution}x{resolution}, {fps:g} fps -> "
        f"train {counts['train']}, val {counts['val']}, test {counts['test']} images, gt masks and motion "
        f"({elapsed:.1f} s)"
    )
