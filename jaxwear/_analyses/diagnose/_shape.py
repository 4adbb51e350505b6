"""The shape of the missing wear: a smooth correction of the local wear along the state
variables, learned from the misfit through the wear loop (design.md §7, `--shape`).

Two forms (`effects.shape`): a **factor** exp(g(z)) of the local Archard rate, and a
**deposit** e(z) ≥ 0 per step where the pin presses (extra wear not tied to sliding), each
g_v or e_v on `SIZE` cubic B-splines along one state variable z. All coefficients zero is
the fit's model exactly, so one forward-mode Jacobian of the model with every variable's
coefficients in both forms switched on (one compiled function, one evaluation) linearises
them all. On the host, in the whitened system the fits see:

1. **What is not physics.** The fit's own free parameters (K_d, clearances, the effect's
   strengths) and the model's own numerical error are nuisance columns projected off the
   misfit (Frisch-Waugh): the numerical error is the difference of the rows at twice the
   nodes and steps (and half the fixed update, or a quarter of the tolerance) at the fit's
   answer, one forward run, so a discretisation misfit at any numerics a user sets is not
   read as missing wear. Noise correlated along a scan (a profilometer's stylus, surface
   roughness) is prewhitened (AR(1), its coefficient read from the lag-1 correlation of
   the data's second differences, where smooth misfit cancels).
2. **Alone.** Per variable and form, a penalised fit (roughness λ Σ (second difference)²,
   λ by generalised cross-validation); T = ΔRSS/σ² with its null simulated (`DRAWS`
   draws, λ re-chosen in each, σ̂ with its ν dof); significant when p < α / (variables ×
   forms). Its share of the misfit, net of the noise it would take up, is not clipped.
3. **Together.** Per form, one additive fit over all its variables (one GCV λ): the share
   each variable adds to the others' fit (unique) says which carry the misfit together;
   a variable significant alone whose unique share is not is a stand-in for the carrier
   its fitted correction resembles most (speed and load turn rate both follow crank speed
   on the paper's rig).
4. **The answer.** `best` is the significant variable that explains most (design.md §7; ties
   within ln 20 of AIC are named as alternatives), `form` its form. The correction of that
   form over the variables that carry the misfit is refitted through the wear loop with
   its true Jacobian by the least-squares core (penalty and, for a factor, zero sum as
   prior rows; a deposit ≥ 0 by bounds); its RMSE is the real model's.
5. **When and where** (`_shape_map`): that correction's extra wear over the cycle and over
   the bore, with bands, the load's reversals and peak marked, and a sentence.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass, field, replace
from dataclasses import replace as dreplace
from types import SimpleNamespace

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from scipy.stats import chi2

from jaxwear._analyses.diagnose import _shape_linear as lin
from jaxwear._analyses.diagnose._fit import Fit, _log
from jaxwear._analyses.diagnose._model import Model
from jaxwear._analyses.diagnose._shape_linear import DRAWS, trend
from jaxwear._analyses.diagnose._shape_map import compile_maps, when_where
from jaxwear._analyses.diagnose._shape_text import describe, threshold
from jaxwear._analyses.diagnose._stats import ALPHA, neighbour_differences
from jaxwear._core.jsonfmt import json_float as _num
from jaxwear._inference import lsq
from jaxwear._physics.cycle import cycle_increment
from jaxwear._physics.effects.shape import (
    DEPOSIT_VARIABLES,
    FORMS,
    VARIABLES,
    ShapeBasis,
    ShapeVariable,
    state_variables,
)
from jaxwear._physics.load import load_history

SIZE = 10  # B-splines per variable
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
class VariableShape:
    """The correction along one variable in one form (JSON: `to_json`). `z`, `g` (factor:
    ln of the rate factor; deposit: e in nm·rad of depth per step) and the band on a grid
    over the range met in the data."""

    name: str
    unit: str
    form: str
    explained_fraction: float
    unique_fraction: float
    dof: float
    p_value: float
    significant: bool
    peak_at: float
    lower: float
    upper: float
    lam: float
    statistic: float  # T = ΔRSS/σ²
    aic: float
    z: np.ndarray = field(repr=False)
    g: np.ndarray = field(repr=False)
    g_lower: np.ndarray = field(repr=False)
    g_upper: np.ndarray = field(repr=False)
    coef: np.ndarray = field(repr=False)
    extra_wear_um: np.ndarray = field(repr=False)  # linearised Δdepth over the bore (N,)
    range: tuple = (0.0, 0.0)
    carries: bool = False  # its unique share is significant in the form's joint fit
    stand_in_for: str | None = None
    refit_rmse_um: float | None = None

    @property
    def label(self) -> str:
        return self.name if self.form == "factor" else f"deposit:{self.name}"

    def threshold(self, rising: bool = True) -> float:
        """Where the correction steps up (`rising`; else down), in the variable's unit: the
        best two-level step fitted to it, weighted by its band (`_shape_text.threshold`).
        For a rate that jumps at a threshold, the threshold."""
        return threshold(self, rising)

    def to_json(self) -> dict:
        return {"name": self.name, "unit": self.unit, "form": self.form,
                "explained_fraction": _num(self.explained_fraction),
                "unique_fraction": _num(self.unique_fraction), "dof": _num(self.dof),
                "p_value": _num(self.p_value), "significant": bool(self.significant),
                "peak_at": _num(self.peak_at), "lower": _num(self.lower),
                "upper": _num(self.upper), "range": [_num(self.range[0]), _num(self.range[1])],
                "penalty": _num(self.lam), "statistic": _num(self.statistic),
                "aic": _num(self.aic), "trend": _num(trend(self)),
                "carries_the_misfit": bool(self.carries), "stand_in_for": self.stand_in_for,
                "refit_rmse_um": _num(self.refit_rmse_um)}


@dataclass(frozen=True)
class ShapeResult:
    """The shape analysis on top of one fit (`after`: "base" or the effect's name)."""

    after: str
    best: str | None
    form: str | None
    variables: tuple  # VariableShape of both forms
    alpha: float
    noise_um: float
    rmse_before_um: float
    rmse_after_um: float | None  # with the refitted correction, through the loop
    evaluations: int
    status: str  # the refit's (lsq) status, or "none"
    sentence: str
    phase_load: dict = field(default_factory=dict, repr=False)  # for the phase plot
    bore_deg: np.ndarray = field(default=None, repr=False)
    experiment: str = ""  # whose bore the extra wear is drawn on
    alternatives: tuple = ()  # variable labels the data cannot tell from `best`
    forms: dict = field(default_factory=dict)  # form -> joint fit summary
    carriers: tuple = ()  # the variables of the refitted correction
    correction: dict = field(default_factory=dict, repr=False)  # for the effect file
    when_where: object = None  # _shape_map.WhenWhere
    numerical: dict = field(default_factory=dict)
    effect_file: str | None = None
    design: object = field(default=None, repr=False)  # `Design`, for a later analysis
    pending: object = field(default=None, repr=False)  # the refit still to run (`defer`)
    pngs: dict = field(default_factory=dict, repr=False)  # figures drawn beforehand
    # the linearised system the variables were tested on (whitened, nuisance projected
    # off): {"blocks": {label: (A, S, Z, cols, var)}, "rho": misfit}, for the law search's
    # pre-screen (`_law`)
    linear: dict = field(default_factory=dict, repr=False)
    law: object = None  # `_law.LawResult`: the law found from the shape, or None


    def finished(self) -> ShapeResult:
        """This result with its refit run (itself if none is pending)."""
        if self.pending is None:
            return self
        return replace(self.pending(), pngs=self.pngs)

    def settled_labels(self) -> tuple:
        """Labels of the variable figures the pending refit will not change (all but its
        carriers')."""
        refitted = {f"deposit:{n}" if self.form == "deposit" else n for n in self.carriers}
        return tuple(v.label for v in self.variables if v.label not in refitted)

    def form_variables(self, form: str | None = None) -> tuple:
        form = form or self.form or "factor"
        return tuple(v for v in self.variables if v.form == form)

    def to_json(self) -> dict:
        return {"after": self.after, "best": self.best, "form": self.form,
                "rmse_after_um": _num(self.rmse_after_um), "effect_file": self.effect_file,
                "variables": [v.to_json() for v in self.form_variables()],
                "other_form": {"form": _other(self.form or "factor"),
                               "variables": [v.to_json() for v in self.form_variables(
                                   _other(self.form or "factor"))]},
                "alternatives": list(self.alternatives),
                "carriers": list(self.carriers),
                "forms": self.forms,
                "when_where": None if self.when_where is None else self.when_where.to_json(),
                "alpha": self.alpha, "noise_um": _num(self.noise_um),
                "rmse_before_um": _num(self.rmse_before_um),
                "model_evaluations": self.evaluations, "refit_status": self.status,
                "numerical_error": self.numerical, "summary": self.sentence,
                **({"law": self.law.to_json()} if self.law is not None else {})}

    def variable(self, name: str, form: str | None = None) -> VariableShape:
        form = form or self.form or "factor"
        return next(v for v in self.variables if v.name == name and v.form == form)


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


def at_answer(model: Model, evaluation, label: str = "base"):
    """A stand-in for the fit of `model` at u = 0 (its start values: the answer of
    calibrate's path, whose coarse `evaluation` holds the snapshots (E, S, N) [µm] and
    sliding distances there), for `prepare_design` before `model` has evaluated."""

    ev = SimpleNamespace(u=np.zeros(len(model.names)), snaps=np.asarray(evaluation.snaps),
                         sliding_m=np.asarray(evaluation.sliding_m))
    return SimpleNamespace(label=label, ev=ev)


class Background:
    """`fn(*args, **kw)` in a daemon thread (`result()` joins it and re-raises what it
    raised). Why: the shape's design Jacobian (~25 s, most of it compilation) needs only
    the base fit, so `diagnose --shape` computes it while the verdict's screens and refits
    run; XLA's compilation and runs release the interpreter."""

    def __init__(self, fn, *args, **kw):

        self._out = None
        self._err = None

        def run():
            try:
                self._out = fn(*args, **kw)
            except BaseException as e:  # re-raised in the caller's thread
                self._err = e

        self._thread = threading.Thread(target=run, daemon=True, name="jaxwear-shape")
        self._thread.start()

    def result(self):
        self._thread.join()
        if self._err is not None:
            raise self._err
        return self._out


def _other(form: str) -> str:
    return "deposit" if form == "factor" else "factor"


# -- the range of each variable met in the data ---------------------------------------------

@eqx.filter_jit
def _cycle_states(p, cfg, hist, regime, h, sliding):
    """Every state variable of one cycle and its wear rate (steps, nodes) [m per step]."""
    _, _, sol = cycle_increment(p, cfg, hist, regime, h, sliding)
    slide, dt = hist.slide[regime], hist.dt[regime]
    z = state_variables(sol.pressure, slide, dt, sliding, hist.angle[regime],
                        hist.load[regime], h)
    rate = p.wear_coefficient * sol.pressure * slide[:, None]
    return {k: jnp.broadcast_to(v, sol.pressure.shape) for k, v in z.items()}, rate


# eager, the mechanism's load history costs ~0.5 s per experiment
_load_history_jit = eqx.filter_jit(load_history)


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


def _band_of_peak(z, g_hat, G, periodic, level):
    peak = float(z[int(np.argmax(g_hat))])
    draws = z[np.argmax(G, axis=-1)]
    q = ((1 - level) / 2, (1 + level) / 2)
    if periodic:
        d = np.mod(draws - peak + 180.0, 360.0) - 180.0
        lo, hi = np.quantile(d, q)
        return peak, float(np.mod(peak + lo, 360.0)), float(np.mod(peak + hi, 360.0))
    lo, hi = np.quantile(draws, q)
    return peak, float(lo), float(hi)


# -- the model's own numerical error ----------------------------------------------------------

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


# -- the analysis ---------------------------------------------------------------------------

def shape_analysis(model: Model, fit: Fit, noise_um: float, nu: float, *, after: str = "base",
                   seed: int = 0, draws: int = DRAWS, size: int = SIZE,
                   verbose: bool = False, numerical: bool = True,
                   numerical_um: np.ndarray | None = None,
                   design: Design | None = None, defer: bool = False) -> ShapeResult:
    """The shape of the misfit left by `fit` (of `model`) along every state variable, in
    both forms (module docstring). `noise_um` σ [µm] with `nu` degrees of freedom
    (diagnose's noise level). `numerical`: count the model's numerical error: the rows of
    a finer level minus the fit's rows at its answer, `numerical_um` (rows,) [µm] where the
    caller has them (calibrate's resolution check ran that forward run at this answer),
    else one forward run at twice the nodes and steps.

    `design` (`prepare_design`, or an earlier analysis's `ShapeResult.design`): the basis,
    the states met in the data and the correction's columns, computed at `fit`'s answer
    (e.g. in the background) or at another fit's on the same model (the base fit's, for
    the analysis on top of an effect found): then this analysis runs no model of its own
    until its refit. Its columns are linearised at that other answer: an effect found
    moves them by its rate factor, which costs the test power only, never its level (the
    misfit tested and the fit's own columns projected off are this fit's); the numerical
    error's rows, also from there, enter one column per experiment, each with its own
    scale, as the effect rescales each experiment's wear.

    `defer`: where a variable is significant, return before the refit through the loop
    (status "pending"; `ShapeResult.finished()` runs it), so that the caller can do other
    work meanwhile (draw the figures the refit does not change)."""

    evals0 = Model.evaluations
    own_groups = [g for g in model.candidates if g in fit.groups]
    spent = 0  # evaluations of a design computed before this call, not yet counted
    if design is None:
        design = prepare_design(model, fit, groups=own_groups, size=size, verbose=verbose)
    else:
        spent = design.evaluations
    if design.study is not model.study or not set(own_groups) <= set(design.groups):
        raise ValueError("a shape design is reused on another model")
    # linearised at this fit's answer, or at another one (an earlier fit's)
    reused = not np.array_equal(design.u, _map_u(model, fit.ev.u, design.smodel))
    if spent and not reused:
        _log(verbose, f"  shape of the missing wear after {after}: its columns were computed "
                      f"while the verdict ran")
    load, exp_name, deepest = design.load, design.exp_name, design.deepest
    smodel, jmodel, ev_j = design.smodel, design.jmodel, design.ev_j
    basis = smodel.ext.cfg.shape
    if reused:
        _log(verbose, f"  shape of the missing wear after {after}: {len(basis.variables)} "
                      f"variable-forms x {size} B-splines (the columns of the analysis "
                      f"before, no model run)")
    u = _map_u(model, fit.ev.u, smodel)
    ev = fit.ev
    sigma = max(float(noise_um), 1e-12)
    free_base = [smodel.index[model.names[i]] for i in np.flatnonzero(fit.mask)]
    n = smodel.n
    # whitened system: data rows /σ, prior rows in SD units; the fit's own columns from
    # the fit, the correction's from the Jacobian model
    J = np.zeros((n, len(smodel.names)))
    Jp = np.zeros((len(ev.r_prior), len(smodel.names)))
    for i, name in enumerate(model.names):
        if name in smodel.index:
            J[:, smodel.index[name]] = ev.J[:, i]
            Jp[:, smodel.index[name]] = ev.J_prior[:, i]
    for name in basis.keys():
        J[:, smodel.index[name]] = ev_j.J[:, jmodel.index[name]]
    Jw = np.vstack([J / sigma, Jp])
    rho_full = -np.concatenate([ev.r / sigma, ev.r_prior])
    # correlated noise along the scans: prewhiten (AR(1) read from second differences)
    e, mids = neighbour_differences(model, model.measured)
    phi, z_phi = lin.ar1_coefficient(e, mids)
    Jw = lin.prewhiten(Jw, model.series, phi, n)
    rho_full = lin.prewhiten(rho_full[:, None], model.series, phi, n)[:, 0]
    nuisance = [Jw[:, free_base]]
    num_info = {"counted": False, "ar1_coefficient": phi, "ar1_z": z_phi}
    d = None
    elsewhere = False  # d taken at another answer (the design's): a column per experiment
    if numerical:
        if reused and design.numerical_um is not None:
            d, elsewhere = design.numerical_um, True
        elif numerical_um is not None:
            d = np.asarray(numerical_um, np.float64)
            _log(verbose, "    the model's numerical error: the rows of the resolution "
                          "check at this answer (no run of its own)")
        else:
            d = numerical_error_rows(model, fit, verbose, candidates=own_groups)
        if d is not None and not np.all(np.isfinite(d)):
            d = None
        if d is not None:
            exps = np.asarray(model.row_exp)
            parts = ([np.where(exps == k, d, 0.0) for k in np.unique(exps)] if elsewhere
                     else [d])
            for part in parts:
                if np.any(part):
                    nuisance.append(lin.prewhiten(np.concatenate(
                        [part / sigma, np.zeros(len(ev.r_prior))])[:, None],
                        model.series, phi, n))
            num_info.update(counted=True, rms_um=float(np.sqrt(np.mean(d ** 2))),
                            max_um=float(np.max(np.abs(d))),
                            columns=len(nuisance) - 1)
    Xb = np.hstack(nuisance)
    Qb = np.linalg.qr(Xb)[0] if Xb.shape[1] else np.zeros((len(rho_full), 0))
    proj = lambda X: X - Qb @ (Qb.T @ X)  # noqa: E731
    rho = proj(rho_full[:, None])[:, 0]
    n_res = n - Qb.shape[1]
    rss0 = float(rho @ rho)
    excess = rss0 - n_res  # the misfit beyond the noise, in σ² units
    rng = np.random.default_rng(seed)
    Zs = lin.sum_zero(size)
    blocks = {}
    results = []
    for var in basis.variables:
        cols = [smodel.index[k] for k in var.keys()]
        Z = Zs if var.form == "factor" else np.eye(size)
        A = proj(Jw[:, cols] @ Z)
        S = Z.T @ var.roughness() @ Z
        blocks[var.label] = (A, S, Z, cols, var)
        pf = lin.penalised_fit(A, S, rho, n_res, nu, rng, draws)
        c = Z @ pf.a
        if var.form == "deposit":
            c = lin.nonnegative_fit(A, S, rho, pf.lam)
        jcols = [jmodel.index[k] for k in var.keys()]
        results.append(_variable_result(var, pf, c, Z, excess, rss0, rng, ev_j, deepest,
                                        jcols))
        v = results[-1]
        _log(verbose, f"    {v.label}: explains {v.explained_fraction:.0%} of the misfit, dof "
                      f"{v.dof:.1f}, p {v.p_value:.1e}, peak at {v.peak_at:.4g} {v.unit}")
    alpha_each = ALPHA / len(results)
    results = [replace(v, significant=v.p_value < alpha_each) for v in results]
    forms = {}
    for form in FORMS:
        results, forms[form] = _joint(form, results, blocks, rho, rss0, excess, n_res, nu, rng,
                                      alpha_each, verbose)
    rmse_before = float(np.sqrt(np.mean(ev.r ** 2)))
    sig = [v for v in results if v.significant]
    best = form = None
    alternatives, carriers = [], ()
    if sig:
        top, alternatives = choose_best(results)
        best, form = top.name, top.form
        carriers = _carriers(results, top)
    design_out = replace(design, evaluations=0,
                         numerical_um=design.numerical_um if elsewhere else d)

    def result(results, rmse_after, status, correction, ww, evaluations):
        sentence = describe(best, form, results, load, after, alternatives, carriers, ww)
        return ShapeResult(after, best, form, tuple(results), ALPHA, sigma, rmse_before,
                           rmse_after, evaluations, status, sentence, load,
                           np.arange(jmodel.ext.cfg.nodes) * 360.0 / jmodel.ext.cfg.nodes,
                           exp_name, tuple(alternatives), forms, tuple(carriers), correction,
                           ww, num_info, design=design_out,
                           linear={"blocks": blocks, "rho": rho})

    def finish() -> ShapeResult:
        """The refit through the loop and the when/where map (the costly part)."""
        e0 = Model.evaluations
        rmse_after, status, corr_model, u_fit, cov, snaps = _refit(
            smodel, own_groups, ev, u, free_base, blocks, carriers, form, rho, n_res, sigma,
            Jw, rho_full, verbose, deepest)
        correction = _correction(corr_model, u_fit, carriers, form)
        done = [replace(v, refit_rmse_um=rmse_after) if v.name in carriers
                and v.form == form else v for v in results]
        ww = when_where(corr_model, u_fit, cov, exp_name, deepest, LEVEL, snaps=snaps)
        return result(done, rmse_after, status, correction, ww,
                      linear.evaluations + Model.evaluations - e0)

    linear = result(results, None, "none", {}, None, Model.evaluations - evals0 + spent)
    if not sig:
        return linear
    linear = replace(linear, status="pending", pending=finish)
    return linear if defer else linear.finished()


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


def choose_best(results):
    """(the best variable-form, the labels of its alternatives): the significant one that
    explains most of the misfit (design.md §7), equal shares broken by the lower AIC; the
    others whose AIC is within ln 20 of it (or lower) are alternatives the data cannot tell
    from it. A ranking by the data, never by the order the variables come in."""
    sig = [v for v in results if v.significant]
    top = max(sig, key=lambda v: (v.explained_fraction, -v.aic))
    alternatives = [f"{v.name}" if v.form == "factor" else f"deposit:{v.name}"
                    for v in sorted(sig, key=lambda v: v.aic)
                    if v is not top and v.aic - top.aic < 2.0 * math.log(20.0)]
    return top, alternatives


def _variable_result(var, pf, c, Z, excess, rss0, rng, ev, deepest, cols) -> VariableShape:
    zg = (np.linspace(0.0, 360.0, 181)[:-1] if var.periodic else
          var.at_coordinate(np.linspace(0.0, 1.0, 181)))
    Bg = np.asarray(var.basis(jnp.asarray(zg)))
    g = Bg @ c
    w, V = np.linalg.eigh(0.5 * (pf.cov + pf.cov.T))
    L = V * np.sqrt(np.clip(w, 0.0, None))
    C = (pf.a + rng.standard_normal((4000, len(pf.a))) @ L.T) @ Z.T
    G = C @ Bg.T
    q = ((1 - LEVEL) / 2, (1 + LEVEL) / 2)
    g_lo, g_hi = np.quantile(G, q, axis=0)
    peak, lo, hi = _band_of_peak(zg, g, G, var.periodic, LEVEL)
    J_snap = None if ev.J_snaps is None else ev.J_snaps[deepest, -1][:, cols]
    extra = (J_snap @ c) if J_snap is not None else np.zeros(0)
    return VariableShape(
        var.name, var.unit, var.form, lin.explained(pf.drop, pf.dof, excess, rss0), math.nan,
        pf.dof, pf.p, False, peak, lo, hi, pf.lam, pf.drop, rss0 - pf.drop + 2.0 * pf.dof,
        zg, g, g_lo, g_hi, c, extra, (float(zg[0]), float(zg[-1])))


def _joint(form, results, blocks, rho, rss0, excess, n_res, nu, rng, alpha_each, verbose):
    """The form's joint fit: its share, p-value, and each variable's unique share; who
    carries the misfit and who stands in for whom."""

    mine = [v for v in results if v.form == form]
    fit, unique = lin.joint_fit([blocks[v.label][:2] for v in mine], rho, n_res, nu, rng,
                                JOINT_DRAWS)
    fitted = {}
    for v in mine:
        A = blocks[v.label][0]
        Z = blocks[v.label][2]
        fitted[v.name] = A @ np.linalg.lstsq(Z, v.coef, rcond=None)[0]
    out = {}
    for v, d in zip(mine, unique):
        p_u = float(chi2.sf(max(d, 0.0), max(v.dof, 1.0)))
        out[v.name] = replace(v, unique_fraction=lin.explained(d, 0.0, excess, rss0),
                              carries=bool(v.significant and p_u < alpha_each))
    carriers = [k for k, v in out.items() if v.carries]
    if not carriers:
        # none adds significantly to the others: the significant ones stand in for each
        # other (the experiments vary them together); the one explaining most leads
        sig = [v for v in out.values() if v.significant]
        if sig:
            lead = max(sig, key=lambda v: v.explained_fraction)
            carriers = [lead.name]
            out[lead.name] = replace(lead, carries=True)
    for k, v in out.items():
        if v.significant and not v.carries and k not in carriers:
            f = fitted[k]
            cos = {w: abs(float(f @ fitted[w])) / max(
                float(np.linalg.norm(f) * np.linalg.norm(fitted[w])), 1e-300)
                for w in carriers}
            out[k] = replace(v, stand_in_for=max(cos, key=cos.get))
    summary = {"explained_fraction": lin.explained(fit.drop, fit.dof, excess, rss0),
               "dof": fit.dof, "p_value": fit.p, "carriers": carriers,
               "stand_ins": {k: v.stand_in_for for k, v in out.items() if v.stand_in_for}}
    _log(verbose, f"    {form}, all variables together: explains "
                  f"{summary['explained_fraction']:.0%}, p {fit.p:.1e}; carried by "
                  f"{', '.join(carriers) or 'none'}")
    return [out.get(v.name, v) if v.form == form else v for v in results], summary


def _carriers(results, top) -> tuple:
    """The variables of the refitted correction: the best, then the others of its form
    that carry the misfit jointly (at most `MAX_CARRIERS`), by unique share."""
    others = sorted([v for v in results if v.form == top.form and v.carries
                     and v.name != top.name], key=lambda v: -v.unique_fraction)
    return tuple([top.name] + [v.name for v in others][:MAX_CARRIERS - 1])


def _refit(smodel: Model, groups, ev, u, free_base, blocks, carriers, form, rho, n_res,
           sigma, Jw, rho_full, verbose, deepest: int):
    """The correction of `form` along the `carriers`, refitted with the fit's own
    parameters through the wear loop by the one least-squares core, with its true Jacobian
    (a model with those columns only), the roughness penalty (at the linearised λ) and, for
    a factor, the zero sum of each variable's coefficients and N(0, FACTOR_SD²) on each as
    prior rows; a deposit ≥ 0 by bounds. Returns (RMSE [µm], status, the model, u at the
    answer, covariance of u, its snapshots (E, S, N) [µm] from the last evaluation, or
    None)."""

    labels = [n if form == "factor" else f"deposit:{n}" for n in carriers]
    vars_ = [blocks[lab][4] for lab in labels]
    # the fit's own candidate groups only (the design may carry more, held at off)
    cm = smodel.variant(candidates=list(groups), shape=ShapeBasis(tuple(vars_)))
    # the when/where map of this model compiles in the background while the refit runs

    maps = Background(compile_maps, cm, deepest)
    u0 = _map_u(smodel, u, cm)
    # the joint linearised start over the carriers (their GCV penalty)
    A, S = lin.block_penalty([blocks[lab][:2] for lab in labels])
    pf = lin.penalised_fit(A, S, rho, n_res, math.inf, None, 0)
    lam = pf.lam
    a = lin.nonnegative_fit(A, S, rho, lam) if form == "deposit" else pf.a
    k = 0
    shift = rho_full.copy()
    for lab in labels:
        _, _, Z, cols_v, var = blocks[lab]
        m = Z.shape[1]
        c = Z @ a[k:k + m]
        k += m
        for key, val in zip(var.keys(), c):
            u0[cm.index[key]] = val
        shift = shift - Jw[:, cols_v] @ c
    # the fit's own parameters move with the correction (K_d takes its level): their
    # least-squares step on what the correction leaves
    if free_base:
        Xb = Jw[:, free_base]
        du = np.linalg.lstsq(Xb, shift, rcond=None)[0]
        for i, d in zip(free_base, du):
            u0[cm.index[smodel.names[i]]] += d
    cols = [cm.index[key] for var in vars_ for key in var.keys()]
    free = np.zeros(len(cm.names), bool)
    base_names = [smodel.names[i] for i in free_base]
    free[[cm.index[nm] for nm in base_names]] = True
    free[cols] = True
    lo, hi = cm.bounds_u()
    D = [np.linalg.cholesky(v.roughness() + 1e-12 * np.eye(v.size)).T for v in vars_]

    def evaluate(v):
        e = cm.evaluate(v)
        pt = e.point()
        rows, J = [], []
        k = 0
        for var, Dv in zip(vars_, D):
            idx = [cm.index[key] for key in var.keys()]
            c = v[idx]
            w = math.sqrt(lam)
            r = w * (Dv @ c)
            Jr = np.zeros((len(r), len(v)))
            Jr[:, idx] = w * Dv
            rows.append(r), J.append(Jr)
            if var.form == "factor":  # a level shift of g is K_d's, not the correction's
                r1 = np.array([np.sum(c) / (0.01 * var.size)])
                J1 = np.zeros((1, len(v)))
                J1[0, idx] = 1.0 / (0.01 * var.size)
                rows.append(r1), J.append(J1)
                # g = ln of the rate factor, N(0, FACTOR_SD²) per coefficient
                rows.append(c / FACTOR_SD)
                J2 = np.zeros((len(c), len(v)))
                J2[np.arange(len(c)), idx] = 1.0 / FACTOR_SD
                J.append(J2)
            k += 1
        return replace(pt, r_prior=np.concatenate([pt.r_prior, *rows]),
                       J_prior=np.vstack([pt.J_prior, *J]))

    log = (lambda m: _log(True, m)) if verbose else None
    _log(verbose, f"    refit of the {form} correction along {', '.join(carriers)} through the "
                  f"loop (true Jacobian)")
    out = lsq.solve(evaluate, np.clip(u0, lo, hi), free=free, lower=lo, upper=hi,
                    noise_um=sigma, max_evaluations=REFIT_EVALUATIONS, se_tol=0.1,
                    project=cm.packing.project, label=f"    shape {form}", log=log)
    maps.result()
    r = out.point.r
    snaps = getattr(out.point.extra, "snaps", None)
    if snaps is not None and not np.array_equal(np.asarray(out.point.u), np.asarray(out.u)):
        snaps = None
    return (float(np.sqrt(np.mean(r ** 2))), out.status, cm, out.u, _full_cov(out, free),
            snaps)


def _full_cov(out: lsq.Outcome, free) -> np.ndarray:
    """The covariance of all of u (P, P), zero on held columns."""
    P = len(free)
    C = np.zeros((P, P))
    idx = np.flatnonzero(free)
    cov = out.errors.cov if out.errors is not None else out.cov.cov
    C[np.ix_(idx, idx)] = np.where(np.isfinite(cov), cov, 0.0)
    return C


def _correction(cm: Model, u, carriers, form) -> dict:
    """The refitted correction as data (for the effect file): per variable its form,
    size, knots and coefficients."""
    out = {"form": form, "variables": []}
    for var in cm.ext.cfg.shape.variables:
        out["variables"].append({"name": var.name, "form": var.form, "size": var.size,
                                 "knots": list(var.knots),
                                 "coefficients": [float(u[cm.index[k]]) for k in var.keys()]})
    return out
