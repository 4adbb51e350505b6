"""The choice among variables that each explain the misfit alone (issue 43 item 1): by the
joint fit's unique shares and the error on left-out experiments, not by a margin of noise.

Where several significant variables explain the misfit within ln 20 of AIC of the best
(`alternatives`: on the paper's rig pressure, sliding speed, load and the load's turn all
follow the crank speed), the share each explains alone differs by noise. Two things the
data can still say:

1. **Unique share**: what a variable adds to all the others of its form in the joint
   additive fit (`shape.analysis._joint`); a significant unique share (p < α / variable-forms)
   says the misfit needs that variable, whatever the others do.
2. **Left-out experiments**: per variable, its penalised correction (the λ of its alone
   fit) fitted on the other experiments' rows of the linearised system (prior rows always
   in) predicts the held-out experiment's rows; the sum over experiments of the squared
   prediction errors (σ² units) ranks the variables by how well their correction carries
   over to conditions it was not fitted on. Two are told apart where their summed errors
   differ by more than the standard error of the difference (from the experiments'
   paired differences).

Where neither tells (unique shares not significant, left-out errors within their standard
error), the variables are `confounded`: the experiments vary them together, and only a
test that varies them apart can say which it is.
"""

from __future__ import annotations

import math

import numpy as np

from jaxwear._analyses.diagnose.shape.linear import psolve


def left_out_errors(A, S, lam, rho, row_exp, n_data) -> np.ndarray:
    """(E,) the held-out experiments' squared prediction errors (σ² units) of the penalised
    fit of A's columns (penalty λ S) to ρ: for each experiment, fitted on every other row
    (data rows of the other experiments, and every prior row at `n_data` and beyond)."""
    exps = np.asarray(row_exp)
    rows = len(rho)
    out = []
    H_all = A.T @ A + lam * S
    ridge = 1e-12 * max(float(np.trace(A.T @ A)), 1e-300) * np.eye(A.shape[1])
    b_all = A.T @ rho
    for e in np.unique(exps):
        held = np.zeros(rows, bool)
        held[:n_data] = exps == e
        Ah = A[held]
        a = psolve(H_all - Ah.T @ Ah + ridge, b_all - Ah.T @ rho[held])
        r = rho[held] - Ah @ a
        out.append(float(r @ r))
    return np.asarray(out)


def _se_of_difference(d: np.ndarray) -> float:
    """Standard error of Σ d_e over experiments (paired differences)."""
    if len(d) < 2:
        return math.inf
    return float(math.sqrt(len(d) * np.var(d, ddof=1)))


def rank_alternatives(top, alternatives, blocks, rho, row_exp, n_data, alpha):
    """(the chosen one, the others in rank order, the confounded labels, {label: left-out
    error [σ² units]}) among `top` (the one explaining most) and its `alternatives`
    (VariableShape's within ln 20 of AIC): the ones with a significant unique share first;
    among them the lowest left-out error where it is lower than the explained-share
    leader's by more than its standard error; confounded: the chosen one and every other
    whose unique share is not significant and whose left-out error is within its standard
    error of the chosen one's (empty where only one remains, or the chosen one's unique
    share is significant)."""
    cands = [top] + list(alternatives)
    if len(cands) < 2:
        return top, [], [], {}
    loo = {v.label: left_out_errors(blocks[v.label][0], blocks[v.label][1], v.lam, rho,
                                    row_exp, n_data) for v in cands}
    unique_sig = {v.label: bool(v.unique_p_value < alpha) for v in cands}
    pool = [v for v in cands if unique_sig[v.label]] or cands
    leader = max(pool, key=lambda v: (v.explained_fraction, -v.aic))
    chosen = leader
    for v in sorted(pool, key=lambda v: float(np.sum(loo[v.label]))):
        d = loo[leader.label] - loo[v.label]
        if v is not leader and float(np.sum(d)) > _se_of_difference(d):
            chosen = v
        break
    total = {k: float(np.sum(x)) for k, x in loo.items()}

    def tied(v):
        d = loo[v.label] - loo[chosen.label]
        return abs(float(np.sum(d))) <= _se_of_difference(d)

    confounded = []
    if not unique_sig[chosen.label]:
        confounded = [v.label for v in cands if not unique_sig[v.label] and tied(v)]
        if len(confounded) < 2:
            confounded = []
    others = sorted([v for v in cands if v is not chosen],
                    key=lambda v: (not unique_sig[v.label], total[v.label]))
    return chosen, others, confounded, total
