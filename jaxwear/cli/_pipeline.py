"""One path for every verb: parse → load the study → check the outputs → estimate the work →
run. Each step refuses bad input (`InputError`, exit 2, one line) before the next begins, so
nothing is computed for a run that cannot finish or cannot write its results.

1. `options(args)`: every option's value (numbers by `jaxwear._core.numbers`), before any file is
   read.
2. `load(args, opts)`: the study (or synth's conditions), validated by `load_study`;
   `resolve(study, opts)` then checks what needs the study (e.g. `--fit` names).
3. `open_outputs`: every planned output against the inputs (name, symlink, hard link), the
   folders created and each probed with a real file (created and removed), so that an
   unwritable `--out` or `--json` (permissions, /proc, a path under a file) is refused now,
   not after the computation.
4. `check_work(study, tangents)`: the work and memory estimate of one model evaluation
   (`jaxwear._study.budget`), with the Jacobian columns of the parameters really fitted.
5. `run(study, out, opts)`: the work.
"""

from __future__ import annotations

from argparse import Namespace

from jaxwear._core import background
from jaxwear._inference.packing import study_columns
from jaxwear._report.figures import warm_plots
from jaxwear._study.budget import check_work
from jaxwear._study.data_checks import check_wear_measured
from jaxwear._study.outputs import open_outputs
from jaxwear._study.study import load_study

DEFAULT_OUT = "jaxwear_out"


class Verb:
    """A verb of the command line; subclasses fill in the steps they need."""

    name = ""
    help = ""
    takes_study = True  # a positional STUDY.toml
    takes_json = False  # --json FILE
    out_required = False  # --out without a default (synth)
    out_help = f"output folder (default {DEFAULT_OUT})"
    fits_data = False  # fits the study's measurements: refuse data with no wear in them
    # the program whose XLA compilation the figures' library is imported beside (a fit's
    # Jacobian where the verb fits data; None: imported where the first figure needs it)
    plots_after: str | None = None

    def add_arguments(self, p) -> None:
        """The verb's own options (STUDY, --out and --json are added by `add_to`)."""

    def add_to(self, sub) -> None:
        p = sub.add_parser(self.name, help=self.help)
        if self.takes_study:
            p.add_argument("study", help="study file (TOML)")
        self.add_arguments(p)
        if self.out_required:
            p.add_argument("--out", required=True, help="output folder")
        else:
            p.add_argument("--out", default=DEFAULT_OUT, help=self.out_help)
        if self.takes_json:
            p.add_argument("--json", default=None, help="write the result as JSON to this file")
        p.set_defaults(verb=self)

    # -- the steps ------------------------------------------------------------------------
    def options(self, args: Namespace) -> dict:
        return {}

    def load(self, args: Namespace, opts: dict):

        return load_study(args.study)

    def resolve(self, study, opts: dict) -> None:
        """Checks that need the study (before the outputs are opened)."""

    def outputs(self, study, opts: dict) -> list[str]:
        return []

    def work_study(self, study, opts: dict):
        """The study whose one evaluation is estimated (predict: to its forecast horizon)."""
        return study

    def length_from(self, study, opts: dict) -> str | None:
        """What set the run's length, when not the study's `revolutions`/`hours` (named by
        the work estimate's refusal)."""
        return None

    def tangents(self, study, opts: dict) -> int:
        """Forward-mode Jacobian columns carried through one evaluation."""
        return 0

    def run(self, study, out, opts: dict):
        raise NotImplementedError

    # -- the path -------------------------------------------------------------------------
    def execute(self, args: Namespace):

        opts = self.options(args)
        opts["args"] = args
        study = self.load(args, opts)
        self.resolve(study, opts)
        if self.fits_data:
            check_wear_measured(study)
        out = open_outputs(study, args.out, planned=self.outputs(study, opts),
                           json_file=getattr(args, "json", None))
        opts["estimate"] = check_work(self.work_study(study, opts),
                                      tangents=self.tangents(study, opts),
                                      length_from=self.length_from(study, opts))
        after = "_evaluate_jit" if self.fits_data else self.plots_after
        if after is None:
            return self.run(study, out, opts)
        # the figures' library imported while the verb's first large program compiles
        lowered = background.lowered(after)
        warm_plots(lowered)
        try:
            return self.run(study, out, opts)
        finally:
            background.forget(lowered)


def fit_columns(study, keys) -> int:
    """Jacobian columns of fitting `keys` (one clearance per experiment, ...)."""

    return len(study_columns(study, keys, [study.params(e) for e in study.experiments]))
