"""Study files (TOML) and measurement files (CSV): design.md §6.

Everything a user can get wrong is checked here, before any computation, and reported as an
`InputError` naming the file, the key or line, and what was expected.
"""

from __future__ import annotations

import csv
import math
import sys
import tomllib
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from jaxwear._core.errors import InputError
from jaxwear._core.noise import profile_noise
from jaxwear._physics.config import DutyBlock, ModelConfig
from jaxwear._physics.effects import STRUCTURAL, effect_parameter_specs, registered_effects
from jaxwear._physics.params import DERIVED_KEYS, PARAMETER_KEYS, PRESETS, Params, preset
from jaxwear._study import load_file as _load_file
from jaxwear._study.csv import _exists, _read_csv, read_text
from jaxwear._study.effect_files import load_effect_files
from jaxwear._study.plausible import check_repeats, check_study


@dataclass(frozen=True)
class Profile:
    """Measured wear profile(s): bushing-frame angle [rad], depth [m], revolution count of
    each row; `angle_offset_deg`: the registration offset already added to the scan's
    angles (the start and prior centre of a fitted `angle_offset_deg/EXP`)."""

    angle: np.ndarray
    depth: np.ndarray
    revolutions: np.ndarray
    path: str
    angle_offset_deg: float = 0.0
    depth_column: str = "depth_um"  # the file's depth column(s), for plausibility messages
    count_column: str = "revolutions"  # or "hours" (timed studies)


@dataclass(frozen=True)
class History:
    """Measured maximum depth vs time: hours [h], depth [m]."""

    hours: np.ndarray
    depth: np.ndarray
    path: str
    depth_column: str = "depth_mm"


@dataclass(frozen=True)
class Experiment:
    """One `[[experiment]]` of a study (docs/design.md §6).

    - `name`; `overrides`: its study keys and values in their units (`speed_rpm`,
      `clearance_mm`, ...), applied over the study's `[model.parameters]`.
    - `revolutions` (crank-slider) or `hours` (oscillating joint, load history): how long
      it runs; the last measured point when the data have several.
    - `profile` (bore scans: angle [rad], depth [m], revolutions) or `history` (maximum
      depth [m] against hours): its measurements, None for a forward run.
    """

    name: str
    overrides: dict  # study keys → values in their units (speed_rpm, clearance_mm, ...)
    revolutions: float | None = None
    hours: float | None = None
    profile: Profile | None = None
    history: History | None = None

    @property
    def snapshot_points(self) -> list[float]:
        """Revolutions (crank) or hours (timed) at which the data measure the profile."""
        # np.unique, not a Python set: a 300 000-row profile asks this often
        if self.profile is not None:
            return np.unique(self.profile.revolutions).tolist()
        if self.history is not None:
            return np.unique(self.history.hours).tolist()
        return []


@dataclass(frozen=True)
class Study:
    """A study file read and checked (`load_study`; docs/design.md §6).

    - `path`: the TOML file; `preset` ("rig", "boom", "load_history"); `config`: the
      static model choices (`ModelConfig`: contact, effects, nodes, steps per cycle, ...).
    - `parameters`: `[model.parameters]` overrides (study keys in their units).
    - `experiments`: the `Experiment`s, in file order.
    - Numerics: `integrator` ("adaptive" or "paper"), `wear_tolerance_um` [µm],
      `revolutions_per_update` (eq 23's M), `auto_resolution` (nodes and steps chosen by
      the error).
    - Fit: `fit` (the `[fit] parameters`), `clearance_tolerance_um` [µm] and
      `angle_tolerance_deg` [deg] (the priors' SDs), `noise_um` (σ if stated) [µm].
    """

    path: Path
    preset: str
    config: ModelConfig
    parameters: dict  # model-level overrides (study keys, user units)
    experiments: tuple[Experiment, ...]
    revolutions_per_update: float = 100.0
    clearance_tolerance_um: float = 5.0
    fit: tuple[str, ...] = ()
    integrator: str = "adaptive"  # or "paper" (fixed M = revolutions_per_update, eq 23)
    wear_tolerance_um: float = 0.002
    angle_tolerance_deg: float = 0.0
    noise_um: float | None = None  # [fit] noise_um: measurement noise σ if known
    # nodes / steps_per_rev absent from [numerics]: chosen by the error (design.md §6)
    auto_resolution: bool = False
    raw: dict = field(default_factory=dict, repr=False)

    def params(self, exp: Experiment | None = None) -> Params:
        """SI parameters of one experiment (model parameters, then the experiment's)."""
        values = dict(self.parameters)
        if exp is not None:
            values.update(exp.overrides)
        return preset(self.preset, **values)

    def with_config(self, **kw) -> Study:

        return replace(self, config=self.config.replace(**kw))

    def with_experiments(self, experiments) -> Study:

        return replace(self, experiments=tuple(experiments))


def _fail(path, msg):
    raise InputError(f"{path}: {msg}")


def _number(path, where, value, *, positive=False, integer=False, nonneg=False):
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        _fail(path, f"{where} must be a number, got {value!r}")
    try:
        v = float(value)
    except OverflowError:  # TOML integers have no size limit in tomllib
        v = math.inf
    if not math.isfinite(v):
        _fail(path, f"{where} must be finite, got {value!r}")
    if positive and not v > 0:
        _fail(path, f"{where} must be > 0, got {value!r}")
    if nonneg and v < 0:
        _fail(path, f"{where} must be >= 0, got {value!r}")
    if integer and v != int(v):
        _fail(path, f"{where} must be a whole number, got {value!r}")
    return v


def _check_keys(path, where, table, allowed):
    if not isinstance(table, dict):
        _fail(path, f"[{where}] must be a table")
    for k in table:
        if k not in allowed:
            _fail(path, f"unknown key {where + '.' if where else ''}{k!r}; expected one of "
                        f"{sorted(allowed)}")


NOISE_WARN_LEVELS = 5.0  # a depth below -5 noise levels is worth a look at the scan's zero
# Plausibility of the units (a warning where another reading is possible, an error where
# none is): angle_deg all below 2π over more than a handful of rows reads like radians (a
# scar is tens of degrees wide); a deepest point under 0.5 µm is below what a gauge
# resolves and far below any scar the model makes, like millimetres under a µm header.
RADIANS_MIN_ROWS = 6
PLAUSIBLE_SCAR_UM = 0.5


def _header(path: Path) -> list[str]:
    """The header names of a CSV file (errors are left to `_read_csv`)."""
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError, ValueError):
        return []
    for line in text.splitlines():
        if line.strip():
            return [h.strip() for h in next(csv.reader([line]))]
    return []


def read_profile(path: Path, angle_offset_deg: float = 0.0) -> Profile:
    """A profile file (design.md §6, docs/measurements.md), one of:

    - `angle_deg,depth_um[,revolutions]` (`depth_mm` may replace `depth_um`; `hours` may
      replace `revolutions`, for a study whose experiments run for hours);
    - `angle_deg,radius_before_um,radius_after_um[,revolutions]`: two raw scans of the bore
      radius, before and after the test, at the same angles; depth = after - before.

    Depths may be negative: a scan is noise around zero outside the wear scar. A depth
    below -5 noise levels (noise estimated robustly from the rows, `_noise.profile_noise`) gets a
    one-line warning on stderr. The scan's angle plus `angle_offset_deg` is the
    bushing-frame angle."""
    header = _header(path)
    count = "hours" if "hours" in header and "revolutions" not in header else "revolutions"
    raw_scans = "radius_before_um" in header or "radius_after_um" in header
    if raw_scans:
        if "depth_um" in header or "depth_mm" in header:
            raise InputError(f"{path}: line 1: give either a depth column (depth_um) or two "
                             f"raw scans (radius_before_um,radius_after_um), not both")
        used, a = _read_csv(path, ["angle_deg", "radius_before_um", "radius_after_um"],
                            [count])
        depth = (a[:, 2] - a[:, 1]) * 1e-6  # wear opens the bore: the radius grows
        rev_col = 3
    else:
        used, a = _read_csv(path, ["angle_deg", "depth_um"], [count],
                            alternatives={"depth_um": ["depth_mm"]})
        depth = a[:, 1] * (1e-3 if used[1] == "depth_mm" else 1e-6)
        rev_col = 2
    for i, ang in enumerate(a[:, 0], start=2):
        if not (0.0 <= ang < 360.0):
            raise InputError(f"{path}: line {i}: angle_deg {ang:g} outside [0, 360)")
    has_revs = a.shape[1] > rev_col
    revs = a[:, rev_col] if has_revs else np.full(len(a), np.nan)
    if has_revs:
        for i, r in enumerate(revs, start=2):
            if not r > 0:
                raise InputError(f"{path}: line {i}: {count} {r:g} must be > 0")
    _check_angles_in_degrees(path, a[:, 0])
    if not raw_scans:
        _check_not_tiny(path, depth, used[1])
    sigma = profile_noise(a[:, 0], depth, revs)
    if math.isfinite(sigma) and sigma > 0:
        low = depth < -NOISE_WARN_LEVELS * sigma
        if low.any():
            j = int(np.argmin(depth))
            print(f"warning: {path}: {int(low.sum())} depth(s) below -{NOISE_WARN_LEVELS:g} "
                  f"noise levels (noise {sigma * 1e6:.3g} µm from neighbouring points; "
                  f"lowest {depth[j] * 1e6:.3g} µm at line {j + 2}): check the scan's zero "
                  f"and sign", file=sys.stderr)
    column = "radius_before_um,radius_after_um" if raw_scans else used[1]
    check_repeats(path, np.c_[a[:, 0], np.where(has_revs, revs, 0.0)],
                  ["angle_deg", count][:1 + has_revs], depth, column, sigma,
                  PLAUSIBLE_SCAR_UM)
    angle = np.mod(np.deg2rad(a[:, 0] + angle_offset_deg), 2 * np.pi)
    return Profile(angle, depth, revs, str(path), float(angle_offset_deg), column, count)


def _check_angles_in_degrees(path: Path, angle_deg: np.ndarray) -> None:
    """A warning when every angle lies below 2π: radians under a degrees header?"""
    distinct = np.unique(angle_deg)
    if len(distinct) >= RADIANS_MIN_ROWS and float(np.max(distinct)) < 2 * math.pi:
        print(f"warning: {path}: all {len(distinct)} angle_deg values lie in [0, "
              f"{float(np.max(distinct)):.3g}], below 2π = 6.28: radians under a degrees "
              f"header? angle_deg expects degrees (multiply by 180/π = 57.3)",
              file=sys.stderr)


def _check_not_tiny(path: Path, depth: np.ndarray, column: str) -> None:
    """A warning when the deepest point is below `PLAUSIBLE_SCAR_UM`: mm under a µm
    header? (`depth` in m.)"""
    deepest = float(np.max(depth)) * 1e6
    if column == "depth_um" and 0 < deepest < PLAUSIBLE_SCAR_UM:
        print(f"warning: {path}: the deepest point is {deepest:.3g} µm, below what a gauge "
              f"resolves (~{PLAUSIBLE_SCAR_UM:g} µm) and far below any wear scar: "
              f"millimetres under a µm header? If the values are in mm, name the column "
              f"depth_mm", file=sys.stderr)


def check_depth_scale(study_path: Path, where: str, data, params: Params) -> None:
    """Refuse (exit 2) measured depths deeper than the layer plus the clearance: no reading
    of them fits the bearing (a `depth_mm` column holding µm, e.g. 195 "mm", once ran a
    calibration for minutes without a word). `data` is a `Profile` or `History`."""
    deepest = float(np.max(data.depth))
    layer, clearance = float(params.layer_thickness), float(params.clearance)
    if not deepest > layer + clearance:
        return
    line = int(np.argmax(data.depth)) + 2
    column = data.depth_column
    if column in ("depth_mm",):
        hint = "micrometres under a mm header? Name the column depth_um"
    elif column == "depth_um":
        hint = "nanometres under a µm header? Give the depths in µm"
    else:
        hint = "check the columns' unit (µm) and which scan is before and which after"
    raise InputError(f"{data.path}: line {line}: {column} gives a depth of "
                     f"{deepest * 1e3:.4g} mm, deeper than the layer ({layer * 1e3:g} mm) "
                     f"plus the clearance ({clearance * 1e3:g} mm) of {where} in "
                     f"{study_path.name}: {hint}")


def read_history(path: Path) -> History:
    """`hours,depth_mm` (maximum depth vs time, design.md §6); `depth_um` may replace
    `depth_mm`."""
    header, a = _read_csv(path, ["hours", "depth_mm"], alternatives={"depth_mm": ["depth_um"]})
    for i, (t, d) in enumerate(a, start=2):
        if not t > 0:
            raise InputError(f"{path}: line {i}: hours {t:g} must be > 0")
    depth = a[:, 1] * (1e-6 if header[1] == "depth_um" else 1e-3)
    if header[1] == "depth_um":
        _check_not_tiny(path, depth, "depth_um")
    check_repeats(path, a[:, :1], ["hours"], depth, header[1],
                  profile_noise(a[:, 0], depth, np.full(len(a), np.nan)),
                  PLAUSIBLE_SCAR_UM)
    return History(a[:, 0], depth, str(path), header[1])


_MODEL_KEYS = {"preset", "contact", "effects", "parameters", "algorithm", "scla_passes",
               "gamma0_deg", "bushing", "double_layer", "duty_cycle", "effect_files",
               "load_history"}
_NUMERIC_KEYS = {"nodes", "steps_per_rev", "revolutions_per_update", "integrator",
                 "wear_tolerance_um"}
_FIT_KEYS = {"clearance_tolerance_um", "angle_tolerance_deg", "parameters", "noise_um"}
_EXP_FIXED = {"name", "revolutions", "hours", "cycles", "profile", "history",
              "angle_offset_deg"}


def _validate_params(path, where, values: dict) -> dict:
    allowed = set(PARAMETER_KEYS) | set(DERIVED_KEYS) | set(effect_parameter_specs())
    _check_keys(path, where, values, allowed)
    out = {}
    for k, v in values.items():
        nonneg = k in ("spring_N_per_m", "backing_thickness_mm")
        positive = (k in PARAMETER_KEYS and PARAMETER_KEYS[k].positive and not nonneg
                    and k not in ("speed_rpm",))
        out[k] = _number(path, f"{where}.{k}", v, positive=positive, nonneg=nonneg)
    return out


def _check_geometry(path, where, params: Params):
    L1, L2 = float(params.crank_length), float(params.coupler_length)
    if not L1 < L2:
        _fail(path, f"{where}: crank_length_mm ({L1 * 1e3:g}) must be < coupler_length_mm "
                    f"({L2 * 1e3:g}) for the crank to turn")
    c, rb = float(params.clearance), float(params.bore_radius)
    if not c > 0:
        _fail(path, f"{where}: clearance_mm must be > 0, got {c * 1e3:g}")
    if not c < rb:
        _fail(path, f"{where}: pin_diameter_mm must be < bore_diameter_mm (pin "
                    f"{(rb - c) * 2e3:g} mm from clearance_mm {c * 1e3:g} and bore "
                    f"{rb * 2e3:g} mm)")
    if not float(params.layer_poisson) < 0.5:
        _fail(path, f"{where}: layer_poisson_ratio must be < 0.5")


def _data_file(path: Path, where: str, name: str):
    """A data file named by the study must be a file beside it (or under its folder)."""
    f = path.parent / name
    try:
        _exists(f, "data file")
    except InputError as e:
        reason = str(e).removeprefix(f"{f}: ")
        if reason == "data file not found":
            _fail(path, f"{where}: data file {name!r} not found (looked for {f})")
        _fail(path, f"{where}: data file {name!r}: {reason}")
    if not f.is_file():
        _fail(path, f"{where}: {name!r} is not a file (looked for {f})")


def load_study(path) -> Study:
    """Read and validate a study file (design.md §6). Raises `InputError` on bad input."""
    path = Path(path)
    _exists(path, "study file")
    if path.is_dir():
        raise InputError(f"{path}: is a folder; expected a study file (TOML)")
    try:
        raw = tomllib.loads(read_text(path, "study file"))
    except tomllib.TOMLDecodeError as e:
        raise InputError(f"{path}: TOML syntax error: {e}") from None
    _check_keys(path, "", raw, {"model", "numerics", "experiment", "fit"})
    model = raw.get("model", {})
    _check_keys(path, "model", model, _MODEL_KEYS)
    if "effect_files" in model:  # user effects, registered before anything is built (§7)
        load_effect_files(path, model["effect_files"])
    name = model.get("preset", "rig")
    if name not in PRESETS:
        _fail(path, f"model.preset must be one of {sorted(PRESETS)}, got {name!r}")
    cfg_kw: dict = {}
    if name == "boom":
        cfg_kw.update(driver="oscillating", double_layer=True)
    if name == "load_history":  # your own joint: its load and motion from files
        cfg_kw.update(driver="load_history",
                      duty_cycle=_load_file.parse_model(path, model, lambda m: _fail(path, m)))
    elif "load_history" in model:
        _fail(path, f"model.load_history is for preset \"load_history\", not {name!r}")
    for key, options in (("contact", ("unsymmetric", "symmetric")),
                         ("algorithm", ("scla", "ideal", "li")),
                         ("bushing", ("coupler", "slider"))):
        if key in model:
            if model[key] not in options:
                _fail(path, f"model.{key} must be one of {list(options)}, got {model[key]!r}")
            cfg_kw[key] = model[key]
    if "double_layer" in model:
        if not isinstance(model["double_layer"], bool):
            _fail(path, "model.double_layer must be true or false")
        cfg_kw["double_layer"] = model["double_layer"]
    if "scla_passes" in model:
        cfg_kw["scla_passes"] = int(_number(path, "model.scla_passes", model["scla_passes"],
                                            positive=True, integer=True))
    if "gamma0_deg" in model:
        cfg_kw["gamma0_rad"] = math.radians(_number(path, "model.gamma0_deg",
                                                    model["gamma0_deg"]))
    effects = model.get("effects", [])
    if not isinstance(effects, list) or not all(isinstance(e, str) for e in effects):
        _fail(path, "model.effects must be a list of effect names")
    known = registered_effects()
    for e in effects:
        if e not in known and e not in STRUCTURAL:
            _fail(path, f"model.effects: unknown effect {e!r}; expected one of "
                        f"{sorted(known) + list(STRUCTURAL)}")
    if "unsymmetric" in effects:
        cfg_kw["contact"] = "unsymmetric"
    if "double_layer" in effects:
        cfg_kw["double_layer"] = True
    cfg_kw["effects"] = tuple(e for e in effects if e in known)
    if "duty_cycle" in model and name != "load_history":
        blocks = model["duty_cycle"]
        if not isinstance(blocks, list) or not blocks:
            _fail(path, "model.duty_cycle must be a non-empty array of tables "
                        "[[model.duty_cycle]] with amplitude_deg and duration_h")
        parsed = []
        for i, b in enumerate(blocks):
            where = f"model.duty_cycle[{i}]"
            _check_keys(path, where, b, {"amplitude_deg", "duration_h"})
            if set(b) != {"amplitude_deg", "duration_h"}:
                _fail(path, f"{where} needs amplitude_deg and duration_h")
            parsed.append(DutyBlock(_number(path, f"{where}.amplitude_deg", b["amplitude_deg"],
                                            positive=True),
                                    _number(path, f"{where}.duration_h", b["duration_h"],
                                            positive=True)))
        cfg_kw["duty_cycle"] = tuple(parsed)
    params = _validate_params(path, "model.parameters", model.get("parameters", {}))
    if name == "load_history":
        _load_file.check_parameters(path, "model.parameters", params)

    num = raw.get("numerics", {})
    _check_keys(path, "numerics", num, _NUMERIC_KEYS)
    if "nodes" in num:
        cfg_kw["nodes"] = int(_number(path, "numerics.nodes", num["nodes"], positive=True,
                                      integer=True))
    # Resolution chosen by the error where neither is given (design.md §6); a study that gives
    # one of them keeps the other's default, as given.
    auto = "nodes" not in num and "steps_per_rev" not in num
    if "steps_per_rev" in num:
        cfg_kw["steps_per_rev"] = int(_number(path, "numerics.steps_per_rev",
                                              num["steps_per_rev"], positive=True, integer=True))
    M = _number(path, "numerics.revolutions_per_update", num.get("revolutions_per_update", 100),
                positive=True)
    # An explicit revolutions_per_update without an integrator asks for eq 23 (as
    # `simulate(..., M=...)` does); no [numerics] M gives the error-controlled default.
    integrator = num.get("integrator",
                         "paper" if "revolutions_per_update" in num else "adaptive")
    if integrator not in ("adaptive", "paper"):
        _fail(path, f"numerics.integrator must be \"adaptive\" or \"paper\", got {integrator!r}")
    wear_tol = _number(path, "numerics.wear_tolerance_um", num.get("wear_tolerance_um", 0.002),
                       positive=True)
    try:
        config = ModelConfig(**cfg_kw)
    except InputError as e:
        _fail(path, str(e))

    fit = raw.get("fit", {})
    _check_keys(path, "fit", fit, _FIT_KEYS)
    tol = fit.get("clearance_tolerance_um", 5.0)
    if isinstance(tol, str) and tol.strip().lower() in ("inf", "infinity"):
        tol = math.inf
    if isinstance(tol, bool) or not isinstance(tol, (int, float)) or not tol >= 0:
        _fail(path, f"fit.clearance_tolerance_um must be a number >= 0 (or inf), got {tol!r}")
    if isinstance(tol, int) and tol > 1e300:
        tol = math.inf  # a huge whole number means no prior, like "inf"
    angle_tol = _number(path, "fit.angle_tolerance_deg", fit.get("angle_tolerance_deg", 0.0),
                        nonneg=True)
    noise = None
    if "noise_um" in fit:
        noise = _number(path, "fit.noise_um", fit["noise_um"], positive=True)
    fit_params = fit.get("parameters", [])
    if not isinstance(fit_params, list):
        _fail(path, "fit.parameters must be a list of names")

    exps_raw = raw.get("experiment", [])
    if not isinstance(exps_raw, list) or not exps_raw:
        _fail(path, "no [[experiment]] tables: a study needs at least one experiment")
    allowed_exp = _EXP_FIXED | set(PARAMETER_KEYS) | set(DERIVED_KEYS) | set(
        effect_parameter_specs())
    experiments = []
    names = set()
    for i, e in enumerate(exps_raw):
        where = f"experiment[{i}]"
        _check_keys(path, where, e, allowed_exp)
        ename = e.get("name", f"experiment{i + 1}")
        if not isinstance(ename, str) or not ename or "/" in ename or "," in ename:
            _fail(path, f"{where}.name must be a non-empty string without '/' or ','")
        if ename in names:
            _fail(path, f"{where}.name {ename!r} is used twice")
        names.add(ename)
        where = f"experiment {ename!r}"
        overrides = _validate_params(path, where, {k: v for k, v in e.items()
                                                   if k not in _EXP_FIXED})
        if name == "load_history":
            _load_file.check_parameters(path, where, overrides)
        if config.driver == "crank_slider" and "speed_rpm" in overrides:
            if not overrides["speed_rpm"] > 0:
                _fail(path, f"{where}.speed_rpm must be > 0, got {e['speed_rpm']!r}")
        profile = history = None
        if "profile" in e:
            if not isinstance(e["profile"], str) or not e["profile"].strip():
                _fail(path, f"{where}.profile must be a file name, got {e['profile']!r}")
            offset = _number(path, f"{where}.angle_offset_deg", e.get("angle_offset_deg", 0.0))
            _data_file(path, f"{where}.profile", e["profile"])
            profile = read_profile(path.parent / e["profile"], offset)
        if "history" in e:
            if config.driver == "crank_slider":  # before the file is read: its columns
                # are not what is wrong (it asked for `hours` in a profile)
                _fail(path, f"{where}.history: 'history' is depth-vs-time data (hours,depth_mm) "
                            f"of the oscillating joint (preset \"boom\"); a {name!r} "
                            f"experiment takes a 'profile' (angle_deg,depth_um[,revolutions])")
            if not isinstance(e["history"], str) or not e["history"].strip():
                _fail(path, f"{where}.history must be a file name, got {e['history']!r}")
            _data_file(path, f"{where}.history", e["history"])
            history = read_history(path.parent / e["history"])
        revs = hours = None
        if config.driver == "crank_slider":
            if "revolutions" not in e:
                _fail(path, f"{where}: missing key 'revolutions'")
            if "cycles" in e or (profile is not None and profile.count_column != "revolutions"):
                _fail(path, f"{where}: a crank-slider experiment counts revolutions (key "
                            f"'revolutions', profile column 'revolutions'), not cycles or hours")
            revs = _number(path, f"{where}.revolutions", e["revolutions"], positive=True)
            if profile is not None:
                r = profile.revolutions
                if np.all(np.isnan(r)):
                    profile = Profile(profile.angle, profile.depth,
                                      np.full(len(r), revs), profile.path,
                                      profile.angle_offset_deg, profile.depth_column)
                elif np.max(r) > revs + 1e-9:
                    _fail(path, f"{where}: profile {e['profile']} has revolutions up to "
                                f"{np.max(r):g} > experiment revolutions {revs:g}")
        else:
            if "cycles" in e:
                hours = _load_file.experiment_hours(path, where, e, config,
                                                    lambda w, v: _number(path, w, v,
                                                                         positive=True))
            elif "hours" in e:
                hours = _number(path, f"{where}.hours", e["hours"], positive=True)
            elif history is not None:
                hours = float(np.max(history.hours))
            else:
                _fail(path, f"{where}: an oscillating joint or a load history needs 'hours' "
                            f"(or 'cycles' of a load history) or a 'history' file")
            if history is not None and np.max(history.hours) > hours + 1e-9:
                length = (f"cycles = {e['cycles']!r}, {hours:g} h" if "cycles" in e
                          else f"hours = {hours:g}")
                _fail(path, f"{where}: history goes to {np.max(history.hours):g} h, beyond the "
                            f"experiment's end ({length}); expected a history within the run")
            if profile is not None:
                profile = _load_file.timed_profile(path, where, profile, hours, config)
        exp = Experiment(ename, overrides, revs, hours, profile, history)
        st = Study(path, name, config, params, (exp,), M, float(tol), tuple(fit_params),
                   integrator, wear_tol, angle_tol, noise, auto, raw)
        try:
            p = st.params(exp)
        except InputError as err:
            _fail(path, f"{where}: {err}")
        _check_geometry(path, where, p)
        for data in (profile, history):
            if data is not None:
                check_depth_scale(path, where, data, p)
        if config.driver == "crank_slider" and not float(p.speed) > 0:
            _fail(path, f"{where}: speed_rpm must be > 0")
        experiments.append(exp)
    # every number against the ranges the model is valid in (`_plausible`), before any work
    study = check_study(Study(path, name, config, params, tuple(experiments), M, float(tol),
                              tuple(fit_params), integrator, wear_tol, angle_tol, noise, auto,
                              raw))
    if config.driver == "load_history":
        _load_file.check_load_magnitudes(study)
    return study
