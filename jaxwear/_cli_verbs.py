"""Argument parsers of the verbs beyond `simulate`; each verb's code lives in its module."""

from __future__ import annotations


def _lazy(module: str, func: str):
    def run(args):
        import importlib

        return getattr(importlib.import_module(f"jaxwear.{module}"), func)(args)

    return run


def add_verbs(sub):
    c = sub.add_parser("calibrate", help="fit K_d, clearances (and effect strengths) to data")
    c.add_argument("study")
    c.add_argument("--fit", default=None,
                   help="comma-separated: K_d, clearance, or any study parameter key "
                        "(default: the study's [fit] parameters, else K_d,clearance)")
    c.add_argument("--out", default="jaxwear_out")
    c.add_argument("--json", default=None, help="write the result as JSON to this file")
    c.set_defaults(func=_lazy("_calibrate_cli", "cmd_calibrate"))

    d = sub.add_parser("diagnose", help="find the physics the base model is missing")
    d.add_argument("study")
    d.add_argument("--out", default="jaxwear_out")
    d.add_argument("--json", default=None)
    d.set_defaults(func=_lazy("_diagnose_cli", "cmd_diagnose"))

    y = sub.add_parser("synth", help="write a study with data from hidden effects")
    y.add_argument("--hidden", action="append", default=[],
                   help="EFFECT[=STRENGTH], repeatable (or comma-separated)")
    y.add_argument("--conditions", default="paper", help="'paper' or a study file")
    y.add_argument("--noise-um", type=float, default=0.3)
    y.add_argument("--seed", type=int, default=0)
    y.add_argument("--angle-offset-deg", type=float, default=0.0,
                   help="registration offset of every scan [deg] (truth.json only)")
    y.add_argument("--out", required=True)
    y.set_defaults(func=_lazy("_synth", "cmd_synth"))

    w = sub.add_parser("sweep", help="batched sweep over speed and clearance")
    w.add_argument("study")
    w.add_argument("--speed-rpm", default=None, help="START:STOP:COUNT")
    w.add_argument("--clearance-mm", default=None, help="START:STOP:COUNT")
    w.add_argument("--out", default="jaxwear_out")
    w.set_defaults(func=_lazy("_sweep", "cmd_sweep"))

    n = sub.add_parser("sensitivity", help="normalised sensitivities by autodiff")
    n.add_argument("study")
    n.add_argument("--out", default="jaxwear_out")
    n.set_defaults(func=_lazy("_sensitivity", "cmd_sensitivity"))

    from ._predict_cli import add_parser as add_predict

    add_predict(sub, _lazy)
