"""External effects: a registry of named, parameterised terms of the MPM grid update.

Each effect is a ``ti.func`` ``f(v, x, I, dt, p, res) -> v`` applied to the velocity ``v`` of grid node ``I`` (integer
index) at world position ``x`` after the momentum division, with ``p`` the effect's parameter field and ``res`` the
static grid shape. An :class:`Effects` object holds the chosen terms; the grid-update kernel receives it as a static
argument and applies every term in a ``ti.static`` loop (no if-chain over effect names).

Parameters live in one small Taichi field per term (``needs_grad=True``: the checkpointed backward accumulates their
gradients), addressed by name: ``effects.get("gravity", "g")``, ``effects.set("gravity", g=(0, 0, -9.8))``.

Spec strings name the terms: ``"gravity:g=0,0,-9.8;walls;linear_drag:c=0.5"``; a parameter left out takes its
default. Forces are applied first, boundary conditions (``walls``) last, whatever the order in the spec.
"""

# No `from __future__ import annotations`: Taichi 1.7 reads kernel annotations as live objects.
from dataclasses import dataclass

import numpy as np

from causalgs import _ti
from causalgs._ti import ti
from causalgs.errors import CausalGSError

# Grid nodes this close to the domain boundary are wall nodes (mpm88 uses 3: the quadratic stencil reaches two nodes
# past a particle's cell, so a particle is stopped before its stencil leaves the grid).
WALL_BAND = 3

FORCE, BOUNDARY = 0, 1  # application order


@dataclass(frozen=True)
class Param:
    name: str
    size: int
    default: tuple[float, ...]
    doc: str = ""


@dataclass(frozen=True)
class EffectDef:
    """A registered effect: its grid-update ``func``, its parameters (packed in this order) and when it applies."""

    name: str
    func: object
    params: tuple[Param, ...]
    order: int
    doc: str

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


def register(name: str, params: tuple[Param, ...] = (), order: int = FORCE, doc: str = ""):
    """Decorator: register a ``ti.func`` ``f(v, x, I, dt, p, res) -> v`` as the effect ``name``."""

    def wrap(func):
        if name in REGISTRY:
            raise CausalGSError(f"effect '{name}' is registered twice")
        REGISTRY[name] = EffectDef(name, func, tuple(params), order, doc)
        return func

    return wrap


@register("gravity", (Param("g", 3, (0.0, 0.0, -9.8), "acceleration (m/s²)"),), doc="uniform acceleration: v += dt g")
@ti.func
def gravity(v, x, I, dt, p: ti.template(), res: ti.template()):
    return v + dt * ti.Vector([p[0], p[1], p[2]])


@register(
    "linear_drag",
    (Param("c", 1, (0.0,), "drag rate (1/s)"),),
    doc="a = -c v, integrated exactly over a substep: v *= exp(-c dt) (stable for any c dt)",
)
@ti.func
def linear_drag(v, x, I, dt, p: ti.template(), res: ti.template()):
    return v * ti.exp(-p[0] * dt)


@register("walls", order=BOUNDARY, doc="domain boundary: zero the velocity component into the wall in the wall band")
@ti.func
def walls(v, x, I, dt, p: ti.template(), res: ti.template()):
    # Element-wise masks, no branches and no writes to vector elements: both make Taichi's autodiff load locals
    # before they are stored (compile warnings in grid_update.grad).
    into = ((I < WALL_BAND) & (v < 0.0)) | ((I >= ti.Vector(res) - WALL_BAND) & (v > 0.0))
    return ti.select(into, ti.Vector.zero(float, 3), v)


class Term:
    """One chosen effect and its parameter field ``p`` (at least one entry, so parameterless terms compile too)."""

    def __init__(self, definition: EffectDef, values: dict[str, tuple[float, ...]]):
        self.definition = definition
        self.p = ti.field(_ti.real(), shape=max(definition.size, 1), needs_grad=True)
        flat = np.zeros(max(definition.size, 1))
        for prm in definition.params:
            off = definition.offset(prm.name)
            flat[off : off + prm.size] = values.get(prm.name, prm.default)
        self.p.from_numpy(flat.astype(_ti.numpy_dtype()))

    @property
    def name(self) -> str:
        return self.definition.name


@ti.data_oriented
class Effects:
    """The effects applied in the grid update, in application order (forces, then boundary conditions)."""

    def __init__(self, terms: list[Term]):
        self.terms = sorted(terms, key=lambda t: t.definition.order)

    @classmethod
    def from_spec(cls, spec: str) -> "Effects":
        """Parse ``"name:param=v1,v2,...,param=...;name;..."``; every problem is one :class:`CausalGSError` line."""
        return cls([Term(REGISTRY[name], values) for name, values in parse_spec(spec)])

    @ti.func
    def apply(self, v, x, I, dt, res: ti.template()):
        out = v
        for t in ti.static(self.terms):
            out = t.definition.func(out, x, I, dt, t.p, res)
        return out

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
        return t.p.to_numpy()[off : off + t.definition.param(param).size].astype(np.float64)

    def set(self, name: str, **values) -> None:
        """Overwrite parameters of an active effect, e.g. ``set("gravity", g=(0, -9.8, 0))``."""
        t = self.term(name)
        flat = t.p.to_numpy().astype(np.float64)
        for key, val in values.items():
            off = t.definition.offset(key)
            prm = t.definition.param(key)
            flat[off : off + prm.size] = _check_values(name, prm, np.atleast_1d(np.asarray(val, dtype=np.float64)))
        t.p.from_numpy(flat.astype(_ti.numpy_dtype()))

    def spec(self) -> str:
        """The canonical spec string of the current terms and values (round-trips through :meth:`from_spec`)."""
        parts = []
        for t in self.terms:
            vals = [
                f"{p.name}={','.join(repr(float(v)) for v in self.get(t.name, p.name))}" for p in t.definition.params
            ]
            parts.append(t.name + (":" + ":".join(vals) if vals else ""))
        return ";".join(parts)


def _check_values(effect: str, prm: Param, vals: np.ndarray) -> tuple[float, ...]:
    if vals.shape != (prm.size,):
        raise CausalGSError(f"effect '{effect}': parameter '{prm.name}' takes {prm.size} number(s), got {vals.size}")
    if not np.isfinite(vals).all():
        raise CausalGSError(f"effect '{effect}': parameter '{prm.name}' must be finite")
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
