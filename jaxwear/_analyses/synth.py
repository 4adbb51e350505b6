"""A virtual test rig with hidden effects: `jaxwear synth` (issue "find the missing physics").

It writes a study (TOML + CSV, design.md §6) whose data come from the full model with chosen
effects switched on, as a careful experimenter would have measured them:

- **Interrupted tests.** Each specimen is measured at several revolution counts (default
  2000, 5000, 10000 and, for the 15000-rev test, 15000), because some effects (running-in
  above all) leave almost no trace in a final profile alone: K_d and the clearances absorb
  them. Oscillating (boom-type) conditions are measured as maximum depth every 5 h.
- **The whole bore, every 2°.** A profilometer scans the whole circumference: outside
  the wear scar the rows are noise around zero (negative depths included). The scan's 0° is
  registered to the bushing only to within a few degrees: `angle_offset_deg` (default 0)
  shifts every scan, and the study does not state it.
- **Real specimens.** Each experiment's actual clearance differs from its nominal value by a
  Gaussian machining tolerance (σ = the study's `clearance_tolerance_um`, default 5 µm); the
  study states the nominal value. The true K_d differs from the study's start value by a
  log-normal factor (σ = 15 %).
- **Noise.** Gaussian, zero mean, `noise_um` (default 0.3 µm), independent per row, never
  clipped.
- **Real parts are not discretised.** The truth is computed at finer numerics than the study
  states: 2x its nodes and steps per revolution, and the fixed-M paper integrator at a tenth
  of its revolutions per update. A fit therefore faces the discretisation mismatch that real
  data bring (no "inverse crime"); what it cannot explain at noise level is either missing
  physics or discretisation error, and the validation (docs/diagnose_validation.md) measures
  how often the latter raises a false alarm.

The truth (effects and strengths, true K_d and clearances, registration offsets, both
numerics, seed) goes to `truth.json` next to the study, which does not reference it. `--out`
never replaces an input (the conditions study or its data files).
"""

from __future__ import annotations

import json
import math
import os
import sys
from dataclasses import dataclass, replace
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from jaxwear._core.errors import InputError
from jaxwear._core.io import OutputDir
from jaxwear._core.jit import jit
from jaxwear._core.periodic import interp_periodic
from jaxwear._physics.config import ModelConfig, timed
from jaxwear._physics.effects import STRUCTURAL_CANDIDATES, get_effect, registered_effects
from jaxwear._study.budget import check_work
from jaxwear._study.effect_files import effect_file_names, effect_file_paths
from jaxwear._study.load_file import cycle_rows, write_load_file
from jaxwear._study.outputs import open_outputs, per_experiment
from jaxwear._study.study import Experiment, History, Profile, Study, load_study

# The paper's rig matrix (§3.3): name, speed [r/min], revolutions, nominal clearance [mm].
PAPER_MATRIX = (
    ("n276-r10000", 276.0, 10000.0, 0.05),
    ("n276-r15000", 276.0, 15000.0, 0.05),
    ("n148-r10000", 148.0, 10000.0, 0.05),
    ("n230-r10000-c010", 230.0, 10000.0, 0.10),
    ("n230-r10000-c015", 230.0, 10000.0, 0.15),
)
INTERRUPTIONS = (2000.0, 5000.0, 10000.0)  # revolutions at which a specimen is measured
PAPER_NUMERICS = {"nodes": 120, "steps_per_rev": 120, "revolutions_per_update": 250}
HISTORY_EVERY_H = 5.0


@dataclass
class SynthResult:
    """What `synthesize` made: `study` as written (with its data), `study_path` its TOML
    file (None when nothing was written), `truth` the hidden parameters and offsets (the
    content of truth.json)."""

    study: Study  # the study as written (with its data)
    study_path: Path | None
    truth: dict


def parse_hidden(items) -> dict:
    """`["running_in=0.5", "friction"]` → {"running_in": {"running_in_amplitude": 0.5},
    "friction": {"friction_coefficient": <realistic>}}. A value names the strength in its
    key's unit; `KEY=VALUE` sets any parameter of a listed effect (e.g.
    `running_in_distance_m=10`). Raises `InputError` for unknown names."""
    out: dict = {}
    flat = []
    for it in items or []:
        flat += [s.strip() for s in str(it).split(",") if s.strip()]
    known = list(registered_effects()) + list(STRUCTURAL_CANDIDATES)
    keys = {}
    for name in known:
        for k in _parameters(name):
            keys[k] = name
    for it in flat:
        name, _, val = it.partition("=")
        name = name.strip()
        if name in keys and val:
            eff = keys[name]
            v, spec = _number(it, val), _parameters(eff)[name]
            if not (spec.lower <= v <= spec.upper):
                raise InputError(f"<<hidden>> {it}: {name} must lie in "
                                 f"[{spec.lower:g}, {spec.upper:g}]")
            out.setdefault(eff, {})[name] = v
            continue
        if name not in known:
            raise InputError(f"<<hidden>>: unknown effect {name!r}; expected one of {known} "
                             f"(EFFECT[=STRENGTH]) or a parameter KEY=VALUE")
        params = out.setdefault(name, {})
        strength = [k for k, s in _parameters(name).items() if not s.log]
        if not strength:
            continue
        spec = _parameters(name)[strength[0]]
        if val:
            v = _number(it, val)
            if not (spec.lower <= v <= spec.upper):
                raise InputError(f"<<hidden>> {it}: {strength[0]} must lie in "
                                 f"[{spec.lower:g}, {spec.upper:g}]")
            params[strength[0]] = v
        else:
            if spec.realistic is None:
                raise InputError(f"<<hidden>> {name}: no realistic strength is declared; give "
                                 f"one as {name}=VALUE")
            params.setdefault(strength[0], spec.realistic)
    for name, params in out.items():  # an effect named only by a shape key: realistic strength
        for k, spec in _parameters(name).items():
            if not spec.log and spec.realistic is not None:
                params.setdefault(k, spec.realistic)
    return out


def _number(item, text):
    try:
        v = float(text)
    except ValueError:
        raise InputError(f"<<hidden>> {item}: {text!r} is not a number") from None
    if not math.isfinite(v):
        raise InputError(f"<<hidden>> {item}: the strength must be finite")
    return v


def _parameters(name):
    if name in STRUCTURAL_CANDIDATES:
        return STRUCTURAL_CANDIDATES[name].parameters
    return get_effect(name).parameters


def paper_conditions(numerics=None) -> Study:
    """The paper's rig matrix as a study without data (Tables 1, 3; spring 1009.4 N/m)."""
    num = dict(PAPER_NUMERICS)
    num.update(numerics or {})
    cfg = ModelConfig(nodes=int(num["nodes"]), steps_per_rev=int(num["steps_per_rev"]))
    exps = tuple(Experiment(name, {"speed_rpm": n, "clearance_mm": c}, revolutions=r)
                 for name, n, r, c in PAPER_MATRIX)
    return Study(path=Path("paper"), preset="rig", config=cfg,
                 parameters={"K_d_per_Pa": 1.0e-13, "spring_N_per_m": 1009.4},
                 experiments=exps, revolutions_per_update=float(num["revolutions_per_update"]),
                 clearance_tolerance_um=5.0, integrator="paper")


def _measure_points(study: Study, exp: Experiment) -> list[float]:
    """Revolutions (crank) or hours (oscillating) at which the specimen is measured."""
    if exp.profile is not None or exp.history is not None:
        return exp.snapshot_points
    if timed(study.config):
        n = max(1, int(round(exp.hours / HISTORY_EVERY_H)))
        return [exp.hours * (i + 1) / n for i in range(n)]
    pts = [r for r in INTERRUPTIONS if r < exp.revolutions - 1e-9]
    if not pts:  # short tests: interrupt at 20 % and 50 % of the run
        pts = [round(0.2 * exp.revolutions), round(0.5 * exp.revolutions)]
    return sorted(set(pts + [float(exp.revolutions)]))


def _with_placeholder_data(study: Study, step_deg: float) -> Study:
    """The study with zero-depth data at the planned measurement points, so that the
    calibration builds the same problem (schedules, snapshots) the written study will give."""
    angles = np.deg2rad(np.arange(0.0, 360.0, step_deg))
    exps = []
    for e in study.experiments:
        pts = _measure_points(study, e)
        if timed(study.config):
            hist = History(np.array(pts), np.zeros(len(pts)), "")
            exps.append(replace(e, profile=None, history=hist, hours=max(pts)))
        else:
            revs = np.repeat(pts, len(angles))
            prof = Profile(np.tile(angles, len(pts)), np.zeros(len(revs)), revs, "")
            exps.append(replace(e, profile=prof, history=None))
    return study.with_experiments(exps)


_snapshots_jit = None


def _true_snapshots(model, u):
    """Snapshots [µm] (E, S, N) and the worn-through flag of the model at u, no Jacobian."""
    global _snapshots_jit
    if _snapshots_jit is None:

        @jit
        def f(ext, u):
            snaps, res = ext.snapshots(u)
            return snaps, jnp.max(res.worn_through_cycle)

        _snapshots_jit = f

    snaps, worn = _snapshots_jit(model.ext, jnp.asarray(u, jnp.float64))
    return np.asarray(snaps), float(worn)


def synthesize(hidden=None, conditions="paper", *, noise_um: float = 0.3, seed: int = 0,
               out=None, numerics=None, angle_step_deg: float = 2.0, kd_sd: float = 0.15,
               perturb=None, verbose: bool = False, angle_offset_deg: float = 0.0,
               refine: int = 2, refine_updates: int = 10) -> SynthResult:
    """Make a study with data from the model with `hidden` effects switched on.

    **Arguments:**
    - `hidden`: `parse_hidden` items (`["running_in=0.5"]`) or its dict
      `{effect: {key: value}}` (values in the keys' units); empty for null data.
    - `conditions`: `"paper"` (the rig matrix), a study file or a `Study`; its data (if
      any) fix the measurement points, else they are planned as described above.
    - `noise_um`: measurement noise σ [µm] on every row; `seed`: random seed.
    - `out`: folder to write `study.toml`, one CSV per experiment and `truth.json` (None:
      nothing is written); it must not hold an input of the conditions (`InputError`).
      `numerics`: overrides of nodes / steps_per_rev / revolutions_per_update (the study's).
      `angle_step_deg`: profile spacing [deg].
    - `angle_offset_deg`: registration offset of every scan [deg]: the row at scan angle a
      measures the bushing at a + offset. Written to truth.json, not to the study.
    - `refine`, `refine_updates`: the truth runs at `refine` x the study's nodes and steps
      per revolution and at revolutions_per_update / `refine_updates` (fixed-M paper
      integrator). `refine=1, refine_updates=1` gives data from the very discretisation the
      study states (only for checking the noise itself: fits on such data commit the
      inverse crime).
    - `perturb(exp_name, points, angle_deg, depth_um) -> depth_um`: optional physics from
      outside the library added to the true profiles before noise (for tests); angles are
      bushing-frame angles.

    **Returns:** `SynthResult` with the study as written and the truth.
    """

    if not (noise_um >= 0 and math.isfinite(noise_um)):
        raise InputError(f"<<noise_um>> must be >= 0, got {noise_um}")
    if not math.isfinite(angle_offset_deg):
        raise InputError(f"<<angle_offset_deg>> must be finite, got {angle_offset_deg}")
    if int(refine) < 1 or int(refine_updates) < 1:
        raise InputError("refine and refine_updates must be whole numbers >= 1")
    base = _conditions(conditions, numerics)  # first: its effect files name effects
    hid = hidden if isinstance(hidden, dict) else parse_hidden(hidden)
    hid = {k: dict(v) for k, v in hid.items()}  # filled in below; the caller's stays
    outdir = None
    if out is not None:  # before any work: the study and CSVs must not replace an input
        outdir = out if isinstance(out, OutputDir) else open_outputs(
            base, out, planned=synth_outputs(base))
    check_work(base)
    rng = np.random.default_rng(seed)
    written_cfg = base.config
    if "unsymmetric" in hid:  # the study states the traditional contact it is missing
        written_cfg = written_cfg.replace(contact="symmetric")
    if "double_layer" in hid and written_cfg.double_layer:
        raise InputError("<<hidden>> double_layer: the conditions already have a double layer")
    for name in hid:
        if name in written_cfg.effects:
            raise InputError(f"<<hidden>> {name}: the conditions already switch it on")
    planned = _with_placeholder_data(replace(base, config=written_cfg), angle_step_deg)
    # The truth at finer numerics: real parts are not discretised at the study's grid.
    fine_cfg = written_cfg.replace(nodes=written_cfg.nodes * int(refine),
                                   steps_per_rev=written_cfg.steps_per_rev * int(refine))
    fine = replace(planned, config=fine_cfg, integrator="paper",
                   revolutions_per_update=planned.revolutions_per_update / int(refine_updates))
    # Only the hidden candidates: a registered effect the truth does not use would be
    # computed at zero strength in every stage of the run (an effect file a notebook loaded
    # earlier made a synth 4-15x slower, measured).
    # the diagnosis package looked up at the call: tests stand in for its model (and
    # `import jaxwear` does not pay for it)
    from jaxwear._analyses import diagnose as _diagnosis
    from jaxwear._analyses.diagnose._extended import candidate_names

    model = _diagnosis.Model(fine, candidates=[n for n in candidate_names(fine.config) if n in hid])
    truth_model = model.with_contact("unsymmetric") if "unsymmetric" in hid else model
    tol_um = planned.clearance_tolerance_um if math.isfinite(
        planned.clearance_tolerance_um) else 5.0
    u = np.zeros(len(model.names))
    truth = {"hidden": {k: dict(v) for k, v in hid.items()}, "noise_um": noise_um,
             "seed": seed, "clearance_mm": {}, "numerics": {
                 "nodes": written_cfg.nodes, "steps_per_rev": written_cfg.steps_per_rev,
                 "revolutions_per_update": planned.revolutions_per_update},
             "truth_numerics": {"nodes": fine_cfg.nodes, "steps_per_rev": fine_cfg.steps_per_rev,
                                "revolutions_per_update": fine.revolutions_per_update,
                                "integrator": "paper"},
             "angle_step_deg": angle_step_deg, "angle_offset_deg": {}}
    for i, name in enumerate(model.names):
        c = model.columns[i]
        start = float(model.ext.start[i])
        if c.key == "K_d_per_Pa" and c.group == "":
            kd = start * math.exp(kd_sd * rng.standard_normal())
            u[i] = model.u_of(name, kd)
            truth["K_d_per_Pa"] = kd
        elif c.key == "clearance_mm" and c.group == "":
            cl = start + 1e-3 * tol_um * rng.standard_normal()
            u[i] = model.u_of(name, cl)
            truth["clearance_mm"][model.exp_names[c.experiment]] = cl
    for eff, params in hid.items():
        # log (shape) parameters first: a strength fitted as a product with one of them
        # needs its partner's u to map its value (`Model.u_of`)
        for key, v in sorted(params.items(), key=lambda kv: not (
                kv[0] in model.index and model.columns[model.index[kv[0]]].log)):
            if key in model.index:
                u[model.index[key]] = model.u_of(key, v, u)
            else:
                raise InputError(f"<<hidden>> {eff}: {key} is not a parameter of the study's "
                                 f"candidates")
        for key, spec in _parameters(eff).items():
            params.setdefault(key, float(truth_model.values(u)[model.index[key]]))
        truth["hidden"][eff] = dict(params)
    if verbose:
        print(f"synth: evaluating the true model ({len(planned.experiments)} experiments, "
              f"{fine_cfg.nodes} nodes x {fine_cfg.steps_per_rev} steps, "
              f"{fine.revolutions_per_update:g} revolutions per update)",
              file=sys.stderr, flush=True)
    snaps, worn = _true_snapshots(truth_model, u)  # (E, S, N) µm
    if not (worn < 0 and np.all(np.isfinite(snaps))):
        raise InputError("the hidden model wears through the layer (or is not finite) for "
                         "these conditions; choose a smaller strength")
    exps = []
    for ei, e in enumerate(planned.experiments):
        pts = e.snapshot_points
        if timed(planned.config):
            depth = snaps[ei, :len(pts)].max(axis=1)
            if perturb is not None:
                depth = np.asarray(perturb(e.name, pts, None, depth), float)
            y = depth + noise_um * rng.standard_normal(len(pts))
            exps.append((e, {"hours": np.array(pts), "depth_mm": y * 1e-3}))
            continue
        truth["angle_offset_deg"][e.name] = float(angle_offset_deg)
        ang = np.arange(0.0, 360.0, angle_step_deg)  # the scan's own angles
        bushing = np.mod(ang + angle_offset_deg, 360.0)
        rows = []
        for si, s in enumerate(pts):
            d = np.asarray(interp_periodic(np.asarray(snaps[ei, si]), np.deg2rad(bushing)))
            if perturb is not None:
                d = np.asarray(perturb(e.name, s, bushing, d), float)
            y = d + noise_um * rng.standard_normal(len(ang))  # every point, zero mean
            rows += [(a, v, s) for a, v in zip(ang, y)]
        exps.append((e, {"rows": rows}))
    truth["K_d_start_per_Pa"] = float(model.ext.start[model.index["K_d_per_Pa"]])
    study_written = _as_study(planned, written_cfg, exps)
    path = None
    if out is not None:
        path = _write(outdir, planned, written_cfg, exps, truth)
        study_written = load_study(path)
    return SynthResult(study_written, path, truth)


def _conditions(conditions, numerics) -> Study:
    if isinstance(conditions, Study):
        st = conditions
    elif conditions in (None, "paper"):
        return paper_conditions(numerics)
    else:
        st = load_study(conditions)
    if numerics:
        kw = {k: int(v) for k, v in numerics.items() if k in ("nodes", "steps_per_rev")}
        st = st.with_config(**kw) if kw else st
        if "revolutions_per_update" in numerics:
            st = replace(st, revolutions_per_update=float(numerics["revolutions_per_update"]),
                         integrator="paper")
    return st


def _as_study(planned: Study, cfg: ModelConfig, exps) -> Study:
    out = []
    for e, data in exps:
        if "rows" in data:
            a = np.array(data["rows"])
            prof = Profile(np.deg2rad(a[:, 0]), a[:, 1] * 1e-6, a[:, 2], "")
            out.append(replace(e, profile=prof, history=None))
        else:
            out.append(replace(e, profile=None,
                               history=History(data["hours"], data["depth_mm"] * 1e-3, "")))
    return replace(planned, config=cfg, experiments=tuple(out))


def _toml_value(v):
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, bool):
        return "true" if v else "false"
    return repr(float(v)) if not float(v).is_integer() or abs(v) >= 1e15 else f"{v:g}"


def synth_outputs(conditions: Study) -> list[str]:
    """Every file name `synthesize(out=...)` writes (for the output guard)."""
    return ["study.toml", "truth.json", *per_experiment(conditions, "{}.csv"),
            *_load_names(conditions.config)]


def _load_names(cfg: ModelConfig) -> list[str]:
    """The load files a load_history study written by synth takes along (its own copies)."""
    if cfg.driver != "load_history":
        return []
    return [f"load_history_{k + 1}.csv" for k in range(len(cfg.duty_cycle))]


def _relative(path: Path, folder: Path) -> str:
    """`path` relative to `folder` (as a study there names it), absolute where no relative
    path exists (another drive)."""
    try:
        return Path(os.path.relpath(path.resolve(), folder.resolve())).as_posix()
    except ValueError:
        return path.resolve().as_posix()


def _write(out: OutputDir, planned: Study, cfg: ModelConfig, exps, truth) -> Path:
    lines = ["# Written by `jaxwear synth`: data from a model with hidden effects.",
             "# The truth is in truth.json (not referenced by this study).",
             "[model]", f"preset = {_toml_value(planned.preset)}",
             f"contact = {_toml_value(cfg.contact)}"]
    if effect_file_names(planned):  # the conditions' own effects, found from the new folder
        lines.append("effect_files = [" + ", ".join(_toml_value(_relative(f, out.root)) for f
                                                    in effect_file_paths(planned)) + "]")
    if cfg.effects:
        lines.append("effects = [" + ", ".join(_toml_value(e) for e in cfg.effects) + "]")
    if cfg.double_layer and planned.preset != "boom":
        lines.append("double_layer = true")
    if cfg.driver == "load_history":

        names = _load_names(cfg)
        for name, b in zip(names, cfg.duty_cycle):
            write_load_file(out, name, cycle_rows(b.load))
        lines.append(f"load_history = {_toml_value(names[0])}" if math.isinf(
            cfg.duty_cycle[0].duration_h) else "duty_cycle = [" + ", ".join(
            f"{{load_history = {_toml_value(n)}, duration_h = {b.duration_h!r}}}"
            for n, b in zip(names, cfg.duty_cycle)) + "]")
    if cfg.driver == "oscillating":
        lines.append("duty_cycle = [" + ", ".join(
            f"{{amplitude_deg = {b.amplitude_deg:g}, duration_h = {b.duration_h:g}}}"
            for b in cfg.duty_cycle) + "]")
    lines.append("[model.parameters]")
    for k, v in planned.parameters.items():
        lines.append(f"{k} = {_toml_value(v)}")
    lines += ["[numerics]", f"nodes = {cfg.nodes}", f"steps_per_rev = {cfg.steps_per_rev}",
              f"revolutions_per_update = {_toml_value(planned.revolutions_per_update)}",
              "[fit]", f"clearance_tolerance_um = {_toml_value(planned.clearance_tolerance_um)}"
              if math.isfinite(planned.clearance_tolerance_um)
              else 'clearance_tolerance_um = "inf"']
    if planned.angle_tolerance_deg > 0:
        lines.append(f"angle_tolerance_deg = {_toml_value(planned.angle_tolerance_deg)}")
    for e, data in exps:
        lines += ["", "[[experiment]]", f"name = {_toml_value(e.name)}"]
        for k, v in e.overrides.items():
            lines.append(f"{k} = {_toml_value(v)}")
        fname = f"{e.name}.csv"
        if "rows" in data:
            lines.append(f"revolutions = {_toml_value(e.revolutions)}")
            lines.append(f"profile = {_toml_value(fname)}")
            out.write_text(fname, "angle_deg,depth_um,revolutions\n" + "".join(
                f"{a:g},{d:.4f},{s:g}\n" for a, d, s in data["rows"]))
        else:
            lines.append(f"hours = {_toml_value(e.hours)}")
            lines.append(f"history = {_toml_value(fname)}")
            out.write_text(fname, "hours,depth_mm\n" + "".join(
                f"{t:g},{d:.6f}\n" for t, d in zip(data["hours"], data["depth_mm"])))
    # the CSVs first: a study file under its final name always has its data beside it
    out.write_text("truth.json", json.dumps(truth, indent=2) + "\n")
    return out.write_text("study.toml", "\n".join(lines) + "\n")
