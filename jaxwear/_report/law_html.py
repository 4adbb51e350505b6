"""The law found from the shape in the HTML report (`law.search`; issue 43): base → shape →
law, in-sample and on left-out experiments, and every law fitted through the loop."""

from __future__ import annotations

import html

from jaxwear._analyses.diagnose._headline import law_status


def _n(x, fmt=".3f") -> str:
    return "—" if x is None else format(float(x), fmt)


def law_section(shape, _table) -> list[str]:
    """HTML parts for `shape.law` (a `law.search.LawResult`), or [] where there is none;
    `_table(rows, header)` renders a table (`_html`'s)."""
    res = shape.law
    if res is None or res.best is None:
        return []
    b = res.best
    steps = [("base model (as written)", _n(res.rmse_before_um), _n(res.loo_before_um)),
             ("with the shape (spline, refitted through the loop)",
              _n(shape.rmse_after_um), "—"),
             (f"with the law: {b.formula}", _n(b.rmse_um), _n(b.loo_rmse_um)),
             ("noise level", _n(res.noise_um), "")]
    # the constants' numerical error (`law.numerical`: their correction to a finer level)
    ne = getattr(b, "numerical_error", None) or {}
    consts = [(k, _n(v, ".5g"), _n(s, ".2g") if s == s else "—",
               _n(ne[k], ".2g") if k in ne else "—", u)
              for k, (v, s, u) in b.constants.items()]
    tried = [(f.law.label, _n(f.rmse_um), _n(f.loo_rmse_um), _n(f.evidence, ".1f"),
              "yes" if f.at_noise else "no", f.status) for f in res.fitted]
    head = ("The law found" if law_status(res) == "found" else
            "The best law tried: worse than the shape, a lead" if res.worse_than_shape
            else "A lead, not a law found")
    return [f"<h3>{head}</h3>", f"<p>{html.escape(res.sentence)}</p>",
            _table(steps, ["model", "RMSE [µm]", "left-out-experiment RMSE [µm]"]),
            _table(consts, ["constant", "value", "SE", "numerical error", "unit"]),
            "<p>Laws of the grammar (power law, hinge, smooth step, exponential and "
            f"products of two, in the factor and deposit forms) screened: {res.screened};"
            " the best of distinct structure fitted through the wear loop with K_d and the "
            "clearances (best first: the simplest within one standard error of the best "
            "left-out-experiment error):</p>",
            _table(tried, ["law", "RMSE [µm]", "left-out [µm]", "evidence (ln BF)",
                           "at noise level", "fit"])]
