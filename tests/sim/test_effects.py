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
    assert {"gravity", "walls", "linear_drag"} <= set(REGISTRY)
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
