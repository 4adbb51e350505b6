"""`jaxwear simulate STUDY.toml [--out DIR]`: profiles.csv, plots, summary.json.

The verb's engine: every experiment run forward (`_analyses.simulate`) at the resolution
the study asks for, and its profiles, snapshots, load files and figures written as they
come (`_report.figures`).
"""

from __future__ import annotations

import time

import jax
import numpy as np

from jaxwear._analyses.simulate import (
    common_length,
    last_cycle_pressure,
    pressure_ahead,
    run_experiment,
)
from jaxwear._core import background
from jaxwear._core.log import progress
from jaxwear._physics.config import timed
from jaxwear._physics.cycle import WearResult
from jaxwear._physics.wear import integration_report
from jaxwear._report import figures as rep
from jaxwear._report.painter import Painter
from jaxwear._study.load_file import load_rows, write_load_file
from jaxwear._study.outputs import per_experiment
from jaxwear._study.resolution import amplification_warnings, for_forward
from jaxwear._study.study import Experiment, Study
from jaxwear.cli._pipeline import Verb


def simulate_outputs(study: Study) -> list[str]:
    """Every file name `simulate_study` may write (for the output guard)."""

    return ["profiles.csv", "snapshots.csv", "summary.json", *per_experiment(
        study, "profile_{}.png", "load_{}.png", "pressure_{}.png", "history_{}.png"),
        *[n for e in study.experiments for n in load_file_names(study, e)]]


def load_file_names(study: Study, exp: Experiment) -> list[str]:
    """The load files `simulate` writes for an experiment (design.md §2): `load_EXP.csv`, or
    one per duty block, `load_EXP_1.csv`, ..., for a duty cycle."""
    n = len(study.config.duty_cycle) if timed(study.config) else 1
    return [f"load_{exp.name}.csv"] if n == 1 else [f"load_{exp.name}_{k + 1}.csv"
                                                    for k in range(n)]


def write_load_files(out, study: Study, exp: Experiment, res: WearResult) -> dict:
    """Each regime of the experiment's load, as the model used it, in the load-history
    format (`time_s,load_x_N,load_y_N,angle_deg`); returns the study lines that run them
    back through preset "load_history" (the rig and the boom as two examples of it)."""

    names = load_file_names(study, exp)
    # R_p of the parameters' host copies: on device arrays the subtraction is an eager
    # program of its own
    pin = float(jax.device_get(study.params(exp)).pin_radius)
    for k, name in enumerate(names):
        write_load_file(out, name, load_rows(res.history, k, pin))
    if len(names) == 1:
        model = f'load_history = "{names[0]}"'
    else:
        model = "duty_cycle = [" + ", ".join(
            f'{{load_history = "{n}", duration_h = {b.duration_h:g}}}'
            for n, b in zip(names, study.config.duty_cycle)) + "]"
    run = f"hours = {exp.hours:g}" if timed(study.config) else f"cycles = {exp.revolutions:g}"
    return {"files": names, "model": model, "experiment": run}


def simulate_study(study: Study, out=None, plots=True) -> dict:
    """Run every experiment; write profiles, snapshots, plots and a summary under `out`."""

    def peaks(st):
        length = common_length(st)
        return [float(np.max(np.asarray(run_experiment(st, e, pad_to=length).depth))) * 1e6
                for e in st.experiments]

    # where the study leaves nodes and steps open, the coarsest level whose peak depths agree
    # with the next finer level's within 0.1 % (design.md §6)
    study, resolution = for_forward(study, peaks, log=progress)
    n = study.config.nodes
    angles = np.arange(n) * 360.0 / n
    rows, snap_rows, summary = [], [], {}
    osc = timed(study.config)
    for line in amplification_warnings(study):
        progress(line)
    length = common_length(study)
    ahead = lowered = None
    if out is not None and plots:
        # the pressure maps' program compiled beside the first experiment's
        lowered = background.lowered("wear_loop")
        ahead = pressure_ahead(study, lowered)
    # figures drawn beside the model in a helper process (`painter`), started now: it
    # imports matplotlib while the first experiment compiles
    paint = Painter() if out is not None and plots else None
    try:
        for i, exp in enumerate(study.experiments, start=1):
            t0 = time.perf_counter()
            what = f"{exp.hours:g} h" if osc else f"{exp.revolutions:g} rev"
            progress(f"[{i}/{len(study.experiments)}] {exp.name}: {what} ...")
            res = run_experiment(study, exp, pad_to=length)
            if lowered is not None:
                # lowered by now; a wear loop compiled before in this process is not
                # lowered again, and the call ahead must not wait for it
                background.forget(lowered)
            depth_um = np.asarray(res.depth) * 1e6
            dt = time.perf_counter() - t0
            rows += [(exp.name, a, d) for a, d in zip(angles, depth_um)]
            snaps = exp.snapshot_points
            snap_um = np.asarray(res.snapshots) * 1e6
            for s, prof in zip(snaps, snap_um):
                snap_rows += [(exp.name, s, a, d) for a, d in zip(angles, prof)]
            peak = int(np.argmax(depth_um))
            summary[exp.name] = {
                "peak_depth_um": float(depth_um[peak]), "peak_angle_deg": float(angles[peak]),
                "worn_volume_mm3": float(res.worn_volume) * 1e9,
                "sliding_distance_m": float(res.sliding_distance),
                "max_contact_residual": float(res.max_residual),
                "scla_last_pass_gamma_change_deg": float(np.degrees(np.max(
                    np.asarray(res.history.gamma_change)))),
                "wall_time_s": dt,
                "integration": integration_report(res, study.integrator, study.wear_tolerance_um),
            }
            if out is not None:
                summary[exp.name]["load_history"] = write_load_files(out, study, exp, res)
            progress(f"    peak {depth_um[peak]:.3f} µm at {angles[peak]:.0f}°, "
                     f"volume {float(res.worn_volume) * 1e9:.4f} mm³, integration error "
                     f"≈ {float(res.error_estimate) * 1e6:.2g} µm in {int(res.steps)} steps "
                     f"({dt:.2f} s)")
            if out is not None and plots:
                measured = None
                if exp.profile is not None:
                    last = exp.profile.revolutions == np.max(exp.profile.revolutions)
                    measured = (np.degrees(exp.profile.angle[last]), exp.profile.depth[last] * 1e6)
                unit = "h" if osc else "rev"
                labels = [(f"{s:g} {unit}", d) for s, d in zip(snaps, snap_um)]
                frame = {"load_history": "the load file's frame, from its x axis, counter-"
                                         "clockwise",
                         "oscillating": "bushing frame, counter-clockwise"}.get(
                    study.config.driver, "from B→D, counter-clockwise")
                paint.draw(out.path(f"profile_{exp.name}.png"), rep.plot_profile, exp.name,
                           angles, depth_um, measured, labels if len(labels) > 1 else None,
                           frame=frame)
                hist = res.history
                paint.draw(out.path(f"load_{exp.name}.png"), rep.plot_load, exp.name,
                           np.asarray(hist.fx)[0], np.asarray(hist.fy)[0],
                           np.asarray(hist.angle)[0])
                paint.draw(out.path(f"pressure_{exp.name}.png"), rep.plot_pressure_map,
                           f"{exp.name}: pressure, last cycle ({study.config.contact})",
                           np.asarray(last_cycle_pressure(study, exp, res)))
                if osc and snaps:
                    meas = None
                    if exp.history is not None:
                        meas = (exp.history.hours, exp.history.depth * 1e3)
                    paint.draw(out.path(f"history_{exp.name}.png"), rep.plot_history,
                               exp.name, snaps, snap_um.max(axis=1) / 1e3, meas)
        if paint is not None:
            paint.close()  # every figure written
    except BaseException:
        if paint is not None:
            paint.abort()  # nothing more is written after an error or an interrupt
        raise
    finally:
        if lowered is not None:
            # where the first experiment raised, the call ahead goes on now (never left
            # waiting, to be joined at the interpreter's exit)
            background.forget(lowered)
    if ahead is not None:
        ahead.join()  # ended with the study: nothing of it compiles on after the answer
    if out is not None:
        out.write_csv("profiles.csv", ["experiment", "angle_deg", "depth_um"], rows)
        if snap_rows:
            col = "hours" if osc else "revolutions"
            out.write_csv("snapshots.csv", ["experiment", col, "angle_deg", "depth_um"],
                          snap_rows)
        out.write_json("summary.json", {"experiments": summary, "resolution": resolution})
    return summary


class Simulate(Verb):
    name = "simulate"
    help = "predict wear profiles for a study"
    plots_after = "wear_loop"

    def outputs(self, study, opts):

        return simulate_outputs(study)

    def run(self, study, out, opts):

        simulate_study(study, out)
        print(f"wrote {out.root / 'profiles.csv'}")
