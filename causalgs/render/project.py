"""Per-Gaussian projection (Taichi): 3D covariance, EWA splatting, SH colour, activated opacity, screen bounds.

``project`` is differentiated by Taichi's autodiff (``project.grad``): it is a plain per-Gaussian map with no loop
over other data, which Taichi handles exactly. The compositing backward is written by hand (see composite.py).
The maths is that of :mod:`causalgs.render.reference`; the constants live there.
"""

# No `from __future__ import annotations`: Taichi 1.7 reads kernel annotations as live objects.
from causalgs._ti import ti
from causalgs.render.reference import ALPHA_MIN, EPS2D, NEAR
from causalgs.render.sh import eval_sh
from causalgs.store import FieldSpec

# Per-particle fields the rasterizer adds to the ParticleStore: an optional full-covariance input and the projected
# quantities the compositing reads. Their adjoints carry the compositing gradients into ``project.grad``.
RENDER_SPECS = (
    FieldSpec("cov3d", (3, 3), doc="world covariance, used instead of scale/quat (deformed Gaussians: F Σ Fᵀ)"),
    FieldSpec("mean2d", (2,), doc="projected mean (px, corner-origin)"),
    FieldSpec("conic", (3,), doc="inverse 2D covariance (a, b, c) of [[a, b], [b, c]]"),
    FieldSpec("depth", (), grad=False, doc="camera depth; 0 for culled Gaussians"),
    FieldSpec("color", (3,), doc="view-dependent colour: max(SH + 0.5, 0)"),
    FieldSpec("opac", (), doc="activated opacity; 0 for culled Gaussians"),
)


@ti.func
def _quat_to_rotmat(q):
    q = q / q.norm()
    w, x, y, z = q[0], q[1], q[2], q[3]
    return ti.Matrix(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


@ti.kernel
def project(
    x: ti.template(),
    scale_raw: ti.template(),
    quat: ti.template(),
    opacity_raw: ti.template(),
    sh: ti.template(),
    cov3d: ti.template(),
    mean2d: ti.template(),
    conic: ti.template(),
    depth: ti.template(),
    color: ti.template(),
    opac: ti.template(),
    viewmat: ti.math.mat4,
    intr: ti.math.vec4,
    campos: ti.math.vec3,
    width: ti.i32,
    height: ti.i32,
    n: ti.i32,
    degree: ti.template(),
    use_cov: ti.template(),
):
    """Project Gaussians [0, n). ``intr`` = (fx, fy, cx, cy); ``campos`` = camera centre for the SH direction.

    Branch-free on purpose: culled Gaussians (closer than NEAR) are computed at a safe depth and masked with
    ``ti.select``. Mutable locals inside branches make Taichi's autodiff use its AD stack, which made ``project.grad``
    take ~45 s to compile; without them it compiles several times faster.
    """
    for i in range(n):
        W = viewmat[0:3, 0:3]
        p = W @ x[i] + ti.Vector([viewmat[0, 3], viewmat[1, 3], viewmat[2, 3]])
        fx, fy, cx, cy = intr[0], intr[1], intr[2], intr[3]
        valid = p.z > NEAR
        z = ti.select(valid, p.z, 1.0)
        cov = ti.Matrix.zero(float, 3, 3)
        if ti.static(use_cov):
            cov = cov3d[i]
        else:
            s = ti.exp(scale_raw[i])
            M = _quat_to_rotmat(quat[i]) @ ti.Matrix([[s[0], 0.0, 0.0], [0.0, s[1], 0.0], [0.0, 0.0, s[2]]])
            cov = M @ M.transpose()
        cov_c = W @ cov @ W.transpose()
        # Jacobian of the perspective map at a position clamped to 1.3x the field of view (gsplat).
        tan_x, tan_y = 0.5 * width / fx, 0.5 * height / fy
        tx = z * ti.min(ti.max(p.x / z, -(cx / fx + 0.3 * tan_x)), (width - cx) / fx + 0.3 * tan_x)
        ty = z * ti.min(ti.max(p.y / z, -(cy / fy + 0.3 * tan_y)), (height - cy) / fy + 0.3 * tan_y)
        J = ti.Matrix([[fx / z, 0.0, -fx * tx / (z * z)], [0.0, fy / z, -fy * ty / (z * z)]])
        c2 = J @ cov_c @ J.transpose()
        a, b, c = c2[0, 0] + EPS2D, c2[0, 1], c2[1, 1] + EPS2D
        det = ti.max(a * c - b * b, 1e-12)  # >= EPS2D² for a PSD covariance; the max only guards rounding
        d = x[i] - campos
        # +1e-20 keeps the direction (and its gradient) finite for a Gaussian at the camera centre.
        col = ti.max(eval_sh(sh[i], d / ti.sqrt(d.dot(d) + 1e-20), degree) + 0.5, 0.0)
        zero2, zero3 = ti.Vector([0.0, 0.0]), ti.Vector([0.0, 0.0, 0.0])
        mean2d[i] = ti.select(valid, ti.Vector([fx * p.x / z + cx, fy * p.y / z + cy]), zero2)
        conic[i] = ti.select(valid, ti.Vector([c / det, -b / det, a / det]), zero3)
        depth[i] = ti.select(valid, z, 0.0)
        opac[i] = ti.select(valid, 1.0 / (1.0 + ti.exp(-opacity_raw[i])), 0.0)
        color[i] = ti.select(valid, col, zero3)


@ti.kernel
def bounds(
    mean2d: ti.template(),
    conic: ti.template(),
    depth: ti.template(),
    opac: ti.template(),
    box: ti.types.ndarray(),
    radii: ti.types.ndarray(),
    width: ti.i32,
    height: ti.i32,
    n: ti.i32,
):
    """Pixel box [x0, x1] × [y0, y1] (inclusive) of pixel centres where alpha can reach 1/255, clipped to the image.

    alpha = o·exp(−σ) ≥ 1/255 ⇔ σ ≤ ln(255·o); on that ellipse |dx| ≤ sqrt(2 ln(255 o) Σxx), |dy| ≤ sqrt(2 ln(255 o)
    Σyy). This box is exact (no 3σ cut), so the tile lists drop nothing the reference would draw; a 1e-4 margin covers
    rounding. An empty box (x0 > x1) marks a Gaussian that draws nothing. ``radii`` gets the two half extents (px).
    """
    for i in range(n):
        x0, x1, y0, y1 = 0, -1, 0, -1
        ex, ey = 0.0, 0.0
        o = opac[i]
        if depth[i] > 0 and o >= ALPHA_MIN:
            co = conic[i]
            det = co[0] * co[2] - co[1] * co[1]
            q = 2.0 * ti.log(255.0 * o) * (1.0 + 1e-4) + 1e-6
            ex = ti.sqrt(q * co[2] / det)
            ey = ti.sqrt(q * co[0] / det)
            m = mean2d[i]
            # Pixel j has its centre at j + 0.5: j in [ceil(m - e - 0.5), floor(m + e - 0.5)], clipped in float first.
            x0 = ti.cast(ti.max(ti.ceil(m[0] - ex - 0.5), 0.0), ti.i32)
            x1 = ti.cast(ti.min(ti.floor(m[0] + ex - 0.5), width - 1.0), ti.i32)
            y0 = ti.cast(ti.max(ti.ceil(m[1] - ey - 0.5), 0.0), ti.i32)
            y1 = ti.cast(ti.min(ti.floor(m[1] + ey - 0.5), height - 1.0), ti.i32)
        if x0 > x1 or y0 > y1:
            ex, ey = 0.0, 0.0
        box[i, 0] = x0
        box[i, 1] = x1
        box[i, 2] = y0
        box[i, 3] = y1
        radii[i, 0] = ex
        radii[i, 1] = ey
