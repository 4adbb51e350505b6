"""The pressure plots of `simulate` come from the contact call of the wear itself.

Issue 12: `_simulate_study._pressure` solved the contact without friction, so the pressure
maps of a friction study left friction out. Independent fact used here: with Coulomb
friction μ the normal pressures carry only the normal part of the load, so for a narrow
contact zone their resultant is |W| / sqrt(1 + μ²) (the friction traction μ p carries the
rest); without friction it is |W| (equilibrium, eq 15).
"""

import threading
from types import SimpleNamespace

import jax.numpy as jnp
import numpy as np
import pytest

import jaxwear as jw
from jaxwear._analyses.simulate import (
    _pressure,
    last_cycle_pressure,
    pressure_ahead,
    run_experiment,
)
from jaxwear._physics.cycle import node_area
from jaxwear._study.study import Experiment, Study

NODES, STEPS = 64, 48


def _study(mu, nodes=NODES):
    effects = ("friction",) if mu else ()
    cfg = jw.ModelConfig(nodes=nodes, steps_per_rev=STEPS, effects=effects)
    params = {"friction_coefficient": mu} if mu else {}
    exp = Experiment("a", {}, revolutions=100.0)
    return Study(path=None, preset="rig", config=cfg, parameters=params, experiments=(exp,))


@pytest.mark.parametrize("mu", [0.0, 0.3])
def test_pressure_map_carries_the_normal_part_of_the_load(mu):
    study = _study(mu)
    exp = study.experiments[0]
    p = study.params(exp)
    hist = jw.load_history(p, study.config)
    res = SimpleNamespace(depth=jnp.zeros(NODES), history=hist)  # unworn bore
    P = last_cycle_pressure(study, exp, res)  # (steps, nodes) Pa
    th = 2 * np.pi * np.arange(NODES) / NODES
    A = float(node_area(p, NODES))
    resultant = np.hypot(P @ np.cos(th), P @ np.sin(th)) * A
    W = np.abs(np.asarray(hist.load[0]))
    ok = W > 0.2 * W.max()
    ratio = resultant[ok] / W[ok]
    assert np.allclose(ratio, 1 / np.sqrt(1 + mu**2), rtol=0.02), ratio.min()


def test_the_program_compiled_ahead_is_the_one_the_map_runs():
    """`pressure_ahead` (the `simulate` verb, beside the first experiment's compilation)
    compiles the map's program on the first experiment's shapes at zero load; the map of
    the experiment's real result then compiles nothing more. A call ahead that differs in
    a static argument, a dtype or a weak type would compile a second program here."""
    study = _study(0.3, nodes=40)  # an effect (friction), and shapes no other test uses
    exp = study.experiments[0]
    ready = threading.Event()
    ready.set()
    before = _pressure._cached._cache_size()
    pressure_ahead(study, ready).result()
    assert _pressure._cached._cache_size() == before + 1
    P = last_cycle_pressure(study, exp, run_experiment(study, exp))
    assert _pressure._cached._cache_size() == before + 1
    assert P.shape == (STEPS, 40) and np.isfinite(P).all() and P.max() > 0
