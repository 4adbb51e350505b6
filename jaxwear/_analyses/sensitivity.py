"""Normalised sensitivities d ln y / d ln θ of peak depth and worn volume, by autodiff.

The derivatives go through the whole wear loop: the contact solves enter by the implicit
function theorem (see `_contact`), the wear loop's scan is differentiated as is. θ runs over
every physical parameter that enters the configured driver and joint (and the strengths of
the effects switched on), except those at 0, where a logarithmic derivative is undefined.

By default (`mode="auto"`) the run's length chooses: forward mode (`jax.jacfwd`, one
tangent per parameter) compiles faster than reverse mode (`jax.jacrev`, two outputs), and
a single call on a short run is mostly compilation; reverse mode runs faster once
compiled, and on long runs the first call too. `REV_WORK` is where the first call's times
cross (below). Measured on a quiet 2-core CPU (2026-11-30, 23:20 UTC, the adaptive
integrator with its stages checkpointed (`_physics.remat`), 15 parameters on the rig and
13 on the boom), first call / a second call:
- rig, 10 000 rev, 64 x 72: fwd 2.7 / 0.05 s, rev 5.0 / 0.01 s;
- rig, 10 000 rev, 360 x 360: fwd 4.3 / 1.75 s, rev 5.6 / 0.17 s;
- boom, 25 h, 360 x 360: fwd 32.0 / 30.4 s, rev 6.7 / 2.7 s (the process's peak memory:
  fwd 319 MB, rev 419 MB);
- `study_sensitivities` of `calibration/rig/study.toml` (5 experiments, one
  compilation; 20:56 UTC, another machine, before the stages were checkpointed): fwd
  6.5-7.3 s, rev 5.6-6.6 s (three runs each).
And where the two cross (23:30 UTC, the first call, with a test suite running beside):
the boom at 90 x 72 (work 2e7 node-steps, see `REV_WORK`) fwd 7.7 s, rev 9.1 s; at
180 x 144 (8e7) fwd 19.0 s, rev 11.3 s; the rig's 100 000 rev at 360 x 360 (1e8) fwd
42.4 s, rev 27.6 s. Pass `mode="rev"` for repeated calls, where reverse mode wins at any
length.

A normalised sensitivity S means: a 1 % increase of θ changes y by about S %.
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from jaxwear._core import pytree
from jaxwear._core.errors import InputError
from jaxwear._core.jit import jit
from jaxwear._inference.calibrate import unit_of
from jaxwear._physics.config import ModelConfig
from jaxwear._physics.effects import effect_parameter_specs, get_effect
from jaxwear._physics.params import PARAMETER_KEYS, Params, key_to_si
from jaxwear._physics.schedule import Schedule, bucket, pad_schedule
from jaxwear._physics.wear import build_schedule, schedule_numerics, wear_loop
from jaxwear._study.budget import EVALUATIONS_PER_ATTEMPT

REV_WORK = 5e7
"""Node-steps of a run's cycle evaluations (the static schedule's: 3 a Runge-Kutta attempt,
1 an update of eq 23; times nodes times steps a cycle) from which `mode="auto"` takes
reverse mode: between the rig's 10 000 rev at 360 x 360 (2.5e7, forward mode's first
call 4.3 s against 5.6 s) and the boom's 25 h at 180 x 144 (8e7, 19.0 s against 11.3 s;
the module docstring)."""

# What enters each part of the model (crank_mass does not: the crank turns at constant
# speed; the pin's elastic constants do not: the pin is rigid in the Winkler model).
CRANK_KEYS = ("crank_length_mm", "coupler_length_mm", "coupler_mass_kg", "slider_mass_kg",
              "spring_N_per_m", "spring_free_position_mm", "gravity_m_per_s2", "speed_rpm")
OSCILLATING_KEYS = ("load_N", "load_angle_deg", "swing_period_s")
LOAD_HISTORY_KEYS = ("load_scale",)  # the file's load and motion are data, not parameters
JOINT_KEYS = ("bore_diameter_mm", "clearance_mm", "width_mm", "layer_thickness_mm",
              "layer_E_GPa", "layer_poisson_ratio", "K_d_per_Pa")
BACKING_KEYS = ("backing_thickness_mm", "backing_E_GPa", "backing_poisson_ratio")


def relevant_keys(p: Params, cfg: ModelConfig) -> list[str]:
    """Study keys that enter the model for this driver and joint, at non-zero values."""
    keys = list({"oscillating": OSCILLATING_KEYS, "load_history": LOAD_HISTORY_KEYS}.get(
        cfg.driver, CRANK_KEYS))
    if cfg.driver == "crank_slider" and float(p.spring_rate) == 0:
        keys.remove("spring_free_position_mm")  # no spring, no free position
    keys += JOINT_KEYS
    if cfg.double_layer:
        keys += BACKING_KEYS
    for name in cfg.effects:
        keys += list(get_effect(name).parameters)
    return [k for k in dict.fromkeys(keys) if float(p.get(k)) != 0.0]


@dataclass(frozen=True)
class Sensitivities:
    """Normalised sensitivities at one operating point.

    - `keys`, `values` (in the keys' units), `units`.
    - `peak_depth_um`, `worn_volume_mm3`: the outputs at the operating point.
    - `peak`, `volume`: d ln(peak depth) / d ln θ and d ln(worn volume) / d ln θ, (keys,).
    - `worn_through_cycle` (-1: never) and `max_contact_residual` of the run.
    - `error_estimate_um`, `steps`: the wear integration's error estimate and step count.
    - `mode`: the autodiff mode that computed them, `"fwd"` or `"rev"`.
    """

    keys: list
    values: np.ndarray
    units: list
    peak_depth_um: float
    worn_volume_mm3: float
    peak: np.ndarray
    volume: np.ndarray
    worn_through_cycle: float
    max_contact_residual: float
    error_estimate_um: float = 0.0
    steps: int = 0
    mode: str = "fwd"

    def as_dict(self) -> dict:
        return {k: {"value": float(v), "unit": u, "peak_depth": float(a),
                    "worn_volume": float(b)}
                for k, v, u, a, b in zip(self.keys, self.values, self.units, self.peak,
                                         self.volume)}


def _log_outputs(s, p: Params, cfg: ModelConfig, sched: Schedule, keys: tuple):
    vals = {k: p.get(k) * jnp.exp(s[i]) for i, k in enumerate(keys)}
    q = p.with_values(vals)
    if cfg.driver == "oscillating" and "swing_period_s" in keys:
        # A run of fixed hours has hours·3600/T_s cycles: a longer period means fewer
        # cycles. The schedule's cycle counts are host integers, so the dependence enters
        # here, scaling every update's cycles (value unchanged at s = 0).
        T = q.swing_period
        sched = pytree.replace(sched, cycles=sched.cycles * (jax.lax.stop_gradient(T) / T))
    r = wear_loop(q, cfg, sched)
    peak, vol = jnp.max(r.depth), r.worn_volume
    return jnp.stack([jnp.log(peak), jnp.log(vol)]), (peak, vol, r.worn_through_cycle,
                                                      r.max_residual, r.error_estimate,
                                                      r.steps)


@jit
def _jac(p: Params, cfg: ModelConfig, sched: Schedule, keys: tuple, mode: str):
    f = lambda s: _log_outputs(s, p, cfg, sched, keys)
    s0 = jnp.zeros(len(keys))
    if mode == "fwd":
        return jax.jacfwd(f, has_aux=True)(s0)
    return jax.jacrev(f, has_aux=True)(s0)


def auto_mode(sched: Schedule, cfg: ModelConfig) -> str:
    """The autodiff mode `mode="auto"` takes for a run of `sched`: `"rev"` from `REV_WORK`
    node-steps of cycle evaluations on, else `"fwd"` (and for a schedule whose attempt
    count is traced: reverse mode cannot go through its while loop)."""
    if sched.dynamic:
        return "fwd"
    evals = EVALUATIONS_PER_ATTEMPT * sched.attempts if sched.adaptive else sched.updates
    return "rev" if evals * cfg.nodes * cfg.steps_per_rev >= REV_WORK else "fwd"


def sensitivities(p: Params, cfg: ModelConfig, *, revolutions=None, hours=None,
                  M: float | None = None, keys=None, mode: str = "auto",
                  schedule: Schedule | None = None) -> Sensitivities:
    """d ln y / d ln θ of y = peak depth and worn volume, by autodiff through the wear loop.

    **Arguments:**
    - `p`, `cfg`: the operating point; `revolutions` (crank-slider) or `hours`
      (oscillating joint); `M`: cycles per wear update of eq 23 (None: the adaptive
      integrator at its default tolerance, as `simulate`).
    - `keys`: study keys θ (default: `relevant_keys(p, cfg)`; each must be non-zero).
    - `mode`: `"fwd"` (`jax.jacfwd`: one tangent per parameter), `"rev"` (`jax.jacrev`:
      one reverse pass per output, through the checkpointed scan) or `"auto"` (the
      default: by the run's length, `auto_mode`). The answers agree to round-off.
    - `schedule`: a prebuilt schedule (overrides revolutions/hours/M), e.g. padded so that
      several runs share one compilation.

    **Returns:** `Sensitivities`.
    """
    keys = tuple(relevant_keys(p, cfg) if keys is None else keys)
    specs = effect_parameter_specs()
    for k in keys:
        if k not in PARAMETER_KEYS and k not in specs:
            raise InputError(f"sensitivity: unknown parameter {k!r}")
        if float(p.get(k)) == 0:
            raise InputError(f"sensitivity: {k} is 0, where d ln y / d ln θ is undefined")
    if mode not in ("rev", "fwd", "auto"):
        raise ValueError(f"sensitivity: mode must be 'auto', 'rev' or 'fwd', got {mode!r}")
    sched = schedule if schedule is not None else build_schedule(
        p, cfg, revolutions=revolutions, hours=hours, M=M)
    if mode == "auto":
        mode = auto_mode(sched, cfg)
    if mode == "fwd":  # a traced attempt count (no reverse pass through a while loop)
        sched = sched.with_dynamic_attempts()
    J, (peak, vol, worn, resid, err, steps) = jax.device_get(_jac(p, cfg, sched, keys, mode))
    # the adaptive loop's attempt count is an estimate: where it fell short (error inf, a
    # truncated history) double it rather than differentiate a run that did not finish
    for _ in range(3):
        if not (sched.adaptive and not np.isfinite(float(err))):
            break
        sched = sched.more_attempts()
        J, (peak, vol, worn, resid, err, steps) = jax.device_get(
            _jac(p, cfg, sched, keys, mode))
    J = np.asarray(J)
    return Sensitivities(keys=list(keys),
                         values=np.array([float(p.get(k)) / key_to_si(k) for k in keys]),
                         units=[unit_of(k) for k in keys], peak_depth_um=float(peak) * 1e6,
                         worn_volume_mm3=float(vol) * 1e9, peak=J[0], volume=J[1],
                         worn_through_cycle=float(worn), max_contact_residual=float(resid),
                         error_estimate_um=float(err) * 1e6, steps=int(steps), mode=mode)


def _padded_schedules(study) -> list[Schedule]:
    """Each experiment's schedule, padded (M = 0 updates) to one length: one compilation."""
    scheds = [build_schedule(study.params(e), study.config, revolutions=e.revolutions,
                             hours=e.hours, pad=False, **schedule_numerics(study))
              for e in study.experiments]
    U = bucket(max(s.updates for s in scheds))  # the length `simulate` would compile
    A = max(s.attempts for s in scheds)
    out = []
    for s in scheds:
        out.append(pad_schedule(s, U, 0, A))
    return out


def study_sensitivities(study, *, mode: str = "auto", progress: bool = False) -> dict:
    """`Sensitivities` of every experiment of a study, by name (one compilation); `mode`
    as `sensitivities`, `"auto"` chosen once for the study (its padded schedules are
    alike)."""
    out = {}
    scheds = _padded_schedules(study)
    if mode == "auto":
        mode = "rev" if any(auto_mode(sc, study.config) == "rev" for sc in scheds) else "fwd"
    for i, (e, sc) in enumerate(zip(study.experiments, scheds), start=1):
        t0 = time.perf_counter()
        p = study.params(e)
        out[e.name] = sensitivities(p, study.config, schedule=sc, mode=mode)
        if progress:
            print(f"  [{i}/{len(scheds)}] {e.name}: {len(out[e.name].keys)} parameters, "
                  f"{'reverse' if mode == 'rev' else 'forward'} mode "
                  f"({time.perf_counter() - t0:.1f} s)", file=sys.stderr, flush=True)
    return out


