"""The study as a residual model: u ↦ model − measured depth at every row [µm].

One definition for every fit: calibrate, each diagnose fit (the base model, every candidate,
the shape of the missing wear), predict's Laplace fit and its NUTS posterior all pose their
problem as a `ResidualModel`; `jaxwear.lsq` solves it. A model holds

- the parameter vector's packing (`_packing.Packing`: columns, starts, bounds, priors),
- every experiment's parameters and wear schedule, batched (schedules padded to a common
  length, so all experiments run in one compiled function),
- the measured rows (`Data`): where each row lives in the model's snapshots,

and one compiled evaluation returns the rows, their exact forward-mode Jacobian through the
whole wear loop (`jax.jacfwd`: a handful of tangents pushed alongside the primal), the
snapshots and their Jacobian. Prior rows are computed on the host from the packing (they
are analytic in u), so changing a prior never recompiles.

Diagnose's candidates are columns of a group (`Column.group`) in the same model, switched
off by masks; the configuration then carries every candidate effect, held at `off`.

One compile per answer: a fit compiles its Jacobian once, at the coarsest resolution, and
consults finer resolutions by forward runs only. The residual difference between a finer
level and this one at the answer is held as a fixed correction of the rows (`defect_um`, a
traced array: changing it never recompiles) while the coarse Jacobian steps (defect
correction, `_calibrate.fit_study`). A `Layout` pads every schedule to shared capacities
(pieces, snapshots, attempts, the early-stop arrays), so that a forecast over other points
runs in the fit's own compiled function. `TRACES` counts the compilations.
"""

from __future__ import annotations

import collections
import dataclasses
import math
from dataclasses import dataclass

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from . import lsq
from ._config import ModelConfig
from ._errors import InputError
from ._packing import (
    Packing,
    candidate_columns,
    packing_of,
    shape_columns,
    study_columns,
)
from ._params import Params
from ._schedule import Schedule, pad_schedule
from ._study import Study
from ._wear import (
    _regime_rates,
    adaptive_attempts,
    build_schedule,
    schedule_numerics,
    wear_loop,
)
from .effects import STRUCTURAL_CANDIDATES
from .effects.shape import pack as pack_shape

# Compilations of the residual model's functions, by kind ("jacobian", "forward"), counted
# when JAX traces them (a trace is a compilation, or a load from the persistent cache):
# a fit reports the difference over its run as its `compiles`.
TRACES: collections.Counter = collections.Counter()


def traces() -> dict:
    """A copy of `TRACES` (to difference around an answer)."""
    return dict(TRACES)


def traces_since(before: dict) -> dict:
    """Compilations by kind since `before` (`traces()`): "jacobian" and "forward" always,
    other kinds ("density": a sampler's log density) where any."""
    kinds = dict.fromkeys(["jacobian", "forward", *TRACES])
    out = {k: TRACES.get(k, 0) - before.get(k, 0) for k in kinds}
    return {k: v for k, v in out.items() if v or k in ("jacobian", "forward")}


@dataclass(frozen=True)
class Layout:
    """Shared capacities of a model's batched schedule, so that problems over other points
    (a forecast, its refinements) share one compiled function with the fit: `updates`
    pieces, `snapshots` snapshot slots, at least `attempts` attempted steps (adaptive), and
    the early-stop arrays present (`stop`: a fit never stops early, its arrays are +inf;
    a forecast sets them, `_predict.stop_past_layer`). Unused capacity costs little: a
    padded piece or attempt skips all work (measured on the boom at 90 x 72: 8x the
    attempts, 0.35 s against 0.21 s a forward run)."""

    updates: int
    snapshots: int
    attempts: int = 0
    stop: bool = True

    def holds(self, sched: Schedule) -> bool:
        """Whether a batched schedule fits in these capacities."""
        return (sched.cycles.shape[-1] <= self.updates
                and sched.n_snapshots <= self.snapshots)


class Data(eqx.Module):
    """Measured rows, flattened over experiments: where each lives in the model output."""

    exp: jax.Array  # experiment index (rows,)
    snap: jax.Array  # snapshot index
    i0: jax.Array  # interpolation nodes and weight (profiles)
    i1: jax.Array
    w: jax.Array
    is_max: jax.Array  # True: maximum depth (history rows)
    depth_um: jax.Array  # measured [µm]
    x: jax.Array  # angle [deg] (profiles) or hours (history), for reports only
    angle: jax.Array  # bushing-frame angle at the given registration [rad] (0: history)
    offset_col: jax.Array  # column of the row's fitted angle offset, or -1

    @property
    def n(self) -> int:
        return int(self.depth_um.shape[0])


def _stack(trees):
    return jax.tree.map(lambda *xs: jnp.stack(xs), *trees)


def _run_length(e) -> dict:
    """`build_schedule`'s run length of an experiment's residuals: up to its last measured
    point, not past it (nothing after it enters a residual: a forecast's training study
    keeps the experiment's duration, and its fits ran 25 h of the boom for data to 15 h)."""
    pts = e.snapshot_points
    end = max(pts) if pts else None
    if e.hours is not None:
        return {"revolutions": None, "hours": e.hours if end is None else min(e.hours, end)}
    return {"revolutions": e.revolutions if end is None or e.revolutions is None
            else min(e.revolutions, end), "hours": None}


def experiment_schedules(study: Study, plist: list[Params], layout: Layout | None = None
                         ) -> Schedule:
    """Every experiment's schedule (to its data's snapshot points), padded and batched;
    with a `layout`, padded to its capacities (which must hold it) with the early-stop
    arrays at +inf (never stops)."""
    scheds = [build_schedule(p, study.config, **_run_length(e),
                             snapshots=e.snapshot_points or [e.hours or e.revolutions],
                             pad=False, **schedule_numerics(study))
              for p, e in zip(plist, study.experiments)]
    U = max(s.updates for s in scheds)
    S = max(s.n_snapshots for s in scheds)
    A = max(s.attempts for s in scheds)
    if layout is not None:
        if U > layout.updates or S > layout.snapshots:
            raise ValueError(f"schedule of {U} pieces and {S} snapshots exceeds the layout "
                             f"{layout}")
        U, S = layout.updates, layout.snapshots
        A = max(A, layout.attempts) if A else 0
    batched = _stack([pad_schedule(s, U, S, A) for s in scheds])
    if layout is not None and layout.stop and batched.adaptive:
        batched = batched.stopping_at(math.inf, math.inf)
    return batched


def measured_data(study: Study, packing: Packing) -> Data:
    """The study's measured rows (profiles and histories) as a `Data`."""
    n = study.config.nodes
    offset_col = {c.experiment: i for i, c in enumerate(packing.columns)
                  if c.key == "angle_offset_deg"}
    rows = {k: [] for k in ("exp", "snap", "i0", "i1", "w", "is_max", "depth_um", "x",
                            "angle", "offset_col")}
    for ei, e in enumerate(study.experiments):
        points = e.snapshot_points
        if e.profile is not None:
            # periodic linear interpolation between the two nodes around each measured angle
            x = np.mod(e.profile.angle / (2 * np.pi) * n, n)
            i0 = np.floor(x).astype(int) % n
            rows["exp"] += [ei] * len(x)
            rows["snap"] += [points.index(float(r)) for r in e.profile.revolutions]
            rows["i0"] += list(i0)
            rows["i1"] += list((i0 + 1) % n)
            rows["w"] += list(x - np.floor(x))
            rows["is_max"] += [False] * len(x)
            rows["depth_um"] += list(np.asarray(e.profile.depth) * 1e6)
            rows["x"] += list(np.degrees(e.profile.angle))
            rows["angle"] += list(np.asarray(e.profile.angle, float))
            rows["offset_col"] += [offset_col.get(ei, -1)] * len(x)
        if e.history is not None:
            k = len(e.history.hours)
            rows["exp"] += [ei] * k
            rows["snap"] += [points.index(float(t)) for t in e.history.hours]
            rows["i0"] += [0] * k
            rows["i1"] += [0] * k
            rows["w"] += [0.0] * k
            rows["is_max"] += [True] * k
            rows["depth_um"] += list(np.asarray(e.history.depth) * 1e6)
            rows["x"] += list(np.asarray(e.history.hours, float))
            rows["angle"] += [0.0] * k
            rows["offset_col"] += [-1] * k
    if not rows["exp"]:
        raise InputError(f"{study.path}: no measured data (profile or history) to fit")
    f = jnp.float64
    return Data(exp=jnp.asarray(rows["exp"], jnp.int32), snap=jnp.asarray(rows["snap"], jnp.int32),
                i0=jnp.asarray(rows["i0"], jnp.int32), i1=jnp.asarray(rows["i1"], jnp.int32),
                w=jnp.asarray(rows["w"], f), is_max=jnp.asarray(rows["is_max"], bool),
                depth_um=jnp.asarray(rows["depth_um"], f), x=jnp.asarray(rows["x"], f),
                angle=jnp.asarray(rows["angle"], f),
                offset_col=jnp.asarray(rows["offset_col"], jnp.int32))


class ResidualModel(eqx.Module):
    """A study's model and data: u (P,) ↦ rows [µm] (see the module docstring)."""

    cfg: ModelConfig = eqx.field(static=True)
    exp_names: tuple = eqx.field(static=True)
    packing: Packing
    params: Params  # batched over experiments (leading axis), candidates at `off`
    schedule: Schedule  # batched
    data: Data
    nominal_angle_deg: jax.Array  # the given registration offsets (experiments,)
    noise_um: float | None = eqx.field(static=True, default=None)  # the study's, if given
    # a fixed correction of every row [µm] (rows,): the residual difference between a
    # finer resolution and this one at the answer (defect correction); zeros: none
    defect_um: jax.Array | None = None

    # ------------------------------------------------------------ the parameter vector
    @property
    def columns(self) -> tuple:
        return self.packing.columns

    @property
    def names(self) -> tuple[str, ...]:
        return self.packing.names

    @property
    def start(self):
        """Start values (P,) in key units: u = 0."""
        return self.packing.start

    @property
    def n_data(self) -> int:
        return self.data.n

    @property
    def measured(self) -> np.ndarray:
        return np.asarray(self.data.depth_um)

    def values(self, u):
        return self.packing.values(u)

    def with_packing(self, packing: Packing) -> ResidualModel:
        return dataclasses.replace(self, packing=packing)

    def with_schedule(self, schedule: Schedule) -> ResidualModel:
        return dataclasses.replace(self, schedule=schedule)

    def with_defect(self, defect_um) -> ResidualModel:
        """The same model with its rows corrected by `defect_um` (rows,) [µm]."""
        return dataclasses.replace(self, defect_um=jnp.asarray(defect_um, jnp.float64))

    @property
    def defect(self) -> np.ndarray:
        """The rows' correction (rows,) [µm] (zeros: none)."""
        return (np.zeros(self.n_data) if self.defect_um is None
                else np.asarray(self.defect_um, np.float64))

    # ------------------------------------------------------------ the model
    def batched_params(self, u) -> Params:
        """Every experiment's parameters (SI, batched) at u."""
        vals = self.values(u)
        p = self.params
        n_exp = len(self.exp_names)
        updates: dict = {}
        structural: dict = {}
        for i, c in enumerate(self.columns):
            if c.key == "angle_offset_deg":
                continue  # a property of the measurement, not of the joint
            si = vals[i] * c.to_si
            if c.group in STRUCTURAL_CANDIDATES:
                structural.setdefault(c.group, {})[c.key] = jnp.broadcast_to(si, (n_exp,))
            elif c.experiment is None:
                updates[c.key] = jnp.broadcast_to(si, (n_exp,))
            else:
                cur = updates.get(c.key, p.get(c.key))
                updates[c.key] = jnp.asarray(cur).at[c.experiment].set(si)
        p = p.with_values(updates) if updates else p
        for name, vals_si in structural.items():
            p = STRUCTURAL_CANDIDATES[name].set_strength(p, vals_si)
        return p

    def snapshots(self, u):
        """Snapshots (experiments, snapshots, nodes) [µm] and the batched `WearResult`."""
        # lax.map, not vmap: on CPU the experiments gain nothing from batching, and mapping
        # keeps the contact solver's data-dependent branches and loop counts per experiment.
        # the shape correction's coefficients packed before the map too (`pack`)
        res = jax.lax.map(lambda ps: wear_loop(ps[0], self.cfg, ps[1]),
                          (pack_shape(self.batched_params(u), self.cfg.shape),
                           self.schedule))
        return res.snapshots * 1e6, res

    def predict_from(self, snaps_um, u=None):
        """Model depth at every row [µm] from snapshots (experiments, snapshots, nodes).

        With fitted registration offsets (and u given), each profile row is read at its
        angle shifted by (fitted − given) offset, by a periodic linear interpolation that is
        differentiable in the offset: the weight is smooth in the angle and the node indices
        (floor) are locally constant, so d depth/d offset is the profile's slope there."""
        d = self.data
        # Each row reads its two nodes (and a history row its snapshot's maximum) straight
        # from the snapshots: gathering each row's whole profile first, (rows, nodes), was
        # under the shape analysis's ~150 forward-mode tangents 58 KB a row at 48 nodes
        # (17 GB for a 300 000-row scan; issue 41).
        n = snaps_um.shape[-1]
        flat = snaps_um.reshape(-1)
        start = (d.exp * snaps_um.shape[1] + d.snap) * n  # (rows,) each row's profile
        fits_angles = any(c.key == "angle_offset_deg" for c in self.columns)
        if fits_angles and u is not None:
            vals = self.values(u)
            k = jnp.clip(d.offset_col, 0, None)
            shift = jnp.where(d.offset_col >= 0, vals[k] - self.nominal_angle_deg[d.exp], 0.0)
            x = jnp.mod((d.angle + jnp.deg2rad(shift)) / (2 * jnp.pi) * n, n)
            fl = jnp.floor(x)
            i0 = fl.astype(jnp.int32) % n
            i1 = (i0 + 1) % n
            w = x - fl
        else:
            i0, i1, w = d.i0, d.i1, d.w
        at = flat[start + i0] * (1 - w) + flat[start + i1] * w
        rows = jnp.where(d.is_max, jnp.max(snaps_um, axis=-1)[d.exp, d.snap], at)
        return rows if self.defect_um is None else rows + self.defect_um

    def predict(self, u):
        """Model depth at every row [µm] at u (traceable)."""
        return self.predict_from(self.snapshots(u)[0], u)

    def prior_rows(self, u):
        """The packing's Gaussian prior rows (SD units) and their Jacobian, numpy."""
        return self.packing.prior_rows(u)


def build_model(study: Study, keys: list[str], start: dict | None = None, *,
                candidates=(), contact: str | None = None, shape=None,
                layout: Layout | None = None) -> ResidualModel:
    """The residual model of `study` fitting the study keys `keys` (`_packing.parse_fit`).

    - `start`: start values by output name (key units), else the study's values.
    - `candidates`: diagnose candidates added as columns of their own group (at `off`),
      the configuration extended with them; `contact`: another contact model; `shape`: the
      shape correction's basis (`effects.shape.ShapeBasis`), its coefficients at 0.
    - `layout`: the schedule's capacities (`Layout`), shared with other problems.
    The rows' correction (`defect_um`) starts at zero.
    """
    plist = [study.params(e) for e in study.experiments]
    cols = study_columns(study, keys, plist)
    cfg = study.config
    parametric = [c for c in candidates if c not in STRUCTURAL_CANDIDATES]
    if candidates:
        cfg = cfg.replace(effects=tuple(cfg.effects) + tuple(parametric))
    if "double_layer" in candidates:
        cfg = STRUCTURAL_CANDIDATES["double_layer"].configure(cfg)
    if contact is not None:
        cfg = cfg.replace(contact=contact)
    params = _stack(plist)
    for cand in candidates:
        if cand != "unsymmetric":
            cols += candidate_columns(cand, params)
    if shape is not None:
        cfg = cfg.replace(shape=shape)
        params = eqx.tree_at(lambda p: p.effect_params, params, {
            **params.effect_params, **{k: jnp.zeros(len(plist)) for k in shape.keys()}})
        cols += shape_columns(shape.keys())
    packing = packing_of(cols, start)
    nominal_angle = [e.profile.angle_offset_deg if e.profile is not None else 0.0
                     for e in study.experiments]
    model = ResidualModel(cfg=cfg, exp_names=tuple(e.name for e in study.experiments),
                          packing=packing, params=params,
                          schedule=experiment_schedules(study, plist, layout),
                          data=measured_data(study, packing),
                          nominal_angle_deg=jnp.asarray(nominal_angle, jnp.float64),
                          noise_um=study.noise_um)
    model = model.with_defect(np.zeros(model.n_data))
    if candidates or shape is not None:
        # candidate strengths at `off` in the batched parameters too (a study may set a
        # value for an effect it does not switch on; the structural strength maps to the
        # backing, which is absent in the single-layer base model)
        model = dataclasses.replace(model, params=model.batched_params(
            jnp.zeros(packing.size)))
    return model


# ---------------------------------------------------------------- evaluation


@dataclass(frozen=True)
class Evaluation:
    """The model at u (numpy).

    `pred`, `r` (rows,) [µm] (model, model − measured); `J` (rows, P) = d r/d u;
    `r_prior` (m,), `J_prior` (m, P): prior rows in SD units; `snaps` (E, S, N) [µm] and
    `J_snaps` (E, S, N, P); `max_residual`: largest relative contact residual; `worn`:
    largest worn-through cycle (−1: none); `sliding_m` (E,); `error_um`: integration
    error estimate of the worst experiment (inf: the adaptive loop ran out of attempts);
    `steps`: accepted integration steps of the longest experiment.
    """

    u: np.ndarray
    pred: np.ndarray
    r: np.ndarray
    J: np.ndarray
    r_prior: np.ndarray
    J_prior: np.ndarray
    snaps: np.ndarray
    J_snaps: np.ndarray | None
    max_residual: float
    worn: float
    sliding_m: np.ndarray
    error_um: float
    steps: int
    adaptive: bool = True

    @property
    def usable(self) -> bool:
        return bool(np.all(np.isfinite(self.r)) and np.all(np.isfinite(self.J))
                    and self.worn < 0 and np.isfinite(self.error_um))

    @property
    def rms_um(self) -> float:
        return float(np.sqrt(np.mean(self.r ** 2))) if self.r.size else 0.0

    def shifted(self, shift) -> Evaluation:
        """The evaluation with every row moved by `shift` (rows,) [µm] (a change of the
        rows' correction: the Jacobian is unchanged, the correction being fixed)."""
        shift = np.asarray(shift, np.float64)
        return dataclasses.replace(self, pred=self.pred + shift, r=self.r + shift)

    def point(self) -> lsq.Point:
        """The least-squares core's view: the integrator's error sets the floor of a
        meaningful decrease only where its steps adapt (their choice makes the error jump
        between nearby parameters; eq 23's fixed steps give a smooth bias instead)."""
        err = float(self.error_um) if self.adaptive and math.isfinite(self.error_um) else 0.0
        return lsq.Point(u=self.u, r=self.r, predicted=self.pred, J=self.J,
                         r_prior=self.r_prior, J_prior=self.J_prior, usable=self.usable,
                         error_um=err, extra=self)


@eqx.filter_jit
def _evaluate_jit(model: ResidualModel, u):
    TRACES["jacobian"] += 1  # runs when traced only
    def g(v):
        snaps, res = model.snapshots(v)
        rows = model.predict_from(snaps, v)
        aux = (rows, snaps, jnp.max(res.max_residual), jnp.max(res.worn_through_cycle),
               res.sliding_distance, jnp.max(res.error_estimate) * 1e6, jnp.max(res.steps))
        return (rows, snaps), aux

    (J, J_snaps), aux = jax.jacfwd(g, has_aux=True)(u)
    return J, J_snaps, aux


@eqx.filter_jit
def _forward_jit(model: ResidualModel, u):
    """Rows [µm], snapshots [µm], worn-through cycle, error estimate [µm], steps: no
    Jacobian (a check of a linearised answer costs one plain run)."""
    TRACES["forward"] += 1  # runs when traced only
    snaps, res = model.snapshots(u)
    return (model.predict_from(snaps, u), snaps, jnp.max(res.worn_through_cycle),
            jnp.max(res.error_estimate) * 1e6, jnp.max(res.steps))


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


def attempts_needed(model: ResidualModel, u) -> int:
    """The adaptive loop's estimated attempt count at u (`adaptive_attempts`, the largest
    over the experiments); 0 for eq-23 schedules."""
    sched = model.schedule
    if not sched.adaptive:
        return 0
    rates = np.asarray(_experiment_rates(model.with_schedule(None),
                                         jnp.asarray(u, jnp.float64)))
    host = jax.tree.map(np.asarray, sched)
    need = 0
    for i in range(sched.cycles.shape[0]):
        one = dataclasses.replace(jax.tree.map(lambda x: x[i], host), attempts=1)
        need = max(need, adaptive_attempts(None, model.cfg, one, rates=rates[i]))
    return need


@eqx.filter_jit
def _experiment_rates(model: ResidualModel, u):
    """`_regime_rates` of every experiment at u (experiments, regimes) [1/cycle], one
    compiled call (the model without its schedule: an attempt count is no new program).
    Eager, the parameters' assembly and the load history cost ~0.2 s per evaluation."""
    return jax.lax.map(lambda p: _regime_rates(p, model.cfg), model.batched_params(u))


def enough_attempts(model: ResidualModel, u, headroom: float = RAISE_HEADROOM
                    ) -> ResidualModel:
    """`model` with the adaptive loop's static attempt count raised (to a power of 2 at
    `headroom` x the need, so that few compilations arise) where the parameters at u need
    more than it has (the stiffness-limited step count grows with K_d, which a fit moves by
    orders)."""
    sched = model.schedule
    need = attempts_needed(model, u)
    if need <= sched.attempts:
        return model
    more = 2 ** math.ceil(math.log2(headroom * need))
    return model.with_schedule(dataclasses.replace(sched, attempts=more))


def needs_more_attempts(model: ResidualModel, u, factor: float = 4.0) -> bool:
    """True where u needs over `factor` times the model's attempt count: a trial at a
    stiff corner (running-in over a millimetre, K_d 100x) that would make the integrator
    crawl."""
    return model.schedule.adaptive and attempts_needed(model, u) > factor * \
        model.schedule.attempts


def evaluate(model: ResidualModel, u, *, doublings: int = 3
             ) -> tuple[Evaluation, ResidualModel]:
    """The model at u with its Jacobian, and the model it ran (its attempt count raised
    where u needed more: a fit keeps it, so later trials neither repeat a short run nor
    recompile)."""
    model = enough_attempts(model, u)
    uj = jnp.asarray(u, jnp.float64)
    out = _evaluate_jit(_dynamic(model), uj)
    # The attempt count is an estimate: where the loop did not reach the end (a stiff
    # layer's rejections), double it (a traced bound: no recompilation) rather than use a
    # truncated history.
    for _ in range(doublings):
        if not (model.schedule.adaptive and not np.isfinite(float(out[2][5]))):
            break
        model = model.with_schedule(model.schedule.more_attempts())
        out = _evaluate_jit(_dynamic(model), uj)
    J, J_snaps, (rows, snaps, mres, worn, sliding, err, steps) = jax.tree.map(np.asarray, out)
    u = np.asarray(u, np.float64)
    meas = model.measured
    r = rows - meas
    if not np.isfinite(float(err)):
        r = np.full_like(r, np.nan)  # a truncated history is not a model evaluation
    r_prior, J_prior = model.prior_rows(u)
    return Evaluation(u=u, pred=rows, r=r, J=J, r_prior=r_prior, J_prior=J_prior, snaps=snaps,
                      J_snaps=J_snaps, max_residual=float(mres), worn=float(worn),
                      sliding_m=sliding, error_um=float(err), steps=int(steps),
                      adaptive=model.schedule.adaptive), model


@dataclass(frozen=True)
class Forward:
    """A forward run (no Jacobian): `rows` (rows,) and `snaps` (E, S, N) [µm], NaN where the
    model wore through or its integration did not reach the end; `error_um` the worst
    experiment's integration error estimate, `steps` the longest one's accepted steps,
    `model` the model it ran (its attempt count raised where needed)."""

    rows: np.ndarray
    snaps: np.ndarray
    error_um: float
    steps: int
    model: ResidualModel

    @property
    def usable(self) -> bool:
        return bool(np.all(np.isfinite(self.rows)))


def forward_run(model: ResidualModel, u, *, doublings: int = 3, worn_ok: bool = False
                ) -> Forward:
    """The model at u without the Jacobian (`Forward`); `worn_ok`: keep the rows and
    snapshots of a run that wore through (a forecast past the layer)."""
    model = enough_attempts(model, u)
    uj = jnp.asarray(u, jnp.float64)
    out = _forward_jit(_dynamic(model), uj)
    for _ in range(doublings):
        if not (model.schedule.adaptive and not np.isfinite(float(out[3]))):
            break
        model = model.with_schedule(model.schedule.more_attempts())
        out = _forward_jit(_dynamic(model), uj)
    rows, snaps, worn, err, steps = (np.asarray(x) for x in out)
    if (float(worn) >= 0 and not worn_ok) or not np.isfinite(float(err)):
        rows, snaps = np.full(rows.shape, np.nan), np.full(snaps.shape, np.nan)
    return Forward(rows, snaps, float(err), int(steps), model)


def forward(model: ResidualModel, u, *, doublings: int = 3):
    """Rows [µm] and snapshots [µm] at u without the Jacobian, NaN where the model wore
    through or its integration did not reach the end; and the model it ran."""
    f = forward_run(model, u, doublings=doublings)
    return f.rows, f.snaps, f.error_um, f.model


def unusable_point(model: ResidualModel, u) -> lsq.Point:
    """A trial a fit declines to evaluate: rejected as unusable."""
    n, P = model.n_data, model.packing.size
    r_prior, J_prior = model.prior_rows(u)
    return lsq.Point(u=np.asarray(u, np.float64), r=np.full(n, np.inf),
                     predicted=np.full(n, np.nan), J=np.zeros((n, P)), r_prior=r_prior,
                     J_prior=J_prior, usable=False)


def integration_report(model: ResidualModel, ev: Evaluation) -> dict:
    """The `"integration"` block of a fit's JSON (same keys as `simulate`'s)."""
    sched = model.schedule
    tol = float(np.max(np.asarray(sched.tolerance))) * 1e6 if sched.adaptive else None
    err = float(ev.error_um)
    return {"integrator": "adaptive" if sched.adaptive else "paper",
            "error_estimate_um": err if math.isfinite(err) else "inf",
            "steps": int(ev.steps), "tolerance_um": tol}
