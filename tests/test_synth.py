"""`jaxwear synth`: the virtual rig writes a valid study whose data are the hidden model plus
the stated noise, measured as a careful experimenter would (interrupted tests, scar scans)."""

import json
import math
import tomllib

import numpy as np
import pytest

from jaxwear import InputError
from jaxwear._study import load_study
from jaxwear._synth import PAPER_MATRIX, parse_hidden, synthesize
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
    st = load_study(out / "study.toml")  # the file contract of DESIGN §6
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
        assert np.all(e.profile.depth >= 0)
        header = (out / f"{name}.csv").read_text().splitlines()[0]
        assert header == "angle_deg,depth_um,revolutions"
    truth = json.loads((out / "truth.json").read_text())
    assert truth["hidden"]["friction"]["friction_coefficient"] == 0.05
    dev = np.array([truth["clearance_mm"][m[0]] - m[3] for m in PAPER_MATRIX]) * 1e3
    assert np.all(np.abs(dev) < 5 * 5.0) and np.std(dev) > 0.5  # real specimens, ~5 µm


def test_data_are_the_hidden_model_plus_the_stated_noise(written):
    """At the true parameters the residuals are white noise of the stated level."""
    from jaxwear.diagnose import Model, lag1_autocorrelation, neighbour_pairs

    out, res = written
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
    assert np.sqrt(np.mean(m.evaluate(u0).r ** 2)) > 1.5 * 0.3


def test_noise_free_data_reproduce_the_model_and_seeds_are_deterministic(tmp_path):
    a = synthesize([], "paper", noise_um=0.0, seed=1, numerics=SMALL, out=tmp_path / "a")
    synthesize([], "paper", noise_um=0.0, seed=1, numerics=SMALL, out=tmp_path / "b")
    for name, *_ in PAPER_MATRIX:
        assert (tmp_path / "a" / f"{name}.csv").read_text() == \
            (tmp_path / "b" / f"{name}.csv").read_text()
    from jaxwear.diagnose import Model

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
