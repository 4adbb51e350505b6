"""Laws with memory as candidates of the law search (issue 48 item 4): which to try, and
from where (`memory_candidates`; the laws themselves: `effects.law_memory`).

**When.** After the memoryless laws, and only where (a) the shape's answer points at the
history: its best variable or a carrier of its refitted correction is the sliding
distance (the cycle count's stand-in) or the worn depth (a law with memory makes a rate
that depends on what the node went through, which the shape, a function of the present
states, follows along the variables that grow with it); or (b) the best memoryless law
leaves an RMSE more than `LAW_WORSE` above the noise (what no law of the present states
explains may be history: on the generator's fatigue law the shape pointed at the sliding
speed, which told the experiments apart, and the best memoryless law stopped at 1.44 x
the noise). Not where a memoryless law already fits to noise by diagnose's tests; where
one of two variables fits as well as the shape (the search's stop for memoryless laws),
only under (a): the shape is a function of the present states, no bound on a law with
memory (on the generator's slow film the search stopped at a deposit ∝ S^−1.14, 0.315 µm,
left-out 0.321, the shape 0.314; the film law, fitted, reached 0.307, left-out 0.308).
Why not always: each costs a compilation of its model (forward and Jacobian), ~17 forward runs
and ~10 evaluations with 5 more Jacobian columns, against `diagnose --shape`'s 2-minute
budget.

**From where.** A law with memory is far from linear in its constants (a damage's step
comes at a cycle count ∝ 1/k1), so the pre-screen's first-order answer does not reach
it. Starts are chosen by one forward run each (`law.start.forward_rmse`, K_d scaled to
the data): a damage driven by the peak pressure or by the contact work (exponent 2, the
median node giving way at a quarter, half or all of the median experiment's cycles,
A = 0.5 or 1.5), and a film (formation and removal at 1/N and 5/N per cycle of the median
experiment's N, either ratio, A = 0.5 or 2); the best start of each form is fitted
through the loop. The references (z_ref, t_ref, w_ref) are the wear-weighted medians of
the variables met at the fit's answer (`memory_states`), as the grammar's.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from jaxwear._analyses.diagnose._fit import _log
from jaxwear._analyses.diagnose.law.result import LAW_WORSE
from jaxwear._analyses.diagnose.law.start import STATE_FRACTIONS, forward_rmse
from jaxwear._analyses.diagnose.shape.design import (
    _cycle_states,
    _load_history_jit,
    _weighted_quantiles,
)
from jaxwear._physics.effects.law_memory import MEMORY_VARIABLES, MemoryLaw, memory_variables

# the shape's variables that grow with the history: a law with memory shows along them
HISTORY_VARIABLES = ("sliding_distance_m", "worn_depth_um")
DAMAGE_DRIVERS = ("peak_pressure_MPa", "contact_work_kJ_per_m2")
FAILURE_FRACTIONS = (0.25, 0.5, 1.0)  # of the median experiment's cycles
DAMAGE_GAINS = (0.5, 1.5)
FILM_RATES = (1.0, 5.0)  # per the median experiment's cycles
FILM_GAINS = (0.5, 2.0)


def points_at_history(prefer, correction) -> bool:
    """The shape's best variable or a carrier of its refitted correction is a history
    variable (`HISTORY_VARIABLES`)."""
    names = {v.get("name") for v in (correction or {}).get("variables", ())}
    if prefer is not None:
        names.add(prefer[1])
    return bool(names & set(HISTORY_VARIABLES))


def memory_states(model, fit):
    """({name: (n,)} of `MEMORY_VARIABLES` per node and cycle, weights (n,) summing to 1,
    the median experiment's cycles): at the start, half-way and the end of each experiment
    at `fit`'s answer, weighted by each node's wear per cycle (an experiment as much as
    the wear it made), as `law.start.joint_states`."""
    ext = model.ext
    cfg = ext.cfg.replace(shape=None)
    P = ext.batched_params(jnp.asarray(fit.ev.u))
    snaps = np.asarray(fit.ev.snaps)  # (E, S, N) µm
    zs = {n: [] for n in MEMORY_VARIABLES}
    ws, cycles = [], []
    for e in range(snaps.shape[0]):
        p = jax.tree_util.tree_map(lambda x: x[e], P)
        hist = _load_history_jit(p, cfg)
        total = float(fit.ev.sliding_m[e])
        per_cycle = float(np.mean(np.sum(np.asarray(hist.slide), axis=1)))
        if per_cycle > 0:
            cycles.append(total / per_cycle)
        last = np.clip(snaps[e, -1], 0.0, None)
        w_e, z_e = [], {n: [] for n in MEMORY_VARIABLES}
        for r in range(hist.load.shape[0]):
            for f in STATE_FRACTIONS:
                z, rate = _cycle_states(p, cfg, hist, r, jnp.asarray(f * last * 1e-6),
                                        jnp.asarray(f * total))
                pressure = np.asarray(z["pressure_MPa"]) * 1e6
                m = memory_variables(pressure, np.asarray(hist.slide[r]),
                                     np.asarray(hist.dt[r]), xp=np)
                w_e.append(np.asarray(rate).sum(axis=0))
                for n in MEMORY_VARIABLES:
                    z_e[n].append(np.asarray(m[n]))
        w_e = np.clip(np.concatenate(w_e), 0.0, None)
        s = float(w_e.sum())
        if not s > 0:
            continue
        ws.append(w_e * (max(float(last.sum()), 1e-12) / s))
        for n in MEMORY_VARIABLES:
            zs[n].append(np.concatenate(z_e[n]))
    if not ws:
        return {}, np.zeros(0), math.nan
    w = np.concatenate(ws)
    keep = w > 0
    z = {n: np.concatenate(v)[keep] for n, v in zs.items()}
    return z, w[keep] / w[keep].sum(), float(np.median(cycles)) if cycles else math.nan


def start_laws(z: dict, w, cycles: float) -> list[MemoryLaw]:
    """The starts screened by a forward run (module docstring), over the states met `z`
    with weights `w` (`memory_states`) and the median experiment's `cycles`."""
    def med(n):
        v = float(_weighted_quantiles(np.asarray(z[n], float), w, [0.5])[0])
        return v if v > 0 else max(float(np.max(z[n])), 1e-12)

    out = []
    for var in DAMAGE_DRIVERS:
        ref = med(var)
        for q in FAILURE_FRACTIONS:
            for A in DAMAGE_GAINS:
                out.append(MemoryLaw("damage", var, ref, strength=A, k1=1.0 / (q * cycles),
                                     a=2.0, width=0.2))
    t_ref, w_ref = med("time_out_of_contact_s"), med("contact_work_kJ_per_m2")
    span = max(float(np.max(z["time_out_of_contact_s"])) / t_ref,
               float(np.max(z["contact_work_kJ_per_m2"])) / w_ref, 1.0)
    for r1 in FILM_RATES:
        for r2 in FILM_RATES:
            for A in FILM_GAINS:
                out.append(MemoryLaw("film", "time_out_of_contact_s", t_ref, w_ref,
                                     strength=A, k1=r1 / cycles, k2=r2 / cycles, span=span))
    return out


def after(todo, more):
    """The candidates of `todo`, then those `more()` returns, called once the first are
    fitted (what it returns may depend on their fits)."""
    yield from todo
    yield from more()


def wanted(prefer, correction, fitted, noise_um, as_shape=False) -> bool:
    """Whether to try laws with memory (module docstring, "When"): the shape points at the
    history, or the best of the memoryless laws `fitted` (`LawFit`s) is more than
    `LAW_WORSE` above the noise `noise_um` [µm] (or none was fitted) and none of two
    variables fits as well as the shape (`as_shape`)."""
    if points_at_history(prefer, correction):
        return True
    if as_shape:
        return False
    best = min((f.rmse_um for f in fitted), default=math.inf)
    return bool(best > (1.0 + LAW_WORSE) * noise_um)


def memory_candidates(model, fit, prefer, correction, law_model, fitted, noise_um, *,
                      skip=False, as_shape=False, verbose=False) -> list:
    """[(nan, law, "memory")]: the best start of each form of law with memory (module
    docstring), or [] where they are not `wanted` or `skip` (a memoryless law already
    fits to noise). `as_shape`: a memoryless law of two variables fits as well as the
    shape (`law.search.as_shape`). `law_model`: `law.search.law_model` (the search's model of a
    candidate); call inside `effects.law.searching()`."""
    if skip or not wanted(prefer, correction, fitted, noise_um, as_shape):
        return []
    z, w, cycles = memory_states(model, fit)
    if not z or not (math.isfinite(cycles) and cycles > 0):
        return []
    laws = start_laws(z, w, cycles)
    rm = [(forward_rmse(law_model(model, fit, law), model.measured), law) for law in laws]
    out = []
    for form in ("damage", "film"):
        mine = [x for x in rm if x[1].form == form and math.isfinite(x[0])]
        if mine:
            r, law = min(mine, key=lambda x: x[0])
            out.append((math.nan, law, "memory"))
            _log(verbose, f"  law search: memory start {law.label} A {law.strength:g} k1 "
                          f"{law.k1:.3g} k2 {law.k2:.3g}: {r:.4f} µm (K_d scaled; best of "
                          f"{len(mine)} forward runs)")
    return out
