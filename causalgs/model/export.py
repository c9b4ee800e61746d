"""Exports of a trained model: the canonical Gaussians as a standard 3DGS PLY and the per-Gaussian physics as NPZ.

Both are in the data's own world frame (where its cameras and ground truth are), not in the physics frame the model
was re-posed into (:mod:`causalgs.model.upright`); ``frame`` [4, 4] is the similarity from the one to the other, in
which the learned effect parameters (a ground plane's offset, gravity) are given.

``physics.npz`` keys (N Gaussians, P simulated particles):

- ``means`` [N, 3], ``dynamic`` [N] bool, ``code`` [N, C] physics code z, ``mixture`` [N, K] h,
  ``velocity`` [N, 3] initial velocity v(p, 0), ``E`` [N] Pa, ``nu`` [N], ``density`` [N] kg/m³;
- with a physical stage: ``particles_x0`` [P, 3], ``particles_vol`` [P], ``particles_v0`` [P, 3], ``particles_E``,
  ``particles_nu``, ``particles_density`` [P], ``particles_gaussian`` [P] (the Gaussian a particle is, with
  ``physics.fill = "gaussians"``; else −1), ``effect_names`` and ``effect_params`` (the learned effect parameters).
"""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import torch

from causalgs.io import write_npz
from causalgs.model.scene import CausalGS


def physics_arrays(model: CausalGS) -> dict[str, np.ndarray]:
    """The arrays of ``physics.npz`` (see the module docstring), positions and velocities in the data's frame."""
    back = model.similarity().inverse()
    out = _model_arrays(model)
    for key in ("means", "particles_x0"):
        if key in out:
            out[key] = back.points(out[key]).astype(out[key].dtype)
    for key in ("velocity", "particles_v0"):
        if key in out:
            out[key] = back.vectors(out[key]).astype(out[key].dtype)
    out["frame"] = model.frame.numpy()
    return out


def _model_arrays(model: CausalGS) -> dict[str, np.ndarray]:
    f = model.fields
    with torch.no_grad():
        x = model.gaussians.means.detach().to(f.centres.dtype)
        z = f.code(x)
        h = f.mixture(z)
        out = {
            "means": x.numpy(),
            "dynamic": model.dynamic.numpy(),
            "code": z.numpy(),
            "mixture": h.numpy(),
            "velocity": f.velocity(x, 0.0, h).numpy(),
            **{k: v.numpy() for k, v in model.materials(x).items()},
        }
        if model.particles is not None:
            c = model.causes()
            p = model.particles
            out.update({
                "particles_x0": p.x0.numpy(), "particles_vol": p.vol.numpy(), "particles_gaussian": p.gaussian.numpy(),
                "particles_v0": c["v0"].numpy(), "particles_E": c["E"].numpy(), "particles_nu": c["nu"].numpy(),
                "particles_density": c["density"].numpy(),
                "effect_names": np.array(model.simulator().effects.param_names()),
                "effect_params": model.effect_params.detach().numpy(),
            })  # fmt: skip
    return out


def export_run(model: CausalGS, out) -> None:
    out = Path(out)
    back = model.similarity().inverse()
    gaussians = model.gaussians
    if not back.is_identity:
        gaussians = copy.deepcopy(gaussians)
        gaussians.reframe(back)
    gaussians.to_ply(out / "gaussians.ply")
    write_npz(out / "physics.npz", **physics_arrays(model))
