"""Work that cannot finish is refused up front: an estimate of a study's work and memory.

A study is cheap to read and can be impossible to run: `revolutions = 1e15` asks for 10¹³
wear updates, `nodes = 100000000` for arrays of steps × nodes floats far beyond any memory.
`check_work` estimates, before any computation, from quantities every integrator has:

- wear updates per experiment: the paper integrator (fixed M = `revolutions_per_update`,
  eq 23) makes at most ceil(cycles / M) updates, plus one per further duty-cycle segment
  and one per snapshot (each may split an update); cycles = revolutions, or
  hours × 3600 / swing_period_s for the oscillating joint.
- the adaptive integrator (the default) has no fixed M: its steps are bounded by what it
  needs, not by a cap. Stability: the explicit 3(2) pair is stable while ΔN·λ ≲ 2.5 with
  λ = K_d k S_cycle per cycle (design.md §4; k the foundation stiffness of the unworn layer,
  S_cycle the sliding per cycle; `_wear.adaptive_attempts`), so a piece of c cycles takes at
  least c λ / 2.5 steps, and about 3.4x that in attempts at the limit (rejections, and
  accepted steps below the limit: measured on the boom; 4x is used). Accuracy: ~40 steps
  at the default tolerance, growing like tol^(-1/2): the controller spends a global error
  budget on local estimates of the embedded 2nd-order solution (error ~ ΔN³ per step, so n
  steps of N/n cycles leave ~N³/n² and n ~ tol^(-1/2); measured on the rig, 2000 rev at 64 x
  72: 7, 19, 66, 211, 649, 1982 accepted steps at 2e-3 ... 2e-8 µm, i.e. x3.1 per decade
  from 2e-5 down, where tol^(-1/3) gave x2.2 and under-counted 1e-12 µm fourfold). Plus 4
  per piece (regime starts,
  snapshots). Each attempt evaluates 3 cycles (first-same-as-last), so the estimate's
  "updates" are cycle evaluations: 3 × attempts. λ comes from the study's parameters by
  closed forms (no model evaluation): S_cycle = R_pin × 4 asin(L1/L2) per revolution of the
  crank-slider (the coupler's swing), R_pin × 4 A per swing of amplitude A. `revolutions =
  1e15` on the rig (λ = 1.4e-3) thus needs ~2.3e12 attempts, refused at once, where a cap
  of 4096 steps once let it run for hours.
- contact work: updates × nodes × steps_per_rev contact node-steps (one Newton solve per
  step over all nodes). Measured throughput on one CPU core pair: ~4-6e7 node-steps/s (rig,
  360 × 360 and 128 × 128, M = 100); the time in the message assumes 3e7/s.
- memory: the per-cycle arrays (steps × nodes float64, about `LIVE_ARRAYS` of them alive in
  a contact solve), times (1 + tangents) for a forward-mode Jacobian with `tangents`
  columns, plus the host-side schedule of the paper integrator (~160 bytes per update).

Limits (raise them for a bigger machine or a GPU; document in docs/reference/cli.md):
`JAXWEAR_MAX_WORK` contact node-steps per evaluation (default 1e11, about an hour on a CPU),
`JAXWEAR_MAX_MEMORY_GB` (default 80 % of the physical memory).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass

from jaxwear._core.errors import InputError
from jaxwear._physics.config import timed
from jaxwear._physics.contact import equivalent_modulus
from jaxwear._physics.load import block_periods

DEFAULT_MAX_WORK = 1e11  # contact node-steps per model evaluation
NODE_STEPS_PER_S = 3e7  # conservative CPU throughput, for the time in the message
LIVE_ARRAYS = 12  # (steps, nodes) float64 arrays alive in one vectorised contact solve
SCHEDULE_BYTES_PER_UPDATE = 160  # 4 Python float lists, then 4 arrays
# The adaptive integrator's schedule is built on the fly, so it holds no per-update lists.
ADAPTIVE_LOOP = True
STABILITY_LIMIT = 2.5  # |λ ΔN| of the Bogacki-Shampine pair (as `_wear.adaptive_attempts`)
# attempts per stability-limited step: accepted steps average below the limit and about a
# third are rejected (measured on the boom, 25 h at 360 x 360: 752 + 286 attempts where the
# limit alone gives 307, i.e. 3.4)
ATTEMPTS_PER_STABLE_STEP = 4.0
ACCURACY_STEPS = 40.0  # accuracy-limited steps at the default tolerance (rig: 25-32)
STEPS_PER_PIECE = 4.0  # a piece's start (regime change, snapshot) costs a few steps
EVALUATIONS_PER_ATTEMPT = 3.0  # new cycle evaluations per attempted step (FSAL)


@dataclass(frozen=True)
class WorkEstimate:
    """Estimate for the most expensive experiment of a study (one model evaluation)."""

    experiment: str
    cycles: float  # revolutions or swing cycles
    updates: float  # wear updates (or integrator steps)
    node_steps: float  # updates × nodes × steps_per_rev
    memory_bytes: float
    nodes: int
    steps_per_rev: int
    stable_cycles: float | None = None  # adaptive: the stability limit of a step [cycles]

    @property
    def seconds(self) -> float:
        return self.node_steps / NODE_STEPS_PER_S


def _block_shares(study, exp) -> tuple[list[float], list[float], float]:
    """Per duty block of a timed study: (share of the cycles, period [s]) and the segments
    of a run of the experiment's hours, by closed forms (no segment list: 1e15 hours must
    be refused at once)."""

    cfg = study.config
    periods = block_periods(study.params(exp), cfg)
    hours = float(exp.hours or 0.0)
    per_block = sum(b.duration_h for b in cfg.duty_cycle)
    if not math.isfinite(per_block):  # one file for the whole run
        return [1.0], periods[:1], 1.0
    segments = math.ceil(hours / per_block) * len(cfg.duty_cycle) if per_block > 0 else 1
    per_cycle = [b.duration_h / T for b, T in zip(cfg.duty_cycle, periods)]
    total = sum(per_cycle)
    return ([c / total if total > 0 else 1.0 for c in per_cycle], periods, float(segments))


def _cycles_and_segments(study, exp) -> tuple[float, float]:
    if not timed(study.config):
        return float(exp.revolutions or 0.0), 1.0
    shares, periods, segments = _block_shares(study, exp)
    seconds_per_cycle = sum(sh * T for sh, T in zip(shares, periods))
    return float(exp.hours or 0.0) * 3600.0 / seconds_per_cycle, segments


def stiff_rates(study, exp) -> list[tuple[float, float]]:
    """[(λ [1/cycle], share of the cycles)] per duty regime of one experiment: λ = K_d k
    S_cycle, the decay rate of the stiff mode that bounds explicit steps (design.md §4), by
    closed forms from the parameters (k of the unworn layer, in series with the backing
    for a double layer; S_cycle from the kinematics, or a load file's rotation), as
    `_wear._regime_rates` computes it from the load history, without evaluating the model."""

    cfg = study.config
    p = study.params(exp)
    # host floats throughout: eager jnp on the parameters compiled a program per operation
    compliance = float(p.layer_thickness) / equivalent_modulus(float(p.layer_modulus),
                                                               float(p.layer_poisson))
    if cfg.double_layer:
        compliance += float(p.backing_thickness) / equivalent_modulus(
            float(p.backing_modulus), float(p.backing_poisson))
    k = 1.0 / compliance if compliance > 0 else math.inf
    kd, r_pin = float(p.wear_coefficient), float(p.bore_radius) - float(p.clearance)
    if timed(cfg):
        shares, _, _ = _block_shares(study, exp)
        rot = [b.load.rotation if cfg.driver == "load_history"
               else 4.0 * math.radians(b.amplitude_deg) for b in cfg.duty_cycle]
        return [(kd * k * r_pin * r, share) for r, share in zip(rot, shares)]
    ratio = min(1.0, float(p.crank_length) / float(p.coupler_length))
    return [(kd * k * r_pin * 4.0 * math.asin(ratio), 1.0)]


def accuracy_attempts(tolerance_um: float) -> float:
    """Attempted steps the accuracy alone asks for at `tolerance_um` [µm] (module docstring:
    `ACCURACY_STEPS` at the default 0.002 µm, growing like tol^(-1/2) below it)."""
    return ACCURACY_STEPS * max(1.0, (0.002 / tolerance_um) ** 0.5)


def adaptive_attempts_estimate(study, exp, cycles: float, pieces: float) -> float:
    """Attempted steps of the adaptive integrator over `cycles` in `pieces` pieces (see the
    module docstring): stability-limited, accuracy-limited and per-piece steps."""
    with_stiff = sum(cycles * share * lam for lam, share in stiff_rates(study, exp)
                     if lam > 0 and share > 0)  # (inf x 0 would be NaN)
    stable = ATTEMPTS_PER_STABLE_STEP * with_stiff / STABILITY_LIMIT
    accuracy = accuracy_attempts(float(getattr(study, "wear_tolerance_um", 0.002) or 0.002))
    return stable + accuracy + STEPS_PER_PIECE * pieces


def wear_updates(study, exp) -> tuple[float, float]:
    """(cycles, wear updates) of one experiment, from the quantities every integrator has;
    for the adaptive integrator "updates" are cycle evaluations (3 per attempted step)."""
    cycles, segments = _cycles_and_segments(study, exp)
    M = float(study.revolutions_per_update)
    snaps = float(len(exp.snapshot_points))
    if ADAPTIVE_LOOP and getattr(study, "integrator", "paper") == "adaptive":
        attempts = adaptive_attempts_estimate(study, exp, cycles, segments + snaps)
        if not math.isfinite(attempts):
            return cycles, math.inf
        return cycles, EVALUATIONS_PER_ATTEMPT * math.ceil(attempts)
    by_m = math.ceil(cycles / M) if math.isfinite(cycles / M) else math.inf
    # Σ_segments ceil(c_s / M) ≤ ceil(cycles / M) + segments - 1; a snapshot splits one more
    return cycles, by_m + segments - 1 + snaps


def estimate_work(study, *, tangents: int = 0) -> WorkEstimate:
    """The most expensive experiment's work and memory for one evaluation of the model
    (with `tangents` forward-mode Jacobian columns)."""
    cfg = study.config
    per_cycle = float(cfg.nodes) * float(cfg.steps_per_rev)
    worst = None
    for exp in study.experiments:
        cycles, updates = wear_updates(study, exp)
        schedule = 0.0 if ADAPTIVE_LOOP and study.integrator == "adaptive" else updates
        mem = (8.0 * per_cycle * LIVE_ARRAYS * (1 + tangents)
               + SCHEDULE_BYTES_PER_UPDATE * schedule)
        stable = None
        if ADAPTIVE_LOOP and study.integrator == "adaptive":
            lam = max((lam for lam, _ in stiff_rates(study, exp)), default=0.0)
            stable = STABILITY_LIMIT / lam if lam > 0 else math.inf
        est = WorkEstimate(exp.name, cycles, updates, updates * per_cycle, mem, cfg.nodes,
                           cfg.steps_per_rev, stable)
        if worst is None or (est.node_steps, est.memory_bytes) > (worst.node_steps,
                                                                  worst.memory_bytes):
            worst = est
    return worst


def _limit(name: str, default: float) -> float:
    raw = os.environ.get(name)
    if raw is None or not raw.strip():
        return default
    try:
        v = float(raw)
    except ValueError:
        raise InputError(f"environment variable {name}={raw!r} must be a number") from None
    if not v > 0:
        raise InputError(f"environment variable {name}={raw!r} must be > 0")
    return v


def _physical_memory() -> float:
    try:
        return float(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):
        return 16e9


def max_work() -> float:
    return _limit("JAXWEAR_MAX_WORK", DEFAULT_MAX_WORK)


def max_memory_bytes() -> float:
    return _limit("JAXWEAR_MAX_MEMORY_GB", 0.8 * _physical_memory() / 1e9) * 1e9


def _duration(s: float) -> str:
    if not math.isfinite(s):
        return "forever"
    for unit, size in (("years", 3.15e7), ("days", 86400.0), ("h", 3600.0), ("min", 60.0)):
        if s >= size:
            return f"~{s / size:.3g} {unit}"
    return f"~{s:.3g} s"


def check_work(study, *, tangents: int = 0, length_from: str | None = None) -> WorkEstimate:
    """Raise `InputError` (exit 2) when one evaluation of the study's model would exceed the
    work or memory limit; the message gives the estimate and the keys to change.
    `length_from`: what set the run's length when not the study's `revolutions`/`hours`
    (predict: "`--at`"), named instead of them."""
    est = estimate_work(study, tangents=tangents)
    if est is None:
        return est
    osc = timed(study.config)
    what = length_from or f"`{'hours' if osc else 'revolutions'}`"
    paper = not (ADAPTIVE_LOOP and study.integrator == "adaptive")
    keys = f"lower {what}" + (", raise `numerics.revolutions_per_update`" if paper else "")
    if not paper and accuracy_attempts(study.wear_tolerance_um) > ACCURACY_STEPS:
        keys += (f", raise `numerics.wear_tolerance_um` ({study.wear_tolerance_um:g} µm: "
                 f"~{accuracy_attempts(study.wear_tolerance_um):.3g} steps for accuracy)")
    where = f"{study.path}: experiment {est.experiment!r}"
    work_limit, mem_limit = max_work(), max_memory_bytes()
    problems, env = [], []
    if not est.node_steps <= work_limit:
        how = f"{est.updates:.3g} wear updates"
        if not paper:
            unit = {"oscillating": "swing cycles", "load_history": "load cycles"}.get(
                study.config.driver, "revolutions")
            how = (f"{est.updates:.3g} cycle evaluations of the adaptive integrator (its "
                   f"steps stay stable up to ~{est.stable_cycles:.3g} {unit}, over "
                   f"{est.cycles:.3g} {unit})")
        problems.append(
            f"too much work to finish: {how} × {est.nodes} nodes × "
            f"{est.steps_per_rev} steps_per_rev = {est.node_steps:.3g} contact node-steps "
            f"({_duration(est.seconds)} at {NODE_STEPS_PER_S:.0e}/s; limit {work_limit:.3g})")
        env.append("JAXWEAR_MAX_WORK")
    if not est.memory_bytes <= mem_limit:
        problems.append(
            f"needs ~{est.memory_bytes / 1e9:.3g} GB of memory ({est.nodes} nodes × "
            f"{est.steps_per_rev} steps_per_rev arrays"
            + (f" × {1 + tangents} Jacobian columns" if tangents else "")
            + (f", {est.updates:.3g} updates in the schedule" if paper else "")
            + f"; limit {mem_limit / 1e9:.3g} GB)")
        env.append("JAXWEAR_MAX_MEMORY_GB")
    if problems:
        raise InputError(f"{where}: {'; and '.join(problems)}. {keys[0].upper() + keys[1:]}, "
                         f"or lower `numerics.nodes` / `numerics.steps_per_rev`; or raise "
                         f"the limit with {' / '.join(env)}")
    return est
