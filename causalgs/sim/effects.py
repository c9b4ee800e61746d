"""External effects: a registry of named, parameterised terms of the MPM step.

An effect is a ``ti.func`` registered under a name with its parameters and a *stage* that says where it acts:

- ``FORCE`` and ``BOUNDARY`` terms change the grid velocity after the momentum division (gravity, a force field,
  drag; ground planes, domain walls), forces first;
- ``PLASTIC`` terms return-map the trial deformation gradient (plasticity);
- ``STRESS`` terms add to the material's Kirchhoff stress (material damping);
- ``PARTICLE`` terms change a particle's velocity before it is scattered to the grid (a floor met by the particles
  themselves, whose contact does not depend on the grid spacing).

An :class:`Effects` object holds the chosen terms; the kernels receive its :class:`Stages` as a static argument and
apply the terms of each stage in a ``ti.static`` loop (no if-chain over effect names). A new effect is one decorated
function.

Parameter values belong to the :class:`Effects` object; the kernels read them from one small Taichi field per
registered effect and runtime (``needs_grad=True``: the checkpointed backward accumulates their gradients there),
so that any number of simulators share one compiled set of kernels. Parameters are addressed by name:
``effects.get("gravity", "g")``, ``effects.set("gravity", g=(0, 0, -9.8))``, or as one vector (:meth:`Effects.flat`,
:meth:`Effects.param_names`). Every term is written so its parameters have gradients: contact uses a one-cell ramp
rather than a hard in/out test, norms are smoothed at zero.

Spec strings name the terms: ``"gravity:g=0,0,-9.8;ground:mu=0.4;linear_drag:c=0.5"``; a parameter left out takes
its default; the order in the spec does not matter.
"""

# No `from __future__ import annotations`: Taichi 1.7 reads kernel annotations as live objects.
import itertools
import math
from dataclasses import dataclass

import numpy as np

from causalgs import _ti
from causalgs._ti import ti
from causalgs.errors import CausalGSError
from causalgs.sim.materials import polar_rotation

# Grid nodes this close to the domain boundary are wall nodes (mpm88 uses 3: the quadratic stencil reaches two nodes
# past a particle's cell, so a particle is stopped before its stencil leaves the grid).
WALL_BAND = 3

# Where a term acts, which is also its application order within the grid update (forces, then boundary conditions).
#   FORCE, BOUNDARY: f(v, x, I, dt, dx, p, res) -> v         grid velocity after the momentum division
#   PLASTIC:         f(F, mu, lam, p) -> F                     return mapping of the trial deformation gradient
#   STRESS:          f(F, C, mu, lam, p) -> tau                Kirchhoff stress added to the material's
#   PARTICLE:        f(v, x, dt, p) -> v                       a particle's velocity before P2G
FORCE, BOUNDARY, PLASTIC, STRESS, PARTICLE = 0, 1, 2, 3, 4
GRID_STAGES = (FORCE, BOUNDARY)

# |v| is taken as sqrt(v·v + EPS²), so norms of zero vectors have a finite (zero) derivative.
EPS = 1e-12


@dataclass(frozen=True)
class Param:
    name: str
    size: int
    default: tuple[float, ...]
    doc: str = ""
    lower: float | None = None  # inclusive bound on every entry, checked when set


@dataclass(frozen=True)
class EffectDef:
    """A registered effect: its ``func``, its parameters (packed in this order), its stage and its law in words.

    ``dt_limit(values, dx, rho_min)``, when given, is the largest stable substep the term allows (s)."""

    name: str
    func: object
    params: tuple[Param, ...]
    order: int
    doc: str
    dt_limit: object = None

    @property
    def size(self) -> int:
        return sum(p.size for p in self.params)

    def param(self, name: str) -> Param:
        for p in self.params:
            if p.name == name:
                return p
        known = ", ".join(p.name for p in self.params) or "none"
        raise CausalGSError(f"effect '{self.name}' has no parameter '{name}' (parameters: {known})")

    def offset(self, name: str) -> int:
        self.param(name)
        off = 0
        for p in self.params:
            if p.name == name:
                return off
            off += p.size
        return off


REGISTRY: dict[str, EffectDef] = {}


def register(name: str, params: tuple[Param, ...] = (), order: int = FORCE, doc: str = "", dt_limit=None):
    """Decorator: register a ``ti.func`` of the stage ``order`` (see the signatures above) as the effect ``name``."""

    def wrap(func):
        if name in REGISTRY:
            raise CausalGSError(f"effect '{name}' is registered twice")
        REGISTRY[name] = EffectDef(name, func, tuple(params), order, doc, dt_limit)
        return func

    return wrap


@ti.func
def _vec(p: ti.template(), o: ti.template()):
    return ti.Vector([p[o], p[o + 1], p[o + 2]])


@ti.func
def _norm(v):
    return ti.sqrt(v.dot(v) + EPS * EPS)


# -- forces ------------------------------------------------------------------------------------------------------


@register("gravity", (Param("g", 3, (0.0, 0.0, -9.8), "acceleration (m/s²)"),), doc="uniform acceleration: v += dt g")
@ti.func
def gravity(v, x, I, dt, dx, p: ti.template(), res: ti.template()):
    return v + dt * _vec(p, 0)


@register(
    "force",
    (Param("b", 3, (0.0, 0.0, 0.0), "acceleration (m/s²)"),),
    doc="uniform external force field per unit mass (e.g. wind): v += dt b",
)
@ti.func
def force(v, x, I, dt, dx, p: ti.template(), res: ti.template()):
    return v + dt * _vec(p, 0)


@register(
    "linear_drag",
    (Param("c", 1, (0.0,), "drag rate (1/s)", lower=0.0),),
    doc="a = -c v, integrated exactly over a substep: v *= exp(-c dt) (stable for any c dt)",
)
@ti.func
def linear_drag(v, x, I, dt, dx, p: ti.template(), res: ti.template()):
    return v * ti.exp(-p[0] * dt)


@register(
    "quadratic_drag",
    (Param("k", 1, (0.0,), "drag coefficient (1/m)", lower=0.0),),
    doc="a = -k |v| v, integrated exactly along v over a substep: v /= 1 + k |v| dt (stable for any k dt)",
)
@ti.func
def quadratic_drag(v, x, I, dt, dx, p: ti.template(), res: ti.template()):
    return v / (1.0 + p[0] * dt * _norm(v))


@register(
    "attractor",
    (Param("k", 1, (0.0,), "stiffness of the pull per unit mass (1/s²)", lower=0.0),
     Param("c", 3, (0.0, 0.0, 0.0), "the point pulled towards (m)")),
    doc="a pull towards a point that grows with the distance, a = -k (x - c) (a harmonic trap; scenes use it as "
    "physics outside the discovery catalogue)",
)
@ti.func
def attractor(v, x, I, dt, dx, p: ti.template(), res: ti.template()):
    return v - dt * p[0] * (x - _vec(p, 1))


# -- boundary conditions -----------------------------------------------------------------------------------------


@ti.func
def _contact(x, p: ti.template(), dx):
    """Unit normal of the plane n·x = d and the contact weight of a node at x: 1 at and below d − dx/2, 0 from
    d + dx/2 up, linear in between (a one-cell ramp, so the plane's offset and normal have gradients)."""
    n = _vec(p, 0)
    n = n / _norm(n)
    phi = n.dot(x) - p[3]
    return n, ti.min(ti.max(0.5 - phi / dx, 0.0), 1.0)


def _plane_params(mu: bool) -> tuple[Param, ...]:
    out = (
        Param("n", 3, (0.0, 0.0, 1.0), "plane normal, pointing out of the ground (normalised when used)"),
        Param("d", 1, (0.0,), "plane offset: the ground is n·x <= d (m)"),
    )
    return out + ((Param("mu", 1, (0.5,), "Coulomb friction coefficient", lower=0.0),) if mu else ())


@register(
    "ground",
    _plane_params(mu=True),
    order=BOUNDARY,
    doc="ground plane n·x = d with Coulomb friction: a node moving into it loses its normal velocity and mu times "
    "that much tangential speed (Stomakhin et al. 2013); mu = 0 is a slip boundary",
)
@ti.func
def ground(v, x, I, dt, dx, p: ti.template(), res: ti.template()):
    n, w = _contact(x, p, dx)
    vn = v.dot(n)
    vt = v - vn * n
    scale = ti.max(0.0, 1.0 + p[4] * vn / _norm(vt))
    vc = ti.select(vn < 0.0, vt * scale, v)
    return v + w * (vc - v)


@register(
    "floor",
    _plane_params(mu=True),
    order=PARTICLE,
    doc="ground plane n·x = d met by the particles themselves rather than by grid nodes, so that bodies touch it where "
    "their particles are, whatever the grid spacing (a grid-node plane stops a body up to about a cell and a half "
    "early): a particle that would cross the plane within the substep gets the normal velocity that puts it on the "
    "plane (one already below is pushed out), and loses mu times that change of tangential speed (Coulomb)",
)
@ti.func
def floor(v, x, dt, p: ti.template()):
    n = _vec(p, 0)
    n = n / _norm(n)
    vn = v.dot(n)
    push = ti.max((p[3] - n.dot(x)) / dt - vn, 0.0)  # the normal velocity change that keeps it out of the plane
    vt = v - vn * n
    scale = ti.max(0.0, 1.0 - p[4] * push / _norm(vt))
    return scale * vt + (vn + push) * n


@register(
    "ground_sticky",
    _plane_params(mu=False),
    order=BOUNDARY,
    doc="sticky ground plane n·x = d: nodes in contact stop (v = 0)",
)
@ti.func
def ground_sticky(v, x, I, dt, dx, p: ti.template(), res: ti.template()):
    _, w = _contact(x, p, dx)
    return (1.0 - w) * v


@register("walls", order=BOUNDARY, doc="domain boundary: zero the velocity component into the wall in the wall band")
@ti.func
def walls(v, x, I, dt, dx, p: ti.template(), res: ti.template()):
    # Element-wise masks, no branches and no writes to vector elements: both make Taichi's autodiff load locals
    # before they are stored (compile warnings in grid_update.grad).
    into = ((I < WALL_BAND) & (v < 0.0)) | ((I >= ti.Vector(res) - WALL_BAND) & (v > 0.0))
    return ti.select(into, ti.Vector.zero(float, 3), v)


# -- material terms ----------------------------------------------------------------------------------------------


@register(
    "plasticity",
    (Param("yield_stress", 1, (1.0e3,), "von Mises yield stress (Pa)", lower=0.0),),
    order=PLASTIC,
    doc="von Mises plasticity: with F = R S (polar), the deviatoric stretch S − tr(S)/3 I is scaled back so the "
    "equivalent stress sqrt(3/2)·2mu·|dev S| stays at or below the yield stress; the rest is permanent deformation",
)
@ti.func
def plasticity(F, mu, lam, p: ti.template()):
    R = polar_rotation(F)
    S = R.transpose() @ F
    S = 0.5 * (S + S.transpose())
    I = ti.Matrix.identity(float, 3)
    m = S.trace() / 3.0
    D = S - m * I
    q = ti.sqrt(1.5) * 2.0 * mu * ti.sqrt((D * D).sum() + EPS * EPS)
    scale = ti.min(1.0, p[0] / q)
    return R @ (m * I + scale * D)


def _viscous_dt(values: dict, dx: float, rho_min: float) -> float:
    eta = float(values["eta"][0])
    # Explicit viscosity is a diffusion of momentum with diffusivity eta/rho: dt <= dx² rho / (6 eta) in 3D.
    return math.inf if eta <= 0 else dx * dx * rho_min / (6.0 * eta)


@register(
    "damping",
    (Param("eta", 1, (0.0,), "viscosity (Pa·s)", lower=0.0),),
    order=STRESS,
    doc="material damping (Kelvin–Voigt viscosity): Cauchy stress 2·eta·sym(∇v) added to the elastic stress; it "
    "damps internal motion (wobble) and leaves rigid motion alone",
    dt_limit=_viscous_dt,
)
@ti.func
def damping(F, C, mu, lam, p: ti.template()):
    return (p[0] * F.determinant()) * (C + C.transpose())


class Term:
    """One chosen effect: its definition and its parameter values (a host-side vector, packed in parameter order)."""

    def __init__(self, definition: EffectDef, values: dict[str, tuple[float, ...]]):
        self.definition = definition
        self.values = np.zeros(definition.size)
        for prm in definition.params:
            off = definition.offset(prm.name)
            self.values[off : off + prm.size] = values.get(prm.name, prm.default)

    @property
    def name(self) -> str:
        return self.definition.name


# Kernel-side state, shared per Taichi runtime. A kernel compiles once per distinct template argument and its
# compiled code names the fields it touches; fresh parameter fields for every Effects object would mean a fresh
# compile of every MPM kernel and gradient kernel (minutes) for every new simulator. So each registered effect has
# one parameter field per runtime (the bank), and each *set* of effect names one Stages object; an Effects object
# uploads its values into the bank before the kernels run.
_bank: dict[tuple[str, int], object] = {}
_stages: dict[tuple[tuple[str, ...], int], "Stages"] = {}
_owner: dict[str, tuple[int, int, int]] = {}  # effect name -> (uid, version, runtime) of the values in the bank
_uids = itertools.count()


def _param_field(name: str):
    key = (name, _ti.generation())
    if key not in _bank:
        for k in [k for k in _bank if k[1] != _ti.generation()]:
            del _bank[k]
        _bank[key] = ti.field(_ti.real(), shape=max(REGISTRY[name].size, 1), needs_grad=True)
    return _bank[key]


@ti.data_oriented
class Stages:
    """What the kernels see of a set of effects: per stage, the (definition, parameter field) pairs in order. Its
    ``ti.func`` methods apply every term of a stage in a ``ti.static`` loop (straight-line code)."""

    def __init__(self, names: tuple[str, ...]):
        defs = sorted((REGISTRY[n] for n in names), key=lambda d: d.order)
        self.grid_terms = [(d, _param_field(d.name)) for d in defs if d.order in GRID_STAGES]
        self.plastic_terms = [(d, _param_field(d.name)) for d in defs if d.order == PLASTIC]
        self.stress_terms = [(d, _param_field(d.name)) for d in defs if d.order == STRESS]
        self.particle_terms = [(d, _param_field(d.name)) for d in defs if d.order == PARTICLE]
        self.has_particle = bool(self.particle_terms)

    @ti.func
    def apply(self, v, x, I, dt, dx, res: ti.template()):
        out = v
        for k in ti.static(range(len(self.grid_terms))):
            out = self.grid_terms[k][0].func(out, x, I, dt, dx, self.grid_terms[k][1], res)
        return out

    @ti.func
    def project(self, F, mu, lam):
        out = F
        for k in ti.static(range(len(self.plastic_terms))):
            out = self.plastic_terms[k][0].func(out, mu, lam, self.plastic_terms[k][1])
        return out

    @ti.func
    def particle(self, v, x, dt):
        out = v
        for k in ti.static(range(len(self.particle_terms))):
            out = self.particle_terms[k][0].func(out, x, dt, self.particle_terms[k][1])
        return out

    @ti.func
    def stress(self, F, C, mu, lam):
        out = ti.Matrix.zero(float, 3, 3)
        for k in ti.static(range(len(self.stress_terms))):
            out += self.stress_terms[k][0].func(F, C, mu, lam, self.stress_terms[k][1])
        return out


def stages(names) -> Stages:
    """The shared kernel-side object for the set of effect ``names`` in the current Taichi runtime."""
    key = (tuple(sorted(names)), _ti.generation())
    if key not in _stages:
        for k in [k for k in _stages if k[1] != _ti.generation()]:
            del _stages[k]
        _stages[key] = Stages(key[0])
    return _stages[key]


class Effects:
    """The chosen terms (sorted by stage: forces, boundary conditions, plasticity, stress) and their values.

    Kernels take :attr:`kernel` (the shared :class:`Stages` of this set of names); call :meth:`upload` before
    running them, which writes this object's values into the runtime's parameter bank if another object's (or
    older values) are there. Adjoints of the parameters accumulate in the bank's gradient fields
    (:meth:`flat_grad`, :meth:`zero_grad`)."""

    def __init__(self, terms: list[Term]):
        self.terms = sorted(terms, key=lambda t: t.definition.order)
        self.kernel = stages([t.name for t in self.terms])
        self.uid = next(_uids)
        self.version = 0

    @classmethod
    def from_spec(cls, spec: str) -> "Effects":
        """Parse ``"name:param=v1,v2,...,param=...;name;..."``; every problem is one :class:`CausalGSError` line."""
        return cls([Term(REGISTRY[name], values) for name, values in parse_spec(spec)])

    def __reduce__(self):
        """Pickled as its spec, which round-trips every value exactly (the kernel and the bank are this process's)."""
        return Effects.from_spec, (self.spec(),)

    def upload(self) -> None:
        """Make the bank hold this object's values (a no-op when it already does)."""
        token = (self.uid, self.version, _ti.generation())
        for t in self.terms:
            if t.definition.size and _owner.get(t.name) != token:
                f = _param_field(t.name)
                f.from_numpy(t.values.astype(_ti.numpy_dtype()))
                _owner[t.name] = token

    def names(self) -> list[str]:
        return [t.name for t in self.terms]

    def term(self, name: str) -> Term:
        for t in self.terms:
            if t.name == name:
                return t
        raise CausalGSError(f"effect '{name}' is not active (active: {', '.join(self.names()) or 'none'})")

    def get(self, name: str, param: str) -> np.ndarray:
        """The current value of parameter ``param`` of effect ``name``."""
        t = self.term(name)
        off = t.definition.offset(param)
        return t.values[off : off + t.definition.param(param).size].copy()

    def values(self, name: str) -> dict[str, np.ndarray]:
        return {p.name: self.get(name, p.name) for p in self.term(name).definition.params}

    def set(self, name: str, **values) -> None:
        """Overwrite parameters of an active effect, e.g. ``set("gravity", g=(0, -9.8, 0))``."""
        t = self.term(name)
        new = t.values.copy()
        for key, val in values.items():
            off = t.definition.offset(key)
            prm = t.definition.param(key)
            new[off : off + prm.size] = _check_values(name, prm, np.atleast_1d(np.asarray(val, dtype=np.float64)))
        t.values = new
        self.version += 1

    # -- all parameters as one vector (the torch boundary's ``params``) ---------------------------------------------
    def param_names(self) -> list[str]:
        """``effect.param[i]`` for every entry of :meth:`flat`, in order."""
        out = []
        for t in self.terms:
            for p in t.definition.params:
                out += [f"{t.name}.{p.name}" + (f"[{i}]" if p.size > 1 else "") for i in range(p.size)]
        return out

    def flat(self) -> np.ndarray:
        """Every parameter of every term, concatenated in term order (parameterless terms contribute nothing)."""
        return np.concatenate([t.values for t in self.terms] + [np.zeros(0)])

    def set_flat(self, values) -> None:
        vals = np.asarray(values, dtype=np.float64).reshape(-1)
        if len(vals) != len(self.param_names()):
            raise CausalGSError(f"effect parameters: got {len(vals)} values, expected {len(self.param_names())} "
                                f"({', '.join(self.param_names()) or 'none'})")  # fmt: skip
        off = 0
        for t in self.terms:
            d = t.definition
            self.set(t.name, **{p.name: vals[off + d.offset(p.name) : off + d.offset(p.name) + p.size]
                                for p in d.params})  # fmt: skip
            off += d.size

    def flat_grad(self) -> np.ndarray:
        parts = [_param_field(t.name).grad.to_numpy()[: t.definition.size].astype(np.float64) for t in self.terms]
        return np.concatenate([*parts, np.zeros(0)])

    def zero_grad(self) -> None:
        for t in self.terms:
            _param_field(t.name).grad.fill(0)

    def dt_limit(self, dx: float, rho_min: float) -> float:
        """The smallest stable substep any term imposes (inf if none does)."""
        out = math.inf
        for t in self.terms:
            if t.definition.dt_limit is not None:
                out = min(out, t.definition.dt_limit(self.values(t.name), dx, rho_min))
        return out

    def spec(self) -> str:
        """The canonical spec string of the current terms and values (round-trips through :meth:`from_spec`)."""
        parts = []
        for t in self.terms:
            vals = [f"{k}={','.join(repr(float(v)) for v in a)}" for k, a in self.values(t.name).items()]
            parts.append(t.name + (":" + ":".join(vals) if vals else ""))
        return ";".join(parts)


def _check_values(effect: str, prm: Param, vals: np.ndarray) -> tuple[float, ...]:
    if vals.shape != (prm.size,):
        raise CausalGSError(f"effect '{effect}': parameter '{prm.name}' takes {prm.size} number(s), got {vals.size}")
    if not np.isfinite(vals).all():
        raise CausalGSError(f"effect '{effect}': parameter '{prm.name}' must be finite")
    if prm.lower is not None and (vals < prm.lower).any():
        low = float(vals.min())
        raise CausalGSError(f"effect '{effect}': parameter '{prm.name}' = {low:g} must be >= {prm.lower:g}")
    return tuple(float(v) for v in vals)


def parse_spec(spec: str) -> list[tuple[str, dict[str, tuple[float, ...]]]]:
    """``"gravity:g=0,0,-9.8;walls"`` → ``[("gravity", {"g": (0, 0, -9.8)}), ("walls", {})]``.

    Parameters of one effect are separated by ``:`` (``name:a=1:b=2,3``); terms by ``;``. Empty spec: no effects.
    """
    out, seen = [], set()
    for raw in (spec or "").split(";"):
        raw = raw.strip()
        if not raw:
            continue
        name, *assigns = [s.strip() for s in raw.split(":")]
        if name not in REGISTRY:
            raise CausalGSError(f"unknown effect '{name}' (effects: {', '.join(sorted(REGISTRY))})")
        if name in seen:
            raise CausalGSError(f"effect '{name}' appears twice in the spec '{spec}'")
        seen.add(name)
        d = REGISTRY[name]
        values = {}
        for a in assigns:
            key, eq, val = a.partition("=")
            key = key.strip()
            if not eq:
                raise CausalGSError(f"effect '{name}': expected param=value, got '{a}'")
            prm = d.param(key)  # raises for an unknown parameter
            try:
                nums = np.array([float(s) for s in val.split(",")], dtype=np.float64)
            except ValueError:
                raise CausalGSError(f"effect '{name}': parameter '{key}' value '{val}' is not a number list") from None
            values[key] = _check_values(name, prm, nums)
        out.append((name, values))
    return out
