from __future__ import annotations

import re

import pytest
import torch

from causalgs import _ti
from causalgs.errors import CausalGSError, RuntimeConfigError


def test_same_arguments_do_not_reinitialise(ti64):
    again = _ti.init("cpu", "float64")
    assert again is ti64 and again.generation == _ti.generation()
    assert _ti.real() == _ti.ti.f64 and _ti.torch_dtype() == torch.float64
    assert torch.get_num_threads() == 1


def test_cache_dir_from_environment(monkeypatch, tmp_path):
    monkeypatch.setenv(_ti.CACHE_ENV, str(tmp_path / "kernels"))
    assert _ti.cache_dir() == tmp_path / "kernels"
    monkeypatch.delenv(_ti.CACHE_ENV)
    assert _ti.cache_dir().parts[-3:] == (".cache", "causalgs", "taichi")


def test_rejects_unknown_device_and_precision():
    with pytest.raises(RuntimeConfigError, match="device 'tpu'"):
        _ti.init("tpu")
    with pytest.raises(RuntimeConfigError, match="precision 'float16'"):
        _ti.init("cpu", "float16")


def test_bad_thread_setting(monkeypatch):
    monkeypatch.setenv(_ti.THREADS_ENV, "many")
    with pytest.raises(RuntimeConfigError, match="CAUSALGS_TORCH_THREADS='many'"):
        _ti._set_torch_threads()
    monkeypatch.setenv(_ti.THREADS_ENV, "2")
    _ti._set_torch_threads()
    assert torch.get_num_threads() == 2
    monkeypatch.delenv(_ti.THREADS_ENV)
    _ti._set_torch_threads()
    assert torch.get_num_threads() == 1


def test_a_cpu_list_pins_the_process_and_a_bad_one_is_one_line(monkeypatch):
    assert _ti.parse_cpus("0,2-3") == [0, 2, 3] and _ti.parse_cpus(" 1 ") == [1]
    for bad in ("two", "3-1", "-1", "0,,1"):
        with pytest.raises(RuntimeConfigError, match=f"CAUSALGS_TI_CPUS={bad!r} is not a CPU list"):
            _ti.parse_cpus(bad)
    monkeypatch.delenv(_ti.CPUS_ENV, raising=False)
    assert _ti.cpus_from_env() is None
    allowed = _ti.allowed_cpus()
    monkeypatch.setenv(_ti.CPUS_ENV, str(max(allowed) + 1))
    with pytest.raises(RuntimeConfigError, match=re.escape(f"may run on CPUs {allowed} only")):
        _ti.cpus_from_env()
    import os
    import subprocess
    import sys

    # a fresh process with the variable set runs where it says once Taichi starts, and its threads with it
    code = ("import os; from causalgs import _ti; before = os.sched_getaffinity(0); _ti.init('cpu'); "
            "print(sorted(before), sorted(os.sched_getaffinity(0)))")  # fmt: skip
    env = {**os.environ, _ti.CPUS_ENV: str(allowed[-1])}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split("\n")[-2] == f"{allowed} {[allowed[-1]]}"


def test_reinitialise_changes_precision_and_invalidates_stores(capfd):
    from causalgs.store import ParticleStore

    before = _ti.init("cpu", "float64")
    store = ParticleStore()
    try:
        rt = _ti.init("cpu", "float32")
        assert rt.generation == before.generation + 1 and rt.arch in ("x64", "arm64")
        assert _ti.real() == _ti.ti.f32
        with pytest.raises(CausalGSError, match="re-initialised"):
            store.to_torch("x")
        fresh = ParticleStore()
        fresh.append(x=torch.ones(2, 3, dtype=torch.float64))
        assert fresh.to_torch("x").dtype == torch.float32
    finally:
        _ti.init("cpu", "float64")


def test_gpu_request_falls_back_visibly(capfd):
    """Without a GPU, 'gpu' must land on the CPU with a message, never segfault (Taichi's ti.gpu does)."""
    try:
        rt = _ti.init("gpu", "float64")
        if rt.on_gpu:
            pytest.skip(f"a GPU is present ({rt.arch})")
        assert rt.arch in ("x64", "arm64")
        assert "running on the CPU" in capfd.readouterr().err
    finally:
        _ti.init("cpu", "float64")
