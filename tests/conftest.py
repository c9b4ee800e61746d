"""Shared fixtures. Taichi is initialised once per precision; float64 is the default for tests (gradient checks
are noise in float32), and tests that need float32 ask for it explicitly."""

from __future__ import annotations

import numpy as np
import pytest


@pytest.fixture
def ti64():
    from causalgs import _ti

    return _ti.init("cpu", "float64")


@pytest.fixture
def ti32():
    from causalgs import _ti

    return _ti.init("cpu", "float32")


def _random_gaussians(n: int = 50, seed: int = 0) -> dict[str, np.ndarray]:
    """``n`` random Gaussians in [-1, 1]³ (raw parameters, degree-3 SH, float32) for rendering tests."""
    rng = np.random.default_rng(seed)
    return {
        "means": rng.uniform(-1.0, 1.0, (n, 3)).astype(np.float32),
        "quats": rng.normal(size=(n, 4)).astype(np.float32),
        "scales": np.log(rng.uniform(0.05, 0.3, (n, 3))).astype(np.float32),
        "opacities": (rng.normal(size=n) + 1.0).astype(np.float32),
        "sh": (rng.normal(size=(n, 16, 3)) * 0.5).astype(np.float32),
    }


@pytest.fixture
def make_gaussians():
    return _random_gaussians


@pytest.fixture
def read_video():
    """Decode every frame of a video file (BGR uint8) with OpenCV."""

    def read(path) -> list[np.ndarray]:
        import cv2

        cap = cv2.VideoCapture(str(path))
        frames = []
        while True:
            ok, frame = cap.read()
            if not ok:
                break
            frames.append(frame)
        cap.release()
        return frames

    return read
