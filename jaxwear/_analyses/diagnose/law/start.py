"""The states met at a fit, for the law search (issue 43, 48): `joint_states` (every state
variable at every step and node of one cycle at five points of each experiment at the fit's
answer, the cycles of the shape's knots, `shape.design.state_knots`; weighted by the wear
rate, or by the steps for a deposit, scaled so that an experiment's states weigh as much as
the wear it made), `resample` (equal weights), the derived p·v's range (`derived_variables`:
p·v is met where p and v occur together, so its range is the joint one), and
`forward_rmse`, one forward run of a law model with K_d's level scaled to the data (a
start's check: the screen is first order in the strength).
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np

from jaxwear._analyses.diagnose.shape.design import (
    RANGE_QUANTILES,
    _cycle_states,
    _load_history_jit,
    _weighted_quantiles,
)
from jaxwear._physics.effects.law import (
    DERIVED,
    derived_states,
)

STATE_FRACTIONS = (0.0, 0.25, 0.5, 0.75, 1.0)  # of each experiment's sliding and final depth


def joint_states(model, fit, names=("pressure_MPa", "sliding_speed_m_per_s"),
                 deposit: bool = False):
    """({name: (n,)}, weights (n,), summing to 1) of the states met at `fit`'s answer where
    there is wear (module docstring); `deposit`: weighted by the steps instead (every
    step of every revolution alike: a deposit is made per step, where Archard wears
    little too: `shape.design.state_knots`)."""
    form = "deposit" if deposit else "factor"
    return states_by_form(model, fit, names, (form,)).get(form, ({}, np.zeros(0)))


def states_by_form(model, fit, names, forms=("factor", "deposit")) -> dict:
    """{form: (states, weights)} as `joint_states` for each of `forms`, the cycles solved
    once for all of them."""
    ext = model.ext
    cfg = ext.cfg.replace(shape=None)
    P = ext.batched_params(jnp.asarray(fit.ev.u))
    snaps = np.asarray(fit.ev.snaps)  # (E, S, N) µm
    zs = {n: [] for n in names}
    ws = {f: [] for f in forms}
    for e in range(snaps.shape[0]):
        p = jax.tree_util.tree_map(lambda x: x[e], P)
        hist = _load_history_jit(p, cfg)
        total = float(fit.ev.sliding_m[e])
        # the last snapshot computed (a forecast's layout leaves later ones NaN)
        done = [k for k in range(snaps.shape[1]) if np.all(np.isfinite(snaps[e, k]))]
        last = np.clip(snaps[e, done[-1]] if done else np.zeros(snaps.shape[2]), 0.0, None)
        rates, z_e = [], {n: [] for n in names}
        for r in range(hist.load.shape[0]):
            for f in STATE_FRACTIONS:
                z, rate = _cycle_states(p, cfg, hist, r, jnp.asarray(f * last * 1e-6),
                                        jnp.asarray(f * total))
                rates.append(np.asarray(rate).ravel())
                for n in names:
                    z_e[n].append(np.asarray(z[n]).ravel())
        rates = np.clip(np.concatenate(rates), 0.0, None)
        if not float(rates.sum()) > 0:
            continue
        for form in forms:
            w_e = np.ones(len(rates)) if form == "deposit" else rates
            # an experiment weighs as the wear it made (a deposit: as its sliding, the
            # revolutions it ran times their length)
            size = total if form == "deposit" else float(last.sum())
            ws[form].append(w_e * (max(size, 1e-12) / float(w_e.sum())))
        for n in names:
            zs[n].append(np.concatenate(z_e[n]))
    out = {}
    for form in forms:
        if not ws[form]:
            continue
        w = np.concatenate(ws[form])
        keep = w > 0
        out[form] = ({n: np.concatenate(v)[keep] for n, v in zs.items()},
                     w[keep] / w[keep].sum())
    return out


def resample(Z: dict, w, size: int, seed: int = 0) -> dict:
    """`size` states drawn from the weighted states `Z` ({name: (n,)}, weights `w`) by
    systematic resampling: equal weights after, so a least-squares fit over them is one
    over the weighted distribution."""
    if len(w) == 0:
        return {k: np.zeros(0) for k in Z}
    c = np.cumsum(np.asarray(w, float))
    c /= c[-1]
    u = (np.random.default_rng(seed).random() + np.arange(size)) / size
    idx = np.minimum(np.searchsorted(c, u), len(c) - 1)
    return {k: np.asarray(v)[idx] for k, v in Z.items()}


@dataclasses.dataclass(frozen=True)
class DerivedVariable:
    """A derived state's range for the grammar's grid (`law.search.single_laws` reads `name`,
    `lo`, `hi` and `at_coordinate`, as of a `ShapeVariable`): its wear-weighted quantiles
    over the states met, `knots` at t = 0, 1/Q, ..., 1 as the shape's."""

    name: str
    knots: tuple

    @property
    def lo(self) -> float:
        return float(self.knots[0])

    @property
    def hi(self) -> float:
        return float(self.knots[-1])

    def at_coordinate(self, t) -> np.ndarray:
        return np.interp(t, np.linspace(0.0, 1.0, len(self.knots)), np.asarray(self.knots))


def derived_variables(Z: dict, w) -> dict:
    """{name: `DerivedVariable`} of the `DERIVED` states whose variables `Z` has (p·v),
    over their wear-weighted range met (`RANGE_QUANTILES`, as the shape's knots)."""
    if not all(v in Z for _, parts in DERIVED.values() for v in parts):
        return {}
    Z = derived_states(Z)
    out = {}
    for name in DERIVED:
        q0, q1 = RANGE_QUANTILES
        zq = _weighted_quantiles(np.asarray(Z[name], float), w, np.linspace(q0, q1, 33))
        span = max(float(zq[-1] - zq[0]), abs(float(zq[0])) * 1e-3, 1e-12)
        zq = np.maximum.accumulate(zq) + np.arange(len(zq)) * span * 1e-9
        out[name] = DerivedVariable(name, tuple(float(v) for v in zq))
    return out


def forward_rmse(lm, measured) -> float:
    """RMSE [µm] of the law model `lm` at its start (one forward run), with K_d's level
    scaled to the data by least squares (depth is nearly proportional to K_d: the scale
    the fit's start then applies, `fit_masked`'s `rescales`); inf where it wore through."""
    d = np.asarray(lm.predict(np.zeros(len(lm.names))), float)
    m = np.asarray(measured, float)
    if not np.all(np.isfinite(d)) or not float(d @ d) > 0:
        return math.inf
    a = float(d @ m) / float(d @ d)
    return float(np.sqrt(np.mean((a * d - m) ** 2))) if a > 0 else math.inf
