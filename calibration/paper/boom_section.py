"""Table 5, the boom joint: the validation page's section (reproduce.py)."""

from __future__ import annotations

import csv
import math
import tempfile
import time
from pathlib import Path

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from page import DATA, NODES, Page, _pct, _plt, _timed

import jaxwear as jw
from jaxwear._physics.config import boom_config
from jaxwear._physics.schedule import Schedule
from jaxwear._physics.wear import build_schedule, check_result

# ----------------------------------------------------------------------------------------
# Table 5: the boom joint
# ----------------------------------------------------------------------------------------

BOOM_NUMERICS = {"nodes": NODES, "steps_per_rev": 72, "revolutions_per_update": 10}


def _read_table5():
    with DATA.open() as f:
        rows = list(csv.DictReader(f))
    return {k: np.array([float(r[k]) for r in rows]) for k in rows[0]}


def _boom_study(tmp: Path, t5) -> Path:
    """A temporary study: boom preset, the five measured maximum depths as history."""
    with (tmp / "history.csv").open("w") as f:
        f.write("hours,depth_mm\n")
        for t, d in zip(t5["hours"], t5["depth_mm"]):
            f.write(f"{t:g},{d:g}\n")
    num = "\n".join(f"{k} = {v}" for k, v in BOOM_NUMERICS.items())
    (tmp / "study.toml").write_text(
        '[model]\npreset = "boom"\n\n[numerics]\n' + num + "\n\n"
        '[[experiment]]\nname = "boom"\nhistory = "history.csv"\n')
    return tmp / "study.toml"


def _fit_kd_1d(p0, cfg, hours, measured_um, M):
    """Fallback: least squares over the single scale K_d (golden section on log K_d)."""

    def rss(log_kd):
        p = p0.with_values({"K_d_per_Pa": math.exp(log_kd)})
        res = jw.simulate(p, cfg, hours=float(hours.max()), snapshots=tuple(hours), M=M,
                          check=False)
        pred = np.asarray(res.snapshots).max(axis=1) * 1e6
        return float(np.sum((pred - measured_um) ** 2))

    lo, hi = math.log(1e-14), math.log(2e-12)
    g = (math.sqrt(5) - 1) / 2
    a, b = hi - g * (hi - lo), lo + g * (hi - lo)
    fa, fb = rss(a), rss(b)
    for _ in range(30):
        if fa < fb:
            hi, b, fb = b, a, fa
            a = hi - g * (hi - lo)
            fa = rss(a)
        else:
            lo, a, fa = a, b, fb
            b = lo + g * (hi - lo)
            fb = rss(b)
    return math.exp(0.5 * (lo + hi))


def _pad_schedule(sc: Schedule, updates: int) -> Schedule:
    """`sc` extended with empty updates (M = 0) to `updates`, so that schedules of different
    M share one compiled wear loop."""
    extra = updates - sc.updates
    return Schedule(
        cycles=jnp.concatenate([sc.cycles, jnp.zeros(extra)]),
        regime=jnp.concatenate([sc.regime, jnp.zeros(extra, jnp.int32)]),
        snapshot=jnp.concatenate([sc.snapshot, jnp.full(extra, sc.n_snapshots, jnp.int32)]),
        cycle_end=jnp.concatenate([sc.cycle_end, jnp.full(extra, sc.cycle_end[-1])]),
        n_snapshots=sc.n_snapshots)


_boom_loop = eqx.filter_jit(jw.wear_loop)


def section_boom(page: Page):
    plt = _plt()
    t5 = _read_table5()
    hours = t5["hours"]
    meas_um = t5["depth_mm"] * 1e3
    method = "jaxwear._inference.calibrate.calibrate(study, \"K_d\")"
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        try:
            from jaxwear._inference.calibrate import calibrate
            from jaxwear._study.study import load_study

            study = load_study(_boom_study(Path(tmp), t5))
            fit = calibrate(study, "K_d")
            kd = float(fit.values[list(fit.names).index("K_d_per_Pa")])
            kd_se = float(fit.stderr[list(fit.names).index("K_d_per_Pa")])
            p0 = study.params(study.experiments[0])
            cfg = study.config
            fit_msg = fit.message
            fit_pred_um = np.asarray(fit.predicted_um)
        except Exception as err:  # the calibration module is being reworked: fall back
            method = (f"own 1-D least squares (golden section on log K_d with jw.simulate), "
                      f"because calibrate failed: {type(err).__name__}: {err}")
            p0 = jw.preset("boom")
            cfg = boom_config(nodes=BOOM_NUMERICS["nodes"],
                              steps_per_rev=BOOM_NUMERICS["steps_per_rev"])
            kd = _fit_kd_1d(p0, cfg, hours, meas_um, BOOM_NUMERICS["revolutions_per_update"])
            kd_se, fit_msg = float("nan"), "golden section, 30 iterations"
            fit_pred_um = None
    t_fit = time.perf_counter() - t0
    p = p0.with_values({"K_d_per_Pa": kd})
    M = BOOM_NUMERICS["revolutions_per_update"]
    # One compiled wear loop for four update sizes: the M used, M/2 and 2M (convergence in
    # M, eq 23) and the study default 100; hourly snapshots for the curve.
    curve_h = tuple(float(h) for h in range(1, 26))
    Ms = (M, M / 2, 2 * M, 100)
    scheds = [build_schedule(p, cfg, hours=25.0, snapshots=curve_h, M=m, pad=False)
              for m in Ms]
    U = max(sc.updates for sc in scheds)
    scheds = [_pad_schedule(sc, U) for sc in scheds]
    runs = [_boom_loop(p, cfg, sc) for sc in scheds]
    check_result(runs[0], cfg, "boom prediction")
    # The M/2 schedule is the longest, so its run is not padded: time that one.
    _, t_run = _timed(lambda: _boom_loop(p, cfg, scheds[1]).depth)
    at = [curve_h.index(float(h)) for h in hours]
    curve = np.asarray(runs[0].snapshots).max(axis=1) * 1e6
    ours = curve[at]
    fit_check = (float(np.max(np.abs(ours - fit_pred_um))) if fit_pred_um is not None
                 else float("nan"))
    m_err = [float(np.max(np.abs(np.asarray(r.snapshots).max(axis=1)[at] * 1e6 - ours)))
             for r in runs[1:3]]
    coarse = runs[3]
    coarse_um = np.asarray(coarse.snapshots).max(axis=1)[at] * 1e6
    coarse_rough = float(np.max(np.abs(np.diff(np.asarray(coarse.depth) * 1e6, 2))))
    fine_rough = float(np.max(np.abs(np.diff(np.asarray(runs[0].depth) * 1e6, 2))))

    paper_mm = t5["paper_predicted_mm"]
    rel = lambda pred, m: (m - pred) / m  # the paper's sign: (actual − predicted)/actual
    rows = []
    for i, t in enumerate(hours):
        rows.append([f"{i + 1} ({t:.0f} h)", f"{t5['depth_mm'][i]:.3f}", f"{paper_mm[i]:.3f}",
                     _pct(rel(paper_mm[i], t5["depth_mm"][i])), f"{ours[i] / 1e3:.3f}",
                     _pct(rel(ours[i] / 1e3, t5["depth_mm"][i])),
                     f"{t5['paper_compute_s'][i]:.1f}"])
    rmse = float(np.sqrt(np.mean((ours - meas_um) ** 2)))
    rmse_paper = float(np.sqrt(np.mean((paper_mm * 1e3 - meas_um) ** 2)))

    page.add("## Table 5: the concrete-pump boom joint", "",
             "> *Paper:* \"the predicted wear depth is smaller than the actual wear depth, but "
             "the relative error is small enough [...] along with the increase of wear time, "
             "the relative error of the predicted wear depth decreases\".", "",
             "Oscillating joint ([design §2](../design.md#s2)): bimetal bearing of Table 4 "
             "(double elastic layer), "
             "duty cycle 20° for 1 h then 1° for 4 h, five 5-h phases. The paper gives neither "
             f"the load nor the swing period: we use the boom preset's |W| = "
             f"{float(p.load) / 1e3:.0f} kN at θ_W0 = {math.degrees(float(p.load_angle)):.0f}° "
             f"and T_s = {float(p.swing_period):.0f} s (`jaxwear/_params.py`); only K_d·|W| "
             "is identifiable from depth-vs-time data. K_d is calibrated on the five measured "
             "depths (`calibration/paper/boom_table5.csv`, the paper's Table 5) "
             f"with {method}; {BOOM_NUMERICS['nodes']} nodes × "
             f"{BOOM_NUMERICS['steps_per_rev']} steps per swing, M = {M} swings per update.",
             "")
    page.table(["phase", "measured [mm]", "paper's prediction [mm]", "paper's rel. error",
                "ours (calibrated) [mm]", "our rel. error", "paper's time [s]"], rows)
    fig, ax = plt.subplots(figsize=(5.5, 3.2))
    ax.plot((0.0,) + curve_h, np.concatenate([[0.0], curve]) / 1e3, "k-", lw=1.2,
            label=f"ours, K_d = {kd:.3e} 1/Pa")
    ax.plot(hours, t5["depth_mm"], "s", color="tab:red", label="measured (Sany)")
    ax.plot(hours, paper_mm, "o", mfc="none", color="tab:blue", label="paper's prediction")
    ax.set(xlabel="time [h]", ylabel="maximum wear depth [mm]",
           title="Table 5: boom joint, depth vs time", xlim=(0, 26), ylim=(0, None))
    ax.legend(fontsize=7)
    fig.tight_layout()
    page.figure(fig, "table5_boom.png", "Table 5 here: measured maximum depth, the paper's "
                                        "prediction and our calibrated base model.")
    se_txt = f" ± {kd_se:.1e}" if math.isfinite(kd_se) else ""
    check_txt = (f"; our rerun reproduces its five predictions to {fit_check:.1e} µm"
                 if math.isfinite(fit_check) else "")
    page.add(f"Calibrated K_d = **{kd:.3e}{se_txt} 1/Pa** (fit: {fit_msg}; {t_fit:.1f} s "
             f"including compilation{check_txt}). RMSE over the five phases: ours "
             f"{rmse:.1f} µm, the paper's {rmse_paper:.1f} µm. One 25-h prediction "
             f"(M = {M / 2:g}, {scheds[1].updates} updates, hourly snapshots) takes "
             f"{t_run:.2f} s once compiled (paper: 11.0 s).", "",
             f"*Update size M (eq 23).* Halving M to {M / 2:g} changes the five depths by at "
             f"most {m_err[0]:.1e} µm: M = {M} is converged. Doubling it to {2 * M} changes "
             f"them by up to {m_err[1]:.2f} µm (close to the stability limit at this K_d). "
             "The study default M = 100 is past the stability limit "
             "of the explicit wear update on the stiff bimetal layer (a node worn a little "
             "deeper loses so much pressure per update that it overshoots): the depths "
             f"become {', '.join(f'{x / 1e3:.3f}' for x in coarse_um)} mm and the profile "
             f"turns jagged (largest second difference {coarse_rough:.1f} µm against "
             f"{fine_rough:.2f} µm at M = {M}). Hence M = {M} here.", "")
    our_err = [rel(o / 1e3, m) for o, m in zip(ours, t5["depth_mm"])]
    best = int(np.argmin(np.abs(our_err)))
    first_err, last_err = rel(ours[0] / 1e3, t5["depth_mm"][0]), rel(ours[-1] / 1e3,
                                                                      t5["depth_mm"][-1])
    page.add(f"**Result: partly agrees.** Like the paper's, our first phase is under-predicted "
             f"({_pct(first_err)}; paper {_pct(rel(paper_mm[0], t5['depth_mm'][0]))}) and the "
             f"error shrinks over the next phases (to {_pct(our_err[best])} in phase "
             f"{best + 1}). Unlike the paper's, ours does not stay below "
             f"the data: one K_d fitted to all five points makes the last phases over-predicted "
             f"({_pct(last_err)} at 25 h). The measured depth grows by "
             f"{meas_um[0]:.0f} µm in the first phase and "
             f"{np.mean(np.diff(meas_um)):.1f} µm per phase after; our base model by "
             f"{ours[0]:.0f} µm and {np.mean(np.diff(ours)):.1f} µm: its first phase runs "
             "faster (the unworn bore concentrates the load) but not as much faster as the "
             "measurement, which suggests running-in that the base Archard model lacks. The "
             "paper's own prediction has a first-phase excess too "
             f"({paper_mm[0] * 1e3:.0f} µm, then "
             f"{np.mean(np.diff(paper_mm)) * 1e3:.1f} µm per phase); with the load and swing "
             "period unknown we cannot tell where its excess comes from.", "")
    page.numbers["table5"] = {
        "method": method, "K_d_per_Pa": kd, "K_d_stderr": kd_se, "fit_time_s": t_fit,
        "hours": hours.tolist(), "measured_mm": t5["depth_mm"].tolist(),
        "paper_mm": paper_mm.tolist(), "ours_mm": (ours / 1e3).tolist(),
        "ours_rel_error": [rel(o / 1e3, m) for o, m in zip(ours, t5["depth_mm"])],
        "paper_rel_error": [rel(a, m) for a, m in zip(paper_mm, t5["depth_mm"])],
        "rmse_um": rmse, "rmse_paper_um": rmse_paper, "run_time_s": t_run,
        "half_M_max_change_um": m_err[0], "double_M_max_change_um": m_err[1],
        "M100_mm": (coarse_um / 1e3).tolist(),
        "M100_max_second_difference_um": coarse_rough,
        "max_second_difference_um": fine_rough, "rerun_vs_calibrate_um": fit_check}
