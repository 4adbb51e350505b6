"""Your own joint: one period of its load and motion from a file (design.md §2, preset
"load_history"), read, checked, and resampled onto the wear loop's steps.

The file is what a multibody program (or a load cell and an encoder) gives:

    time_s,load_x_N,load_y_N,angle_deg

the load on the bushing in the bushing frame [N] and the pin's rotation relative to the
bushing [deg], one period, periodic: the row after the last is the first again, one step
later (the period is the last time minus the first plus one step, the median row interval).
Between rows a row's load holds until the next row's time and the angle moves linearly
(zero-order hold and linear interpolation: exactly what the presets' steps do, so a preset's
load written by `simulate` reads back to the same steps). Differences between consecutive
rows are taken modulo 360° (a wrapped angle is fine; rows must be less than 180° apart), so a
pin that turns full revolutions (a crank bearing) is periodic too.

`simulate` writes every experiment's load in this format (`load_rows`): the rig and the boom
are two examples of it.
"""

from __future__ import annotations

import hashlib
import math
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from jaxwear._core.errors import InputError
from jaxwear._physics.config import DutyBlock
from jaxwear._physics.load_cycle import LoadCycle
from jaxwear._physics.params import MECHANISM_KEYS
from jaxwear._study.csv import _read_csv

COLUMNS = ["time_s", "load_x_N", "load_y_N", "angle_deg"]
# Periodic ends: the closing step (last row -> first row) may change a column by at most
# CLOSING_FACTOR times the largest change between consecutive rows among the CLOSING_ROWS
# rows on either side of the end (what the signal does there: a spike elsewhere in the file
# must not excuse a jump at the end), plus CLOSING_FLOOR times the column's largest
# magnitude (a constant column closes exactly).
CLOSING_FACTOR = 2.0
CLOSING_ROWS = 3
CLOSING_FLOOR = 1e-6
# Plausibility of the units. A peak load whose projected pressure |W|/(2 R_b B) is below
# KN_PRESSURE_PA (0.05 MPa; loaded joints run at 1-100 MPa) reads like kN under an N header:
# a warning. An angle that turns by a whole number of 2π (±RADIANS_TURN_TOL turns) where
# degrees would have it close reads like radians: an error (the file does not close on
# itself either way). Angles that span less than 2π in all reads like radians too, or a small
# oscillation: a warning.
KN_PRESSURE_PA = 5e4
RADIANS_TURN_TOL = 0.1


def make_cycle(time_s, load_x_N, load_y_N, angle_deg, path: str = "<memory>") -> LoadCycle:
    """A `LoadCycle` from the columns of a load file as arrays (rows,) in the file's units
    (s, N, N, deg), checked as a file's rows are (`read_load_file`; row i is "line" i + 2).
    For a load computed in Python, e.g. by a multibody model, without a file."""
    a = np.stack([np.asarray(x, np.float64).reshape(-1) for x in
                  (time_s, load_x_N, load_y_N, angle_deg)], axis=1)
    if not np.all(np.isfinite(a)):
        i, j = map(int, np.argwhere(~np.isfinite(a))[0])
        raise InputError(f"{path}: line {i + 2}, column {j + 1} ({COLUMNS[j]}): {a[i, j]} is "
                         f"not a finite number")
    _check(path, a)
    return _cycle(*a.T, str(path))


def _cycle(time_s, load_x_N, load_y_N, angle_deg, path: str) -> LoadCycle:
    t = np.asarray(time_s, np.float64)
    f = np.stack([np.asarray(load_x_N, np.float64), np.asarray(load_y_N, np.float64)], 1)
    a = np.asarray(angle_deg, np.float64)
    step = float(np.median(np.diff(t)))
    period = float(t[-1] - t[0] + step)
    d = _wrap_deg(np.diff(np.r_[a, a[0]]))  # the closing step comes back to the first row
    angle = np.deg2rad(a[0] + np.r_[0.0, np.cumsum(d)])
    digest = hashlib.sha1(np.concatenate([t - t[0], f.ravel(), angle]).tobytes()).hexdigest()
    return LoadCycle(str(path), t - t[0], f, angle, period, digest)


def _near_end(changes: np.ndarray) -> np.ndarray:
    """The changes between the `CLOSING_ROWS` first and last rows (the ends' neighbours)."""
    return np.r_[changes[:CLOSING_ROWS], changes[-CLOSING_ROWS:]]


def _wrap_deg(d):
    return (np.asarray(d) + 180.0) % 360.0 - 180.0


def read_load_file(path: Path) -> LoadCycle:
    """Read and check a load file (module docstring). Raises `InputError` naming the file,
    the line and the column, and what was expected: missing columns, a value that is not
    a finite number, one row (no period), time not increasing, ends that do not close on
    each other (tolerance: `CLOSING_FACTOR` x the largest change between the
    `CLOSING_ROWS` rows on either side of the end, plus `CLOSING_FLOOR` of the column's
    scale), an angle that turns by whole turns of 2π (radians). Warns (stderr) on angles
    that span less than 2π and on a last row equal to the first (the first row again at
    t = period?)."""

    _, a = _read_csv(Path(path), COLUMNS)
    _check(path, a)
    return _cycle(*a.T, str(path))


def _check(path, a: np.ndarray) -> None:
    """The checks of `read_load_file` on the rows `a` (rows, 4) of `COLUMNS`."""
    t, fx, fy, ang = a.T
    if len(t) < 2:
        raise InputError(f"{path}: line 2: one row is no period; expected the rows of one "
                         f"period ({','.join(COLUMNS)}), at least 2, the row after the last "
                         f"being the first again")
    dt = np.diff(t)
    bad = np.flatnonzero(~(dt > 0))
    if bad.size:
        i = int(bad[0]) + 1
        raise InputError(f"{path}: line {i + 2}, column 1 (time_s): {t[i]:g} s is not after "
                         f"{t[i - 1]:g} s on line {i + 1}; expected time increasing row by row")
    step = float(np.median(dt))
    for j, name in ((1, "load_x_N"), (2, "load_y_N")):
        col = a[:, j]
        inner = _near_end(np.abs(np.diff(col)))
        closing = abs(col[0] - col[-1])
        tol = CLOSING_FACTOR * float(np.max(inner)) + CLOSING_FLOOR * float(np.max(np.abs(col)))
        if closing > tol:
            raise InputError(
                f"{path}: line {len(t) + 1}, column {j + 1} ({name}): {col[-1]:g} on the last "
                f"row and {col[0]:g} on the first differ by {closing:.4g}, more than "
                f"{CLOSING_FACTOR:g} x the largest change between consecutive rows near the end "
                f"({float(np.max(inner)):.4g}); expected one period, periodic (the row after "
                f"the last is the first again, {step:g} s later): the ends do not close")
    inner = _near_end(np.abs(_wrap_deg(np.diff(ang))))
    closing = float(np.abs(_wrap_deg(ang[0] - ang[-1])))
    tol = CLOSING_FACTOR * float(np.max(inner)) + CLOSING_FLOOR * max(
        float(np.max(np.abs(ang))), 1.0)
    turn = float(ang[-1] - ang[0]) * len(t) / (len(t) - 1)  # to one period on, as the rows go
    turns = turn / (2 * math.pi)
    if closing > tol:
        hint = ""
        if round(turns) != 0 and abs(turns - round(turns)) < RADIANS_TURN_TOL:
            hint = (f"; it turns by {turn:.4g} over the period, {round(turns):d} x 2π: radians "
                    f"under a degrees header? (multiply by 180/π = 57.3)")
        raise InputError(
            f"{path}: line {len(t) + 1}, column 4 (angle_deg): {ang[-1]:g}° on the last row "
            f"and {ang[0]:g}° on the first are {closing:.4g}° apart (modulo 360°), more than "
            f"{CLOSING_FACTOR:g} x the largest change between consecutive rows near the end "
            f"({float(np.max(inner)):.4g}°); expected one period, periodic (the pin back where "
            f"it started, or whole turns on): the ends do not close{hint}")
    span = float(np.max(ang) - np.min(ang))
    if 0 < span <= 2 * math.pi and len(t) >= 6:
        print(f"warning: {path}: angle_deg spans only {span:.3g}° over the period: if these "
              f"are radians ({span:.3g} rad = {math.degrees(span):.3g}°), multiply by "
              f"180/π = 57.3; a small oscillation in degrees is fine", file=sys.stderr)
    moving = np.any(np.diff(a[:, 1:], axis=0) != 0)
    same = (fx[-1] == fx[0] and fy[-1] == fy[0] and _wrap_deg(ang[-1] - ang[0]) == 0)
    if moving and same and len(t) > 2 and np.any(a[-2, 1:] != a[-1, 1:]):
        print(f"warning: {path}: line {len(t) + 1} equals the first row (line 2): if it is "
              f"the first row again at the end of the period, leave it out (the period is "
              f"the last time minus the first plus one step: {t[-1] - t[0] + step:g} s as "
              f"the file stands)", file=sys.stderr)


def check_load_magnitude(study_path, where: str, cycle: LoadCycle, params) -> None:
    """A warning (stderr) when the file's peak load, times `load_scale`, gives a projected
    pressure |W|/(2 R_b B) below `KN_PRESSURE_PA`: kN under an N header? (`params` SI.)"""
    peak = cycle.peak_load * float(params.load_scale)
    area = 2.0 * float(params.bore_radius) * float(params.width)
    pressure = peak / area
    if 0 < pressure < KN_PRESSURE_PA:
        bore = f"{2e3 * float(params.bore_radius):g} x {1e3 * float(params.width):g} mm"
        print(f"warning: {cycle.path}: the peak load {peak:.4g} N on the {bore} bore of "
              f"{where} in {Path(study_path).name} "
              f"is {pressure / 1e6:.3g} MPa of projected pressure, far below a loaded joint's "
              f"(1-100 MPa): kN under an N header? The columns are load_x_N and load_y_N, in "
              f"newtons", file=sys.stderr)


def load_rows(hist, regime: int, pin_radius: float) -> list[tuple]:
    """The rows of the load file (`COLUMNS`) of one regime of a `LoadHistory`: what the
    wear loop used, step by step. Row i is step i: its time, its load in the bushing frame
    and the rotation accumulated before it (Σ_k<i of the step's sense x sliding / R_p), so
    that the file read back (`read_load_file`, `resample` at the same steps) gives the
    same steps."""
    # host copies first: indexing and multiplying the device arrays compiled a program for
    # each operation (20-50 ms of XLA each)
    load = np.asarray(hist.load, np.float64)[regime]
    ang = np.asarray(hist.angle, np.float64)[regime]
    dt = np.asarray(hist.dt, np.float64)[regime]
    rot = (np.asarray(hist.sense, np.float64)[regime] * np.asarray(hist.slide, np.float64)[regime]
           / float(pin_radius))
    t = np.r_[0.0, np.cumsum(dt)[:-1]]
    phi = np.degrees(np.r_[0.0, np.cumsum(rot)[:-1]])
    return [(float(a), float(b), float(c), float(d)) for a, b, c, d in
            zip(t, load * np.cos(ang), load * np.sin(ang), phi)]


def cycle_rows(cycle: LoadCycle) -> list[tuple]:
    """The rows (`COLUMNS`) of a `LoadCycle`, as read (times from 0, angles unwrapped)."""
    deg = np.degrees(cycle.angle[:-1])
    return [(float(t), float(f[0]), float(f[1]), float(a))
            for t, f, a in zip(cycle.time, cycle.force, deg)]


def write_load_file(out, name: str, rows) -> Path:
    """`rows` (`COLUMNS`) to `name` under the `OutputDir` `out`, at full precision (shortest
    repr that reads back to the same float)."""
    return out.write_text(name, ",".join(COLUMNS) + "\n" + "".join(
        ",".join(repr(float(v)) for v in r) + "\n" for r in rows))


def parse_model(path: Path, model: dict, fail) -> tuple:
    """The duty cycle of a load_history study's `[model]`: `load_history = "cycle.csv"` (one
    file, repeated for the whole run) or `duty_cycle = [{load_history = "lift.csv",
    duration_h = 1}, ...]` (repeated in order). Returns the `DutyBlock`s; `fail(msg)`
    raises the study's `InputError`."""

    if ("load_history" in model) == ("duty_cycle" in model):
        fail("preset \"load_history\" needs model.load_history = \"FILE.csv\" (one period, "
             "repeated) or model.duty_cycle = [{load_history = \"FILE.csv\", duration_h = H}, "
             "...], one of the two")

    def cycle(where, name):
        if not isinstance(name, str) or not name.strip():
            fail(f"{where} must be a file name ({','.join(COLUMNS)}), got {name!r}")
        f = path.parent / name
        if f.is_dir():
            fail(f"{where}: {name!r} is a folder ({f}); expected a load file "
                 f"({','.join(COLUMNS)})")
        if not f.is_file():
            fail(f"{where}: load file {name!r} not found (looked for {f})")
        return read_load_file(f)

    if "load_history" in model:
        return (DutyBlock(0.0, math.inf, cycle("model.load_history", model["load_history"])),)
    blocks = model["duty_cycle"]
    if not isinstance(blocks, list) or not blocks or not all(isinstance(b, dict)
                                                             for b in blocks):
        fail("model.duty_cycle must be a non-empty array of tables {load_history = "
             "\"FILE.csv\", duration_h = H}")
    out = []
    for i, b in enumerate(blocks):
        where = f"model.duty_cycle[{i}]"
        if set(b) != {"load_history", "duration_h"}:
            fail(f"{where} needs exactly load_history and duration_h, got {sorted(b)}")
        d = b["duration_h"]
        if isinstance(d, bool) or not isinstance(d, (int, float)) or not (
                math.isfinite(float(d)) and float(d) > 0):
            fail(f"{where}.duration_h must be a number > 0 (hours), got {d!r}")
        out.append(DutyBlock(0.0, float(d), cycle(f"{where}.load_history", b["load_history"])))
    return tuple(out)


def cycles_to_hours(blocks, cycles: float) -> float:
    """Hours of a run of `cycles` periods counted through the duty cycle `blocks` in order
    (repeated): one period of block b lasts its file's period."""
    periods = [b.load.period for b in blocks]
    if len(blocks) == 1:
        return cycles * periods[0] / 3600.0
    per_pass = [b.duration_h * 3600.0 / T for b, T in zip(blocks, periods)]
    passes = math.floor(cycles / sum(per_pass))
    rest = cycles - passes * sum(per_pass)
    hours = passes * sum(b.duration_h for b in blocks)
    for b, n, T in zip(blocks, per_pass, periods):
        take = min(rest, n)
        hours += take * T / 3600.0
        rest -= take
        if rest <= 0:
            break
    return hours


def check_parameters(path, where: str, values: dict) -> None:
    """Refuse the mechanism keys in a load_history study (`InputError`): the files give the
    load and the motion, so a crank speed or a boom load would be silently ignored."""

    for k in values:
        if k in MECHANISM_KEYS:
            raise InputError(f"{path}: {where}.{k} does not enter a load_history joint (its "
                             f"load and motion come from the load file); expected the joint's "
                             f"geometry and materials (bore_diameter_mm, width_mm, "
                             f"layer_thickness_mm, layer_E_GPa, ..., K_d_per_Pa, load_scale)")


def experiment_hours(path, where: str, exp: dict, config, number) -> float:
    """Hours of an experiment given by `cycles` (periods counted through the duty cycle):
    load_history studies only. `number(where, value)` checks the value (> 0)."""
    if config.driver != "load_history":
        raise InputError(f"{path}: {where}.cycles is for preset \"load_history\"; an "
                         f"oscillating joint runs for 'hours'")
    if "hours" in exp:
        raise InputError(f"{path}: {where}: give 'hours' or 'cycles', not both")
    return cycles_to_hours(config.duty_cycle, number(f"{where}.cycles", exp["cycles"]))


def timed_profile(path, where: str, profile, hours: float, config):
    """A profile of a timed study: measured at the experiment's hours unless its third
    column (`hours`) says when; a load history's profile counts hours, not revolutions."""

    counts = np.asarray(profile.revolutions, float)
    if config.driver == "load_history" and profile.count_column == "revolutions" and not np.all(
            np.isnan(counts)):
        raise InputError(f"{path}: {where}: profile {profile.path} has a 'revolutions' column; "
                         f"a load history counts hours: name the column 'hours'")
    if np.all(np.isnan(counts)):
        return replace(profile, revolutions=np.full(len(counts), float(hours)))
    if np.max(counts) > hours + 1e-9:
        raise InputError(f"{path}: {where}: profile {profile.path} goes to {np.max(counts):g} h "
                         f"> the experiment's {hours:g} h")
    return profile


def check_load_magnitudes(study) -> None:
    """`check_load_magnitude` once per load file of a load_history study, at the experiment
    that loads it least (the smallest `load_scale` x file load over the bore); and, first,
    a joint that never wears (`check_joint_moves`)."""
    check_joint_moves(study)
    for b in study.config.duty_cycle:
        plist = [study.params(e) for e in study.experiments]
        p = min(plist, key=lambda q: float(q.load_scale) / (float(q.bore_radius)
                                                             * float(q.width)))
        i = plist.index(p)
        check_load_magnitude(study.path, f"experiment {study.experiments[i].name!r}", b.load, p)



def check_joint_moves(study) -> None:
    """Refuse (`InputError`) a load_history study whose joint never wears in the base model:
    every load file all 0 N (never loaded: no pressure), or every file's angle constant
    (the pin never turns in the bushing: no sliding, and Archard wear is K_d p dS = 0).
    Such a run ended with exit 0 and depths of exactly 0, without a word (issue 41). With
    an effect switched on (creep, or a user's deposit, may wear without sliding) a still
    joint is a study: then a warning (stderr) says that only the effects can wear."""
    blocks = study.config.duty_cycle
    files = ", ".join(dict.fromkeys(b.load.path for b in blocks))
    if all(b.load.peak_load == 0 for b in blocks):
        raise InputError(f"{files}: columns 2-3 (load_x_N, load_y_N): every row is 0 N, so the "
                         f"joint is never loaded and nothing wears (every depth would be "
                         f"exactly 0); expected the load on the bushing in newtons")
    if all(b.load.rotation == 0 for b in blocks):
        still = list(study.config.effects)
        why = ("column 4 (angle_deg): every row has the same angle, so the pin never turns "
               "in the bushing: no sliding, and the Archard wear K_d p dS is exactly 0")
        if not still:
            raise InputError(f"{files}: {why}; expected the pin's rotation relative to the "
                             f"bushing in degrees, changing over the period (wear not tied "
                             f"to sliding needs an effect such as creep switched on)")
        print(f"warning: {files}: {why}; only the effects switched on ({', '.join(still)}) "
              f"can wear it", file=sys.stderr)
