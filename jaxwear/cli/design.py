"""`jaxwear design STUDY.toml [--goal separate|parameters|forecast] [--between A,B]
[--from DIAGNOSIS.json] [--vary KEY=LO:HI[:N],...] [--budget N] [--for KEY,...] [--at X]
[--train-until X] [--level 0.9] [--out DIR] [--json FILE]` (design.md §7).

Ranks candidate next experiments for a goal from the study's fitted model(s)
(`jaxwear._analyses.design`). Writes under DIR: `design.json` (the §7 document), `design.png` (the
goal's value over the varied ranges), `next_experiment.toml` (the recommended experiment(s)
as `[[experiment]]` stanzas) and, for crank-slider studies, `next_conditions.toml` (a study
without data for `jaxwear synth --conditions`). `--json FILE` writes the document to FILE
too. The first lines (stderr) say how many candidates and the estimated time. With
`--from DIAGNOSIS.json` (a `diagnose --json` document) and no --goal or --between, the goal
is `separate` between the diagnosis's tied pair (`_analyses.design.tied`), and the first
line says so.
Exit codes: 0 done, 2 bad input (the message names the option), 1 anything else.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from jaxwear._analyses.design import (
    GOALS,
    check_between,
    design,
    parse_vary,
    plan_candidates,
    tied_pair,
)
from jaxwear._core.errors import InputError
from jaxwear._core.numbers import number
from jaxwear._inference.packing import ALIASES, study_fit_keys
from jaxwear._report.design import (
    DESIGN_OUTPUTS,
    conditions_study,
    plot,
    stanza,
    summary_lines,
    to_json,
)
from jaxwear.cli._pipeline import Verb, fit_columns


class Design(Verb):
    name = "design"
    help = "rank candidate next experiments for a goal (which test to run next)"
    takes_json = True

    def add_arguments(self, p):
        p.add_argument("--goal", default=None,
                       help="separate, parameters or forecast (default: separate with "
                            "--between, else parameters)")
        p.add_argument("--between", default=None,
                       help="A,B: two explanations for --goal separate (effects, base, or "
                            "variables of the shape: shape:pressure_MPa, "
                            "shape:deposit:load_N)")
        p.add_argument("--from", dest="from_diagnosis", default=None,
                       help="DIAGNOSIS.json (diagnose --json): without --goal and "
                            "--between, separate its tied pair")
        p.add_argument("--vary", default=None,
                       help="KEY=LO:HI[:N],... over speed_rpm, clearance_mm, load_scale, "
                            "revolutions (crank-slider) or hours (timed: the next "
                            "measurement); default: around the study's conditions")
        p.add_argument("--budget", default="1", help="experiments in the recommended set")
        p.add_argument("--for", dest="for_keys", default=None,
                       help="KEY,...: --goal parameters ranks by these parameters' "
                            "standard errors (default: D-optimal)")
        p.add_argument("--at", default=None,
                       help="--goal forecast: the forecast point (revolutions or hours)")
        p.add_argument("--train-until", default=None,
                       help="use only the measurements at or before this point")
        p.add_argument("--level", default="0.9", help="--goal forecast: the band's level")

    def options(self, args):

        note = None
        if args.from_diagnosis is not None and not args.between and args.goal in (
                None, "separate"):
            pair = tied_pair(_read_diagnosis(args.from_diagnosis))
            if pair is not None:
                args.between = ",".join(pair[0])
                note = (f"design: goal separate between {pair[0][0]} and {pair[0][1]}: the "
                        f"tied pair of {args.from_diagnosis} ({pair[1]})")
            else:
                note = (f"design: {args.from_diagnosis} names no tied pair; goal "
                        f"{args.goal or 'parameters'}")
        goal = args.goal or ("separate" if args.between else "parameters")
        if goal not in GOALS:
            raise InputError(f"--goal: expected one of {', '.join(GOALS)}, got {goal!r}")
        between = [s.strip() for s in (args.between or "").split(",") if s.strip()]
        if goal == "separate" and not between:
            raise InputError("--goal separate: give the two explanations with --between A,B "
                             "(effects such as running_in, or base)")
        if between and goal != "separate":
            raise InputError(f"--between: only with --goal separate (got --goal {goal})")
        for_keys = [s.strip() for s in (args.for_keys or "").split(",") if s.strip()]
        if for_keys and goal != "parameters":
            raise InputError(f"--for: only with --goal parameters (got --goal {goal})")
        if args.at is not None and goal != "forecast":
            raise InputError(f"--at: only with --goal forecast (got --goal {goal})")
        level = number("--level", args.level, lo=0.0, hi=1.0)
        return {"goal": goal, "between": between, "for_keys": for_keys, "note": note,
                "budget": number("--budget", args.budget, integer=True, positive=True),
                "at": number("--at", args.at, positive=True),
                "train_until": number("--train-until", args.train_until, positive=True),
                "level": level}

    def resolve(self, study, opts):

        opts["vary"] = parse_vary(opts["args"].vary, study)
        if opts["between"]:
            check_between(study, opts["between"])
        if opts["for_keys"]:

            opts["for_keys"] = [ALIASES.get(k, k) for k in opts["for_keys"]]
            shared = [k for k in study_fit_keys(study)
                      if k not in ("clearance_mm", "angle_offset_deg")]
            for k in opts["for_keys"]:
                if k not in shared:
                    raise InputError(f"--for: {k!r} is not a fitted shared parameter of "
                                     f"{study.path}; expected one of {', '.join(shared)}")
        plan = plan_candidates(study, opts["vary"])
        if opts["budget"] > plan.size:
            raise InputError(f"--budget {opts['budget']}: only {plan.size} candidates; vary "
                             f"more values")

    def outputs(self, study, opts):

        return list(DESIGN_OUTPUTS)

    def tangents(self, study, opts):

        return fit_columns(study, study_fit_keys(study))

    def run(self, study, out, opts):
        if opts.get("note"):
            print(opts["note"], file=sys.stderr, flush=True)

        res = design(study, goal=opts["goal"], between=opts["between"], vary=opts["vary"],
                     budget=opts["budget"], for_keys=opts["for_keys"] or None, at=opts["at"],
                     train_until=opts["train_until"], level=opts["level"], verbose=True)
        doc = to_json(res, study)
        if opts.get("note"):
            doc["goal_from"] = {"diagnosis": opts["args"].from_diagnosis, "note": opts["note"]}
        out.write_json("design.json", doc)
        out.write_text("next_experiment.toml", stanza(res, study))
        cond = conditions_study(res, study, out.root)
        if cond is not None:
            out.write_text("next_conditions.toml", cond)
        plot(res, out.path("design.png"))
        out.write_json_file(doc)
        for line in summary_lines(res, study):
            print(line)
        t = res.timing
        print(f"{res.plan.size} candidates ranked in {t['total_s']:.1f} s (fit "
              f"{t.get('fit_s', 0):.1f} s, candidates {t.get('candidates_s', 0):.1f} s)",
              file=sys.stderr)
        print(f"wrote {out.path('design.json')}, {out.path('next_experiment.toml')}"
              + (f", {out.path('next_conditions.toml')} (for `jaxwear synth --conditions`)"
                 if cond is not None else ""))
        return res


def _read_diagnosis(path: str) -> dict:
    """The diagnosis document at `path`; `InputError` naming --from and the file."""
    try:
        return json.loads(Path(path).read_text(encoding="utf-8"))
    except OSError as e:
        raise InputError(f"--from {path}: cannot read the diagnosis ({e.strerror or e})"
                         ) from None
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise InputError(f"--from {path}: not a JSON document ({e}); expected the output "
                         f"of `jaxwear diagnose --json`") from None
