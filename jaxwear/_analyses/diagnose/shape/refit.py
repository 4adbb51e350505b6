"""The shape's correction refitted through the wear loop on its carrying variables (the
one least-squares core), and the correction as data for the effect file."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from jaxwear._analyses.diagnose._fit import _log
from jaxwear._analyses.diagnose._model import Model
from jaxwear._analyses.diagnose.shape import linear as lin
from jaxwear._analyses.diagnose.shape.design import (
    FACTOR_SD,
    MAX_CARRIERS,
    REFIT_EVALUATIONS,
    _map_u,
)
from jaxwear._analyses.diagnose.shape.map import compile_maps
from jaxwear._core.background import Background
from jaxwear._inference import lsq
from jaxwear._inference.evaluation import seeds
from jaxwear._physics.effects.shape import ShapeBasis

# The refit's answer is its misfit (the RMSE base -> shape), not its spline's coefficients:
# it stops once 3 evaluations together lower ½χ² by less than 1 (χ² by 2: no comparison
# the report makes turns on it). Measured on the running_pressure study: both refits ran to
# their budget of 10 at 0.3338 -> 0.3333 µm (½χ² ~1 over the last seven), 20 s each.
SETTLED_CHI2 = 1.0
# ... or once its last 3 accepted steps together lowered the data's RMSE by less than 0.4 %
# (`lsq.solve`'s `settled_rmse`). Why: the refit's RMSE enters only comparisons with a
# tolerance of 1 % (`law.search.as_shape`, `LOO_TIE`) or 5 % (`LAW_WORSE`), and the shape's
# refits creep: measured on the generator's `fatigue` study (48 x 72, 2026-11-29), from the
# 5th evaluation on by 2-8 of ½χ² per evaluation (½χ² ~1800; 0.06-0.2 % of the RMSE) with
# Gauss-Newton steps of 3-6 standard errors along flat directions, which neither the step
# rule (0.1 SE) nor `SETTLED_CHI2` can stop: the first refit spent its 10 evaluations
# (0.3351 -> 0.3339 µm over the 5th-8th, 0.3340 at the 10th; ~5.5 s of CPU each, 51
# Jacobian columns). At 0.4 % it stops at the 8th (0.3339 µm); at a pace that only
# slows, the two evaluations left could have lowered the RMSE by less than 0.3 %, under a
# third of the 1 % tie. On g_step_p_power_v the first refit stops at the 7th (0.3149 µm)
# where `SETTLED_CHI2` stopped it at the 9th (0.3148).
SETTLED_RMSE = 0.004
# Where the linearised start is not usable (the model wears through, overflows or cannot be
# integrated there), the refit starts again at these fractions of it; 0 is the fit's own
# answer, a point of the model by construction. Measured on the generator's `fatigue`
# study (seed 1, 48 x 72): the joint linearised start along sliding speed and pressure with
# the speed x pressure surface could not be integrated ("the adaptive loop ran out of
# attempts"), the refit ended at its start ("unusable") and `rmse_after_um` was null, so
# the law search's check against the shape was skipped; from half of it the refit reached
# 0.338 µm (base 0.511). (That start's coefficients, up to 14, came from directions the data
# hardly see; a factor's start now carries the refit's own prior, `_factor_start`, and is
# integrated there: these fractions are the fallback for a start that still is not.)
START_FRACTIONS = (0.5, 0.0)
# The refit integrates at this many times the study's wear tolerance (adaptive integrator).
# Why: its correction makes the local rate a steep function of the state (a factor e^g of
# the pressure), so at the study's tolerance its runs took 107-385 adaptive steps, 3-10x
# the other models' (the generator's `fatigue` study, 48 x 72: ~2.5 s a Jacobian of 23
# tangents, on the diagnosis's critical path). Its answer is its RMSE, which enters only
# comparisons with a tolerance of 1 % or more (see `SETTLED_RMSE`). Measured there, at
# four of the refit's points against a run at a quarter of the tolerance: at 5x the rows
# moved by 0.0007-0.0029 µm RMS (noise 0.30 µm) and the RMSE by at most 0.1 % (a tenth of
# that tie); at 10x by up to 0.018 µm RMS and 0.65 %. The JSON says the tolerance
# (`shape.refit_tolerance_um`).
REFIT_TOLERANCE = 5.0


def _carriers(results, top) -> tuple:
    """The variables of the refitted correction: the best, then the others of its form
    that carry the misfit jointly (at most `MAX_CARRIERS`), by unique share."""
    others = sorted([v for v in results if v.form == top.form and v.carries
                     and v.name != top.name], key=lambda v: -v.unique_fraction)
    return tuple([top.name] + [v.name for v in others][:MAX_CARRIERS - 1])


@dataclass(frozen=True)
class _Setup:
    """The refit's model (`cm`: the fit's candidate groups and the correction along the
    carriers), its linearised start and what its objective needs (`_setup`): u of `cm`
    at the linearised start (`u0`) and at the fit's own answer (`own`), (P,); the
    roughness penalty's λ; the correction's terms and each one's roughness factor `D`
    (Cholesky, (size, size)); the free columns (P,) bool and the bounds (P,)."""

    cm: Model
    u0: np.ndarray
    own: np.ndarray
    lam: float
    terms: list
    D: list
    free: np.ndarray
    lo: np.ndarray
    hi: np.ndarray

    def start(self, frac: float) -> np.ndarray:
        """u at `frac` of the linearised start (0: the fit's own answer), in the box."""
        return np.clip(self.own + frac * (self.u0 - self.own), self.lo, self.hi)


def _label(name: str, form: str) -> str:
    return name if form == "factor" else f"deposit:{name}"


def refit_basis(blocks, carriers, form, tensor=None) -> ShapeBasis:
    """The basis of the refit's model: the carriers' variables in `form` and, where the
    analysis tested a surface (`tensor`), the pair's variables and the surface too, whether
    or not the refit carries them: a gated basis (`ShapeBasis.gated`), whose terms the
    refit does not fit are switched off (`_setup`: the model without them exactly, at no
    cost in its runs). Why: the surface's columns (`design.tensor_columns` with this
    model, every term on) and the refit then run one compiled program, whatever the
    surface's test decides (`shape.analysis`)."""
    vars_ = [blocks[_label(n, form)][4] for n in carriers]
    if tensor is None:
        return ShapeBasis(tuple(vars_))
    first = len(vars_)  # the carriers' terms are always on: no switch
    vars_ += [blocks[_label(n, form)][4] for n in (tensor.a.name, tensor.b.name)
              if n not in carriers]
    return ShapeBasis(tuple(vars_), (tensor,), gated=tuple(range(first, len(vars_) + 1)))


def refit_model(smodel: Model, groups, basis: ShapeBasis) -> Model:
    """The refit's model: `smodel`'s study with the candidate `groups` and the correction
    `basis`, at `REFIT_TOLERANCE` (the same compiled programs for every call with equal
    arguments)."""
    return smodel.variant(candidates=list(groups), shape=basis
                          ).with_wear_tolerance(REFIT_TOLERANCE)


def refit_width(cm: Model, basis: ShapeBasis, carriers, form) -> int:
    """The tangents of the refit's Jacobian program: those of every column of `cm` that is
    not the correction's (the base parameters and the candidates it carries, free in one
    of diagnose's two refits or the other) and of the `carriers`' coefficients. A surface
    the refit carries, and the pair's variables with it, are computed in further parts of
    this width. Why every candidate's: both refits then run one program (the effect found
    is held in the first, free in the second)."""
    shape_keys = set(basis.keys())
    cols = [i for i, n in enumerate(cm.names) if n not in shape_keys]
    keys = {_label(n, form) for n in carriers}
    cols += [cm.index[k] for v in basis.variables if v.label in keys for k in v.keys()]
    return seeds(cm.packing.columns, cols)[0].shape[1]


def _setup(smodel: Model, groups, u, free_base, blocks, carriers, form, rho, n_res, Jw,
           rho_full, surface=None, linear_start: bool = True, basis=None,
           width: int | None = None) -> _Setup:
    """The refit's model, its joint linearised start over the carriers and its prior rows'
    ingredients (host work; the model's programs compile at its first evaluation).
    `basis`: the refit model's basis where it holds more than the carriers (and the
    surface) (`refit_basis`, held at zero), with `width` its Jacobian program's tangents:
    the refit's evaluations then compute its free columns only."""
    labels = [_label(n, form) for n in carriers]
    vars_ = [blocks[lab][4] for lab in labels]
    tensors = ()
    if surface is not None:
        A_t, S_t, Z_t, X_t, tensor = surface
        tensors = (tensor,)
        # its columns beside the design's, as one more block of the linearised start
        cols_t = list(range(Jw.shape[1], Jw.shape[1] + tensor.size))
        Jw = np.hstack([Jw, X_t])
        blocks = {**blocks, tensor.label: (A_t, S_t, Z_t, cols_t, tensor)}
        labels = labels + [tensor.label]
    # the fit's own candidate groups only (the design may carry more, held at off)
    cm = refit_model(smodel, groups, basis if basis is not None
                     else ShapeBasis(tuple(vars_), tensors))
    u0 = _map_u(smodel, u, cm)
    own = u0.copy()  # the fit's own answer: the correction off
    # the joint linearised start over the carriers (their GCV penalty)
    A, S = lin.block_penalty([blocks[lab][:2] for lab in labels])
    pf = lin.penalised_fit(A, S, rho, n_res, math.inf, None, 0)
    lam = pf.lam
    a = (lin.nonnegative_fit(A, S, rho, lam) if form == "deposit" else
         _factor_start(A, S, rho, lam, [blocks[lab][2] for lab in labels]))
    if not linear_start:
        a = np.zeros_like(a)
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
    terms = list(vars_) + list(tensors)
    cols = [cm.index[key] for var in terms for key in var.keys()]
    free = np.zeros(len(cm.names), bool)
    base_names = [smodel.names[i] for i in free_base]
    free[[cm.index[nm] for nm in base_names]] = True
    free[cols] = True
    if cm.ext.cfg.shape.gated:
        # the terms the refit does not fit are off: they cost nothing in its runs
        on = set(labels)
        cm = cm.with_terms_on([t.label in on for t in cm.ext.cfg.shape.terms()])
    if width is not None:
        cm = cm.with_jacobian_columns(np.flatnonzero(free), width)
    lo, hi = cm.bounds_u()
    D = [np.linalg.cholesky(v.roughness() + 1e-12 * np.eye(v.size)).T for v in terms]
    return _Setup(cm=cm, u0=u0, own=own, lam=lam, terms=terms, D=D, free=free, lo=lo, hi=hi)


def _objective(s: _Setup):
    """u -> the refit's `lsq.Point`: the model's rows and priors, the roughness penalty
    (at the linearised λ) and, for a factor, the zero sums and N(0, FACTOR_SD²) prior."""
    cm = s.cm

    def evaluate(v):
        e = cm.evaluate(v)
        pt = e.point()
        rows, J = [], []
        for var, Dv in zip(s.terms, s.D):
            idx = [cm.index[key] for key in var.keys()]
            c = v[idx]
            w = math.sqrt(s.lam)
            r = w * (Dv @ c)
            Jr = np.zeros((len(r), len(v)))
            Jr[:, idx] = w * Dv
            rows.append(r), J.append(Jr)
            if var.form == "factor":  # a level shift of g is K_d's, not the correction's
                # (a surface's functions of one variable alone are the additive terms')
                M = _sums(var)
                rows.append(M @ c / (0.01 * var.size))
                J1 = np.zeros((len(M), len(v)))
                J1[:, idx] = M / (0.01 * var.size)
                J.append(J1)
                # g = ln of the rate factor, N(0, FACTOR_SD²) per coefficient
                rows.append(c / FACTOR_SD)
                J2 = np.zeros((len(c), len(v)))
                J2[np.arange(len(c)), idx] = 1.0 / FACTOR_SD
                J.append(J2)
        return replace(pt, r_prior=np.concatenate([pt.r_prior, *rows]),
                       J_prior=np.vstack([pt.J_prior, *J]))

    return evaluate


class Ahead:
    """The refit's model built and its first evaluation (at the linearised start) made in
    a background thread, started once the analysis has chosen the carriers and decided on
    the surface (`shape.analysis`), while the caller goes on with host work (the analysis
    on top of the effect found, the figures); `_refit` takes it where it refits the same
    correction. Why: on the generator's `fatigue` study (48 x 72) the refit's model
    compiled in 5.6 s and its first evaluation ran 2.5 s after that host work, on the
    critical path. (Started before the surface's decision, it saved ~4 s there and cost
    ~3 s on the `thermal` study, whose surface the refit carries: a compilation of the
    model without it, discarded.)"""

    def __init__(self, smodel: Model, groups, u, free_base, blocks, carriers, form, rho,
                 n_res, Jw, rho_full, surface=None, basis=None, width=None):
        self.key = (tuple(groups), tuple(carriers), form, basis, width)
        self.surface = surface
        self.used = False
        self.evaluations = 0  # the thread's model evaluations (counted where used)

        def first():
            e0 = Model.own_evaluations()
            try:
                s = _setup(smodel, groups, u, free_base, blocks, carriers, form, rho, n_res,
                           Jw, rho_full, surface=surface, basis=basis, width=width)
                start = s.start(1.0)
                return s, start, _objective(s)(start)
            finally:
                self.evaluations = Model.own_evaluations() - e0

        self._job = Background(first)

    def take(self, groups, carriers, form, surface, basis=None, width=None):
        """(setup, start, its point) where they are the refit's, else None (a failure
        there is met again, and reported, by the refit's own evaluation)."""
        if (surface is not self.surface
                or self.key != (tuple(groups), tuple(carriers), form, basis, width)):
            return None
        try:
            got = self._job.result()
        except Exception:  # noqa: BLE001 (the refit evaluates the start itself)
            return None
        self.used = True
        return got


def _refit(smodel: Model, groups, ev, u, free_base, blocks, carriers, form, rho, n_res,
           sigma, Jw, rho_full, verbose, deepest: int, surface=None, maps: bool = True,
           linear_start: bool = True, ahead: Ahead | None = None, warm=None, basis=None,
           width: int | None = None):
    """The correction of `form` along the `carriers`, refitted with the fit's own
    parameters through the wear loop by the one least-squares core, with its true Jacobian
    (a model with those columns only), the roughness penalty (at the linearised λ) and, for
    a factor, the zero sum of each variable's coefficients and N(0, FACTOR_SD²) on each as
    prior rows; a deposit ≥ 0 by bounds. Returns (RMSE [µm], status, the model, u at the
    answer, covariance of u, its snapshots (E, S, N) [µm] from the last evaluation, or
    None, the rows' residuals at the answer [µm] (rows,), the refit's message: how it
    ended, with the starts that were not usable before it). The RMSE is NaN only where
    no start was usable; the message then says why.

    `surface`: the leading pair's surface where it is significant
    (`shape.interaction.Interaction.block`: (A, S, Z, X, tensor)), refitted with the
    carriers: its roughness along both directions and, for a factor, zero row and column
    sums of its coefficients and N(0, FACTOR_SD²) on each as prior rows. `maps`: compile
    the when/where map's functions meanwhile (False for a caller that draws no map:
    `design`'s shape rivals). `linear_start`: start the correction at the joint linearised
    fit (False: at zero, the fit's own answer; a caller's retry where the linearised start
    led the loop astray). `ahead`: its model and first evaluation made in the
    background (`Ahead`), used where they are this refit's. `warm`: an earlier refit's
    (model, u at its answer) (`ShapeResult.refit_at`); where that model has this one's
    columns (the same candidate groups, carriers, form and surface, on the same study),
    the refit starts from its correction with this fit's own parameters, ahead of the
    linearised start, and with its model's attempt count (`_warm_start`). `basis`,
    `width`: the refit model's basis where it holds more than it refits (`refit_basis`)
    and its Jacobian program's tangents (`_setup`)."""

    got = (ahead.take(groups, carriers, form, surface, basis, width)
           if ahead is not None and linear_start else None)
    if got is not None:
        s, start_ahead, point_ahead = got
    else:
        s, start_ahead, point_ahead = _setup(
            smodel, groups, u, free_base, blocks, carriers, form, rho, n_res, Jw, rho_full,
            surface=surface, linear_start=linear_start, basis=basis, width=width), None, None
    cm, free, lo, hi = s.cm, s.free, s.lo, s.hi
    evaluate = _objective(s)

    log = (lambda m: _log(True, m)) if verbose else None
    _log(verbose, f"    refit of the {form} correction along {', '.join(carriers)} through the "
                  f"loop (true Jacobian)")
    # the linearised start, then fractions of it where the model cannot be evaluated there
    # (`START_FRACTIONS`: the last is the fit's own answer)
    fractions = ((1.0,) + START_FRACTIONS) if linear_start else (0.0,)
    starts = [("the fit's own answer" if frac == 0 else "the linearised start"
               if frac == 1 else f"{frac:g} of the linearised start", s.start(frac))
              for frac in fractions]
    at = _warm_start(s, warm)
    if at is not None:
        _log(verbose, "      starts from the correction of the refit before it, with "
                      "this fit's own parameters")
        starts.insert(0, ("the correction of the refit before it", at))
        # ... and with the attempt count that refit's runs raised its model to (the same
        # program: the count is a traced bound). Why: on the fatigue study this start's
        # Jacobian run did not reach the end at the estimated count nor at twice it, so
        # the count was found by forward runs (its forward program compiled: 7 s of CPU,
        # a compilation more in the JSON) and the Jacobian run a third time
        if warm[0].ext.schedule.attempts > cm.ext.schedule.attempts:
            object.__setattr__(cm, "ext", cm.ext.with_schedule(warm[0].ext.schedule))
    # the when/where map of this model compiles in the background while the refit runs
    maps = Background(compile_maps, cm, deepest) if maps else None
    failed = []
    for what, start in starts:
        point0 = (point_ahead if start_ahead is not None
                  and np.array_equal(start, start_ahead) else None)
        out = lsq.solve(evaluate, start, point0=point0, point0_counts=True, free=free,
                        lower=lo, upper=hi,
                        noise_um=sigma, max_evaluations=REFIT_EVALUATIONS, se_tol=0.1,
                        project=cm.packing.project, label=f"    shape {form}", log=log,
                        settled=SETTLED_CHI2, settled_rmse=SETTLED_RMSE)
        if out.status != "unusable":
            break
        # the cause, without the start's values (lsq's message lists every coefficient)
        failed.append(f"{what} was not usable: "
                      f"{lsq.failure(out.point, jacobian=False) or out.message}")
        _log(verbose, f"    the refit's start, {failed[-1]}")
    if maps is not None:
        maps.result()
    message = "; ".join(failed + [out.message])
    if out.status == "unusable":
        return (math.nan, out.status, cm, out.u, np.zeros((len(cm.names),) * 2), None,
                np.asarray(out.point.r), message)
    r = out.point.r
    snaps = getattr(out.point.extra, "snaps", None)
    if snaps is not None and not np.array_equal(np.asarray(out.point.u), np.asarray(out.u)):
        snaps = None
    return (float(np.sqrt(np.mean(r ** 2))), out.status, cm, out.u, _full_cov(out, free),
            snaps, np.asarray(r), message)


def _warm_start(s: _Setup, warm) -> np.ndarray | None:
    """u of `s.cm` with the correction's coefficients of an earlier refit (`warm`: (its
    model, u (P,))) and this fit's own parameters (`s.own`: the effect found among them),
    in the box; None where that refit's model has other columns or another study.

    Why: diagnose refits the shape's correction twice on one model, after the base fit
    (the effect found held at off) and on top of the effect found. The linearised start
    through the loop is far off (the generator's `fatigue` study, 48 x 72: 4.16 and
    4.29 µm RMS, the base fit 0.51; both refits ended at 0.3355-0.3358 µm, the second
    in 9 evaluations of ~3 s of CPU each). From the first's correction with the effect
    at its own fit's value: 0.63 µm, and 3 evaluations to 0.3358 µm. Not from the
    first's answer itself (0.3355 µm, where the second stopped at once): its effect is
    held at off there, so the correction "on top of the effect" would be the first's,
    and the effect file made from it would count the effect twice beside it."""
    if warm is None:
        return None
    cm, u = warm
    if (cm is None or u is None or cm.study is not s.cm.study
            or list(cm.names) != list(s.cm.names)):
        return None
    u = np.asarray(u, np.float64)
    if u.shape != s.u0.shape or not np.all(np.isfinite(u)):
        return None
    cols = [s.cm.index[key] for var in s.terms for key in var.keys()]
    out = s.own.copy()
    out[cols] = u[cols]
    return np.clip(out, s.lo, s.hi)


def _factor_start(A, S, rho, lam, Zs) -> np.ndarray:
    """The linearised start of a factor correction (k,), in the blocks' constrained
    coordinates: the minimum of the linearised refit's own objective, its N(0,
    FACTOR_SD²) prior on every coefficient included (c = Z a, each Z orthonormal, so
    |c|² = |a|²), beside the data rows A (rows, k) and the penalty λ S (k, k).

    Why the prior: the GCV fit alone leaves the directions the data hardly see at
    whatever the penalty allows, which is little where GCV takes its smallest λ.
    Measured on the generator's `fatigue` study (seed 1, 48 x 72; along sliding speed
    and pressure with their surface): coefficients up to 14 (a rate factor e^14), a
    start the loop could not integrate in either refit (its doubled Jacobian run, a
    forward program compiled and forward runs at 4x and 8x the attempts, all wasted),
    and half of it still at 1.1 µm RMS (base 0.51); with the prior the largest is 4.1,
    the linearised misfit's drop 4673 against 4717 (σ² units: the same fit where the
    data see it), the start is integrated, and `diagnose --shape` took 0.81x the CPU
    (326.9 -> 265.4 s at load ~9; the refits' RMSEs 0.3377 -> 0.3340 and 0.3380 ->
    0.3347 µm, the first now converged where it ran out of budget)."""
    k = A.shape[1]
    Z = np.zeros((sum(z.shape[0] for z in Zs), k))
    i = j = 0
    for z in Zs:
        Z[i:i + z.shape[0], j:j + z.shape[1]] = z
        i, j = i + z.shape[0], j + z.shape[1]
    H = A.T @ A + lam * S + (Z.T @ Z) / FACTOR_SD ** 2
    return lin.psolve(H, A.T @ rho)


def _sums(term) -> np.ndarray:
    """The sums of a factor term's coefficients held at zero: all of them for one variable
    (1, size); for a surface each row's and each column's of its grid (rows + columns,
    size)."""
    if not hasattr(term, "a"):
        return np.ones((1, term.size))
    na, nb = term.a.size, term.b.size
    return np.vstack([np.kron(np.eye(na), np.ones((1, nb))),
                      np.kron(np.ones((1, na)), np.eye(nb))])


def _full_cov(out: lsq.Outcome, free) -> np.ndarray:
    """The covariance of all of u (P, P), zero on held columns."""
    P = len(free)
    C = np.zeros((P, P))
    idx = np.flatnonzero(free)
    cov = out.errors.cov if out.errors is not None else out.cov.cov
    C[np.ix_(idx, idx)] = np.where(np.isfinite(cov), cov, 0.0)
    return C


def _correction(cm: Model, u, carriers, form, carried: bool = True) -> dict:
    """The refitted correction as data (for the effect file): per variable its form,
    size, knots and coefficients; the model's terms the refit held at zero (a pair's
    variable and surface it does not carry, `refit_basis`) left out. `carried`: whether
    the refit carried the model's surface."""
    out = {"form": form, "variables": []}
    for var in cm.ext.cfg.shape.variables:
        if var.name not in carriers:
            continue
        out["variables"].append({"name": var.name, "form": var.form, "size": var.size,
                                 "knots": list(var.knots),
                                 "coefficients": [float(u[cm.index[k]]) for k in var.keys()]})
    out["tensors"] = [{"variables": [t.a.name, t.b.name], "form": t.form,
                       "size": [t.a.size, t.b.size], "knots": [list(t.a.knots), list(t.b.knots)],
                       "coefficients": [float(u[cm.index[k]]) for k in t.keys()]}
                      for t in cm.ext.cfg.shape.tensors if carried]
    return out
