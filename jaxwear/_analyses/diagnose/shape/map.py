"""When in the cycle the missing wear is made and where on the bore it lands (`shape.analysis`).

For the refitted correction, on the experiment that wears most, at its last measured
profile: the extra wear of one cycle per step i and node j, Δ_ij = (corrected − model's
own) wear, in µm per 10⁴ cycles. Its marginals say when (over the cycle phase: the extra
volume made in each step) and where (over the bore angle: the extra depth), each with a
band from the refit's covariance (linearised: the Jacobian of the marginals with respect to
the columns the covariance holds, by central differences of one forward program,
`marginal_jacobian`). The load's events are marked: its reversals (where its direction
turns fastest) and its peak.

Why differences and not `jax.jacfwd`: the map's Jacobian program was the costliest
compilation of a shape refit's map, for a figure and a band. Measured on the generator's
fatigue study (48 x 72, 27 columns, 2026-11-29): `jax.jacfwd` at LLVM's O0 traced,
lowered and compiled in 3.3 + 1.0 + 7.2 s of CPU, in the background while the refit ran on
both cores; the forward program 0.75 + 1.1 + 2.5 s, and its 2 x 26 runs 0.1-0.4 s. The
bands agree with `jax.jacfwd`'s to within `FD_STEP`'s truncation (tests/test_shape.py).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import jax
import jax.numpy as jnp
import numpy as np
from scipy.stats import norm

from jaxwear._core.jit import jit
from jaxwear._physics.cycle import cycle_rates, run_history
from jaxwear._physics.effects.shape import state_variables

PER_CYCLES = 1e4  # the map's unit: µm per 10⁴ cycles
# the central differences' step in u (a log-multiplier, a log-clearance, a correction's
# coefficient: all O(1)), relative above 1: the truncation error ~FD_STEP² of the
# marginals' curvature, the contact solve's own tolerance (1e-10 relative) ~1e-10/FD_STEP
FD_STEP = 1e-5
EVENT_WINDOW_DEG = 20.0  # "at a reversal": within this many degrees of the cycle


@dataclass(frozen=True)
class WhenWhere:
    """The map and its marginals (arrays over steps or nodes) with bands at `level`.

    `when_um_rad` (steps,): extra volume made in each step per 10⁴ cycles, as µm·rad of
    bore (volume / (R_b B)); `where_um` (nodes,): extra depth per 10⁴ cycles; `map_um`
    (steps, nodes). `reversals_deg`: phases where the load direction turns fastest (local
    maxima of its turn rate above 3x its median); `peak_load_deg`: where |W| peaks;
    `share_at_reversals`: the share of the extra volume made within `EVENT_WINDOW_DEG` of
    a reversal; `made`, `lands`: the arcs (from, to [deg], share) over the cycle and over
    the bore where the extra wear is above a tenth of its peak, largest first, as many as
    hold 80 % of it (at most three)."""

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
    made: tuple = ()
    lands: tuple = ()
    total_um_rad: float = math.nan

    def to_json(self) -> dict:
        f = lambda x: None if x is None or not math.isfinite(float(x)) else float(x)  # noqa: E731
        return {"experiment": self.experiment, "unit": "per 1e4 cycles",
                "made_at_phase_deg": [{"from": a, "to": b, "share": w}
                                      for a, b, w in self.made],
                "lands_at_bore_deg": [{"from": a, "to": b, "share": w}
                                      for a, b, w in self.lands],
                "load_reversals_deg": [f(x) for x in self.reversals_deg],
                "peak_load_deg": f(self.peak_load_deg),
                "share_at_reversals": f(self.share_at_reversals),
                "extra_volume_um_rad": f(self.total_um_rad),
                "peak_extra_depth_um": f(np.max(self.where_um))}


def when_where(cm, u, cov, experiment: str, deepest: int, level: float, snaps=None
               ) -> WhenWhere | None:
    """The map of the refitted correction `cm` at `u` (its covariance `cov` (P, P)) on
    experiment `deepest`, at its last measured profile; `snaps` (E, S, N) [µm]: the model's
    snapshots at u where the caller has them (the refit's last evaluation: no forward
    compilation of its own)."""
    u = np.asarray(u, np.float64)
    if snaps is None:
        snaps = cm.snapshots(u)
    if not np.all(np.isfinite(snaps)):
        return None
    h = jnp.asarray(snaps[deepest, -1] * 1e-6)
    ext = cm.ext.with_schedule(None)
    (when, where), (d, load_n, turn) = _jit_parts(ext, jnp.asarray(u), deepest, h)
    # the columns the covariance holds (the others are held: zero variance)
    cols = np.flatnonzero(np.diag(np.asarray(cov)) > 0)
    Jw, Jr = marginal_jacobian(ext, u, deepest, h, cols, at=(when, where))
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
                     arcs(phase, np.clip(when, 0, None)), arcs(bore, np.clip(where, 0, None)),
                     total)


def compile_maps(cm, deepest: int) -> None:
    """Compile (and run once) the map's program for the model `cm` on experiment
    `deepest`, so that `when_where` finds it compiled: `shape.analysis` calls this in the
    background while the refit compiles and runs. A failure here is left to `when_where`
    to meet and report."""
    try:
        ext = cm.ext.with_schedule(None)  # the schedule's attempt count: no new program
        jax.block_until_ready(_jit_parts(ext, jnp.zeros(len(cm.names)), deepest,
                                         jnp.zeros(ext.cfg.nodes)))
    except Exception:  # noqa: BLE001 (the real call reports it)
        pass


def map_parts(ext, u, deepest, h):
    """One cycle of experiment `deepest` at u (P,) on the worn profile h (nodes,) [m]:
    ((when (steps,) [µm·rad per 10⁴ cycles], where (nodes,) [µm per 10⁴ cycles]),
    (the map (steps, nodes) [µm per 10⁴ cycles], |W| (steps,) [N], the load's turn rate
    (steps,) [deg/s])): the correction's extra wear, (corrected − model's own) rates."""
    cfg = ext.cfg
    base_cfg = cfg.replace(shape=None)
    p = jax.tree.map(lambda x: x[deepest], ext.batched_params(u))
    hist = run_history(p, cfg)
    S = jnp.zeros(())
    corrected, sol = cycle_rates(p, cfg, hist, 0, h, S)
    own, _ = cycle_rates(p, base_cfg, hist, 0, h, S)
    d = (corrected - own) * 1e6 * PER_CYCLES
    n = d.shape[1]
    z = state_variables(sol.pressure, hist.slide[0], hist.dt[0], S, hist.angle[0],
                        hist.load[0], h)
    marg = (jnp.sum(d, axis=1) * (2 * jnp.pi / n), jnp.sum(d, axis=0))
    return marg, (d, hist.load[0], z["load_turn_rate_deg_per_s"][:, 0])


# O0 (`once`): the map runs 2 x (columns) + 2 times per refitted model, milliseconds each
_jit_parts = jit(map_parts, once=True)


def marginal_jacobian(ext, u, deepest, h, cols, at=None) -> tuple[np.ndarray, np.ndarray]:
    """d when / d u (steps, P) and d where / d u (nodes, P) by central differences of
    `map_parts` in the columns `cols` (the others 0), step `FD_STEP` (relative above 1).
    `at`: the marginals (when, where) at u where the caller has them (no run for them)."""
    u = np.asarray(u, np.float64)
    w0, r0 = at if at is not None else _jit_parts(ext, jnp.asarray(u), deepest, h)[0]
    Jw = np.zeros((np.shape(w0)[0], len(u)))
    Jr = np.zeros((np.shape(r0)[0], len(u)))
    for k in cols:
        step = FD_STEP * max(1.0, abs(float(u[k])))
        out = []
        for sign in (1.0, -1.0):
            v = u.copy()
            v[k] += sign * step
            out.append(_jit_parts(ext, jnp.asarray(v), deepest, h)[0])
        (wp, rp), (wm, rm) = out
        Jw[:, k] = (np.asarray(wp) - np.asarray(wm)) / (2 * step)
        Jr[:, k] = (np.asarray(rp) - np.asarray(rm)) / (2 * step)
    return Jw, Jr


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


def arcs(x_deg, w, floor: float = 0.1, hold: float = 0.8, most: int = 3) -> tuple:
    """((from, to [deg], share), ...): the periodic runs of w above `floor` of its peak,
    largest share first, as many as hold `hold` of the total (at most `most`)."""
    w = np.asarray(w, float)
    total = float(np.sum(w))
    if not total > 0:
        return ()
    on = w > floor * float(np.max(w))
    n = len(w)
    if on.all():
        return ((float(x_deg[0]), float(x_deg[-1]), 1.0),)
    start = int(np.argmin(on))  # a point that is off: runs never wrap past it
    runs, cur = [], []
    for k in range(n):
        i = (start + k) % n
        if on[i]:
            cur.append(i)
        elif cur:
            runs.append(cur)
            cur = []
    if cur:
        runs.append(cur)
    out = sorted(((float(x_deg[r[0]]), float(x_deg[r[-1]]), float(np.sum(w[r])) / total)
                  for r in runs), key=lambda t: -t[2])
    kept, held = [], 0.0
    for a in out[:most]:
        kept.append(a)
        held += a[2]
        if held >= hold:
            break
    return tuple(kept)
