"""The law search's screen of the whole grammar before any model run (issue 48 item 1):
every one- and two-term law (each kind along each variable, the derived p·v included, both
forms, constants on grids), ranked by the χ² its linearised response removes from the
shape's misfit, and the best few of distinct structure chosen for the loop.

The linearised response of a law. The shape's columns (`ShapeResult.linear["blocks"]`:
whitened, the fit's own parameters and the numerical error projected off) give the change
of the rows per B-spline coefficient of a correction along one variable. A law Φ of one or
two variables (p·v: of p and v) is not a function of one variable, so it is projected on
the additive space of its variables' splines, Φ(z) ≈ Σ_v B_v(z_v) c_v, by least squares
over the states met at the fit (`law.start.joint_states`: every node and step of cycles at
five points of each experiment, weighted by the wear for a factor and by the steps for a
deposit, resampled to equal weights); its response is then Σ_v A_v Z_v' c_v, first order
in its strength (1 + AΦ ≈ exp(AΦ) for a factor; a factor's level is K_d's, projected off
with the sum-zero coefficients). What the additive space cannot hold of a product (its
interaction) the screen does not see; the loop fits the law exactly.

Why the whole grammar and not the shape's best variable first: a law the shape's ranking
does not point at was never fitted (issue 48: an event deposit whose size depends on the
turn rate and the load, a form the grammar holds, was missed for a single power of the
turn rate, 1.21 x the noise where the right form reaches 1.01).

Why a few of distinct structure: the screen is first order and optimistic (the best of a
grid); the loop decides. Structures (form, kinds and variables) are ranked by the χ² drop
less ln(n) per fitted constant (BIC's price: the grid's choice of the constants is paid
for as if they were fitted); the best `PICKS` are fitted, the simplest of them always
among them (the front needs its simple end).
"""

from __future__ import annotations

import dataclasses
import itertools
import math

import numpy as np

from jaxwear._analyses.diagnose.law.start import derived_variables
from jaxwear._physics.effects.law import (
    DEPOSIT_LAW_VARIABLES,
    DERIVED,
    LAW_VARIABLES,
    LawSpec,
    law_phi_numpy,
)

SAMPLES = 3000  # states the projection is fitted over (resampled to equal weights)
PICKS = 3  # laws of distinct structure fitted through the loop at most (the cost: each ~20 runs)


def structure(law: LawSpec) -> tuple:
    """(form, (kind, variable) per term): what a law is apart from its constants."""
    return (law.form,) + tuple((t.kind, t.variable) for t in law.terms)


def parts(name: str) -> tuple:
    """The shape's variables a law variable is made of (p·v: p and v)."""
    return DERIVED[name][1] if name in DERIVED else (name,)


class Screen:
    """The projection of laws of one form on the shape's linearised system."""

    def __init__(self, linear: dict, form: str, Z: dict):
        blocks = linear["blocks"]
        rho = linear["rho"]
        self.form = form
        self.Z = Z
        self.H, self.B, self.g = {}, {}, {}
        names = LAW_VARIABLES if form == "factor" else DEPOSIT_LAW_VARIABLES
        for name in names:
            if name in DERIVED:
                continue
            label = name if form == "factor" else f"deposit:{name}"
            if label not in blocks or name not in Z:
                continue
            A, _, Zc, _, var = blocks[label]
            # response per B-spline coefficient: A over the block's coordinates Zc
            # (orthonormal columns: sum-zero for a factor, all for a deposit)
            self.H[name] = A @ np.asarray(Zc).T
            self.B[name] = np.asarray(var.basis(np.asarray(Z[name], float), xp=np))
            self.g[name] = self.H[name].T @ rho
        self.variables = {}
        for name in names:
            if name in DERIVED:
                if all(v in self.H for v in parts(name)):
                    n = len(Z[parts(name)[0]])
                    dv = derived_variables(Z, np.full(n, 1.0 / max(n, 1)))
                    if name in dv:
                        self.variables[name] = dv[name]
            elif name in self.H:
                label = name if form == "factor" else f"deposit:{name}"
                self.variables[name] = blocks[label][4]
        self._ops = {}

    def _op(self, names: tuple):
        """(P, g, G) of the additive space of `names`: the least-squares operator from Φ at
        the states to the splines' coefficients, H'ρ and H'H over those coefficients."""
        key = tuple(sorted(set(names)))
        if key not in self._ops:
            X = np.hstack([self.B[v] for v in key])
            P = np.linalg.pinv(X, rcond=1e-10)
            H = np.hstack([self.H[v] for v in key])
            g = np.concatenate([self.g[v] for v in key])
            self._ops[key] = (P, g, H.T @ H)
        return self._ops[key]

    def drops(self, F: np.ndarray, names) -> tuple[np.ndarray, np.ndarray]:
        """(χ² removed [σ²], least-squares strength ≥ 0) of laws whose Φ at the states are
        the columns of F (n, K), along the variables `names`; 0 where the strength would
        be negative or Φ is flat."""
        P, g, G = self._op(names)
        C = P @ F
        num = g @ C
        den = np.einsum("ik,ij,jk->k", C, G, C)
        ok = (den > 1e-300) & (num > 0) & np.all(np.isfinite(F), axis=0)
        amp = np.where(ok, num / np.where(ok, den, 1.0), 0.0)
        return np.where(ok, amp * num, 0.0), amp


def _phis(laws, Z) -> np.ndarray:
    return np.stack([law_phi_numpy(law, Z) * np.ones(len(next(iter(Z.values()))))
                     for law in laws], axis=1)


def screen_grammar(linear: dict, samples: dict, grids, forms=("factor", "deposit"),
                   bounded=None) -> list[tuple[float, LawSpec]]:
    """(χ² removed [σ²], the law at its least-squares strength) of every one- and two-term
    law of the grammar (module docstring), best first. `samples`: {form: {variable: (n,)}}
    states met, equal weights (`law.start.resample`); `grids`: (variable object, form)
    -> the one-term laws of the grid (`law.search.single_laws`); `bounded`: law -> "" or why it
    is refused (`law.search.unbounded`: only what no cap can bound): refused laws are not
    screened."""
    out = []
    for form in forms:
        Z = samples.get(form)
        if not Z:
            continue
        sc = Screen(linear, form, Z)
        singles = {}
        for name, var in sc.variables.items():
            laws = [law for law in grids(var, form) if not (bounded and bounded(law))]
            if not laws:
                continue
            F = _phis(laws, Z)
            d, a = sc.drops(F, parts(name))
            singles[name] = (laws, F)
            out += [(float(x), dataclasses.replace(law, strength=float(s)))
                    for x, s, law in zip(d, a, laws) if x > 0]
        for x1, x2 in itertools.combinations(sorted(singles), 2):
            if set(parts(x1)) & set(parts(x2)):
                continue  # p·v with p or v: its own variables again
            l1, F1 = singles[x1]
            l2, F2 = singles[x2]
            F = (F1[:, :, None] * F2[:, None, :]).reshape(F1.shape[0], -1)
            d, a = sc.drops(F, parts(x1) + parts(x2))
            for k in np.flatnonzero(d > 0):
                i, j = divmod(int(k), len(l2))
                law = LawSpec(form, (l1[i].terms[0], l2[j].terms[0]), float(a[k]))
                out.append((float(d[k]), law))
    out.sort(key=lambda x: -x[0])
    return out


def score(x, n_rows: int) -> float:
    """The screen's score of (χ² drop, law): the drop less ln(n_rows) per fitted constant
    (module docstring)."""
    return x[0] - math.log(max(n_rows, 2)) * len(x[1].free_keys())


def ranked_structures(screened, n_rows: int) -> list[tuple[float, LawSpec]]:
    """The best (χ² drop, law) of each structure (`structure`) of `screened` (best drop
    first), best `score` first."""
    best = {}
    for drop, law in screened:
        best.setdefault(structure(law), (drop, law))
    return sorted(best.values(), key=lambda x: score(x, n_rows), reverse=True)


def picks(screened, n_rows: int, n: int = PICKS) -> list[tuple[float, LawSpec]]:
    """The laws fitted through the loop: the best of each structure (`structure`), ranked
    by the χ² drop less ln(n_rows) per fitted constant, the first `n`; the best one-term
    law among them (in the last place where it was not)."""
    ranked = ranked_structures(screened, n_rows)
    out = ranked[:n]
    single = next((x for x in ranked if len(x[1].terms) == 1), None)
    if single is not None and all(len(x[1].terms) > 1 for x in out):
        out = out[:n - 1] + [single]
    # simplest first: the products may start from the single laws as fitted
    return sorted(out, key=lambda x: (len(x[1].terms), -score(x, n_rows)))
