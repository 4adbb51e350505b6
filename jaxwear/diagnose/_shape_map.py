"""When in the cycle the missing wear is made and where on the bore it lands (`_shape`).

For the refitted correction, on the experiment that wears most, at its last measured
profile: the extra wear of one cycle per step i and node j, Δ_ij = (corrected − model's
own) wear, in µm per 10⁴ cycles. Its marginals say when (over the cycle phase: the extra
volume made in each step) and where (over the bore angle: the extra depth), each with a
band from the refit's covariance (linearised: the exact Jacobian of the marginals with
respect to u, `jax.jacfwd`). The load's events are marked: its reversals (where its
direction turns fastest) and its peak.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from scipy.stats import norm

from .._load import load_history
from .._wear import cycle_rates

PER_CYCLES = 1e4  # the map's unit: µm per 10⁴ cycles
EVENT_WINDOW_DEG = 20.0  # "at a reversal": within this many degrees of the cycle


@dataclass(frozen=True)
class WhenWhere:
    """The map and its marginals (arrays over steps or nodes) with bands at `level`.

    `when_um_rad` (steps,): extra volume made in each step per 10⁴ cycles, as µm·rad of
    bore (volume / (R_b B)); `where_um` (nodes,): extra depth per 10⁴ cycles; `map_um`
    (steps, nodes). `reversals_deg`: phases where the load direction turns fastest (local
    maxima of its turn rate above 3x its median); `peak_load_deg`: where |W| peaks;
    `share_at_reversals`: the share of the extra volume made within `EVENT_WINDOW_DEG` of
    a reversal; `made_deg`, `lands_deg`: the shortest arcs that hold 68 % of the extra
    volume over the cycle and over the bore."""

    experiment: str
    level: float
    phase_deg: np.ndarray = field(repr=False)
    when_um_rad: np.ndarray = field(repr=False)
    when_lower: np.ndarray = field(repr=False)
    when_upper: np.ndarray = field(repr=False)
    bore_deg: np.ndarray = field(repr=False)
    where_um: np.ndarray = field(repr=False)
    where_lower: np.ndarray = field(repr=False)
    where_upper: np.ndarray = field(repr=False)
    map_um: np.ndarray = field(repr=False)
    load_N: np.ndarray = field(repr=False)
    turn_rate_deg_per_s: np.ndarray = field(repr=False)
    reversals_deg: tuple = ()
    peak_load_deg: float = math.nan
    share_at_reversals: float = math.nan
    made_deg: tuple = (math.nan, math.nan)
    lands_deg: tuple = (math.nan, math.nan)
    total_um_rad: float = math.nan

    def to_json(self) -> dict:
        f = lambda x: None if x is None or not math.isfinite(float(x)) else float(x)  # noqa: E731
        return {"experiment": self.experiment, "unit": "per 1e4 cycles",
                "made_at_phase_deg": [f(x) for x in self.made_deg],
                "lands_at_bore_deg": [f(x) for x in self.lands_deg],
                "load_reversals_deg": [f(x) for x in self.reversals_deg],
                "peak_load_deg": f(self.peak_load_deg),
                "share_at_reversals": f(self.share_at_reversals),
                "extra_volume_um_rad": f(self.total_um_rad),
                "peak_extra_depth_um": f(np.max(self.where_um))}


def when_where(cm, u, cov, experiment: str, deepest: int, level: float
               ) -> WhenWhere | None:
    """The map of the refitted correction `cm` at `u` (its covariance `cov` (P, P)) on
    experiment `deepest`, at its last measured profile."""
    u = np.asarray(u, np.float64)
    snaps = cm.snapshots(u)
    if not np.all(np.isfinite(snaps)):
        return None
    h = jnp.asarray(snaps[deepest, -1] * 1e-6)
    (Jw, Jr), (when, where), (d, load_n, turn) = _jit_maps(cm.ext, jnp.asarray(u), deepest, h)
    Jw, Jr = np.asarray(Jw), np.asarray(Jr)
    when, where, d = np.asarray(when), np.asarray(where), np.asarray(d)
    load_n, turn = np.asarray(load_n), np.asarray(turn)
    q = norm.ppf(0.5 + level / 2)
    sd_w = np.sqrt(np.clip(np.einsum("ij,jk,ik->i", Jw, cov, Jw), 0, None))
    sd_r = np.sqrt(np.clip(np.einsum("ij,jk,ik->i", Jr, cov, Jr), 0, None))
    steps, nodes = d.shape
    phase = np.arange(steps) * 360.0 / steps
    bore = np.arange(nodes) * 360.0 / nodes
    rev = _reversals(phase, turn)
    total = float(np.sum(np.clip(when, 0, None)))
    near = np.zeros(steps, bool)
    for r in rev:
        near |= np.abs(np.mod(phase - r + 180.0, 360.0) - 180.0) <= EVENT_WINDOW_DEG
    share = float(np.sum(np.clip(when, 0, None)[near]) / total) if total > 0 else math.nan
    return WhenWhere(experiment, level, phase, when, when - q * sd_w,
                     when + q * sd_w, bore, where, where - q * sd_r, where + q * sd_r, d,
                     load_n, turn, tuple(rev), float(phase[int(np.argmax(load_n))]), share,
                     _arc(phase, np.clip(when, 0, None)), _arc(bore, np.clip(where, 0, None)),
                     total)


@eqx.filter_jit
def _jit_maps(ext, u, deepest, h):
    from ..effects.shape import state_variables

    cfg = ext.cfg
    base_cfg = cfg.replace(shape=None)

    def parts(v):
        p = jax.tree.map(lambda x: x[deepest], ext.batched_params(v))
        hist = load_history(p, cfg)
        S = jnp.zeros(())
        corrected, sol = cycle_rates(p, cfg, hist, 0, h, S)
        own, _ = cycle_rates(p, base_cfg, hist, 0, h, S)
        d = (corrected - own) * 1e6 * PER_CYCLES
        n = d.shape[1]
        z = state_variables(sol.pressure, hist.slide[0], hist.dt[0], S, hist.angle[0],
                            hist.load[0])
        marg = (jnp.sum(d, axis=1) * (2 * jnp.pi / n), jnp.sum(d, axis=0))
        return marg, (d, hist.load[0], z["load_turn_rate_deg_per_s"][:, 0])

    J, aux = jax.jacfwd(parts, has_aux=True)(u)
    marg, _ = parts(u)
    return J, marg, aux


def _reversals(phase, turn) -> list[float]:
    """Phases of the local maxima of the load's turn rate above 3x its median (a force
    reversal: the direction swings round while the load dips)."""
    med = float(np.median(turn))
    out = []
    n = len(turn)
    for i in range(n):
        if turn[i] > 3 * med and turn[i] >= turn[i - 1] and turn[i] >= turn[(i + 1) % n]:
            out.append(float(phase[i]))
    # one per swing (neighbouring maxima of one reversal merged)
    merged = []
    for r in out:
        if merged and abs(np.mod(r - merged[-1] + 180.0, 360.0) - 180.0) < EVENT_WINDOW_DEG:
            continue
        merged.append(r)
    return merged


def _arc(x_deg, w, share: float = 0.68) -> tuple[float, float]:
    """The shortest periodic arc [deg] holding `share` of the weights w over x_deg."""
    n = len(w)
    total = float(np.sum(w))
    if not total > 0:
        return (math.nan, math.nan)
    best = (n, 0)
    ww = np.concatenate([w, w])
    c = np.concatenate([[0.0], np.cumsum(ww)])
    for start in range(n):
        # the smallest length from `start` holding the share
        k = int(np.searchsorted(c, c[start] + share * total, side="left")) - start
        if 0 < k <= n and k < best[0]:
            best = (k, start)
    k, start = best
    step = 360.0 / n
    return (float(x_deg[start]), float(np.mod(x_deg[start] + (k - 1) * step, 360.0)))
