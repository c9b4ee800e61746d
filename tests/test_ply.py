"""Point-cloud and 3DGS PLY round trips, and malformed files reported as one-line DataErrors naming the file."""

from __future__ import annotations

import numpy as np
import pytest
from plyfile import PlyData, PlyElement

from causalgs.errors import DataError
from causalgs.ply import (
    gaussian_ply_properties,
    read_gaussians_ply,
    read_points_ply,
    write_gaussians_ply,
    write_points_ply,
)


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


# ---------------------------------------------------------------------------------------------------------------------
# 3D Gaussian splats (INRIA 3DGS layout)
# ---------------------------------------------------------------------------------------------------------------------
def _gaussians(n: int = 12, n_sh: int = 16, seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {
        "means": rng.normal(size=(n, 3)).astype(np.float32),
        "quats": rng.normal(size=(n, 4)).astype(np.float32),
        "scales": rng.normal(-2.0, 0.5, size=(n, 3)).astype(np.float32),
        "opacities": rng.normal(size=n).astype(np.float32),
        "sh": rng.normal(size=(n, n_sh, 3)).astype(np.float32),
    }


def _header(path) -> list[str]:
    return path.read_bytes().split(b"end_header")[0].decode().splitlines()


@pytest.mark.parametrize("n_sh", [1, 4, 9, 16])
def test_gaussians_round_trip(tmp_path, n_sh):
    g = _gaussians(n_sh=n_sh)
    path = tmp_path / "sub" / "point_cloud.ply"
    write_gaussians_ply(path, **g)
    back = read_gaussians_ply(path)
    assert set(back) == set(g)
    for k, v in g.items():
        assert back[k].dtype == np.float32 and back[k].shape == v.shape, k
        np.testing.assert_array_equal(back[k], v, err_msg=k)
    assert [p.name for p in path.parent.iterdir()] == ["point_cloud.ply"]  # no temporary file left


def test_gaussians_header_is_the_inria_layout(tmp_path):
    g = _gaussians(n=3, n_sh=16)
    write_gaussians_ply(tmp_path / "g.ply", **g)
    header = _header(tmp_path / "g.ply")
    assert header[:3] == ["ply", "format binary_little_endian 1.0", "element vertex 3"]
    props = [line.split() for line in header if line.startswith("property")]
    assert all(p[1] == "float" for p in props)
    expected = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    expected += [f"f_rest_{i}" for i in range(45)]
    expected += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    assert [p[2] for p in props] == expected == gaussian_ply_properties(16)
    # Values sit where the reference implementation puts them: raw, rot_0 = w, f_rest channel-major, normals zero.
    v = PlyData.read(str(tmp_path / "g.ply"))["vertex"].data
    np.testing.assert_array_equal(v["nx"], 0.0)
    np.testing.assert_array_equal(v["rot_0"], g["quats"][:, 0])
    np.testing.assert_array_equal(v["opacity"], g["opacities"])
    np.testing.assert_array_equal(v["scale_2"], g["scales"][:, 2])
    np.testing.assert_array_equal(v["f_dc_1"], g["sh"][:, 0, 1])
    for k in (1, 5, 15):
        for c in range(3):
            np.testing.assert_array_equal(v[f"f_rest_{c * 15 + k - 1}"], g["sh"][:, k, c])


def test_degree_0_has_no_f_rest_and_reads_without_it(tmp_path):
    g = _gaussians(n=4, n_sh=1)
    write_gaussians_ply(tmp_path / "g.ply", **g)
    assert not any("f_rest" in line for line in _header(tmp_path / "g.ply"))
    assert read_gaussians_ply(tmp_path / "g.ply")["sh"].shape == (4, 1, 3)


def test_reads_files_from_other_tools(tmp_path):
    """Extra properties are ignored, doubles are accepted, normals are optional."""
    g = _gaussians(n=5, n_sh=4)
    write_gaussians_ply(tmp_path / "g.ply", **g)
    v = PlyData.read(str(tmp_path / "g.ply"))["vertex"].data
    fields = {k: v[k].astype(np.float64) for k in v.dtype.names if k not in ("nx", "ny", "nz")}
    fields["filter_3D"] = np.ones(5, dtype=np.float32)
    _write_raw(tmp_path / "other.ply", fields)
    back = read_gaussians_ply(tmp_path / "other.ply")
    for k, val in g.items():
        np.testing.assert_array_equal(back[k], val, err_msg=k)


def test_torch_tensors_are_accepted(tmp_path):
    torch = pytest.importorskip("torch")
    g = _gaussians(n=3, n_sh=4)
    write_gaussians_ply(tmp_path / "g.ply", **{k: torch.from_numpy(v).double().requires_grad_() for k, v in g.items()})
    np.testing.assert_array_equal(read_gaussians_ply(tmp_path / "g.ply")["sh"], g["sh"])


def test_write_gaussians_rejects_bad_arrays(tmp_path):
    g = _gaussians(n=3)
    with pytest.raises(ValueError, match="quats must be"):
        write_gaussians_ply(tmp_path / "g.ply", **{**g, "quats": g["quats"][:, :3]})
    with pytest.raises(ValueError, match="sh must be"):
        write_gaussians_ply(tmp_path / "g.ply", **{**g, "sh": g["sh"][:, :5]})
    bad = g["opacities"].copy()
    bad[1] = np.nan
    with pytest.raises(ValueError, match="opacities has non-finite"):
        write_gaussians_ply(tmp_path / "g.ply", **{**g, "opacities": bad})
    assert not (tmp_path / "g.ply").exists()


def _gs_fields(n_sh: int = 4) -> dict[str, np.ndarray]:
    """The properties of a small valid 3DGS PLY, to break one at a time."""
    g = _gaussians(n=3, n_sh=n_sh)
    return {
        **{k: g["means"][:, i] for i, k in enumerate("xyz")},
        **{f"f_dc_{c}": g["sh"][:, 0, c] for c in range(3)},
        **{f"f_rest_{i}": np.zeros(3, np.float32) for i in range(3 * (n_sh - 1))},
        "opacity": g["opacities"],
        **{f"scale_{i}": g["scales"][:, i] for i in range(3)},
        **{f"rot_{i}": g["quats"][:, i] for i in range(4)},
    }


def _gs_no_opacity(path):
    f = _gs_fields()
    del f["opacity"]
    _write_raw(path, f)


def _gs_point_cloud(path):
    write_points_ply(path, *_cloud(4))


def _gs_bad_rest_count(path):
    f = _gs_fields(n_sh=1)
    for i in range(5):
        f[f"f_rest_{i}"] = np.zeros(3, np.float32)
    _write_raw(path, f)


def _gs_rest_gap(path):
    f = _gs_fields(n_sh=4)
    f["f_rest_9"] = f.pop("f_rest_3")
    _write_raw(path, f)


def _gs_non_finite(path):
    f = _gs_fields()
    f["scale_1"] = np.array([0.0, 0.0, -np.inf], dtype=np.float32)
    _write_raw(path, f)


@pytest.mark.parametrize(
    ("make", "expected"),
    [
        (None, "not found"),
        (_not_ply, "not a readable PLY"),
        (_gs_point_cloud, "no 'f_dc_0'"),
        (_gs_no_opacity, "no 'opacity' property"),
        (_gs_bad_rest_count, "5 f_rest properties"),
        (_gs_rest_gap, "9 f_rest properties"),
        (_gs_non_finite, "'scale_1' has 1 non-finite"),
        (_no_vertex, "no 'vertex' element"),
    ],
    ids=["missing", "not-ply", "point-cloud", "no-opacity", "rest-count", "rest-gap", "non-finite", "no-vertex"],
)
def test_malformed_gaussian_files_raise_one_line_data_error(tmp_path, make, expected):
    path = tmp_path / "bad_splats.ply"
    if make is not None:
        make(path)
    with pytest.raises(DataError) as info:
        read_gaussians_ply(path)
    msg = str(info.value)
    assert "bad_splats.ply" in msg and expected in msg, msg
    assert "\n" not in msg
