"""`jaxwear design` (issue 44): the selection code on a linear-Gaussian toy whose D-optimal
and greedy choices are provable, a one-parameter rig design whose information is checked
against finite differences of independent forward runs, the JSON contract of the CLI on a
small rig study, and bad input (exit 2 naming the option)."""

from __future__ import annotations

import dataclasses
import json
import math
import tomllib

import numpy as np
import pytest

from jaxwear._analyses.design import (
    _goal_value,
    _greedy,
    _logdet,
    design,
    measure_points,
    parse_vary,
    scan_metric,
)
from jaxwear._core.errors import InputError
from jaxwear._study.study import load_study
from jaxwear.cli import main

NUM = {"nodes": 64, "steps_per_rev": 72, "revolutions_per_update": 250}


# ------------------------------------------------------------------ linear-Gaussian toy


def test_d_optimal_greedy_on_a_linear_gaussian_toy():
    """y = x·θ + noise, θ in R². det(I + x xᵀ) = det(I)(1 + xᵀ I⁻¹ x): the best single
    candidate maximises xᵀ I⁻¹ x, i.e. lies along the least-known direction. With
    I0 = diag(1, 10) and unit candidates at angles t, the first pick is t = 0 (the weak
    axis); after it (I = diag(2, 10)) the second is again the one maximising xᵀ I⁻¹ x among
    the others: t = 0 is excluded, so the next nearest to the first axis (t = ±15°) wins
    over t = 90° (1/2 cos² vs 1/10)."""
    t = np.deg2rad(np.arange(-90, 91, 15))
    X = np.stack([np.cos(t), np.sin(t)], axis=1)
    Ic = np.einsum("ci,cj->cij", X, X)
    I0 = np.diag([1.0, 10.0])
    idx = [0, 1]

    def value_of(info):
        return _goal_value("parameters", info, idx, [], np.eye(2), np.ones(2), None, 1.0)[0]

    # the value is log det of the marginal information (here: the whole matrix)
    v = value_of(I0[None] + Ic)
    want = np.log(10.0) + np.log1p(np.einsum("ci,ij,cj->c", X, np.linalg.inv(I0), X))
    np.testing.assert_allclose(v, want, rtol=1e-12)
    picks, vals = _greedy(value_of, I0, Ic, "higher", 3)
    assert round(float(np.rad2deg(t[picks[0]]))) == 0
    assert round(abs(float(np.rad2deg(t[picks[1]])))) == 15
    # every pick maximises x^T I^-1 x over the candidates not yet taken (the determinant
    # lemma), I the information with the earlier picks added
    info = I0.copy()
    for p in picks:
        q = np.einsum("ci,ij,cj->c", X, np.linalg.inv(info), X)
        q[[x for x in picks[:picks.index(p)]]] = -np.inf
        assert q[p] == pytest.approx(q.max(), rel=1e-12)
        info = info + Ic[p]
    assert len(set(picks)) == 3  # a set of different experiments, not copies
    # the cumulative value after the set is the log det of the summed information
    assert vals[-1] == pytest.approx(_logdet(I0 + Ic[picks].sum(0)), rel=1e-12)


def test_standard_error_goal_prefers_the_named_parameter():
    """--for θ1: the standard error of θ1 after the candidate is smallest for a candidate
    along θ1 (given θ2 well known and the two uncorrelated)."""
    t = np.deg2rad(np.array([0.0, 45.0, 90.0]))
    X = np.stack([np.cos(t), np.sin(t)], axis=1)
    Ic = np.einsum("ci,cj->cij", X, X)
    I0 = np.diag([1.0, 1.0])
    v, se = _goal_value("parameters", I0[None] + Ic, [0, 1], [0], np.eye(2),
                        np.ones(2), None, 1.0)
    assert int(np.argmin(v)) == 0
    np.testing.assert_allclose(se[0, 0], math.sqrt(1 / 2), rtol=1e-12)  # var 1/(1+1)


def test_scan_metric_is_the_rows_gram_matrix():
    """W^T W of a scan every 2° over 64 nodes: its sum is the row count (each row's
    weights sum to 1, and W^T W sums to Σ_rows (Σ w)² = rows)."""
    M = scan_metric(64, 2.0)
    assert M.sum() == pytest.approx(180.0)
    assert np.allclose(M, M.T)


# ------------------------------------------------------------------ the rig, one parameter


@pytest.fixture(scope="module")
def small_rig(tmp_path_factory):
    """Two rig experiments of 2000 revolutions at 64 x 72, data from synth (its truth at
    twice the nodes and steps, 10x finer updates: no inverse crime), noise 0.3 µm."""
    from jaxwear._analyses.synth import paper_conditions, synthesize

    st = paper_conditions(NUM)
    keep = ("n276-r10000", "n148-r10000")
    st = st.with_experiments([dataclasses.replace(e, revolutions=2000.0)
                              for e in st.experiments if e.name in keep])
    out = tmp_path_factory.mktemp("rig")
    res = synthesize([], st, noise_um=0.3, seed=2, out=out)
    return res.study_path


def test_k_d_alone_longest_run_wins_and_information_matches_finite_differences(small_rig):
    """K_d alone (clearances held): a candidate's information is Σ (∂y/∂ln K_d)² / σ² over
    its scan rows, and ∂y/∂ln K_d ≈ y grows with the run's length, so the longest run in
    the range wins and the value rises with revolutions. The information of the winner is
    checked against central differences of two forward runs (`simulate`'s model at
    K_d (1 ± h)) read at the scan angles: an independent path through the bookkeeping."""
    from jaxwear._analyses.sweep import sweep

    st = dataclasses.replace(load_study(small_rig), clearance_tolerance_um=0.0)
    vary = parse_vary("revolutions=1000:4000:4", st)
    res = design(st, goal="parameters", vary=vary)
    revs = [c["revolutions"] for c in res.plan.conditions]
    assert res.plan.conditions[int(res.order[0])]["revolutions"] == 4000
    for r in set(c.get("speed_rpm") for c in res.plan.conditions):
        v = [res.values[i] for i in np.argsort(revs) if res.plan.conditions[i].get(
            "speed_rpm") == r]
        assert np.all(np.diff(v) > 0)
    # the winner's information (u = ln K_d), from the design ...
    best = int(res.order[0])
    info_design = math.exp(res.values[best]) - math.exp(res.baseline)
    # ... and from finite differences of forward runs of the same conditions
    sigma = res.info["fit"]["error_scale_um"]
    kd = res.info["fit"]["parameters"]["K_d_per_Pa"]["value"]
    cond = res.plan.conditions[best]
    run = res.plan.runs[res.plan.run[best]]
    h = 1e-4
    pts = measure_points(cond["revolutions"])
    exp = dataclasses.replace(run, revolutions=cond["revolutions"])
    sw = sweep(st.with_experiments([exp]), grid={"K_d_per_Pa": [kd * (1 + h), kd * (1 - h)],
                                                 "revolutions": pts},
               choose_resolution=False)
    n = sw.depth_um.shape[-1]
    ang = np.arange(0.0, 360.0, 2.0)
    nodes = np.arange(n + 1) * 360.0 / n
    info_fd = 0.0
    for j in range(len(pts)):
        a, b = sw.depth_um[0, j], sw.depth_um[1, j]
        da = np.interp(ang, nodes, np.append(a, a[0]))
        db = np.interp(ang, nodes, np.append(b, b[0]))
        dy = (da - db) / (math.log(1 + h) - math.log(1 - h))
        info_fd += float(np.sum(dy ** 2)) / sigma ** 2
    print("information: design", info_design, "finite differences", info_fd)
    assert info_design == pytest.approx(info_fd, rel=2e-3)


# ------------------------------------------------------------------ the CLI


def test_design_json_contract(small_rig, tmp_path):
    """design.md §7: goal, between, candidates (conditions, value) best first, recommended
    (speed_rpm, clearance_mm, revolutions, measure_at, value) of --budget different
    experiments; the stanza pastes into a study and the conditions load as one."""
    out, js = tmp_path / "out", tmp_path / "d.json"
    rc = main(["design", str(small_rig), "--vary",
               "speed_rpm=150:280:2,revolutions=1000:3000:3", "--budget", "2",
               "--out", str(out), "--json", str(js)])
    assert rc == 0
    doc = json.loads(js.read_text())
    assert doc["goal"] == "parameters" and doc["between"] == []
    vals = [c["value"] for c in doc["candidates"]]
    assert len(vals) == 6 and vals == sorted(vals, reverse=True)
    for c in doc["candidates"]:
        assert set(c["conditions"]) == {"speed_rpm", "revolutions"}
    rec = doc["recommended"]
    assert len(rec) == 2
    for r in rec:
        for k in ("speed_rpm", "clearance_mm", "revolutions", "measure_at", "value"):
            assert k in r
        assert r["measure_at"][-1] == r["revolutions"]
    assert (rec[0]["speed_rpm"], rec[0]["revolutions"]) != (rec[1]["speed_rpm"],
                                                            rec[1]["revolutions"])
    assert rec[0]["value"] == vals[0] and rec[1]["value"] > rec[0]["value"]
    assert json.loads((out / "design.json").read_text())["goal"] == "parameters"
    stanza = tomllib.loads((out / "next_experiment.toml").read_text())
    assert stanza["experiment"][0]["revolutions"] == rec[0]["revolutions"]
    cond = load_study(out / "next_conditions.toml")
    assert [e.name for e in cond.experiments] == [r["name"] for r in rec]
    assert (out / "design.png").stat().st_size > 0


@pytest.mark.parametrize("argv, needle", [
    (["--vary", "speed_rpm=abc"], "--vary speed_rpm"),
    (["--vary", "speed_rpm"], "--vary"),
    (["--vary", "bore_colour=1:2"], "--vary: unknown key 'bore_colour'"),
    (["--vary", "speed_rpm=1e9:2e9:3"], "plausible range"),
    (["--vary", "hours=1:5"], "--vary: unknown key 'hours'"),
    (["--goal", "best"], "--goal"),
    (["--goal", "separate"], "--between"),
    (["--between", "running_in"], "--between"),
    (["--between", "running_in,warp_drive"], "unknown explanation 'warp_drive'"),
    (["--budget", "0"], "--budget"),
    (["--for", "spring_N_per_m"], "--for"),
    (["--at", "100"], "--at: only with --goal forecast"),
])
def test_bad_input_exits_2_naming_the_option(small_rig, tmp_path, capsys, argv, needle):
    rc = main(["design", str(small_rig), *argv, "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert rc == 2, err
    assert needle in err
    assert "Traceback" not in err
    assert not (tmp_path / "o" / "design.json").exists()


def test_parse_vary_keeps_value_lists():
    st = load_study_like()
    v = parse_vary("speed_rpm=100,200,300,revolutions=1000:2000", st)
    assert list(v["speed_rpm"]) == [100, 200, 300]
    assert len(v["revolutions"]) == 5  # LO:HI without N: 5 values
    with pytest.raises(InputError, match="given twice"):
        parse_vary("speed_rpm=1:2,speed_rpm=3:4", st)


def load_study_like():
    from jaxwear._analyses.synth import paper_conditions

    return paper_conditions(NUM)


def test_diagnose_points_at_design_when_effects_are_tied():
    """The verdict's sentence names the command where alternatives are tied (effects
    only: `--between` takes effects, not the structural candidates)."""
    from types import SimpleNamespace

    from jaxwear._analyses.diagnose._text import design_pointer

    diag = SimpleNamespace(alternatives=["unsymmetric", "speed_dependence"],
                           study=SimpleNamespace(path="s.toml"))
    s = design_pointer(diag, "pressure_exponent")
    assert "jaxwear design s.toml --between pressure_exponent,speed_dependence" in s
    assert design_pointer(SimpleNamespace(alternatives=["unsymmetric"],
                                          study=diag.study), "creep") == ""


def test_separate_chi2_by_woodbury_equals_the_direct_solve():
    """d^T (a I + U U^T)^-1 d from d·d, U^T d and U^T U (Woodbury), against the direct
    solve; and repeated scans (a → a/n) only raise it."""
    from jaxwear._analyses.design import _chi2

    rng = np.random.default_rng(0)
    U = rng.standard_normal((40, 3))
    d = rng.standard_normal(40)
    a = 0.7
    direct = d @ np.linalg.solve(a * np.eye(40) + U @ U.T, d)
    got = _chi2(np.array([d @ d]), (U.T @ d)[None], (U.T @ U)[None], np.array([a]))[0]
    assert got == pytest.approx(direct, rel=1e-10)
    more = _chi2(np.array([d @ d]), (U.T @ d)[None], (U.T @ U)[None], np.array([a / 4]))[0]
    assert more > got


def test_timed_candidates_are_next_measurements_of_the_experiment():
    """The boom: a candidate is the next maximum-depth measurement of its experiment, all
    in one run (no model evaluation here)."""
    from jaxwear._analyses.design import plan_candidates
    from jaxwear._analyses.predict.grid import training_study

    st = training_study(load_study("calibration/boom/study.toml"), 15)
    plan = plan_candidates(st, parse_vary("hours=16:25:10", st))
    assert plan.size == 10 and len(plan.runs) == 1 and plan.continuation == "boom"
    assert [m[0] for m in plan.measure_at] == list(np.linspace(16, 25, 10))
    with pytest.raises(InputError, match="unknown key 'speed_rpm'"):
        parse_vary("speed_rpm=100:200", st)
