"""Wear-update schedule: how many cycles each update of the wear loop amplifies (eq 23).

Built on the host from integers (so shapes are static): blocks of M cycles, a partial block
where a segment's cycle count is not divisible by M, and updates that end exactly at every
requested snapshot and at every change of duty-cycle regime.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np

from jaxwear._core import pytree
from jaxwear._core.errors import InputError
from jaxwear._core.host import to_device
from jaxwear._core.types import Array, Float, Int

DYNAMIC_ATTEMPTS = -1
"""`Schedule.attempts` of a schedule whose attempt count is traced (`attempt_limit`)."""


class Schedule(pytree.Struct):
    """Per-update arrays, shape (updates,).

    - `cycles`: the amplification M of each update (0 for padding).
    - `regime`: index into the load history's regimes.
    - `snapshot`: index of the snapshot taken after the update (n_snapshots = none).
    - `cycle_end`: cumulative cycle count after the update.

    Adaptive schedules (`attempts != 0`) hold one entry per *piece* (a stretch of one regime
    between cuts) instead of per update; `tolerance` [m] bounds the integration error and
    `attempts` is the static number of attempted Runge-Kutta steps the loop runs, or
    `DYNAMIC_ATTEMPTS` (`with_dynamic_attempts`): the loop is a while loop bounded by the
    traced `attempt_limit`, so that runs of any attempt count share one compilation (forward
    and forward-mode derivatives only: a while loop has no reverse-mode derivative).
    """

    cycles: Float[Array, " updates"]
    regime: Int[Array, " updates"]
    snapshot: Int[Array, " updates"]
    cycle_end: Float[Array, " updates"]
    n_snapshots: int = pytree.field(static=True)
    # requested snapshot i is the order[i]-th distinct count in increasing order
    order: tuple = pytree.field(static=True, default=())
    attempts: int = pytree.field(static=True, default=0)
    tolerance: Float[Array, ""] | None = None
    # Optional early stop (adaptive only): the loop ends at the first snapshot at or after
    # `stop_after` cycles where the maximum depth is ≥ `stop_depth` [m]; snapshots after it
    # are not computed and come back as +inf ("deeper than stop_depth"). For forecasts whose
    # tail only asks *when* a depth is reached (life), not how deep the wear goes past it.
    stop_depth: Float[Array, ""] | None = None
    stop_after: Float[Array, ""] | None = None
    attempt_limit: Int[Array, ""] | None = None

    @property
    def adaptive(self) -> bool:
        return self.attempts != 0

    @property
    def dynamic(self) -> bool:
        return self.attempts == DYNAMIC_ATTEMPTS

    @property
    def tolerance_um(self) -> float | None:
        """The adaptive loop's wear tolerance [µm], the largest of its experiments' (a
        batched schedule holds one each); None under the paper's fixed-step integrator or
        where none is set. Read on the host (not inside a traced function)."""
        if not self.adaptive or self.tolerance is None:
            return None
        return float(np.max(np.asarray(self.tolerance))) * 1e6

    def with_dynamic_attempts(self) -> Schedule:
        """The same run with its attempt count a traced bound instead of a static one (see
        the class docstring). A fit raises the count as K_d moves (the stiffness-limited step
        count grows with it); with a static count each raise recompiled the whole Jacobian
        (measured: twice in every boom fit)."""
        if not self.adaptive or self.dynamic:
            return self
        shape = self.cycles.shape[:-1]
        return dataclasses.replace(self, attempts=DYNAMIC_ATTEMPTS, attempt_limit=to_device(
            np.full(shape, self.attempts, np.int32)))

    @property
    def updates(self) -> int:
        return self.cycles.shape[0]

    def more_attempts(self, factor: int = 2) -> Schedule:
        """The same schedule with `factor` times the adaptive loop's static attempt count
        (one more compilation unless dynamic), for a run whose error estimate came back
        inf: the attempt count is an estimate, and a run that exhausts it returns a
        truncated history."""
        if self.dynamic:
            return dataclasses.replace(self, attempt_limit=factor * self.attempt_limit)
        return dataclasses.replace(self, attempts=factor * self.attempts)

    def stopping_at(self, depth_m, after_cycles) -> Schedule:
        """The same schedule with the early stop set (see the class docstring); arrays of
        the schedule's batch shape (or scalars)."""
        shape = self.cycles.shape[:-1]

        def full(x):
            if isinstance(x, jax.Array):
                return jnp.broadcast_to(jnp.asarray(x, jnp.float64), shape)
            # a host value: no program of its own (`_core.host`)
            return to_device(np.broadcast_to(np.asarray(x, np.float64), shape).copy())

        return dataclasses.replace(self, stop_depth=full(depth_m), stop_after=full(after_cycles))


def make_schedule(segments, snapshots, M: float, pad_to: int | None = None) -> Schedule:
    """Schedule of the paper's fixed-step loop (eq 23) for consecutive `segments`
    [(regime, cycles)], with snapshots at cumulative cycle counts `snapshots` [cycles:
    revolutions of a crank, swings of an oscillating joint] (each ≤ the total, in any
    order, repeats allowed: the wear loop returns them in the order asked), at most `M`
    cycles per update. `pad_to`: pad with no-op updates to this length (shared
    compilations).
    """
    if not (M > 0):
        raise InputError(f"revolutions_per_update must be > 0, got {M}")
    total = sum(c for _, c in segments)
    requested = [float(s) for s in snapshots]
    snaps = sorted(set(requested))
    order = tuple(snaps.index(s) for s in requested)
    for s in snaps:
        if s <= 0 or s > total * (1 + 1e-12):
            raise InputError(f"snapshot at {s:g} cycles is outside (0, {total:g}]")
    cuts = sorted(set(snaps))
    cyc, reg, snap, end = [], [], [], []
    pos = 0.0
    for regime, n in segments:
        seg_end = pos + n
        stops = [c for c in cuts if pos < c < seg_end - 1e-9] + [seg_end]
        for stop in stops:
            remaining = stop - pos
            nfull = math.floor(remaining / M + 1e-9)
            for _ in range(nfull):
                pos += M
                cyc.append(M), reg.append(regime), snap.append(-1), end.append(pos)
            rest = stop - pos
            if rest > 1e-9:
                pos = stop
                cyc.append(rest), reg.append(regime), snap.append(-1), end.append(pos)
            pos = stop
    end_arr = np.array(end)
    snap_idx = np.full(len(cyc), len(snaps), dtype=np.int32)
    for i, s in enumerate(snaps):
        j = int(np.argmin(np.abs(end_arr - s)))
        snap_idx[j] = i
    n = len(cyc)
    if pad_to is not None and pad_to > n:
        extra = pad_to - n
        cyc += [0.0] * extra
        reg += [0] * extra
        snap_idx = np.concatenate([snap_idx, np.full(extra, len(snaps), np.int32)])
        end_arr = np.concatenate([end_arr, np.full(extra, end_arr[-1] if n else 0.0)])
    # host arrays onto the device without a compilation per shape (`_core.host`)
    return Schedule(cycles=to_device(cyc, np.float64), regime=to_device(reg, np.int32),
                    snapshot=to_device(snap_idx), cycle_end=to_device(end_arr, np.float64),
                    n_snapshots=len(snaps), order=order)


def pad_schedule(s: Schedule, updates: int, n_snapshots: int | None = None,
                 attempts: int | None = None) -> Schedule:
    """`s` padded with no-op entries (0 cycles) to `updates` entries, with its "no snapshot"
    index moved to `n_snapshots` and (adaptive) `attempts` raised, so that schedules of
    several experiments stack into one batch. Snapshots come back in increasing order."""
    S = s.n_snapshots if n_snapshots is None else n_snapshots
    extra = updates - s.updates
    # on the host (a schedule is host data): eager jnp here compiled ~8 small programs
    cyc, reg = np.asarray(s.cycles, np.float64), np.asarray(s.regime, np.int32)
    snap0, end = np.asarray(s.snapshot, np.int32), np.asarray(s.cycle_end, np.float64)
    snap = np.where(snap0 >= s.n_snapshots, S, snap0).astype(np.int32)
    return Schedule(cycles=to_device(np.concatenate([cyc, np.zeros(extra)])),
                    regime=to_device(np.concatenate([reg, np.zeros(extra, np.int32)])),
                    snapshot=to_device(np.concatenate([snap, np.full(extra, S, np.int32)])),
                    cycle_end=to_device(np.concatenate([end, np.full(extra, end[-1])])),
                    n_snapshots=S,
                    attempts=s.attempts if attempts is None else attempts,
                    tolerance=s.tolerance)


def crank_segments(revolutions: float):
    return [(0, float(revolutions))]


def duty_segments(blocks, hours: float, period_s):
    """Repeat the duty-cycle blocks [(..., duration_h)] up to `hours` (a block of infinite
    duration runs for the rest); cycles per block = duration / the block's period
    (`period_s`: one for all blocks, or one per block). Returns the segments and the map
    hours → cumulative cycles (a function of a sequence of hours)."""
    periods = [float(period_s)] * len(blocks) if np.ndim(period_s) == 0 else [
        float(x) for x in period_s]
    per_h = [3600.0 / T for T in periods]
    segs = []
    t = 0.0
    edges_h, edges_c = [0.0], [0.0]
    while t < hours - 1e-12:
        for i, b in enumerate(blocks):
            d = min(b.duration_h, hours - t)
            if d <= 1e-12:
                break
            segs.append((i, d * per_h[i]))
            t += d
            edges_h.append(t)
            edges_c.append(edges_c[-1] + segs[-1][1])
    if len(set(periods)) == 1:
        return segs, lambda hs: [float(h) * per_h[0] for h in hs]
    # cycles per hour differ between blocks: piecewise linear in the hours
    return segs, lambda hs: [float(np.interp(float(h), edges_h, edges_c)) for h in hs]


def bucket(n: int) -> int:
    """Round an update count up so that similar runs share one compiled loop."""
    if n <= 8:
        return 8
    return int(2 ** math.ceil(math.log2(n))) if n < 64 else int(math.ceil(n / 64) * 64)
