"""The rasterizer over a ParticleStore, and its single torch boundary.

- :class:`Rasterizer` renders the Gaussians held in a :class:`~causalgs.store.ParticleStore` (the physical path
  renders the simulator's particles in place) and back-propagates an image gradient into the store's adjoint fields.
- :func:`rasterize` is the torch API: tensors in, ``(image, alpha, meta)`` out, differentiable with respect to every
  Gaussian parameter through one ``torch.autograd.Function``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from causalgs import _ti
from causalgs._ti import ti
from causalgs.errors import CausalGSError
from causalgs.render import composite, project
from causalgs.store import ParticleStore

# Fields of the store that the projection reads, and the tensor argument of `rasterize` each comes from.
INPUTS = ("x", "quat", "scale_raw", "opacity_raw", "sh", "cov3d")


@dataclass(frozen=True)
class View:
    """A camera as the kernels take it: world-to-camera ``viewmat`` [4, 4] (OpenCV frame), ``K`` [3, 3], size."""

    viewmat: np.ndarray
    K: np.ndarray
    width: int
    height: int

    @classmethod
    def of(cls, viewmat, K, width: int, height: int) -> View:
        vm = torch.as_tensor(viewmat).detach().cpu().double().numpy().reshape(4, 4)
        k = torch.as_tensor(K).detach().cpu().double().numpy().reshape(3, 3)
        if not (np.isfinite(vm).all() and np.isfinite(k).all()):
            raise CausalGSError("camera viewmat or K has non-finite values")
        if width < 1 or height < 1:
            raise CausalGSError(f"image size {width}x{height} must be positive")
        return cls(vm, k, int(width), int(height))

    @property
    def kernel_args(self) -> dict:
        campos = np.linalg.inv(self.viewmat)[:3, 3]
        k = self.K
        return {
            "viewmat": ti.math.mat4(self.viewmat.tolist()),
            "intr": ti.math.vec4(k[0, 0], k[1, 1], k[0, 2], k[1, 2]),
            "campos": ti.math.vec3(*campos.tolist()),
            "width": self.width,
            "height": self.height,
        }


@dataclass
class RenderPass:
    """What a forward pass keeps for its backward: the tile lists, packed entries and per-pixel state."""

    view: View
    background: tuple[float, float, float]
    sh_degree: int
    use_cov: bool
    n: int
    gids: torch.Tensor
    ranges: torch.Tensor
    packed: torch.Tensor
    pbox: torch.Tensor
    T_final: torch.Tensor
    last: torch.Tensor
    upload: int


class Rasterizer:
    """Renders the first ``store.n`` Gaussians of ``store``; adds the projected per-particle fields it needs."""

    def __init__(self, store: ParticleStore, tile: int = composite.TILE):
        store.add_fields(project.RENDER_SPECS)
        self.store = store
        self.tile = tile
        self.upload = 0  # incremented by whoever rewrites the store's Gaussian parameters
        self.last_pass: RenderPass | None = None

    def _fields(self, names):
        return [self.store.field(nm) for nm in names]

    def _project_args(self, view: View, sh_degree: int, use_cov: bool) -> tuple:
        s = self.store
        f = self._fields(("x", "scale_raw", "quat", "opacity_raw", "sh", "cov3d"))
        out = self._fields(("mean2d", "conic", "depth", "color", "opac"))
        a = view.kernel_args
        return (*f, *out, a["viewmat"], a["intr"], a["campos"], a["width"], a["height"], s.n, sh_degree, use_cov)

    def forward(self, view: View, background=(0.0, 0.0, 0.0), sh_degree: int | None = None, use_cov: bool = False):
        """Render. Returns ``(rgb [H, W, 3], alpha [H, W], depth [H, W], radii [N, 2], frame)`` as CPU tensors."""
        s = self.store
        deg = s.sh_degree if sh_degree is None else int(sh_degree)
        if not 0 <= deg <= s.sh_degree:
            raise CausalGSError(f"sh_degree {deg} exceeds the store's degree {s.sh_degree}")
        dt = _ti.torch_dtype()
        W, H = view.width, view.height
        project.project(*self._project_args(view, deg, use_cov))
        box = torch.empty((s.n, 4), dtype=torch.int32)
        radii = torch.empty((s.n, 2), dtype=dt)
        project.bounds(s.mean2d, s.conic, s.depth, s.opac, box, radii, W, H, s.n)
        gids, ranges, packed, pbox = composite.bin_and_pack(s, box, W, H, self.tile)
        rgb = torch.empty((H, W, 3), dtype=dt)
        T_final = torch.empty((H, W), dtype=dt)
        last = torch.empty((H, W), dtype=torch.int32)
        dacc = torch.empty((H, W), dtype=dt)
        tiles_x = (W + self.tile - 1) // self.tile
        bg = ti.math.vec3(*[float(c) for c in background])
        composite.composite_forward(
            packed, pbox, ranges, bg, rgb, T_final, last, dacc, W, H, tiles_x, len(ranges), self.tile
        )
        alpha = 1.0 - T_final
        depth_img = torch.where(alpha > 0, dacc / alpha.clamp(min=1e-12), torch.zeros_like(dacc))
        frame = RenderPass(
            view, tuple(background), deg, use_cov, s.n, gids, ranges, packed, pbox, T_final, last, self.upload
        )
        self.last_pass = frame
        return rgb, alpha, depth_img, radii, frame

    def backward(self, frame: RenderPass, v_rgb: torch.Tensor, v_alpha: torch.Tensor) -> torch.Tensor:
        """Back-propagate ∂L/∂rgb [H, W, 3] and ∂L/∂alpha [H, W] into the store's adjoint fields of the projection
        inputs (cleared first). Returns the screen-space gradients ∂L/∂mean2d [N, 2] (what densification uses)."""
        s = self.store
        if frame.upload != self.upload or frame.n != s.n:
            raise CausalGSError("the store changed between the forward and the backward pass of this render")
        dt = _ti.torch_dtype()
        W, H = frame.view.width, frame.view.height
        m = len(frame.gids)
        v_packed = torch.zeros((m, composite.VPACK), dtype=dt)
        if m:
            composite.composite_backward(
                frame.packed, frame.pbox, frame.ranges, ti.math.vec3(*frame.background), frame.T_final, frame.last,
                v_rgb.detach().to(dt).contiguous(), v_alpha.detach().to(dt).contiguous(),
                torch.empty((H, W), dtype=dt), torch.empty((H, W, 3), dtype=dt), v_packed,
                W, H, (W + self.tile - 1) // self.tile, len(frame.ranges), self.tile,
            )  # fmt: skip
        s.zero_grad((*INPUTS, "mean2d", "conic", "opac", "color"))
        if m:
            composite.scatter_grads(frame.gids, v_packed, s.mean2d, s.conic, s.opac, s.color, m)
        v_mean2d = s.to_torch("mean2d", grad=True)  # read before project.grad, which consumes it
        project.project.grad(*self._project_args(frame.view, frame.sh_degree, frame.use_cov))
        return v_mean2d


# ---------------------------------------------------------------------------------------------------------------------
# The torch boundary
# ---------------------------------------------------------------------------------------------------------------------
_private: dict[int, Rasterizer] = {}


def _scratch_rasterizer() -> Rasterizer:
    """A private degree-3 store for tensor inputs, kept across calls so kernels compile once per capacity bucket
    (lower SH degrees are padded with zeros; the evaluated degree is a kernel constant)."""
    key = _ti.generation()
    if key not in _private:
        _private.clear()
        _private[key] = Rasterizer(ParticleStore(0, sh_degree=3))
    return _private[key]


class _RasterizeFunction(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, quats, scales, opacities, sh, covs, means2d, rast, view, background, sh_degree):
        inputs = {"x": means, "opacity_raw": opacities}
        use_cov = covs is not None
        if use_cov:
            inputs["cov3d"] = covs
        else:
            inputs["quat"], inputs["scale_raw"] = quats, scales
        _upload(rast, inputs, sh)
        rgb, alpha, depth, radii, frame = rast.forward(view, background, sh_degree, use_cov)
        ctx.rast, ctx.frame, ctx.use_cov = rast, frame, use_cov
        ctx.n_sh = sh.shape[1]
        ctx.dtypes = [t.dtype if t is not None else None for t in (means, quats, scales, opacities, sh, covs)]
        ctx.save_for_backward(means, quats, scales, opacities, sh, covs)
        ctx.mark_non_differentiable(depth, radii)
        return rgb, alpha, depth, radii

    @staticmethod
    def backward(ctx, v_rgb, v_alpha, _v_depth, _v_radii):
        rast, frame = ctx.rast, ctx.frame
        if frame.upload != rast.upload:  # another render used the scratch store since: restore this one's inputs
            means, quats, scales, opacities, sh, covs = ctx.saved_tensors
            inputs = {"x": means, "opacity_raw": opacities}
            inputs.update({"cov3d": covs} if ctx.use_cov else {"quat": quats, "scale_raw": scales})
            _upload(rast, inputs, sh)
            frame.upload = rast.upload
        if v_alpha is None:
            v_alpha = torch.zeros(v_rgb.shape[:2], dtype=v_rgb.dtype)
        if v_rgb is None:
            v_rgb = torch.zeros((*v_alpha.shape, 3), dtype=v_alpha.dtype)
        v_mean2d = rast.backward(frame, v_rgb, v_alpha)
        s = rast.store

        def grad(name, i, need, stop=None):
            if not need:
                return None
            g = s.to_torch(name, grad=True)
            return (g if stop is None else g[:, :stop]).to(ctx.dtypes[i])

        need = ctx.needs_input_grad
        return (
            grad("x", 0, need[0]),
            grad("quat", 1, need[1] and not ctx.use_cov),
            grad("scale_raw", 2, need[2] and not ctx.use_cov),
            grad("opacity_raw", 3, need[3]),
            grad("sh", 4, need[4], stop=ctx.n_sh),
            grad("cov3d", 5, need[5] and ctx.use_cov),
            v_mean2d.to(ctx.dtypes[0]) if need[6] else None,
            None, None, None, None,
        )  # fmt: skip


def _upload(rast: Rasterizer, inputs: dict[str, torch.Tensor], sh: torch.Tensor) -> None:
    s = rast.store
    n = len(inputs["x"])
    if s.n != n:
        s.resize(n)
    for name, t in inputs.items():
        s.from_torch(name, t)
    full = torch.zeros((n, s.specs["sh"].elem[0], 3), dtype=sh.dtype)
    full[:, : sh.shape[1]] = sh.detach()
    s.from_torch("sh", full)
    rast.upload += 1


def rasterize(
    means: torch.Tensor,
    quats: torch.Tensor | None,
    scales: torch.Tensor | None,
    opacities: torch.Tensor,
    sh: torch.Tensor,
    viewmat,
    K,
    width: int,
    height: int,
    *,
    background=(0.0, 0.0, 0.0),
    sh_degree: int | None = None,
    covs: torch.Tensor | None = None,
):
    """Render N Gaussians from one camera; differentiable in means, quats, scales, opacities, sh and covs.

    Args:
        means: [N, 3] world positions.
        quats: [N, 4] rotations (w, x, y, z), any norm; ignored when ``covs`` is given.
        scales: [N, 3] log-scales (raw, activated with exp); ignored when ``covs`` is given.
        opacities: [N] logit opacities (raw, activated with a sigmoid).
        sh: [N, S, 3] SH coefficients, S = (d + 1)² for some d ≤ 3 (S = 1: constant colour = 0.28209·sh + 0.5).
        viewmat: [4, 4] world-to-camera (OpenCV frame); K: [3, 3] intrinsics; width, height: image size.
        background: RGB in [0, 1] behind the Gaussians.
        sh_degree: degree evaluated (default: the one S implies).
        covs: [N, 3, 3] world covariances used instead of quats and scales (deformed Gaussians: F Σ Fᵀ).

    Returns:
        ``image`` [H, W, 3], ``alpha`` [H, W] and ``meta``: ``depth`` [H, W] expected depth (not differentiated),
        ``radii`` [N, 2] half extents of the drawn box in pixels (0 = not drawn), ``means2d`` [N, 2] a zero tensor
        whose ``.grad`` after ``backward()`` holds ∂L/∂(projected mean), the screen-space gradient densification
        uses, and ``n_isect``, the number of tile entries.
    """
    n = means.shape[0] if means.dim() == 2 else -1
    if means.shape != (n, 3):
        raise CausalGSError(f"means has shape {list(means.shape)}, expected [N, 3]")
    n_sh = sh.shape[1] if sh.dim() == 3 else 0
    deg = math.isqrt(n_sh) - 1
    if sh.shape != (n, n_sh, 3) or (deg + 1) ** 2 != n_sh or not 0 <= deg <= 3:
        raise CausalGSError(f"sh has shape {list(sh.shape)}, expected [N, (d+1)^2, 3] with d <= 3 and N = {n}")
    if opacities.shape != (n,):
        raise CausalGSError(f"opacities has shape {list(opacities.shape)}, expected [{n}]")
    if covs is None:
        if quats is None or scales is None:
            raise CausalGSError("rasterize needs quats and scales, or covs")
        if quats.shape != (n, 4) or scales.shape != (n, 3):
            raise CausalGSError(
                f"quats/scales have shapes {list(quats.shape)}/{list(scales.shape)}, expected [N, 4]/[N, 3]"
            )
    elif covs.shape != (n, 3, 3):
        raise CausalGSError(f"covs has shape {list(covs.shape)}, expected [N, 3, 3]")
    sh_degree = deg if sh_degree is None else int(sh_degree)
    if sh_degree > deg:
        raise CausalGSError(f"sh_degree {sh_degree} needs {(sh_degree + 1) ** 2} SH coefficients, sh has {n_sh}")
    view = View.of(viewmat, K, width, height)
    bg = tuple(float(c) for c in torch.as_tensor(background, dtype=torch.float64).flatten().tolist())
    if len(bg) != 3:
        raise CausalGSError("background must be three numbers (RGB)")
    rast = _scratch_rasterizer()
    means2d = torch.zeros((n, 2), dtype=means.dtype, requires_grad=torch.is_grad_enabled())
    rgb, alpha, depth, radii = _RasterizeFunction.apply(
        means, quats, scales, opacities, sh, covs, means2d, rast, view, bg, sh_degree
    )
    meta = {"depth": depth, "radii": radii, "means2d": means2d, "n_isect": len(rast.last_pass.gids)}
    return rgb, alpha, meta
