"""`jaxwear sweep STUDY.toml --speed-rpm 100:300:21 --clearance-mm 0.05:0.15:11
[--load-scale A:B:N] [--hours A:B:N | --revolutions A:B:N] [--out DIR]`."""

from __future__ import annotations

import itertools
import math
import sys
import time
from dataclasses import replace

import numpy as np

from jaxwear._analyses import sweep as _sweep
from jaxwear._core.errors import InputError
from jaxwear._core.numbers import MAX_POINTS, parse_range
from jaxwear._physics.config import timed
from jaxwear._physics.params import key_to_si, preset
from jaxwear._report.figures import sweep_heatmap
from jaxwear._study.plausible import check_params, check_value
from jaxwear._study.study import _check_geometry
from jaxwear.cli._pipeline import Verb

SWEEP_OUTPUTS = ("sweep.csv", "sweep_peak_depth.png", "sweep_worn_volume.png")


def _preset(study, values: dict):

    return preset(study.preset, **values)


def status_counts(status) -> str:
    """'3 worn through, 1 with a failed contact solve' from `SweepResult.status` (failures
    only)."""
    names = {"worn_through": "worn through", "contact_failed": "with a failed contact solve",
             "integration_failed": "with an unfinished integration"}
    return ", ".join(f"{int((status == k).sum())} {v}" for k, v in names.items()
                     if (status == k).any())


class Sweep(Verb):
    name = "sweep"
    help = "batched sweep over speed, clearance, load scale and duration"

    def add_arguments(self, p):
        p.add_argument("--speed-rpm", default=None, help="START:STOP:COUNT [r/min]")
        p.add_argument("--clearance-mm", default=None, help="START:STOP:COUNT [mm]")
        p.add_argument("--load-scale", default=None,
                       help="START:STOP:COUNT, multiplier of the joint load [-]")
        p.add_argument("--hours", default=None,
                       help="START:STOP:COUNT, duration of a timed joint (snapshots) [h]")
        p.add_argument("--revolutions", default=None,
                       help="START:STOP:COUNT, duration of a crank-slider (snapshots)")

    def options(self, args):
        grid = {}
        for key in ("speed_rpm", "clearance_mm", "load_scale", "hours", "revolutions"):
            text = getattr(args, key)
            if text is not None:
                grid[key] = parse_range("--" + key.replace("_", "-"), text)
        if not grid:
            raise InputError("sweep: give --speed-rpm START:STOP:COUNT, --clearance-mm, "
                             "--load-scale, --hours or --revolutions (one or more)")
        if "hours" in grid and "revolutions" in grid:
            raise InputError("sweep: give --hours (timed joints) or --revolutions "
                             "(crank-slider), not both")
        total = math.prod(len(v) for v in grid.values())
        if total > MAX_POINTS:
            raise InputError(f"sweep: {total} grid points; at most {MAX_POINTS} (each is a "
                             f"whole wear simulation): give fewer values")
        return {"grid": grid, "total": total}

    def resolve(self, study, opts):
        if "speed_rpm" in opts["grid"] and timed(study.config):
            raise InputError("--speed-rpm: the study's joint is oscillating or a load history "
                             "(no crank speed); sweep --clearance-mm, --load-scale or --hours")
        want = "hours" if timed(study.config) else "revolutions"
        for key in ("hours", "revolutions"):
            if key in opts["grid"] and key != want:
                raise InputError(f"--{key}: the study's experiments run for {want}; "
                                 f"give --{want}")
        # the grid's ends against the geometry of the swept experiment (clearance > 0 and
        # below the bore radius, speed > 0: each check is monotone in its value), now rather
        # than inside the sweep


        exp = study.experiments[0]
        ends = {}
        for key, values in opts["grid"].items():
            option = "--" + key.replace("_", "-")
            if key in ("hours", "revolutions"):
                continue  # a duration is checked by the engine (> 0)
            ends[key] = (float(np.min(values)), float(np.max(values)))
            for v in ends[key]:
                if key == "speed_rpm" and not v > 0:
                    raise InputError(f"{option}: speed_rpm must be > 0, got {v:g}")
                try:
                    values_at = {**study.parameters, **exp.overrides, key: v}
                    _check_geometry(option, f"{key} = {v:g}", _preset(study, values_at))
                except InputError as e:
                    raise InputError(f"{e} (experiment {exp.name!r} of {study.path})"
                                     ) from None
                check_value(option, key, v, preset=study.preset)
        # the ratios and the layer strain at the grid's corners (each grows monotonically
        # with speed and with clearance, so the corners bound the grid)
        for corner in itertools.product(*ends.values()):
            at = dict(zip(ends, corner))
            p = _preset(study, {**study.parameters, **exp.overrides, **at})
            where = ", ".join(f"--{k.replace('_', '-')} {v:g}" for k, v in at.items())
            check_params(f"{where} (experiment {exp.name!r} of {study.path})", p,
                         study.config)

    def outputs(self, study, opts):
        return list(SWEEP_OUTPUTS)

    def work_study(self, study, opts):
        """The swept experiment run to the longest duration of a duration axis."""

        grid = opts["grid"]
        e = study.experiments[0]
        if "hours" in grid:
            e = replace(e, hours=float(np.max(grid["hours"])))
        elif "revolutions" in grid:
            e = replace(e, revolutions=float(np.max(grid["revolutions"])))
        return study.with_experiments([e])

    def run(self, study, out, opts):

        grid, total = opts["grid"], opts["total"]
        exp = study.experiments[0]
        p = study.params(exp)
        osc = timed(study.config)
        what = f"{exp.hours:g} h" if osc else f"{exp.revolutions:g} rev"
        print(f"sweep: {total} points around experiment {exp.name!r} ({what}); the first "
              f"chunk compiles the model", file=sys.stderr, flush=True)
        t0 = time.perf_counter()
        res = _sweep.sweep(study, grid=grid, progress=True)
        dt = time.perf_counter() - t0
        pts = res.points()
        cols = ["clearance_mm"] if osc else ["speed_rpm", "clearance_mm"]
        cols += [k for k in grid if k not in cols]
        fixed = {k: float(p.get(k)) / key_to_si(k) for k in cols
                 if k not in ("hours", "revolutions")}
        valid = res.valid.ravel()
        status = res.status.ravel()
        rows = []
        for i in range(total):
            keyvals = [pts[k][i] if k in pts else fixed[k] for k in cols]
            ok = valid[i]
            rows.append(keyvals + [res.peak_depth_um.ravel()[i] if ok else np.nan,
                                   res.worn_volume_mm3.ravel()[i] if ok else np.nan,
                                   res.peak_angle_deg.ravel()[i] if ok else np.nan,
                                   res.worn_through_cycle.ravel()[i],
                                   res.error_estimate_um.ravel()[i], res.steps.ravel()[i],
                                   status[i]])
        unit = "cycle" if osc else "revolution"
        # status last: the columns before it kept their places for existing readers
        out.write_csv("sweep.csv", cols + ["peak_depth_um", "worn_volume_mm3",
                                           "peak_angle_deg", f"worn_through_{unit}",
                                           "integration_error_um", "integration_steps",
                                           "status"], rows)
        at = exp.name if ("hours" in grid or "revolutions" in grid) else f"{exp.name}, {what}"
        sweep_heatmap(out.path("sweep_peak_depth.png"), f"{at}: peak wear depth",
                        "peak depth [µm]", res, res.peak_depth_um)
        sweep_heatmap(out.path("sweep_worn_volume.png"), f"{at}: worn volume",
                        "worn volume [mm³]", res, res.worn_volume_mm3)
        v = res.valid
        print(f"sweep of {total} points in {dt:.1f} s: peak depth "
              f"{np.nanmin(np.where(v, res.peak_depth_um, np.nan)):.4g} to "
              f"{np.nanmax(np.where(v, res.peak_depth_um, np.nan)):.4g} µm, worn volume "
              f"{np.nanmin(np.where(v, res.worn_volume_mm3, np.nan)):.4g} to "
              f"{np.nanmax(np.where(v, res.worn_volume_mm3, np.nan)):.4g} mm³"
              if v.any() else f"sweep of {total} points in {dt:.1f} s: no point gave a "
                              f"result ({status_counts(res.status)})")
        err = res.error_estimate_um[np.isfinite(res.error_estimate_um)]
        if err.size:
            how = (f"adaptive, tolerance {res.tolerance_um:g} µm"
                   if res.tolerance_um is not None else "eq 23, Euler's estimate")
            print(f"integration ({how}): error estimate up to {err.max():.3g} µm, "
                  f"{int(res.steps.min())}-{int(res.steps.max())} steps per point")
        if not v.all():
            print(f"{int((~v).sum())} of {total} points without a result "
                  f"({status_counts(res.status)}): NaN in sweep.csv with their status, "
                  f"marked in the plots"
                  + ("; a failed contact solve is outside what the model can solve there: "
                     "narrow the grid" if (res.status == "contact_failed").any() else ""))
        r = res.resolution
        if r is not None:
            if r.get("auto"):
                err = r.get("error_estimate_um")
                print(f"resolution: {r['nodes']} nodes x {r['steps_per_rev']} steps, chosen at "
                      f"the grid's corners" + (f" (peak within {err:.3g} µm of the next finer "
                                               f"level)" if err is not None else ""))
            else:
                print(f"resolution: {r['nodes']} nodes x {r['steps_per_rev']} steps (as given)")
        print(f"wrote {out.root / 'sweep.csv'}, sweep_peak_depth.png, sweep_worn_volume.png")
        return res
