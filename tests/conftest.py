"""Shared fixtures. Taichi is initialised once per precision; float64 is the default for tests (gradient checks
are noise in float32), and tests that need float32 ask for it explicitly."""

from __future__ import annotations

import pytest


@pytest.fixture
def ti64():
    from causalgs import _ti

    return _ti.init("cpu", "float64")


@pytest.fixture
def ti32():
    from causalgs import _ti

    return _ti.init("cpu", "float32")
