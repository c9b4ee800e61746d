"""The MPM background grid: its geometry and its Taichi fields.

Grid fields are not per-particle, so the simulator (not the ParticleStore) owns them. They are allocated once per
grid shape in their own SNode tree and kept across calls: :func:`grid_fields` returns the same fields for the same
shape (a new shape is a new set of fields and a new compile of every grid kernel).

P2G scatters into ``v_in`` (momentum) and ``m`` (mass); the grid update reads those and writes ``v_out``; G2P reads
``v_out``. No kernel reads a grid field and then overwrites it, which Taichi's autodiff requires. The grid is scratch
of one substep: the checkpointed backward recomputes it for each substep (as difftaichi's diffmpm does).
"""

# No `from __future__ import annotations`: Taichi 1.7 reads kernel annotations as live objects.
import math
from dataclasses import dataclass

from causalgs import _ti
from causalgs._ti import ti
from causalgs.errors import CausalGSError

N_STATS = 4  # see mpm.frame_stats


@dataclass(frozen=True)
class GridGeometry:
    """Node ``I`` sits at ``lo + I * dx``. ``shape`` nodes per axis cover the box [lo, hi] (the last cell may stick
    out past ``hi``). A particle is inside the grid while its stencil is: (x − lo)/dx ∈ [0.5, shape − 1.5)."""

    lo: tuple[float, float, float]
    dx: float
    shape: tuple[int, int, int]

    @classmethod
    def from_box(cls, lo, hi, res: int) -> "GridGeometry":
        """``res`` cells along the longest axis of the box; the other axes get the cells that cover them."""
        lo = tuple(float(a) for a in lo)
        hi = tuple(float(a) for a in hi)
        if len(lo) != 3 or len(hi) != 3 or not all(math.isfinite(a) for a in lo + hi):
            raise CausalGSError(f"domain bounds lo={lo}, hi={hi} must be three finite numbers each")
        ext = [h - a for a, h in zip(lo, hi, strict=True)]
        if min(ext) <= 0:
            raise CausalGSError(f"domain hi={hi} must exceed lo={lo} on every axis")
        if res < 4:
            raise CausalGSError(f"grid resolution {res} must be at least 4 cells")
        dx = max(ext) / res
        shape = tuple(max(math.ceil(e / dx - 1e-9), 4) + 1 for e in ext)
        return cls(lo, dx, shape)

    @property
    def inv_dx(self) -> float:
        return 1.0 / self.dx


class GridFields:
    """``v_in`` (momentum, then velocity numerator), ``m`` (mass), ``v_out`` (updated velocity), all with adjoints,
    ``box`` (the nodes the particles reach this substep) and ``stats`` (frame diagnostics)."""

    def __init__(self, shape: tuple[int, int, int]):
        real = _ti.real()
        fb = ti.FieldsBuilder()
        self.v_in = ti.Vector.field(3, real, needs_grad=True)
        self.m = ti.field(real, needs_grad=True)
        self.v_out = ti.Vector.field(3, real, needs_grad=True)
        fb.dense(ti.ijk, shape).place(self.v_in, self.m, self.v_out)
        self.stats = ti.field(real)
        fb.dense(ti.i, N_STATS).place(self.stats)
        self.box = ti.field(ti.i32)
        fb.dense(ti.i, 6).place(self.box)
        # The grid's origin ``lo`` as a field, read by the kernels as a template: a vector *argument* costs ~65 µs
        # per launch in Taichi 1.7 (a scalar ~5 µs), several times per substep.
        self.lo = ti.Vector.field(3, real)
        fb.dense(ti.i, 1).place(self.lo)
        fb.lazy_grad()
        self.tree = fb.finalize()
        self.shape = tuple(shape)
        self.generation = _ti.generation()
        self._lo: tuple[float, float, float] | None = None

    def origin(self, lo: tuple[float, float, float]):
        """The ``lo`` field holding ``lo`` (written only when it changes: the fields of one shape are shared by
        every simulator of that shape, so each sets its own origin before its kernels run)."""
        if self._lo != lo:
            self.lo[0] = ti.Vector([float(a) for a in lo])
            self._lo = tuple(lo)
        return self.lo


_cache: dict[tuple, GridFields] = {}


def grid_fields(shape: tuple[int, int, int]) -> GridFields:
    """The grid fields for ``shape`` at the current precision, allocated on first use and kept afterwards."""
    key = (tuple(shape), _ti.generation())
    if key not in _cache:
        for k in [k for k in _cache if k[1] != _ti.generation()]:
            del _cache[k]  # fields of a Taichi runtime that was reset
        _cache[key] = GridFields(shape)
    return _cache[key]
