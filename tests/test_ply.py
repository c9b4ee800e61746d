"""Point-cloud PLY round trips, and malformed files reported as one-line DataErrors naming the file."""

from __future__ import annotations

import numpy as np
import pytest
from plyfile import PlyData, PlyElement

from causalgs.errors import DataError
from causalgs.ply import read_points_ply, write_points_ply


def _cloud(n: int = 20, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    return rng.normal(size=(n, 3)).astype(np.float32), rng.uniform(size=(n, 3)).astype(np.float32)


def _write_raw(path, fields: dict[str, np.ndarray], name: str = "vertex") -> None:
    """Write a PLY with arbitrary properties straight through plyfile (to make files our writer never would)."""
    n = len(next(iter(fields.values())))
    data = np.empty(n, dtype=[(k, v.dtype.str) for k, v in fields.items()])
    for k, v in fields.items():
        data[k] = v
    PlyData([PlyElement.describe(data, name)], text=False, byte_order="<").write(str(path))


def test_round_trip_with_colours(tmp_path):
    xyz, rgb = _cloud()
    path = tmp_path / "sub" / "points.ply"
    write_points_ply(path, xyz, rgb)
    xyz2, rgb2 = read_points_ply(path)
    assert xyz2.dtype == np.float32 and rgb2.dtype == np.float32
    np.testing.assert_array_equal(xyz2, xyz)
    np.testing.assert_allclose(rgb2, rgb, atol=0.5 / 255 + 1e-7)
    assert [p.name for p in tmp_path.joinpath("sub").iterdir()] == ["points.ply"]  # no temporary file left


def test_round_trip_without_colours(tmp_path):
    xyz, _ = _cloud(5)
    write_points_ply(tmp_path / "p.ply", xyz)
    xyz2, rgb2 = read_points_ply(tmp_path / "p.ply")
    np.testing.assert_array_equal(xyz2, xyz)
    assert rgb2 is None


def test_format_is_binary_little_endian_float_xyz_uchar_rgb(tmp_path):
    xyz, rgb = _cloud(3)
    write_points_ply(tmp_path / "p.ply", xyz, (rgb * 255).astype(np.uint8))
    header = (tmp_path / "p.ply").read_bytes().split(b"end_header")[0].decode()
    assert "format binary_little_endian 1.0" in header
    assert "element vertex 3" in header
    for line in ("property float x", "property float z", "property uchar red", "property uchar blue"):
        assert line in header
    _, rgb2 = read_points_ply(tmp_path / "p.ply")
    np.testing.assert_array_equal(np.round(rgb2 * 255).astype(np.uint8), (rgb * 255).astype(np.uint8))


def test_reads_float_and_16_bit_colours(tmp_path):
    xyz = np.zeros(2, dtype=np.float64)
    red = np.array([0.25, 2.0], dtype=np.float32)
    _write_raw(tmp_path / "f.ply", {"x": xyz, "y": xyz, "z": xyz, "red": red, "green": 0 * red, "blue": 0 * red})
    _, rgb = read_points_ply(tmp_path / "f.ply")
    np.testing.assert_allclose(rgb[:, 0], [0.25, 1.0])  # clipped to [0, 1]
    u16 = np.array([65535, 0], dtype=np.uint16)
    _write_raw(tmp_path / "u.ply", {"x": xyz, "y": xyz, "z": xyz, "red": u16, "green": u16, "blue": u16})
    _, rgb = read_points_ply(tmp_path / "u.ply")
    np.testing.assert_allclose(rgb[:, 1], [1.0, 0.0])


def test_write_rejects_bad_arrays(tmp_path):
    with pytest.raises(ValueError, match="xyz must be"):
        write_points_ply(tmp_path / "p.ply", np.zeros((3, 2)))
    with pytest.raises(ValueError, match="non-finite"):
        write_points_ply(tmp_path / "p.ply", np.full((1, 3), np.nan))
    with pytest.raises(ValueError, match="rgb must be"):
        write_points_ply(tmp_path / "p.ply", np.zeros((3, 3)), np.zeros((2, 3)))
    assert not (tmp_path / "p.ply").exists()


def _not_ply(path):
    path.write_text("hello, this is not a PLY file\n")


def _truncated(path):
    write_points_ply(path, *_cloud(50))
    data = path.read_bytes()
    path.write_bytes(data[: len(data) - 40])


def _no_z(path):
    v = np.zeros(3, dtype=np.float32)
    _write_raw(path, {"x": v, "y": v})


def _non_finite(path):
    v = np.zeros(3, dtype=np.float32)
    _write_raw(path, {"x": v, "y": np.array([0, np.inf, 0], dtype=np.float32), "z": v})


def _no_vertex(path):
    v = np.zeros(3, dtype=np.float32)
    _write_raw(path, {"x": v, "y": v, "z": v}, name="face")


@pytest.mark.parametrize(
    ("make", "expected"),
    [
        (_not_ply, "not a readable PLY"),
        (_truncated, "not a readable PLY"),
        (_no_z, "no 'z' property"),
        (_non_finite, "vertex 1"),
        (_no_vertex, "no 'vertex' element"),
        (None, "not found"),
    ],
    ids=["not-ply", "truncated", "no-z", "non-finite", "no-vertex", "missing"],
)
def test_malformed_files_raise_one_line_data_error(tmp_path, make, expected):
    path = tmp_path / "bad_cloud.ply"
    if make is not None:
        make(path)
    with pytest.raises(DataError) as info:
        read_points_ply(path)
    msg = str(info.value)
    assert "bad_cloud.ply" in msg and expected in msg
    assert "\n" not in msg
