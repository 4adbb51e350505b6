"""Output of `design` (no model runs here): the design.md §7 document `design.json`, the plot of
the goal's value over the varied ranges, the ready-to-paste `[[experiment]]` stanza of the
recommended experiment(s), the conditions study `jaxwear synth --conditions` makes their
virtual data from, and the text summary.
"""

from __future__ import annotations

import math
import os
import tomllib
from pathlib import Path

import numpy as np

from jaxwear._analyses.design import DesignResult
from jaxwear._core.io import save_figure
from jaxwear._physics.params import key_to_si
from jaxwear._report.figures import plt
from jaxwear._study.study import Study

DESIGN_OUTPUTS = ("design.json", "design.png", "next_experiment.toml",
                  "next_conditions.toml")


def _f(x):
    if x is None:
        return None
    x = float(x)
    return x if math.isfinite(x) else None


def experiment_name(res: DesignResult, i: int, k: int) -> str:
    c = res.plan.conditions[i]
    if res.plan.continuation is not None:
        return res.plan.continuation
    parts = [f"n{c['speed_rpm']:g}" if "speed_rpm" in c else "",
             f"r{c['revolutions']:g}", f"c{c['clearance_mm']:g}" if "clearance_mm" in c
             else "", f"l{c['load_scale']:g}" if "load_scale" in c else ""]
    return f"next{k + 1}-" + "-".join(p for p in parts if p)


def recommended_experiment(res: DesignResult, study: Study, i: int, k: int) -> dict:
    """The §7 `recommended` entry: speed, clearance, revolutions or hours, measure_at,
    value (the goal's value with the set up to this pick)."""
    c = res.plan.conditions[i]
    run = res.plan.runs[res.plan.run[i]]
    p = study.params(run)
    out = {"name": experiment_name(res, i, k)}
    if res.plan.unit == "revolutions":
        out["speed_rpm"] = float(c.get("speed_rpm", float(p.get("speed_rpm"))
                                       / key_to_si("speed_rpm")))
    else:
        out["speed_rpm"] = None  # an oscillating joint has no crank speed
    out["clearance_mm"] = float(c.get("clearance_mm", float(p.clearance) * 1e3))
    if "load_scale" in c:
        out["load_scale"] = float(c["load_scale"])
    out[res.plan.unit] = float(c[res.plan.unit])
    out["measure_at"] = [float(x) for x in res.plan.measure_at[i]]
    out["value"] = _f(res.recommended_values[k])
    out["candidate_value"] = _f(res.values[i])
    out.update({k2: v for k2, v in _detail(res.details[i]).items()})
    return out


def _detail(d: dict) -> dict:
    out = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out[k] = {kk: (_f(vv) if not isinstance(vv, (str, type(None))) else vv)
                      for kk, vv in v.items()}
        elif isinstance(v, (int, float, np.floating)) and not isinstance(v, bool):
            out[k] = _f(v) if not isinstance(v, int) else int(v)
        else:
            out[k] = v
    return out


def to_json(res: DesignResult, study: Study, *, limit: int | None = None) -> dict:
    """The design.md §7 document: `goal`, `between`, `candidates` (best first, each its
    `conditions` and `value`, with `measure_at` and the goal's details), `recommended`."""
    order = res.order if limit is None else res.order[:limit]
    cands = []
    for i in order:
        cands.append({"conditions": res.conditions(int(i)), "value": _f(res.values[i]),
                      "measure_at": [float(x) for x in res.plan.measure_at[i]],
                      **_detail(res.details[i])})
    return {
        "goal": res.goal,
        "between": list(res.between),
        "better": res.better,
        "unit": res.plan.unit,
        "varied": list(res.plan.keys),
        "n_candidates": int(res.plan.size),
        "n_runs": len(res.plan.runs),
        "baseline": _f(res.baseline),
        "candidates": cands,
        "recommended": [recommended_experiment(res, study, int(i), k)
                        for k, i in enumerate(res.recommended)],
        "criterion": res.info.get("criterion"),
        "info": res.info,
        "timing_s": {k: _f(v) for k, v in res.timing.items()},
    }


def _toml(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{k} = {_toml(x)}" for k, x in v.items()) + "}"
    if isinstance(v, int):
        return str(v)
    return f"{float(v):g}" if float(v).is_integer() and abs(v) < 1e15 else repr(float(v))


def stanza(res: DesignResult, study: Study) -> str:
    """The recommended experiment(s) as `[[experiment]]` stanzas to paste into the study."""
    lines = [f"# Recommended by `jaxwear design --goal {res.goal}`"
             + (f" --between {','.join(res.between)}" if res.between else "")
             + f": {res.info.get('criterion', '')}."]
    for k, i in enumerate(res.recommended):
        e = recommended_experiment(res, study, int(i), k)
        pts = ", ".join(f"{x:g}" for x in e["measure_at"])
        lines.append("")
        if res.plan.continuation is not None:
            lines.append(f"# measure the maximum depth of {e['name']} again at {pts} hours: "
                         f"add the row to its history file")
            lines.append(f"# (value {e['candidate_value']:.6g})")
            continue
        lines.append(f"# value {e['candidate_value']:.6g}; scan the profile at {pts} "
                     f"revolutions (interrupt the test there)")
        lines += ["[[experiment]]", f"name = {_toml(e['name'])}",
                  f"speed_rpm = {_toml(e['speed_rpm'])}",
                  f"clearance_mm = {_toml(e['clearance_mm'])}"]
        if "load_scale" in e:
            lines.append(f"load_scale = {_toml(e['load_scale'])}")
        lines += [f"revolutions = {_toml(e['revolutions'])}",
                  f"# profile = {_toml(e['name'] + '.csv')}  "
                  f"# columns angle_deg,depth_um,revolutions"]
    return "\n".join(lines) + "\n"


def _relative(path: Path, folder: Path) -> str:
    try:
        return Path(os.path.relpath(path.resolve(), folder.resolve())).as_posix()
    except ValueError:
        return path.resolve().as_posix()


def conditions_study(res: DesignResult, study: Study, folder: Path) -> str | None:
    """A study without data: the study's model and the recommended experiments (crank-
    slider studies), for `jaxwear synth --conditions FILE --hidden ... --out DIR`
    (synth interrupts at the same points). Its `[model]`, `[numerics]` and `[fit]` are
    the study's, with file paths rewritten relative to `folder`. None for a timed study
    (the recommendation is a further measurement of its own experiment)."""
    if res.plan.continuation is not None:
        return None
    try:  # the study's own sections, as written (the loader keeps no copy)
        raw = tomllib.loads(Path(study.path).read_text(encoding="utf-8-sig"))
    except (OSError, tomllib.TOMLDecodeError):
        raw = {}
    src = Path(study.path).parent
    lines = [f"# Conditions for `jaxwear synth --conditions {folder / 'next_conditions.toml'}"
             f" --hidden ... --out DIR`:", "# the recommended experiment(s) of `jaxwear "
             "design`, the study's own model and numerics (no data)."]
    model = dict(raw.get("model", {}) or {"preset": study.preset})
    params = model.pop("parameters", None) or {}

    def rel(v):
        return _relative(src / v, folder) if isinstance(v, str) else v

    for key in ("effect_files",):
        if key in model:
            model[key] = [rel(x) for x in model[key]]
    if "load_history" in model:
        model["load_history"] = rel(model["load_history"])
    if "duty_cycle" in model:
        model["duty_cycle"] = [{k: (rel(v) if k == "load_history" else v) for k, v in b.items()}
                               for b in model["duty_cycle"]]
    lines.append("[model]")
    lines += [f"{k} = {_toml(v)}" for k, v in model.items() if not isinstance(v, dict)]
    lines.append("[model.parameters]")
    lines += [f"{k} = {_toml(v)}" for k, v in params.items()]
    for section in ("numerics", "fit"):
        if raw.get(section):
            lines.append(f"[{section}]")
            lines += [f"{k} = {_toml(v)}" for k, v in raw[section].items()
                      if not isinstance(v, dict)]
    for k, i in enumerate(res.recommended):
        e = recommended_experiment(res, study, int(i), k)
        lines += ["", "[[experiment]]", f"name = {_toml(e['name'])}",
                  f"speed_rpm = {_toml(e['speed_rpm'])}",
                  f"clearance_mm = {_toml(e['clearance_mm'])}"]
        if "load_scale" in e:
            lines.append(f"load_scale = {_toml(e['load_scale'])}")
        lines.append(f"revolutions = {_toml(e['revolutions'])}")
    return "\n".join(lines) + "\n"


def summary_lines(res: DesignResult, study: Study, top: int = 5) -> list[str]:
    """The text summary: the criterion, the top candidates and the recommended set."""
    lines = [f"goal {res.goal}" + (f" between {' and '.join(res.between)}" if res.between
                                   else "") + f": {res.info.get('criterion', '')} "
             f"({res.better} is better)"]
    if res.baseline is not None:
        lines.append(f"  the study as it is: {res.baseline:.6g}")
    if res.goal == "separate":
        lines.append(f"  the two explanations now differ by a chi-square of "
                     f"{res.info['chi2_between_now']:.3g} (a tie below "
                     f"{res.info['separate_chi2']:.3g})")
    for i in res.order[:top]:
        c = ", ".join(f"{k} {v:g}" for k, v in res.plan.conditions[i].items())
        extra = ""
        if res.goal == "separate":
            n = res.details[i]["scans_needed"]
            extra = (f"; {n} scan set(s) to reach {res.info['separate_chi2']:.3g}"
                     if n is not None else "; no number of scans reaches it (parameter "
                     "uncertainty)")
        lines.append(f"  {c}: {res.values[i]:.6g}{extra}")
    for k, i in enumerate(res.recommended):
        e = recommended_experiment(res, study, int(i), k)
        c = ", ".join(f"{kk} {vv:g}" for kk, vv in res.plan.conditions[i].items())
        lines.append(f"recommended {k + 1}: {c}, measure at "
                     f"{', '.join(f'{x:g}' for x in e['measure_at'])} {res.plan.unit} "
                     f"(value with the set so far {e['value']:.6g})")
    return lines


def plot(res: DesignResult, path) -> None:
    """The goal's value over the varied ranges: one line per value of the second varied key
    against the first (the duration last), at the best values of the others."""
    pl = plt()
    keys = list(res.plan.keys)
    conds = res.plan.conditions
    best = conds[int(res.order[0])]
    x_key = keys[-1] if len(keys) else None
    series_key = next((k for k in keys[:-1] if len({c[k] for c in conds}) > 1), None)
    others = [k for k in keys if k not in (x_key, series_key)]
    fig, ax = pl.subplots(figsize=(6.6, 4.4))
    groups = sorted({c[series_key] for c in conds}) if series_key else [None]
    for g in groups:
        idx = [i for i, c in enumerate(conds)
               if (series_key is None or c[series_key] == g)
               and all(c[k] == best[k] for k in others)]
        idx.sort(key=lambda i: conds[i][x_key])
        xs = [conds[i][x_key] for i in idx]
        ys = [res.values[i] for i in idx]
        ax.plot(xs, ys, "-o", ms=3, label=None if g is None else f"{series_key} {g:g}")
    for k, i in enumerate(res.recommended):
        if all(conds[i][kk] == best[kk] for kk in others):
            ax.plot(conds[i][x_key], res.values[i], "*", color="tab:red", ms=12,
                    label="recommended" if k == 0 else None)
    if res.baseline is not None:
        ax.axhline(res.baseline, color="0.5", ls="--", lw=1, label="the study as it is")
    if res.goal == "separate":
        ax.axhline(res.info["separate_chi2"], color="tab:red", ls=":", lw=1,
                   label="2 ln 20 (told apart)")
    ax.set_xlabel(x_key)
    ax.set_ylabel(f"{res.goal} value ({res.better} is better)")
    at = ", ".join(f"{k} {best[k]:g}" for k in others)
    ax.set_title(f"design --goal {res.goal}" + (f" ({at})" if at else ""), fontsize=10)
    ax.grid(alpha=0.3)
    if len(groups) > 1 or res.recommended or res.baseline is not None or res.between:
        ax.legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, path)
    pl.close(fig)
