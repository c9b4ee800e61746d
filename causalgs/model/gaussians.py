"""The canonical (t = 0) 3D Gaussians as a torch module.

Parameters are stored raw, exactly as the rasterizer takes them (and as gsplat and the reference 3DGS store them):
``means`` [N, 3], ``quats`` [N, 4] (w, x, y, z, unnormalised), ``scales`` [N, 3] log-scales, ``opacities`` [N]
logits and ``sh`` [N, S, 3] colour coefficients with S = (d + 1)² (``sh[:, 0]`` is the DC term). They are activated
where they are used. The dtype is the Taichi runtime's (:func:`causalgs._ti.torch_dtype`), so Taichi must be
initialised (through :func:`causalgs._ti.init`) before Gaussians are made.

The number of Gaussians changes during training (densification clones, splits and prunes rows). Only the training
code does that, through :meth:`Gaussians.set_params`, because it must keep the optimizer state aligned with the rows.
"""

from __future__ import annotations

import math
import os

import numpy as np
import torch
from torch import nn

from causalgs import _ti
from causalgs.errors import CausalGSError
from causalgs.ply import read_gaussians_ply, write_gaussians_ply
from causalgs.render import rasterize

__all__ = ["PARAMS", "SH_C0", "Gaussians", "quat_to_rotmat", "rgb_to_sh"]

PARAMS = ("means", "quats", "scales", "opacities", "sh")
SH_C0 = 0.28209479177387814  # the degree-0 SH basis value: colour = SH_C0 * sh_dc + 0.5
_TRAILING = {"means": (3,), "quats": (4,), "scales": (3,), "opacities": ()}
_OVERRIDES = frozenset({*PARAMS, "covs", "sh_degree"})
_KNN_CHUNK = 4096  # rows per torch.cdist block when scipy is missing: bounds memory at 4096 x N distances


def rgb_to_sh(rgb: torch.Tensor) -> torch.Tensor:
    """The SH DC coefficient that renders as colour ``rgb`` (the rasterizer adds 0.5 to the SH colour)."""
    return (rgb - 0.5) / SH_C0


def quat_to_rotmat(quats: torch.Tensor) -> torch.Tensor:
    """Rotation matrices [N, 3, 3] of unnormalised quaternions [N, 4] (w, x, y, z)."""
    w, x, y, z = torch.nn.functional.normalize(quats, dim=-1).unbind(-1)
    rows = (
        (1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)),
        (2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)),
        (2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)),
    )
    return torch.stack([torch.stack(r, dim=-1) for r in rows], dim=-2)


def _knn_mean_sq_dist(xyz: np.ndarray, k: int = 3) -> np.ndarray:
    """Mean squared distance of every point to its ``k`` nearest other points (what 3DGS's ``distCUDA2`` computes for
    the initial scales). scipy's KD-tree when scipy is installed, else a chunked brute force in torch."""
    try:
        from scipy.spatial import cKDTree
    except ImportError:
        cKDTree = None
    if cKDTree is not None:
        dist, _ = cKDTree(xyz).query(xyz, k=k + 1)  # the first neighbour is the point itself
        return (dist[:, 1:] ** 2).mean(axis=1)
    pts = torch.as_tensor(xyz, dtype=torch.float64)
    out = []
    for start in range(0, len(pts), _KNN_CHUNK):
        d2 = torch.cdist(pts[start : start + _KNN_CHUNK], pts).pow(2)
        out.append(d2.topk(k + 1, dim=1, largest=False).values[:, 1:].mean(dim=1))
    return torch.cat(out).numpy()


class Gaussians(nn.Module):
    """N 3D Gaussians with raw parameters (see the module docstring) and :attr:`active_sh_degree`, the SH degree
    rendered by default (training raises it step by step, as 3DGS does; it is saved in the state dict)."""

    def __init__(self, means, quats, scales, opacities, sh):
        super().__init__()
        dt = _ti.torch_dtype()
        values = {"means": means, "quats": quats, "scales": scales, "opacities": opacities, "sh": sh}
        tensors = {k: torch.as_tensor(v).detach().to(dtype=dt, device="cpu").clone() for k, v in values.items()}
        _check_shapes(tensors)
        for name in PARAMS:
            setattr(self, name, nn.Parameter(tensors[name]))
        self.active_sh_degree = self.sh_degree

    # -- construction ---------------------------------------------------------------------------------------------
    @classmethod
    def from_points(cls, xyz, rgb=None, *, sh_degree: int = 3, opacity: float = 0.1) -> Gaussians:
        """Gaussians centred on points ``xyz`` [N, 3], initialised as in 3DGS: isotropic, scale = root of the mean
        squared distance to the 3 nearest neighbours (at least 1e-7 squared, so duplicate points stay finite),
        identity rotation, opacity 0.1 and colour ``rgb`` [N, 3] in [0, 1] (grey without) as the SH DC term."""
        pts = np.asarray(xyz, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) == 0:
            raise CausalGSError(f"initial points must be a non-empty [N, 3] array, got shape {list(pts.shape)}")
        if not np.all(np.isfinite(pts)):
            raise CausalGSError("initial points have non-finite coordinates")
        if not 0 <= sh_degree <= 3:
            raise CausalGSError(f"sh_degree = {sh_degree} must be in 0..3")
        n = len(pts)
        # A lone point has no neighbours: give it a 1 cm scale rather than a degenerate one.
        dist2 = np.maximum(_knn_mean_sq_dist(pts, min(3, n - 1)), 1e-7) if n > 1 else np.full(1, 1e-4)
        colour = torch.full((n, 3), 0.5, dtype=torch.float64) if rgb is None else torch.as_tensor(rgb).double()
        if colour.shape != (n, 3):
            raise CausalGSError(f"initial colours must be [{n}, 3] like the points, got shape {list(colour.shape)}")
        sh = torch.zeros((n, (sh_degree + 1) ** 2, 3), dtype=torch.float64)
        sh[:, 0] = rgb_to_sh(colour.clamp(0.0, 1.0))
        return cls(
            means=torch.as_tensor(pts),
            quats=torch.tensor([1.0, 0.0, 0.0, 0.0]).repeat(n, 1),
            scales=torch.as_tensor(0.5 * np.log(dist2))[:, None].repeat(1, 3),
            opacities=torch.full((n,), math.log(opacity / (1.0 - opacity))),
            sh=sh,
        )

    @classmethod
    def random(cls, n: int, lo, hi, seed: int = 0, *, sh_degree: int = 3, opacity: float = 0.1) -> Gaussians:
        """``n`` Gaussians at uniform random points of the box [lo, hi] with random colours (the 3DGS initialisation
        for scenes without a point cloud), otherwise as :meth:`from_points`."""
        lo, hi = np.broadcast_to(np.asarray(lo, np.float64), 3), np.broadcast_to(np.asarray(hi, np.float64), 3)
        if n < 1 or not np.all(hi > lo):
            raise CausalGSError(f"random Gaussians need n >= 1 and lo < hi, got n = {n}, lo = {lo}, hi = {hi}")
        rng = np.random.default_rng(seed)
        xyz = lo + (hi - lo) * rng.random((n, 3))
        return cls.from_points(xyz, rng.random((n, 3)), sh_degree=sh_degree, opacity=opacity)

    # -- properties -----------------------------------------------------------------------------------------------
    @property
    def n(self) -> int:
        return self.means.shape[0]

    @property
    def sh_degree(self) -> int:
        """The largest SH degree the coefficients hold."""
        return math.isqrt(self.sh.shape[1]) - 1

    def params(self) -> dict[str, nn.Parameter]:
        """The raw parameters by name, in :data:`PARAMS` order."""
        return {name: getattr(self, name) for name in PARAMS}

    def set_params(self, tensors: dict[str, torch.Tensor]) -> dict[str, nn.Parameter]:
        """Replace all parameters with new tensors of one new N (new ``nn.Parameter`` objects: an optimizer that held
        the old ones must be re-pointed, which the training code does). Returns the new parameters."""
        if set(tensors) != set(PARAMS):
            raise CausalGSError(f"set_params needs exactly {', '.join(PARAMS)}")
        dt = _ti.torch_dtype()
        tensors = {k: v.detach().to(dt) for k, v in tensors.items()}
        _check_shapes(tensors)
        for name in PARAMS:
            setattr(self, name, nn.Parameter(tensors[name].contiguous()))
        self.active_sh_degree = min(self.active_sh_degree, self.sh_degree)
        return self.params()

    # -- rendering ------------------------------------------------------------------------------------------------
    def reframe(self, sim) -> None:
        """Re-pose the Gaussians in place by the similarity ``sim`` (:class:`causalgs.similarity.Similarity`): means
        moved, orientations turned, log-scales shifted by log s, view-dependent colour turned with the world; a camera
        re-posed by the same ``sim`` renders the same image."""
        from causalgs.model.kinematic import quat_mul
        from causalgs.render.sh import rotate_sh

        R = torch.tensor(sim.R, dtype=self.means.dtype)
        q = torch.tensor(sim.quaternion(), dtype=self.quats.dtype)
        with torch.no_grad():
            self.means.copy_(sim.scale * self.means @ R.T + torch.tensor(sim.t, dtype=self.means.dtype))
            self.quats.copy_(quat_mul(q.expand_as(self.quats), self.quats))
            self.scales.add_(math.log(sim.scale))
            self.sh.copy_(rotate_sh(self.sh, sim.R, self.sh_degree))

    def render(self, camera, background=(0.0, 0.0, 0.0), **override):
        """Render from ``camera`` (a :class:`causalgs.cameras.Camera`); returns ``(image [H, W, 3], alpha [H, W],
        meta)`` as :func:`causalgs.render.rasterize` does.

        ``override`` replaces what is rendered without touching the parameters: ``means``, ``quats``, ``scales``,
        ``opacities``, ``sh`` (tensors shaped like the parameters), ``covs`` [N, 3, 3] (world covariances used instead
        of quats and scales) and ``sh_degree`` (default :attr:`active_sh_degree`). The dynamic model renders its
        deformed Gaussians this way, so gradients reach both the overrides and the untouched parameters.
        """
        unknown = sorted(set(override) - _OVERRIDES)
        if unknown:
            known = ", ".join(sorted(_OVERRIDES))
            raise CausalGSError(f"render: unknown override(s) {', '.join(unknown)} (known: {known})")
        p = {**self.params(), **{k: override[k] for k in PARAMS if k in override}}
        return rasterize(
            p["means"], p["quats"], p["scales"], p["opacities"], p["sh"], camera.viewmat, camera.K,
            camera.width, camera.height, background=background,
            sh_degree=override.get("sh_degree", self.active_sh_degree), covs=override.get("covs"),
        )  # fmt: skip

    # -- files ----------------------------------------------------------------------------------------------------
    def to_ply(self, path: str | os.PathLike) -> None:
        """Write the Gaussians as a standard 3DGS PLY (raw values; readable by the common splat viewers)."""
        p = self.params()
        write_gaussians_ply(path, p["means"], p["quats"], p["scales"], p["opacities"], p["sh"])

    @classmethod
    def from_ply(cls, path: str | os.PathLike) -> Gaussians:
        """Read Gaussians from a 3DGS PLY (the SH degree follows the file; the active degree is the full one)."""
        return cls(**read_gaussians_ply(path))

    # -- state dict: the count may differ from the module's --------------------------------------------------------
    def get_extra_state(self) -> dict:
        return {"active_sh_degree": int(self.active_sh_degree)}

    def set_extra_state(self, state: dict) -> None:
        self.active_sh_degree = min(int(state.get("active_sh_degree", self.sh_degree)), self.sh_degree)

    def _load_from_state_dict(self, state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys,
                              error_msgs):  # fmt: skip
        """Resize the parameters to the checkpoint's count before the normal load: densification changes N, so a
        saved model rarely has the count of a freshly built one. This also works when the Gaussians are a submodule.
        Replaces the ``nn.Parameter`` objects when N differs (re-create optimizers after loading)."""
        incoming = {k: state_dict[prefix + k] for k in PARAMS if prefix + k in state_dict}
        counts = {v.shape[0] if v.dim() else -1 for v in incoming.values()}
        if len(counts) > 1:
            raise CausalGSError(f"checkpoint Gaussians '{prefix}' have parameters of different counts {sorted(counts)}")
        for name, value in incoming.items():
            mine = getattr(self, name)
            if value.shape[1:] != mine.shape[1:]:
                raise CausalGSError(
                    f"checkpoint Gaussians '{prefix}{name}' have shape {list(value.shape)}, expected "
                    f"[N, {', '.join(str(s) for s in mine.shape[1:])}]"
                )
            if value.shape[0] != mine.shape[0]:
                setattr(self, name, nn.Parameter(torch.empty(value.shape, dtype=mine.dtype)))
        super()._load_from_state_dict(
            state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys, error_msgs
        )

    def extra_repr(self) -> str:
        return f"n={self.n}, sh_degree={self.sh_degree}, active_sh_degree={self.active_sh_degree}"


def _check_shapes(t: dict[str, torch.Tensor]) -> None:
    """One-line errors for parameters that are not [N, ...] of one N with the rasterizer's trailing shapes."""
    n = t["means"].shape[0] if t["means"].dim() == 2 else -1
    for name, trailing in _TRAILING.items():
        if tuple(t[name].shape) != (n, *trailing):
            raise CausalGSError(f"Gaussians: {name} has shape {list(t[name].shape)}, expected {[n, *trailing]}")
    s = t["sh"]
    if s.dim() != 3 or s.shape[0] != n or s.shape[2] != 3 or s.shape[1] not in (1, 4, 9, 16):
        raise CausalGSError(f"Gaussians: sh has shape {list(s.shape)}, expected [{n}, S, 3] with S in 1, 4, 9, 16")
