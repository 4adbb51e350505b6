"""`jaxwear calibrate STUDY.toml [--fit K_d,clearance] [--out DIR] [--json FILE]` (design.md §7).

Writes under DIR: `calibration.json` (the §7 document plus diagnostics), `fit_residuals.csv`
(one row per measured point), `fitted_profiles.csv` (the fitted model at every node and
snapshot), and `fit_<experiment>.png` (measured vs fitted, residuals below). `--json FILE`
writes the same document to FILE too. A readable summary goes to stdout, progress to stderr.

Exit codes: 0 when the fit ran, converged or not: a fit that stopped without converging
still writes its results, with `"converged": false`, the reason in `"message"`, and a
warning on stdout. 2 for bad input (study or data files, `--fit` names). 1 when the fit
cannot run at all (e.g. the model wears through the layer whatever K_d).
"""

from __future__ import annotations

import sys
import time

import numpy as np

from jaxwear._analyses.state_range import range_flags
from jaxwear._core.errors import InputError
from jaxwear._core.io import png_bytes
from jaxwear._inference.calibrate import build_problem, fit_study, study_fit_keys, unit_of
from jaxwear._inference.result import FitResult
from jaxwear._physics.config import timed
from jaxwear._report.figures import plt, thinned, thinned_label
from jaxwear._study.outputs import per_experiment
from jaxwear._study.outside import loud_lines
from jaxwear._study.resolution import at_level
from jaxwear.cli._pipeline import Verb, fit_columns

DEFAULT_FIT = "K_d,clearance"


def fit_spec(args, study) -> str | list[str]:
    """--fit wins; without it (or with the default) the study's `[fit] parameters`."""
    given = getattr(args, "fit", None)
    if given is None and study.fit:
        return list(study.fit)
    return given or DEFAULT_FIT


def _fmt(v: float) -> str:
    if v is None or not np.isfinite(v):
        return "n/a"
    return f"{v:.6g}" if 1e-3 <= abs(v) < 1e5 or v == 0 else f"{v:.5e}"


def summary_text(result: FitResult, study_name: str) -> str:
    """The stdout summary: parameter table, RMSE overall and per experiment, flags."""
    prob = result.problem
    lines = loud_lines(result.flags)  # answers outside the model first
    lines.append(f"calibration of {study_name}: {len(prob.exp_names)} experiments, "
                 f"{result.n_data} data rows, {len(result.names)} fitted parameters")
    status = "converged" if result.converged else "NOT CONVERGED"
    lines.append(f"fit: {status} after {result.iterations} model evaluations ({result.message})")
    w = max([len("parameter")] + [len(n) for n in result.names]) + 2
    lines.append(f"{'parameter':<{w}}{'value':>14}   {'± SE':<15}{'unit'}")
    for n, v, s in zip(result.names, result.values, result.stderr):
        lines.append(f"{n:<{w}}{_fmt(v):>14}   ± {_fmt(s):<13}{unit_of(n)}")
    lines.append(f"RMSE {result.rmse_um:.4g} µm overall (noise estimate {result.noise_um:.4g} µm)")
    for name, r in result.rmse_per_experiment.items():
        lines.append(f"  {name:<{w}}{r:.4g} µm")
    integ = result.integration
    if integ:
        tol, err = integ.get("tolerance_um"), integ["error_estimate_um"]
        err = f"{err:.3g}" if isinstance(err, float) else str(err)
        lines.append(f"integration ({integ['integrator']}): error estimate "
                     f"{err} µm in {integ['steps']} steps at the fitted "
                     f"values" + (f" (tolerance {tol:g} µm)" if tol is not None else ""))
    res = result.resolution
    if res:
        line = f"resolution: {res['nodes']} nodes x {res['steps_per_rev']} steps"
        if res.get("auto"):
            chk = res.get("checked_against")
            jac = res.get("jacobian")
            if res.get("corrected_to") and jac:
                line += (f" (Jacobian at {jac['nodes']} x {jac['steps_per_rev']}, residuals "
                         f"corrected to this level by {res['defect_corrections']} defect "
                         f"correction(s))")
            line += (f", chosen by the error: one Gauss-Newton step at {chk['nodes']} x "
                     f"{chk['steps_per_rev']} moves the answer by "
                     f"{res['refinement_step_standard_errors']:.2g} standard errors"
                     if chk else ", the finest level (not checked against a finer one)")
        else:
            line += " (as given)"
        lines.append(line)
    if result.flags:
        lines.append("flags:")
        lines += [f"  - {f}" for f in result.flags]
    else:
        lines.append("flags: none")
    if not result.converged:
        lines.append(f"WARNING: the fit did not converge ({result.message}); the values above "
                     f"are where it stopped, written with \"converged\": false.")
    return "\n".join(lines)


def write_tables(out, study, result: FitResult):
    """fit_residuals.csv (measured rows) and fitted_profiles.csv (model at every node)."""
    prob = result.problem
    osc = timed(study.config)
    d = prob.data
    exp_idx, snap = np.asarray(d.exp), np.asarray(d.snap)
    x, is_max = np.asarray(d.x), np.asarray(d.is_max)
    points = [e.snapshot_points for e in study.experiments]  # once: not per row
    names = [e.name for e in study.experiments]
    rows = [(names[ei], "history" if h else "profile", points[ei][si], np.nan if h else xi,
             m, f, r)
            for ei, si, h, xi, m, f, r in zip(
                exp_idx.tolist(), snap.tolist(), is_max.tolist(), x.tolist(),
                *(np.asarray(v, float).tolist() for v in (
                    result.measured_um, result.predicted_um, result.residuals_um)))]
    col = "hours" if osc else "revolutions"
    out.write_csv("fit_residuals.csv", ["experiment", "kind", col, "angle_deg", "measured_um",
                                        "fitted_um", "residual_um"], rows)
    n = study.config.nodes
    angles = np.arange(n) * 360.0 / n
    prof_rows = []
    for ei, e in enumerate(study.experiments):
        for si, s in enumerate(e.snapshot_points):
            prof_rows += [(e.name, s, a, v) for a, v in zip(angles, result.snapshots_um[ei, si])]
    out.write_csv("fitted_profiles.csv", ["experiment", col, "angle_deg", "depth_um"],
                  prof_rows)


def plot_fits(out, study, result: FitResult, drawn: list | None = None):
    """fit_<experiment>.png: measured vs fitted, with the residual below; `drawn`: the
    figures of this answer already rendered (`render_fits`)."""

    drawn = render_fits(study, result) if drawn is None else drawn
    return [out.write_bytes(name, data) for name, data in drawn]


def render_fits(study, result: FitResult) -> list[tuple[str, bytes]]:
    """(file name, PNG bytes) of each fit_<experiment>.png of `result` (`plot_fits`)."""

    pl = plt()
    prob = result.problem
    d = prob.data
    exp_idx, snap = np.asarray(d.exp), np.asarray(d.snap)
    x = np.asarray(d.x)
    n = study.config.nodes
    angles = np.arange(n + 1) * 360.0 / n
    drawn = []
    for ei, e in enumerate(study.experiments):
        rows = exp_idx == ei
        if not rows.any():
            continue
        fig, (top, bot) = pl.subplots(2, 1, figsize=(7, 5), sharex=True,
                                      gridspec_kw={"height_ratios": [2.2, 1]})
        points = e.snapshot_points
        if e.history is not None:
            model = result.snapshots_um[ei, :len(points)].max(axis=1) / 1e3
            # a fresh bore at t = 0 (no wear), for a readable curve from the origin
            top.plot([0.0] + list(points), [0.0] + list(model), "k-o", ms=3,
                     label="fitted model")
            top.plot(x[rows], result.measured_um[rows] / 1e3, "s", color="tab:red",
                     label="measured")
            top.set_ylabel("maximum depth [mm]")
            bot.set_xlabel("time [h]")
            bot.plot(x[rows], result.residuals_um[rows], "s", color="tab:red", ms=4)
        else:
            colors = pl.rcParams["axes.prop_cycle"].by_key()["color"]
            for si, s in enumerate(points):
                c = colors[si % len(colors)]
                prof = result.snapshots_um[ei, si]
                label = f"fitted, {s:g} rev" if len(points) > 1 else "fitted model"
                top.plot(angles, np.append(prof, prof[0]), "-", color=c, lw=1.4, label=label)
                m = np.flatnonzero(rows & (snap == si))
                last = si == len(points) - 1
                label = None if not last else thinned_label(
                    "measured (same colours)" if len(points) > 1 else "measured", len(m))
                k = m[thinned(x[m], result.measured_um[m])]
                top.plot(x[k], result.measured_um[k], "o", ms=3, color=c, alpha=0.8,
                         mfc="none", label=label)
                k = m[thinned(x[m], result.residuals_um[m])]
                bot.plot(x[k], result.residuals_um[k], "o", ms=3, color=c)
            top.set_ylabel("wear depth [µm]")
            bot.set_xlabel("bushing angle θ [deg] (from B→D, counter-clockwise)")
            bot.set_xlim(0, 360)
            bot.set_xticks(range(0, 361, 45))
        rm = result.rmse_per_experiment.get(e.name, float("nan"))
        top.set_title(f"{e.name}: measured vs fitted (RMSE {rm:.3g} µm)")
        top.legend(fontsize=8)
        top.grid(alpha=0.3)
        bot.axhline(0, color="k", lw=0.8)
        bot.set_ylabel("residual [µm]")
        bot.grid(alpha=0.3)
        fig.tight_layout()
        drawn.append((f"fit_{e.name}.png", png_bytes(fig)))
        pl.close(fig)
    return drawn


def calibrate_outputs(study) -> list[str]:
    """Every file name `calibrate` writes under --out (for the output guard)."""

    return ["calibration.json", "fit_residuals.csv", "fitted_profiles.csv",
            *per_experiment(study, "fit_{}.png")]


class Calibrate(Verb):
    fits_data = True
    name = "calibrate"
    help = "fit K_d, clearances (and effect strengths) to data"
    takes_json = True

    def add_arguments(self, p):
        p.add_argument("--fit", default=None,
                       help="comma-separated: K_d, clearance, or any study parameter key "
                            "(default: the study's [fit] parameters, else K_d,clearance)")

    def options(self, args):
        return {"fit": args.fit}

    def resolve(self, study, opts):
        # the parameters really fitted (`--fit` when given): their names are checked now and
        # their Jacobian columns enter the memory estimate
        opts["keys"] = study_fit_keys(study, fit_spec(opts["args"], study))

    def outputs(self, study, opts):
        return calibrate_outputs(study)

    def tangents(self, study, opts):
        return fit_columns(study, opts["keys"])

    def run(self, study, out, opts):
        keys = opts["keys"]
        problem = build_problem(study, keys)
        if not problem.names:
            raise InputError(f"{study.path}: nothing to fit: {', '.join(keys)} requested, and "
                             f"[fit] clearance_tolerance_um = 0 fixes the clearances")
        n_exp = len(study.experiments)
        print(f"calibrate: {n_exp} experiments, {problem.n_data} data rows, fitting "
              f"{', '.join(problem.names) or 'nothing'} (first call compiles the model)",
              file=sys.stderr, flush=True)
        t0 = time.perf_counter()
        # the one fit path: refusals before any evaluation, the core, the integration
        # error and the resolution checked at the answer; the figures of the answer as
        # it stands are rendered while a finer check's program compiles (0.5 s of the rig
        # study's calibration) and written if the check leaves the answer as it was (the
        # last one drawn)
        early = {}

        def meanwhile(r, level):
            early.update(level=level, predicted=np.array(r.predicted_um),
                         snapshots=np.array(r.snapshots_um),
                         drawn=render_fits(at_level(study, level), r))

        result = fit_study(study, keys, verbose=True, meanwhile=meanwhile)
        # a loaded law (law.py) used beyond the states it was fitted on
        result.flags += [f for f in range_flags(study, result.problem, result.evaluation)
                         if f not in result.flags]
        res = result.resolution or {}
        if res.get("auto"):  # tables and plots at the nodes the answer was computed on
            study = at_level(study, (res["nodes"], res["steps_per_rev"]))
        comp = result.compiles or {}
        print(f"calibrate: fit took {time.perf_counter() - t0:.1f} s ({result.iterations} "
              f"model evaluations, {result.forward_runs} of them forward runs; "
              f"{comp.get('jacobian', '?')} Jacobian and {comp.get('forward', '?')} forward "
              f"compilations)", file=sys.stderr, flush=True)
        doc = result.to_json()
        written = [out.write_json("calibration.json", doc)]
        if out.json_file is not None:
            written.append(out.write_json_file(doc))
        write_tables(out, study, result)
        same = (early and early["level"] == (study.config.nodes, study.config.steps_per_rev)
                and np.array_equal(early["predicted"], np.asarray(result.predicted_um))
                and np.array_equal(early["snapshots"], np.asarray(result.snapshots_um)))
        written += plot_fits(out, study, result, early["drawn"] if same else None)
        print(summary_text(result, str(study.path)))
        print(f"wrote {written[0]}" + (f" and {written[1]}" if out.json_file is not None
                                       else "")
              + f"; tables and plots in {out.root}")
        return result
