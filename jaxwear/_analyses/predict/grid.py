"""The forecast's grid: the training study, the points each experiment is forecast at, and
the problem that runs them (one compiled layout for the fit and its forecasts)."""

from __future__ import annotations

import math
from dataclasses import replace

import jax.numpy as jnp
import numpy as np

from jaxwear._analyses.predict.life import LIFE_HORIZON, LIFE_REFINE_POINTS, LIFE_ROOM_ROUNDS
from jaxwear._core.errors import InputError, ModelFailure
from jaxwear._inference.evaluation import evaluate, integration_report
from jaxwear._inference.residual import Layout, experiment_schedules
from jaxwear._physics.config import timed
from jaxwear._physics.schedule import bucket
from jaxwear._study.study import Experiment, History, Profile, Study

LAPLACE_STOP_LAYERS = 2.0  # Laplace forecasts stop past this multiple of the layer (life tail)


MAX_REGIME_POINTS = 1000  # duty-block boundaries added to the grid at most


def unit_of_study(study: Study) -> str:
    return "hours" if timed(study.config) else "revolutions"


def training_study(study: Study, train_until: float | None) -> Study:
    """The study with only the measurements at or before `train_until` (revolutions for a
    crank-slider study, hours for an oscillating one). Experiments keep their place even when
    none of their rows remain: their clearance is then known from the prior only."""
    if train_until is None:
        return study
    lim = float(train_until) * (1 + 1e-12)
    exps = []
    for e in study.experiments:
        prof, hist = e.profile, e.history
        if prof is not None:
            keep = np.asarray(prof.revolutions) <= lim
            prof = replace(prof, angle=prof.angle[keep], depth=prof.depth[keep],
                           revolutions=prof.revolutions[keep]) if keep.any() else None
        if hist is not None:
            keep = np.asarray(hist.hours) <= lim
            hist = replace(hist, hours=hist.hours[keep],
                           depth=hist.depth[keep]) if keep.any() else None
        exps.append(replace(e, profile=prof, history=hist))
    if all(e.profile is None and e.history is None for e in exps):
        raise InputError(f"<<train_until>> {train_until:g}: no measurement of {study.path} is "
                         f"at or before it (unit: {unit_of_study(study)})")
    return study.with_experiments(exps)


def measured_max(e: Experiment) -> tuple[np.ndarray, np.ndarray]:
    """Measured maximum depth per measured point [µm] (history rows, or a scan's deepest row)."""
    if e.history is not None:
        return np.asarray(e.history.hours, float), np.asarray(e.history.depth) * 1e6
    if e.profile is not None:
        pts = np.array(e.snapshot_points)
        r = np.asarray(e.profile.revolutions)
        return pts, np.array([np.max(e.profile.depth[r == s]) * 1e6 for s in pts])
    return np.zeros(0), np.zeros(0)


def _last_count(e: Experiment) -> float:
    pts = e.snapshot_points
    return float(max(pts)) if pts else float(e.hours or e.revolutions)


def forecast_points(study: Study, e: Experiment, at: list[float], n_dense: int = 48,
                    life: bool = True) -> np.ndarray:
    """Snapshot points of one experiment: the `at` points, the measured points, a fan-chart
    grid to max(at) and (with `life`) a life grid to 10x the last measured count (sorted,
    unique)."""
    crank = not timed(study.config)
    top = max(at)
    horizon = max(LIFE_HORIZON * _last_count(e), top) if life else top
    grid = np.concatenate([np.linspace(0, top, n_dense // 2 + 1)[1:],
                           np.linspace(0, horizon, n_dense + 1)[1:]])
    if not crank:
        grid = np.concatenate([grid, regime_boundaries(study, horizon)])
    grid = np.round(grid) if crank else np.round(grid, 6)  # whole revolutions
    pts = np.concatenate([np.asarray(at, float), np.asarray(e.snapshot_points, float), grid])
    return np.unique(pts[pts > 0])


def regime_boundaries(study: Study, horizon: float) -> np.ndarray:
    """Hours at which the duty cycle changes block, up to `horizon` (none past
    MAX_REGIME_POINTS). Within a block the depth grows smoothly; at a change its rate jumps
    (the boom: 1 h at 20°, then 4 h at 1°), so a grid that straddles a change misplaces a
    crossing by up to the grid step. The adaptive wear loop already ends a piece at each
    change, so snapshots there cost no integration steps."""
    blocks = study.config.duty_cycle
    if len(blocks) < 2:
        return np.zeros(0)
    ends = np.cumsum([b.duration_h for b in blocks])
    period = float(ends[-1])
    n = int(math.ceil(horizon / period))
    if n * len(blocks) > MAX_REGIME_POINTS:
        return np.zeros(0)
    t = (np.arange(n)[:, None] * period + ends[None, :]).ravel()
    return t[t <= horizon * (1 + 1e-12)]


def forecast_study(study: Study, points: list[np.ndarray]) -> Study:
    """The study with placeholder rows at `points` per experiment (so that `build_problem`
    makes one snapshot per point); the rows' values are never used."""
    exps = []
    for e, pts in zip(study.experiments, points):
        pts = np.asarray(pts, float)
        z = np.zeros(len(pts))
        if timed(study.config):
            exps.append(replace(e, hours=float(pts.max()), profile=None,
                                history=History(hours=pts, depth=z, path="<forecast>")))
        else:
            exps.append(replace(e, revolutions=float(pts.max()), history=None,
                                profile=Profile(angle=z, depth=z, revolutions=pts,
                                                path="<forecast>")))
    return study.with_experiments(exps)


def forecast_snapshots(problem, u):
    """Snapshots (E, S, N) [µm], their exact Jacobian (E, S, N, p) w.r.t. u and the
    integration report of the forecast: one evaluation of the residual model over the
    forecast points (`_residual.evaluate`, whose attempt count is doubled where a history
    was truncated rather than returned)."""
    ev, used = evaluate(problem, u, doublings=4)
    return ev.snaps, ev.J_snaps, integration_report(used, ev)


def forecast_layout(study: Study, train: Study, points, refine: bool = True) -> Layout:
    """Capacities (`_residual.Layout`) that hold the training problem and the forecast over
    `points` with room for the life's refinement rounds (`LIFE_ROOM_ROUNDS` x 3
    brackets x `LIFE_REFINE_POINTS` more points per experiment), rounded up to buckets:
    the fit and every forecast then share one compiled function. Attempts: the forecast's
    at the study's values (a fit raises them where its values need more)."""

    plist = [study.params(e) for e in study.experiments]
    fs = experiment_schedules(forecast_study(study, points), plist)
    ts = experiment_schedules(train, plist)
    room = LIFE_ROOM_ROUNDS * 3 * LIFE_REFINE_POINTS if refine else 0
    return Layout(updates=bucket(max(fs.cycles.shape[-1], ts.cycles.shape[-1]) + room),
                  snapshots=bucket(max(fs.n_snapshots, ts.n_snapshots) + room),
                  attempts=max(fs.attempts, ts.attempts))


def forecast_problem(train: Study, base, points, layout: Layout | None = None):
    """The problem `base` (a training problem, or a `FitResult` whose problem it is) over
    the forecast `points` (one array per experiment): the same packing, parameters, rows
    and row correction, its rows read from the forecast's snapshots (`train`: the training
    study whose snapshot points the rows index), the schedule to max(points) padded to
    `layout` (when it holds it; else bucketed capacities, so that refinement rounds share
    a compilation). Its u is the training problem's: u = `result.u` is the fit."""

    base = getattr(base, "problem", base)
    plist = [train.params(e) for e in train.experiments]
    fstudy = forecast_study(train, points)
    sched = experiment_schedules(fstudy, plist)
    if layout is None or not layout.holds(sched):
        layout = Layout(bucket(sched.cycles.shape[-1]), bucket(sched.n_snapshots),
                        sched.attempts)
    attempts = max(layout.attempts, base.schedule.attempts)
    sched = experiment_schedules(fstudy, plist, replace(layout, attempts=attempts))
    d = base.data
    exp, snap = np.asarray(d.exp), np.asarray(d.snap)
    new = np.empty_like(snap)
    for i, (e, s) in enumerate(zip(exp, snap)):
        t = train.experiments[e].snapshot_points[s]
        j = int(np.argmin(np.abs(np.asarray(points[e]) - t)))
        if not math.isclose(float(points[e][j]), float(t), rel_tol=1e-9, abs_tol=1e-9):
            raise ModelFailure(f"forecast points of experiment {e} miss the training point "
                               f"{t:g}")
        new[i] = j
    data = replace(d, snap=jnp.asarray(new, jnp.int32))
    return replace(base, schedule=sched, data=data)


def stop_past_layer(study: Study, fprob, points, at, factor: float = 1.0):
    """`fprob` whose (adaptive) runs stop once, past the last `at` point, the maximum depth
    has reached `factor` x the layer (≥ every allowed limit): the points after serve only
    the life estimate, which needs to know that the forecast is past the limit, not by how
    much; their snapshots come back +inf (`fill_past_stop`). Integrating on through the
    substrate to 10x the last measurement cost the boom's forecasts over 30x the steps (and
    ran out of attempts). Eq-23 schedules are returned unchanged."""
    sched = fprob.schedule
    if not sched.adaptive:
        return fprob
    depth, after = [], []
    snap = np.asarray(sched.snapshot)
    ends = np.asarray(sched.cycle_end)
    for i, (e, pts) in enumerate(zip(study.experiments, points)):
        k = int(np.argmin(np.abs(np.asarray(pts) - max(at))))
        j = np.nonzero(snap[i] == k)[0]
        after.append(float(ends[i, j[0]]) if len(j) else float(ends[i].max()))
        depth.append(factor * float(study.params(e).layer_thickness))
    return replace(fprob, schedule=sched.stopping_at(np.array(depth), np.array(after)))
