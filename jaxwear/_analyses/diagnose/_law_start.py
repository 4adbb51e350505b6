"""Starts of the law search's fits from the shape's refitted correction (issue 43): the
laws of the grammar fitted, without any run of the wear loop, to the rate factor that the
shape's correction reached through the loop, over the states the data met.

Why: the pre-screen (`_law.prescreen`) is first order in the law's strength (1 + AΦ ≈
exp(AΦ)) and sees one variable at a time; a law that doubles the rate (the generator's PV
step: A = 1) is far outside that, and a product of two variables is not a sum of
one-variable shapes at all. Measured on the generator's PV step (paper's five experiments,
study 48 x 72): from the pre-screen's constants the step in the sliding speed started at
an RMSE of 0.852 µm (the linearised strength overshoots) and ended at 0.412 after its ten
evaluations, where the shape's correction along the sliding speed and the pressure
reached 0.317. The shape's correction, refitted through the loop, is the nonlinear answer
the law should approximate: exp(Σ_k g_k(z_k)) over its carriers (the factor form).

1. **The states met** (`joint_states`): every state variable at every step and node of one
   cycle at the start, half-way and the end of each experiment, at the fit's answer (the
   same cycles as the shape's knots, `_shape_design.state_knots`), each point weighted by
   its wear rate, scaled so that an experiment's points weigh as much as the wear it made
   (its deepest profile's area). Jointly, not variable by variable: a product of two
   terms is judged where the two variables occur together.
2. **The curve** (`shape_factor`, `Curve`): y = exp(Σ_k g_k(z_k)) at those points, summed
   as the rows see it: per node over each cycle, the shape's wear Σ w y against the
   law's c Σ w (1 + A Φ).
3. **The fit** (`curve_fit`): every law of the grammar's grid (`_law.single_laws`), and
   every product of two of them, by least squares in (c, cA) (linear, A ≥ 0); the best
   few, their continuous constants then refined by `scipy.optimize.least_squares` (c and
   A solved inside: variable projection). The through-loop fit then starts at those
   constants, with K_d first scaled to the data (`fit_masked`'s `rescales`).
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
from scipy.optimize import least_squares

from jaxwear._analyses.diagnose._shape_design import _cycle_states, _load_history_jit
from jaxwear._physics.effects.law import (
    HINGE_MIN_EXPONENT,
    KIND_CONSTANTS,
    LAW_VARIABLES,
    LawSpec,
    law_phi_numpy,
)
from jaxwear._physics.effects.shape import ShapeVariable

STATE_FRACTIONS = (0.0, 0.5, 1.0)  # of each experiment's sliding and final depth
# the bounds of the normalised constants (`effects.law._parameters`)
BOUNDS = {"a": (-3.0, 6.0), "x0": (-5.0, 50.0), "w": (1e-3, 10.0), "b": (-50.0, 50.0)}


@dataclasses.dataclass(frozen=True)
class CurveFit:
    """A law fitted to the shape's curve (`Curve`): the law (its strength A), c (the
    level: K_d's factor on the curve's) and the residual left, relative to that of a
    level alone (0: the law follows the correction exactly, 1: not at all)."""

    law: LawSpec
    kd_scale: float
    residual: float


def joint_states(model, fit, names=LAW_VARIABLES):
    """({name: (n,)}, weights (n,), groups (n,)) of the states met at `fit`'s answer
    (module docstring, step 1): the points with wear; `groups` numbers each (cycle, node)
    whose wear over the cycle the points of that group make."""
    ext = model.ext
    cfg = ext.cfg.replace(shape=None)
    P = ext.batched_params(jnp.asarray(fit.ev.u))
    snaps = np.asarray(fit.ev.snaps)  # (E, S, N) µm
    zs = {n: [] for n in names}
    ws, gs = [], []
    g0 = 0
    for e in range(snaps.shape[0]):
        p = jax.tree_util.tree_map(lambda x: x[e], P)
        hist = _load_history_jit(p, cfg)
        total = float(fit.ev.sliding_m[e])
        last = np.clip(snaps[e, -1], 0.0, None)
        w_e, g_e, z_e = [], [], {n: [] for n in names}
        for r in range(hist.load.shape[0]):
            for f in STATE_FRACTIONS:
                z, rate = _cycle_states(p, cfg, hist, r, jnp.asarray(f * last * 1e-6),
                                        jnp.asarray(f * total))
                rate = np.asarray(rate)
                w_e.append(rate.ravel())
                g_e.append((g0 + np.broadcast_to(np.arange(rate.shape[1]), rate.shape)).ravel())
                g0 += rate.shape[1]
                for n in names:
                    z_e[n].append(np.asarray(z[n]).ravel())
        w_e = np.clip(np.concatenate(w_e), 0.0, None)
        s = float(w_e.sum())
        if not s > 0:
            continue
        ws.append(w_e * (max(float(last.sum()), 1e-12) / s))
        gs.append(np.concatenate(g_e))
        for n in names:
            zs[n].append(np.concatenate(z_e[n]))
    if not ws:
        return {}, np.zeros(0), np.zeros(0, int)
    w = np.concatenate(ws)
    keep = np.flatnonzero(w > 0)
    g = np.unique(np.concatenate(gs)[keep], return_inverse=True)[1]
    return ({n: np.concatenate(v)[keep] for n, v in zs.items()}, w[keep] / w[keep].sum(),
            g.ravel())


def shape_factor(correction: dict, Z: dict):
    """y (n,): the shape's refitted factor exp(Σ_k g_k(z_k)) at the states `Z`,
    normalised to a weighted mean of 1 by the caller; None where the correction is not a
    factor or a carrier is not among `Z`."""
    if not correction or correction.get("form") != "factor":
        return None
    g = 0.0
    for v in correction.get("variables", ()):
        if v["form"] != "factor" or v["name"] not in Z:
            return None
        var = ShapeVariable(v["name"], int(v["size"]), tuple(v["knots"]), "factor")
        B = np.asarray(var.basis(np.asarray(Z[v["name"]], float), xp=np))
        g = g + B @ np.asarray(v["coefficients"], float)
    return np.exp(np.clip(g, -30.0, 30.0)) if not np.isscalar(g) else None


class Curve:
    """The shape's curve over the states met, summed as the rows see it: per group (a
    node over one cycle) the wear R_g = Σ w, the shape's T_g = Σ w y; a law's F_g = Σ w Φ
    (module docstring, step 3). Why per node over the cycle rather than per state: a depth
    is the wear summed over the cycle, so a law may trade a little more here for a little
    less there within one cycle at no cost in the rows, and a state with little wear
    where the spline's exp(g) is large (it spans 0.16 to 20 on the PV step) weighs no more
    than its wear."""

    def __init__(self, Z: dict, w, groups, y):
        order = np.argsort(groups, kind="stable")
        self.Z = {k: np.asarray(v)[order] for k, v in Z.items()}
        self.w = np.asarray(w)[order]
        g = np.asarray(groups)[order]
        self.starts = np.flatnonzero(np.r_[True, g[1:] != g[:-1]])
        self.R = self.sum(np.ones_like(self.w))
        self.T = self.sum(np.asarray(y)[order])
        c0 = float(self.R @ self.T) / float(self.R @ self.R)
        self.sse0 = float(np.sum((self.T - c0 * self.R) ** 2))

    def sum(self, values):
        """Σ over each group of w · values (..., n) -> (..., G)."""
        return np.add.reduceat(values * self.w, self.starts, axis=-1)

    def phis(self, laws):
        return _phis(laws, self.Z)

    def lin(self, F):
        """T ≈ c R + b F per row of F (L, G), b ≥ 0: (c, b, SSE) (L,)."""
        R, T = self.R, self.T
        S_RR, S_RT, S_TT = R @ R, R @ T, T @ T
        S_RF, S_FF, S_FT = F @ R, np.sum(F * F, axis=-1), F @ T
        det = S_RR * S_FF - S_RF * S_RF
        ok = det > 1e-12 * np.maximum(S_RR * S_FF, 1e-300)
        b = np.maximum(np.where(ok, (S_RR * S_FT - S_RF * S_RT) / np.where(ok, det, 1.0),
                                0.0), 0.0)
        c = (S_RT - b * S_RF) / S_RR
        sse = S_TT - 2 * c * S_RT - 2 * b * S_FT + c * c * S_RR + 2 * c * b * S_RF + b * b * S_FF
        return c, b, np.maximum(sse, 0.0)


def _phis(laws, Z):
    n = len(next(iter(Z.values())))
    out = []
    for law in laws:
        with np.errstate(all="ignore"):
            phi = law_phi_numpy(law, Z) * np.ones(n)
        out.append(np.where(np.isfinite(phi), phi, 0.0))
    return np.array(out)


def _free(law: LawSpec) -> list[tuple[int, str]]:
    return [(k, c) for k, t in enumerate(law.terms) for c in KIND_CONSTANTS[t.kind]]


def _with(law: LawSpec, x) -> LawSpec:
    terms = list(law.terms)
    for (k, c), v in zip(_free(law), x):
        terms[k] = dataclasses.replace(terms[k], **{c: float(np.exp(v) if c == "w" else v)})
    return LawSpec(law.form, tuple(terms), law.strength)


def refine(law: LawSpec, curve: Curve, max_nfev: int = 200) -> tuple[LawSpec, float, float]:
    """`law`'s continuous constants refined on the curve (c and A solved inside): (the law
    with its strength A, c, SSE)."""
    free = _free(law)
    x0 = np.array([math.log(getattr(law.terms[k], c)) if c == "w"
                   else getattr(law.terms[k], c) for k, c in free])
    lo = np.array([math.log(BOUNDS[c][0]) if c == "w" else
                   (HINGE_MIN_EXPONENT if c == "a" and law.terms[k].kind == "hinge"
                    else BOUNDS[c][0]) for k, c in free])
    hi = np.array([math.log(BOUNDS[c][1]) if c == "w" else BOUNDS[c][1] for k, c in free])
    x0 = np.clip(x0, lo + 1e-9, hi - 1e-9)

    def resid(x):
        F = curve.sum(curve.phis([_with(law, x)]))
        c, b, _ = curve.lin(F)
        return curve.T - c[0] * curve.R - b[0] * F[0]

    x = x0
    if len(free):
        try:
            x = least_squares(resid, x0, bounds=(lo, hi), max_nfev=max_nfev, x_scale="jac").x
        except (ValueError, FloatingPointError):
            x = x0
    out = _with(law, x)
    c, b, sse = curve.lin(curve.sum(curve.phis([out])))
    c0 = float(c[0]) if c[0] > 0 else 1.0
    return dataclasses.replace(out, strength=float(b[0]) / c0), c0, float(sse[0])


def curve_fit(singles: dict, curve: Curve, first: str, second: str | None = None,
              top: int = 3) -> CurveFit | None:
    """The best law of the grammar on `curve` (module docstring, step 3): along `first`
    alone (`second` None), or the product of a law of `first` and one of `second`;
    `singles`: {variable: its grid of one-term laws (`_law.single_laws`)}. The `top` best
    of the grid are refined, the best of them returned."""
    if first not in singles or (second is not None and second not in singles):
        return None
    if not curve.sse0 > 0:
        return None
    L1 = singles[first]
    P1 = curve.phis(L1)
    if second is None:
        _, _, sse = curve.lin(curve.sum(P1))
        starts = [L1[i] for i in np.argsort(sse)[:top]]
    else:
        L2 = singles[second]
        P2 = curve.phis(L2)
        sse = np.array([curve.lin(curve.sum(P1[i] * P2))[2] for i in range(len(L1))])
        flat = np.argsort(sse, axis=None)[:top]
        starts = [LawSpec(L1[i].form, (L1[i].terms[0], L2[j].terms[0]))
                  for i, j in zip(*np.unravel_index(flat, sse.shape))]
    best = None
    for law in starts:
        found, c, sse = refine(law, curve)
        if best is None or sse < best[2]:
            best = (found, c, sse)
    if best is None or not best[0].strength > 0:
        return None
    return CurveFit(best[0], best[1], math.sqrt(best[2] / curve.sse0))
