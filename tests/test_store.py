# No `from __future__ import annotations`: Taichi 1.7 reads kernel annotations as live objects.

import numpy as np
import pytest
import torch

from causalgs import _ti
from causalgs._ti import ti
from causalgs.errors import CausalGSError, DataError
from causalgs.store import MIN_CAPACITY, FieldSpec, ParticleStore, bucket_capacity


def _random_rows(store: ParticleStore, n: int, seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    rows = {}
    for name, spec in store.specs.items():
        shape = (n, *spec.row_shape())
        rows[name] = rng.integers(-5, 50, shape).astype(np.int32) if spec.dtype == "i32" else rng.normal(size=shape)
    return rows


@pytest.fixture
def store(ti64):
    s = ParticleStore(10)
    s.append(**_random_rows(s, 10))
    return s


def test_bucket_capacity():
    assert bucket_capacity(0) == MIN_CAPACITY
    assert bucket_capacity(MIN_CAPACITY) == MIN_CAPACITY
    assert bucket_capacity(MIN_CAPACITY + 1) == 2 * MIN_CAPACITY
    assert bucket_capacity(5000) == 8192


def test_round_trip_every_field(ti64):
    s = ParticleStore(7, sh_degree=2)
    rows = _random_rows(s, 7, seed=1)
    s.append(**rows)
    assert s.n == 7 and s.capacity == MIN_CAPACITY
    assert s.to_torch("sh").shape == (7, 9, 3)
    for name, val in rows.items():
        out = s.to_numpy(name)
        assert out.shape == val.shape, name
        np.testing.assert_array_equal(out, val, err_msg=name)
    assert s.to_torch("x").dtype == torch.float64
    assert s.to_torch("obj_id").dtype == torch.int32


def test_partial_rows_and_fill_values(ti64):
    s = ParticleStore()
    s.append(x=np.ones((3, 3)))
    np.testing.assert_array_equal(s.to_numpy("quat"), np.tile([1.0, 0, 0, 0], (3, 1)))
    np.testing.assert_array_equal(s.to_numpy("F"), np.tile(np.eye(3), (3, 1, 1)))
    np.testing.assert_array_equal(s.to_numpy("obj_id"), [-1, -1, -1])
    np.testing.assert_allclose(s.to_numpy("scale_raw"), np.log(0.01))
    s.from_torch("x", torch.full((1, 3), 7.0), start=1)
    np.testing.assert_array_equal(s.to_numpy("x")[:, 0], [1, 7, 1])
    np.testing.assert_array_equal(s.to_torch("x", start=1, stop=2).numpy(), [[7, 7, 7]])


def test_shrink_then_grow_refills_rows(store):
    store.resize(4)
    store.resize(6)
    np.testing.assert_array_equal(store.to_numpy("F")[4:], np.tile(np.eye(3), (2, 1, 1)))
    np.testing.assert_array_equal(store.to_numpy("x")[4:], 0)


def test_grow_past_capacity_keeps_rows(store):
    before = store.state_dict()
    version = store.version
    store.resize(5)  # within the bucket: same fields
    assert store.version == version
    store.resize(MIN_CAPACITY + 3)
    assert store.capacity == 2 * MIN_CAPACITY and store.version == version + 1
    for name, val in before.items():
        np.testing.assert_array_equal(store.to_numpy(name)[:5], val[:5], err_msg=name)
    np.testing.assert_array_equal(store.to_numpy("quat")[5:], np.tile([1.0, 0, 0, 0], (MIN_CAPACITY - 2, 1)))


def test_prune_keeps_rows_aligned(store):
    before = store.state_dict()
    keep = np.array([True, False, True, True, False, False, True, False, False, True])
    store.prune(keep)
    assert store.n == keep.sum()
    for name, val in before.items():
        np.testing.assert_array_equal(store.to_numpy(name), val[keep], err_msg=name)


def test_reorder_and_clone(store):
    before = store.state_dict()
    perm = np.random.default_rng(3).permutation(10)
    store.reorder(perm)
    for name, val in before.items():
        np.testing.assert_array_equal(store.to_numpy(name), val[perm], err_msg=name)
    store.gather(np.array([0, 0, 4]))  # densification clones rows
    assert store.n == 3
    np.testing.assert_array_equal(store.to_numpy("sh"), before["sh"][perm][[0, 0, 4]])
    with pytest.raises(CausalGSError, match="permutation"):
        store.reorder(np.array([0, 0, 1]))
    with pytest.raises(CausalGSError, match="out of range"):
        store.gather(np.array([5]))
    with pytest.raises(CausalGSError, match="boolean mask"):
        store.prune(np.array([0, 1, 2]))


def test_write_errors_name_field_and_value(store):
    with pytest.raises(CausalGSError, match=r"field 'x': got rows of shape \[4\], expected \[3\]"):
        store.from_torch("x", np.zeros((2, 4)))
    bad = np.zeros((3, 3, 3))
    bad[2, 1, 1] = np.nan
    with pytest.raises(CausalGSError, match=r"field 'F': non-finite value in row 2"):
        store.from_torch("F", bad)
    with pytest.raises(CausalGSError, match=r"outside \[0, 10\)"):
        store.from_torch("v", np.zeros((2, 3)), start=9)
    with pytest.raises(CausalGSError, match="no particle field 'colour'"):
        store.from_torch("colour", np.zeros((1, 3)))
    with pytest.raises(CausalGSError, match="has no gradient"):
        store.to_torch("obj_id", grad=True)


def test_gradients_reach_store_fields(store):
    """Taichi autodiff through the store's fields: d/dx sum(m |x|²) = 2 m x; d/dm = |x|²."""

    @ti.kernel
    def energy(x: ti.template(), m: ti.template(), out: ti.template(), n: ti.i32):
        for i in range(n):
            out[None] += m[i] * x[i].norm_sqr()

    out = ti.field(_ti.real(), shape=(), needs_grad=True)
    with ti.ad.Tape(loss=out):
        energy(store.x, store.mass, out, store.n)
    x, m = store.to_numpy("x"), store.to_numpy("mass")
    assert out[None] == pytest.approx(float((m * (x**2).sum(1)).sum()))
    np.testing.assert_allclose(store.to_numpy("x", grad=True), 2 * m[:, None] * x, rtol=1e-12)
    np.testing.assert_allclose(store.to_numpy("mass", grad=True), (x**2).sum(1), rtol=1e-12)
    store.from_torch("v", torch.ones(10, 3), grad=True)
    np.testing.assert_array_equal(store.to_numpy("v", grad=True), 1.0)
    store.zero_grad()
    assert not store.to_numpy("x", grad=True).any() and not store.to_numpy("v", grad=True).any()


def test_kernels_see_only_count_rows(store):
    @ti.kernel
    def count_rows(x: ti.template(), n: ti.i32) -> ti.i32:
        c = 0
        for i in range(n):
            if x[i][0] == x[i][0]:
                c += 1
        return c

    assert count_rows(store.x, store.n) == 10
    store.resize(3)
    assert count_rows(store.x, store.n) == 3


def test_extra_fields_and_save_load(tmp_path, ti64):
    extra = (
        FieldSpec("yield_stress", (), fill=1e4, doc="plastic yield stress"),
        FieldSpec("x_hist", (3,), per_row=(4,), doc="positions at 4 substeps (a per-row axis)"),
    )
    s = ParticleStore(5, sh_degree=1, extra=extra)
    rows = _random_rows(s, 5, seed=4)
    s.append(**rows)
    s.save(tmp_path / "p.npz")
    assert not list(tmp_path.glob(".*tmp"))  # atomic write leaves no temporary behind
    t = ParticleStore.load(tmp_path / "p.npz")
    assert t.n == 5 and t.sh_degree == 1 and "yield_stress" in t.specs
    assert t.to_torch("x_hist").shape == (5, 4, 3)
    for name, val in rows.items():
        np.testing.assert_array_equal(t.to_numpy(name), val, err_msg=name)
    # One index of the per-row axis in and out, the other indices untouched.
    t.from_torch("x_hist", np.full((5, 3), 7.0), slot=2)
    np.testing.assert_array_equal(t.to_torch("x_hist", slot=2).numpy(), 7.0)
    np.testing.assert_array_equal(t.to_numpy("x_hist")[:, [0, 1, 3]], rows["x_hist"][:, [0, 1, 3]])
    with pytest.raises(CausalGSError, match="has no slot 4"):
        t.to_torch("x_hist", slot=4)
    with pytest.raises(CausalGSError, match=r"expected \[3\]"):
        t.from_torch("x_hist", np.zeros((5, 4, 3)), slot=0)
    t.resize(6)
    assert t.to_numpy("yield_stress")[5] == 1e4


def test_load_errors(tmp_path, ti64):
    with pytest.raises(DataError, match="particle store file not found"):
        ParticleStore.load(tmp_path / "missing.npz")
    (tmp_path / "junk.npz").write_text("not a zip")
    with pytest.raises(DataError, match="junk.npz: not a readable .npz"):
        ParticleStore.load(tmp_path / "junk.npz")
    np.savez(tmp_path / "other.npz", a=np.zeros(3))
    with pytest.raises(DataError, match="not a causalgs particle store"):
        ParticleStore.load(tmp_path / "other.npz")
    s = ParticleStore()
    s.append(x=np.zeros((2, 3)))
    s.save(tmp_path / "p.npz")
    with np.load(tmp_path / "p.npz") as z:
        data = {k: z[k] for k in z.files if k != "field/F"}
    np.savez(tmp_path / "cut.npz", **data)
    with pytest.raises(DataError, match="cut.npz: missing field 'F'"):
        ParticleStore.load(tmp_path / "cut.npz")


def test_bad_specs(ti64):
    with pytest.raises(CausalGSError, match="duplicate"):
        ParticleStore(extra=(FieldSpec("x", (3,)),))
    with pytest.raises(CausalGSError, match="only real fields"):
        ParticleStore(extra=(FieldSpec("label", (), dtype="i32"),))
    with pytest.raises(CausalGSError, match="sh_degree"):
        ParticleStore(sh_degree=4)


def test_add_fields_keeps_rows(store):
    before = store.state_dict()
    version = store.version
    spec = FieldSpec("mean2d", (2,), fill=(-1.0, 2.0), doc="projected mean")
    assert store.add_fields([spec]) is True
    assert store.version == version + 1
    assert store.add_fields([spec]) is False  # idempotent
    for name, val in before.items():
        np.testing.assert_array_equal(store.to_numpy(name), val, err_msg=name)
    np.testing.assert_array_equal(store.to_numpy("mean2d"), np.tile([-1.0, 2.0], (10, 1)))
    with pytest.raises(CausalGSError, match="another layout"):
        store.add_fields([FieldSpec("mean2d", (3,))])
    with pytest.raises(CausalGSError, match="only real fields"):
        store.add_fields([FieldSpec("tile", (), dtype="i32")])
    assert "tile" not in store.specs
