"""Shared fixtures. Taichi is initialised once per precision; float64 is the default for tests (gradient checks
are noise in float32), and tests that need float32 ask for it explicitly."""

from __future__ import annotations

import subprocess
import sys

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


_gpu_arch: list[str] = []


def gpu_arch() -> str:
    """The backend ``_ti.init("gpu")`` takes on this machine ("cuda", "vulkan" or the CPU's), asked once, in a
    separate process: asked here, a machine without a GPU would switch this process's Taichi to the CPU fallback
    and every test after it would start a new runtime."""
    if not _gpu_arch:
        code = "from causalgs import _ti; print(_ti.init('gpu', 'float32', quiet=True).arch)"
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
        _gpu_arch.append(out.stdout.strip().splitlines()[-1] if out.returncode == 0 and out.stdout.strip() else "")
    return _gpu_arch[0]


@pytest.fixture
def cuda64():
    """Taichi on CUDA in float64 (Vulkan has no float64); the test is skipped on a machine without CUDA."""
    if gpu_arch() != "cuda":
        pytest.skip("needs a CUDA device")
    from causalgs import _ti

    rt = _ti.init("gpu", "float64")
    assert rt.arch == "cuda", rt.arch
    return rt


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
