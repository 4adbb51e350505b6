"""`jaxwear synth --hidden EFFECT[=STRENGTH] --noise-um 0.3 --seed N [--angle-offset-deg D]
[--conditions paper|STUDY.toml] --out DIR`: a study with data from hidden effects."""

from __future__ import annotations

from jaxwear._analyses.synth import _conditions, parse_hidden, synth_outputs, synthesize
from jaxwear._core.numbers import number
from jaxwear._study.plausible import check_value
from jaxwear.cli._pipeline import Verb


class Synth(Verb):
    name = "synth"
    help = "write a study with data from hidden effects"
    takes_study = False
    out_required = True

    def add_arguments(self, p):
        p.add_argument("--hidden", action="append", default=[],
                       help="EFFECT[=STRENGTH], repeatable (or comma-separated)")
        p.add_argument("--conditions", default="paper", help="'paper' or a study file")
        p.add_argument("--noise-um", default="0.3", help="measurement noise σ [µm]")
        p.add_argument("--seed", default="0", help="random seed (a whole number)")
        p.add_argument("--angle-offset-deg", default="0",
                       help="registration offset of every scan [deg] (truth.json only)")

    def options(self, args):

        noise = number("--noise-um", args.noise_um, nonneg=True)
        if noise > 0:  # 0: noise-free data
            check_value("--noise-um", "fit.noise_um", noise, name="--noise-um")
        offset = number("--angle-offset-deg", args.angle_offset_deg)
        check_value("--angle-offset-deg", "experiment.angle_offset_deg", offset,
                    name="--angle-offset-deg")
        return {"noise_um": noise,
                "seed": number("--seed", args.seed, integer=True, nonneg=True),
                "angle_offset_deg": offset}

    def load(self, args, opts):

        return _conditions(args.conditions, None)

    def resolve(self, study, opts):

        # after the conditions: their effect files may define the hidden effects
        opts["hidden"] = parse_hidden(opts["args"].hidden)

    def outputs(self, study, opts):

        return synth_outputs(study)

    def run(self, study, out, opts):

        res = synthesize(opts["hidden"], study, noise_um=opts["noise_um"], seed=opts["seed"],
                         out=out, angle_offset_deg=opts["angle_offset_deg"], verbose=True)
        n = sum(len(e.profile.angle) if e.profile is not None else len(e.history.hours)
                for e in res.study.experiments)
        hidden = ", ".join(f"{k}({', '.join(f'{kk}={vv:g}' for kk, vv in v.items())})"
                           for k, v in res.truth["hidden"].items()) or "none"
        print(f"wrote {res.study_path} ({len(res.study.experiments)} experiments, {n} rows; "
              f"hidden: {hidden}); truth in {res.study_path.parent / 'truth.json'}")
        return res
