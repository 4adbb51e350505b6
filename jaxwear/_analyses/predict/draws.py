"""Forecasts of posterior draws, for the sampling methods of `predict` (NUTS, importance).

Each chosen draw's parameter vector u is run forward (`_residual.forward_run`: no
Jacobian, one compiled function for every draw, its attempt count raised where a draw needs
more) over the forecast problem's points. Where the fit's answer is corrected to a finer
resolution (`_calibrate.correct_to_finer`), the draws are run at the fit's own level and
corrected as its rows are: by the difference between the finer level's forecast and this
level's at the answer (on the finer level's nodes), a fixed snapshot correction.

Draws run on `workers` threads (JAX releases the interpreter while a compiled run
executes, so two draws run at once on two cores).
"""

from __future__ import annotations

import math
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from jaxwear._analyses.predict.snapshots import fill_past_stop, on_nodes
from jaxwear._core.errors import ModelFailure
from jaxwear._core.log import log as _log
from jaxwear._inference.evaluation import forward_run


def run_forward(fp, u, what: str = "a posterior draw's forecast"):
    """(snapshots (E, S, N) [µm] with +inf past an early stop, error estimate [µm], steps,
    the problem it ran with) at u; a run whose integration cannot reach its end (after 3
    doublings of the attempt count) raises RuntimeError naming the count."""
    first = fp.schedule.attempts
    f = forward_run(fp, u, doublings=3, worn_ok=True)
    if not math.isfinite(f.error_um):
        raise ModelFailure(f"predict: {what} ran out of integration attempts: "
                           f"{f.model.schedule.attempts} attempted steps "
                           f"({f.model.schedule.attempts / max(first, 1):g}x the first "
                           f"estimate, {first}) did not reach its end")
    return f.snaps, f.error_um, f.steps, f.model


def integration_block(schedule, integ: dict) -> dict:
    """The JSON "integration" block of the posterior draws' forecasts (the form of
    laplace's): the largest error estimate (`integ["error"]` [m]) and step count over the
    draws."""
    adaptive = schedule.adaptive
    err = integ["error"] * 1e6
    return {"integrator": "adaptive" if adaptive else "paper",
            "error_estimate_um": (err if math.isfinite(err) else "inf") if adaptive else None,
            "steps": int(integ["steps"]),
            "tolerance_um": schedule.tolerance_um}


def new_measurements(max_um, past, noise_um, rng):
    """Posterior-predictive new measurements of the maximum depth (D, E, S) [µm]: each
    draw's depth `max_um` plus its noise `noise_um` (D,). Where `past` (D, E, S) the draw had
    stopped, worn through the layer (≥ every allowed limit), before that point: a new
    measurement there is past the limit (+inf), not the depth the draw stopped at plus noise,
    which, being only a lower bound, kept the band's lower edge under the limit for good
    (measured on the boom: "no upper bound" for the life once the grid was fine enough to
    stop the draws within a micrometre of the layer)."""
    new = max_um + noise_um[:, None, None] * rng.standard_normal(max_um.shape)
    return np.where(past, np.inf, new)


class DrawForecasts:
    """The forecasts of draws `u` (D, p) (the training problem's coordinates) with noise
    levels `noise` (D,) [µm]; `u_fit` (p,) the answer. Call with a forecast problem (and
    the corrected level's, or None) for the draws dict: `max_um` (D, E, S), `new_um`
    (D, E, S), `snapshots_um` (D, E, S, N), `noise` (D,); `integration` holds the last
    call's JSON block (largest error estimate and step count over the draws)."""

    def __init__(self, u, noise, u_fit, *, seed: int = 0, workers: int = 2,
                 verbose: bool = False, label: str = "predict"):
        self.u = np.asarray(u, np.float64)
        self.noise = np.asarray(noise, np.float64)
        self.u_fit = np.asarray(u_fit, np.float64)
        self.seed, self.workers, self.verbose, self.label = seed, workers, verbose, label
        self.integration: dict = {}

    def __call__(self, fp, ff=None) -> dict:
        # the answer first: it settles the attempt count every draw then shares (and the
        # correction to the finer level, where the answer has one)
        s0, _, _, fp = run_forward(fp, self.u_fit)
        corr = None
        if ff is not None:
            f0 = run_forward(ff, self.u_fit)[0]
            corr = fill_past_stop(f0)[0] - on_nodes(fill_past_stop(s0)[0], f0.shape[2])
        integ = {"error": 0.0, "steps": 0}
        t0 = last = time.perf_counter()
        done = [0]

        def one(u):
            nonlocal last
            s, err, steps, _ = run_forward(fp, u)
            done[0] += 1
            if time.perf_counter() - last > 30:
                last = time.perf_counter()
                _log(self.verbose, f"{self.label}: forecast {done[0]}/{len(self.u)} draws "
                                   f"({last - t0:.0f} s)")
            return s, err, steps

        with ThreadPoolExecutor(max_workers=max(1, self.workers)) as pool:
            runs = list(pool.map(one, self.u))
        mx, prof, past = [], [], []
        for s, err, steps in runs:
            integ["error"] = max(integ["error"], err * 1e-6)
            integ["steps"] = max(integ["steps"], steps)
            past.append(np.isinf(s).any(axis=-1))  # (E, S): after the draw's early stop
            s = fill_past_stop(s)[0]
            if corr is not None:
                s = on_nodes(s, corr.shape[2]) + corr
            mx.append(s.max(axis=-1))
            prof.append(s)
        mx = np.stack(mx)
        new = new_measurements(mx, np.stack(past), self.noise,
                               np.random.default_rng(self.seed))
        self.integration.clear()
        self.integration.update(integration_block(fp.schedule, integ))
        return {"max_um": mx, "new_um": new, "snapshots_um": np.stack(prof),  # (D, E, S, N)
                "noise": self.noise}
