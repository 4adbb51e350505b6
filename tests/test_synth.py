"""`jaxwear synth`: the virtual rig writes a valid study whose data are the hidden model plus
the stated noise, measured as a careful experimenter would (interrupted tests, whole-bore
scans with zero-mean noise), with the truth computed at finer numerics than the study's."""

import json
import math
import tomllib

import numpy as np
import pytest

from jaxwear import InputError
from jaxwear._analyses.synth import PAPER_MATRIX, parse_hidden, synthesize
from jaxwear._study.study import load_study
from jaxwear.cli import main

SMALL = dict(nodes=64, steps_per_rev=72, revolutions_per_update=500)


def test_parse_hidden():
    h = parse_hidden(["running_in=0.5", "friction"])
    assert h["running_in"] == {"running_in_amplitude": 0.5}
    assert h["friction"]["friction_coefficient"] == pytest.approx(0.1)  # its realistic value
    h = parse_hidden(["creep,double_layer=0.4", "running_in", "running_in_distance_m=8"])
    assert h["double_layer"] == {"backing_compliance_um_per_MPa": 0.4}
    assert h["running_in"]["running_in_distance_m"] == 8.0
    assert parse_hidden(["unsymmetric"]) == {"unsymmetric": {}}
    with pytest.raises(InputError, match="unknown effect"):
        parse_hidden(["humidity"])
    with pytest.raises(InputError, match="must lie in"):
        parse_hidden(["friction=-0.1"])
    with pytest.raises(InputError, match="not a number"):
        parse_hidden(["creep=lots"])


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    out = tmp_path_factory.mktemp("synth")
    res = synthesize(["friction=0.05"], "paper", noise_um=0.3, seed=7, out=out, numerics=SMALL)
    return out, res


def test_written_study_is_a_valid_interrupted_test_design(written):
    out, res = written
    st = load_study(out / "study.toml")  # the file contract of design.md §6
    raw = tomllib.loads((out / "study.toml").read_text())
    lines = [ln for ln in (out / "study.toml").read_text().splitlines()
             if not ln.startswith("#")]
    assert not any("truth" in ln for ln in lines)  # the study does not reference the truth
    assert raw["model"]["contact"] == "unsymmetric" and "effects" not in raw["model"]
    assert [e.name for e in st.experiments] == [m[0] for m in PAPER_MATRIX]
    for e, (name, speed, revs, clearance) in zip(st.experiments, PAPER_MATRIX):
        # nominal conditions, as the experimenter set them
        assert e.overrides["speed_rpm"] == speed and e.overrides["clearance_mm"] == clearance
        assert e.revolutions == revs
        pts = sorted(set(e.profile.revolutions.tolist()))
        assert pts == [2000.0, 5000.0, 10000.0] + ([15000.0] if revs == 15000 else [])
        ang = np.degrees(e.profile.angle)
        assert np.allclose(ang / 2.0, np.round(ang / 2.0))  # every 2 degrees
        for r in pts:  # the whole circumference at every interruption
            np.testing.assert_allclose(np.sort(ang[e.profile.revolutions == r]),
                                       np.arange(0.0, 360.0, 2.0), atol=1e-9)
        assert np.sum(e.profile.depth < 0) > 20  # noise around zero outside the scar
        header = (out / f"{name}.csv").read_text().splitlines()[0]
        assert header == "angle_deg,depth_um,revolutions"
    truth = json.loads((out / "truth.json").read_text())
    assert truth["hidden"]["friction"]["friction_coefficient"] == 0.05
    dev = np.array([truth["clearance_mm"][m[0]] - m[3] for m in PAPER_MATRIX]) * 1e3
    assert np.all(np.abs(dev) < 5 * 5.0) and np.std(dev) > 0.5  # real specimens, ~5 µm
    # the truth at finer numerics than the study states: 2x nodes and steps, M/10
    assert truth["truth_numerics"] == {"nodes": 128, "steps_per_rev": 144,
                                       "revolutions_per_update": 50.0, "integrator": "paper"}
    assert truth["numerics"]["nodes"] == 64


@pytest.fixture(scope="module")
def same_grid(tmp_path_factory):
    """Data from the discretisation the study states (refine=1): only for checking the
    noise generator itself, since a fit on such data commits the inverse crime."""
    out = tmp_path_factory.mktemp("synth1")
    res = synthesize(["friction=0.05"], "paper", noise_um=0.3, seed=7, out=out, numerics=SMALL,
                     refine=1, refine_updates=1)
    return out, res


def test_data_are_the_hidden_model_plus_the_stated_noise(same_grid):
    """At the true parameters (same grid) the residuals are white noise of the stated level."""
    from jaxwear._analyses.diagnose import Model, lag1_autocorrelation, neighbour_pairs

    out, res = same_grid
    m = Model(load_study(out / "study.toml"))
    t = res.truth
    u = np.zeros(len(m.names))
    u[m.index["K_d_per_Pa"]] = m.u_of("K_d_per_Pa", t["K_d_per_Pa"])
    for name, c in t["clearance_mm"].items():
        u[m.index[f"clearance_mm/{name}"]] = m.u_of(f"clearance_mm/{name}", c)
    u[m.index["friction_coefficient"]] = m.u_of("friction_coefficient", 0.05)
    r = m.evaluate(u).r
    n = len(r)
    assert n > 300
    assert abs(np.mean(r)) < 4 * 0.3 / math.sqrt(n)
    # chi-square with n dof: |s²/σ² - 1| < 4 sqrt(2/n); rows rounded to 0.1 nm in the file
    assert abs(np.mean(r ** 2) / 0.09 - 1) < 4 * math.sqrt(2 / n)
    rho, z = lag1_autocorrelation(r, neighbour_pairs(m))
    assert abs(z) < 4
    # the same study without its hidden friction misses it badly (the effect is visible)
    u0 = u.copy()
    u0[m.index["friction_coefficient"]] = 0.0
    # (a chi-square excess of > 10 of its standard deviations; the scan is mostly unworn bore)
    r0 = m.evaluate(u0).r
    assert np.sum(r0 ** 2) / 0.09 - n > 10 * math.sqrt(2 * n)


def test_noise_free_data_reproduce_the_model_and_seeds_are_deterministic(tmp_path):
    kw = dict(numerics=SMALL, refine=1, refine_updates=1)
    a = synthesize([], "paper", noise_um=0.0, seed=1, out=tmp_path / "a", **kw)
    synthesize([], "paper", noise_um=0.0, seed=1, out=tmp_path / "b", **kw)
    for name, *_ in PAPER_MATRIX:
        assert (tmp_path / "a" / f"{name}.csv").read_text() == \
            (tmp_path / "b" / f"{name}.csv").read_text()
    from jaxwear._analyses.diagnose import Model

    m = Model(a.study)
    t = a.truth
    u = np.zeros(len(m.names))
    u[m.index["K_d_per_Pa"]] = m.u_of("K_d_per_Pa", t["K_d_per_Pa"])
    for name, c in t["clearance_mm"].items():
        u[m.index[f"clearance_mm/{name}"]] = m.u_of(f"clearance_mm/{name}", c)
    np.testing.assert_allclose(m.evaluate(u).pred, m.measured, atol=1e-4)  # CSV: 4 decimals


def test_cli_synth_with_conditions_file(tmp_path):
    cond = tmp_path / "cond.toml"
    cond.write_text(
        '[model]\npreset = "rig"\n[model.parameters]\nK_d_per_Pa = 1e-13\n'
        '[numerics]\nnodes = 64\nsteps_per_rev = 72\nrevolutions_per_update = 500\n'
        + "".join(f'[[experiment]]\nname = "{n}"\nspeed_rpm = {s}\nrevolutions = {r}\n'
                  f'clearance_mm = {c}\n' for n, s, r, c in PAPER_MATRIX))
    out = tmp_path / "out"
    rc = main(["synth", "--hidden", "creep", "--hidden", "running_in=0.5",
               "--conditions", str(cond), "--noise-um", "0.2", "--seed", "4",
               "--out", str(out)])
    assert rc == 0
    truth = json.loads((out / "truth.json").read_text())
    assert set(truth["hidden"]) == {"creep", "running_in"}
    assert truth["noise_um"] == 0.2
    assert load_study(out / "study.toml").config.nodes == 64
    assert main(["synth", "--hidden", "humidity", "--out", str(tmp_path / "x")]) == 2
    assert main(["synth", "--hidden", "friction", "--noise-um", "-1",
                 "--out", str(tmp_path / "x")]) == 2


def test_hidden_unsymmetric_writes_a_symmetric_study(tmp_path):
    res = synthesize(["unsymmetric"], "paper", noise_um=0.3, seed=2, numerics=SMALL,
                     out=tmp_path)
    assert load_study(tmp_path / "study.toml").config.contact == "symmetric"
    assert res.truth["hidden"] == {"unsymmetric": {}}


def _rows(res):
    return {e.name: (np.degrees(e.profile.angle), e.profile.revolutions, e.profile.depth * 1e6)
            for e in res.study.experiments}


def test_noise_is_zero_mean_on_every_point_and_the_truth_is_finer(tmp_path):
    """Same seed, noise 0 vs 0.3 µm: the same truth; the difference is the noise alone,
    Gaussian with zero mean on every row (no clipping, no selection)."""
    clean = synthesize([], "paper", noise_um=0.0, seed=11, numerics=SMALL)
    noisy = synthesize([], "paper", noise_um=0.3, seed=11, numerics=SMALL)
    c, n = _rows(clean), _rows(noisy)
    diff = np.concatenate([n[k][2] - c[k][2] for k in c])
    assert all(np.array_equal(n[k][0], c[k][0]) for k in c)
    m = len(diff)
    assert m == 180 * (3 * 4 + 4)  # 5 experiments, 3 or 4 interruptions, every 2°
    assert abs(np.mean(diff)) < 4 * 0.3 / math.sqrt(m)
    assert abs(np.std(diff) / 0.3 - 1) < 4 / math.sqrt(2 * m)
    assert abs(np.mean(diff < 0) - 0.5) < 4 * 0.5 / math.sqrt(m)
    # the clean truth is not the study's own discretisation: the coarse model at the true
    # parameters misses it by a small but nonzero amount
    from jaxwear._analyses.diagnose import Model

    m_ = Model(clean.study)
    t = clean.truth
    u = np.zeros(len(m_.names))
    u[m_.index["K_d_per_Pa"]] = m_.u_of("K_d_per_Pa", t["K_d_per_Pa"])
    for name, cl in t["clearance_mm"].items():
        u[m_.index[f"clearance_mm/{name}"]] = m_.u_of(f"clearance_mm/{name}", cl)
    r = m_.evaluate(u).r
    peak = max(float(np.max(v[2])) for v in c.values())
    assert 1e-3 < np.sqrt(np.mean(r ** 2)) < 0.1 * peak


def test_registration_offset_shifts_the_scan(tmp_path):
    """Offset δ: the row at scan angle a is the bushing at a + δ, i.e. the offset-free
    row at angle a + δ (δ a multiple of the 2° spacing, so no interpolation differs)."""
    a = synthesize([], "paper", noise_um=0.0, seed=12, numerics=SMALL)
    b = synthesize([], "paper", noise_um=0.0, seed=12, numerics=SMALL, angle_offset_deg=6.0,
                   out=tmp_path)
    ra, rb = _rows(a), _rows(b)
    for k in ra:
        for r in np.unique(ra[k][1]):
            da = ra[k][2][ra[k][1] == r]
            db = rb[k][2][rb[k][1] == r]
            np.testing.assert_allclose(db, np.roll(da, -3), atol=1e-4)  # 6° = 3 rows
    truth = json.loads((tmp_path / "truth.json").read_text())
    assert set(truth["angle_offset_deg"].values()) == {6.0}
    assert "angle_offset" not in (tmp_path / "study.toml").read_text()


def test_synth_never_overwrites_an_input(tmp_path):
    cond = tmp_path / "study.toml"
    text = ('[model]\npreset = "rig"\n[numerics]\nnodes = 64\nsteps_per_rev = 72\n'
            'revolutions_per_update = 500\n[[experiment]]\nname = "a"\nrevolutions = 2000\n'
            'profile = "a.csv"\n')
    cond.write_text(text)
    data = "angle_deg,depth_um\n" + "".join(f"{a},0.0\n" for a in range(0, 360, 10))
    (tmp_path / "a.csv").write_text(data)
    before = {p.name: p.read_text() for p in tmp_path.iterdir()}
    assert main(["synth", "--conditions", str(cond), "--out", str(tmp_path)]) == 2
    assert {p.name: p.read_text() for p in tmp_path.iterdir()} == before
    with pytest.raises(InputError, match="overwrite"):  # a data file alone, too
        other = tmp_path / "other.toml"
        other.write_text(text.replace('profile = "a.csv"', 'profile = "sub/a.csv"'))
        (tmp_path / "sub").mkdir()
        (tmp_path / "sub" / "a.csv").write_text(data)
        synthesize([], other, out=tmp_path / "sub")


def test_the_truth_computes_no_effect_it_does_not_hide():
    """An effect registered in the process (an effect file a notebook loaded) and not
    hidden is not part of the true model: its hook is never called (it was, at zero
    strength, in every stage of the run: a synth 4-15x slower after the shape's worked
    example). The conftest puts the registry back."""
    import jaxwear as jw

    class Trap(jw.Effect):
        name = "trap_effect"
        parameters = {"trap_gain": jw.EffectParameter(
            1.0, 0.0, 0.0, 0.0, 10.0, "g [-]", scale=0.1, realistic=0.5)}
        signature = "a hook that must not run"

        def local_rate(self, p, rate, ctx):
            raise AssertionError("the truth computed an effect it does not hide")

    jw.register_effect(Trap())
    res = synthesize(["speed_dependence"], "paper", noise_um=0.3, seed=4, numerics=SMALL)
    assert set(res.truth["hidden"]) == {"speed_dependence"}
