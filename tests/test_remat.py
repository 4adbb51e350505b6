"""Reverse mode through the wear loops keeps the contact solves' Newton answers
(`jaxwear._physics.remat`): the backward pass runs no Newton iteration of its own; and it
sums no steps x nodes field in one reduction (`cycle.archard_rate`).

The check is structural, on the traced programs (no timing): Newton's iterations are the
only `while` loops of a wear loop differentiable in reverse mode (eq 23, or the adaptive
integrator with its static attempt count), so a gradient's program holds as many of them
as the forward run's; without the kept answers each checkpoint level ran them again in
the backward pass (9 loops against 3 on the rig before this). Where the kept answers
would pass `remat.OUTER_BYTES`, the outer blocks keep only their carries (the memory
bound of the two-level scan), checked by hand: 7 numbers of 8 bytes per step of a cycle
and contact solve. The gradients themselves are checked against central finite
differences in `test_gradients.py` and `test_integrator.py`.
"""

import jax
import jax.numpy as jnp
import pytest

import jaxwear as jw
from jaxwear._physics import remat
from jaxwear._physics.wear import build_schedule, wear_loop


def equations(jaxpr):
    """Every equation of `jaxpr`, its sub-programs' included."""
    for eqn in jaxpr.eqns:
        yield eqn
        for v in eqn.params.values():
            for sub in (v if isinstance(v, (list, tuple)) else [v]):
                inner = getattr(sub, "jaxpr", sub)
                if hasattr(inner, "eqns"):
                    yield from equations(inner)


def count(jaxpr, name: str) -> int:
    """Equations of primitive `name` in `jaxpr`, its sub-programs included."""
    return sum(eqn.primitive.name == name for eqn in equations(jaxpr))


def rig_loss(p0, cfg, sched):
    """Σh³/Σh² of a rig run [µm] as a function of (K_d, clearance)."""

    def f(x):
        p = p0.with_values({"K_d_per_Pa": x[0], "clearance_mm": x[1]})
        h = wear_loop(p, cfg, sched).depth * 1e6
        return jnp.sum(h**3) / jnp.sum(h**2)

    return f


@pytest.mark.parametrize("contact,M", [("unsymmetric", 100.0), ("symmetric", 100.0),
                                       ("unsymmetric", None)])
def test_the_gradient_runs_no_newton_iteration_of_its_own(contact, M):
    p0 = jw.preset("rig")
    cfg = jw.ModelConfig(nodes=64, steps_per_rev=72, contact=contact)
    # M = 100: eq 23's 20 updates (5 blocks of 4); None: the adaptive integrator
    sched = build_schedule(p0, cfg, revolutions=2000, M=M)
    assert sched.adaptive == (M is None) and not sched.dynamic

    f = rig_loss(p0, cfg, sched)
    x = jnp.asarray([1e-13, 0.05])
    forward = count(jax.make_jaxpr(f)(x).jaxpr, "while")
    backward = count(jax.make_jaxpr(jax.grad(f))(x).jaxpr, "while")
    assert forward > 0  # Newton's loops are there to count
    assert backward == forward, (forward, backward)


def test_the_outer_blocks_keep_the_answers_only_within_the_memory_bound():
    steps = 360
    per_item = 8 * 7 * steps  # bytes of one cycle's kept answers (one contact solve)
    fits = remat.OUTER_BYTES // per_item
    assert remat.outer_policy(fits, steps, 1) is remat.KEEP_NEWTON
    assert remat.outer_policy(fits + 1, steps, 1) is None
    # four stages an adaptive attempt: a quarter as many attempts
    assert remat.outer_policy(fits // 4, steps, 4) is remat.KEEP_NEWTON
    assert remat.outer_policy(fits // 4 + 1, steps, 4) is None
    # the paper's 100 000 revolutions at M = 1, 360 steps a cycle: carries only
    assert remat.outer_policy(100_000, steps, 1) is None


def test_the_gradient_sums_no_steps_by_nodes_field_at_once():
    """K_d enters each step's wear through the steps' sliding (`archard_rate`), so its
    cotangent is a sum over steps of row sums. Multiplied into the (steps, nodes) field, its
    cotangent was one sum over the whole field, which XLA:CPU ran as a blocked
    reduce-window at ~1.1 ms a call at 360 x 360 (a row sum ~0.1 ms): 145 calls, ~0.16 s
    of the rig's ~0.4 s gradient."""
    p0 = jw.preset("rig")
    cfg = jw.ModelConfig(nodes=64, steps_per_rev=72)
    sched = build_schedule(p0, cfg, revolutions=2000)

    jaxpr = jax.make_jaxpr(jax.grad(rig_loss(p0, cfg, sched)))(jnp.asarray([1e-13, 0.05]))
    found = [eqn for eqn in equations(jaxpr.jaxpr)
             if eqn.primitive.name == "reduce_sum"
             and tuple(eqn.invars[0].aval.shape[-2:]) == (72, 64)
             and {eqn.invars[0].aval.ndim - 2, eqn.invars[0].aval.ndim - 1}
             <= set(eqn.params["axes"])]
    assert found == [], [str(e.source_info.traceback) for e in found][:1]


def test_the_adaptive_gradient_stacks_no_stage_fields():
    """Each Runge-Kutta stage of an adaptive attempt is checkpointed: reverse mode keeps a
    stage's carries and Newton's answers, and runs the stage again in the backward pass,
    instead of stacking the stages' (steps, nodes) fields (the pressure, the rate, the
    contact's intermediate fields) four at a time. Stacking them wrote and read several
    MB an attempt at 360 x 360 (dynamic-slice fusions and copies ~1/4 of the backward
    pass's time); the rig's gradient took 3.9-4.1x its forward run's time with them, 2.5-
    2.6x without (docs/performance.md). Checked on the traced program: no scan of the four
    stages returns an array with a (steps, nodes) field per stage."""
    p0 = jw.preset("rig")
    cfg = jw.ModelConfig(nodes=64, steps_per_rev=72)
    sched = build_schedule(p0, cfg, revolutions=2000)
    assert sched.adaptive and not sched.dynamic

    jaxpr = jax.make_jaxpr(jax.grad(rig_loss(p0, cfg, sched)))(jnp.asarray([1e-13, 0.05]))
    stage_scans = [eqn for eqn in equations(jaxpr.jaxpr)
                   if eqn.primitive.name == "scan" and eqn.params["length"] == 4]
    stacked = [v.aval.shape for eqn in stage_scans for v in eqn.outvars
               if tuple(v.aval.shape[:1] + v.aval.shape[-2:]) == (4, 72, 64)]
    assert stage_scans  # the stage loops are there to look at
    assert stacked == [], stacked
