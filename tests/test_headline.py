"""The answer first (issue 49): numbers for people, the law's status read or derived, the
stand-ins in one clause per leading variable, no degenerate bands. The whole verdict
(headline, summary, details) of each status is rendered and checked in a browser by
`test_report_browser.py`."""

import math
from types import SimpleNamespace

from jaxwear._analyses.diagnose._headline import law_status, num, shape_adds
from jaxwear._analyses.diagnose.shape.text import stand_ins
from jaxwear._report.diagnose_html import peak_text, study_name


def test_numbers_for_people():
    # significant digits, trailing zeros where significant, no float noise
    assert num(0.58) == "0.580" and num(0.30686) == "0.307" and num(12.34) == "12.3"
    assert num(1.9999999999999996) == "2.00" and num(2.0, 1) == "2"
    assert num(15000.4) == "15000" and num(3.196e-18) == "3.20e-18"
    assert num(None) == "—" and num(math.nan) == "—" and num(0.0) == "0"


def _law(**kw):
    best = SimpleNamespace(undetermined=(), loo_rmse_um=0.33, rmse_um=0.31)
    base = dict(best=best, worse_than_shape=False, loo_before_um=0.62)
    base.update(kw)
    return SimpleNamespace(**base)


def test_the_laws_status_is_read_where_the_search_gives_it_else_derived():
    assert law_status(None) is None and law_status(_law(best=None)) is None
    # the search's own word wins (design.md §7 shape.law.status)
    assert law_status(_law(status="lead")) == "lead"
    assert law_status(_law(status="found", worse_than_shape=True)) == "found"
    # without it: worse than the shape, a constant undetermined, or no better on left-out
    # experiments than the base model is a lead
    assert law_status(_law()) == "found"
    assert law_status(_law(worse_than_shape=True)) == "lead"
    und = SimpleNamespace(undetermined=("h_width",), loo_rmse_um=0.33, rmse_um=0.31)
    assert law_status(_law(best=und)) == "lead"
    assert law_status(_law(loo_before_um=0.30)) == "lead"


def _var(name, lead=None, form="factor"):
    return SimpleNamespace(name=name, form=form, stand_in_for=lead)


def test_stand_ins_are_one_clause_per_leading_variable():
    """The sentence listed "bore_angle_deg for worn_depth_um, cycle_phase_deg for
    worn_depth_um, ..." for eight variables."""
    others = ["bore_angle_deg", "cycle_phase_deg", "load_N", "pressure_MPa",
              "sliding_distance_m"]
    results = ([_var("worn_depth_um")] + [_var(n, "worn_depth_um") for n in others]
               + [_var("load_turn_deg_per_deg", "sliding_distance_m"),
                  _var("load_N", "worn_depth_um", form="deposit")])
    s = stand_ins(results, "factor")
    assert s.count("worn_depth_um") == 1 and s.count("for ") == 2
    assert "bore_angle_deg, cycle_phase_deg, load_N and 2 more" in s
    assert "for sliding_distance_m, load_turn_deg_per_deg" in s
    assert stand_ins([_var("worn_depth_um")], "factor") == ""


def _peak(peak, lo, hi, rng=(0.0, 0.05), unit="m/s"):
    return SimpleNamespace(peak_at=peak, lower=lo, upper=hi, range=rng, unit=unit)


def test_a_band_is_shown_only_where_it_is_not_degenerate():
    """Bands such as [3.196e-18, 3.196e-18] m/s and [0.0007322, 0.0007322] deg/deg."""
    assert peak_text(_peak(3.196e-18, 3.196e-18, 3.196e-18)) == "0 m/s"
    assert peak_text(_peak(7.322e-4, 7.322e-4, 7.322e-4, (0.0, 9.0), "deg/deg")) == \
        "7.322e-04 deg/deg"
    assert peak_text(_peak(3.03, 2.9, 3.2, (0.0, 6.0), "µm")) == "3.030 [2.90, 3.20] µm"
    assert peak_text(_peak(3.03, math.nan, math.nan, (0.0, 6.0), "µm")) == "3.030 µm"


def test_the_shape_on_top_of_a_candidate_only_where_it_adds():
    first = SimpleNamespace(best="worn_depth_um", form="factor")
    assert not shape_adds(first, None)
    assert not shape_adds(first, SimpleNamespace(best=None, form=None))
    assert not shape_adds(first, SimpleNamespace(best="worn_depth_um", form="factor"))
    assert shape_adds(first, SimpleNamespace(best="worn_depth_um", form="deposit"))
    assert shape_adds(first, SimpleNamespace(best="pressure_MPa", form="factor"))
    assert shape_adds(None, SimpleNamespace(best="pressure_MPa", form="factor"))


def test_the_title_is_the_studys_name_not_its_path():
    assert study_name("/home/me/runs/2026/coating/study.toml") == "coating"
    assert study_name("/home/me/runs/impact_load.toml") == "impact_load"
    assert study_name("/a/b/c.toml") == "c"


def test_a_law_that_predicts_worse_than_the_base_model_is_no_lead():
    """Seen on a running-in study: the law of the search (its constants undetermined)
    predicted the left-out experiments at 0.774 µm against the base model's 0.317; the
    headline named it the best lead, with its RMSE."""
    from jaxwear._analyses.diagnose._headline import lead

    base, cand = object(), object()
    bad = _law(best=SimpleNamespace(undetermined=("A",), loo_rmse_um=0.774, rmse_um=0.235),
               loo_before_um=0.317)
    shape = SimpleNamespace(law=bad, best="sliding_distance_m")
    diag = SimpleNamespace(shape=shape, partial=["running_in"], final=cand, base=base)
    assert lead(diag) == "shape"
    diag = SimpleNamespace(shape=SimpleNamespace(law=bad, best=None), partial=["running_in"],
                           final=cand, base=base)
    assert lead(diag) == "library"
    good = _law(worse_than_shape=True)  # a lead that predicts: still the best lead
    diag = SimpleNamespace(shape=SimpleNamespace(law=good, best="worn_depth_um"), partial=[],
                           final=base, base=base)
    assert lead(diag) == "law"
    assert lead(SimpleNamespace(shape=None, partial=[], final=base, base=base)) is None


def test_a_laws_error_falls_from_the_base_models_left_out_error_by_the_same_rule():
    """Seen on the fatigue study: the headline said "left-out experiments 0.565 → 0.329 µm"
    (the base model's one unchecked Gauss-Newton step per experiment against the law's
    checked one) and the evidence sentence "0.551 → 0.329 µm". Both sides of the arrow are
    now the law search's checked rule; the diagnosis's own value where the search has none."""
    from jaxwear._analyses.diagnose._headline import errors

    law = _law(status="found", loo_before_um=0.551)
    diag = SimpleNamespace(status="partly_explained", base=SimpleNamespace(rmse=0.511),
                           loo_before={"a": 0.6, "b": 0.53}, shape=SimpleNamespace(law=law),
                           partial=[], final=None)
    e = errors(diag)
    assert (e["before"], e["after"]) == (0.511, 0.31)
    assert (e["loo_before"], e["loo_after"]) == (0.551, 0.33)
    diag.shape = SimpleNamespace(law=_law(status="found", loo_before_um=None))
    assert math.isclose(errors(diag)["loo_before"], math.sqrt((0.6**2 + 0.53**2) / 2))
