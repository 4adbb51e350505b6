"""The candidates run as one batched computation: their snapshots and Jacobians, and the rows a
scan would add."""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from jaxwear._analyses.design.plan import DEFAULT_SCAN_STEP_DEG, NUISANCE, _placeholder
from jaxwear._core.errors import InputError
from jaxwear._core.jit import jit
from jaxwear._inference.attempts import enough_attempts
from jaxwear._inference.residual import build_model
from jaxwear._inference.result import FitResult
from jaxwear._study.study import Study


@jit
def _candidate_jit(model, v):
    """Snapshots (runs, S, N) [µm] and their Jacobian (runs, S, N, P + 1) in (u, δ): δ [mm]
    a shift of every run's clearance; the integration's worst error estimate [µm] and the
    worn-through flag. One compiled call: `model.snapshots` maps over the runs."""

    def g(w):
        p = model.params
        m = dataclasses.replace(model, params=p.replace(clearance=p.clearance + w[-1] * 1e-3))
        snaps, res = m.snapshots(w[:-1])
        return snaps, (snaps, jnp.max(res.error_estimate) * 1e6,
                       jnp.max(res.worn_through_cycle))

    return jax.jacfwd(g, has_aux=True)(v)


@dataclass(frozen=True)
class Runs:
    """The candidate runs of one model at its fitted values: `snaps` (R, S, N) [µm],
    `J` (R, S, N, P) with respect to the study's packed shared parameters (u of the fit),
    `J_clear` (R, S, N) [µm/mm] to the run's own clearance; `names` the P parameters;
    `seconds` the wall time of the batched call (compilation included)."""

    snaps: np.ndarray
    J: np.ndarray
    J_clear: np.ndarray
    names: tuple
    seconds: float
    error_um: float


def shared_keys(keys: list[str]) -> list[str]:
    return [k for k in keys if k not in NUISANCE]


def run_candidates(study: Study, result: FitResult, keys: list[str], runs: list,
                   points: list, *, is_timed: bool, shape=None,
                   shape_start: dict | None = None) -> Runs:
    """Every candidate run of `runs` (experiments, measured at `points`) in the fitted
    model of `result`, as one batched Jacobian (`_candidate_jit`). `shape`: the basis of
    a shape correction the model carries (a `shape:` rival), its coefficients at
    `shape_start` (by key) and among the shared parameters."""
    skeys = shared_keys(keys)
    fitted = dict(zip(result.names, map(float, result.values)))
    cfg = result.problem.cfg
    cand = dataclasses.replace(
        study.with_experiments([_placeholder(e, p, is_timed) for e, p in zip(runs, points)]),
        auto_resolution=False)
    cand = cand.with_config(nodes=cfg.nodes, steps_per_rev=cfg.steps_per_rev)
    start = {k: fitted[k] for k in skeys if k in fitted}
    start.update(shape_start or {})
    model = build_model(cand, skeys, start, shape=shape)
    u0 = np.zeros(model.packing.size)
    model = enough_attempts(model, u0)
    t0 = time.perf_counter()
    v = jnp.zeros(model.packing.size + 1)
    for _ in range(4):  # the attempt count is an estimate: double it where it ran short
        (Js, (snaps, err, worn)) = _candidate_jit(
            model.with_schedule(model.schedule.with_dynamic_attempts()), v)
        if not (model.schedule.adaptive and not np.isfinite(float(err))):
            break
        model = model.with_schedule(model.schedule.more_attempts())
    Js, snaps = np.asarray(Js), np.asarray(snaps)
    seconds = time.perf_counter() - t0
    if not np.isfinite(float(err)) or not np.all(np.isfinite(Js)):
        raise InputError("design: a candidate run did not complete (integration or contact "
                         "failed); narrow <<vary>>")
    if float(worn) >= 0:
        raise InputError("design: a candidate wears through the layer; narrow <<vary>> "
                         "(shorter runs or lower speeds)")
    # candidate u (start = fitted values, u = 0) → the fit's u of the same parameters
    names = tuple(model.packing.names)
    idx = [result.names.index(n) for n in names]
    Gc = model.packing.value_jacobian(u0)
    Gs = result.problem.packing.value_jacobian(result.u)[np.ix_(idx, idx)]
    T = np.linalg.solve(Gc, Gs)  # dv/du_c^-1 dv/du_s
    J = np.einsum("rsnp,pq->rsnq", Js[..., :-1], T)
    return Runs(snaps=snaps, J=J, J_clear=Js[..., -1], names=names, seconds=seconds,
                error_um=float(err))


def scan_metric(nodes: int, step_deg: float) -> np.ndarray:
    """W^T W (N, N): the rows of one scan every `step_deg` degrees, read from the nodes by
    periodic linear interpolation (as the residual model reads a profile)."""
    ang = np.arange(0.0, 360.0, step_deg)
    x = np.mod(ang / 360.0 * nodes, nodes)
    i0 = np.floor(x).astype(int) % nodes
    w = x - np.floor(x)
    W = np.zeros((len(ang), nodes))
    np.add.at(W, (np.arange(len(ang)), i0), 1 - w)
    np.add.at(W, (np.arange(len(ang)), (i0 + 1) % nodes), w)
    return W.T @ W


def scan_step_deg(study: Study) -> float:
    """The study's scan spacing (median of its first profile's angle steps), else 2°."""
    for e in study.experiments:
        if e.profile is not None and len(e.profile.angle) > 2:
            a = np.unique(np.round(np.degrees(np.asarray(e.profile.angle)), 9))
            d = np.diff(a)
            if d.size and np.median(d) > 0:
                return float(np.median(d))
    return DEFAULT_SCAN_STEP_DEG


def row_blocks(runs: Runs, metric: np.ndarray | None) -> np.ndarray:
    """Per (run, snapshot), the rows' information blocks Z^T M Z (R, S, q, q), Z = [J,
    J_clear]: profile scans with `metric` M = W^T W; depth histories (None) the row of
    the node at the maximum."""
    Z = np.concatenate([runs.J, runs.J_clear[..., None]], axis=-1)
    if metric is None:  # a history row: the maximum over the nodes
        k = np.argmax(runs.snaps, axis=-1)  # (R, S)
        z = np.take_along_axis(Z, k[..., None, None], axis=2)[:, :, 0]  # (R, S, q)
        return np.einsum("rsp,rsq->rspq", z, z)
    return np.einsum("rsnp,nm,rsmq->rspq", Z, metric, Z)
