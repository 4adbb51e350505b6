"""Which test to run next (`jaxwear design`, docs/design_experiments.md): the candidates
(`plan`), run as one batched computation (`runs`), valued by the Fisher information they
add (`information`) and ranked for a goal (`rank`)."""

from jaxwear._analyses.design.information import SEPARATE_CHI2, _chi2, _goal_value, _greedy, _logdet
from jaxwear._analyses.design.plan import GOALS, measure_points, parse_vary, plan_candidates
from jaxwear._analyses.design.rank import DesignResult, check_between, design, model_study
from jaxwear._analyses.design.runs import scan_metric

__all__ = [
    "DesignResult", "GOALS", "SEPARATE_CHI2", "_chi2", "_goal_value", "_greedy", "_logdet",
    "check_between", "design", "measure_points", "model_study", "parse_vary",
    "plan_candidates", "scan_metric",
]
