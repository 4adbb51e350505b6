"""The wear loop: Archard increments on a frozen profile, amplified M cycles per update (§4).

One update: contact for all steps of a cycle at once (vectorised), Δh_j = Σ_i K_d p_ij dS_i,
h ← h + M Δh. Updates run under `lax.scan`; the scan is split in two levels with
`jax.checkpoint` on each inner block, so reverse-mode memory grows like √updates, not like
updates × steps × nodes (100 000 revolutions at M = 1 fit in memory); the checkpoints keep
the contact solves' Newton answers (`remat`).
"""

from __future__ import annotations

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from jaxwear._core import tangents
from jaxwear._core.errors import InputError, WornThroughError
from jaxwear._core.host import to_device
from jaxwear._core.jit import jit
from jaxwear._core.types import NodeArray
from jaxwear._physics.adaptive import DEFAULT_WEAR_TOLERANCE_UM, _adaptive_loop, adaptive_attempts
from jaxwear._physics.config import ModelConfig, timed
from jaxwear._physics.cycle import (
    WearResult,
    _cold_starts,
    _warm_start,
    cycle_step,
    memory_size,
    node_area,
    run_history,
)
from jaxwear._physics.effects import get_effect
from jaxwear._physics.effects.shape import pack as pack_shape
from jaxwear._physics.limits import contact_failure
from jaxwear._physics.load import block_periods
from jaxwear._physics.params import Params
from jaxwear._physics.remat import KEEP_NEWTON, outer_policy
from jaxwear._physics.schedule import Schedule, bucket, crank_segments, duty_segments, make_schedule


def wear_loop(p: Params, cfg: ModelConfig, schedule: Schedule, h0: NodeArray | None = None
              ) -> WearResult:
    """Run the wear loop over `schedule` (pure, jit-able, differentiable in `p` and `h0`):
    the adaptive Runge-Kutta integrator for adaptive schedules, eq 23 otherwise.

    **Arguments:** `p` the joint's parameters (SI); `cfg` the static choices (nodes N,
    steps per cycle, contact, effects); `schedule` from `build_schedule` or
    `make_schedule`; `h0` (N,) the initial wear depth [m] (default zeros: a new bore).

    **Returns:** a `WearResult` (depths [m], snapshots, sliding [m], worn volume [m³],
    the integrator's error estimate [m] and step counts)."""
    p = pack_shape(p, cfg.shape)  # one array of coefficients through the loops, not ~140
    if schedule.adaptive:
        return _adaptive_loop(p, cfg, schedule, h0)
    effects = [get_effect(n) for n in cfg.effects]
    hist = run_history(p, cfg)
    n = cfg.nodes
    area = node_area(p, n)
    per_cycle_slide = jnp.sum(hist.slide, axis=1)  # (regimes,)
    h0 = jnp.zeros(n) if h0 is None else h0
    m = memory_size(cfg)  # the effects' hidden per-node states (0 on a new bore)

    # Warm starts: each regime's offsets from its previous update (the profile moves little
    # per update), the first update of each regime cold.
    n_reg = hist.load.shape[0]
    starts0 = _cold_starts(hist)

    def body(carry, x):
        # Padding updates (M = 0, from shape bucketing) skip all work.
        return lax.cond(x[0] > 0, live, lambda c, _: c, carry, x), None

    def live(carry, x):
        h, S, snaps, vol, res, its, worn, starts, h_seen, prev, err, steps, mem = carry
        M, regime, snap, end = x
        warm = _warm_start(cfg, hist, starts, h_seen, regime, h)
        dh, ds, work, sol = cycle_step(p, cfg, hist, regime, h, S, warm, mem if m else None)
        if m:  # the hidden states: Euler over the M cycles too
            mem = mem + M * ds
        starts = starts.at[regime].set(lax.stop_gradient(sol.offset))
        h_seen = h_seen.at[regime].set(lax.stop_gradient(h))
        s_cyc = per_cycle_slide[regime]
        factor = jnp.ones(())
        for eff in effects:
            factor = factor * eff.block_factor(p, S, s_cyc, M)
        h_new = h + M * factor * dh  # eq 23
        S_new = S + M * s_cyc
        # Euler's local error M²/2 h'' per node, h'' from the change of the rate since the
        # previous update of the same regime, summed with signs (an oscillation that decays
        # cancels); reported, never used to steer.
        rate = lax.stop_gradient(factor * dh)
        prev_rate, prev_reg, prev_M = prev
        local = 0.5 * M * M / jnp.maximum(prev_M, 1e-300) * (rate - prev_rate)
        err = err + jnp.where(prev_reg == regime, local, 0.0)
        prev = (rate, regime, M)
        if schedule.n_snapshots:
            snaps = snaps.at[snap].set(h_new, mode="drop")
        vol = vol + p.wear_coefficient * M * work
        # Once the layer is worn through the model is meaningless, and so are residuals.
        res = jnp.maximum(res, jnp.where(worn < 0, jnp.max(sol.residual), 0.0))
        its = jnp.maximum(its, sol.iterations)
        hit = (M > 0) & jnp.any(h_new >= p.layer_thickness) & (worn < 0)
        worn = jnp.where(hit, end, worn)
        return (h_new, S_new, snaps, vol, res, its, worn, starts, h_seen, prev, err, steps + 1,
                mem)

    U = schedule.updates
    inner = max(1, int(math.ceil(math.sqrt(U))))
    outer = int(math.ceil(U / inner))
    pad = outer * inner - U

    def padded(a, fill):
        return jnp.concatenate([a, jnp.full((pad,), fill, a.dtype)]).reshape(outer, inner)

    xs = (padded(schedule.cycles, 0.0), padded(schedule.regime, 0),
          padded(schedule.snapshot, schedule.n_snapshots), padded(schedule.cycle_end, 0.0))

    # the contact solves' Newton answers kept, not iterated again in reverse mode (`remat`)
    @functools.partial(jax.checkpoint, policy=outer_policy(U, hist.load.shape[-1], 1))
    def block(carry, xs_block):
        return lax.scan(jax.checkpoint(body, policy=KEEP_NEWTON), carry, xs_block)

    prev0 = (jnp.zeros(n), jnp.asarray(-1, jnp.int32), jnp.ones(()))
    # the carries the updates give a tangent, ready for it from the start: each level of
    # the checkpointed scan traced once under forward mode, not until its fixpoint
    # (`_core.tangents`); not the warm starts, the previous rate and the error estimate
    # (stop-gradient)
    h0r, S0, snaps0, vol0, res0, worn0, mem0 = tangents.ready(
        (h0, jnp.zeros(()), jnp.zeros((schedule.n_snapshots, n)), jnp.zeros(()),
         jnp.zeros(()), jnp.asarray(-1.0), jnp.zeros((m, n))),
        tangents.anchor_of((p, h0, schedule.cycles)))
    carry0 = (h0r, S0, snaps0, vol0, res0, jnp.zeros((), jnp.int32), worn0, starts0,
              jnp.broadcast_to(lax.stop_gradient(h0), (n_reg, n)), prev0, jnp.zeros(n),
              jnp.zeros((), jnp.int32), mem0)
    (h, S, snaps, vol, res, its, worn, _, _, _, err, steps, mem), _ = lax.scan(block, carry0,
                                                                               xs)
    if schedule.order and list(schedule.order) != list(range(schedule.n_snapshots)):
        snaps = snaps[jnp.asarray(schedule.order)]
    return WearResult(depth=h, snapshots=snaps, sliding_distance=S,
                      worn_volume=jnp.sum(h) * area, archard_volume=vol, max_residual=res,
                      max_iterations=its, worn_through_cycle=worn, history=hist,
                      error_estimate=jnp.max(jnp.abs(err)), steps=steps,
                      rejected_steps=jnp.zeros((), jnp.int32), memory=mem if m else None)


_wear_loop_jit = jit(wear_loop)



"""Default `[numerics] wear_tolerance_um`: bound on the summed local error estimates [µm]."""


def build_schedule(p: Params, cfg: ModelConfig, *, revolutions=None, hours=None,
                   snapshots=(), M: float | None = None, pad: bool = True,
                   pad_to: int | None = None, integrator: str | None = None,
                   tolerance_um: float = DEFAULT_WEAR_TOLERANCE_UM,
                   attempts: int | None = None) -> Schedule:
    """Schedule for a crank-slider run of `revolutions` or a timed run (oscillating joint,
    load history) of `hours`; `snapshots` in revolutions (crank) or hours (timed).

    `integrator`: "adaptive" (Runge-Kutta 3(2) with error control to `tolerance_um` [µm];
    the default when `M` is None) or "paper" (eq 23, M cycles per update; the default when
    `M` is given). Padded (with no-op entries) to `pad_to` entries, or with `pad` to a
    bucket size, so that runs share compilations. `attempts` overrides the adaptive loop's
    static number of attempted steps."""
    if integrator is None:
        integrator = "adaptive" if M is None else "paper"
    if integrator not in ("adaptive", "paper"):
        raise InputError(f'integrator must be "adaptive" or "paper", got {integrator!r}')
    if timed(cfg):
        if hours is None or not hours > 0:
            raise InputError(f"an oscillating joint or a load history needs hours > 0, got "
                             f"{hours}")
        segs, to_cycles = duty_segments(cfg.duty_cycle, float(hours), block_periods(p, cfg))
        snaps = to_cycles(snapshots)
    else:
        if revolutions is None or not revolutions > 0:
            raise InputError(f"revolutions must be > 0, got {revolutions}")
        segs = crank_segments(revolutions)
        snaps = list(snapshots)
    if integrator == "adaptive":
        if not tolerance_um > 0:
            raise InputError(f"wear_tolerance_um must be > 0, got {tolerance_um}")
        M = math.inf  # one entry per piece between cuts
    elif M is None:
        M = 100.0
    sched = make_schedule(segs, snaps, M)
    target = max(pad_to or 0, bucket(sched.updates) if pad else 0)
    if target > sched.updates:
        sched = make_schedule(segs, snaps, M, pad_to=target)
    if integrator == "adaptive":
        sched = dataclasses.replace(sched, attempts=1,
                                    tolerance=to_device(float(tolerance_um) * 1e-6, np.float64))
        sched = dataclasses.replace(sched, attempts=attempts or adaptive_attempts(p, cfg, sched))
    return sched


def schedule_numerics(study) -> dict:
    """`build_schedule` keywords from a study's `[numerics]`: integrator, M, tolerance."""
    return {"integrator": study.integrator, "M": study.revolutions_per_update,
            "tolerance_um": study.wear_tolerance_um}


def integration_report(res: WearResult, integrator: str, tolerance_um: float | None) -> dict:
    """The `"integration"` block of JSON outputs: error estimate [µm] (largest over a batch),
    accepted and rejected steps, tolerance [µm] (adaptive) and integrator."""
    return {"integrator": integrator,
            "error_estimate_um": float(np.max(np.asarray(res.error_estimate))) * 1e6,
            "steps": int(np.max(np.asarray(res.steps))),
            "rejected_steps": int(np.max(np.asarray(res.rejected_steps))),
            "tolerance_um": tolerance_um if integrator == "adaptive" else None}


def simulate(p: Params, cfg: ModelConfig = ModelConfig(), *, revolutions=None, hours=None,
             snapshots=(), M: float | None = None, h0=None, check: bool = True,
             pad_to: int | None = None, integrator: str | None = None,
             tolerance_um: float = DEFAULT_WEAR_TOLERANCE_UM) -> WearResult:
    """Predict the wear of one joint (jit-compiled; recompiles only when shapes or `cfg` change).

    **Arguments:**
    - `p`: parameters (SI). `cfg`: static model choices.
    - `revolutions` (crank-slider) or `hours` (oscillating joint); `snapshots` at revolution
      counts or hours.
    - `integrator`: "adaptive" (default when `M` is None: error-controlled Runge-Kutta,
      `tolerance_um` [µm] on the depth) or "paper" (eq 23 with `M` cycles per update; the
      default when `M` is given).
    - `check`: raise `WornThroughError` if the layer wears through and `RuntimeError` if a
      contact solve did not converge (relative force residual ≥ 1e-9).

    **Returns:** a `WearResult` (with `error_estimate` [m] and `steps`).
    """
    sched = build_schedule(p, cfg, revolutions=revolutions, hours=hours, snapshots=snapshots, M=M,
                           pad_to=pad_to, integrator=integrator, tolerance_um=tolerance_um)
    # The attempt count is a traced bound: runs of any count share one compilation. The
    # while loop stops at the run's end, so a bound above the estimate costs nothing, and
    # it is twice the estimate: a run that met the bound started again from the beginning,
    # and the boom's 25 h took 1 014 of its 1 024 attempts (the step controller at the
    # stiff layer's stability limit moves by ±3 % with round-off: 1 042 doubled the time).
    sched = sched.with_dynamic_attempts().more_attempts()
    res = _wear_loop_jit(p, cfg, sched, h0)
    # The attempt count is an estimate: if the loop did not reach the end, rerun with more
    # (rare).
    for _ in range(4):
        if not (sched.adaptive and not np.isfinite(float(res.error_estimate))):
            break
        sched = sched.more_attempts()
        res = _wear_loop_jit(p, cfg, sched, h0)
    if check:
        check_result(res, cfg, p=p)
    return res


def check_result(res: WearResult, cfg: ModelConfig, what: str = "simulation", p=None):
    """Raise for a run whose numbers are not physical: a contact solve that did not converge
    (`_plausible.contact_failure`: exit 2 naming the keys when the load strains the layer
    beyond the model's range, given the parameters `p`) or a layer worn through."""
    # NumPy on the host copies: an eager jnp.max compiled a program of its own for each
    # shape (20-90 ms of XLA each, every process; `integration_report` too)
    worn = float(np.max(np.asarray(res.worn_through_cycle)))
    unit = {"oscillating": "swing cycle", "load_history": "load cycle"}.get(cfg.driver,
                                                                            "revolution")
    residual = float(np.max(np.asarray(res.max_residual)))
    if not residual < 1e-9:

        raise contact_failure(what, p, cfg, residual,
                              float(np.max(np.asarray(res.history.load))))
    if worn >= 0:
        raise WornThroughError(f"{what}: the bushing layer is worn through at {unit} "
                               f"{worn:.0f} (h ≥ layer thickness)")
