"""PLY files: point clouds (a dataset's ``points3d.ply`` initial cloud).

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

__all__ = ["read_points_ply", "write_points_ply"]

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


def read_points_ply(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray | None]:
    """Read a point cloud: ``xyz`` float32 [N, 3] and ``rgb`` float32 [N, 3] in [0, 1], or ``None`` without colours.

    Colours are taken from ``red/green/blue`` when all three exist: 8-bit values are divided by 255, 16-bit ones by
    65535, floats are used as they are (clipped to [0, 1]).
    """
    path = Path(path)
    if not path.is_file():
        raise DataError(f"point cloud not found: {path}")
    try:
        # mmap=False: read everything now, so a truncated file fails here and the file is not kept open.
        ply = PlyData.read(str(path), mmap=False)
    except Exception as e:  # plyfile raises many kinds (PlyParseError, ValueError, EOFError...) for bad input
        raise DataError(f"{path}: not a readable PLY file ({_one_line(e)})") from None
    names = [el.name for el in ply.elements]
    if "vertex" not in names:
        raise DataError(f"{path}: no 'vertex' element (found: {', '.join(names) or 'none'})")
    vertex = ply["vertex"].data
    props = vertex.dtype.names or ()
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
