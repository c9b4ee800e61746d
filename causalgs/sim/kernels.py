"""MLS-MPM kernels (Hu et al. 2018, "A moving least squares material point method").

Layout follows taichi's mpm88 and difftaichi's diffmpm: quadratic B-spline weights, the 3×3×3 stencil unrolled with
``ti.static``, separate input/output grids, and particle state indexed by substep within a checkpoint segment:
``x[p, s]``, ``v[p, s]``, ``C[p, s]``, ``F[p, s]`` (the store's per-row axis). A substep reads slot ``s`` and writes
slot ``s + 1``, so no kernel reads a field and then overwrites it (Taichi's global data access rule for autodiff).
Its phases:

    particle box(s) → clear grid → stress(s) → [particle terms(s)] → P2G(s) → grid update → G2P(s)

The forward runs them as the top-level loops of one kernel, :func:`substep`: on a small scene a substep is bound
by launch overhead, not arithmetic (one launch instead of six or seven: 2.8× faster at 27 particles, 1.2× at 8000,
``causalgs bench sim``). Each phase is also a kernel of its own (built from the same ``ti.func`` element), for its
gradient: ``stress`` (per particle: deformation update, plasticity, stress) is separate from ``p2g`` (the stencil
scatter) because two small gradient kernels compile much faster than one large one, and the scatter does not
depend on the material model or the effects.

Particle loops run serially on the CPU (:func:`causalgs._ti.serial_scatter`): with the two cores here, contended
float atomics cost far more than the parallelism gives.

The backward of a substep recomputes its grid, zeroes the grid and ``affine`` adjoints and runs the gradient kernels
in reverse: g2p_adjoint, grid_update.grad, p2g_adjoint, stress.grad (see :mod:`causalgs.sim.mpm`). The transfers'
adjoints are written by hand (Taichi's autodiff of the unrolled stencils was the slowest code to compile, ~50 s and
~20 s); the material, plasticity and effects, where the maths changes with every model, use Taichi's autodiff.

Kernels loop over ``range(n)`` with the count a runtime argument, so they compile once per store capacity. Stencil
base indices are clamped into the grid: a particle that leaves it (or turns NaN) cannot write out of bounds; the
frame check in :mod:`causalgs.sim.mpm` reports it instead.
"""

# No `from __future__ import annotations`: Taichi 1.7 reads kernel annotations as live objects.
from causalgs import _ti
from causalgs._ti import ti
from causalgs.sim.materials import kirchhoff, lame_ti

# Grid mass (kg) below which a node is empty (see grid_update).
MASS_EPS = 1e-12


@ti.func
def _base(Xp, shape: ti.template()):
    """Lower stencil corner of a particle at grid coordinates ``Xp``, clamped so the stencil stays in the grid."""
    b = ti.cast(ti.floor(Xp - 0.5), ti.i32)
    return ti.max(ti.min(b, ti.Vector(shape) - 3), 0)


@ti.func
def _stencil(x, lo, inv_dx, shape: ti.template()):
    """The 3×3×3 stencil of a particle at ``x``: its lower corner node, its position in cells from that corner
    (``fx``) and the quadratic B-spline weights ``W[i, d]`` of node offset ``i`` along axis ``d``."""
    Xp = (x - lo) * inv_dx
    base = _base(Xp, shape)
    fx = Xp - ti.cast(base, float)
    W = ti.Matrix.rows([0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1.0) ** 2, 0.5 * (fx - 0.5) ** 2])
    return base, fx, W


@ti.func
def _weight_grad(fx, W, i: ti.template(), j: ti.template(), k: ti.template()):
    """∇_fx of the weight W[i, 0] W[j, 1] W[k, 2] (the adjoints' position term)."""
    dW = ti.Matrix.rows([fx - 1.5, -2.0 * (fx - 1.0), fx - 0.5])
    return ti.Vector([dW[i, 0] * W[j, 1] * W[k, 2], W[i, 0] * dW[j, 1] * W[k, 2], W[i, 0] * W[j, 1] * dW[k, 2]])


# -- one element of each phase: the bodies of the phase kernels below and of the fused `substep` -----------------
@ti.func
def _box_reset(shape: ti.template(), box: ti.template()):
    for d in ti.static(range(3)):
        box[d] = shape[d]
        box[d + 3] = 0


@ti.func
def _box_grow(xp, lo, inv_dx, shape: ti.template(), box: ti.template()):
    b = _base((xp - lo) * inv_dx, shape)
    for d in ti.static(range(3)):
        ti.atomic_min(box[d], b[d])
        ti.atomic_max(box[d + 3], b[d] + 3)


@ti.func
def _clear_node(I, grid_v_in: ti.template(), grid_m: ti.template(), grid_v_out: ti.template()):
    grid_v_in[I] = ti.Vector.zero(float, 3)
    grid_m[I] = 0.0
    grid_v_out[I] = ti.Vector.zero(float, 3)


@ti.func
def _stress_at(p, C: ti.template(), F: ti.template(), vol: ti.template(), density: ti.template(), E: ti.template(),
               nu: ti.template(), affine: ti.template(), s, dt, inv_dx, model: ti.template(),
               effects: ti.template()):  # fmt: skip
    mu, lam = lame_ti(E[p], nu[p])
    F_new = effects.project((ti.Matrix.identity(float, 3) + dt * C[p, s]) @ F[p, s], mu, lam)
    F[p, s + 1] = F_new
    tau = kirchhoff(F_new, mu, lam, model) + effects.stress(F_new, C[p, s], mu, lam)
    affine[p] = (-dt * vol[p] * 4.0 * inv_dx * inv_dx) * tau + (density[p] * vol[p]) * C[p, s]


@ti.func
def _scatter_at(p, x: ti.template(), v: ti.template(), vol: ti.template(), density: ti.template(),
                affine: ti.template(), grid_v_in: ti.template(), grid_m: ti.template(), s, lo, inv_dx):  # fmt: skip
    base, fx, W = _stencil(x[p, s], lo, inv_dx, grid_m.shape)
    mass = density[p] * vol[p]
    mv = mass * v[p, s]
    A = affine[p]
    for i, j, k in ti.static(ti.ndrange(3, 3, 3)):
        offset = ti.Vector([i, j, k])
        dpos = (ti.cast(offset, float) - fx) / inv_dx
        weight = W[i, 0] * W[j, 1] * W[k, 2]
        grid_v_in[base + offset] += weight * (mv + A @ dpos)
        grid_m[base + offset] += weight * mass


@ti.func
def _update_node(I, grid_v_in: ti.template(), grid_m: ti.template(), grid_v_out: ti.template(), dt, lo, dx,
                 effects: ti.template()):  # fmt: skip
    m = grid_m[I]
    has = m > MASS_EPS
    v = grid_v_in[I] / ti.select(has, m, 1.0)
    xi = lo + ti.cast(I, float) * dx
    v = effects.apply(v, xi, I, dt, dx, ti.static(grid_m.shape))
    grid_v_out[I] = ti.select(has, v, ti.Vector.zero(float, 3))


@ti.func
def _gather_at(p, x: ti.template(), v: ti.template(), C: ti.template(), grid_v_out: ti.template(), s, dt, lo,
               inv_dx):  # fmt: skip
    base, fx, W = _stencil(x[p, s], lo, inv_dx, grid_v_out.shape)
    new_v = ti.Vector.zero(float, 3)
    new_C = ti.Matrix.zero(float, 3, 3)
    for i, j, k in ti.static(ti.ndrange(3, 3, 3)):
        offset = ti.Vector([i, j, k])
        dpos = ti.cast(offset, float) - fx
        g_v = grid_v_out[base + offset]
        weight = W[i, 0] * W[j, 1] * W[k, 2]
        new_v += weight * g_v
        new_C += (4.0 * inv_dx * weight) * g_v.outer_product(dpos)
    v[p, s + 1] = new_v
    C[p, s + 1] = new_C
    x[p, s + 1] = x[p, s] + dt * new_v


# -- the substep in one launch --------------------------------------------------------------------------------------
@ti.kernel
def substep(
    x: ti.template(),
    v: ti.template(),
    vc: ti.template(),
    v_scatter: ti.template(),
    C: ti.template(),
    F: ti.template(),
    vol: ti.template(),
    density: ti.template(),
    E: ti.template(),
    nu: ti.template(),
    affine: ti.template(),
    grid_v_in: ti.template(),
    grid_m: ti.template(),
    grid_v_out: ti.template(),
    box: ti.template(),
    s: ti.i32,
    n: ti.i32,
    dt: float,
    lo: ti.template(),
    inv_dx: float,
    dx: float,
    model: ti.template(),
    effects: ti.template(),
):
    """One MLS-MPM substep, slot ``s`` → ``s + 1``: every phase of the module docstring, each a top-level loop
    (Taichi runs a kernel's top-level loops one after another), in one launch instead of six or seven. The
    backward recomputes a substep's grid with it too, so the phase kernels below compile only for their gradients
    and for the tests and the benchmark that hold this kernel to them (``Simulator.step(phased=True)``).
    ``v_scatter`` is what P2G scatters: ``vc`` when the effects have a particle stage, else ``v``."""
    ti.loop_config(serialize=ti.static(_ti.serial_loops()))
    for _ in range(1):
        _box_reset(grid_m.shape, box)
    ti.loop_config(serialize=ti.static(_ti.serial_scatter()))
    for p in range(n):
        _box_grow(x[p, s], lo[0], inv_dx, grid_m.shape, box)
    ti.loop_config(serialize=ti.static(_ti.serial_loops()))
    for i, j, k in ti.ndrange((box[0], box[3]), (box[1], box[4]), (box[2], box[5])):
        _clear_node(ti.Vector([i, j, k]), grid_v_in, grid_m, grid_v_out)
    ti.loop_config(serialize=ti.static(_ti.serial_loops()))
    for p in range(n):
        _stress_at(p, C, F, vol, density, E, nu, affine, s, dt, inv_dx, model, effects)
    if ti.static(effects.has_particle):
        ti.loop_config(serialize=ti.static(_ti.serial_loops()))
        for p in range(n):
            vc[p, s] = effects.particle(v[p, s], x[p, s], dt)
    ti.loop_config(serialize=ti.static(_ti.serial_scatter()))
    for p in range(n):
        _scatter_at(p, x, v_scatter, vol, density, affine, grid_v_in, grid_m, s, lo[0], inv_dx)
    ti.loop_config(serialize=ti.static(_ti.serial_loops()))
    for i, j, k in ti.ndrange((box[0], box[3]), (box[1], box[4]), (box[2], box[5])):
        _update_node(ti.Vector([i, j, k]), grid_v_in, grid_m, grid_v_out, dt, lo[0], dx, effects)
    ti.loop_config(serialize=ti.static(_ti.serial_scatter()))
    for p in range(n):
        _gather_at(p, x, v, C, grid_v_out, s, dt, lo[0], inv_dx)


# -- the phases one by one: their gradients (Taichi's autodiff) and the hand-written adjoints' checks -------------
@ti.kernel
def particle_box(x: ti.template(), s: ti.i32, n: ti.i32, lo: ti.template(), inv_dx: float, shape: ti.template(),
                 box: ti.template()):  # fmt: skip
    """The box of grid nodes the particles' stencils reach: ``box`` = [lo_i, lo_j, lo_k, hi_i, hi_j, hi_k) (hi
    exclusive). Every grid loop runs over this box only: nodes outside it hold stale values that nothing in this
    substep reads (a body in a 64³ grid touches a few percent of its nodes)."""
    ti.loop_config(serialize=ti.static(_ti.serial_loops()))
    for _ in range(1):
        _box_reset(shape, box)
    ti.loop_config(serialize=ti.static(_ti.serial_scatter()))
    for p in range(n):
        _box_grow(x[p, s], lo[0], inv_dx, shape, box)


@ti.kernel
def clear_grid(grid_v_in: ti.template(), grid_m: ti.template(), grid_v_out: ti.template(), box: ti.template()):
    ti.loop_config(serialize=ti.static(_ti.serial_loops()))
    for i, j, k in ti.ndrange((box[0], box[3]), (box[1], box[4]), (box[2], box[5])):
        _clear_node(ti.Vector([i, j, k]), grid_v_in, grid_m, grid_v_out)


@ti.kernel
def stress(
    v: ti.template(),
    C: ti.template(),
    F: ti.template(),
    vol: ti.template(),
    density: ti.template(),
    E: ti.template(),
    nu: ti.template(),
    affine: ti.template(),
    s: ti.i32,
    n: ti.i32,
    dt: float,
    inv_dx: float,
    model: ti.template(),
    effects: ti.template(),
):
    """Per particle: the trial F = (I + dt C[p, s]) F[p, s], return-mapped by the plastic terms, into F[p, s+1]; its
    Kirchhoff stress (material + stress terms) folded with the APIC term into ``affine[p]`` (MLS-MPM eq. 29: the
    stress force uses ∇w ≈ 4/dx² w (x_i − x_p)). Mass = density · volume, so the density has a gradient."""
    ti.loop_config(serialize=ti.static(_ti.serial_loops()))
    for p in range(n):
        _stress_at(p, C, F, vol, density, E, nu, affine, s, dt, inv_dx, model, effects)


@ti.kernel
def particle_terms(x: ti.template(), v: ti.template(), vc: ti.template(), s: ti.i32, n: ti.i32, dt: float,
                   effects: ti.template()):  # fmt: skip
    """Per particle: its velocity after the particle-stage effects (contact met by the particles themselves) into
    ``vc[p, s]``, which P2G then scatters in place of ``v[p, s]`` (a separate field: no kernel overwrites what it
    reads). Its gradient is Taichi's autodiff."""
    ti.loop_config(serialize=ti.static(_ti.serial_loops()))
    for p in range(n):
        vc[p, s] = effects.particle(v[p, s], x[p, s], dt)


@ti.kernel
def zero_slot_grad(f: ti.template(), s: ti.i32, n: ti.i32):
    """Zero the adjoint of slot ``s`` of a substep-indexed vector field (once the kernels that read it have run)."""
    ti.loop_config(serialize=ti.static(_ti.serial_loops()))
    for p in range(n):
        f.grad[p, s] = ti.Vector.zero(float, 3)


@ti.kernel
def p2g(
    x: ti.template(),
    v: ti.template(),
    vol: ti.template(),
    density: ti.template(),
    affine: ti.template(),
    grid_v_in: ti.template(),
    grid_m: ti.template(),
    s: ti.i32,
    n: ti.i32,
    lo: ti.template(),
    inv_dx: float,
):
    """Scatter mass and affine momentum m v + A (x_i − x_p) to the 3×3×3 stencil (independent of the material and
    the effects, so it compiles once)."""
    ti.loop_config(serialize=ti.static(_ti.serial_scatter()))
    for p in range(n):
        _scatter_at(p, x, v, vol, density, affine, grid_v_in, grid_m, s, lo[0], inv_dx)


@ti.kernel
def p2g_adjoint(
    x: ti.template(),
    v: ti.template(),
    vol: ti.template(),
    density: ti.template(),
    affine: ti.template(),
    grid_v_in: ti.template(),
    grid_m: ti.template(),
    s: ti.i32,
    n: ti.i32,
    lo: ti.template(),
    inv_dx: float,
):
    """The adjoint of :func:`p2g`, written out: a gather of the grid adjoints into x, v, affine and density.

    Taichi's autodiff of the unrolled 27-point scatter compiles for ~50 s on these machines; this gather compiles in
    seconds and needs no atomics (each particle owns its adjoint rows). With g_i = dL/dp_i, h_i = dL/dm_i and
    c_ip = m v + A dpos_ip:  dL/dv = Σ w m g_i;  dL/dA = Σ w g_i dposᵀ;  dL/dm = Σ w (v·g_i + h_i);
    dL/dx = inv_dx Σ [(g_i·c_ip + h_i m) ∇_fx w − w dx Aᵀ g_i]  (dpos = (i − fx) dx, fx = (x − lo)/dx − base).
    Checked against Taichi's autodiff of :func:`p2g` and finite differences (tests/sim)."""
    ti.loop_config(serialize=ti.static(_ti.serial_scatter()))
    for p in range(n):
        base, fx, W = _stencil(x[p, s], lo[0], inv_dx, grid_m.shape)
        mass = density[p] * vol[p]
        vp = v[p, s]
        A = affine[p]
        At = A.transpose()
        g_fx = ti.Vector.zero(float, 3)
        g_v = ti.Vector.zero(float, 3)
        g_A = ti.Matrix.zero(float, 3, 3)
        g_mass = 0.0
        for i, j, k in ti.static(ti.ndrange(3, 3, 3)):
            offset = ti.Vector([i, j, k])
            dpos = (ti.cast(offset, float) - fx) / inv_dx
            weight = W[i, 0] * W[j, 1] * W[k, 2]
            grad_w = _weight_grad(fx, W, i, j, k)
            gp = grid_v_in.grad[base + offset]
            gm = grid_m.grad[base + offset]
            g_fx += (gp.dot(mass * vp + A @ dpos) + gm * mass) * grad_w - (weight / inv_dx) * (At @ gp)
            g_v += (weight * mass) * gp
            g_A += weight * gp.outer_product(dpos)
            g_mass += weight * (vp.dot(gp) + gm)
        x.grad[p, s] = x.grad[p, s] + inv_dx * g_fx
        v.grad[p, s] = v.grad[p, s] + g_v
        affine.grad[p] = affine.grad[p] + g_A
        density.grad[p] = density.grad[p] + g_mass * vol[p]


@ti.kernel
def grid_update(
    grid_v_in: ti.template(),
    grid_m: ti.template(),
    grid_v_out: ti.template(),
    dt: float,
    lo: ti.template(),
    dx: float,
    effects: ti.template(),
    box: ti.template(),
):
    """Momentum → velocity, then every force and boundary term in order, over the particles' box. Empty nodes keep
    zero velocity (branch-free: the division uses a safe mass so its adjoint stays finite). A node counts as empty
    below ``MASS_EPS``: at the edge of a B-spline's support a node can get a denormal mass in float32, whose adjoint
    −mv/m² overflows to inf and, times a zero adjoint, poisons every particle with NaN."""
    ti.loop_config(serialize=ti.static(_ti.serial_loops()))
    for i, j, k in ti.ndrange((box[0], box[3]), (box[1], box[4]), (box[2], box[5])):
        _update_node(ti.Vector([i, j, k]), grid_v_in, grid_m, grid_v_out, dt, lo[0], dx, effects)


@ti.kernel
def g2p(
    x: ti.template(),
    v: ti.template(),
    C: ti.template(),
    grid_v_out: ti.template(),
    s: ti.i32,
    n: ti.i32,
    dt: float,
    lo: ti.template(),
    inv_dx: float,
):
    """Gather v and the APIC matrix C = 4/dx² Σ w v_i (x_i − x_p)ᵀ into slot s+1; advect x with the new v."""
    ti.loop_config(serialize=ti.static(_ti.serial_scatter()))
    for p in range(n):
        _gather_at(p, x, v, C, grid_v_out, s, dt, lo[0], inv_dx)


@ti.kernel
def g2p_adjoint(
    x: ti.template(),
    v: ti.template(),
    C: ti.template(),
    grid_v_out: ti.template(),
    s: ti.i32,
    n: ti.i32,
    dt: float,
    lo: ti.template(),
    inv_dx: float,
):
    """The adjoint of :func:`g2p`, written out: scatter the adjoints of x, v, C at slot s+1 into the grid velocity
    adjoint and x at slot s (Taichi's autodiff of g2p compiles for ~20 s and runs ~2× slower).

    With a = dL/dv' + dt dL/dx' and G = dL/dC', per stencil node (dpos = i − fx in cells, c = 4 inv_dx):
    dL/dv_i += w a + c w G dpos;  dL/dw = v_i·a + c v_iᵀ G dpos;  dL/dfx += dL/dw ∇w − c w Gᵀ v_i;
    dL/dx += dL/dx' + inv_dx dL/dfx. Checked against Taichi's autodiff of :func:`g2p` and finite differences."""
    ti.loop_config(serialize=ti.static(_ti.serial_scatter()))
    for p in range(n):
        base, fx, W = _stencil(x[p, s], lo[0], inv_dx, grid_v_out.shape)
        gx = x.grad[p, s + 1]
        a = v.grad[p, s + 1] + dt * gx
        G = C.grad[p, s + 1]
        c = 4.0 * inv_dx
        g_fx = ti.Vector.zero(float, 3)
        for i, j, k in ti.static(ti.ndrange(3, 3, 3)):
            offset = ti.Vector([i, j, k])
            dpos = ti.cast(offset, float) - fx
            weight = W[i, 0] * W[j, 1] * W[k, 2]
            grad_w = _weight_grad(fx, W, i, j, k)
            g_v = grid_v_out[base + offset]
            Gd = G @ dpos
            grid_v_out.grad[base + offset] += weight * (a + c * Gd)
            g_fx += (g_v.dot(a) + c * g_v.dot(Gd)) * grad_w - (c * weight) * (G.transpose() @ g_v)
        x.grad[p, s] = x.grad[p, s] + gx + inv_dx * g_fx


@ti.kernel
def clear_grid_grad(grid_v_in: ti.template(), grid_m: ti.template(), grid_v_out: ti.template(), box: ti.template()):
    """Zero the grid adjoints (in the particles' box) before the gradient kernels of one substep."""
    ti.loop_config(serialize=ti.static(_ti.serial_loops()))
    for i, j, k in ti.ndrange((box[0], box[3]), (box[1], box[4]), (box[2], box[5])):
        I = ti.Vector([i, j, k])
        grid_v_in.grad[I] = ti.Vector.zero(float, 3)
        grid_m.grad[I] = 0.0
        grid_v_out.grad[I] = ti.Vector.zero(float, 3)


@ti.kernel
def carry_adjoint(x: ti.template(), v: ti.template(), C: ti.template(), F: ti.template(), dst: ti.i32, n: ti.i32):
    """Between two segments of the backward: the adjoint of slot 0 (the start of the later segment) becomes the
    adjoint of slot ``dst`` (the end of the earlier one); every other slot's adjoint is zeroed."""
    ti.loop_config(serialize=ti.static(_ti.serial_loops()))
    for p in range(n):
        gx, gv, gC, gF = x.grad[p, 0], v.grad[p, 0], C.grad[p, 0], F.grad[p, 0]
        for s in range(x.grad.shape[1]):
            x.grad[p, s] = ti.Vector.zero(float, 3)
            v.grad[p, s] = ti.Vector.zero(float, 3)
            C.grad[p, s] = ti.Matrix.zero(float, 3, 3)
            F.grad[p, s] = ti.Matrix.zero(float, 3, 3)
        x.grad[p, dst] = gx
        v.grad[p, dst] = gv
        C.grad[p, dst] = gC
        F.grad[p, dst] = gF


@ti.kernel
def copy_slot(
    x: ti.template(), v: ti.template(), C: ti.template(), F: ti.template(), src: ti.i32, dst: ti.i32, n: ti.i32
):
    """Carry the end state of a segment into slot 0 of the next (the checkpoint boundary)."""
    ti.loop_config(serialize=ti.static(_ti.serial_loops()))
    for p in range(n):
        x[p, dst] = x[p, src]
        v[p, dst] = v[p, src]
        C[p, dst] = C[p, src]
        F[p, dst] = F[p, src]


@ti.kernel
def rows_to_slot(
    x0: ti.template(),
    v0: ti.template(),
    C0: ti.template(),
    F0: ti.template(),
    x: ti.template(),
    v: ti.template(),
    C: ti.template(),
    F: ti.template(),
    s: ti.i32,
    n: ti.i32,
):
    """Copy the store's plain state fields (x, v, C, F) into slot ``s`` of the substep-indexed ones."""
    ti.loop_config(serialize=ti.static(_ti.serial_loops()))
    for p in range(n):
        x[p, s] = x0[p]
        v[p, s] = v0[p]
        C[p, s] = C0[p]
        F[p, s] = F0[p]


@ti.kernel
def slot_to_rows(
    x: ti.template(),
    v: ti.template(),
    C: ti.template(),
    F: ti.template(),
    x0: ti.template(),
    v0: ti.template(),
    C0: ti.template(),
    F0: ti.template(),
    s: ti.i32,
    n: ti.i32,
):
    ti.loop_config(serialize=ti.static(_ti.serial_loops()))
    for p in range(n):
        x0[p] = x[p, s]
        v0[p] = v[p, s]
        C0[p] = C[p, s]
        F0[p] = F[p, s]


@ti.kernel
def frame_stats(x: ti.template(), v: ti.template(), F: ti.template(), s: ti.i32, n: ti.i32, lo: ti.template(),
                inv_dx: float, shape: ti.template(), stats: ti.template()):  # fmt: skip
    """stats = [Σ |x|+|v|+|F| (non-finite if any entry is), max |v|, particles outside the grid, 0]."""
    ti.loop_config(serialize=ti.static(_ti.serial_loops()))
    for i in range(stats.shape[0]):
        stats[i] = 0.0
    ti.loop_config(serialize=ti.static(_ti.serial_loops()))
    for p in range(n):
        Xp = (x[p, s] - lo[0]) * inv_dx
        stats[0] += x[p, s].norm() + v[p, s].norm() + F[p, s].norm()
        ti.atomic_max(stats[1], v[p, s].norm())
        out = 0
        for d in ti.static(range(3)):
            out += ti.select((Xp[d] < 0.5) | (Xp[d] >= shape[d] - 1.5), 1, 0)
        stats[2] += ti.select(out > 0, 1.0, 0.0)
