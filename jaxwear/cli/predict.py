"""`jaxwear predict STUDY.toml --at LIST [--train-until X] [--level 0.9] [--limit-um D]
[--method laplace|nuts|importance] [--out DIR] [--json FILE]` (design.md §7).

Writes under DIR: `prediction.json` (the §7 document plus diagnostics), `predictions.csv`
(one row per experiment and `--at` point, both bands), `forecast_curves.csv` (the forecast
and its bands on a fine grid, for plots of your own), `fan_<experiment>.png` (measured
points, forecast line and band), `profile_<experiment>.png` (profile studies: the profile at
the last `--at` point with its band) and, for `--method nuts` and `importance`,
`posterior.nc` (ArviZ InferenceData). `--json FILE` writes the document to FILE too.
Progress goes to stderr.
Exit codes: 0 done, 2 bad input (the message names the option or key), 1 anything else.
"""

from __future__ import annotations

import sys
import time
from dataclasses import replace

import numpy as np

from jaxwear._analyses.predict import forecast as _predict
from jaxwear._analyses.predict.life import LIFE_HORIZON
from jaxwear._core.errors import InputError
from jaxwear._core.jsonfmt import json_float
from jaxwear._core.numbers import number, number_list
from jaxwear._core.optional import check_method_packages
from jaxwear._inference.packing import study_fit_keys
from jaxwear._physics.config import timed
from jaxwear._report.figures import plt, thinned, thinned_label
from jaxwear._study.outputs import per_experiment
from jaxwear._study.outside import loud_lines
from jaxwear._study.plausible import check_value
from jaxwear._study.resolution import amplification_warnings
from jaxwear.cli._pipeline import Verb, fit_columns


def parse_at(text: str) -> list[float]:
    """`--at`: comma-separated forecast points > 0 (revolutions or hours)."""
    return number_list("--at", text, positive=True)


def predict_outputs(study, method: str) -> list[str]:
    """Every file name `predict` writes under --out (for the output guard)."""

    names = ["prediction.json", "predictions.csv", "forecast_curves.csv",
             *per_experiment(study, "fan_{}.png", "profile_{}.png")]
    return names + (["posterior.nc"] if method in ("nuts", "importance") else [])


def write_outputs(out, study, res):
    """predictions.csv, forecast_curves.csv, the plots; returns the paths written."""

    rows = [(p.experiment, p.at, p.unit, p.depth_um, p.lower_um, p.upper_um, p.conf_lower_um,
             p.conf_upper_um, json_float(p.measured_um) if p.measured_um is not None else "")
            for p in res.predictions]
    paths = [out.write_csv("predictions.csv",
                           ["experiment", "at", "unit", "depth_um", "lower_um", "upper_um",
                            "conf_lower_um", "conf_upper_um", "measured_um"], rows)]
    crows = []
    for name, c in res.curves.items():
        crows += [(name, a, res.unit, d, lo, hi, cl, ch, int(v)) for a, d, lo, hi, cl, ch, v in
                  zip(c.at, c.depth_um, c.lower_um, c.upper_um, c.conf_lower_um,
                      c.conf_upper_um, c.valid)]
    paths.append(out.write_csv("forecast_curves.csv",
                               ["experiment", "at", "unit", "depth_um", "lower_um", "upper_um",
                                "conf_lower_um", "conf_upper_um", "valid"], crows))
    paths += plot_fans(out, res)
    paths += plot_profiles(out, study, res)
    return paths


def plot_fans(out, res):
    """fan_<experiment>.png: measured points (trained / held out), forecast and both bands."""

    pl = plt()
    paths = []
    last_at = max(p.at for p in res.predictions)
    lives = {x.experiment: x for x in res.life}
    for name, c in res.curves.items():
        fig, ax = pl.subplots(figsize=(7, 4.2))
        life = lives.get(name)
        # the chart reaches the life (central, and the band's far edge where found) when it
        # lies within a few times the forecast range, so the question "when?" has a picture
        reach = None if life is None or life.at is None else (life.upper or life.at)
        top = reach * 1.05 if reach is not None and reach <= 4 * last_at else last_at
        m = (c.at <= top * 1.0001) & c.valid
        # and the first point past the layer, so that the line is seen to cross the limit
        past = np.flatnonzero(~c.valid & np.isfinite(c.depth_um) & np.isfinite(c.lower_um)
                              & (c.at <= top * 1.0001))
        if len(past):
            m[past[0]] = True
        x = np.r_[0.0, c.at[m]]
        # a NUTS band edge is +inf where enough draws have worn through: left open there
        upper = np.where(np.isfinite(c.upper_um), c.upper_um, np.nan)
        ax.fill_between(x, np.r_[0.0, c.lower_um[m]], np.r_[0.0, upper[m]],
                        color="tab:blue", alpha=0.18,
                        label=f"{res.level:.0%} prediction band (new measurement)")
        ax.fill_between(x, np.r_[0.0, c.conf_lower_um[m]], np.r_[0.0, c.conf_upper_um[m]],
                        color="tab:blue", alpha=0.35, label=f"{res.level:.0%} confidence band")
        ax.plot(x, np.r_[0.0, c.depth_um[m]], "-", color="tab:blue", lw=1.5, label="forecast")
        pts, mx, trained = res.measured.get(name, (np.zeros(0),) * 3)
        if len(pts):
            tr = np.asarray(trained, bool)
            ax.plot(pts[tr], mx[tr], "ko", ms=5, label="measured (trained on)")
            if (~tr).any():
                ax.plot(pts[~tr], mx[~tr], "s", color="tab:red", ms=6, mfc="none", mew=1.5,
                        label="measured (held out)")
        if res.train_until is not None:
            ax.axvline(res.train_until, color="0.4", ls=":", lw=1, label="--train-until")
        if life is not None and life.limit_um <= 1.2 * np.nanmax(c.upper_um[m]):
            ax.axhline(life.limit_um, color="tab:red", ls="--", lw=1, label="limit")
            if life.at is not None and life.at <= top:
                lo = life.lower if life.lower is not None else life.at
                hi = min(life.upper if life.upper is not None else top, top)
                ax.axvspan(lo, hi, color="tab:red", alpha=0.12, lw=0,
                           label=f"life {life.at:.4g} [{lo:.4g}, "
                                 f"{'n/a' if life.upper is None else f'{hi:.4g}'}] {res.unit}")
        ax.set_xlabel(f"{res.unit}")
        ax.set_ylabel("maximum wear depth [µm]")
        ax.set_title(f"{name}: forecast ({res.method}), trained "
                     + (f"until {res.train_until:g} {res.unit}" if res.train_until else
                        "on all data"))
        ax.set_xlim(0, top * 1.02)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="upper left")
        fig.tight_layout()
        p = out.savefig(fig, f"fan_{name}.png")
        pl.close(fig)
        paths.append(p)
    return paths


def plot_profiles(out, study, res):
    """profile_<experiment>.png (crank-slider studies): the profile at the last --at point."""
    if timed(study.config):
        return []

    pl = plt()
    paths = []
    for name, pr in res.profiles.items():
        a = np.r_[pr["angle_deg"], 360.0]

        def closed(v):
            return np.r_[v, v[0]]

        fig, ax = pl.subplots(figsize=(7, 4))
        ax.fill_between(a, closed(pr["lower_um"]), closed(pr["upper_um"]), color="tab:blue",
                        alpha=0.18, label=f"{res.level:.0%} prediction band")
        ax.fill_between(a, closed(pr["conf_lower_um"]), closed(pr["conf_upper_um"]),
                        color="tab:blue", alpha=0.35, label=f"{res.level:.0%} confidence band")
        ax.plot(a, closed(pr["depth_um"]), "-", color="tab:blue", label="forecast")
        e = next(x for x in study.experiments if x.name == name)
        if e.profile is not None:
            r = np.asarray(e.profile.revolutions)
            hit = np.isclose(r, pr["at"])
            if hit.any():
                xs, ys = np.degrees(e.profile.angle[hit]) % 360, e.profile.depth[hit] * 1e6
                k = thinned(xs, ys)
                ax.plot(xs[k], ys[k], "o", ms=2.5, color="tab:red",
                        label=thinned_label("measured at this count", len(xs)))
        ax.set_xlim(0, 360)
        ax.set_xticks(range(0, 361, 45))
        ax.set_xlabel("bushing angle θ [deg] (from B→D, counter-clockwise)")
        ax.set_ylabel("wear depth [µm]")
        ax.set_title(f"{name}: profile at {pr['at']:g} {res.unit}")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
        fig.tight_layout()
        p = out.savefig(fig, f"profile_{name}.png")
        pl.close(fig)
        paths.append(p)
    return paths


def summary_text(res) -> str:
    lines = loud_lines(res.flags)  # answers outside the model first
    lines.append(f"forecast ({res.method}, level {res.level:g}): noise {res.noise_um:.3g} µm "
                 f"({'given' if res.noise_given else f'estimated, {res.dof:.3g} dof'}), "
                 f"quantile {res.quantile:.3g}")
    for name, v in res.parameters.items():
        lines.append(f"  {name} = {v['value']:.5g} ± {v['stderr'] or float('nan'):.2g}")
    lines.append(f"{'experiment':<20}{'at':>10}  {'depth_um':>10}  {'band_um':>21}  measured")
    for p in res.predictions:
        m = "" if p.measured_um is None else f"{p.measured_um:.4g}"
        lines.append(f"{p.experiment:<20}{p.at:>10g}  {p.depth_um:>10.4g}  "
                     f"[{p.lower_um:>9.4g}, {p.upper_um:>9.4g}]  {m}")
    for x in res.life:
        if x.at is None:
            lines.append(f"life {x.experiment}: {x.reason}")
        else:
            def f(v):
                return "n/a" if v is None else f"{v:.4g}"
            lines.append(f"life {x.experiment}: {x.limit_um:g} µm reached at {f(x.at)} "
                         f"[{f(x.lower)}, {f(x.upper)}] {x.unit} (each within "
                         f"{f(x.numerical_error_bound)} {x.unit} of the model's crossing)")
    integ = res.extra.get("integration")
    if integ and integ["integrator"] == "adaptive":
        lines.append(f"integration (adaptive) of the forecast: error estimate "
                     f"{float(integ['error_estimate_um']):.3g} µm (tolerance "
                     f"{integ['tolerance_um']:g} µm) in {integ['steps']} steps")
    lines += [f"flag: {f}" for f in res.flags]
    return "\n".join(lines)


class Predict(Verb):
    fits_data = True
    name = "predict"
    help = "forecast wear and remaining life with bands"
    takes_json = True

    def add_arguments(self, r):
        r.add_argument("--at", required=True,
                       help="comma-separated forecast points: revolutions (crank-slider) or "
                            "hours (oscillating joint)")
        r.add_argument("--train-until", default=None,
                       help="fit only the measurements at or before this count (same unit)")
        r.add_argument("--level", default="0.9", help="central probability of the bands")
        r.add_argument("--limit-um", default=None,
                       help="depth limit for the life estimate [µm] (default: layer "
                            "thickness)")
        r.add_argument("--method", default="laplace",
                       help="laplace (default), nuts, or importance (PSIS importance sampling "
                            "from the Laplace fit: forward runs only, k-hat says when to "
                            "prefer nuts)")
        r.add_argument("--fit", default=None, help="parameters to fit, as for calibrate")
        r.add_argument("--noise-um", default=None,
                       help="measurement noise σ [µm] if known (default: from the residuals)")
        r.add_argument("--draws", default=None,
                       help="nuts: posterior draws per chain (default 500); importance: "
                            "draws per batch at most (default 1000)")
        r.add_argument("--ess", default=None,
                       help="importance: stop drawing once every parameter's effective "
                            "sample size reaches this (and R-hat <= 1.01, k-hat <= 0.5; "
                            "default 400); 0: all --draws")
        r.add_argument("--warmup", default="300", help="nuts: warm-up steps per chain")
        r.add_argument("--chains", default="2",
                       help="nuts: chains; importance: independent batches (R-hat between "
                            "them)")
        r.add_argument("--seed", default="0", help="nuts, importance: random seed")
        r.add_argument("--predictive-draws", default="200",
                       help="nuts, importance: posterior draws the forecast is run at (each "
                            "a full forecast)")
        r.add_argument("--max-minutes", default="20",
                       help="nuts, importance: refuse when the estimated run time exceeds "
                            "this")

    def options(self, args):
        opts = {"at": parse_at(args.at),
                "train_until": number("--train-until", args.train_until, positive=True),
                "level": number("--level", args.level, lo=0, hi=1),
                "limit_um": number("--limit-um", args.limit_um, positive=True),
                "noise_um": number("--noise-um", args.noise_um, positive=True)}
        if args.method not in ("laplace", "nuts", "importance"):
            raise InputError(f"--method: expected laplace, nuts or importance, got "
                             f"{args.method!r}")
        check_method_packages(args.method)  # before any file is read or model built
        if args.ess is not None and args.method != "importance":
            raise InputError(f"--ess: only with --method importance (got --method "
                             f"{args.method})")
        nuts = None
        if args.method in ("nuts", "importance"):
            default = "500" if args.method == "nuts" else "1000"
            nuts = dict(draws=number("--draws", args.draws or default, positive=True,
                                     integer=True),
                        chains=number("--chains", args.chains, positive=True, integer=True),
                        seed=number("--seed", args.seed, integer=True, nonneg=True,
                                    hi=2 ** 32),
                        max_minutes=number("--max-minutes", args.max_minutes, positive=True),
                        n_predictive=number("--predictive-draws", args.predictive_draws,
                                            positive=True, integer=True))
            if args.method == "importance":
                nuts["ess_target"] = number("--ess", args.ess or "400", nonneg=True,
                                            integer=True)
            if args.method == "nuts":
                nuts["warmup"] = number("--warmup", args.warmup, positive=True, integer=True)
        return {"kw": opts, "nuts": nuts, "method": args.method, "fit": args.fit}

    def resolve(self, study, opts):

        # the flags against the ranges of what they stand for (revolutions or hours, noise)
        osc = timed(study.config)
        count = "experiment.hours" if osc else "experiment.revolutions"
        kw = opts["kw"]
        for at in kw["at"]:
            check_value("--at", count, at, preset=study.preset,
                        name=f"--at ({'hours' if osc else 'revolutions'})")
        if kw["train_until"] is not None:
            check_value("--train-until", count, kw["train_until"], preset=study.preset,
                        name=f"--train-until ({'hours' if osc else 'revolutions'})")
        if kw["noise_um"] is not None:
            check_value("--noise-um", "fit.noise_um", kw["noise_um"], preset=study.preset,
                        name="--noise-um")
        opts["keys"] = study_fit_keys(study, opts["fit"])

    def outputs(self, study, opts):
        return predict_outputs(study, opts["method"])

    def work_study(self, study, opts):
        """The study run to its forecast horizon: the last `--at` point, and the life's
        search up to `LIFE_HORIZON` x the last measured count."""


        osc = timed(study.config)
        exps = []
        for e in study.experiments:
            pts = e.snapshot_points
            last = float(max(pts)) if pts else float((e.hours if osc else e.revolutions) or 0)
            top = max(max(opts["kw"]["at"]), LIFE_HORIZON * last)
            exps.append(replace(e, hours=top) if osc else replace(e, revolutions=top))
        return study.with_experiments(exps)

    def length_from(self, study, opts):
        """`--at` when its largest point sets the forecast's length (not the study's)."""

        osc = timed(study.config)
        at = max(opts["kw"]["at"])
        last = max((max(e.snapshot_points) if e.snapshot_points else
                    float((e.hours if osc else e.revolutions) or 0))
                   for e in study.experiments)
        if at >= LIFE_HORIZON * last:
            return f"`--at` (its largest point, {at:g} {'hours' if osc else 'revolutions'})"
        return (f"the life search ({LIFE_HORIZON:g}x the last measured "
                f"{'hours' if osc else 'revolutions'}, {last:g}: lower the study's)")

    def tangents(self, study, opts):
        return fit_columns(study, opts["keys"])

    def run(self, study, out, opts):

        for line in amplification_warnings(study):
            print(line, file=sys.stderr, flush=True)
        args, nuts = opts["args"], opts["nuts"]
        t0 = time.perf_counter()
        if nuts is not None:
            nuts["out"] = out
        kw = dict(opts["kw"])
        res = _predict.predict(study, kw.pop("at"), method=opts["method"], fit_spec=args.fit,
                               verbose=True, nuts_options=nuts, **kw)
        print(f"predict: took {time.perf_counter() - t0:.1f} s", file=sys.stderr, flush=True)
        nuts_block = (res.extra.get(opts["method"]) if isinstance(res.extra, dict)
                      else None)
        for flag in (nuts_block or {}).get("flags", []):
            if flag not in res.flags:  # the sampler's own warnings (a non-finite R-hat)
                res.flags.append(flag)
        doc = res.to_json()
        written = [out.write_json("prediction.json", doc)]
        if out.json_file is not None:
            written.append(out.write_json_file(doc))
        written += write_outputs(out, study, res)
        print(summary_text(res))
        print(f"wrote {written[0]}; tables and plots in {out.root}")
        return res
