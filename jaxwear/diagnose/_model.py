"""`Model`: a study's data with the extended model (evaluation, bounds, row coordinates)."""

from __future__ import annotations

import math
import time
from dataclasses import replace

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._params import key_to_si
from .._study import Study
from ..effects import STRUCTURAL_CANDIDATES, effect_parameter_specs, product_pairs
from ._extended import (
    Column,
    Eval,
    Extended,
    _candidate_parameters,
    _evaluate_ext,
    _predict_ext,
    candidate_names,
)


class Model:
    """A study's data with the extended model: evaluation, fits and statistics on the host.

    Built from the calibration's `Problem` (data rows, clearance prior, start values,
    schedules), so its base model is the model `calibrate` fits, to the same data. One
    difference: the prior rows are weighted with the noise level estimated from the data
    (`calibrate` uses its first pass's RMSE).
    """

    # process-wide counters of compiled-model evaluations (progress, benchmarks)
    evaluations = 0
    evaluation_s = 0.0  # wall time spent in them [s], compilations included
    first_evaluation_s = 0.0  # the last evaluation that compiled (the first of its shape)

    def __init__(self, study: Study, problem=None, *, candidates=None, contact=None,
                 noise_weight: float = 1.0, shape=None):
        from .._calibrate import build_problem, parse_fit

        self.study = study
        if problem is None:
            # the study's [fit] parameters, as calibrate fits them (registration offsets
            # are not: `diagnose` fits them with the base model first and holds them,
            # `_calibrate.registered`)
            problem = build_problem(study, parse_fit(
                study, list(study.fit) if study.fit else "K_d,clearance"))
        self.problem = problem
        cfg = study.config
        self.candidates = candidate_names(cfg) if candidates is None else list(candidates)
        parametric = [c for c in self.candidates if c not in STRUCTURAL_CANDIDATES]
        cfg_ext = cfg.replace(effects=tuple(cfg.effects) + tuple(parametric))
        if "double_layer" in self.candidates:
            cfg_ext = STRUCTURAL_CANDIDATES["double_layer"].configure(cfg_ext)
        if contact is not None:
            cfg_ext = cfg_ext.replace(contact=contact)
        if shape is not None:
            cfg_ext = cfg_ext.replace(shape=shape)
        self.contact = contact
        self.shape = shape
        self.base_cfg = cfg
        columns, names, start = [], [], []
        specs = effect_parameter_specs()
        for f, s in problem.fitted():
            if f.key in specs:  # a strength of an effect the study switches on
                lower, upper = specs[f.key].lower, specs[f.key].upper
            else:
                lower, upper = (0.0, math.inf) if f.log else (-math.inf, math.inf)
            columns.append(Column(f.key, f.experiment, f.log, f.scale, key_to_si(f.key), "",
                                  lower, upper))
            names.append(f.name)
            start.append(float(s))
        p0, schedule, exp_names = problem.experiments()
        for cand in self.candidates:
            if cand == "unsymmetric":
                continue
            for key, spec in _candidate_parameters(cand).items():
                columns.append(Column(key, None, spec.log, spec.scale, spec.to_si, cand,
                                      spec.lower, spec.upper, strength=not spec.log))
                names.append(key)
                if spec.log:
                    v = float(np.asarray(p0.effect_params[key])[0]) / spec.to_si
                    start.append(v if v > 0 else spec.default)
                else:
                    start.append(spec.off)
        if shape is not None:
            # the coefficients of exp(g(z)) (`effects.shape`), 0 = the model as written
            n_exp = len(exp_names)
            p0 = eqx.tree_at(lambda p: p.effect_params, p0, {
                **p0.effect_params, **{k: jnp.zeros(n_exp) for k in shape.keys()}})
            for key in shape.keys():
                columns.append(Column(key, None, False, 1.0, 1.0, "shape", -math.inf,
                                      math.inf))
                names.append(key)
                start.append(0.0)
        self.columns = tuple(columns)
        self.names = names
        self.index = {n: i for i, n in enumerate(names)}
        # Candidate strengths at `off` in the batched parameters as well (a study may set
        # a value for an effect it does not switch on); the structural strength maps to the
        # backing thickness, which is zero in the single-layer base model.
        u0 = np.zeros(len(columns))
        self.ext = Extended(cfg=cfg_ext, columns=self.columns, params=p0,
                            schedule=schedule, start=jnp.asarray(start, jnp.float64))
        self.ext = eqx.tree_at(lambda e: e.params, self.ext, self.ext.batched_params(u0))
        d = problem.measured_rows()
        self.row_exp = d["exp"]
        self.row_snap = d["snap"]
        self._i0 = d["i0"]
        self._i1 = d["i1"]
        self._w = d["w"]
        self._is_max = d["is_max"]
        self.measured = d["depth_um"]
        self.n = len(self.measured)
        self.exp_names = list(exp_names)
        self.tolerance_um = float(study.clearance_tolerance_um)
        self.nominal_mm = problem.nominal_clearances_mm()
        self.prior_cols = [i for i, c in enumerate(columns)
                           if c.key == "clearance_mm" and c.group == ""]
        if not math.isfinite(self.tolerance_um):
            self.prior_cols = []
        self.base_mask = np.array([c.group == "" for c in columns])
        self.noise_weight = float(noise_weight)  # µm: prior rows are (c - c_nom)/τ times this
        self._rows_x, self._rows_t = _row_coordinates(study, d, self.row_exp,
                                                       self.row_snap)
        self._frozen = True

    def __setattr__(self, name, value):
        # immutable once built: variants are new models (`with_contact`, `with_noise_weight`)
        if getattr(self, "_frozen", False):
            raise AttributeError(f"Model is immutable; cannot set {name!r}")
        object.__setattr__(self, name, value)

    @property
    def is_max(self) -> np.ndarray:
        """True for maximum-depth (history) rows, False for profile rows."""
        return self._is_max

    def group_mask(self, groups) -> np.ndarray:
        """Free columns: the base parameters and those of the named candidates."""
        groups = set(groups)
        return np.array([c.group == "" or c.group in groups for c in self.columns])

    def _variant(self, contact, noise_weight) -> Model:
        return Model(self.study, self.problem, candidates=self.candidates, contact=contact,
                     noise_weight=noise_weight, shape=self.shape)

    def with_contact(self, contact: str | None) -> Model:
        """The same model with another contact choice (None: the study's; one more compiled
        function per contact model)."""
        return self._variant(contact, self.noise_weight)

    def with_noise_weight(self, noise_um: float) -> Model:
        """The same model with the clearance prior rows weighted by `noise_um` [µm] (the
        same compiled function: the weight is applied on the host)."""
        return self._variant(self.contact, noise_um)

    def values(self, u) -> np.ndarray:
        return np.asarray(self.ext.values(jnp.asarray(u, jnp.float64)))

    def u_of(self, name: str, value: float, u=None) -> float:
        """u of one column for `value`, the other columns at u (default 0: their starts);
        a product strength needs its partner's u (see `Extended.values`)."""
        i = self.index[name]
        c, s = self.columns[i], float(self.ext.start[i])
        if c.log:
            return math.log(value / s)
        for a, b in product_pairs([col.key for col in self.columns]):
            if a == i:
                value = value * math.exp(0.0 if u is None else float(u[b]))
        return (value - s) / c.scale

    def value_jacobian(self, u) -> np.ndarray:
        """d values / d u (P, P) at u."""
        return np.asarray(jax.jacfwd(self.ext.values)(jnp.asarray(u, jnp.float64)))

    def bounds_u(self):
        lo, hi = [], []
        for c, s in zip(self.columns, np.asarray(self.ext.start)):
            if c.log:
                lo.append(math.log(c.lower / s) if c.lower > 0 else -math.inf)
                hi.append(math.log(c.upper / s) if math.isfinite(c.upper) else math.inf)
            else:
                lo.append((c.lower - s) / c.scale)
                hi.append((c.upper - s) / c.scale)
        return np.array(lo), np.array(hi)

    def evaluate(self, u) -> Eval:
        """The model at u: rows, prior rows, Jacobian (one compiled call)."""
        Model.evaluations += 1
        t0 = time.perf_counter()
        n_compiled = _compiled_count()
        u = np.asarray(u, np.float64)
        snaps, J, mres, worn, sliding, err, steps = _evaluate_ext(self.ext, jnp.asarray(u))
        # The adaptive loop's static attempt count is an estimate that grows with K_d and
        # the candidates' strengths: where it fell short (error inf), double it (one more
        # compilation, kept for the rest of the run) rather than use a truncated history.
        for _ in range(3):
            if not (self.ext.schedule.adaptive and not np.isfinite(float(err))):
                break
            sched = self.ext.schedule
            object.__setattr__(self, "ext", eqx.tree_at(
                lambda e: e.schedule, self.ext,
                sched.more_attempts()))
            snaps, J, mres, worn, sliding, err, steps = _evaluate_ext(self.ext,
                                                                      jnp.asarray(u))
        snaps, J = np.asarray(snaps), np.asarray(J)
        dt = time.perf_counter() - t0
        Model.evaluation_s += dt
        if _compiled_count() > n_compiled:
            Model.first_evaluation_s = dt
        prof = snaps[self.row_exp, self.row_snap]  # (rows, N)
        Jp = J[self.row_exp, self.row_snap]  # (rows, N, P)
        rows = np.arange(self.n)
        w = self._w
        pred = prof[rows, self._i0] * (1 - w) + prof[rows, self._i1] * w
        Jr = Jp[rows, self._i0] * (1 - w)[:, None] + Jp[rows, self._i1] * w[:, None]
        if self._is_max.any():
            # maximum depth: the derivative is the one of the deepest node (a subgradient)
            jmax = np.argmax(prof, axis=1)
            m = self._is_max
            pred = np.where(m, prof[rows, jmax], pred)
            Jr[m] = Jp[rows[m], jmax[m]]
        r_prior, J_prior = self._prior_rows(u)
        return Eval(u=u, pred=pred, r=pred - self.measured, J=Jr, r_prior=r_prior,
                    J_prior=J_prior, snaps=snaps, max_residual=float(mres), worn=float(worn),
                    sliding_m=np.asarray(sliding), error_um=float(err), steps=int(steps),
                    J_snaps=J)

    def predict(self, u) -> np.ndarray:
        """Model depth at every row [µm] at u, forward only (no Jacobian: a check of a
        linearised answer costs one plain evaluation); NaN rows where the model wore
        through or its integration ran out of attempts."""
        return self._rows(self.snapshots(u))

    def snapshots(self, u) -> np.ndarray:
        """Model snapshots (E, S, N) [µm] at u, forward only; NaN where the model wore
        through or its integration ran out of attempts."""
        Model.evaluations += 1
        t0 = time.perf_counter()
        snaps, worn, err = (np.asarray(x) for x in _predict_ext(self.ext, jnp.asarray(
            np.asarray(u, np.float64))))
        Model.evaluation_s += time.perf_counter() - t0
        if float(worn) >= 0 or not np.isfinite(float(err)):
            return np.full(snaps.shape, np.nan)
        return snaps

    def _rows(self, snaps) -> np.ndarray:
        prof = snaps[self.row_exp, self.row_snap]
        rows = np.arange(self.n)
        pred = prof[rows, self._i0] * (1 - self._w) + prof[rows, self._i1] * self._w
        if self._is_max.any():
            pred = np.where(self._is_max, prof.max(axis=1), pred)
        return pred

    def integration(self, ev: Eval) -> dict:
        """The integration report of an evaluation (same keys as `calibrate`'s)."""
        sched = self.ext.schedule
        tol = float(np.max(np.asarray(sched.tolerance))) * 1e6 if sched.adaptive else None
        err = ev.error_um if sched.adaptive else None
        return {"integrator": "adaptive" if sched.adaptive else "paper",
                "error_estimate_um": err if err is None or math.isfinite(err) else "inf",
                "steps": int(ev.steps), "tolerance_um": tol}

    def _prior_rows(self, u):
        """Clearance prior rows (c - c_nom)/τ · noise_weight [µm] and their Jacobian."""
        vals = self.values(u)
        r_prior, J_prior = [], []
        for i in self.prior_cols:
            c = self.columns[i]
            k = self.noise_weight * 1e3 / self.tolerance_um
            r_prior.append(k * (vals[i] - self.nominal_mm[c.experiment]))
            row = np.zeros(len(u))
            row[i] = k * (vals[i] if c.log else c.scale)
            J_prior.append(row)
        return np.array(r_prior).reshape(-1), np.array(J_prior).reshape(-1, len(u))

    def reweigh(self, ev: Eval) -> Eval:
        """`ev` (from a model with another prior weight) with this model's prior rows:
        the compiled model does not depend on the weight, so no evaluation is needed."""
        r_prior, J_prior = self._prior_rows(ev.u)
        return replace(ev, r_prior=r_prior, J_prior=J_prior)

    # Row coordinates for the residual analysis
    @property
    def row_x(self) -> np.ndarray:
        """Angle [deg] of profile rows, hours of history rows."""
        return self._rows_x

    @property
    def row_time(self) -> np.ndarray:
        """Revolutions (profiles) or hours (history) at which each row was measured."""
        return self._rows_t


def _compiled_count() -> int:
    """How many versions of the evaluation are compiled (for the timing counters; -1 where
    this jax/equinox does not say)."""
    try:
        return int(_evaluate_ext._cached._cache_size())
    except AttributeError:
        return -1


def _row_coordinates(study: Study, data: dict, row_exp, row_snap):
    """Angle [deg] (profiles) or hours (histories) of each row, and its measurement time
    (revolutions or hours: the snapshot the row is compared with)."""
    points = [e.snapshot_points for e in study.experiments]
    t = np.array([points[e][s] for e, s in zip(row_exp, row_snap)], float)
    return np.asarray(data["x"], float), t
