"""The adaptive wear integrator: the Bogacki-Shampine 3(2) pair over cycles with error
control, its stability limit and its static attempt budget (docs/design.md §4)."""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from jaxwear._core import tangents
from jaxwear._core.errors import TrialFailed
from jaxwear._core.jit import jit
from jaxwear._physics.config import ModelConfig
from jaxwear._physics.contact import stiffness_per_area
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
from jaxwear._physics.load import load_history
from jaxwear._physics.params import Params
from jaxwear._physics.remat import KEEP_NEWTON, outer_policy
from jaxwear._physics.schedule import Schedule, bucket

# Bogacki-Shampine 3(2) pair (FSAL): nodes c, weights b (3rd order), error weights b - b̂.
_SAFETY, _SHRINK, _GROW = 0.9, 0.2, 5.0  # the step controller's factors
_PI = (0.7 / 3, 0.4 / 3)
"""Exponents (α, β) of the step controller after an accepted step: the next step is the
last one times 0.9 r_n^-α r_{n-1}^β, with r the error ratio of the last and the previous
accepted attempt (Gustafsson's PI controller; α = 0.7/k, β = 0.4/k with k = 3 for the
pair's embedded 2nd order, Hairer & Wanner, Solving ODEs II, §IV.2). The plain controller,
0.9 r_n^(-1/3), grew a step 1.5x from a ratio of ~0.25 to a ratio of ~2.5 and a rejection:
the estimate at the contact's edge does not scale as step³. Measured (360 x 360): rig
10 000 rev 32 + 16 rejected attempts -> 40 + 1, boom 25 h 663 + 168 -> 691 + 52; the error
against M = 1 the same (docs/performance.md, "A PI step controller")."""
_PI_START = 1e-4  # r_{n-1} before the first accepted attempt (and its floor): a cautious
# first growth
_BS_C = (0.0, 0.5, 0.75, 1.0)


_BS_B = (2 / 9, 1 / 3, 4 / 9)


_BS_E = (2 / 9 - 7 / 24, 1 / 3 - 1 / 4, 4 / 9 - 1 / 3, -1 / 8)


# The same pair as arrays for the stage loop: row i of _BS_A gives stage i's input
# h + ΔN Σ_j a_ij k_j (row 3 is the 3rd-order solution y1, input of the FSAL stage).
_BS_A = np.array([[0.0, 0.0, 0.0, 0.0], [0.5, 0.0, 0.0, 0.0], [0.0, 0.75, 0.0, 0.0],
                  [*_BS_B, 0.0]])


_BS_BW = np.array([*_BS_B, 0.0])  # weights of the stages' work (3rd order)
STABILITY = 2.5
"""The pair's stability limit on the negative real axis, |λ ΔN| ≤ 2.5 (2.51 for any
3-stage 3rd-order Runge-Kutta method): each step is capped at STABILITY / λ with λ the
wear-rate bound K_d max_j k_j(h) S_cycle at the step's depth (`stability_cap`)."""
STATE_TOL = 1e-3  # the hidden states' local error a step (`Effect.memory_rate`) [-]


def _adaptive_loop(p: Params, cfg: ModelConfig, schedule: Schedule, h0) -> WearResult:
    return _adaptive_trace(p, cfg, schedule, h0)[0]


def _adaptive_trace(p: Params, cfg: ModelConfig, schedule: Schedule, h0, replay=None):
    """dh/dN = rate(h, S(N)) (one cycle's wear on the frozen profile, the instantaneous
    effect factor), integrated piece by piece with the Bogacki-Shampine 3(2) pair. Where an
    effect is a clock (`Effect.cycles_at`: running-in), in its clock τ = ∫ factor dN
    instead: dh/dτ = rate / factor, each piece τ(cycles) long, S at a stage from the
    inverse; the factor's fast start then costs no steps.

    Error control on a *global* error estimate per node [m], carried along: the signed sum
    of the pair's local estimates (3rd minus embedded 2nd order). A step is accepted while
    max |sum| stays within tol (½ + ½ N/N_total): half the tolerance may be spent at any
    time (the fast start of a stiff layer), the other half accrues with N. The final
    max |sum| is `error_estimate`; as the 3rd-order solution is propagated it bounds the
    error from above in practice (measured: docs/numerics.md). Stiff layers: the explicit
    pair's stability limit (|λ ΔN| ≲ 2.5, λ = K_d k S_cycle) bounds the steps; linearly
    implicit W-methods (ROS2 with a diagonal Jacobian; ROS34PW2 and extrapolated linearly
    implicit Euler with the diagonal-plus-rank-two Winkler Jacobian) were measured and
    rejected: docs/numerics.md, "Stiff layers".
    One scan iteration is one attempted step (a static number, under the same two-level
    checkpointing as eq 23, each stage checkpointed at the inner level: `remat`);
    attempts after the end skip all work. Step sizes are held
    fixed under differentiation (gradients of the solution on the chosen steps; they
    differ from those of the adaptive answer by about the integration error).

    Returns the result and the trace of attempts (step tried [cycles, or the clock's unit]
    (attempts,), accepted (attempts,), clipped to its piece's end (attempts,)); `replay` =
    such a trace re-runs exactly those steps and decisions (no controller): the solution
    on the chosen steps as a smooth function of `p`.
    """
    effects = [get_effect(n) for n in cfg.effects]
    hist = run_history(p, cfg)
    anchor = tangents.anchor_of((p, h0, schedule.cycles))
    n = cfg.nodes
    area = node_area(p, n)
    per_cycle_slide = jnp.sum(hist.slide, axis=1)
    h0 = jnp.zeros(n) if h0 is None else h0
    # the effects' hidden per-node states ride with the depth in one state vector y =
    # (h, s_1, ..., s_m) (0 on a new bore): the same stages and steps; the error control
    # and everything read as a depth take its first n entries
    m = memory_size(cfg)
    y0 = jnp.concatenate([h0, jnp.zeros(m * n, h0.dtype)]) if m else h0
    n_reg = hist.load.shape[0]
    starts0 = _cold_starts(hist)

    P = schedule.updates
    cycles, regime_of = schedule.cycles, schedule.regime
    total = jnp.max(schedule.cycle_end)
    tol = schedule.tolerance
    # The clock: an effect whose block factor has an inverse (running-in) is integrated
    # exactly by stepping in τ = ∫ factor dN (dh/dτ = the cycle's wear without it): a factor
    # of 1 + a at the start made the steps ~(1 + a)x shorter while it decayed (the boom at
    # a = 100, S_r = 0.046 m: 1 538 steps against 294 at a = 1, the same a·S_r). Pieces are
    # `span` long in τ; `cycles_in(seg, τ)` is the count of cycles into piece seg at τ.
    clock = _clock_effect(p, effects)
    slide_of = per_cycle_slide[regime_of]  # (P,)
    s_start = jnp.concatenate([jnp.zeros(1), jnp.cumsum(cycles * slide_of)[:-1]])
    if clock is None:
        span = cycles

        def cycles_in(seg, tau):
            return tau
    else:
        span = cycles * clock.block_factor(p, s_start, slide_of, cycles)

        def cycles_in(seg, tau):
            return jnp.clip(clock.cycles_at(p, s_start[seg], slide_of[seg], tau), 0.0,
                            cycles[seg])

    def rate(y, S, reg, ws):
        """Wear per unit of the clock [m] (nodes,) at profile h and sliding S (per cycle
        without a clock effect), with the work per cycle and the factor the clock divided
        out; with hidden states (y = (h, s)), their rates per unit of the clock after it."""
        h = y[:n]
        starts, h_seen = ws
        warm = _warm_start(cfg, hist, starts, h_seen, reg, h)
        dh, ds, work, sol = cycle_step(p, cfg, hist, reg, h, S, warm,
                                       y[n:].reshape(m, n) if m else None)
        factor = jnp.ones(())
        for eff in effects:
            if eff is not clock:
                factor = factor * eff.block_factor(p, S, per_cycle_slide[reg], 0.0)
        ws = (starts.at[reg].set(lax.stop_gradient(sol.offset)),
              h_seen.at[reg].set(lax.stop_gradient(h)))
        if clock is not None:  # Archard's volume counts cycles: work per unit of τ
            work = work / clock.block_factor(p, S, per_cycle_slide[reg], 0.0)
        dy = factor * dh
        if m:  # dN/dτ = 1/clock factor: the states are driven per cycle
            per = 1.0 if clock is None else clock.block_factor(p, S, per_cycle_slide[reg], 0.0)
            dy = jnp.concatenate([dy, ds.reshape(-1) / per])
        return (dy, work, jnp.max(sol.residual),
                jnp.asarray(sol.iterations, jnp.int32), ws)

    mem_stiff = jnp.zeros(())
    for eff in effects:  # hidden states that relax on their own (`_regime_rates`)
        mem_stiff = jnp.maximum(mem_stiff, eff.memory_stiffness(p))

    def stability_cap(h, S, reg):
        """The longest step [cycles, or the clock's unit] the pair takes stably at depth h
        in regime `reg`: STABILITY / λ, λ = K_d max_j k_j(h) S_cycle, the bound of
        `_regime_rates` at the current depth (a thinner layer is stiffer). On the stiff boom
        the controller alone ran into the limit and back: 282 of 1 042 attempts rejected
        (boom, 25 h, 360 x 360), 172 of 834 with the cap, the answer within 0.0002 µm
        (its tolerance 0.002 µm; docs/performance.md). A cap is no decision of the
        controller's: it only shortens proposals, each step is still accepted or rejected
        on its error. In the clock τ of running-in (dh/dτ = rate / factor) λ is divided
        by the factor."""
        lam = jnp.maximum(p.wear_coefficient * per_cycle_slide[reg]
                          * jnp.max(stiffness_per_area(h, p, cfg.double_layer)), mem_stiff)
        cap = STABILITY / jnp.maximum(lam, 1e-300)
        if clock is not None:
            cap = cap * clock.block_factor(p, S, per_cycle_slide[reg], 0.0)
        return lax.stop_gradient(cap)

    def attempt(c):
        (h, S, seg, pos, (dt, r_prev), k1, w1, k1_ok, err, steps, rej, snaps, vol, res,
         its, worn, ws) = c
        reg = regime_of[seg]
        s_cyc = per_cycle_slide[reg]
        rem = span[seg] - pos
        dt = jnp.minimum(dt, stability_cap(h[:n], S, reg))
        clipped = dt >= rem * (1 - 1e-9)
        if replay is not None:
            # the trace's decision: a piece's length in τ moves with the clock's parameters
            dt, clipped = replay[0][steps + rej], replay[2][steps + rej]
        step = jnp.where(clipped, rem, dt)
        n0 = schedule.cycle_end[seg] - cycles[seg]  # cycles before the piece

        def sliding_at(tau):
            return s_start[seg] + s_cyc * cycles_in(seg, tau)

        # cycles into the piece at the step's start and end
        n_pos, n_step = cycles_in(seg, pos), cycles_in(seg, pos + step)
        S1 = jnp.where(clipped, s_start[seg] + cycles[seg] * s_cyc, s_start[seg] + s_cyc * n_step)

        # The four stages are one loop, not four inlined copies of the cycle's contact
        # solve: the compiled program is ~3x smaller (compile time is most of a cold
        # answer). Stage 0 is the last step's final stage (FSAL) unless that is stale.
        def stage(carry, i):
            K, Wk, ws, rmax, imax = carry
            y = h + step * (jnp.asarray(_BS_A)[i] @ K)

            def fresh(ws):
                return rate(y, sliding_at(pos + jnp.asarray(_BS_C)[i] * step), reg, ws)

            def reuse(ws):
                return k1, w1, jnp.zeros(()), jnp.zeros((), jnp.int32), ws

            k, w, r, it, ws = lax.cond((i > 0) | ~k1_ok, fresh, reuse, ws)
            return (K.at[i].set(k), Wk.at[i].set(w), ws, jnp.maximum(rmax, r),
                    jnp.maximum(imax, it)), None

        K0, W0, r0 = tangents.ready(
            (jnp.zeros((4, h.shape[0]), h.dtype), jnp.zeros(4), jnp.zeros(())), anchor)
        # each stage checkpointed (`remat`): reverse mode keeps its carries and Newton's
        # answers, not the stacked (steps, nodes) fields of the four stages
        (K, Wk, ws, r_att, i_att), _ = lax.scan(
            jax.checkpoint(stage, policy=KEEP_NEWTON, prevent_cse=False),
            (K0, W0, ws, r0, jnp.zeros((), jnp.int32)), jnp.arange(4))
        y1 = h + step * (jnp.asarray(_BS_A)[3] @ K)  # the last stage's own input, bit for bit
        k1, w1, k4, w4 = K[0], Wk[0], K[3], Wk[3]
        wsum = jnp.asarray(_BS_BW) @ Wk
        est_y = step * (jnp.asarray(_BS_E) @ K)  # signed, ~ΔN³
        est = est_y[:n]  # the depth's
        # Global error per node (signed sum of local estimates). Budget: half the tolerance
        # at any time (the start's fast transient), the other half accrues with N.
        n_end = jnp.where(clipped, schedule.cycle_end[seg], n0 + n_step)
        budget = tol * (0.5 + 0.5 * n_end / total)
        slack = jnp.maximum(budget - jnp.max(jnp.abs(err)),
                            1e-3 * tol * (n_end - n0 - n_pos) / total)
        ratio = jnp.max(jnp.abs(est)) / slack
        if m:
            # the hidden states (of order 1): a local error of at most STATE_TOL a step.
            # The depth's control alone let a film whose depth barely moved relax in 4
            # steps of ~1000 cycles at λΔN ≈ 3 (s overshot 1 by 5 %,
            # tests/test_law_memory.py); per unit step (STATE_TOL x the step's share of
            # the run) it took 485 steps and 740 rejections where 27 served the depth
            ratio = jnp.maximum(ratio, jnp.max(jnp.abs(est_y[n:])) / STATE_TOL)
        accept = ratio <= 1.0 if replay is None else replay[1][steps + rej]
        # A PI controller after an accepted step (`_PI`), the plain one after a rejection
        r = jnp.maximum(ratio, 1e-12)
        fac = jnp.clip(_SAFETY * jnp.where(accept, r ** -_PI[0] * r_prev ** _PI[1],
                                           r ** (-1 / 3)), _SHRINK, _GROW)
        r_prev = lax.stop_gradient(jnp.where(accept, jnp.maximum(ratio, _PI_START), r_prev))
        proposal = step * fac
        # Step sizes are not differentiated: at a stiff layer's stability limit the
        # controller's sequence is chaotic and its derivative explodes (measured: 1e19 on
        # the boom). Gradients are those of the solution on the chosen steps.
        dt_new = lax.stop_gradient(
            jnp.where(accept & clipped, jnp.maximum(dt, proposal), proposal))
        done_piece = accept & clipped
        nxt = jnp.minimum(seg + 1, P - 1)
        snap_idx = jnp.where(done_piece, schedule.snapshot[seg], schedule.n_snapshots)
        if schedule.n_snapshots:
            snaps = snaps.at[snap_idx].set(y1[:n], mode="drop")
        end = n_end
        hit = accept & jnp.any(y1[:n] >= p.layer_thickness) & (worn < 0)
        new_worn = jnp.where(hit, end, worn)
        res = jnp.maximum(res, jnp.where(worn < 0, r_att, 0.0))
        its = jnp.maximum(its, i_att)
        keep = lambda a, b: jnp.where(accept, a, b)  # noqa: E731
        # FSAL: the last stage starts the next step unless the regime changes
        fsal = (keep(k4, k1), keep(w4, w1),
                jnp.where(done_piece, regime_of[nxt] == reg, True))
        return (keep(y1, h), keep(S1, S), jnp.where(done_piece, seg + 1, seg),
                jnp.where(done_piece, 0.0, keep(pos + step, pos)), (dt_new, r_prev),
                *fsal,
                keep(err + est, err), steps + accept, rej + (~accept), snaps,
                keep(vol + p.wear_coefficient * step * wsum, vol), res, its,
                new_worn, ws), (step, accept, clipped)

    stop = schedule.stop_depth is not None

    def finished(c):
        seg = c[2]
        done = (seg >= P) | (cycles[jnp.minimum(seg, P - 1)] <= 0)
        if stop:
            # at the end (pos 0) of a piece that took a snapshot (a regime change alone
            # would leave the last snapshot short of `stop_depth`), past `stop_after`, with
            # the depth past `stop_depth`
            prev = jnp.clip(seg - 1, 0, P - 1)
            past = schedule.cycle_end[prev] >= schedule.stop_after * (1 - 1e-12)
            snapped = schedule.snapshot[prev] < schedule.n_snapshots
            done = done | ((seg > 0) & past & snapped & (c[3] == 0.0)
                           & (jnp.max(c[0]) >= schedule.stop_depth))
        return done

    def body(c, _):
        return lax.cond(finished(c), lambda c: (c, (jnp.zeros(()), jnp.asarray(False),
                                                     jnp.asarray(False))), attempt, c)

    z = jnp.zeros(())
    # the carries the steps give a tangent, ready for it from the start: the attempt's
    # body is traced once under forward mode, not until its fixpoint (`_core.tangents`);
    # not the step size and the warm starts (stop-gradient)
    y0, S0, pos0, k10, w10, err0, snaps0, vol0, res0, worn0 = tangents.ready(
        (y0, z, z, jnp.zeros_like(y0), z, jnp.zeros(n),
         jnp.full((schedule.n_snapshots, n), jnp.inf if stop else 0.0), z, z,
         jnp.asarray(-1.0)), anchor)
    c0 = (y0, S0, jnp.zeros((), jnp.int32), pos0,
          (jnp.minimum(total / 64, span[0]), jnp.asarray(_PI_START)),
          k10, w10, jnp.asarray(False), err0, jnp.zeros((), jnp.int32),
          jnp.zeros((), jnp.int32), snaps0, vol0, res0,
          jnp.zeros((), jnp.int32), worn0,
          (starts0, jnp.broadcast_to(lax.stop_gradient(h0), (n_reg, n))))
    if schedule.dynamic:
        # A while loop bounded by the traced attempt count: one compilation for any count
        # (forward and forward-mode runs: the fits' Jacobians); no trace, no replay.
        if replay is not None:
            raise ValueError("a replay needs a static attempt count")

        def more(cc):
            return (cc[1] < schedule.attempt_limit) & ~finished(cc[0])

        c, _ = lax.while_loop(more, lambda cc: (attempt(cc[0])[0], cc[1] + 1),
                              (c0, jnp.zeros((), jnp.int32)))
        trace = None
    else:
        A = schedule.attempts
        inner = max(1, int(math.ceil(math.sqrt(A))))
        outer = int(math.ceil(A / inner))

        # the contact solves' Newton answers kept, 4 stages an attempt (`remat`); the
        # attempts of a block are not checkpointed one by one: their stages are
        @functools.partial(jax.checkpoint, policy=outer_policy(A, hist.load.shape[-1], 4))
        def block(c, _):
            return lax.scan(body, c, None, length=inner)

        c, trace = lax.scan(block, c0, None, length=outer)
        trace = jax.tree.map(lambda a: a.reshape(-1), trace)  # (outer * inner,) >= attempts
    y, S, _, _, _, _, _, _, err, steps, rej, snaps, vol, res, its, worn, _ = c
    h, memory = y[:n], (y[n:].reshape(m, n) if m else None)
    err = jnp.where(finished(c), jnp.max(jnp.abs(err)), jnp.inf)
    if schedule.order and list(schedule.order) != list(range(schedule.n_snapshots)):
        snaps = snaps[jnp.asarray(schedule.order)]
    return WearResult(depth=h, snapshots=snaps, sliding_distance=S,
                      worn_volume=jnp.sum(h) * area, archard_volume=vol, max_residual=res,
                      max_iterations=its, worn_through_cycle=worn, history=hist,
                      error_estimate=err, steps=steps, rejected_steps=rej,
                      memory=memory), trace


def _clock_effect(p: Params, effects):
    """The effect whose block factor the adaptive loop integrates exactly (its clock), or
    None: the one effect that gives `cycles_at` (with two, none: the product of their
    factors has no clock of either's form)."""
    z = jnp.zeros(())
    own = [e for e in effects if e.cycles_at(p, z, z + 1.0, z) is not None]
    return own[0] if len(own) == 1 else None


def stable_amplification(p: Params, cfg: ModelConfig) -> float:
    """Largest M for which the explicit wear update (eq 23) is expected to stay stable.

    Linearised, one update changes the wear rate at a loaded node by -M K_d k S_c times the
    extra depth (k the foundation stiffness, S_c the sliding per cycle), so the update is a
    stable, non-oscillating relaxation only while M K_d k S_c stays below ~2. We use the
    whole cycle's sliding for S_c (a node touches for part of it), which makes the estimate
    conservative: measured onset of trouble at M ≈ 2500 on the rig (estimate 1400) and
    M ≈ 20 on the stiff bimetal boom bearing (estimate ~6).
    """
    rate = float(_update_rate(p, cfg))
    return math.inf if not rate > 0 else 2.0 / rate


@jit
def _update_rate(p: Params, cfg: ModelConfig):
    """K_d k S_cycle (per cycle) of the unworn joint, for `stable_amplification`."""
    return jnp.max(_regime_rates(p, cfg))


def _regime_rates(p: Params, cfg: ModelConfig):
    """K_d k S_cycle per duty regime (regimes,) [1/cycle]: the stiff decay rate's bound (or
    an effect's hidden states' own relaxation rate, `Effect.memory_stiffness`, if larger)."""
    k = jnp.max(stiffness_per_area(jnp.zeros(1), p, cfg.double_layer))
    out = p.wear_coefficient * k * jnp.sum(load_history(p, cfg).slide, axis=1)
    for name in cfg.effects:  # hidden states that relax on their own (a film)
        out = jnp.maximum(out, get_effect(name).memory_stiffness(p))
    return out


DEFAULT_WEAR_TOLERANCE_UM = 0.002
RATE_STEPS = 72  # the load history's steps per cycle for the rate bound (`rate_config`)


def rate_config(cfg: ModelConfig) -> ModelConfig:
    """The configuration the rate bound (`_regime_rates`) is computed in: at most
    `RATE_STEPS` steps per cycle, and the nodes fixed (the bound does not depend on them).
    Every resolution of a study (90 x 72 to 360 x 360, design.md §6) then shares one
    compiled rate program where each compiled its own (3 x 2 programs in a rig calibration,
    ~0.5 s of a cold answer). The bound moves with the steps only through the cycle's
    sliding (a sum over the steps): 0.06 % between 72 and 360 steps on the rig and the
    boom, inside the attempt count's own margins (`adaptive_attempts`: x3, then a bucket;
    and a short count is doubled and rerun)."""
    return cfg.replace(nodes=8, steps_per_rev=min(cfg.steps_per_rev, RATE_STEPS))


def adaptive_attempts(p: Params, cfg: ModelConfig, sched: Schedule, rates=None) -> int:
    """Static number of attempted steps for an adaptive schedule: the explicit stability
    limit of the 3(2) pair (|λ ΔN| ≲ 2.5, λ bounded by `_regime_rates`) over every piece,
    a few steps per piece for accuracy and regime starts, rounded up to a bucket so that
    similar runs share a compilation. Unused attempts cost nothing (no vmap). `rates`:
    `_regime_rates` where the caller has them (one call for every experiment). Raises
    `TrialFailed` where the estimate is not finite (a rate bound NaN or inf at these
    parameters): no attempt count can run them."""
    rates = np.asarray(_regime_rates_jit(p, rate_config(cfg)) if rates is None
                       else rates).reshape(-1)
    cyc = np.asarray(sched.cycles)
    reg = np.asarray(sched.regime)
    live = cyc > 0
    # at the stability limit a third or more of the attempts are rejected and the accepted
    # steps average below the limit (measured on the boom: ~800 accepted at K_d 3e-13 where
    # the limit alone gives ~400); `simulate` and `evaluate` double it if short
    stiff = 3 * float(np.sum(cyc[live] * rates[np.minimum(reg[live], len(rates) - 1)]) / 2.5)
    # accuracy-limited steps grow like tol^(-1/3) (3rd order): ~25 for the rig at 0.002 µm
    tol_um = DEFAULT_WEAR_TOLERANCE_UM if sched.tolerance_um is None else sched.tolerance_um
    acc = 40 * max(1.0, (DEFAULT_WEAR_TOLERANCE_UM / tol_um) ** (1 / 3))
    if not math.isfinite(stiff + acc):
        raise TrialFailed(f"the work estimate is not finite: the wear-rate bound K_d k "
                          f"S_cycle is {np.max(rates):g} per cycle")
    return bucket(int(math.ceil(stiff + acc)) + 4 * int(np.sum(live)))


_regime_rates_jit = jit(_regime_rates, once=True)
