"""Calibration against synthetic data of known truth (design.md §6-7).

The data are made by the model through the public API (`jw.simulate`) with chosen true K_d
and clearances, at finer numerics than the fit's (128 nodes, 144 steps, M = 10 against 64,
72, M = 100: no inverse crime, the fit meets a discretisation it does not share), sampled
as whole scans every 2° by periodic interpolation (numpy), with Gaussian noise of 0.3 µm on
every row (noise around zero outside the scar, negative depths kept). A correct
least-squares fit must then recover the truth within its standard errors, and those
standard errors must match the scatter of the estimates over noise realisations: the known
truth is the independent reason for every check here.

Small fit grid (64 nodes, 72 steps, 3000 revolutions, M = 100) keeps the cost to one
compilation of the study's residual/Jacobian function, shared by all tests of this module.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from scipy import stats

import jaxwear as jw
from jaxwear._inference.calibrate import build_problem, calibrate, fit, parse_fit
from jaxwear._study.study import load_study
from jaxwear.cli import main

NODES, STEPS, M, REVS = 64, 72, 100, 3000
FINE_NODES, FINE_STEPS, M_FINE = 128, 144, 10  # the truth's numerics
SNAPS = (1000.0, 2000.0, 3000.0)
K_D_TRUE = 2.0e-13  # the study file starts from 1e-13
NOISE_UM = 0.3
# name, speed [r/min], nominal clearance [mm], true clearance [mm], interrupted test?
EXPERIMENTS = [("i276", 276.0, 0.05, 0.053, True),
               ("b148", 148.0, 0.05, 0.047, False),
               ("c230", 230.0, 0.10, 0.104, False)]
CFG = jw.ModelConfig(nodes=NODES, steps_per_rev=STEPS)


@pytest.fixture(scope="module")
def truth():
    """True snapshot profiles [µm], (3 snapshots, FINE_NODES), per experiment, at the finer
    numerics."""
    cfg = jw.ModelConfig(nodes=FINE_NODES, steps_per_rev=FINE_STEPS)
    out = {}
    for name, speed, _, c_true, _ in EXPERIMENTS:
        p = jw.preset("rig", speed_rpm=speed, clearance_mm=c_true, K_d_per_Pa=K_D_TRUE)
        res = jw.simulate(p, cfg, revolutions=REVS, snapshots=SNAPS, M=M_FINE)
        out[name] = np.asarray(res.snapshots) * 1e6
    return out


def write_study(root, truth, seed, *, tolerance="inf", noise=NOISE_UM, k_d_start=1e-13,
                blind=None):
    """A study file with noisy profiles of the true model; returns its path.

    Whole scans: every 2° around the bore, noise on every row (zero mean; negative depths
    outside the scar are kept, as an instrument delivers them). The experiment named
    `blind` is measured only at 232-292°, where the bore never wears (true depth 0): its
    rows are noise around zero.
    """
    rng = np.random.default_rng(seed)
    root.mkdir(parents=True, exist_ok=True)
    node_deg = np.arange(FINE_NODES) * 360.0 / FINE_NODES
    angles = np.arange(0.0, 360.0, 2.0) + 0.7  # off the nodes: exercises the interpolation
    lines = ['[model]', 'preset = "rig"', '[model.parameters]', f'K_d_per_Pa = {k_d_start!r}',
             '[numerics]', f'nodes = {NODES}', f'steps_per_rev = {STEPS}',
             f'revolutions_per_update = {M}', '[fit]', f'clearance_tolerance_um = {tolerance}']
    for name, speed, c_nom, _, interrupted in EXPERIMENTS:
        rows = []
        for si, s in enumerate(SNAPS):
            if not interrupted and s != REVS:
                continue
            a = angles
            if name == blind:
                # as many rows as usual (the same array shapes reuse the compiled fit)
                a = np.linspace(232.0, 292.0, len(angles))
            d = np.interp(a, node_deg, truth[name][si], period=360.0)
            if name == blind:
                assert np.all(d == 0)
            y = d + noise * rng.standard_normal(len(a))  # every row, zero mean, unclipped
            rows += [(ai, v, s) for ai, v in zip(a, y)]
        with open(root / f"{name}.csv", "w") as f:
            f.write("angle_deg,depth_um,revolutions\n" if interrupted else "angle_deg,depth_um\n")
            for a, v, s in rows:
                f.write(f"{a:.3f},{v:.6f},{s:g}\n" if interrupted else f"{a:.3f},{v:.6f}\n")
        lines += ['[[experiment]]', f'name = "{name}"', f'speed_rpm = {speed}',
                  f'revolutions = {REVS}', f'clearance_mm = {c_nom}', f'profile = "{name}.csv"']
    path = root / "study.toml"
    path.write_text("\n".join(lines) + "\n")
    return path


TRUE = {"K_d_per_Pa": K_D_TRUE, **{f"clearance_mm/{n}": c for n, _, _, c, _ in EXPERIMENTS}}


N_SEEDS = 10
# Family-wise 1 % over the 10 seeds x 4 parameters: if z = (estimate - noise-free
# estimate)/SE ~ N(0, 1), P(any |z| > K) <= 40 x 2 Φ(-K) = 1 % at K = 3.66.
K_SE = float(stats.norm.isf(0.01 / (2 * N_SEEDS * len(TRUE))))


@pytest.fixture(scope="module")
def seed_fits(truth, tmp_path_factory):
    """Free-clearance fits (τ = inf) of 10 noise realisations."""
    fits = []
    for seed in range(N_SEEDS):
        study = load_study(write_study(tmp_path_factory.mktemp(f"s{seed}"), truth, seed))
        fits.append(calibrate(study, "K_d,clearance"))
    return fits


@pytest.fixture(scope="module")
def noise_free_fit(truth, tmp_path_factory):
    """The fit of the noise-free finer data: its distance from the truth is the fit's
    discretisation bias (64 x 72, M = 100 against the 128 x 144, M = 10 truth)."""
    return calibrate(load_study(write_study(tmp_path_factory.mktemp("nf"), truth, 0,
                                            noise=0.0)), "K_d,clearance")


def test_estimates_within_standard_errors(seed_fits, noise_free_fit):
    """Each fit's error is its noise (within K_SE standard errors, K_SE justified above)
    plus the discretisation bias, which must itself stay below one standard error (the
    fit's grid is fine enough for its data; measured 0.33-0.66 SE). Measured: the largest
    |z| of the noise part 2.5 (seed 5's K_d, 3.2 SE from the truth, bias included)."""
    nf = noise_free_fit
    assert nf.converged, nf.message
    se0 = seed_fits[0].stderr
    bias = np.array([(v - TRUE[n]) for n, v in zip(nf.names, nf.values)])
    assert np.all(np.abs(bias) < 1.0 * se0), dict(zip(nf.names, bias / se0))
    # not the inverse crime: a misfit, but small next to the noise (measured 0.028 µm)
    assert 0.001 < nf.rmse_um < 0.2 * NOISE_UM
    zs = []
    for r in seed_fits:
        assert r.converged, r.message
        assert r.names == nf.names
        assert r.values.dtype == np.float64
        z = (r.values - nf.values) / r.stderr
        assert np.all(np.abs(z) < K_SE), dict(zip(r.names, z))
        zs.append(z)
        # the noise estimate from the residuals recovers the 0.3 µm that was added (900
        # rows: its relative SE is ~2.4 %, so 10 % is 4 of them)
        assert abs(r.noise_um / NOISE_UM - 1) < 0.1
    # the mean over seeds of each z is N(0, 1/10): within 2.8/√10 (Bonferroni over the 4
    # parameters at 1 %); a bias that the noise-free fit does not show, or SEs too small,
    # fail this first
    mean_z = np.mean(zs, axis=0)
    assert np.all(np.abs(mean_z) < stats.norm.isf(0.01 / 8) / math.sqrt(N_SEEDS)), mean_z


def test_standard_errors_match_scatter(seed_fits):
    """The reported SE against the sample scatter of 10 estimates: with σ the true
    standard deviation, (n-1) s²/σ² is chi-square(9), so SE/s lies in
    [√(9/χ²₉(1-α)), √(9/χ²₉(α))] = [0.57, 2.72] at α = 0.125 % per tail (family-wise 1 %
    over the 4 parameters). Measured: 0.72-1.63."""
    values = np.array([r.values for r in seed_fits])
    se = np.array([r.stderr for r in seed_fits])
    scatter = values.std(axis=0, ddof=1)
    ratio = se.mean(axis=0) / scatter
    n, a = len(seed_fits), 0.01 / (2 * len(TRUE))
    lo = math.sqrt((n - 1) / stats.chi2.isf(a, n - 1))
    hi = math.sqrt((n - 1) / stats.chi2.ppf(a, n - 1))
    assert np.all((ratio > lo) & (ratio < hi)), (dict(zip(seed_fits[0].names, ratio)), lo, hi)


@pytest.fixture(scope="module")
def study0(truth, tmp_path_factory):
    return load_study(write_study(tmp_path_factory.mktemp("base"), truth, 0))


@pytest.mark.parametrize("kd_factor,c_factor", [(100.0, 1.5), (0.01, 0.5), (1e4, 1.0)])
def test_recovers_from_a_bad_start(study0, seed_fits, kd_factor, c_factor):
    """K_d 100x off and clearances 50 % off converge to the same minimum as a good start."""
    ref = seed_fits[0]
    start = {"K_d_per_Pa": 1e-13 * kd_factor}
    start.update({f"clearance_mm/{n}": c * c_factor for n, _, c, _, _ in EXPERIMENTS})
    if kd_factor >= 1e4:
        # this start wears through the layer: the robust start must have to back off first
        n, speed, c, _, _ = EXPERIMENTS[0]
        p = jw.preset("rig", speed_rpm=speed, clearance_mm=c, K_d_per_Pa=start["K_d_per_Pa"])
        with pytest.raises(jw.WornThroughError):
            jw.simulate(p, CFG, revolutions=REVS, snapshots=SNAPS, M=M)
    r = calibrate(study0, "K_d,clearance", start=start)
    assert r.converged, r.message
    # the same minimum, to a small fraction of the standard errors (the misfit is flat there)
    assert np.all(np.abs(r.values - ref.values) < 0.01 * ref.stderr), (r.values, ref.values)


def test_prior_pulls_clearances_to_nominal(truth, tmp_path, seed_fits):
    """τ = 5 µm: a Gaussian prior around nominal shrinks the estimates towards it and
    tightens them (posterior precision = data precision + 1/τ²); τ = 0 fixes them."""
    free = seed_fits[0]
    prior = calibrate(load_study(write_study(tmp_path / "t5", truth, 0, tolerance=5)))
    assert prior.converged, prior.message
    nominal = {f"clearance_mm/{n}": c for n, _, c, _, _ in EXPERIMENTS}
    for i, name in enumerate(free.names):
        if name in nominal:
            j = prior.names.index(name)
            assert abs(prior.values[j] - nominal[name]) < abs(free.values[i] - nominal[name])
            assert prior.stderr[j] < min(free.stderr[i], 5e-3)
            assert prior.stderr[j] > 1 / math.sqrt(1 / free.stderr[i] ** 2 + 1 / 5e-3 ** 2) / 2

    fixed_study = load_study(write_study(tmp_path / "t0", truth, 0, tolerance=0))
    assert parse_fit(fixed_study, "K_d,clearance") == ["K_d_per_Pa", "clearance_mm"]
    fixed = fit(build_problem(fixed_study, parse_fit(fixed_study, "K_d,clearance")))
    assert fixed.names == ["K_d_per_Pa"]
    # the fitted model is the true model at the nominal clearances with the fitted K_d
    for ei, (name, speed, c_nom, _, _) in enumerate(EXPERIMENTS):
        p = jw.preset("rig", speed_rpm=speed, clearance_mm=c_nom, K_d_per_Pa=fixed.values[0])
        res = jw.simulate(p, CFG, revolutions=REVS, snapshots=SNAPS, M=M)
        snaps = np.asarray(res.snapshots) * 1e6
        want = snaps if name == "i276" else snaps[-1:]
        np.testing.assert_allclose(fixed.snapshots_um[ei, :len(want)], want, rtol=1e-9,
                                   atol=1e-9)


def test_cli_json_contract(truth, tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("JAXWEAR_NO_CACHE", "1")
    study = write_study(tmp_path / "study", truth, 1, tolerance=5)
    out, js = tmp_path / "out", tmp_path / "deep" / "er" / "cal.json"
    assert main(["calibrate", str(study), "--out", str(out), "--json", str(js)]) == 0
    doc = json.loads(js.read_text())
    assert json.loads((out / "calibration.json").read_text()) == doc
    assert set(doc["parameters"]) == set(TRUE)
    for name, entry in doc["parameters"].items():
        assert set(entry) == {"value", "stderr"}
        assert abs(entry["value"] - TRUE[name]) < 3 * entry["stderr"]
    assert isinstance(doc["rmse_um"], float) and 0.2 < doc["rmse_um"] < 0.4
    assert doc["converged"] is True
    assert doc["correlation"]["names"] == list(doc["parameters"])
    corr = np.array(doc["correlation"]["matrix"])
    np.testing.assert_allclose(np.diag(corr), 1.0, atol=1e-9)
    assert set(doc["rmse_per_experiment_um"]) == {n for n, *_ in EXPERIMENTS}
    for name, *_ in EXPERIMENTS:
        assert (out / f"fit_{name}.png").stat().st_size > 0
    text = capsys.readouterr().out
    assert "K_d_per_Pa" in text and "1/Pa" in text and "RMSE" in text


def test_non_identifiable_parameter_is_flagged(truth, tmp_path):
    """An experiment measured only where the bore never touches the pin (232-292°, depth 0)
    says nothing about its clearance: the fit must flag it and give it no standard error."""
    r = calibrate(load_study(write_study(tmp_path, truth, 0, blind="c230")))
    i = r.names.index("clearance_mm/c230")
    assert not np.isfinite(r.stderr[i])
    assert any("clearance_mm/c230" in f for f in r.flags), r.flags
    assert r.to_json()["parameters"]["clearance_mm/c230"]["stderr"] is None
    # K_d stays determined by the other experiments
    assert np.isfinite(r.stderr[r.names.index("K_d_per_Pa")])


BAD = {
    "nan": ("angle_deg,depth_um\n0,1.0\n10,nan\n", "line 3"),
    "inf": ("angle_deg,depth_um\n0,1.0\n10,inf\n", "line 3"),
    "angle": ("angle_deg,depth_um\n0,1.0\n360,0.5\n", "line 3"),
    "angle_negative": ("angle_deg,depth_um\n-5,1.0\n", "line 2"),
    "empty": ("", "empty"),
    "columns": ("angle,depth\n0,1.0\n", "line 1"),
    "text": ("angle_deg,depth_um\n0,abc\n", "line 2"),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_cli_bad_data_exit_2(tmp_path, capsys, monkeypatch, case):
    monkeypatch.setenv("JAXWEAR_NO_CACHE", "1")
    text, where = BAD[case]
    (tmp_path / "p.csv").write_text(text)
    (tmp_path / "s.toml").write_text('[model]\npreset = "rig"\n[[experiment]]\nname = "e"\n'
                                     'revolutions = 1000\nprofile = "p.csv"\n')
    assert main(["calibrate", str(tmp_path / "s.toml"), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "p.csv" in err and where in err, err


def test_cli_unknown_fit_parameter_exit_2(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("JAXWEAR_NO_CACHE", "1")
    (tmp_path / "p.csv").write_text("angle_deg,depth_um\n0,1.0\n")
    (tmp_path / "s.toml").write_text('[model]\npreset = "rig"\n[[experiment]]\nname = "e"\n'
                                     'revolutions = 1000\nprofile = "p.csv"\n')
    assert main(["calibrate", str(tmp_path / "s.toml"), "--fit", "K_d,bogus"]) == 2
    assert "bogus" in capsys.readouterr().err


def test_cli_nothing_to_fit_exit_2(tmp_path, capsys, monkeypatch):
    """--fit clearance with clearance_tolerance_um = 0 (clearances fixed) leaves nothing."""
    monkeypatch.setenv("JAXWEAR_NO_CACHE", "1")
    (tmp_path / "p.csv").write_text("angle_deg,depth_um\n0,1.0\n")
    (tmp_path / "s.toml").write_text('[model]\npreset = "rig"\n[fit]\nclearance_tolerance_um = 0\n'
                                     '[[experiment]]\nname = "e"\nrevolutions = 1000\n'
                                     'profile = "p.csv"\n')
    assert main(["calibrate", str(tmp_path / "s.toml"), "--fit", "clearance"]) == 2
    assert "clearance_tolerance_um = 0" in capsys.readouterr().err


def test_enabled_effects_strengths_are_fitted(tmp_path):
    """A study that switches running-in on fits its two parameters too, the nested
    amplitude starting from 'off' (the base model), so the first evaluation is the base fit."""
    (tmp_path / "p.csv").write_text("angle_deg,depth_um\n0,1.0\n180,2.0\n")
    (tmp_path / "s.toml").write_text('[model]\npreset = "rig"\neffects = ["running_in"]\n'
                                     '[[experiment]]\nname = "e"\nrevolutions = 1000\n'
                                     'profile = "p.csv"\n')
    study = load_study(tmp_path / "s.toml")
    keys = parse_fit(study, "K_d")
    assert keys == ["K_d_per_Pa", "running_in_amplitude", "running_in_distance_m"]
    problem = build_problem(study, keys)
    assert problem.names == ("K_d_per_Pa", "running_in_amplitude", "running_in_distance_m")
    start = dict(zip(problem.names, np.asarray(problem.start)))
    assert start["running_in_amplitude"] == 0.0  # off: nested at the base model
    assert start["running_in_distance_m"] > 0  # fitted in log space
