"""`jaxwear design` with the shape's variables as rivals (issue 44): `--between
shape:A,shape:B`, the default goal after a diagnosis with a tied pair (`--from`), and the
diagnose pointer for tied variables of the shape.

The rival's model is the study's plus the shape's correction along one variable: with its
coefficients zero it is the study's model exactly (the shape's nesting), and its Jacobian
column of a coefficient is checked against central differences of the candidates' own
runs (an independent path through the start values, the packing and the batched runs)."""

from __future__ import annotations

import dataclasses
import json
from types import SimpleNamespace as V

import numpy as np
import pytest

from jaxwear._analyses.design import check_between, parse_shape, parse_vary, plan_candidates
from jaxwear._analyses.design.runs import run_candidates
from jaxwear._analyses.design.tied import tied_pair
from jaxwear._analyses.diagnose._model import Model
from jaxwear._analyses.diagnose.shape.result import ShapeResult
from jaxwear._analyses.diagnose.shape.text import next_test, rival_of
from jaxwear._core.errors import InputError
from jaxwear._inference.packing import study_fit_keys
from jaxwear._physics.effects.shape import ShapeBasis, ShapeVariable
from jaxwear._study.study import load_study
from jaxwear.cli import build_parser, main

NUM = {"nodes": 48, "steps_per_rev": 36, "revolutions_per_update": 100}


@pytest.fixture(scope="module")
def tiny_rig(tmp_path_factory):
    """Two rig experiments of 1000 revolutions at 48 x 36, data from synth (its truth at
    finer numerics), noise 0.3 µm."""
    from jaxwear._analyses.synth import paper_conditions, synthesize

    st = paper_conditions(NUM)
    keep = ("n276-r10000", "n148-r10000")
    st = st.with_experiments([dataclasses.replace(e, revolutions=1000.0)
                              for e in st.experiments if e.name in keep])
    res = synthesize([], st, noise_um=0.3, seed=3, out=tmp_path_factory.mktemp("rig"))
    return res.study_path


# ------------------------------------------------------------------ names


def test_shape_rival_names():
    assert parse_shape("shape:pressure_MPa") == ("pressure_MPa", "factor")
    assert parse_shape("shape:deposit:load_N") == ("load_N", "deposit")
    with pytest.raises(InputError, match="names no variable of the shape"):
        parse_shape("shape:pressure")
    with pytest.raises(InputError, match="variables of events in the cycle"):
        parse_shape("shape:deposit:pressure_MPa")


@pytest.mark.parametrize("between, needle", [
    ("shape:pressure_MPa,shape:pressure_MPa", "two different explanations"),
    ("shape:warp_speed,shape:pressure_MPa", "names no variable of the shape"),
    ("shape:deposit:bore_angle_deg,base", "a deposit is made along"),
    ("pressure_MPa,base", "unknown explanation 'pressure_MPa'; expected base, "
                          "shape:VARIABLE"),
])
def test_bad_shape_rivals_exit_2_naming_between(tiny_rig, tmp_path, capsys, between, needle):
    rc = main(["design", str(tiny_rig), "--between", between, "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert rc == 2, err
    assert "--between" in err and needle in err, err
    assert "Traceback" not in err


def test_check_between_takes_shape_rivals(tiny_rig):
    st = load_study(tiny_rig)
    assert check_between(st, ["shape:pressure_MPa", "shape:sliding_speed_m_per_s"]) == [
        "shape:pressure_MPa", "shape:sliding_speed_m_per_s"]
    assert check_between(st, ["base", "shape:deposit:load_N"])[1] == "shape:deposit:load_N"


# ------------------------------------------------------------------ the rival's runs


def _fake_fit(model):
    """What `run_candidates` reads of a fit, at the model's start values (u = 0)."""
    u = np.zeros(len(model.names))
    return V(names=list(model.names), values=model.values(u), u=u, problem=model.ext)


def test_shape_rival_at_zero_is_the_study_and_its_column_matches_differences(tiny_rig):
    """A rival `shape:pressure_MPa` whose correction is zero predicts every candidate as
    the study's model does (exp(0) = 1: the same depths, the same K_d column); the column
    of one coefficient equals central differences of the candidates' runs at ±h of that
    coefficient's start (h = 0.02, a 2 % rate factor)."""
    st = load_study(tiny_rig)
    keys = study_fit_keys(st)
    plan = plan_candidates(st, parse_vary("speed_rpm=150,300,revolutions=600,1200", st))
    var = ShapeVariable("pressure_MPa", 8, tuple(np.linspace(0.2, 4.0, 17)), "factor")
    basis = ShapeBasis((var,))
    base_fit = _fake_fit(Model(st, candidates=[]))
    shape_fit = _fake_fit(Model(st, candidates=[], shape=basis))
    zero = {k: 0.0 for k in var.keys()}
    r0 = run_candidates(st, base_fit, keys, plan.runs, plan.points, is_timed=False)
    r1 = run_candidates(st, shape_fit, keys, plan.runs, plan.points, is_timed=False,
                        shape=basis, shape_start=zero)
    assert r0.snaps.max() > 0.1  # the runs wear
    np.testing.assert_allclose(r1.snaps, r0.snaps, rtol=0, atol=1e-9 * r0.snaps.max())
    kd = list(r1.names).index("K_d_per_Pa")
    np.testing.assert_allclose(r1.J[..., kd], r0.J[..., list(r0.names).index("K_d_per_Pa")],
                               rtol=1e-9, atol=1e-9 * np.abs(r0.J).max())
    key = var.keys()[4]
    h = 0.02
    rp = run_candidates(st, shape_fit, keys, plan.runs, plan.points, is_timed=False,
                        shape=basis, shape_start={**zero, key: h})
    rm = run_candidates(st, shape_fit, keys, plan.runs, plan.points, is_timed=False,
                        shape=basis, shape_start={**zero, key: -h})
    fd = (rp.snaps - rm.snaps) / (2 * h)
    col = r1.J[..., list(r1.names).index(key)]
    assert np.abs(col).max() > 1e-3 * r0.snaps.max()  # the coefficient moves the depth
    np.testing.assert_allclose(col, fd, rtol=0, atol=2e-3 * np.abs(col).max())


# ------------------------------------------------------------------ the default goal


DIAG_EFFECT = {"verdict": {"status": "effect_found", "missing_effect": "pressure_exponent",
                           "alternatives": ["unsymmetric", "speed_dependence"]}}
DIAG_SHAPE = {"verdict": {"status": "unexplained", "missing_effect": None,
                          "alternatives": []},
              "shape": {"best": "pressure_MPa", "form": "factor",
                        "alternatives": ["sliding_speed_m_per_s", "load_N"]}}


def test_tied_pair_of_a_diagnosis():
    assert tied_pair(DIAG_EFFECT) == (["pressure_exponent", "speed_dependence"],
                                      "verdict.alternatives")
    assert tied_pair(DIAG_SHAPE) == (["shape:pressure_MPa", "shape:sliding_speed_m_per_s"],
                                     "shape.alternatives")
    dep = {"verdict": {"alternatives": []},
           "shape": {"best": "load_turn_rate_deg_per_s", "form": "deposit",
                     "alternatives": ["deposit:load_N"]}}
    assert tied_pair(dep)[0] == ["shape:deposit:load_turn_rate_deg_per_s",
                                 "shape:deposit:load_N"]
    cmd = {"verdict": {"alternatives": []},
           "shape": {"best": "pressure_MPa", "alternatives": [],
                     "next_test": "jaxwear design s.toml --goal separate --between "
                                  "shape:pressure_MPa,shape:load_N"}}
    assert tied_pair(cmd)[0] == ["shape:pressure_MPa", "shape:load_N"]
    # structural alternatives are not rivals for --between; no tie: None
    assert tied_pair({"verdict": {"missing_effect": "creep",
                                  "alternatives": ["double_layer"]}}) is None
    with pytest.raises(InputError, match="--from: expected a diagnosis document"):
        tied_pair({"goal": "separate"})


def test_from_a_diagnosis_the_goal_becomes_separate(tmp_path):
    p = tmp_path / "diagnosis.json"
    p.write_text(json.dumps(DIAG_SHAPE))
    args = build_parser().parse_args(["design", "s.toml", "--from", str(p)])
    opts = args.verb.options(args)
    assert opts["goal"] == "separate"
    assert opts["between"] == ["shape:pressure_MPa", "shape:sliding_speed_m_per_s"]
    assert opts["note"].startswith("design: goal separate between shape:pressure_MPa and "
                                   "shape:sliding_speed_m_per_s")
    # an explicit goal or pair wins over the diagnosis
    args = build_parser().parse_args(["design", "s.toml", "--from", str(p), "--goal",
                                      "parameters"])
    assert args.verb.options(args)["goal"] == "parameters"
    args = build_parser().parse_args(["design", "s.toml", "--from", str(p), "--between",
                                      "base,running_in"])
    assert args.verb.options(args)["between"] == ["base", "running_in"]
    # no tie: the default goal, and the first line says why
    p.write_text(json.dumps({"verdict": {"alternatives": []}}))
    args = build_parser().parse_args(["design", "s.toml", "--from", str(p)])
    opts = args.verb.options(args)
    assert opts["goal"] == "parameters" and "names no tied pair" in opts["note"]


@pytest.mark.parametrize("content, needle", [(None, "cannot read the diagnosis"),
                                             ("{not json", "not a JSON document"),
                                             ("[1, 2]", "expected a diagnosis document")])
def test_bad_diagnosis_exits_2_naming_from(tiny_rig, tmp_path, capsys, content, needle):
    p = tmp_path / "d.json"
    if content is not None:
        p.write_text(content)
    rc = main(["design", str(tiny_rig), "--from", str(p), "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert rc == 2 and "--from" in err and needle in err, err
    assert "Traceback" not in err


# ------------------------------------------------------------------ the diagnose pointer


def _var(name, form="factor", share=1.0, stand_in_for=None, significant=True):
    return V(name=name, form=form, explained_fraction=share, stand_in_for=stand_in_for,
             significant=significant,
             label=name if form == "factor" else f"deposit:{name}")


def test_shape_pointer_names_the_design_command():
    """The rival: the first other of the variables the data cannot tell apart
    (`confounded`); else a stand-in explaining at least 90 % of what the best explains;
    else none. An alternative the data told apart (AIC within ln 20, preferred by the unique
    shares or the left-out error) is no rival."""
    best = _var("pressure_MPa", share=1.03)
    speed = _var("sliding_speed_m_per_s", share=1.02, stand_in_for="pressure_MPa")
    load = _var("load_N", share=0.5, stand_in_for="pressure_MPa")
    res = [best, speed, load]
    assert rival_of("pressure_MPa", "factor", res, ("load_N",),
                    ("pressure_MPa", "load_N")) == "load_N"
    assert rival_of("pressure_MPa", "factor", [best, load], ("load_N",)) is None
    assert rival_of("pressure_MPa", "factor", res) == "sliding_speed_m_per_s"
    assert rival_of("pressure_MPa", "factor", [best, load]) is None
    assert rival_of(None, None, res) is None
    cmd = next_test("s.toml", "pressure_MPa", "factor", res)
    assert cmd == ("jaxwear design s.toml --goal separate --between "
                   "shape:pressure_MPa,shape:sliding_speed_m_per_s")
    dep = [_var("load_turn_rate_deg_per_s", "deposit", 0.9)]
    assert next_test("s.toml", "load_turn_rate_deg_per_s", "deposit", dep,
                     ("deposit:load_turn_deg_per_deg",),
                     ("deposit:load_turn_rate_deg_per_s",
                      "deposit:load_turn_deg_per_deg")).endswith(
        "--between shape:deposit:load_turn_rate_deg_per_s,shape:deposit:load_turn_deg_per_deg")
    # the command parses back into the pair design takes (--from)
    doc = {"verdict": {"alternatives": []},
           "shape": ShapeResult("base", "pressure_MPa", "factor", (), 0.05, 1.0, 1.0, None,
                                0, "none", "", next_test=cmd).to_json()}
    assert doc["shape"]["next_test"] == cmd
    assert tied_pair(doc)[0] == ["shape:pressure_MPa", "shape:sliding_speed_m_per_s"]


# ------------------------------------------------------------------ a rival fitted


@pytest.fixture(scope="module")
def threshold_rig(tmp_path_factory):
    """Two rig experiments of 2000 revolutions with a pressure-threshold law hidden
    (benchmarks/hidden_physics.py, the independent NumPy generator, at 96 x 72 and M 10),
    studied at 48 x 36 with the paper integrator at M 100; noise 0.3 µm."""
    import dataclasses as dc
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    import hidden_physics as hp

    conds = tuple(dc.replace(c, revolutions=2000.0) for c in hp.PAPER[:2])
    gen = hp.generate(hp.Law("threshold", 1.0, threshold_MPa=1.2), conds, seed=5,
                      noise_um=0.3, num=hp.Numerics(nodes=96, steps=72, M=10.0))
    path = hp.write(tmp_path_factory.mktemp("thr"), gen, conds, study_numerics=(48, 36))
    st = load_study(path)
    return dc.replace(st, integrator="paper", revolutions_per_update=100.0)


def test_a_shape_rival_fits_better_than_the_study_and_design_ranks_with_it(threshold_rig):
    """The rival `shape:pressure_MPa` on data with a pressure law: its refit ends below the
    study's misfit (the correction nests the study, and the refit keeps the better of its
    two starts), its information is a symmetric positive definite matrix, and `design
    --between shape:pressure_MPa,base` ranks candidates by a finite expected χ² ≥ 0 with
    the rival's fit and its correction's coefficients reported."""
    from jaxwear._analyses.design import design, fit_shape
    from jaxwear._analyses.design.rank import _fit

    st, base = _fit(threshold_rig, study_fit_keys(threshold_rig), False, "the study", [])
    rival = fit_shape(st, base, "shape:pressure_MPa")
    assert rival.rss <= base.rss * (1 + 1e-6)
    assert (base.rss - rival.rss) / base.noise_um ** 2 > 2.0  # the law is there to find
    info = rival.information
    assert np.allclose(info, info.T) and np.all(np.linalg.eigvalsh(info) > 0)
    res = design(threshold_rig, goal="separate", between=["shape:pressure_MPa", "base"],
                 vary=parse_vary("speed_rpm=150,300,revolutions=2000", threshold_rig))
    assert np.all(np.isfinite(res.values)) and np.all(res.values >= 0)
    assert res.info["chi2_between_now"] >= -1e-6  # base RSS − rival RSS, in σ²
    # 150 and 300 r/min lie beyond the study's 276: flagged (the rival is flat there)
    assert all(d["beyond_study_speeds"] for d in res.details)
    assert any("beyond the study's (276-276 r/min)" in f for f in res.info["flags"])
    pars = res.info["fits"]["shape:pressure_MPa"]["parameters"]
    assert sum(k.startswith("shape_pressure_MPa_") for k in pars) == 10
