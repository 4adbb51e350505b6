"""The plausibility table (`jaxwear._study.plausible`, issue 29): every key has a range, the
presets and the example studies lie inside them, and what the layer-strain check computes
without the model agrees with the model: the peak joint load with the mechanism's, the
closed-form Winkler strain with the discrete contact solve's."""

import math
from pathlib import Path

import jax
import numpy as np
import pytest

import jaxwear as jw
from jaxwear import InputError
from jaxwear._physics.contact import equivalent_modulus, solve_contact, stiffness_per_area
from jaxwear._physics.cycle import node_area
from jaxwear._physics.effects import effect_parameter_specs
from jaxwear._physics.limits import (
    LOAD_BOUNDS,
    STRAIN_LIMIT,
    crank_slider_peak_load,
    peak_strain,
    strain_load_limit,
)
from jaxwear._physics.load import load_history
from jaxwear._physics.params import PARAMETER_KEYS, PRESETS
from jaxwear._study.plausible import RANGES, check_params, check_value, key_range

ROOT = Path(__file__).resolve().parents[1]


def test_every_key_has_a_range():
    """A key added without a range would go unchecked: every parameter key, every effect
    strength and every number of [numerics], [fit] and [[experiment]] is in the table."""
    from jaxwear._study.study import _FIT_KEYS, _NUMERIC_KEYS

    for key in PARAMETER_KEYS:
        assert key in RANGES, key
    for key, spec in effect_parameter_specs().items():
        r = key_range(key)
        assert (r.lo, r.hi) == (spec.lower, spec.upper), key
    numbers = (_NUMERIC_KEYS - {"integrator"}, _FIT_KEYS - {"parameters"})
    for section, keys in zip(("numerics", "fit"), numbers):
        for key in keys:
            assert f"{section}.{key}" in RANGES, (section, key)
    for key in ("revolutions", "hours", "angle_offset_deg"):
        assert f"experiment.{key}" in RANGES


@pytest.mark.parametrize("name", sorted(PRESETS))
def test_presets_are_plausible(name):
    """The presets' own values lie in their ranges, and their joints pass the ratios and
    the strain check with room to spare."""
    for key, v in PRESETS[name].items():
        r = key_range(key, name)
        if r is not None and not math.isnan(v):
            assert v in r, (name, key, v, str(r))
    if name == "load_history":  # its load is a file's (tests/test_load_history*.py)
        return
    cfg = jw.ModelConfig(driver="oscillating", double_layer=True) if name == "boom" else (
        jw.ModelConfig())
    p = jw.preset(name, **({"speed_rpm": 276} if name == "rig" else {}))
    check_params(name, p, cfg)
    load = LOAD_BOUNDS[cfg.driver].bound(p, cfg)
    assert peak_strain(p, load, cfg.double_layer) < 0.1 * STRAIN_LIMIT


@pytest.mark.parametrize("study", ["calibration/rig/study.toml", "calibration/boom/study.toml"])
def test_example_studies_load(study):
    jw.load_study(ROOT / study)


def test_message_names_key_value_and_range():
    with pytest.raises(InputError) as e:
        check_value("s.toml", "speed_rpm", 1e9, name="experiment 'a'.speed_rpm")
    msg = str(e.value)
    assert msg.startswith("s.toml: experiment 'a'.speed_rpm = 1e+09 is outside the plausible "
                          "range [0.001, 100000]: ")
    assert check_value("--x", "speed_rpm", 276.0) == 276.0
    assert key_range("speed_rpm", "boom") is None  # the boom has no crank speed


@pytest.fixture(scope="module")
def peak_loads():
    """max |F_C| of one revolution (the model's mechanism, SCLA, 360 steps) at a set of
    parameters: (overrides, peak [N])."""
    cfg = jw.ModelConfig(nodes=8, steps_per_rev=360)
    peak = jax.jit(lambda p: load_history(p, cfg).load.max())
    cases = [dict(speed_rpm=s, spring_N_per_m=k) for s in (1.0, 148.0, 276.0, 1000.0, 2500.0)
             for k in (0.0, 1009.4)]
    cases += [dict(speed_rpm=276.0, crank_length_mm=150.0),  # λ = 0.75
              dict(speed_rpm=600.0, slider_mass_kg=0.5, coupler_mass_kg=3.0),
              dict(speed_rpm=276.0, spring_N_per_m=1e5, spring_free_position_mm=100.0)]
    return [(kw, float(peak(jw.preset("rig", **kw)))) for kw in cases]


def test_peak_load_is_the_mechanisms(peak_loads):
    """The peak load the strain check uses (the hand-derived eqs in NumPy, ideal joint, 720
    angles) is the model's (jvp kinematics, SCLA, 360 steps) to 2e-3: design.md §8 bounds the
    clearance link's effect by 2e-4, the rest is where the samples fall."""
    for kw, peak in peak_loads:
        assert crank_slider_peak_load(jw.preset("rig", **kw)) == pytest.approx(peak,
                                                                               rel=2e-3), kw


@pytest.mark.parametrize("name,load", [("rig", 250.0), ("rig", 2e4), ("boom", 1e4),
                                       ("boom", 3e6)])
def test_winkler_strain_matches_the_contact_solve(name, load):
    """The closed-form peak strain (continuous Winkler contact on the unworn bore) against
    `solve_contact` at 720 nodes: max pressure / E_w of the layer, within 2 %."""
    cfg_double = name == "boom"
    p = jw.preset(name)
    nodes = 720
    k = stiffness_per_area(np.zeros(nodes), p, cfg_double)
    sol = solve_contact(np.array([load]), np.array([0.3]), np.zeros(nodes), p.clearance, k,
                        node_area(p, nodes))
    assert float(sol.residual.max()) < 1e-9
    discrete = float(sol.pressure.max()) / float(equivalent_modulus(p.layer_modulus,
                                                                    p.layer_poisson))
    assert peak_strain(p, load, cfg_double) == pytest.approx(discrete, rel=0.02)
    # and the load limit is the load at the strain limit
    assert peak_strain(p, strain_load_limit(p, cfg_double), cfg_double) == pytest.approx(
        STRAIN_LIMIT, rel=1e-6)


def test_the_docs_list_every_range():
    """docs/plausibility.md is the table in prose: every key and ratio is in it."""
    from jaxwear._study.plausible import RELATIONS

    text = (ROOT / "docs" / "plausibility.md").read_text()
    for key in RANGES:
        assert f"`{key}`" in text, key
    for rel in RELATIONS:
        assert f"`{rel.keys}`" in text, rel.keys
