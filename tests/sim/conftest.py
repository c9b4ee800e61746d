"""Shared helpers for the simulator tests: one ParticleStore per Taichi runtime, reused across tests (every new store
is a new set of fields and so a new compile of every MPM kernel), and small particle blocks."""

from __future__ import annotations

import itertools
from types import SimpleNamespace

import pytest
import torch

DX = 1.0 / 16  # the tests' grid: res 16 on the unit box
SLOTS = 16  # substeps per segment the test store can hold (any test may use a segment up to this)
_stores: dict = {}


def shared_store(n: int):
    """The runtime's test store, emptied and resized to ``n`` rows (rows take their fill values)."""
    from causalgs import _ti
    from causalgs.sim.mpm import segment_specs
    from causalgs.store import ParticleStore

    key = _ti.generation()
    if key not in _stores:
        _stores.clear()
        _stores[key] = ParticleStore(0, sh_degree=0)
        _stores[key].add_fields(segment_specs(SLOTS))
    store = _stores[key]
    store.resize(0)
    store.resize(n)
    return store


def block(center, count: int = 6, spacing: float = DX / 2, dtype=torch.float64) -> torch.Tensor:
    """A cube of count³ lattice points around ``center`` (8 particles per cell at the default spacing)."""
    idx = torch.tensor(list(itertools.product(range(count), repeat=3)), dtype=dtype)
    return torch.tensor(center, dtype=dtype) + (idx - (count - 1) / 2) * spacing


def fill_block(store, x: torch.Tensor, E: float = 1.0e4, nu: float = 0.3, density: float = 1.0e3, spacing=DX / 2):
    """Write positions and uniform materials; each particle carries the mass of its lattice cell."""
    n = len(x)
    vol = spacing**3
    store.from_torch("x", x)
    store.from_torch("vol", torch.full((n,), vol))
    store.from_torch("mass", torch.full((n,), density * vol))
    store.from_torch("E", torch.full((n,), E))
    store.from_torch("nu", torch.full((n,), nu))
    store.from_torch("density", torch.full((n,), density))


@pytest.fixture
def mk():
    """Helpers: ``mk.store(n)``, ``mk.block(center, count)``, ``mk.fill(store, x, E=...)``, ``mk.DX``."""
    return SimpleNamespace(store=shared_store, block=block, fill=fill_block, DX=DX)
