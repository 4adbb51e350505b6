"""`Model`: a study's residual model with every candidate as a column group (evaluation,
bounds, row coordinates), for the diagnosis.

It wraps the one residual model of every fit (`_residual.ResidualModel`): the base model is
the model `calibrate` fits, to the same data, with the same packing (`_packing`), priors in
units of their standard deviation and bounds; the candidates are columns of their own
group, switched by masks, so one compiled function serves the base fit, every candidate and
every pair.
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import threading
import time

import numpy as np

from jaxwear._analyses.diagnose._extended import candidate_names
from jaxwear._core.host import to_device
from jaxwear._core.noise import series
from jaxwear._inference.attempts import needs_more_attempts
from jaxwear._inference.evaluation import (
    Evaluation,
    _evaluate_jit,
    evaluate,
    forward,
    integration_report,
)
from jaxwear._inference.packing import parse_fit
from jaxwear._inference.residual import build_model
from jaxwear._study.study import Study


class Model:
    """A study's data with the extended model: evaluation, fits and statistics on the host.

    - `study`; `keys`: the study keys the base model fits (the study's `[fit]`, else K_d and
      the clearances; registration offsets are not: `diagnose` fits them with the base
      model first and holds them, `_calibrate.registered`); `start`: start values by name.
    - `candidates`: the candidate groups (default: every one the study can be missing);
      `contact`: another contact model; `shape`: the shape correction's basis.
    - `defect_um` (rows,) [µm]: a fixed correction of the rows, the residual difference
      between the finer resolution calibrate's answer is corrected to and this study's
      (`_calibrate.correct_to_finer`): the base fit then meets that answer, and every
      candidate is compared at the same correction (the same compiled function).
    - `jacobian_columns` (K,): the only columns of u whose Jacobian `evaluate` computes
      (one repeated to pad; the others 0: `evaluation.evaluate`'s `columns`), for a fit
      that holds the rest (`with_jacobian_columns`); None: every column.
      `jacobian_width`: the program's tangents, columns that need more computed in parts
      (`evaluation.evaluate`'s `width`); None: as many as the columns need.
    """

    # process-wide counters of compiled-model evaluations (progress, benchmarks); this
    # thread's own: `own_evaluations`
    evaluations = 0
    evaluation_s = 0.0  # wall time spent in them [s], compilations included
    first_evaluation_s = 0.0  # the last evaluation that compiled (the first of its shape)

    def __init__(self, study: Study, *, keys=None, start: dict | None = None,
                 candidates=None, contact=None, shape=None, defect_um=None):
        self.study = study
        self.jacobian_columns = None  # every column (`with_jacobian_columns`)
        self.jacobian_width = None
        self.keys = list(keys) if keys is not None else parse_fit(
            study, list(study.fit) if study.fit else "K_d,clearance")
        self.start = dict(start or {})
        self.candidates = (candidate_names(study.config) if candidates is None
                           else list(candidates))
        self.contact = contact
        self.shape = shape
        self.base_cfg = study.config
        self.ext = build_model(study, self.keys, self.start, candidates=self.candidates,
                               contact=contact, shape=shape)
        if defect_um is not None:
            self.ext = self.ext.with_defect(defect_um)
        self.columns = self.ext.columns
        self.names = list(self.ext.names)
        self.index = {n: i for i, n in enumerate(self.names)}
        d = self.ext.data
        self.row_exp = np.asarray(d.exp)
        self.row_snap = np.asarray(d.snap)
        self._is_max = np.asarray(d.is_max)
        self.measured = self.ext.measured
        self.n = len(self.measured)
        self.exp_names = list(self.ext.exp_names)
        self.tolerance_um = float(study.clearance_tolerance_um)
        self.base_mask = np.array([c.group == "" for c in self.columns])
        self._rows_x = np.asarray(d.x, float)
        points = [e.snapshot_points for e in study.experiments]
        self._rows_t = np.array([points[e][s] for e, s in zip(self.row_exp, self.row_snap)],
                                float)
        self.series = series(self.row_exp, self.row_snap, self._is_max, self._rows_x)
        self._frozen = True

    def __setattr__(self, name, value):
        # immutable once built: variants are new models (`with_contact`)
        if getattr(self, "_frozen", False):
            raise AttributeError(f"Model is immutable; cannot set {name!r}")
        object.__setattr__(self, name, value)

    @property
    def is_max(self) -> np.ndarray:
        """True for maximum-depth (history) rows, False for profile rows."""
        return self._is_max

    @property
    def packing(self):
        return self.ext.packing

    def group_mask(self, groups) -> np.ndarray:
        """Free columns: the base parameters and those of the named candidates."""
        return self.packing.mask(groups)

    def variant(self, *, candidates=None, contact="same", shape="same") -> Model:
        """The same study, base parameters and starts with other candidates, contact model
        or shape basis (each one more compiled function)."""
        return Model(self.study, keys=self.keys, start=self.start,
                     candidates=self.candidates if candidates is None else candidates,
                     contact=self.contact if contact == "same" else contact,
                     shape=self.shape if shape == "same" else shape,
                     defect_um=self.ext.defect)

    def with_jacobian_columns(self, columns, width: int | None = None) -> Model:
        """The same model whose evaluations compute the Jacobian of `columns` only (indices
        (K,) into u, one repeated to pad; the others 0), None: of every column. `width`:
        the compiled program's tangents (one program for every column set the model is
        given with that width); columns that need more are computed in parts, a run each
        (`evaluation.evaluate`); None: the columns' own."""
        out = copy.copy(self)
        object.__setattr__(out, "jacobian_columns", None if columns is None
                           else np.asarray(columns, np.int32))
        object.__setattr__(out, "jacobian_width", None if columns is None else width)
        return out

    def with_terms_on(self, on) -> Model:
        """The same model (the same compiled programs) with the terms of its gated shape
        basis switched on or off (`ResidualModel.with_terms_on`)."""
        out = copy.copy(self)
        object.__setattr__(out, "ext", self.ext.with_terms_on(on))
        return out

    def with_defect(self, defect_um) -> Model:
        """The same model with its rows corrected by `defect_um` (rows,) [µm] instead of
        its own correction: the same compiled programs (the correction is a traced
        array), e.g. a fit's rows moved to a finer resolution's (`law.profile`)."""
        out = copy.copy(self)
        object.__setattr__(out, "ext", self.ext.with_defect(np.asarray(defect_um, np.float64)))
        return out

    def with_wear_tolerance(self, factor: float) -> Model:
        """The same model integrating at `factor` times its adaptive wear tolerance: the
        same compiled programs (the tolerance is a traced array of the schedule); itself
        under the paper's fixed-step integrator, which has none."""
        sched = self.ext.schedule
        if not sched.adaptive or factor == 1:
            return self
        tol = to_device(np.asarray(sched.tolerance, np.float64) * factor)
        out = copy.copy(self)
        object.__setattr__(out, "ext", self.ext.with_schedule(
            dataclasses.replace(sched, tolerance=tol)))
        return out

    @property
    def wear_tolerance_um(self) -> float | None:
        """The adaptive loop's wear tolerance [µm] (the largest of the experiments'), None
        under the paper's fixed-step integrator."""
        return self.ext.schedule.tolerance_um

    def with_contact(self, contact: str | None) -> Model:
        """The same model with another contact choice (None: the study's)."""
        return self.variant(contact=contact)

    def values(self, u) -> np.ndarray:
        return self.packing.values_np(u)

    def u_of(self, name: str, value: float, u=None) -> float:
        """u of one column for `value`, the other columns at u (default 0: their starts);
        a product strength needs its partner's u (see `Packing.values`)."""
        i = self.index[name]
        full = np.zeros(len(self.names)) if u is None else np.array(u, np.float64)
        vals = self.packing.values_np(full)
        vals[i] = value
        return float(self.packing.u_of(vals)[i])

    def value_jacobian(self, u) -> np.ndarray:
        """d values / d u (P, P) at u."""
        return self.packing.value_jacobian(u)

    def bounds_u(self):
        return self.packing.bounds_u()

    @staticmethod
    def own_evaluations() -> int:
        """Evaluations this thread made (forward runs included): an analysis's count where
        another runs beside it (`diagnose`: the refit on top of the effect beside the law
        search; the law model's warm-up beside the first refit), which the process-wide
        `evaluations` would add in."""
        return getattr(_own, "n", 0)

    def evaluate(self, u) -> Evaluation:
        """The model at u: rows, prior rows, Jacobian (one compiled call)."""
        stop_if_asked()
        Model.evaluations += 1
        _own.n = getattr(_own, "n", 0) + 1
        t0 = time.perf_counter()
        n_compiled = _compiled_count()
        ev, used = evaluate(self.ext, u, columns=self.jacobian_columns,
                            width=self.jacobian_width)
        if used.schedule.attempts > self.ext.schedule.attempts:
            # the attempt count an evaluation needed is kept for the rest of the run
            object.__setattr__(self, "ext", used)
        dt = time.perf_counter() - t0
        Model.evaluation_s += dt
        if _compiled_count() > n_compiled:
            Model.first_evaluation_s = dt
        return ev

    def predict(self, u, *, doublings: int = 3, stiff: float | None = None) -> np.ndarray:
        """Model depth at every row [µm] at u, forward only (no Jacobian: a check of a
        linearised answer costs one plain evaluation); NaN rows where the model wore
        through or its integration ran out of attempts (`doublings`: times the attempt
        count may double before that, `evaluation.forward`). `stiff`: NaN rows, and no
        run, where u's estimated attempt count is over `stiff` times the model's (a check
        at a stiff corner the fit never went to: an estimate of 2^46 attempts on a
        held-out study, a run of hours)."""
        if stiff is not None and needs_more_attempts(self.ext, u, factor=stiff):
            return np.full(self.n, np.nan)
        return self._forward(u, doublings=doublings)[0]

    def snapshots(self, u) -> np.ndarray:
        """Model snapshots (E, S, N) [µm] at u, forward only; NaN where the model wore
        through or its integration ran out of attempts."""
        return self._forward(u)[1]

    def _forward(self, u, doublings: int = 3):
        stop_if_asked()
        Model.evaluations += 1
        _own.n = getattr(_own, "n", 0) + 1
        t0 = time.perf_counter()
        rows, snaps, _, used = forward(self.ext, u, doublings=doublings)
        if used.schedule.attempts > self.ext.schedule.attempts:
            object.__setattr__(self, "ext", used)
        Model.evaluation_s += time.perf_counter() - t0
        return rows, snaps

    def integration(self, ev: Evaluation) -> dict:
        """The integration report of an evaluation (same keys as `calibrate`'s)."""

        return integration_report(self.ext, ev)

    # Row coordinates for the residual analysis
    @property
    def row_x(self) -> np.ndarray:
        """Angle [deg] of profile rows, hours of history rows."""
        return self._rows_x

    @property
    def row_time(self) -> np.ndarray:
        """Revolutions (profiles) or hours (history) at which each row was measured."""
        return self._rows_t


_own = threading.local()  # this thread's evaluations (`Model.own_evaluations`)


class Stopped(BaseException):
    """A job asked to stop (`stopping`), raised at its next model evaluation. Not an
    `Exception`: no fit's handler of a failed evaluation takes it for one."""


@contextlib.contextmanager
def stopping(event: threading.Event):
    """Within it, this thread's model evaluations raise `Stopped` once `event` is set
    (`law.ahead`: a job the search will not take stops at its next evaluation, not at its
    end)."""
    before = getattr(_own, "stop", None)
    _own.stop = event
    try:
        yield
    finally:
        _own.stop = before


def stop_if_asked() -> None:
    """`Stopped` where this thread's job has been asked to stop (`stopping`)."""
    ev = getattr(_own, "stop", None)
    if ev is not None and ev.is_set():
        raise Stopped


def _compiled_count() -> int:
    """How many versions of the evaluation are compiled (for the timing counters; -1 where
    this jax/equinox does not say)."""

    try:
        return int(_evaluate_jit._cached._cache_size())
    except AttributeError:
        return -1


def objective(ev: Evaluation, noise_um: float) -> float:
    """Q = Σ r² + σ² Σ r_prior² [µm²]: the weighted least-squares objective (the core's χ²
    times σ²), which the BIC evidence compares between fits."""
    return float(ev.r @ ev.r + noise_um ** 2 * (ev.r_prior @ ev.r_prior))


__all__ = ["Model", "objective"]
