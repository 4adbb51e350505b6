"""Candidate next experiments: what `--vary` may change and the plan of runs that covers them."""

from __future__ import annotations

import dataclasses
import itertools
from dataclasses import dataclass

import numpy as np

from jaxwear._analyses.synth import INTERRUPTIONS
from jaxwear._core.errors import InputError
from jaxwear._core.numbers import parse_range
from jaxwear._physics.config import timed
from jaxwear._physics.params import key_to_si
from jaxwear._study.plausible import check_value
from jaxwear._study.study import Experiment, History, Profile, Study

GOALS = ("separate", "parameters", "forecast")


MAX_SCANS = 100  # repeated scans searched for `scans_needed`


NUISANCE = ("clearance_mm", "angle_offset_deg")  # per experiment, marginalised


# keys a candidate may vary: a new specimen's conditions (crank-slider studies)
CRANK_KEYS = ("speed_rpm", "clearance_mm", "load_scale", "revolutions")


TIMED_KEYS = ("hours",)


DEFAULT_SCAN_STEP_DEG = 2.0


# compilation of the candidates' batched Jacobian, added to the work estimate (measured on
# 2 shared cores: 1-3 s for the rig at 64-90 nodes, one or two tangents)
COMPILE_ALLOWANCE_S = 5.0


@dataclass(frozen=True)
class Plan:
    """The candidate set: `conditions[i]` (key → value in its unit) of candidate i, its
    measurement points `measure_at[i]` (revolutions or hours), the run `run[i]` it reads and
    the snapshot indices `snaps[i]` of that run it measures. `runs`: the runs' experiments
    (conditions without data), `points[r]` each run's snapshot points (sorted)."""

    keys: tuple
    conditions: list
    measure_at: list
    run: np.ndarray
    snaps: list
    runs: list
    points: list
    unit: str  # "revolutions" or "hours"
    continuation: str | None = None  # timed: the experiment measured again

    @property
    def size(self) -> int:
        return len(self.conditions)


def parse_vary(text: str | None, study: Study) -> dict:
    """`KEY=LO:HI[:N],KEY=...` → {key: values}; LO:HI without N: 5 values. `InputError`
    (exit 2) naming `--vary` for bad syntax, unknown keys and implausible values."""
    if text is None or not str(text).strip():
        return {}
    allowed = TIMED_KEYS if timed(study.config) else CRANK_KEYS
    out: dict = {}
    # split on commas that start a new KEY= (a value list A,B,C stays whole)
    items, cur = [], ""
    for part in str(text).split(","):
        if "=" in part or not cur:
            if cur:
                items.append(cur)
            cur = part
        else:
            cur += "," + part
    if cur:
        items.append(cur)
    for item in items:
        key, eq, val = item.partition("=")
        key = key.strip()
        if not eq or not key or not val.strip():
            raise InputError(f"<<vary>> {item!r}: expected KEY=LO:HI[:N] (e.g. "
                             f"speed_rpm=100:300:5)")
        if key not in allowed:
            raise InputError(f"<<vary>>: unknown key {key!r} for this study; expected one of "
                             f"{', '.join(allowed)}")
        v = val.strip()
        if v.count(":") == 1:
            v += ":5"
        vals = parse_range(f"<<vary>> {key}", v)
        if key in out:
            raise InputError(f"<<vary>>: {key} given twice")
        where = f"<<vary>> {key}"
        rng_key = ("experiment." + key) if key in ("revolutions", "hours") else key
        for x in (float(np.min(vals)), float(np.max(vals))):
            check_value(where, rng_key, x, preset=study.preset, name=where)
        if key == "clearance_mm":
            radius_mm = float(study.params().bore_radius) * 1e3
            if np.max(vals) >= radius_mm:
                raise InputError(f"<<vary>> clearance_mm: values must be below the bore radius "
                                 f"{radius_mm:g} mm")
        if key in ("revolutions", "hours", "speed_rpm", "load_scale") and np.min(vals) <= 0:
            raise InputError(f"<<vary>> {key}: values must be > 0")
        out[key] = np.unique(vals)
    return out


def default_vary(study: Study, after: float | None = None) -> dict:
    """The default candidate ranges: around the study's own conditions, inside the
    plausibility table. Crank-slider: speed 0.5-1.5x the studied speeds (5 values),
    clearance 0.5-1.5x the studied clearances (5), revolutions 0.25-2x the longest run (8):
    200 candidates in 25 runs. Timed: hours from the last measurement (`after`) to twice it,
    20 values."""
    if timed(study.config):
        last = after if after is not None else max(
            max(e.snapshot_points or [e.hours or 0.0]) for e in study.experiments)
        last = max(float(last), 1e-3)
        return {"hours": np.linspace(last * 1.05, 2.0 * last, 20)}
    plist = [study.params(e) for e in study.experiments]
    speeds = [float(p.get("speed_rpm")) / key_to_si("speed_rpm") for p in plist]
    clear = [float(p.clearance) * 1e3 for p in plist]
    revs = max(float(e.revolutions or 1.0) for e in study.experiments)
    return {"speed_rpm": np.linspace(0.5 * min(speeds), 1.5 * max(speeds), 5),
            "clearance_mm": np.linspace(0.5 * min(clear), 1.5 * max(clear), 5),
            "revolutions": np.round(np.linspace(0.25 * revs, 2.0 * revs, 8))}


def measure_points(revolutions: float) -> list[float]:
    """Where a new crank-slider specimen is scanned: synth's interruptions below its end,
    and the end (so that `jaxwear synth --conditions` makes the same measurements)."""
    pts = [r for r in INTERRUPTIONS if r < revolutions - 1e-9]
    if not pts:  # short tests: interrupt at 20 % and 50 % of the run
        pts = [round(0.2 * revolutions), round(0.5 * revolutions)]
    return sorted(set(pts + [float(revolutions)]))


def plan_candidates(study: Study, vary: dict, *, experiment: int = 0) -> Plan:
    """The candidate set of `vary` (`parse_vary`/`default_vary`) for `study`."""
    if timed(study.config):
        hours = np.asarray(vary.get("hours", default_vary(study)["hours"]), float)
        e = study.experiments[experiment]
        pts = sorted(set(hours.tolist()))
        conds = [{"hours": float(h)} for h in hours]
        return Plan(keys=("hours",), conditions=conds, measure_at=[[float(h)] for h in hours],
                    run=np.zeros(len(hours), int), snaps=[[pts.index(float(h))] for h in hours],
                    runs=[e], points=[pts], unit="hours", continuation=e.name)
    vary = dict(vary)
    base = dict(default_vary(study)) if not vary else {}
    grid = {**base, **vary}
    if "revolutions" not in grid:
        grid["revolutions"] = np.array([max(float(e.revolutions or 1.0)
                                            for e in study.experiments)])
    cond_keys = [k for k in grid if k != "revolutions"]
    template = study.experiments[experiment]
    runs, points, conds, measure, run_idx, snaps = [], [], [], [], [], []
    durations = sorted(float(r) for r in grid["revolutions"])
    for combo in itertools.product(*(grid[k] for k in cond_keys)):
        over = dict(template.overrides)
        over.update({k: float(v) for k, v in zip(cond_keys, combo)})
        pts = sorted(set(itertools.chain.from_iterable(measure_points(r) for r in durations)))
        name = "cand-" + "-".join(f"{k}{float(v):g}" for k, v in zip(cond_keys, combo))
        runs.append(Experiment(name, over, revolutions=max(durations)))
        points.append(pts)
        for r in durations:
            m = measure_points(r)
            conds.append({**{k: float(v) for k, v in zip(cond_keys, combo)},
                          "revolutions": float(r)})
            measure.append(m)
            run_idx.append(len(runs) - 1)
            snaps.append([pts.index(x) for x in m])
    return Plan(keys=tuple(cond_keys) + ("revolutions",), conditions=conds,
                measure_at=measure, run=np.asarray(run_idx), snaps=snaps, runs=runs,
                points=points, unit="revolutions")


def _placeholder(e: Experiment, pts: list[float], is_timed: bool) -> Experiment:
    """`e` with zero data at `pts`: its run's snapshots (the rows are never compared)."""
    pts = [float(x) for x in pts]
    if is_timed:
        return dataclasses.replace(e, profile=None, hours=max(pts),
                                   history=History(np.array(pts), np.zeros(len(pts)), ""))
    return dataclasses.replace(e, history=None, revolutions=max(pts), profile=Profile(
        np.zeros(len(pts)), np.zeros(len(pts)), np.array(pts), ""))
