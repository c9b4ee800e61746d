"""The ParticleStore: the single owner of every per-particle Taichi field.

Every Gaussian of the scene is also an MPM particle, so the rasterizer and the simulator read and write the same rows.
The store allocates all per-particle fields together, keeps their rows aligned through growth, pruning, cloning and
reordering, and is the only way particle data enters or leaves Taichi.

Capacity and count. Fields have a fixed *capacity* (a power of two, at least ``MIN_CAPACITY``) and the store a runtime
*count* ``n``; kernels loop over ``range(n)``. Taichi compiles a kernel per field shape, so every kernel compiles once
per capacity bucket, not once per particle count (a gradient kernel of the simulator takes minutes to compile cold).
Growing past the capacity reallocates every field in the next bucket, copies the rows over and increments
:attr:`ParticleStore.version`, which is how users of the store know their kernels see new fields.

Parameters are stored raw, as gsplat does: log-scales, logit-opacities, unnormalised quaternions (w, x, y, z); they are
activated where they are used.

Fields (``FieldSpec.elem`` is the element shape, ``FieldSpec.per_row`` extra axes of a row):

========== ========== ============================================================================
name       shape      meaning
========== ========== ============================================================================
x          [N, 3]     position (world)
scale_raw  [N, 3]     log of the Gaussian's axis scales
quat       [N, 4]     rotation quaternion, w x y z, unnormalised
opacity_raw [N]       logit of opacity
sh         [N, S, 3]  spherical-harmonics colour coefficients, S = (degree + 1)²; sh[:, 0] is the DC term
v          [N, 3]     velocity
F          [N, 3, 3]  deformation gradient (identity at rest)
C          [N, 3, 3]  APIC affine velocity matrix
mass       [N]        particle mass
vol        [N]        particle volume at rest
E          [N]        Young's modulus (Pa)
nu         [N]        Poisson ratio
density    [N]        rest density (kg/m³)
obj_id     [N]        object or cluster id (int32; -1 = unassigned)
========== ========== ============================================================================
"""

# No `from __future__ import annotations`: Taichi 1.7 reads kernel annotations as live objects.

import json
import math
import os
from collections.abc import Iterable, Mapping
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from causalgs import _ti
from causalgs._ti import ti
from causalgs.errors import CausalGSError, DataError

MIN_CAPACITY = 1024
FORMAT_VERSION = 1


@dataclass(frozen=True)
class FieldSpec:
    """How one per-particle field is laid out.

    ``elem``: element shape: () scalar, (k,) vector, (k, k) matrix. ``per_row``: extra axes of a row (e.g. (16,) SH
    coefficients). ``dtype``: "real" (the runtime precision) or "i32". ``fill``: value of rows nobody wrote yet; a
    number, or "identity" for square matrices, or a tuple for vectors. ``grad``: allocate an adjoint field (Taichi's
    ``needs_grad``; only possible for real fields).
    """

    name: str
    elem: tuple[int, ...] = ()
    per_row: tuple[int, ...] = ()
    dtype: str = "real"
    fill: float | str | tuple[float, ...] = 0.0
    grad: bool = True
    doc: str = ""

    def row_shape(self) -> tuple[int, ...]:
        """Shape of one row as a torch/numpy array: per-row axes, then the element shape."""
        return tuple(self.per_row) + tuple(self.elem)

    def fill_array(self) -> np.ndarray:
        """The fill value broadcast to :meth:`row_shape`."""
        if self.fill == "identity":
            if len(self.elem) != 2 or self.elem[0] != self.elem[1]:
                raise ValueError(f"field '{self.name}': 'identity' fill needs a square matrix element")
            val = np.eye(self.elem[0])
        else:
            val = np.asarray(self.fill, dtype=np.float64)
        return np.broadcast_to(val, self.row_shape())


def default_specs(sh_degree: int = 3) -> tuple[FieldSpec, ...]:
    """The standard fields shared by the rasterizer and the simulator (see the module docstring)."""
    n_sh = (sh_degree + 1) ** 2
    return (
        FieldSpec("x", (3,), doc="position (world)"),
        FieldSpec("scale_raw", (3,), fill=math.log(0.01), doc="log of the Gaussian's axis scales"),
        FieldSpec("quat", (4,), fill=(1.0, 0.0, 0.0, 0.0), doc="rotation quaternion w x y z, unnormalised"),
        FieldSpec("opacity_raw", (), doc="logit of opacity"),
        # A (S, 3) matrix per row rather than S vec3 rows: copies and kernels then loop over particles only.
        FieldSpec("sh", (n_sh, 3), doc="SH colour coefficients; sh[:, 0] is the DC term"),
        FieldSpec("v", (3,), doc="velocity"),
        FieldSpec("F", (3, 3), fill="identity", doc="deformation gradient"),
        FieldSpec("C", (3, 3), doc="APIC affine velocity matrix"),
        FieldSpec("mass", (), doc="particle mass"),
        FieldSpec("vol", (), doc="particle volume at rest"),
        FieldSpec("E", (), fill=1.0e5, doc="Young's modulus (Pa)"),
        FieldSpec("nu", (), fill=0.3, doc="Poisson ratio"),
        FieldSpec("density", (), fill=1.0e3, doc="rest density (kg/m^3)"),
        FieldSpec("obj_id", (), dtype="i32", fill=-1, grad=False, doc="object or cluster id (-1 = unassigned)"),
    )


def bucket_capacity(n: int) -> int:
    """The capacity bucket that holds ``n`` rows: the next power of two, at least :data:`MIN_CAPACITY`."""
    return max(MIN_CAPACITY, 1 << max(0, int(n) - 1).bit_length())


# ---------------------------------------------------------------------------------------------------------------------
# Copy kernels between a field's rows [start, start + count) and an external array [count, *per_row, *elem].
# ``es`` is the static element shape; a kernel compiles once per field (and so once per capacity bucket).
# ---------------------------------------------------------------------------------------------------------------------
@ti.kernel
def _rows_to_array(f: ti.template(), es: ti.template(), arr: ti.types.ndarray(), start: ti.i32, count: ti.i32):
    for I in ti.grouped(ti.ndrange(count, *f.shape[1:])):
        J = I
        J[0] += start
        if ti.static(len(es) == 0):
            arr[I] = f[J]
        elif ti.static(len(es) == 1):
            for a in ti.static(range(es[0])):
                arr[I, a] = f[J][a]
        else:
            for a, b in ti.static(ti.ndrange(es[0], es[1])):
                arr[I, a, b] = f[J][a, b]


@ti.kernel
def _array_to_rows(f: ti.template(), es: ti.template(), arr: ti.types.ndarray(), start: ti.i32, count: ti.i32):
    for I in ti.grouped(ti.ndrange(count, *f.shape[1:])):
        J = I
        J[0] += start
        if ti.static(len(es) == 0):
            f[J] = arr[I]
        elif ti.static(len(es) == 1):
            for a in ti.static(range(es[0])):
                f[J][a] = arr[I, a]
        else:
            for a, b in ti.static(ti.ndrange(es[0], es[1])):
                f[J][a, b] = arr[I, a, b]


@ti.kernel
def _slot_to_array(f: ti.template(), es: ti.template(), arr: ti.types.ndarray(), slot: ti.i32, start: ti.i32,
                   count: ti.i32):  # fmt: skip
    for p in range(count):
        if ti.static(len(es) == 0):
            arr[p] = f[p + start, slot]
        elif ti.static(len(es) == 1):
            for a in ti.static(range(es[0])):
                arr[p, a] = f[p + start, slot][a]
        else:
            for a, b in ti.static(ti.ndrange(es[0], es[1])):
                arr[p, a, b] = f[p + start, slot][a, b]


@ti.kernel
def _array_to_slot(f: ti.template(), es: ti.template(), arr: ti.types.ndarray(), slot: ti.i32, start: ti.i32,
                   count: ti.i32):  # fmt: skip
    for p in range(count):
        if ti.static(len(es) == 0):
            f[p + start, slot] = arr[p]
        elif ti.static(len(es) == 1):
            for a in ti.static(range(es[0])):
                f[p + start, slot][a] = arr[p, a]
        else:
            for a, b in ti.static(ti.ndrange(es[0], es[1])):
                f[p + start, slot][a, b] = arr[p, a, b]


@ti.kernel
def _zero_rows(f: ti.template(), es: ti.template(), count: ti.i32):
    for I in ti.grouped(ti.ndrange(count, *f.shape[1:])):
        if ti.static(len(es) == 0):
            f[I] = 0
        elif ti.static(len(es) == 1):
            f[I] = ti.Vector.zero(f.dtype, es[0])
        else:
            f[I] = ti.Matrix.zero(f.dtype, es[0], es[1])


class ParticleStore:
    """Fixed-capacity Taichi fields for ``n`` particles, one row per particle, all rows aligned.

    Create it after :func:`causalgs._ti.init`. Fields are reached as attributes (``store.x``, ``store.F``) or with
    :meth:`field`; pass them to kernels as ``ti.template()`` arguments together with ``store.n``.
    """

    def __init__(self, capacity: int = 0, *, sh_degree: int = 3, extra: Iterable[FieldSpec] = ()):
        if not 0 <= sh_degree <= 3:
            raise CausalGSError(f"sh_degree = {sh_degree} must be between 0 and 3")
        specs = list(default_specs(sh_degree)) + list(extra)
        names = [s.name for s in specs]
        dup = {nm for nm in names if names.count(nm) > 1}
        if dup:
            raise CausalGSError(f"duplicate particle field name(s): {', '.join(sorted(dup))}")
        self._validate_specs(specs)
        self.sh_degree = sh_degree
        self.specs: dict[str, FieldSpec] = {s.name: s for s in specs}
        self.version = 0
        self._n = 0
        self._fields: dict[str, object] = {}
        self._tree = None
        self._allocate(bucket_capacity(capacity))

    @staticmethod
    def _validate_specs(specs: list[FieldSpec]) -> None:
        for s in specs:
            if s.dtype not in ("real", "i32"):
                raise CausalGSError(f"field '{s.name}': dtype '{s.dtype}' must be 'real' or 'i32'")
            if s.grad and s.dtype != "real":
                raise CausalGSError(f"field '{s.name}': only real fields can have gradients")
            if (
                len(s.elem) > 2
                or len(s.per_row) > 1
                or (len(s.elem) == 2 and s.fill == "identity" and s.elem[0] != s.elem[1])
            ):
                raise CausalGSError(f"field '{s.name}': at most a matrix element and one per-row axis")

    # -- allocation ---------------------------------------------------------------------------------------------
    def _allocate(self, capacity: int) -> None:
        """Allocate every field at ``capacity`` in one SNode tree (released as a whole on the next reallocation)."""
        real = _ti.real()
        fb = ti.FieldsBuilder()
        fields, groups = {}, {}
        for s in self.specs.values():
            dt = real if s.dtype == "real" else ti.i32
            if len(s.elem) == 0:
                f = ti.field(dt, needs_grad=s.grad)
            elif len(s.elem) == 1:
                f = ti.Vector.field(s.elem[0], dt, needs_grad=s.grad)
            else:
                f = ti.Matrix.field(s.elem[0], s.elem[1], dt, needs_grad=s.grad)
            fields[s.name] = f
            groups.setdefault(tuple(s.per_row), []).append(f)
        for per_row, fs in groups.items():
            axes = ti.ij if per_row else ti.i
            fb.dense(axes, (capacity, *per_row) if per_row else capacity).place(*fs)
        fb.lazy_grad()
        tree = fb.finalize()
        if self._tree is not None:
            self._tree.destroy()
        self._tree, self._fields, self._capacity = tree, fields, capacity
        self._generation = _ti.generation()
        self.version += 1
        for name, s in self.specs.items():
            if np.any(s.fill_array() != 0):  # a new SNode tree is zeroed already
                self._fill_rows(name, 0, capacity)

    def _check_alive(self) -> None:
        if self._generation != _ti.generation():
            raise CausalGSError("this ParticleStore was allocated before Taichi was re-initialised; create a new one")

    # -- basic properties ---------------------------------------------------------------------------------------
    @property
    def n(self) -> int:
        """Number of particles in use (rows [0, n))."""
        return self._n

    def __len__(self) -> int:
        return self._n

    @property
    def capacity(self) -> int:
        return self._capacity

    @property
    def names(self) -> list[str]:
        return list(self.specs)

    def field(self, name: str):
        """The Taichi field ``name`` (valid until the next reallocation, see :attr:`version`)."""
        self._check_alive()
        try:
            return self._fields[name]
        except KeyError:
            raise CausalGSError(f"no particle field '{name}' (fields: {', '.join(self.specs)})") from None

    def __getattr__(self, name: str):
        fields = self.__dict__.get("_fields")
        if fields is not None and name in fields:
            return self.field(name)
        raise AttributeError(name)

    def __repr__(self) -> str:
        return f"ParticleStore(n={self._n}, capacity={self._capacity}, sh_degree={self.sh_degree})"

    def add_fields(self, specs: Iterable[FieldSpec]) -> bool:
        """Register fields a subsystem needs (e.g. the rasterizer's projected 2D means); idempotent.

        New fields take their fill value in every row; existing rows of every field are kept. Adding a field
        reallocates the store (a new :attr:`version`), so subsystems register theirs once, before their first
        kernel call. Returns whether anything was added. A name already registered with another layout is an error.
        """
        self._check_alive()
        new = []
        for s in specs:
            old = self.specs.get(s.name)
            if old is None:
                new.append(s)
            elif (old.elem, old.per_row, old.dtype, old.grad) != (s.elem, s.per_row, s.dtype, s.grad):
                raise CausalGSError(f"particle field '{s.name}' is already registered with another layout")
        if not new:
            return False
        keep = {name: self.to_torch(name) for name in self.specs}
        before = dict(self.specs)
        try:
            self.specs.update({s.name: s for s in new})
            self._validate_specs(list(self.specs.values()))
        except CausalGSError:
            self.specs = before
            raise
        self._allocate(self._capacity)
        for name, t in keep.items():
            self._write(name, t, 0)
        for s in new:
            self._fill_rows(s.name, 0, self._n)
        return True

    # -- size changes -------------------------------------------------------------------------------------------
    def resize(self, n: int) -> None:
        """Set the count to ``n``; rows beyond the old count take their fill value; grows capacity if needed."""
        self._check_alive()
        n = int(n)
        if n < 0:
            raise CausalGSError(f"particle count {n} must be non-negative")
        if n > self._capacity:
            keep = {name: self.to_torch(name) for name in self.specs}
            self._allocate(bucket_capacity(n))
            for name, t in keep.items():
                self._write(name, t, 0)
        elif n < self._n:
            for name in self.specs:
                self._fill_rows(name, n, self._n)
        self._n = n

    def append(self, count: int | None = None, **values) -> slice:
        """Add rows; ``values`` maps field names to arrays [count, *row_shape]; other fields take their fill value.

        Returns the slice of the new rows.
        """
        if count is None:
            if not values:
                raise CausalGSError("append needs a count or field values")
            count = len(next(iter(values.values())))
        start = self._n
        self.resize(start + int(count))
        for name, val in values.items():
            self.from_torch(name, val, start=start)
        return slice(start, start + int(count))

    def gather(self, index) -> None:
        """Keep the rows ``index`` in that order: a bool mask [n] prunes, an int array reorders or clones rows.

        All fields move together, so rows stay aligned. Gradients are cleared.
        """
        self._check_alive()
        idx = torch.as_tensor(np.asarray(index) if not isinstance(index, torch.Tensor) else index)
        if idx.dtype == torch.bool:
            if idx.shape != (self._n,):
                raise CausalGSError(f"mask has shape {list(idx.shape)}, expected [{self._n}]")
            idx = torch.nonzero(idx).flatten()
        idx = idx.long().flatten()
        if len(idx) and (int(idx.min()) < 0 or int(idx.max()) >= self._n):
            raise CausalGSError(f"row index out of range [0, {self._n}): {int(idx.min())}..{int(idx.max())}")
        moved = {name: self.to_torch(name)[idx] for name in self.specs}
        self.resize(0)
        self.resize(len(idx))
        for name, t in moved.items():
            self._write(name, t, 0)
        self.zero_grad()

    def prune(self, keep) -> None:
        """Drop the rows where the bool mask ``keep`` [n] is False."""
        keep = torch.as_tensor(np.asarray(keep) if not isinstance(keep, torch.Tensor) else keep)
        if keep.dtype != torch.bool:
            raise CausalGSError("prune expects a boolean mask of the rows to keep")
        self.gather(keep)

    def reorder(self, perm) -> None:
        """Permute the rows: row i becomes old row ``perm[i]`` (e.g. a spatial sort for cache-friendly kernels)."""
        perm = torch.as_tensor(np.asarray(perm) if not isinstance(perm, torch.Tensor) else perm).long()
        if perm.shape != (self._n,) or not torch.equal(torch.sort(perm).values, torch.arange(self._n)):
            raise CausalGSError(f"reorder expects a permutation of range({self._n})")
        self.gather(perm)

    # -- copies to and from torch -------------------------------------------------------------------------------
    def _torch_dtype(self, name: str):
        return torch.int32 if self.specs[name].dtype == "i32" else _ti.torch_dtype()

    def to_torch(
        self, name: str, *, grad: bool = False, start: int = 0, stop: int | None = None, slot: int | None = None
    ) -> torch.Tensor:
        """A copy of rows [start, stop) (default: all ``n``) of field ``name`` (or its adjoint) as a CPU tensor.

        ``slot`` picks one index of the field's per-row axis (e.g. one substep of the simulator's state): the result
        is then [rows, *elem] instead of [rows, *per_row, *elem].
        """
        f = self.field(name)
        if grad:
            if not self.specs[name].grad:
                raise CausalGSError(f"field '{name}' has no gradient")
            f = f.grad
        stop = self._n if stop is None else stop
        if not 0 <= start <= stop <= self._n:
            raise CausalGSError(f"rows [{start}, {stop}) are outside [0, {self._n})")
        spec = self.specs[name]
        self._check_slot(name, slot)
        shape = spec.row_shape() if slot is None else tuple(spec.elem)
        out = torch.empty((stop - start, *shape), dtype=self._torch_dtype(name))
        if stop > start:
            if slot is None:
                _rows_to_array(f, spec.elem, out, start, stop - start)
            else:
                _slot_to_array(f, spec.elem, out, slot, start, stop - start)
        return out

    def _check_slot(self, name: str, slot: int | None) -> None:
        if slot is None:
            return
        per_row = self.specs[name].per_row
        if len(per_row) != 1 or not 0 <= slot < per_row[0]:
            raise CausalGSError(f"field '{name}' has no slot {slot} (per-row axis {list(per_row)})")

    def to_numpy(self, name: str, *, grad: bool = False) -> np.ndarray:
        return self.to_torch(name, grad=grad).numpy()

    def from_torch(self, name: str, values, *, start: int = 0, grad: bool = False, slot: int | None = None) -> None:
        """Write ``values`` [m, *row_shape] (torch or numpy) into rows [start, start + m) of ``name``; with
        ``slot``, values [m, *elem] go into that index of the per-row axis and the other indices are left alone.

        Raises a one-line error for a wrong shape, rows past ``n`` or non-finite values.
        """
        spec = self.specs.get(name)
        if spec is None:
            raise CausalGSError(f"no particle field '{name}' (fields: {', '.join(self.specs)})")
        self._check_slot(name, slot)
        expect = spec.row_shape() if slot is None else tuple(spec.elem)
        t = torch.as_tensor(values)
        if t.dim() >= 1 and t.shape[1:] != expect:
            raise CausalGSError(f"field '{name}': got rows of shape {list(t.shape[1:])}, expected {list(expect)}")
        if t.dim() == 0:
            raise CausalGSError(f"field '{name}': expected an array of rows, got a scalar")
        if start < 0 or start + len(t) > self._n:
            raise CausalGSError(f"field '{name}': rows [{start}, {start + len(t)}) are outside [0, {self._n})")
        if t.is_floating_point() and not bool(torch.isfinite(t).all()):
            bad = int(torch.nonzero(~torch.isfinite(t.reshape(len(t), -1)).all(dim=1))[0])
            raise CausalGSError(f"field '{name}': non-finite value in row {start + bad}")
        if grad and not spec.grad:
            raise CausalGSError(f"field '{name}' has no gradient")
        self._write(name, t, start, grad=grad, slot=slot)

    def _write(self, name: str, t: torch.Tensor, start: int, grad: bool = False, slot: int | None = None) -> None:
        spec = self.specs[name]
        f = self.field(name)
        f = f.grad if grad else f
        t = t.detach().to(device="cpu", dtype=self._torch_dtype(name)).contiguous()
        if len(t) and slot is None:
            _array_to_rows(f, spec.elem, t, start, len(t))
        elif len(t):
            _array_to_slot(f, spec.elem, t, slot, start, len(t))

    def _fill_rows(self, name: str, start: int, stop: int) -> None:
        if stop <= start:
            return
        spec = self.specs[name]
        fill = torch.tensor(np.array(spec.fill_array()), dtype=self._torch_dtype(name))
        self._write(name, fill.expand(stop - start, *fill.shape).contiguous(), start)

    def zero_grad(self, names: Iterable[str] | None = None) -> None:
        """Clear the adjoint fields of ``names`` (default: every field that has one) in rows [0, n)."""
        self._check_alive()
        for name in self.specs if names is None else names:
            if self.specs[name].grad and self._n:
                _zero_rows(self.field(name).grad, self.specs[name].elem, self._n)

    # -- persistence --------------------------------------------------------------------------------------------
    def state_dict(self) -> dict[str, np.ndarray]:
        """Every field's rows [0, n) as numpy arrays."""
        return {name: self.to_numpy(name) for name in self.specs}

    def load_state_dict(self, state: Mapping[str, np.ndarray]) -> None:
        """Replace the contents with ``state`` (all standard and extra fields, equal row counts)."""
        missing = [name for name in self.specs if name not in state]
        if missing:
            raise CausalGSError(f"particle state is missing field(s): {', '.join(missing)}")
        counts = {len(state[name]) for name in self.specs}
        if len(counts) != 1:
            raise CausalGSError(f"particle state has fields of different lengths: {sorted(counts)}")
        self.resize(0)
        self.resize(counts.pop())
        for name in self.specs:
            self.from_torch(name, np.asarray(state[name]))

    def save(self, path: str | os.PathLike) -> None:
        """Write the store to ``path`` (``.npz``) atomically, with the field specs needed to load it back."""
        from causalgs.io import write_npz

        meta = {
            "format": "causalgs.ParticleStore",
            "format_version": FORMAT_VERSION,
            "sh_degree": self.sh_degree,
            "n": self._n,
            "specs": [asdict(s) for s in self.specs.values()],
        }
        arrays = {f"field/{k}": v for k, v in self.state_dict().items()}
        write_npz(path, __meta__=np.array(json.dumps(meta)), **arrays)

    @classmethod
    def load(cls, path: str | os.PathLike) -> "ParticleStore":
        """Read a store written by :meth:`save`; every problem is one :class:`DataError` line naming the file."""
        path = Path(path)
        if not path.is_file():
            raise DataError(f"particle store file not found: {path}")
        try:
            with np.load(path, allow_pickle=False) as z:
                data = {k: z[k] for k in z.files}
        except (OSError, ValueError) as e:
            raise DataError(f"{path}: not a readable .npz file ({e})") from None
        if "__meta__" not in data:
            raise DataError(f"{path}: not a causalgs particle store (no __meta__ entry)")
        try:
            meta = json.loads(str(data["__meta__"]))
            specs = [
                FieldSpec(
                    **{
                        **s,
                        "elem": tuple(s["elem"]),
                        "per_row": tuple(s["per_row"]),
                        "fill": tuple(s["fill"]) if isinstance(s["fill"], list) else s["fill"],
                    }
                )
                for s in meta["specs"]
            ]
            sh_degree = int(meta["sh_degree"])
        except (ValueError, KeyError, TypeError) as e:
            raise DataError(f"{path}: malformed particle store metadata ({e})") from None
        if meta.get("format_version", 0) > FORMAT_VERSION:
            raise DataError(f"{path}: written by a newer causalgs (format {meta['format_version']})")
        standard = {s.name for s in default_specs(sh_degree)}
        extra = [s for s in specs if s.name not in standard]
        state = {}
        for s in specs:
            key = f"field/{s.name}"
            if key not in data:
                raise DataError(f"{path}: missing field '{s.name}'")
            state[s.name] = data[key]
        store = cls(len(state["x"]) if "x" in state else 0, sh_degree=sh_degree, extra=extra)
        for name, arr in state.items():
            expect = store.specs[name].row_shape()
            if arr.shape[1:] != expect:
                raise DataError(
                    f"{path}: field '{name}' has rows of shape {list(arr.shape[1:])}, expected {list(expect)}"
                )
        try:
            store.load_state_dict(state)
        except CausalGSError as e:
            raise DataError(f"{path}: {e}") from None
        return store
