"""The candidates a study can be missing (the columns of diagnose's extended model are
built by `_residual.build_model`, one group per candidate)."""

from __future__ import annotations

from jaxwear._physics.config import ModelConfig
from jaxwear._physics.effects import STRUCTURAL_CANDIDATES, get_effect, registered_effects


def candidate_names(cfg: ModelConfig) -> list[str]:
    """Candidates a study can be missing: registered effects it does not switch on, then
    the structural choices it does not make."""
    names = [n for n in registered_effects() if n not in cfg.effects]
    names += [n for n, c in STRUCTURAL_CANDIDATES.items() if c.applies(cfg)]
    return names


def _candidate_parameters(name):
    if name in STRUCTURAL_CANDIDATES:
        return STRUCTURAL_CANDIDATES[name].parameters
    return get_effect(name).parameters
