"""Running a study's experiments forward (the `simulate` verb's engine)."""

from __future__ import annotations

import threading

import jax
import jax.numpy as jnp
import numpy as np

from jaxwear._core.background import Background
from jaxwear._core.jit import jit
from jaxwear._physics.cycle import WearResult, cycle_increment, run_history
from jaxwear._physics.wear import build_schedule, check_result, schedule_numerics, simulate
from jaxwear._study.study import Experiment, Study


def _numerics(study: Study, M):
    num = schedule_numerics(study)
    if M is not None:
        num.update(M=M, integrator="paper")
    return num


def common_length(study: Study, M=None) -> int:
    """Update count (bucketed) that fits every experiment: one compilation for the study."""
    return max(build_schedule(study.params(e), study.config, revolutions=e.revolutions,
                              hours=e.hours, snapshots=e.snapshot_points,
                              **_numerics(study, M)).updates
               for e in study.experiments)


def run_experiment(study: Study, exp: Experiment, *, M=None, check=True,
                   pad_to: int | None = None) -> WearResult:
    """Simulate one experiment with snapshots at its measured revolution counts / hours."""
    p = study.params(exp)
    res = simulate(p, study.config, revolutions=exp.revolutions, hours=exp.hours,
                   snapshots=exp.snapshot_points, check=False, pad_to=pad_to,
                   **_numerics(study, M))
    if check:
        check_result(res, study.config, f"{study.path}: experiment {exp.name!r}", p)
    return res


@jit
def _pressure(p, cfg, h, hist, regime):
    # The contact call of the wear itself (friction and every effect's contact terms), so
    # that the plotted pressure is the pressure that wore the bore.
    return cycle_increment(p, cfg, hist, regime, h, jnp.zeros(()))[2].pressure


def pressure_ahead(study: Study, after: threading.Event):
    """`last_cycle_pressure`'s program compiled in a daemon thread once `after` is set (the
    first experiment's wear loop lowered: its XLA compilation leaves the interpreter free
    and a core idle), by one call on the first experiment's shapes at zero load and an
    unworn bore. Why: traced, lowered and compiled after the first experiment, it was
    ~0.4 s of a cold `simulate` on the rig study (2 cores, 2026-11-30). Failures are left
    to `last_cycle_pressure`, which meets them again. Returns the `Background`."""

    def pressure_program():  # the thread's name: jaxwear-pressure_program
        after.wait()
        try:
            p = study.params(study.experiments[0])
            shapes = jax.eval_shape(lambda p: run_history(p, study.config), p)
            # zeros put on the device (jnp.zeros compiled a program for each shape), as the
            # real call's arrays are: the same entry of the program's cache
            hist = jax.tree.map(lambda s: jax.device_put(np.zeros(s.shape, s.dtype)), shapes)
            _pressure(p, study.config, jax.device_put(np.zeros(study.config.nodes)), hist, 0)
        except Exception:  # noqa: BLE001 (met again, and reported, where it is used)
            pass

    return Background(pressure_program)


def last_cycle_pressure(study: Study, exp: Experiment, res: WearResult, regime: int = 0):
    """Pressure map (steps, nodes) [Pa] of the last cycle, on the final profile."""
    return np.asarray(_pressure(study.params(exp), study.config, res.depth, res.history,
                                regime))


