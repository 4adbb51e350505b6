"""The shape analysis's design: the state variables' knots over the range met in the data,
the spline basis, the correction's Jacobian columns through the wear loop (computed in the
background while the verdict runs), and the model's own numerical error rows."""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from dataclasses import replace as dreplace
from types import SimpleNamespace

import jax
import jax.numpy as jnp
import numpy as np

from jaxwear._analyses.diagnose._fit import Fit, _log
from jaxwear._analyses.diagnose._model import Model
from jaxwear._core.background import Background
from jaxwear._core.jit import jit
from jaxwear._physics.cycle import archard_rate, cycle_increment
from jaxwear._physics.effects.shape import (
    DEPOSIT_VARIABLES,
    FORMS,
    VARIABLES,
    ShapeBasis,
    ShapeTensor,
    ShapeVariable,
    state_variables,
)
from jaxwear._physics.load import load_history

SIZE = 10  # B-splines per variable


TENSOR_SIZE = 5  # B-splines per direction of the leading pair's surface (issue 43)


JOINT_DRAWS = 2000  # null simulations of a form's joint fit (larger matrices)


LEVEL = 0.9  # band of the correction and of its peak


RANGE_QUANTILES = (0.005, 0.995)  # of the wear-weighted state: the range met in the data


KNOT_QUANTILES = 32  # pieces of the piecewise-linear quantile coordinate


REFIT_EVALUATIONS = 10


MAX_CARRIERS = 3  # variables of the refitted correction at most


JACOBIAN_NODES = 90  # nodes of the correction's Jacobian at most (its steps are the fit's)


# The correction's Jacobian at this many times the fit's wear tolerance (adaptive
# integrator): its columns are the test's design, so their integration error costs power
# only. Measured on a 5-experiment speed study at 90 x 72 (146 columns): x1 51 steps,
# 14.3 s; x4 31 steps, 9.2 s, columns within 1.4 % (median 0.4 %); x10 20 steps, 6.4 s,
# within 4 % (median 0.6 %); x30 within 13 %.
JACOBIAN_TOLERANCE = 10.0


# Prior SD of each factor coefficient in the refit (g = ln of the rate factor: e at one SD).
# Why: where little wears (a range's end) the data leave a coefficient loose (SE 26 measured
# on a speed study), and a Gauss-Newton step of 0.4 SE moved it by 9: exp(9) on that part of
# the rate, χ² up by 112 where the quadratic model promised 0.14 down; the refit then crept
# at ~1 SE per step to its budget. The data override this prior wherever they determine g.
FACTOR_SD = 1.0


@dataclass(frozen=True)
class Design:
    """What one analysis computed that a later one on the same model reuses: the basis
    knots and the states of the data (`state_knots`), the model with the correction
    (`smodel`), the Jacobian model and its evaluation (`ev_j`: the correction's columns),
    and the rows' numerical error (µm, or None)."""

    study: object
    groups: tuple
    knots: dict
    load: dict
    exp_name: str
    deepest: int
    smodel: Model
    jmodel: Model
    ev_j: object
    numerical_um: np.ndarray | None
    u: np.ndarray = None  # where the columns are linearised (smodel's u)
    evaluations: int = 1  # model evaluations it took (0 once an analysis has counted them)
    # the columns of a pair's surface (`tensor_columns`) by its label, shared by the
    # analyses on this design (a later one on top of an effect reuses them)
    tensors: dict = field(default_factory=dict, repr=False)
    # the refit model's basis and Jacobian width by (carriers, form) (`shape.analysis`):
    # a later analysis that refits the same carriers takes them, so that both refits run
    # one compiled program (its surface off where that analysis tests none)
    refit_bases: dict = field(default_factory=dict, repr=False)


def prepare_design(model: Model, fit, *, groups=None, size: int = SIZE,
                   verbose: bool = False) -> Design:
    """The states met in the data, the basis on them and the correction's columns at the
    answer of `fit` (one Jacobian of the model with every variable-form switched on).
    `fit`: a `Fit` of `model`, or anything with its `label` and `ev.u`, `ev.snaps`,
    `ev.sliding_m` (`at_answer`). `groups`: the candidate groups the model with the
    correction carries (held at off where `fit` does not fit them); default every
    candidate of `model`, so that an analysis on top of any effect found later reuses it
    (`diagnose` starts this in the background, before it knows the effect:
    `Background`)."""
    groups = list(model.candidates) if groups is None else list(groups)
    knots, load, exp_name, deepest = state_knots(model, fit)
    basis = make_basis(knots, size)
    _log(verbose, f"  shape: {len(basis.variables)} variable-forms x {size} B-splines at the "
                  f"answer of the {fit.label} fit (one Jacobian; compiles the model with the "
                  f"correction)")
    smodel = model.variant(candidates=groups, shape=basis)
    # The correction's columns by one Jacobian of a model with no more than
    # `JACOBIAN_NODES` nodes and a looser wear tolerance (their cost grows with nodes x
    # steps x columns): they are the design of the test, not its data, so a coarser
    # discretisation of them costs power only, never false alarms (the misfit tested is
    # the fit's own); the answer is refitted at the fit's numerics.
    jmodel = _coarse(smodel, groups, basis)
    ev_j = jmodel.evaluate(_map_u(model, fit.ev.u, jmodel))
    return Design(model.study, tuple(groups), knots, load, exp_name, deepest, smodel, jmodel,
                  ev_j, None, u=_map_u(model, fit.ev.u, smodel))


def pair_tensor(design: Design, a: str, b: str, form: str,
                size: int = TENSOR_SIZE) -> ShapeTensor:
    """The surface over variables `a` and `b` in `form`, on `size` B-splines along each
    (the design's knots: uniform in the same quantile coordinate as the variables')."""
    ka = () if VARIABLES[a][1] else design.knots[form][a]
    kb = () if VARIABLES[b][1] else design.knots[form][b]
    return ShapeTensor(ShapeVariable(a, size, ka, form), ShapeVariable(b, size, kb, form))


def tensor_columns(design: Design, tensor: ShapeTensor, groups=(),
                   verbose: bool = False, model: Model | None = None) -> np.ndarray:
    """The model's derivative (rows, tensor.size) [µm per unit coefficient] with respect to
    each coefficient of the surface `tensor`, at the design's answer: one forward-mode
    Jacobian of the design's (coarse) Jacobian model with the surface as its only
    correction (its own compiled function; cached on the design). Why a run of its own:
    the pair is known only once the variables have been tested, after the design's
    Jacobian; 25 columns of ~170 cost far less than every pair's surface in it.
    `groups`: the candidate groups the fit has on (the others are off at the answer).
    `model`: the model whose program computes them instead (its basis holds `tensor`, its
    Jacobian columns are the surface's: the shape's refit model, `shape.analysis`, so
    that the refit compiles nothing more)."""
    if tensor.label in design.tensors:
        return design.tensors[tensor.label]
    tm = (model if model is not None else
          design.jmodel.variant(candidates=list(groups), shape=ShapeBasis((), (tensor,))))
    t0 = time.perf_counter()
    ev = tm.evaluate(_map_u(design.smodel, design.u, tm))
    cols = np.asarray(ev.J)[:, [tm.index[k] for k in tensor.keys()]]
    _log(verbose, f"    the surface over {tensor.a.name} x {tensor.b.name} ({tensor.form}): "
                  f"{tensor.size} columns, one Jacobian ({time.perf_counter() - t0:.1f} s)")
    design.tensors[tensor.label] = cols
    return cols


class NumericalAhead:
    """`numerical_error_rows` at a fit's answer run in a background thread, for the shape
    analysis of that fit (`take`). Why: the finer level's forward program compiled where
    the analysis asked for it, after the design's Jacobian: on the generator's fatigue
    study (48 x 72, 2 cores) 3-4.6 s of the diagnosis's critical path, while the design's
    run and the law search's compilations (`law.search.compile_ahead`), needed ~20 s
    later, held both cores. Started beside the design (`diagnose`), it is done when the
    analysis asks; the rows are the same forward run's."""

    def __init__(self, model: Model, fit: Fit, groups):
        self.key = (model, fit, tuple(groups))
        cfg = model.study.config
        self.level = f"{2 * cfg.nodes} x {2 * cfg.steps_per_rev}"

        def job():
            e0 = Model.own_evaluations()
            rows = numerical_error_rows(model, fit, False, candidates=list(groups))
            return rows, Model.own_evaluations() - e0

        self._job = Background(job)

    def take(self, model: Model, fit: Fit, groups):
        """((the rows' error [µm] (rows,) or None, the finer level in words), the model
        evaluations it made) where it was made for this model, fit and candidate groups
        (waiting for it), else None (also where it raised: the analysis runs it itself and
        meets the error there)."""
        if self.key[0] is not model or self.key[1] is not fit or self.key[2] != tuple(groups):
            return None
        try:
            rows, evals = self._job.result()
        except Exception:  # noqa: BLE001 (met again where the analysis runs it)
            return None
        return (rows, self.level), evals


def at_answer(model: Model, evaluation, label: str = "base"):
    """A stand-in for the fit of `model` at u = 0 (its start values: the answer of
    calibrate's path, whose coarse `evaluation` holds the snapshots (E, S, N) [µm] and
    sliding distances there), for `prepare_design` before `model` has evaluated."""

    ev = SimpleNamespace(u=np.zeros(len(model.names)), snaps=np.asarray(evaluation.snaps),
                         sliding_m=np.asarray(evaluation.sliding_m))
    return SimpleNamespace(label=label, ev=ev)


@jit
def _cycle_states(p, cfg, hist, regime, h, sliding):
    """Every state variable of one cycle and its wear rate (steps, nodes) [m per step]."""
    _, _, sol = cycle_increment(p, cfg, hist, regime, h, sliding)
    slide, dt = hist.slide[regime], hist.dt[regime]
    z = state_variables(sol.pressure, slide, dt, sliding, hist.angle[regime],
                        hist.load[regime], h)
    rate = archard_rate(p, sol.pressure, slide)
    return {k: jnp.broadcast_to(v, sol.pressure.shape) for k, v in z.items()}, rate


def _weighted_quantiles(x, w, qs):
    order = np.argsort(x)
    x, w = x[order], w[order]
    c = np.cumsum(w)
    if c[-1] <= 0:
        return np.interp(qs, [0.0, 1.0], [x[0], x[-1]])
    return np.interp(np.asarray(qs) * c[-1], c, x)


def state_knots(model: Model, fit: Fit):
    """{form: {name: knots}} of every non-periodic variable: its quantiles at t = 0, 1/Q,
    ..., 1 (`KNOT_QUANTILES` + 1 values, the ends at `RANGE_QUANTILES`) from the states of
    one cycle at the start and at the end of each experiment at the fit: weighted by the
    wear for the factor form (a factor multiplies the wear that is there), by the time
    (every step alike) for the deposit (a deposit is made where Archard puts little: at a
    force reversal the load dips and the sliding stops, and a wear-weighted range would
    leave those steps beyond its end). The sliding distance: uniform over each
    experiment's total, weighted by its wear. Also the joint load over the cycle of the
    experiment that wears most (for the plots)."""
    ext = model.ext
    cfg = ext.cfg.replace(shape=None)
    P = ext.batched_params(jnp.asarray(fit.ev.u))
    samples = {k: ([], [], []) for k in VARIABLES}  # values, wear weights, time weights
    snaps = fit.ev.snaps  # (E, S, N) µm
    deepest = int(np.argmax(snaps[:, -1].max(axis=1)))
    load = {}
    for e in range(snaps.shape[0]):
        p = jax.tree_util.tree_map(lambda x: x[e], P)
        hist = _load_history_jit(p, cfg)
        total = float(fit.ev.sliding_m[e])
        for r in range(hist.load.shape[0]):
            for h, s in ((np.zeros(snaps.shape[2]), 0.0), (snaps[e, -1] * 1e-6, total)):
                z, rate = _cycle_states(p, cfg, hist, r, jnp.asarray(h), jnp.asarray(s))
                w = np.asarray(rate).ravel()
                dt = np.broadcast_to(np.asarray(hist.dt[r])[:, None], rate.shape).ravel()
                for k in samples:
                    if k in ("sliding_distance_m", "worn_depth_um"):
                        continue  # their own samples, below
                    samples[k][0].append(np.asarray(z[k]).ravel())
                    samples[k][1].append(w)
                    samples[k][2].append(dt)
        samples["sliding_distance_m"][0].append(np.linspace(0.0, total, 64))
        for i in (1, 2):
            samples["sliding_distance_m"][i].append(
                np.full(64, max(float(snaps[e, -1].max()), 1e-12)))
        # the depth worn: every node on its way from 0 to its final depth (16 fractions),
        # weighted by the node's wear (the cycles' samples above would put half the
        # weight at the unworn start's 0)
        last = np.clip(snaps[e, -1], 0.0, None)
        frac = np.linspace(0.0, 1.0, 16)[:, None]
        samples["worn_depth_um"][0].append((frac * last[None, :]).ravel())
        for i in (1, 2):
            samples["worn_depth_um"][i].append(
                np.broadcast_to(last[None, :] + 1e-12, (16, len(last))).ravel())
        if e == deepest:
            z0, _ = _cycle_states(p, cfg, hist, 0, jnp.zeros(snaps.shape[2]),
                                  jnp.asarray(0.0))
            n = hist.load.shape[1]
            load = {"phase_deg": np.arange(n) * 360.0 / n,
                    "load_N": np.asarray(hist.load[0]),
                    "angle_deg": np.degrees(np.asarray(hist.angle[0])),
                    "turn_rate_deg_per_s": np.asarray(z0["load_turn_rate_deg_per_s"][:, 0])}
    knots = {"factor": {}, "deposit": {}}
    q0, q1 = RANGE_QUANTILES
    for k, (xs, ws, ts) in samples.items():
        if VARIABLES[k][1]:
            continue
        x = np.concatenate(xs)
        for form, weights in (("factor", ws), ("deposit", ts)):
            zq = _weighted_quantiles(x, np.concatenate(weights),
                                     np.linspace(q0, q1, KNOT_QUANTILES + 1))
            # strictly increasing (a state met at one value only, e.g. one speed)
            span = max(float(zq[-1] - zq[0]), abs(float(zq[0])) * 1e-3, 1e-12)
            zq = np.maximum.accumulate(zq) + np.arange(len(zq)) * span * 1e-9
            knots[form][k] = tuple(float(v) for v in zq)
    return knots, load, model.exp_names[deepest], deepest


def make_basis(knots: dict, size: int = SIZE, forms=FORMS, names=None) -> ShapeBasis:
    """Every variable (or `names`) in each of `forms` (the deposit only along the variables
    of events in the cycle, `DEPOSIT_VARIABLES`)."""
    out = []
    for form in forms:
        for name, (_, periodic, _) in VARIABLES.items():
            if names is not None and name not in names:
                continue
            if form == "deposit" and name not in DEPOSIT_VARIABLES:
                continue
            out.append(ShapeVariable(name, size, () if periodic else knots[form][name],
                                     form))
    return ShapeBasis(tuple(out))


def numerical_error_rows(model: Model, fit: Fit, verbose=False, candidates=None):
    """The rows' numerical error at the fit's answer (µm): the same model at twice the nodes
    and steps per cycle (and half the fixed update M, or a quarter of the adaptive
    tolerance) minus the model, one forward run; None where it cannot be run. The error of
    the finer level is left in (for second-order convergence ~ a quarter). `candidates`:
    those the finer model carries (default: the fit's; more, held at off, share its
    compiled function with a later analysis)."""

    st = model.study
    cfg = st.config
    finer = dreplace(st, config=cfg.replace(nodes=2 * cfg.nodes,
                                            steps_per_rev=2 * cfg.steps_per_rev),
                     revolutions_per_update=max(st.revolutions_per_update / 2, 1.0),
                     wear_tolerance_um=st.wear_tolerance_um / 4)
    _log(verbose, f"    the model's numerical error: one run at {2 * cfg.nodes} x "
                  f"{2 * cfg.steps_per_rev}")
    if candidates is None:
        candidates = [g for g in fit.groups if g in model.candidates]
    fm = Model(finer, keys=model.keys, start=model.start, candidates=candidates,
               contact=model.contact)
    u = np.zeros(len(fm.names))
    for i, name in enumerate(model.names):
        if name in fm.index:
            u[fm.index[name]] = fit.ev.u[i]
    rows = fm.predict(u)
    if not np.all(np.isfinite(rows)):
        return None
    return rows - fit.ev.pred


# eager, the mechanism's load history costs ~0.5 s per experiment
_load_history_jit = jit(load_history)


def _coarse(smodel: Model, groups, basis) -> Model:
    """`smodel` with no more than `JACOBIAN_NODES` nodes and, for the adaptive integrator,
    `JACOBIAN_TOLERANCE` times its tolerance (itself where neither changes it). The steps
    per cycle stay the fit's: a deposit at the reversals lives on how the load is sampled
    in time (measured: the columns of a 60-step model predicted a 72-step model's misfit
    falling 85 %, where it fell 57 %)."""

    st = smodel.study
    cfg = st.config
    nodes = min(cfg.nodes, JACOBIAN_NODES)
    adaptive = bool(smodel.ext.schedule.adaptive)
    if nodes == cfg.nodes and not adaptive:
        return smodel
    coarse = dreplace(st, config=cfg.replace(nodes=nodes))
    if adaptive:
        coarse = dreplace(coarse, wear_tolerance_um=st.wear_tolerance_um * JACOBIAN_TOLERANCE)
    return Model(coarse, keys=smodel.keys, start=smodel.start, candidates=groups,
                 contact=smodel.contact, shape=basis)


def _map_u(model: Model, u_model, other: Model) -> np.ndarray:
    """u of `other` holding `model`'s values at u_model (its extra columns at 0)."""
    u = np.zeros(len(other.names))
    for i, name in enumerate(model.names):
        if name in other.index:
            u[other.index[name]] = u_model[i]
    return u
