"""Diagnosis: find the physics the base model is missing (design.md §5, §7 `diagnose`).

The steps, each a function below:

1. **Base fit.** The study's own model and fitted parameters (`parse_fit`, `build_problem`
   of the calibration: K_d, the clearances with their tolerance prior, the strengths of
   effects the study switches on), fitted by Levenberg-Marquardt (`fit_masked`).
2. **Where it fails.** Residuals per experiment, over angle, over revolutions (or hours)
   and across speed and clearance (`where_it_fails`). The noise level comes from the data:
   each residual against the straight line through its two neighbours (angle order within
   one profile, time order within a history), normalised (`line_residuals`); the smooth
   profile and any smooth misfit cancel, white noise does not. Stated tests say whether the
   misfit is noise (`Tests`): a chi-square test of RSS/(n-k) against that noise level
   (F distribution: the noise level has ν degrees of freedom), a lag-1 autocorrelation
   (Durbin-Watson) test of the angle-ordered residuals, and the candidates' score tests,
   Bonferroni-combined at α = 1e-3.
3. **Rank the candidates.** A score (Lagrange-multiplier) test per candidate (`screen`)
   from the Jacobian column of its strength at the base fit: every candidate is switched
   on at its `off` value, where the model is the base model exactly (nesting), so one
   forward-mode Jacobian of the extended model gives every candidate's column at once.
   The leading candidates are refitted (where a refit is unusable, unstable derivatives
   or a model that does not run, the next ones by score in its place: `refit_leaders`)
   and compared by the `evidence`, the BIC log Bayes factor against the base model with
   the noise level unknown (`evidence_from`). `adequate` needs the base model's tests to
   accept and the screen's promise (very strong linearised evidence) to have been tested
   by a refit that came to an answer (`_verdict.settle`); a fixed-M study beyond the
   update's stability is diagnosed at a stable M (`diagnose`).
4. **Refit with the winner**: RMSE per experiment before and after, and left-out-experiment
   prediction error before and after (`loo`: one Gauss-Newton step from the full fit).
   A candidate is named when its evidence is very strong (> ln 150) and its residuals pass
   the tests of step 2; when the best explains over half the misfit but leaves a
   systematic remainder, pairs with it are tried; a best candidate (or pair) that lowers
   the misfit with very strong evidence but whose own combined test still rejects makes
   the verdict `partly_explained` (named as partial, never as the missing effect; the
   sentence never says "at the noise level": `_verdict.verdict_status`,
   `_text.noise_claim`); otherwise the verdict is `unexplained` and names nothing.
   Candidates within ln 20 of the winner that also fit to noise are reported as
   alternatives the data cannot tell apart.
5. **Verdict** (`adequate` / `effect_found` / `partly_explained` / `unexplained`) in the
   design.md §7 JSON (`Diagnosis.to_json`), and a self-contained HTML report (`_html.py`).
6. **The shape of the missing wear** (`shape.analysis`; always with `shape=True`, else when the
   verdict is `unexplained`): a smooth correction along each state variable in two forms
   (a factor exp(g(z)) of the local rate, or a deposit e(z) ≥ 0 where the pin presses),
   alone and jointly, against a null that counts noise, correlated noise and the model's
   own numerical error; the best refitted through the loop, when in the cycle and where
   on the bore it is made (`shape.map`), and an effect file (`_effect_file`).
7. **The law** (`law.search`, where the shape finds a significant variable): a small grammar of
   physical laws over the state variables (`effects.law`: power, hinge, smooth step,
   exponential and products of two, in both forms), screened whole on the shape's
   linearised columns (`law.screen`), the best few of distinct structure fitted through
   the wear loop by the one least-squares core, the simplest within one standard error of
   the best left-out-experiment error answering; `found` only where it predicts, else a
   lead; `law.py` (`_law_file`) is the best as an effect file. Where the effect found is
   a pair or passes its test narrowly, that law is weighed against it (`_verdict`).

Why one extended model: compiling the wear loop costs far more than evaluating it, so the
base model, every candidate and every pair of candidates are evaluated by the same
compiled function (all candidates switched on, the unused ones held at `off`). Only the
structural candidate that changes the contact model (`unsymmetric`) needs a second one.
The compiled function depends on the shapes of the model (experiments, snapshots, nodes,
updates), not on the measured rows, so studies with the same design share it (`synth`
uses it to make data; the tests reuse it across seeds).

Modules: `_extended` (the extended model), `_model` (data and evaluation), `_fit`
(Levenberg-Marquardt, standard errors), `_stats` (noise level, tests), `_screen` (score
tests), `_evidence`, `_refit`, `_verdict` (`diagnose`), `_result` (frozen results, JSON),
`_text` (the verdict in words), `_html` (the report).
"""

from jaxwear._analyses.diagnose._evidence import (
    AMBIGUOUS_LOG_BF,
    STRONG_LOG_BF,
    derived,
    evidence,
    evidence_from,
    loo,
    rmse_per_experiment,
    where_it_fails,
)
from jaxwear._analyses.diagnose._extended import candidate_names
from jaxwear._analyses.diagnose._fit import Fit, fit_masked
from jaxwear._analyses.diagnose._model import Model, objective
from jaxwear._analyses.diagnose._result import METHOD_NOTE, Candidate, Diagnosis
from jaxwear._analyses.diagnose._screen import SHAPE_GRID, Screen, screen
from jaxwear._analyses.diagnose._stats import (
    ALPHA,
    Tests,
    chi2_sf,
    f_sf,
    lag1_autocorrelation,
    measurement_series,
    neighbour_differences,
    neighbour_pairs,
    norm_sf,
    run_tests,
)
from jaxwear._analyses.diagnose._text import summarize_verdict
from jaxwear._analyses.diagnose._verdict import diagnose
from jaxwear._analyses.diagnose.shape.analysis import shape_analysis
from jaxwear._analyses.diagnose.shape.result import ShapeResult, VariableShape
from jaxwear._analyses.diagnose.shape.text import threshold
from jaxwear._core.noise import line_residuals, noise_level
from jaxwear._inference.evaluation import Evaluation
from jaxwear._inference.packing import Column

__all__ = [
    "ALPHA", "AMBIGUOUS_LOG_BF", "METHOD_NOTE", "SHAPE_GRID", "STRONG_LOG_BF", "Candidate",
    "Column", "Diagnosis", "Evaluation", "Fit", "Model", "Screen", "Tests",
    "candidate_names", "chi2_sf", "derived", "diagnose", "evidence", "evidence_from", "f_sf",
    "fit_masked", "lag1_autocorrelation", "line_residuals", "loo",
    "measurement_series", "neighbour_differences", "neighbour_pairs", "noise_level", "norm_sf",
    "objective", "rmse_per_experiment", "run_tests", "screen", "summarize_verdict",
    "where_it_fails",
    "ShapeResult", "VariableShape", "shape_analysis", "shape_figure", "threshold",

]
