"""Atomic file output.

A run never leaves a half-written file where a good one was: everything is written to a temporary file in the target's
folder and moved into place with :func:`os.replace`, which is atomic on POSIX file systems.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import tempfile
from pathlib import Path

import numpy as np

from causalgs.errors import CausalGSError


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike):
    """Yield a temporary path beside ``path``; on success it replaces ``path``, on error it is removed."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    os.chmod(tmp, 0o666 & ~_umask())  # mkstemp creates 0600; outputs get the usual permissions
    try:
        yield Path(tmp)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def write_bytes(path: str | os.PathLike, data: bytes) -> None:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def write_text(path: str | os.PathLike, text: str) -> None:
    write_bytes(path, text.encode("utf-8"))


def write_json(path: str | os.PathLike, obj, indent: int = 2) -> None:
    """Deterministic JSON (insertion-ordered keys, fixed float repr) written atomically."""
    write_text(path, json.dumps(obj, indent=indent, allow_nan=False) + "\n")


def write_npz(path: str | os.PathLike, **arrays) -> None:
    """Uncompressed ``.npz`` written atomically; byte-identical for identical arrays."""
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    write_bytes(path, buf.getvalue())


def write_image(path: str | os.PathLike, image: np.ndarray) -> None:
    """Write an 8-bit image (RGB or RGBA order, [H, W], [H, W, 3] or [H, W, 4]) as PNG, atomically."""
    import cv2

    img = np.asarray(image)
    if img.dtype != np.uint8:
        raise TypeError(f"write_image expects uint8, got {img.dtype}")
    if img.ndim == 3 and img.shape[2] == 3:
        img = img[..., ::-1]
    elif img.ndim == 3 and img.shape[2] == 4:
        img = img[..., [2, 1, 0, 3]]
    ok, enc = cv2.imencode(Path(path).suffix or ".png", np.ascontiguousarray(img))
    if not ok:
        raise CausalGSError(f"{path}: could not encode image")
    write_bytes(path, enc.tobytes())


def read_json(path: str | os.PathLike, what: str | None = None):
    """Read JSON, turning a missing or malformed file into a one-line :class:`~causalgs.errors.DataError`."""
    from causalgs.errors import DataError

    path = Path(path)
    if not path.is_file():
        raise DataError(f"{what or 'file'} not found: {path}")
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as e:
        raise DataError(f"{path}: malformed JSON (line {e.lineno}, column {e.colno}: {e.msg})") from None
    except UnicodeDecodeError:
        raise DataError(f"{path}: not a UTF-8 text file") from None
