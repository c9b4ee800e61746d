"""PLY files: point clouds (a dataset's ``points3d.ply`` initial cloud) and 3D Gaussian splats (the INRIA 3DGS layout).

Point clouds are written the way most tools expect them (binary little-endian, ``x/y/z`` float32 and
``red/green/blue`` uint8 on a ``vertex`` element) so that MeshLab, CloudCompare and the original 3DGS code read them.
The reader is more lenient about types (any numeric coordinates, 8/16-bit or float colours) because datasets come
from many exporters, but strict about content: a file that is not a PLY, has no coordinates or non-finite ones is a
one-line :class:`~causalgs.errors.DataError` naming the file, never a parser traceback.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from plyfile import PlyData, PlyElement

from causalgs.errors import DataError
from causalgs.io import atomic_path

__all__ = [
    "gaussian_ply_properties",
    "read_gaussians_ply",
    "read_points_ply",
    "write_gaussians_ply",
    "write_points_ply",
]

_XYZ = ("x", "y", "z")
_RGB = ("red", "green", "blue")


def _one_line(exc: BaseException) -> str:
    """An exception's text squeezed onto one line (parser messages sometimes span several)."""
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text if len(text) <= 160 else text[:157] + "..."


def write_points_ply(path: str | os.PathLike, xyz, rgb=None) -> None:
    """Write a point cloud as a binary little-endian PLY, atomically.

    ``xyz`` is [N, 3] (stored as float32). ``rgb`` is optional [N, 3]: floats in [0, 1] (rounded to 8 bits, values
    outside are clipped) or integers in [0, 255].
    """
    pts = np.asarray(xyz, dtype=np.float32)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"write_points_ply: xyz must be [N, 3], got shape {list(pts.shape)}")
    if not np.all(np.isfinite(pts)):
        raise ValueError("write_points_ply: xyz has non-finite values")
    fields = [(k, "<f4") for k in _XYZ]
    colors = None
    if rgb is not None:
        c = np.asarray(rgb)
        if c.shape != pts.shape:
            raise ValueError(f"write_points_ply: rgb must be [N, 3] like xyz {list(pts.shape)}, got {list(c.shape)}")
        if np.issubdtype(c.dtype, np.integer):
            if c.size and (c.min() < 0 or c.max() > 255):
                raise ValueError("write_points_ply: integer rgb must be in [0, 255]")
            colors = c.astype(np.uint8)
        else:
            c = np.nan_to_num(c.astype(np.float64), nan=0.0)
            colors = np.clip(np.round(c * 255.0), 0, 255).astype(np.uint8)
        fields += [(k, "u1") for k in _RGB]
    data = np.empty(len(pts), dtype=fields)
    for i, k in enumerate(_XYZ):
        data[k] = pts[:, i]
    if colors is not None:
        for i, k in enumerate(_RGB):
            data[k] = colors[:, i]
    ply = PlyData([PlyElement.describe(data, "vertex")], text=False, byte_order="<")
    with atomic_path(path) as tmp:
        ply.write(str(tmp))


def _read_vertices(path: Path, what: str):
    """The vertex records of a PLY file and their property names; one-line DataErrors for unreadable files."""
    if not path.is_file():
        raise DataError(f"{what} not found: {path}")
    try:
        # mmap=False: read everything now, so a truncated file fails here and the file is not kept open.
        ply = PlyData.read(str(path), mmap=False)
    except Exception as e:  # plyfile raises many kinds (PlyParseError, ValueError, EOFError...) for bad input
        raise DataError(f"{path}: not a readable PLY file ({_one_line(e)})") from None
    names = [el.name for el in ply.elements]
    if "vertex" not in names:
        raise DataError(f"{path}: no 'vertex' element (found: {', '.join(names) or 'none'})")
    vertex = ply["vertex"].data
    return vertex, vertex.dtype.names or ()


def read_points_ply(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray | None]:
    """Read a point cloud: ``xyz`` float32 [N, 3] and ``rgb`` float32 [N, 3] in [0, 1], or ``None`` without colours.

    Colours are taken from ``red/green/blue`` when all three exist: 8-bit values are divided by 255, 16-bit ones by
    65535, floats are used as they are (clipped to [0, 1]).
    """
    path = Path(path)
    vertex, props = _read_vertices(path, "point cloud")
    missing = [k for k in _XYZ if k not in props]
    if missing:
        raise DataError(f"{path}: vertex element has no '{missing[0]}' property (found: {', '.join(props) or 'none'})")
    try:
        xyz = np.stack([np.asarray(vertex[k], dtype=np.float32) for k in _XYZ], axis=-1).reshape(-1, 3)
    except (TypeError, ValueError):
        raise DataError(f"{path}: vertex coordinates x/y/z are not numbers") from None
    bad = ~np.all(np.isfinite(xyz), axis=1)
    if bad.any():
        first = int(np.argmax(bad))
        raise DataError(
            f"{path}: {int(bad.sum())} of {len(xyz)} vertices have non-finite coordinates "
            f"(first: vertex {first} = {xyz[first].tolist()})"
        )
    if not all(k in props for k in _RGB):
        return xyz, None
    try:
        raw = np.stack([np.asarray(vertex[k]) for k in _RGB], axis=-1).reshape(-1, 3)
        if raw.dtype == np.uint8:
            rgb = raw.astype(np.float32) / 255.0
        elif raw.dtype == np.uint16:
            rgb = raw.astype(np.float32) / 65535.0
        elif np.issubdtype(raw.dtype, np.integer):
            rgb = raw.astype(np.float32) / 255.0
        else:
            rgb = raw.astype(np.float32)
    except (TypeError, ValueError):
        raise DataError(f"{path}: vertex colours red/green/blue are not numbers") from None
    if not np.all(np.isfinite(rgb)):
        raise DataError(f"{path}: vertex colours have non-finite values")
    return xyz, np.clip(rgb, 0.0, 1.0).astype(np.float32)


# ---------------------------------------------------------------------------------------------------------------------
# 3D Gaussian splats in the INRIA 3DGS layout
# ---------------------------------------------------------------------------------------------------------------------
# The property order of the reference implementation (graphdeco-inria/gaussian-splatting), which the common viewers
# (SuperSplat, antimatter15/splat, the SIBR viewer) expect. ``f_rest_*`` sits between ``f_dc_2`` and ``opacity``.
_GS_HEAD = ("x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2")
_GS_TAIL = ("opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3")
_GS_REQUIRED = ("x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", *_GS_TAIL)
_SH_SIZES = (1, 4, 9, 16)  # (d + 1)^2 for SH degrees 0..3


def gaussian_ply_properties(n_sh: int) -> list[str]:
    """The vertex property names, in file order, of a 3DGS PLY with ``n_sh`` SH coefficients per channel."""
    if n_sh not in _SH_SIZES:
        raise ValueError(f"n_sh = {n_sh} must be one of {_SH_SIZES}")
    return [*_GS_HEAD, *(f"f_rest_{i}" for i in range(3 * (n_sh - 1))), *_GS_TAIL]


def write_gaussians_ply(path: str | os.PathLike, means, quats, scales, opacities, sh) -> None:
    """Write Gaussians as a standard 3DGS PLY (binary little-endian, float32 properties), atomically.

    ``means`` [N, 3]; ``quats`` [N, 4] (w, x, y, z; stored as given, not normalised); ``scales`` [N, 3] log-scales;
    ``opacities`` [N] logits; ``sh`` [N, S, 3] with S in {1, 4, 9, 16}. Raw values are stored, as the reference
    implementation does: ``scale_*`` are logs, ``opacity`` is a logit, ``rot_0`` is w. Normals are zero. ``f_rest``
    is channel-major: coefficient k ≥ 1 of channel c is ``f_rest_{c * (S - 1) + k - 1}``. Accepts numpy arrays or
    torch tensors (detached and moved to the CPU); raises ``ValueError`` for wrong shapes or non-finite values.
    """
    arrays = {}
    for name, value in (("means", means), ("quats", quats), ("scales", scales), ("opacities", opacities), ("sh", sh)):
        if hasattr(value, "detach"):  # a torch tensor
            value = value.detach().cpu().numpy()
        arrays[name] = np.asarray(value, dtype=np.float32)
    m = arrays["means"]
    if m.ndim != 2 or m.shape[1] != 3:
        raise ValueError(f"write_gaussians_ply: means must be [N, 3], got shape {list(m.shape)}")
    n = len(m)
    expected = {"quats": (n, 4), "scales": (n, 3), "opacities": (n,)}
    for name, shape in expected.items():
        if arrays[name].shape != shape:
            raise ValueError(f"write_gaussians_ply: {name} must be {list(shape)}, got shape {list(arrays[name].shape)}")
    s = arrays["sh"]
    if s.ndim != 3 or s.shape[0] != n or s.shape[2] != 3 or s.shape[1] not in _SH_SIZES:
        raise ValueError(f"write_gaussians_ply: sh must be [{n}, S, 3] with S in {_SH_SIZES}, got {list(s.shape)}")
    for name, a in arrays.items():
        if not np.all(np.isfinite(a)):
            raise ValueError(f"write_gaussians_ply: {name} has non-finite values")
    n_sh = s.shape[1]
    rest = s[:, 1:, :].transpose(0, 2, 1).reshape(n, 3 * (n_sh - 1))  # channel-major
    columns = np.concatenate(
        [m, np.zeros((n, 3), np.float32), s[:, 0, :], rest, arrays["opacities"][:, None], arrays["scales"],
         arrays["quats"]],
        axis=1,
    )  # fmt: skip
    names = gaussian_ply_properties(n_sh)
    data = np.empty(n, dtype=[(k, "<f4") for k in names])
    for i, k in enumerate(names):
        data[k] = columns[:, i]
    ply = PlyData([PlyElement.describe(data, "vertex")], text=False, byte_order="<")
    with atomic_path(path) as tmp:
        ply.write(str(tmp))


def read_gaussians_ply(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Read a 3DGS PLY: a dict of float32 arrays ``means`` [N, 3], ``quats`` [N, 4] (w, x, y, z), ``scales`` [N, 3]
    (log), ``opacities`` [N] (logit) and ``sh`` [N, S, 3].

    S is inferred from the ``f_rest_*`` properties (3 (S - 1) of them, none for degree 0); other properties
    (normals, extra attributes some tools add) are ignored. A missing file, a file that is not a PLY, a missing
    property, a wrong number of ``f_rest`` or non-finite values are a one-line :class:`DataError` naming the file.
    """
    path = Path(path)
    vertex, props = _read_vertices(path, "Gaussian PLY")
    missing = [k for k in _GS_REQUIRED if k not in props]
    if missing:
        raise DataError(
            f"{path}: not a 3D Gaussian splat PLY: vertex element has no {', '.join(repr(k) for k in missing[:4])}"
            f"{' ...' if len(missing) > 4 else ''} propert{'y' if len(missing) == 1 else 'ies'}"
        )
    rest_names = [k for k in props if k.startswith("f_rest_")]
    indices = sorted(int(k[7:]) for k in rest_names if k[7:].isdigit())
    n_rest = len(rest_names)
    if indices != list(range(n_rest)) or n_rest % 3 or (n_rest // 3 + 1) not in _SH_SIZES:
        raise DataError(
            f"{path}: {n_rest} f_rest properties; expected f_rest_0 .. f_rest_{{3 (S - 1) - 1}} for S in "
            f"{{1, 4, 9, 16}}, i.e. 0, 9, 24 or 45 of them"
        )
    n_sh = n_rest // 3 + 1
    try:
        columns = {k: np.asarray(vertex[k], dtype=np.float32) for k in (*_GS_REQUIRED, *rest_names)}
    except (TypeError, ValueError):
        raise DataError(f"{path}: vertex properties are not numbers") from None
    for k, v in columns.items():
        bad = ~np.isfinite(v)
        if bad.any():
            first = int(np.argmax(bad))
            raise DataError(
                f"{path}: property '{k}' has {int(bad.sum())} non-finite values of {len(v)} "
                f"(first: vertex {first} = {v[first]})"
            )
    n = len(vertex)

    def stack(keys):
        return np.stack([columns[k] for k in keys], axis=-1).reshape(n, len(keys))

    sh = np.empty((n, n_sh, 3), dtype=np.float32)
    sh[:, 0, :] = stack(("f_dc_0", "f_dc_1", "f_dc_2"))
    if n_sh > 1:
        rest = stack([f"f_rest_{i}" for i in range(n_rest)])
        sh[:, 1:, :] = rest.reshape(n, 3, n_sh - 1).transpose(0, 2, 1)
    return {
        "means": stack(("x", "y", "z")),
        "quats": stack(("rot_0", "rot_1", "rot_2", "rot_3")),
        "scales": stack(("scale_0", "scale_1", "scale_2")),
        "opacities": columns["opacity"].reshape(n).copy(),
        "sh": sh,
    }
