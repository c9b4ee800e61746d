"""The effects registry and spec strings; the simulator config."""

from __future__ import annotations

import numpy as np
import pytest

from causalgs.errors import CausalGSError
from causalgs.sim import REGISTRY, Effects, SimConfig
from causalgs.sim.effects import parse_spec


def test_spec_parses_with_defaults_and_order(ti64):
    eff = Effects.from_spec("walls; gravity:g=0,-9.8,0 ;linear_drag")
    assert eff.names() == ["gravity", "linear_drag", "walls"]  # forces first, boundary conditions last
    np.testing.assert_array_equal(eff.get("gravity", "g"), [0.0, -9.8, 0.0])
    np.testing.assert_array_equal(eff.get("linear_drag", "c"), [0.0])
    eff.set("linear_drag", c=0.5)
    assert eff.get("linear_drag", "c")[0] == 0.5
    again = Effects.from_spec(eff.spec())
    assert again.spec() == eff.spec()
    assert Effects.from_spec("").names() == []
    # Simulators with the same set of effects share the kernel-side object (one compile), not the values.
    other = Effects.from_spec("gravity:g=1,2,3;walls;linear_drag")
    assert other.kernel is eff.kernel
    assert other.get("gravity", "g")[2] == 3.0 and eff.get("gravity", "g")[2] == 0.0


@pytest.mark.parametrize(
    ("spec", "pattern"),
    [
        ("gravty", r"unknown effect 'gravty' \(effects: .*gravity"),
        ("gravity:h=1", r"effect 'gravity' has no parameter 'h' \(parameters: g\)"),
        ("gravity:g=1,2", r"parameter 'g' takes 3 number\(s\), got 2"),
        ("gravity:g=a,b,c", r"parameter 'g' value 'a,b,c' is not a number list"),
        ("linear_drag:c=nan", r"parameter 'c' must be finite"),
        ("gravity:g", r"expected param=value, got 'g'"),
        ("walls;walls", r"effect 'walls' appears twice"),
        ("walls:band=2", r"effect 'walls' has no parameter 'band' \(parameters: none\)"),
    ],
)
def test_bad_specs_are_one_line_errors(spec, pattern):
    with pytest.raises(CausalGSError, match=pattern) as e:
        parse_spec(spec)
    assert "\n" not in str(e.value)


def test_bad_set_and_get(ti64):
    eff = Effects.from_spec("gravity")
    with pytest.raises(CausalGSError, match="effect 'walls' is not active"):
        eff.get("walls", "g")
    with pytest.raises(CausalGSError, match="takes 3 number"):
        eff.set("gravity", g=(1.0, 2.0))
    with pytest.raises(CausalGSError, match="no parameter 'q'"):
        eff.set("gravity", q=1.0)


def test_registry_contents():
    assert {"gravity", "force", "linear_drag", "quadratic_drag", "ground", "ground_sticky", "walls", "damping",
            "plasticity"} <= set(REGISTRY)  # fmt: skip
    assert all(d.doc for d in REGISTRY.values())


def test_config_refuses_unknown_keys_and_bad_values():
    with pytest.raises(CausalGSError, match="unknown simulator setting"):
        SimConfig.from_dict({"res": 16, "substep": 3})
    with pytest.raises(CausalGSError, match="unknown material model 'rubber'"):
        SimConfig(material="rubber")
    with pytest.raises(CausalGSError, match="must exceed lo"):
        SimConfig(lo=(0, 0, 0), hi=(1, 0, 1))
    cfg = SimConfig.from_dict({"res": 16, "hi": (2.0, 1.0, 0.5)})
    assert cfg.geometry.dx == 2.0 / 16
    assert cfg.geometry.shape == (17, 9, 5)
    assert SimConfig.from_dict(cfg.to_dict()) == cfg


def test_parameter_vector_round_trip_and_bounds(ti64):
    eff = Effects.from_spec("ground:mu=0.3;gravity;walls;damping:eta=2")
    names = eff.param_names()
    assert names == ["gravity.g[0]", "gravity.g[1]", "gravity.g[2]", "ground.n[0]", "ground.n[1]", "ground.n[2]",
                     "ground.d", "ground.mu", "damping.eta"]  # fmt: skip
    flat = eff.flat()
    np.testing.assert_array_equal(flat, [0, 0, -9.8, 0, 0, 1, 0, 0.3, 2])
    eff.set_flat(flat * 2)
    assert eff.get("ground", "mu")[0] == 0.6 and eff.get("damping", "eta")[0] == 4
    with pytest.raises(CausalGSError, match=r"got 3 values, expected 9"):
        eff.set_flat([1, 2, 3])
    with pytest.raises(CausalGSError, match=r"parameter 'mu' = -0.1 must be >= 0"):
        eff.set("ground", mu=-0.1)
    with pytest.raises(CausalGSError, match=r"parameter 'c' = -1 must be >= 0"):
        parse_spec("linear_drag:c=-1")
    # Viscosity limits the explicit time step: dx² rho / (6 eta).
    assert eff.dt_limit(0.1, 1000.0) == pytest.approx(0.01 * 1000 / (6 * 4))
    assert Effects.from_spec("gravity").dt_limit(0.1, 1000.0) == float("inf")
