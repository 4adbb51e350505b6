"""The wear loop: Archard increments on a frozen profile, amplified M cycles per update (§4).

One update: contact for all steps of a cycle at once (vectorised), Δh_j = Σ_i K_d p_ij dS_i,
h ← h + M Δh. Updates run under `lax.scan`; the scan is split in two levels with
`jax.checkpoint` on each inner block, so reverse-mode memory grows like √updates, not like
updates × steps × nodes (100 000 revolutions at M = 1 fit in memory).
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
from jax import lax

from ._config import ModelConfig
from ._contact import interp_periodic, solve_contact, stiffness_per_area
from ._custom_types import Array, Float, NodeArray, Scalar
from ._errors import InputError, WornThroughError
from ._load import LoadHistory, load_history
from ._params import Params
from ._schedule import Schedule, bucket, crank_segments, duty_segments, make_schedule
from .effects import RateContext, get_effect


class WearResult(eqx.Module):
    """Outcome of a wear simulation (SI units).

    - `depth`: final wear depth h_j [m], (nodes,). `snapshots`: (n_snapshots, nodes) [m].
    - `sliding_distance`: accumulated S [m].
    - `worn_volume`: Σ h_j A_j [m³]; `archard_volume`: K_d Σ_updates M Σ_i (Σ_j p_ij A_j) dS_i
      [m³] (equal for the base model: the volume identity of §4).
    - `max_residual`: largest relative contact force residual met. `max_iterations`: Newton.
    - `worn_through_cycle`: cycle count at which some h_j first reached L (-1: never).
    - `history`: the load history used.
    """

    depth: NodeArray
    snapshots: Float[Array, "snapshots nodes"]
    sliding_distance: Scalar
    worn_volume: Scalar
    archard_volume: Scalar
    max_residual: Scalar
    max_iterations: Array
    worn_through_cycle: Scalar
    history: LoadHistory


def node_area(p: Params, nodes: int) -> Scalar:
    """A_j = R_b (2π/N) B [m²]."""
    return p.bore_radius * (2 * jnp.pi / nodes) * p.width


def cycle_increment(p: Params, cfg: ModelConfig, hist: LoadHistory, regime, h, sliding,
                    start=None):
    """Wear of one cycle on the frozen profile `h`, with its contact solution.

    Returns (Δh per cycle [m] (nodes,), Σ_i (Σ_j p_ij A_j) dS_i [N·m], contact solution).
    """
    effects = [get_effect(n) for n in cfg.effects]
    load, angle = hist.load[regime], hist.angle[regime]
    slide, dt, sense = hist.slide[regime], hist.dt[regime], hist.sense[regime]
    area = node_area(p, cfg.nodes)
    k = stiffness_per_area(h, p, cfg.double_layer)
    friction = None
    for eff in effects:
        mu = eff.friction(p, sense)
        if mu is not None:
            friction = mu if friction is None else friction + mu
    sol = solve_contact(load, angle, h, p.clearance, k, area, contact=cfg.contact,
                        friction=friction, iterations=cfg.newton_iterations, start=start)
    rate = p.wear_coefficient * sol.pressure * slide[:, None]  # eq 21, per step
    if effects:
        ctx = RateContext(sol.pressure, slide, dt, sliding)
        for eff in effects:
            rate = eff.local_rate(p, rate, ctx)
    dh = jnp.sum(rate, axis=0)
    work = jnp.sum(jnp.sum(sol.pressure, axis=1) * area * slide)
    return dh, work, sol


def wear_loop(p: Params, cfg: ModelConfig, schedule: Schedule, h0: NodeArray | None = None
              ) -> WearResult:
    """Run the wear loop over `schedule` (pure, jit-able, differentiable in `p` and `h0`)."""
    effects = [get_effect(n) for n in cfg.effects]
    hist = load_history(p, cfg)
    n = cfg.nodes
    area = node_area(p, n)
    per_cycle_slide = jnp.sum(hist.slide, axis=1)  # (regimes,)
    h0 = jnp.zeros(n) if h0 is None else h0

    # Warm starts: each regime's offsets from its previous update (the profile moves little
    # per update), first from a cold solve on the initial profile.
    n_reg = hist.load.shape[0]
    cold = [cycle_increment(p, cfg, hist, r, h0, jnp.zeros(()))[2] for r in range(n_reg)]
    starts0 = jnp.stack([lax.stop_gradient(s.offset) for s in cold])

    def body(carry, x):
        # Padding updates (M = 0, from shape bucketing) skip all work.
        return lax.cond(x[0] > 0, live, lambda c, _: c, carry, x), None

    def live(carry, x):
        h, S, snaps, vol, res, its, worn, starts, h_seen = carry
        M, regime, snap, end = x
        warm = None
        if cfg.contact == "unsymmetric":
            # Predictor: where the bore wore by Δh since this regime's last solve, the pin
            # moves out by about Δh along the load to keep its penetration.
            ang = hist.angle[regime]
            grown = lax.stop_gradient(interp_periodic(h - h_seen[regime], ang))
            warm = starts[regime] + grown[:, None] * jnp.stack([jnp.cos(ang), jnp.sin(ang)], 1)
        dh, work, sol = cycle_increment(p, cfg, hist, regime, h, S, warm)
        starts = starts.at[regime].set(lax.stop_gradient(sol.offset))
        h_seen = h_seen.at[regime].set(lax.stop_gradient(h))
        s_cyc = per_cycle_slide[regime]
        factor = jnp.ones(())
        for eff in effects:
            factor = factor * eff.block_factor(p, S, s_cyc, M)
        h_new = h + M * factor * dh  # eq 23
        S_new = S + M * s_cyc
        if schedule.n_snapshots:
            snaps = snaps.at[snap].set(h_new, mode="drop")
        vol = vol + p.wear_coefficient * M * work
        # Once the layer is worn through the model is meaningless, and so are residuals.
        res = jnp.maximum(res, jnp.where(worn < 0, jnp.max(sol.residual), 0.0))
        its = jnp.maximum(its, sol.iterations)
        hit = (M > 0) & jnp.any(h_new >= p.layer_thickness) & (worn < 0)
        worn = jnp.where(hit, end, worn)
        return (h_new, S_new, snaps, vol, res, its, worn, starts, h_seen)

    U = schedule.updates
    inner = max(1, int(math.ceil(math.sqrt(U))))
    outer = int(math.ceil(U / inner))
    pad = outer * inner - U

    def padded(a, fill):
        return jnp.concatenate([a, jnp.full((pad,), fill, a.dtype)]).reshape(outer, inner)

    xs = (padded(schedule.cycles, 0.0), padded(schedule.regime, 0),
          padded(schedule.snapshot, schedule.n_snapshots), padded(schedule.cycle_end, 0.0))

    @jax.checkpoint
    def block(carry, xs_block):
        return lax.scan(jax.checkpoint(body), carry, xs_block)

    carry0 = (h0, jnp.zeros(()), jnp.zeros((schedule.n_snapshots, n)), jnp.zeros(()),
              jnp.zeros(()), jnp.zeros((), jnp.int32), jnp.asarray(-1.0), starts0,
              jnp.broadcast_to(lax.stop_gradient(h0), (n_reg, n)))
    (h, S, snaps, vol, res, its, worn, *_), _ = lax.scan(block, carry0, xs)
    if schedule.order and list(schedule.order) != list(range(schedule.n_snapshots)):
        snaps = snaps[jnp.asarray(schedule.order)]
    return WearResult(depth=h, snapshots=snaps, sliding_distance=S,
                      worn_volume=jnp.sum(h) * area, archard_volume=vol, max_residual=res,
                      max_iterations=its, worn_through_cycle=worn, history=hist)


_wear_loop_jit = eqx.filter_jit(wear_loop)


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


@eqx.filter_jit
def _update_rate(p: Params, cfg: ModelConfig):
    """K_d k S_cycle (per cycle) of the unworn joint, for `stable_amplification`."""
    k = jnp.max(stiffness_per_area(jnp.zeros(1), p, cfg.double_layer))
    return p.wear_coefficient * k * jnp.max(jnp.sum(load_history(p, cfg).slide, axis=1))


def build_schedule(p: Params, cfg: ModelConfig, *, revolutions=None, hours=None,
                   snapshots=(), M: float = 100, pad: bool = True,
                   pad_to: int | None = None) -> Schedule:
    """Schedule for a crank-slider run of `revolutions` or an oscillating run of `hours`;
    `snapshots` in revolutions (crank) or hours (oscillating). Padded (with no-op updates)
    to `pad_to` updates, or with `pad` to a bucket size, so that runs share compilations."""
    if cfg.driver == "oscillating":
        if hours is None or not hours > 0:
            raise InputError(f"an oscillating joint needs hours > 0, got {hours}")
        segs, per_h = duty_segments(cfg.duty_cycle, float(hours), float(p.swing_period))
        snaps = [s * per_h for s in snapshots]
    else:
        if revolutions is None or not revolutions > 0:
            raise InputError(f"revolutions must be > 0, got {revolutions}")
        segs = crank_segments(revolutions)
        snaps = list(snapshots)
    sched = make_schedule(segs, snaps, M)
    target = max(pad_to or 0, bucket(sched.updates) if pad else 0)
    if target > sched.updates:
        sched = make_schedule(segs, snaps, M, pad_to=target)
    return sched


def simulate(p: Params, cfg: ModelConfig = ModelConfig(), *, revolutions=None, hours=None,
             snapshots=(), M: float = 100, h0=None, check: bool = True,
             pad_to: int | None = None) -> WearResult:
    """Predict the wear of one joint (jit-compiled; recompiles only when shapes or `cfg` change).

    **Arguments:**
    - `p`: parameters (SI). `cfg`: static model choices.
    - `revolutions` (crank-slider) or `hours` (oscillating joint); `snapshots` at revolution
      counts or hours; `M`: cycles per wear update (amplification, eq 23).
    - `check`: raise `WornThroughError` if the layer wears through and `RuntimeError` if a
      contact solve did not converge (relative force residual ≥ 1e-9).

    **Returns:** a `WearResult`.
    """
    sched = build_schedule(p, cfg, revolutions=revolutions, hours=hours, snapshots=snapshots, M=M,
                           pad_to=pad_to)
    res = _wear_loop_jit(p, cfg, sched, h0)
    if check:
        check_result(res, cfg)
    return res


def check_result(res: WearResult, cfg: ModelConfig, what: str = "simulation"):
    worn = float(jnp.max(res.worn_through_cycle))
    unit = "swing cycle" if cfg.driver == "oscillating" else "revolution"
    residual = float(jnp.max(res.max_residual))
    if not residual < 1e-9:
        raise RuntimeError(f"{what}: contact solve did not converge (relative force residual "
                           f"{residual:.2e} ≥ 1e-9)")
    if worn >= 0:
        raise WornThroughError(f"{what}: the bushing layer is worn through at {unit} "
                               f"{worn:.0f} (h ≥ layer thickness)")
