"""Which test to run next (`jaxwear design`, docs/design_experiments.md): the candidates
(`plan`), run as one batched computation (`runs`), valued by the Fisher information they
add (`information`) and ranked for a goal (`rank`); a variable of the shape as a rival
(`shape_rival`); the tied pair of a diagnosis (`tied`)."""

from jaxwear._analyses.design.information import SEPARATE_CHI2, _chi2, _goal_value, _greedy, _logdet
from jaxwear._analyses.design.plan import GOALS, measure_points, parse_vary, plan_candidates
from jaxwear._analyses.design.rank import DesignResult, check_between, design, model_study
from jaxwear._analyses.design.runs import scan_metric
from jaxwear._analyses.design.shape_rival import fit_shape, is_shape, parse_shape
from jaxwear._analyses.design.tied import tied_pair

__all__ = [
    "DesignResult", "GOALS", "SEPARATE_CHI2", "_chi2", "_goal_value", "_greedy", "_logdet",
    "check_between", "design", "measure_points", "model_study", "parse_vary",
    "plan_candidates", "scan_metric", "fit_shape", "is_shape", "parse_shape", "tied_pair",
]
