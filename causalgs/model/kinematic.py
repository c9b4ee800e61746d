"""The kinematic path: integrate the inferred velocity field from t = 0 and rotate the Gaussians with it.

RK2 (midpoint) at dt = 1/fps (or a fraction of it): for every particle

    x_mid = x + dt/2 · v(x, t),   x ← x + dt · v(x_mid, t + dt/2),

and the rotation follows the velocity Jacobian: for v_i = a_i + ω_i × x the Jacobian is [ω_i]×, a pure rotation rate,
so q ← exp(½ ω_i(t + dt/2) dt) ⊗ q (the midpoint rule again). Both are second order in dt; the tests check the
orders against a rigid rotation with a known closed form.

Training uses the same rule on the K patterns instead of the N particles (:func:`pattern_motion`): each pattern's
field is affine in x, so one RK2 step is an affine map and stepping the map (R_k, t_k) steps every point exactly. A
particle is then placed by blending its patterns' motions with its mixture h (:func:`blend`). For a particle of one
pattern this is exactly :func:`integrate`; for a mixed one it is a linear blend of rigid motions rather than the
integral of the blended velocity (they agree to first order in time and both start with the blended velocity). It
costs O(T·K) for the integration plus O(N·K) per rendered frame, instead of O(T·N) autograd operations — 5× faster
training at 20k Gaussians. :func:`integrate` remains the per-particle reference the tests hold it to.
"""

from __future__ import annotations

import torch

from causalgs.model.fields import InversePhysics


def quat_mul(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product of wxyz quaternions [..., 4]."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack([
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    ], dim=-1)  # fmt: skip


def rotvec_quat(r: torch.Tensor) -> torch.Tensor:
    """exp of a rotation vector [..., 3] as a unit wxyz quaternion (smooth at 0: sin(θ/2)/θ → ½)."""
    theta2 = (r * r).sum(-1, keepdim=True)
    theta = torch.sqrt(theta2 + 1e-24)
    half = 0.5 * theta
    small = theta2 < 1e-8
    s = torch.where(small, 0.5 - theta2 / 48.0, torch.sin(half) / theta)
    c = torch.where(small, 1.0 - theta2 / 8.0, torch.cos(half))
    return torch.cat([c, s * r], dim=-1)


def integrate(
    fields: InversePhysics,
    h: torch.Tensor,
    x0: torch.Tensor,
    q0: torch.Tensor | None,
    steps: int,
    dt: float,
    substeps: int = 1,
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Positions [steps + 1, N, 3] (and quaternions [steps + 1, N, 4] if ``q0`` is given) at t = k·dt, k = 0..steps,
    for particles with mixtures ``h`` [N, K] starting at ``x0`` at t = 0. ``substeps`` RK2 steps per ``dt``."""
    m = max(1, int(substeps))
    dts = dt / m
    n_steps = int(steps) * m
    # Twists at every midpoint and step start, computed in one batched call: the network is a function of t only.
    t_start = torch.arange(n_steps, dtype=torch.float64) * dts
    W = fields.twists(torch.cat([t_start, t_start + 0.5 * dts]).to(x0.dtype)).to(x0.dtype)
    u, w = W[..., :3], W[..., 3:]
    c = fields.centres.to(x0.dtype)
    moving = bool(fields.moving_centres)
    xs, qs = [x0], ([q0 / q0.norm(dim=-1, keepdim=True)] if q0 is not None else None)
    x, q = x0, qs[0] if qs is not None else None

    def velocity(i, y, centres):  # v_i = Σ_k h_ik (u_k + ω_k × (y − c_k)) at twist row i
        a = torch.einsum("nk,kd->nd", h, u[i] - torch.linalg.cross(w[i], centres))
        return a + torch.linalg.cross(h @ w[i], y)

    for k in range(n_steps):
        i0, im = k, n_steps + k
        xm = x + 0.5 * dts * velocity(i0, x, c)
        c_mid = c + 0.5 * dts * u[i0] if moving else c  # a centre is a point of its pattern: it moves with u_k
        x = x + dts * velocity(im, xm, c_mid)
        if moving:
            c = c + dts * u[im]
        wm = h @ w[im]
        if q is not None:
            q = quat_mul(rotvec_quat(wm * dts), q)
        if (k + 1) % m == 0:
            xs.append(x)
            if qs is not None:
                qs.append(q)
    return torch.stack(xs), (torch.stack(qs) if qs is not None else None)


def skew(w: torch.Tensor) -> torch.Tensor:
    """[..., 3] → [..., 3, 3] with skew(w) @ x = w × x."""
    z = torch.zeros_like(w[..., 0])
    wx, wy, wz = w.unbind(-1)
    return torch.stack([z, -wz, wy, wz, z, -wx, -wy, wx, z], dim=-1).reshape(*w.shape[:-1], 3, 3)


def pattern_motion(fields: InversePhysics, steps: int, dt: float, substeps: int = 1):
    """The rigid motion of every pattern, integrated by the same RK2 midpoint rule: x(t) = R_k(t) x(0) + t_k(t).

    Pattern k's twist (u_k, ω_k) turns it about its centre c_k. With ``fields.moving_centres`` the centre is a point
    of the pattern, carried along (c_k(t) = R_k c_k(0) + t_k: u_k is the velocity of the body's centre and ω_k its
    spin, whatever the body's path); otherwise it stays where it is in space.

    For the affine field v = a + ω × x one RK2 step is an affine map of x, so stepping the map (R, t) is exactly
    stepping every point; a particle that belongs to one pattern moves precisely as :func:`integrate` moves it.
    Returns R [steps + 1, K, 3, 3], t [steps + 1, K, 3] and the patterns' rotations q [steps + 1, K, 4] (wxyz)."""
    m = max(1, int(substeps))
    dts = dt / m
    n = int(steps) * m
    t_start = torch.arange(n, dtype=torch.float64) * dts
    W = fields.twists(torch.cat([t_start, t_start + 0.5 * dts]).to(fields.centres.dtype))
    u, w = W[..., :3], W[..., 3:]
    c0 = fields.centres
    moving = bool(fields.moving_centres)
    u0, w0, um, wm = u[:n], w[:n], u[n:], w[n:]
    S0, Sm = skew(w0), skew(wm)
    K = fields.config.patterns
    dtype = fields.centres.dtype
    R = torch.eye(3, dtype=dtype).expand(K, 3, 3)
    tr = torch.zeros(K, 3, dtype=dtype)
    q = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=dtype).expand(K, 4)
    Rs, ts, qs = [R], [tr], [q]

    def offset(u_k, w_k, R_, t_):  # a_k = u_k − ω_k × c_k, the centre where the pattern has carried it (or fixed)
        c = (R_ @ c0[..., None])[..., 0] + t_ if moving else c0
        return u_k - torch.linalg.cross(w_k, c)

    for k in range(n):
        R_mid = R + 0.5 * dts * S0[k] @ R
        t_mid = tr + 0.5 * dts * (offset(u0[k], w0[k], R, tr) + (S0[k] @ tr[..., None])[..., 0])
        am = offset(um[k], wm[k], R_mid, t_mid)
        R = R + dts * Sm[k] @ R_mid
        tr = tr + dts * (am + (Sm[k] @ t_mid[..., None])[..., 0])
        q = quat_mul(rotvec_quat(wm[k] * dts), q)
        if (k + 1) % m == 0:
            Rs.append(R)
            ts.append(tr)
            qs.append(q)
    return torch.stack(Rs), torch.stack(ts), torch.stack(qs)


def blend(h: torch.Tensor, x0: torch.Tensor, q0: torch.Tensor | None, R: torch.Tensor, t: torch.Tensor,
          q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:  # fmt: skip
    """Positions [N, 3] (and rotations [N, 4]) of particles with mixtures h [N, K] at one time, from the patterns'
    motion R [K, 3, 3], t [K, 3], q [K, 4]: x = Σ_k h_k (R_k x0 + t_k); the rotation is the h-weighted quaternion
    average (signs aligned with the particle's dominant pattern) applied to q0. Exact for a particle in one pattern;
    a linear blend of the patterns' rigid motions otherwise."""
    x = torch.einsum("nk,nki->ni", h, torch.einsum("kij,nj->nki", R, x0) + t)
    if q0 is None:
        return x, None
    ref = q[h.argmax(dim=1)]  # [N, 4]
    sign = torch.sign((q[None] * ref[:, None]).sum(-1)).detach()  # [N, K]
    sign = torch.where(sign == 0, torch.ones_like(sign), sign)
    qb = torch.einsum("nk,kd->nd", h * sign, q)
    qb = qb / qb.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    return x, quat_mul(qb, q0 / q0.norm(dim=-1, keepdim=True))


def flow_paths(fields: InversePhysics, x0: torch.Tensor, steps: int, dt: float, substeps: int = 1) -> torch.Tensor:
    """Positions [steps + 1, N, 3] of material points at canonical ``x0`` moved by the unstructured velocity
    (:class:`~causalgs.model.fields.Flow`, the ablation without VFD): v depends on the point and the time only, so the
    midpoint rule is a sum, x(k·dt) = x0 + Σ_{j < k·m} dt/m · v(x0, (j + ½)·dt/m), with m = ``substeps``."""
    m = max(1, int(substeps))
    dts = dt / m
    n = int(steps) * m
    if n == 0:
        return x0[None]
    mid = (torch.arange(n, dtype=torch.float64) + 0.5) * dts
    v = fields.flow_velocity(x0, mid.to(x0.dtype))  # [n, N, 3]
    path = torch.cumsum(v * dts, dim=0)[m - 1::m]
    return torch.cat([x0[None], x0[None] + path], dim=0)
