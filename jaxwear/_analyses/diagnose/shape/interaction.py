"""Products of variables in the shape (issue 43 item 1): a surface over the leading pair of
the chosen form, tested on top of the additive fit of the pair and the carriers.

The additive joint fit (`shape.analysis._joint`) can represent Σ_v g_v(z_v) only; a law of two
variables at once (a factor p · tanh(v), an impact whose size follows the load as well as
the turn rate) is not such a sum. For the leading pair of the form (`leading_pair`: the
variable that explains most alone and the leading carrier beside it, else the next
significant variable), a surface g(z_a, z_b) on `TENSOR_SIZE` x `TENSOR_SIZE`
tensor-product B-splines
(`effects.shape.ShapeTensor`; penalised by second differences along both directions; in the
factor form its coefficient grid has zero row and column sums, so it holds no function of
one variable alone, which are the additive terms' and K_d's) has its columns computed
through the wear loop (`shape.design.tensor_columns`, one Jacobian, computed in the
background from the form's joint fit on) and is tested as the variables are, with the
additive terms of the pair and of the form's carriers (the variables the refit uses)
treated as nuisance:

    T = ΔRSS/σ² of the penalised surface on the misfit with those additive columns and the
    fit's own columns projected off; its null simulated with the penalty re-chosen in each
    draw (`shape.linear.penalised_fit`).

So under a truth additive in those variables (in the linearisation) the misfit tested is
noise and the test has its level. It is run only where two variables of the form are
significant alone, so it adds nothing to the family-wise error of a null study, and it is
significant below the same α / (variable-forms) as each variable. Where it is, and where it
is material (`SURFACE_MATERIAL`: linearised, it lowers the refit's RMSE by 1 % or more),
the refit through the loop carries the surface beside the additive terms (`shape.refit`).

Why not on top of every variable of the form: on the paper's rig the nine factor variables
are all functions of the cycle phase, the bore angle and the experiment, and their sum
holds most of a product of two of them in the linearised system (measured on the
generator's `pv_tanh`: the surface over pressure x sliding speed then adds 0 %, p 0.73),
while the refit through the loop carries only the carriers.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from jaxwear._analyses.diagnose.shape import linear as lin
from jaxwear._core.jsonfmt import json_float as _num

# A significant surface is carried through the loop only where its linearised gain
# (`rmse_gain_linearised`) is at least this fraction of the refit's RMSE. Why: the refit's
# RMSE enters only comparisons with a tolerance of 1 % or more (the law search's tie,
# `law.search.LOO_TIE`; `LAW_WORSE`, 5 %), while the surface is the largest block of the
# refit's Jacobian. Measured on the generator's studies (48 x 72, 2026-11-29):
# - `fatigue`: the surface over sliding speed x pressure is significant in both analyses
#   (T = 52 and 58, p 5e-5; linearised gain 0.7 and 0.8 %); it is 25 of the refits' 51
#   Jacobian columns (~5 s of CPU per evaluation, 18 evaluations). Without it the refits
#   end at 0.3355 and 0.3352 µm against 0.3339 and 0.3343 (+0.5 %, +0.3 %), and
#   `diagnose --shape` took 104.6 s against 140-146 s.
# - `g_step_p_power_v` (rich design, seeds 1-3; its law a product of a step in p and v):
#   the surface over pressure x the load's turn rate, significant (T = 44-60), linearised
#   gain 0.20-0.29 %; the first refit ends at 0.3125, 0.3131, 0.3163 µm against 0.3091,
#   0.3097, 0.3129 (+1.1 % each; the turn rate, a carrier only through the surface, goes
#   with it): the loop gave more than the linearisation there. The
#   law found (the true structure), its RMSE, left-out error, constants and evaluations
#   are the same in all three.
# The figure is a linearisation, loose by a factor of 3 either way on these studies; the
# largest refit's RMSE a surface under it moved is 1.1 %.
SURFACE_MATERIAL = 0.01


@dataclass(frozen=True)
class Interaction:
    """The surface over a pair of variables on top of the additive fit (JSON `to_json`)."""

    variables: tuple  # (a, b)
    form: str
    explained_fraction: float  # of the misfit beyond noise, beyond the additive fit
    p_value: float
    dof: float
    statistic: float  # T = ΔRSS/σ²
    significant: bool
    # the refit's RMSE the surface would lower, linearised, as a fraction
    rmse_gain_linearised: float = math.inf
    # (A, S, Z, X, tensor): the columns projected off the nuisance (not off the additive
    # ones), penalty, constraint basis, whitened columns unprojected, the `ShapeTensor`
    block: tuple = field(default=None, repr=False)

    @property
    def label(self) -> str:
        return self.block[4].label if self.block is not None else "*".join(self.variables)

    @property
    def carried(self) -> bool:
        """Whether the refit through the loop carries the surface: significant and material
        (`SURFACE_MATERIAL`)."""
        return bool(self.significant and self.rmse_gain_linearised >= SURFACE_MATERIAL)

    def to_json(self) -> dict:
        return {"variables": list(self.variables), "form": self.form,
                "explained_fraction": _num(self.explained_fraction),
                "p_value": _num(self.p_value), "dof": _num(self.dof),
                "statistic": _num(self.statistic), "significant": bool(self.significant),
                "rmse_gain_linearised": _num(self.rmse_gain_linearised),
                "carried": self.carried}


def rmse_gain_linearised(drop: float, dof: float, n_rows: int, phi: float = 0.0) -> float:
    """The fraction by which a correction whose penalised fit lowers the linearised misfit
    by `drop` (σ² units) with `dof` effective parameters would lower a refit's RMSE: net of
    what noise alone gives it, (ΔRSS − dof)⁺ σ² over the `n_rows` rows off the mean
    square, relative to a refit at the noise (σ²; a refit above it gains less) and halved
    for the root: (ΔRSS − dof)⁺ / (2 n). Where the noise is AR(1) of coefficient `phi`
    along the scans, `drop` is of the prewhitened rows, which hold as little as
    (1 − |φ|)/(1 + |φ|) of a smooth correction's raw sum of squares
    (`shape.linear.prewhiten`'s gain at its lowest): taken back. A linearisation, not a
    bound: the refit through the loop moved by 0.3-0.5 % where it said 0.7-0.8 % on the
    generator's `fatigue` study, by 1.1 % where it said 0.2-0.3 % on `g_step_p_power_v`
    (`SURFACE_MATERIAL`)."""
    a = min(abs(phi), 0.99)
    return float(max(drop - dof, 0.0) * (1.0 + a) / (1.0 - a) / (2.0 * max(n_rows, 1)))


def leading_pair(results, form: str) -> tuple | None:
    """The pair of `form` a surface is fitted over, or None: the variable that explains most
    alone and the carrier (significant unique share in the form's joint fit) that explains
    most alone beside it, as the refit's carriers are chosen; where no other variable
    carries, the two significant variables that explain most alone.

    Why carriers first: a stand-in varies with its carrier on the experiments (the load's
    turn per second and per degree of the cycle; the load and the sliding speed on the
    paper's rig), and a surface over a variable and its stand-in is no product of two
    quantities. Measured on the generator's `two_variable` (a step in p·v): by alone share
    the pair is sliding speed x load (surface p 0.092), with the carrier sliding speed x
    pressure (p 1.5e-4)."""
    sig = sorted([v for v in results if v.form == form and v.significant],
                 key=lambda v: -v.explained_fraction)
    if len(sig) < 2:
        return None
    carry = [v for v in sig[1:] if v.carries]
    return sig[0].name, (carry[0] if carry else sig[1]).name


def tensor_system(tensor, columns, sigma, n_prior, series, phi, n, proj):
    """The surface's whitened system: (A (rows, k') projected off the nuisance, S (k', k'),
    Z (size, k'), X (rows, size) whitened, unprojected). `columns` (n, size) [µm per unit]
    from `tensor_columns`; rows as the design's (data / σ, then `n_prior` prior rows)."""
    X = np.vstack([np.asarray(columns) / sigma, np.zeros((n_prior, tensor.size))])
    X = lin.prewhiten(X, series, phi, n)
    if tensor.form == "factor":
        Z = np.kron(lin.sum_zero(tensor.a.size), lin.sum_zero(tensor.b.size))
    else:
        Z = np.eye(tensor.size)
    A = proj(X @ Z)
    S = Z.T @ tensor.roughness() @ Z
    return A, S, Z, X


def interaction_test(tensor, A, S, Z, X, additive, rho, n_res, nu, rng, draws, excess, rss0,
                     alpha, phi: float = 0.0) -> Interaction:
    """The surface's test on top of the additive columns `additive` (list of (rows, k)
    arrays, already projected off the nuisance): both ρ and A are projected off their span
    (unpenalised) and the penalised surface fitted to what is left (module docstring);
    `phi`: the noise's AR(1) coefficient the rows were prewhitened with
    (`rmse_gain_linearised`)."""
    Add = np.hstack(additive) if additive else np.zeros((len(rho), 0))
    if Add.shape[1]:
        U, s, _ = np.linalg.svd(Add, full_matrices=False)
        Q = U[:, s > 1e-10 * max(float(s[0]), 1e-300)]
    else:
        Q = np.zeros((len(rho), 0))
    A2 = A - Q @ (Q.T @ A)
    r2 = rho - Q @ (Q.T @ rho)
    pf = lin.penalised_fit(A2, S, r2, n_res - Q.shape[1], nu, rng, draws)
    share = lin.explained(pf.drop, pf.dof, excess, rss0)
    return Interaction((tensor.a.name, tensor.b.name), tensor.form, share, pf.p, pf.dof,
                       pf.drop, bool(pf.p < alpha),
                       rmse_gain_linearised(pf.drop, pf.dof, n_res, phi), (A, S, Z, X, tensor))


def pair_interaction(result, model, a: str, b: str, form: str = "factor", additive=None,
                     seed: int = 0, draws: int = 20000, alpha: float = 1e-3 / 15,
                     verbose: bool = False) -> Interaction:
    """The surface over `a` x `b` tested on a finished `ShapeResult` of `model` (its design
    and linear system), whether or not the analysis ran it: for validation (e.g. its
    p-value on null studies, where no pair is significant and the analysis skips it).
    `additive`: the variables whose additive fit it is tested on top of (default the pair
    and the result's carriers)."""
    from jaxwear._analyses.diagnose.shape.design import pair_tensor, tensor_columns

    lin_ = result.linear
    Qb = lin_["Qb"]
    tensor = pair_tensor(result.design, a, b, form)
    cols = tensor_columns(result.design, tensor, lin_["groups"], verbose)
    A, S, Z, X = tensor_system(tensor, cols, lin_["sigma"], lin_["n_prior"], model.series,
                               lin_["phi"], lin_["n"], lambda M: M - Qb @ (Qb.T @ M))
    names = additive if additive is not None else list(
        dict.fromkeys(list(result.carriers) + [a, b]))
    blocks = lin_["blocks"]
    add = [blocks[nm if form == "factor" else f"deposit:{nm}"][0] for nm in names]
    return interaction_test(tensor, A, S, Z, X, add, lin_["rho"], lin_["n_res"], lin_["nu"],
                            np.random.default_rng(seed), draws, lin_["excess"], lin_["rss0"],
                            alpha, lin_["phi"])
