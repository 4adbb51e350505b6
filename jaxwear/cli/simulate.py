"""`jaxwear simulate STUDY.toml [--out DIR]`: profiles.csv, plots, summary.json."""

from __future__ import annotations

from ._pipeline import Verb


class Simulate(Verb):
    name = "simulate"
    help = "predict wear profiles for a study"

    def outputs(self, study, opts):
        from .._simulate_study import simulate_outputs

        return simulate_outputs(study)

    def run(self, study, out, opts):
        from .. import _simulate_study  # looked up now: tests stand in for the engine

        _simulate_study.simulate_study(study, out)
        print(f"wrote {out.root / 'profiles.csv'}")
