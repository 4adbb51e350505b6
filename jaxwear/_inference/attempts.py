"""How much integration a trial point needs: the adaptive loop's static attempt count raised
where the parameters need more, and a trial cut off (a rejected step) where the need is not
finite or far beyond the current point's."""

from __future__ import annotations

import dataclasses
import math

import jax
import numpy as np

from jaxwear._core.errors import TrialFailed
from jaxwear._core.jit import jit
from jaxwear._inference.residual import ResidualModel
from jaxwear._physics.adaptive import _regime_rates, adaptive_attempts, rate_config

# Headroom of a raised attempt count: a fit's first rescale of K_d sets the stiffness to
# within a small factor. The count is a traced bound in the fits' programs (`_dynamic`), so
# a raise costs no compilation; the headroom only keeps the host's bookkeeping from raising
# at every small move. An unused attempt costs nothing (the loop ends at the run's end).
RAISE_HEADROOM = 2.0


def _dynamic(model: ResidualModel) -> ResidualModel:
    """`model` whose adaptive loop takes its attempt count as a traced bound: a raise of the
    count (the model it returns keeps the static count, for the host's bookkeeping) does not
    recompile the Jacobian."""
    return model.with_schedule(model.schedule.with_dynamic_attempts())


def attempts_needed(model: ResidualModel, u) -> int | float:
    """The adaptive loop's estimated attempt count at u (`adaptive_attempts`, the largest
    over the experiments); 0 for eq-23 schedules; inf where the work estimate is not
    finite (a wear-rate bound K_d k S_cycle that is NaN or inf at these parameters: the
    model cannot be run there, `work_failure`)."""
    sched = model.schedule
    if not sched.adaptive:
        return 0
    rates = experiment_rates(model, u)
    if not np.all(np.isfinite(rates)):
        return math.inf
    host = jax.tree.map(np.asarray, sched)
    need = 0
    for i in range(sched.cycles.shape[0]):
        one = dataclasses.replace(jax.tree.map(lambda x: x[i], host), attempts=1)
        need = max(need, adaptive_attempts(None, model.cfg, one, rates=rates[i]))
    return need


# The last rates asked for: a fit's trial asks three times at the same u (is the work
# finite, is it affordable, how many attempts), and the answer depends on the model's
# parameters, packing and configuration only (not its schedule).
_last: list = [None]


def experiment_rates(model: ResidualModel, u) -> np.ndarray:
    """`_experiment_rates` of `model` at u (experiments, regimes) [1/cycle], on the host;
    the last call's answer again where the model's parameters, packing and configuration
    are the same objects and u the same values."""
    u = np.asarray(u, np.float64)
    last = _last[0]
    if (last is not None and last[0] is model.params and last[1] is model.packing
            and last[2] is model.cfg and last[3] == u.tobytes()):
        return last[4].copy()
    rates = np.asarray(_experiment_rates(rate_model(model), u))
    _last[0] = (model.params, model.packing, model.cfg, u.tobytes(), rates)
    return rates.copy()


def rate_model(model: ResidualModel) -> ResidualModel:
    """`model` as `_experiment_rates` takes it: without its schedule (an attempt count is no
    new program) and in `rate_config` (every resolution of a study one program)."""
    return dataclasses.replace(model, schedule=None, cfg=rate_config(model.cfg))


@jit(once=True)
def _experiment_rates(model: ResidualModel, u):
    """`_regime_rates` of every experiment at u (experiments, regimes) [1/cycle], one
    compiled call (the model without its schedule: an attempt count is no new program).
    Eager, the parameters' assembly and the load history cost ~0.2 s per evaluation."""
    return jax.lax.map(lambda p: _regime_rates(p, model.cfg), model.batched_params(u))


def enough_attempts(model: ResidualModel, u, headroom: float = RAISE_HEADROOM,
                    need: int | float | None = None) -> ResidualModel:
    """`model` with the adaptive loop's static attempt count raised (to a power of 2 at
    `headroom` x the need, so that few compilations arise) where the parameters at u need
    more than it has (the stiffness-limited step count grows with K_d, which a fit moves by
    orders). `need`: `attempts_needed(model, u)` where the caller has it. Raises
    `TrialFailed` where the need is not finite."""
    sched = model.schedule
    need = attempts_needed(model, u) if need is None else need
    if need <= sched.attempts:
        return model
    if not math.isfinite(need):
        raise TrialFailed(work_failure(model, u))
    if need > MAX_ATTEMPTS:
        raise TrialFailed(too_stiff(need))
    more = min(2 ** math.ceil(math.log2(headroom * need)), MAX_ATTEMPTS)
    return model.with_schedule(dataclasses.replace(sched, attempts=more))


# the most attempts a run is given: the loop's bound is an int32 on the device, and a run
# that needs more (a left-out step that took a clearance to 1e-300 or K_d to 1e30:
# measured 2^46 on a held-out study) cannot be integrated in any time a user waits for
MAX_ATTEMPTS = 2 ** 24


def too_stiff(need: float) -> str:
    """Why a run is not made whose integration would need `need` attempts."""
    return (f"the integration would need ~{need:.3g} steps (over {MAX_ATTEMPTS}): the "
            f"wear rate is far beyond any measured one there (not run)")


def needs_more_attempts(model: ResidualModel, u, factor: float = 4.0) -> bool:
    """True where u needs over `factor` times the model's attempt count: a trial at a
    stiff corner (running-in over a millimetre, K_d 100x) that would make the integrator
    crawl."""
    return model.schedule.adaptive and attempts_needed(model, u) > factor * \
        model.schedule.attempts


def work_failure(model: ResidualModel, u) -> str:
    """Why the model cannot be run at u where its work estimate is not finite: the
    experiments whose wear-rate bound K_d k S_cycle [1/cycle] is NaN or inf there."""
    rates = experiment_rates(model, u).reshape(model.schedule.cycles.shape[0], -1)
    bad = [i for i in range(rates.shape[0]) if not np.all(np.isfinite(rates[i]))]
    which = ", ".join(model.exp_names[i] if i < len(model.exp_names) else str(i)
                      for i in bad)
    return (f"the work estimate is not finite: the wear-rate bound K_d k S_cycle is "
            f"{rates[bad[0]].max() if bad else math.nan:g} per cycle in experiment(s) "
            f"{which} (not run)")
