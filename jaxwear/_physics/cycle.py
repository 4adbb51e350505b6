"""One cycle of the wear loop: the Archard rates and increment on a frozen profile (all steps
of a cycle at once), and the result type of a wear history."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
from jax import lax

from jaxwear._core import pytree
from jaxwear._core.periodic import interp_periodic
from jaxwear._core.types import Array, Float, NodeArray, Scalar
from jaxwear._physics.config import ModelConfig
from jaxwear._physics.contact import solve_contact, stiffness_per_area
from jaxwear._physics.effects import RateContext, get_effect
from jaxwear._physics.effects.shape import precompute, shape_terms, swept_kernel
from jaxwear._physics.load import LoadHistory, load_history
from jaxwear._physics.params import Params


class WearResult(pytree.Struct):
    """Outcome of a wear simulation (SI units).

    - `depth`: final wear depth h_j [m], (nodes,). `snapshots`: (n_snapshots, nodes) [m].
    - `sliding_distance`: accumulated S [m].
    - `worn_volume`: Σ h_j A_j [m³]; `archard_volume`: K_d Σ_updates M Σ_i (Σ_j p_ij A_j) dS_i
      [m³] (equal for the base model: the volume identity of §4).
    - `max_residual`: largest relative contact force residual met. `max_iterations`: Newton.
    - `worn_through_cycle`: cycle count at which some h_j first reached L (-1: never).
    - `history`: the load history used.
    - `error_estimate`: estimated integration error of `depth` [m] (max over nodes of the
      signed sum of local error estimates; inf if the adaptive loop ran out of attempts).
      Adaptive: the embedded pair's; paper (eq 23): Euler's (M/2) Δrate between updates.
    - `steps`: accepted steps (updates); `rejected_steps`: steps the controller redid.
    - `memory`: the effects' hidden per-node states at the end (states, nodes) [-]
      (`Effect.memory_states`; None where no effect has any).
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
    error_estimate: Scalar
    steps: Array
    rejected_steps: Array
    memory: object = None


def node_area(p: Params, nodes: int) -> Scalar:
    """A_j = R_b (2π/N) B [m²]."""
    return p.bore_radius * (2 * jnp.pi / nodes) * p.width


def run_history(p: Params, cfg: ModelConfig) -> LoadHistory:
    """The load history of a run, with what the shape correction needs precomputed (its
    constant parts are computed once, not at every stage of every step)."""
    hist = load_history(p, cfg)
    if cfg.shape is not None:
        hist = dataclasses.replace(hist, shape_pre=precompute(cfg.shape, hist, cfg.nodes))
    if any(getattr(get_effect(n), "uses_swept_kernel", False) for n in cfg.effects):
        hist = dataclasses.replace(hist, swept=jax.vmap(
            lambda a: swept_kernel(a, cfg.nodes))(hist.angle))
    return hist


def memory_size(cfg: ModelConfig) -> int:
    """Hidden per-node states of the configuration's effects (`Effect.memory_states`)."""
    return sum(get_effect(n).memory_states for n in cfg.effects)


def archard_rate(p: Params, pressure, slide):
    """K_d p_ij dS_i (eq 21): each step's wear [m] (steps, nodes) from the pressure [Pa]
    (steps, nodes) and the steps' sliding [m] (steps,).

    K_d is folded into the steps' sliding first. Why: reverse mode's cotangent of K_d is
    then a sum over the steps of a row sum, not one sum over steps x nodes, which XLA:CPU
    runs as a blocked reduce-window at ~1.1 ms a call at 360 x 360 (a row sum ~0.1 ms;
    docs/performance.md, "K_d enters through the steps' sliding")."""
    return pressure * (p.wear_coefficient * slide)[:, None]


def cycle_rates(p: Params, cfg: ModelConfig, hist: LoadHistory, regime, h, sliding,
                start=None, memory=None):
    """Wear of each step of one cycle on the frozen profile `h` [m] (steps, nodes), with the
    contact solution: K_d p_ij dS_i (eq 21), then every effect's hook, then the shape
    correction (`effects.shape`) where the configuration carries one. `memory` (states,
    nodes): the effects' hidden states (`memory_size`; None: 0, a new surface)."""
    rate, sol, _ = _cycle(p, cfg, hist, regime, h, sliding, start, memory)
    return rate, sol


def _cycle(p: Params, cfg: ModelConfig, hist: LoadHistory, regime, h, sliding, start,
           memory):
    """(`cycle_rates`' rate and contact, ds/dN (states, nodes) of the hidden states or
    None where no effect has any)."""
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
    rate = archard_rate(p, sol.pressure, slide)  # eq 21, per step
    ds = None
    if effects:
        m_total = memory_size(cfg)
        if m_total and memory is None:
            memory = jnp.zeros((m_total, cfg.nodes))
        parts, off = [], 0
        for eff in effects:
            m = eff.memory_states
            ctx = RateContext(sol.pressure, slide, dt, sliding, angle, load, h,
                              None if hist.swept is None else hist.swept[regime],
                              memory[off:off + m] if m else None)
            if m:
                parts.append(eff.memory_rate(p, ctx))
                off += m
            rate = eff.local_rate(p, rate, ctx)
        ds = jnp.concatenate(parts) if parts else None
    if cfg.shape is not None:
        g, deposit = shape_terms(cfg.shape, p, sol.pressure, slide, dt, sliding, angle, load,
                                 hist.shape_pre, regime, h)
        rate = rate * jnp.exp(g)
        if deposit is not None:
            rate = rate + deposit
    return rate, sol, ds


def cycle_increment(p: Params, cfg: ModelConfig, hist: LoadHistory, regime, h, sliding,
                    start=None):
    """Wear of one cycle on the frozen profile `h`, with its contact solution.

    Returns (Δh per cycle [m] (nodes,), Σ_i (Σ_j p_ij A_j) dS_i [N·m], contact solution).
    """
    dh, _, work, sol = cycle_step(p, cfg, hist, regime, h, sliding, start)
    return dh, work, sol


def cycle_step(p: Params, cfg: ModelConfig, hist: LoadHistory, regime, h, sliding,
               start=None, memory=None):
    """`cycle_increment` with the hidden states: (Δh per cycle [m] (nodes,), ds/dN per
    cycle (states, nodes) or None, work [N·m], contact solution); `memory` (states, nodes)
    the states the cycle starts from (`memory_size`; None: 0)."""
    rate, sol, ds = _cycle(p, cfg, hist, regime, h, sliding, start, memory)
    slide = hist.slide[regime]
    area = node_area(p, cfg.nodes)
    dh, slid = _step_sums(rate, slide[:, None] * sol.pressure)
    return dh, ds, area * jnp.sum(slid), sol


@jax.custom_jvp
def _step_sums(a, b):
    """Σ_i a_ij and Σ_i b_ij (nodes,) of two (steps, nodes) arrays: one variadic reduction.

    XLA:CPU then computes the pressure field, the rate and both sums in one pass, writing
    no (steps, nodes) array (measured, 360 x 360, legacy emitters: 38 µs against 81 µs for
    the pressure and rate written out and summed by two matrix-vector products, 103 µs for
    two plain sums; a cycle evaluation of the boom's is ~0.4 ms). The derivative is two
    plain sums over the steps (`_step_sums_jvp`): reverse mode cannot transpose a variadic
    reduction."""
    return tuple(lax.reduce([a, b], [jnp.zeros((), a.dtype)] * 2,
                            lambda x, y: [x[0] + y[0], x[1] + y[1]], (0,)))


@_step_sums.defjvp
def _step_sums_jvp(primals, tangents):
    # Plain sums, not matrix-vector products with ones: under the vmap over a Jacobian's
    # tangents a product `ones @ ta` became a dot over (steps, tangents x nodes), for which
    # XLA wrote every tangent's (steps, nodes) field out transposed first, recomputing in
    # that copy the contact's primal terms per tangent (two copy fusions: ~half of the
    # leaf-op time of the fatigue diagnosis's extended-model Jacobian, 48 x 72, 8 tangents).
    # Summed, the field is reduced where it is made: that Jacobian 0.37 -> 0.21 s, the
    # shape design's 5.4 -> 3.6 s (docs/performance.md, "A Jacobian's sums over the steps").
    ta, tb = tangents
    return _step_sums(*primals), (jnp.sum(ta, 0), jnp.sum(tb, 0))


def _cold_starts(hist: LoadHistory):
    """Warm-start offsets (regimes, steps, 2) that ask the contact solve for a cold start
    (NaN: `_contact._unsymmetric`), for each regime's first solve."""
    return jnp.full((*hist.load.shape, 2), jnp.nan)


def _warm_start(cfg: ModelConfig, hist: LoadHistory, starts, h_seen, regime, h):
    """Pin offsets (steps, 2) [m] to start the contact solve of `regime` from, or None.

    Predictor: where the bore wore by Δh since this regime's last solve (`starts` at
    profile `h_seen`), the pin moves out by about Δh along the load to keep its
    penetration. Held out of differentiation: only the solve's answer carries gradients."""
    if cfg.contact != "unsymmetric":
        return None
    ang = hist.angle[regime]
    grown = lax.stop_gradient(interp_periodic(h - h_seen[regime], ang))
    return starts[regime] + grown[:, None] * jnp.stack([jnp.cos(ang), jnp.sin(ang)], 1)
