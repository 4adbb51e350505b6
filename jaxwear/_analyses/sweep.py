"""Batched parameter sweeps: one compiled, batched wear loop over a grid of named parameters.

`sweep(...)` runs the outer product of any study keys' values (speed, clearance, K_d, an
effect strength...), a fixed-size chunk of grid points at a time (`jax.vmap`, or `lax.map`
on CPU where that is faster), so memory stays bounded and every chunk reuses one
compilation. Results are numpy arrays shaped by the grid, with
the axes named by their study keys. The CLI verb `jaxwear sweep` sweeps speed and clearance
around a study's first experiment.
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from jaxwear._core.errors import InputError
from jaxwear._core.jit import jit
from jaxwear._core.numbers import MAX_POINTS, parse_range  # noqa: F401  (the CLI range parser)
from jaxwear._core.parallel import sharded_vmap
from jaxwear._physics.adaptive import DEFAULT_WEAR_TOLERANCE_UM
from jaxwear._physics.config import ModelConfig, timed
from jaxwear._physics.cycle import node_area
from jaxwear._physics.effects import effect_parameter_specs
from jaxwear._physics.params import MECHANISM_KEYS, PARAMETER_KEYS, Params, key_to_si
from jaxwear._physics.schedule import Schedule
from jaxwear._physics.wear import build_schedule, wear_loop
from jaxwear._study.resolution import for_forward, given
from jaxwear._study.study import Study

# Duration axes: the run's length (revolutions of a crank-slider, hours of a timed joint),
# swept by one run to the longest with a snapshot at each value, not by a run per value.
DURATION_KEYS = ("revolutions", "hours")


@dataclass(frozen=True)
class SweepResult:
    """Outcome of a sweep; every array has the grid's shape `tuple(len(v) for v in axes)`.

    - `axes`: axis name (study key) → values in the key's unit, in grid order.
    - `peak_depth_um`, `peak_angle_deg`: maximum of the final profile and where it is.
    - `worn_volume_mm3`: Σ h_j A_j of the final profile.
    - `worn_through_cycle`: revolution / swing cycle at which the layer wore through (-1:
      never). Where it is ≥ 0 the other numbers describe a bore worn past its layer and are
      not physical (`valid` is False there).
    - `max_contact_residual`: largest relative contact force residual met.
    - `depth_um`: final profiles, shape grid + (nodes,).
    - `error_estimate_um`: the wear integration's error estimate at each point (adaptive:
      the controlled global estimate; eq 23: Euler's), `steps` its accepted steps, and
      `tolerance_um` the adaptive tolerance (None for eq 23).
    - `resolution`: the nodes and steps per revolution used; for a study that leaves them
      open, chosen at the grid's corners (`_resolution.for_forward`) with its check.
    """

    axes: dict
    peak_depth_um: np.ndarray
    peak_angle_deg: np.ndarray
    worn_volume_mm3: np.ndarray
    worn_through_cycle: np.ndarray
    max_contact_residual: np.ndarray
    depth_um: np.ndarray
    error_estimate_um: np.ndarray | None = None
    steps: np.ndarray | None = None
    tolerance_um: float | None = None
    resolution: dict | None = None  # nodes and steps used, and their check (design.md §6)

    @property
    def shape(self) -> tuple:
        return tuple(len(v) for v in self.axes.values())

    @property
    def valid(self) -> np.ndarray:
        """True where the layer did not wear through, the contact converged and the wear
        integration reached the end (a finite error estimate)."""
        ok = (self.worn_through_cycle < 0) & (self.max_contact_residual < 1e-9)
        if self.error_estimate_um is not None:
            ok &= np.isfinite(self.error_estimate_um)
        return ok

    @property
    def status(self) -> np.ndarray:
        """Per point, why its numbers can or cannot be used: `"ok"`, `"worn_through"` (the
        layer wore through: `worn_through_cycle` says when), `"contact_failed"` (a contact
        solve did not converge: its numbers are not a solution) or `"integration_failed"`
        (the wear integration did not reach the end). A failure is named before a worn
        layer: a point whose contact failed may look worn through."""
        out = np.full(self.shape, "ok", dtype=object)
        out[self.worn_through_cycle >= 0] = "worn_through"
        if self.error_estimate_um is not None:
            out[~np.isfinite(self.error_estimate_um)] = "integration_failed"
        out[~(self.max_contact_residual < 1e-9)] = "contact_failed"
        return out

    def points(self) -> dict:
        """Axis values at every grid point, each flattened in C order (like `.ravel()`)."""
        mesh = np.meshgrid(*self.axes.values(), indexing="ij")
        return {k: m.ravel() for k, m in zip(self.axes, mesh)}


def _check_grid(p: Params, cfg: ModelConfig, grid: dict) -> dict:
    if not grid:
        raise InputError("sweep: the grid is empty; give at least one parameter and its values")
    specs = effect_parameter_specs()
    out = {}
    for key, vals in grid.items():
        if key in DURATION_KEYS:
            want = "hours" if timed(cfg) else "revolutions"
            if key != want:
                raise InputError(f"sweep: this joint runs for {want}, not {key}")
            v = np.atleast_1d(np.asarray(vals, dtype=np.float64))
            if v.ndim != 1 or v.size == 0 or not np.all(np.isfinite(v) & (v > 0)):
                raise InputError(f"sweep: {key} needs a non-empty 1-D list of values > 0")
            out[key] = v
            continue
        if key not in PARAMETER_KEYS and key not in specs:
            raise InputError(f"sweep: unknown parameter {key!r}; expected a study key such as "
                             f"speed_rpm or clearance_mm")
        if cfg.driver == "oscillating" and key == "swing_period_s":
            raise InputError("sweep: swing_period_s changes the number of cycles of an "
                             "oscillating joint's schedule; sweep it with separate runs")
        if cfg.driver == "load_history" and key in MECHANISM_KEYS:
            raise InputError(f"sweep: {key} does not enter a load_history joint (its load and "
                             f"motion come from the load file; sweep load_scale instead)")
        if cfg.driver == "oscillating" and key in ("speed_rpm", "crank_length_mm",
                                                   "coupler_length_mm"):
            raise InputError(f"sweep: {key} does not enter an oscillating joint")
        v = np.atleast_1d(np.asarray(vals, dtype=np.float64))
        if v.ndim != 1 or v.size == 0 or not np.all(np.isfinite(v)):
            raise InputError(f"sweep: {key} needs a non-empty 1-D list of finite values")
        if key in PARAMETER_KEYS and PARAMETER_KEYS[key].positive and np.any(v <= 0):
            raise InputError(f"sweep: {key} values must be > 0, got {v.min():g}")
        if key == "clearance_mm" and np.any(v * 1e-3 >= float(p.bore_radius)):
            raise InputError(f"sweep: clearance_mm must be < the bore radius "
                             f"{float(p.bore_radius) * 1e3:g} mm")
        out[key] = v
    return out


def _outputs(p, cfg, sched, keys, vals):
    q = p.with_values({k: vals[i] for i, k in enumerate(keys)})
    r = wear_loop(q, cfg, sched)
    return (r.depth, r.worn_volume, r.worn_through_cycle, r.max_residual,
            node_area(q, cfg.nodes), r.error_estimate, r.steps, r.snapshots)


@jit
def _run_chunk(p: Params, cfg: ModelConfig, sched: Schedule, keys: tuple, vals, method: str):
    """The wear loop at `vals` (chunk, keys) [SI], batched over the chunk."""
    one = lambda v: _outputs(p, cfg, sched, keys, v)
    if method == "vmap":
        return jax.vmap(one)(vals)
    return jax.lax.map(one, vals)


def _method(method: str) -> str:
    if method not in ("auto", "vmap", "map"):
        raise ValueError(f"sweep: method must be 'auto', 'vmap' or 'map', got {method!r}")
    if method == "auto":
        # On CPU the two are level since the contact solve branches per lane under vmap
        # (issue 50, 2026-11-29; 256 points at 120 x 120, eq 23: single calls 1.0x, vmap
        # 1.06-1.2x, lax.map 1.0-1.3x, within the shared host's noise; it was vmap 0.075x).
        # lax.map stays: the adaptive integrator's lanes take different step counts, and a
        # batch waits for its slowest lane. Accelerators fill their lanes.
        return "map" if jax.default_backend() == "cpu" else "vmap"
    return method


def _base(base, cfg, revolutions, hours, M, experiment):

    tol = DEFAULT_WEAR_TOLERANCE_UM

    if isinstance(base, Study):
        exp = base.experiments[experiment]
        p = base.params(exp)
        cfg = base.config if cfg is None else cfg
        if revolutions is None and hours is None:
            revolutions, hours = exp.revolutions, exp.hours
        if M is None and base.integrator == "paper":
            M = base.revolutions_per_update
        tol = base.wear_tolerance_um
    elif isinstance(base, Params):
        p = base
        if cfg is None:
            raise TypeError("sweep: pass a ModelConfig `cfg` with a Params base")
    else:
        raise TypeError(f"sweep: base must be a Study or Params, got {type(base).__name__}")
    return p, cfg, revolutions, hours, M, tol


def sweep(base, cfg: ModelConfig | None = None, grid: dict | None = None, *,
          revolutions=None, hours=None, M: float | None = None, chunk: int = 16,
          experiment: int = 0, method: str = "auto", progress: bool = False,
          choose_resolution: bool = True) -> SweepResult:
    """Wear over the outer product of parameter values, batched in compiled chunks.

    **Arguments:**
    - `base`: a `Study` (its experiment `experiment` gives parameters, config, revolutions
      or hours and M) or a `Params` (then `cfg` and `revolutions`/`hours` are needed).
    - `grid`: study key → 1-D values in the key's unit, e.g.
      `{"speed_rpm": np.linspace(100, 300, 21), "clearance_mm": [0.05, 0.1]}`; the
      result's axes follow this order. A duration axis (`"revolutions"` of a crank-slider,
      `"hours"` of a timed joint) runs once per point of the other axes, to the longest,
      with a snapshot at each value: its outputs are those snapshots (the integration's
      error estimate and steps are the whole run's).
    - `chunk`: grid points per batched call; memory grows with it, compilation happens once
      (the last chunk is padded by repeating a point).
    - `method`: `"vmap"` (one batched wear loop per chunk), `"map"` (`lax.map`: the chunk's
      points one after the other inside one compiled call) or `"auto"`: `"map"` on CPU
      (as fast as `"vmap"` there for eq 23, and free of the adaptive integrator's waits for
      a batch's slowest lane), `"vmap"` on GPU/TPU.
    - `progress`: report chunks on stderr.
    - `choose_resolution`: for a `Study` that leaves `nodes`/`steps_per_rev` open, pick
      them by the error at the grid's corners (default); False runs at the study's values.

    **Returns:** a `SweepResult`. Each point equals `simulate` at that point: same schedule
    (the bucketed one `simulate` builds; with a duration axis, the snapshots' cuts), same
    wear loop.
    """

    resolution = None
    if choose_resolution and isinstance(base, Study) and cfg is None:
        # a study that leaves nodes and steps open: the coarsest level whose peak depths at
        # the grid's corners (every axis at its two ends) agree with the next finer level's
        # within 0.1 % (design.md §6), then the whole grid at that level

        if base.auto_resolution and grid:
            corners = {k: sorted({float(np.min(v)), float(np.max(v))})
                       for k, v in grid.items()}

            def peaks(st):
                return sweep(st, grid=corners, revolutions=revolutions, hours=hours, M=M,
                             chunk=chunk, experiment=experiment, method=method,
                             choose_resolution=False).peak_depth_um.ravel()

            base, resolution = for_forward(base, peaks, log=(
                (lambda m: print(f"  sweep: {m}", file=sys.stderr, flush=True))
                if progress else None))
        else:
            resolution = given(base)
    p, cfg, revolutions, hours, M, tol = _base(base, cfg, revolutions, hours, M, experiment)
    method = _method(method)
    grid = _check_grid(p, cfg, dict(grid or {}))
    full_grid = dict(grid)
    dur_key = next((k for k in grid if k in DURATION_KEYS), None)
    durations = grid.pop(dur_key) if dur_key else None
    if durations is not None:  # one run to the longest, a snapshot at each duration
        if timed(cfg):
            hours = float(np.max(durations))
        else:
            revolutions = float(np.max(durations))
    sched = build_schedule(p, cfg, revolutions=revolutions, hours=hours, M=M, tolerance_um=tol,
                           snapshots=() if durations is None else list(durations))
    if sched.adaptive:
        # one attempt count for the whole grid: room for stiffer points (a point that runs
        # out reports an infinite error estimate); a traced bound, so that the reruns of
        # such points (below) compile nothing
        sched = sched.more_attempts().with_dynamic_attempts()
    keys = tuple(grid)
    shape = tuple(len(v) for v in grid.values())
    mesh = np.meshgrid(*grid.values(), indexing="ij")
    si = (np.stack([m.ravel() * key_to_si(k) for k, m in zip(keys, mesh)], axis=1) if keys
          else np.zeros((1, 0)))  # a duration axis alone: one run
    total = si.shape[0]
    chunk = max(1, min(int(chunk), total))
    t0 = time.perf_counter()

    def run(si, sched):
        parts = []
        for start in range(0, si.shape[0], chunk):
            block = si[start:start + chunk]
            n = block.shape[0]
            if n < chunk:  # pad: one compiled chunk size for the whole sweep
                block = np.concatenate([block, np.repeat(block[-1:], chunk - n, axis=0)])
            if jax.device_count() > 1:  # shard the chunk's points over all devices/processes
                out = sharded_vmap(_outputs, (jnp.asarray(block),),
                                   broadcast_args=(p, cfg, sched, keys), method=method)
            else:
                out = jax.device_get(_run_chunk(p, cfg, sched, keys, jnp.asarray(block),
                                                method))
            parts.append([np.asarray(o)[:n] for o in out])
            if progress:
                print(f"  sweep: {min(start + chunk, si.shape[0])}/{si.shape[0]} points "
                      f"({time.perf_counter() - t0:.1f} s)", file=sys.stderr, flush=True)
        return [np.concatenate(x) for x in zip(*parts)]

    cols = run(si, sched)
    # Points whose adaptive loop ran out of attempts (stiffer than the base point: error
    # inf, a truncated history) are rerun with twice the attempts, not returned truncated.
    for _ in range(3):
        short = ~np.isfinite(cols[5])
        if not (sched.adaptive and short.any()):
            break
        sched = sched.more_attempts()
        if progress:
            print(f"  sweep: {int(short.sum())} point(s) need more integration steps: rerun "
                  f"with {int(np.max(sched.attempt_limit))} attempts", file=sys.stderr, flush=True)
        again = run(si[short], sched)
        for c, a in zip(cols, again):
            c[short] = a
    depth, vol, worn, resid, area, err, steps, snaps = cols
    if durations is not None:
        depth, vol, worn, resid, err, steps, shape = _at_durations(
            sched, shape, list(full_grid).index(dur_key), snaps, area, worn, resid, err, steps)
        grid = full_grid
    depth_um = depth * 1e6
    nodes = cfg.nodes
    peak_idx = np.argmax(depth_um, axis=1)
    return SweepResult(
        axes=dict(grid),
        peak_depth_um=depth_um.max(axis=1).reshape(shape),
        peak_angle_deg=(peak_idx * 360.0 / nodes).reshape(shape),
        worn_volume_mm3=(vol * 1e9).reshape(shape),
        worn_through_cycle=worn.reshape(shape),
        max_contact_residual=resid.reshape(shape),
        depth_um=depth_um.reshape(shape + (nodes,)),
        error_estimate_um=(err * 1e6).reshape(shape), steps=steps.reshape(shape),
        tolerance_um=sched.tolerance_um, resolution=resolution)


def _at_durations(sched: Schedule, shape, axis, snaps, area, worn, *per_run):
    """The outputs at each duration of a duration axis (position `axis` in the requested
    grid) from one run's snapshots, the other axes of shape `shape`: profiles (points,
    durations, nodes) → (grid points, nodes), the worn volume of each snapshot, the
    wear-through only where it happened by the snapshot's count, and `per_run` outputs
    (residual, error estimate, steps: one per run) repeated along the durations. Returns
    (depth, volume, worn-through, *per_run, the grid's shape)."""
    ends, snap = np.asarray(sched.cycle_end), np.asarray(sched.snapshot)
    sorted_cycles = [float(ends[snap == j][0]) for j in range(sched.n_snapshots)]
    cycles = np.array([sorted_cycles[o] for o in (sched.order or range(sched.n_snapshots))])
    D = len(cycles)
    worn_d = np.where((worn[:, None] >= 0) & (worn[:, None] <= cycles * (1 + 1e-12)),
                      worn[:, None], -1.0)

    def place(a, trailing=()):  # (points, D, ...) → the grid in the requested axis order
        return np.moveaxis(a.reshape(tuple(shape) + (D,) + trailing), len(shape), axis)

    n = snaps.shape[-1]
    vol = snaps.sum(axis=2) * area[:, None]
    outs = [place(snaps, (n,)).reshape(-1, n), place(vol).ravel(), place(worn_d).ravel()]
    outs += [place(np.repeat(x[:, None], D, axis=1)).ravel() for x in per_run]
    return (*outs, place(vol).shape)


