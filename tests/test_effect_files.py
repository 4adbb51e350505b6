"""User effects from files: `[model] effect_files = [...]` (design.md §7, docs/effects.md).

A study names Python files; every `jaxwear.Effect` subclass they define is registered before
the study is built, in every verb. Checked here: a loaded effect switched on changes the
model exactly as its law says (a rate factor 1 + g with g = 1 is K_d doubled, to round-off);
`synth --conditions` hides it and writes a study that still finds the file; `calibrate`
recovers its strength from that study's noisy data (made at finer numerics); loaded but
not switched on it is a diagnose candidate; bad files exit 2 naming the file and line;
loading is idempotent; the effect file is an input no output may replace.
"""

import csv
import json
from pathlib import Path

import numpy as np
import pytest

import jaxwear as jw
from jaxwear import InputError
from jaxwear._physics.effects import registered_effects
from jaxwear.cli import main

ROOT = Path(__file__).resolve().parents[1]

EFFECTS = '''\
"""Two effects for the tests."""
import jaxwear as jw

P_REF = 1.0e6  # Pa


class UniformGain(jw.Effect):
    """K_d -> K_d (1 + g)."""

    name = "uniform_gain"
    parameters = {"uniform_gain": jw.EffectParameter(
        1.0, 0.0, 0.0, 0.0, 10.0, "g [-]", scale=0.1, realistic=0.5)}
    signature = "more wear everywhere"

    def local_rate(self, p, rate, ctx):
        return rate * (1.0 + p.effect_params["uniform_gain"])


class PressureGain(jw.Effect):
    """K_d -> K_d (1 + b p / 1 MPa)."""

    name = "pressure_gain"
    parameters = {"pressure_gain_per_MPa": jw.EffectParameter(
        1.0, 0.0, 0.0, 0.0, 10.0, "b [1/MPa]", scale=0.1, realistic=0.5)}
    signature = "more wear where the pressure is high"

    def local_rate(self, p, rate, ctx):
        return rate * (1.0 + p.effect_params["pressure_gain_per_MPa"] * ctx.pressure / P_REF)
'''

STUDY = """\
[model]
preset = "rig"
effect_files = {files}
effects = {effects}
[model.parameters]
K_d_per_Pa = {kd}
{extra}
[numerics]
nodes = 40
steps_per_rev = 36
revolutions_per_update = 100

[[experiment]]
name = "a"
speed_rpm = 276
revolutions = 2000
clearance_mm = 0.05
"""


def _study(folder: Path, files=("effects.py",), effects=(), kd=1e-13, extra="",
           name="study.toml") -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    text = STUDY.format(files=json.dumps(list(files)), effects=json.dumps(list(effects)),
                        kd=kd, extra=extra)
    (folder / name).write_text(text)
    return folder / name


@pytest.fixture
def folder(tmp_path):
    (tmp_path / "effects.py").write_text(EFFECTS)
    return tmp_path


def _profiles(out: Path) -> np.ndarray:
    with open(out / "profiles.csv") as f:
        return np.array([float(r["depth_um"]) for r in csv.DictReader(f)])


def test_switched_on_in_simulate_is_its_law(folder):
    """uniform_gain = 1 doubles the local rate: the profile of K_d doubled, to round-off
    (both with the effect on, so that one compiled model serves both runs)."""
    on = _study(folder, effects=["uniform_gain"], extra="uniform_gain = 1.0", name="on.toml")
    doubled = _study(folder, effects=["uniform_gain"], kd=2e-13, name="doubled.toml")
    for s in (on, doubled):
        assert main(["simulate", str(s), "--out", str(folder / s.stem)]) == 0
    h_on, h_2 = _profiles(folder / "on"), _profiles(folder / "doubled")
    assert h_2.max() > 1.0  # µm: a real scar
    np.testing.assert_allclose(h_on, h_2, rtol=1e-9, atol=1e-9 * h_2.max())


def test_synth_conditions_then_calibrate_and_diagnose_candidate(folder):
    """`synth --conditions` hides the file's effect (truth at finer numerics, noise); the
    written study (in another folder) still loads the file; loaded but off, the effect is a
    diagnose candidate; switched on, `calibrate` recovers its strength."""
    from jaxwear._analyses.diagnose import candidate_names

    cond = _study(folder)
    out = folder / "virtual"
    assert main(["synth", "--hidden", "pressure_gain=2", "--noise-um", "0.05", "--seed", "3",
                 "--conditions", str(cond), "--out", str(out)]) == 0
    text = (out / "study.toml").read_text()
    assert 'effect_files = ["../effects.py"]' in text
    study = jw.load_study(out / "study.toml")
    assert "pressure_gain" in candidate_names(study.config)
    assert "uniform_gain" in candidate_names(study.config)
    (out / "on.toml").write_text(text.replace("[model]\n",
                                              '[model]\neffects = ["pressure_gain"]\n', 1))
    assert main(["calibrate", str(out / "on.toml"), "--out", str(out / "fit"), "--json",
                 str(out / "fit.json")]) == 0
    fit = json.loads((out / "fit.json").read_text())["parameters"]["pressure_gain_per_MPa"]
    assert fit["stderr"] is not None and fit["stderr"] < 0.5
    assert abs(fit["value"] - 2.0) < 4 * fit["stderr"] + 0.05, fit


# (file name, its text, pattern the one-line message must match: file and line)
BAD = [
    ("syntax.py", "import jaxwear as jw\n\nclass A(jw.Effect)\n    name = 'a'\n",
     r"syntax\.py: line 3: syntax error"),
    ("raises.py", "import jaxwear as jw\n\nx = 1\nraise RuntimeError('no lubricant table')\n",
     r"raises\.py: line 4: RuntimeError: no lubricant table \(raised while loading"),
    ("deep.py", "def f():\n    return 1 / 0\n\n\nf()\n",
     r"deep\.py: line 2: ZeroDivisionError"),
    ("none.py", "import jaxwear as jw\nfrom jaxwear.effects import Creep\nX = 1\n",
     r"none\.py: defines no jaxwear\.Effect subclass"),
    ("invalid.py", "import jaxwear as jw\n\n\nclass NoStrength(jw.Effect):\n    name = 'ns'\n"
                   "    parameters = {'ns_m': jw.EffectParameter(1.0, 1.0, 1.0, 0.1, 10.0, 'x',"
                   " log=True)}\n",
     r"invalid\.py: line 4: effect ns: needs a strength parameter"),
    ("clash.py", "import jaxwear as jw\n\n\nclass Mu(jw.Effect):\n    name = 'mu2'\n"
                 "    parameters = {'friction_coefficient': jw.EffectParameter(1.0, 0.0, 0.0, "
                 "0.0, 1.0, 'mu')}\n",
     r"clash\.py: line 4: parameter 'friction_coefficient' of effect 'mu2' already belongs to "
     r"effect 'friction' from .*jaxwear/_physics/effects/friction\.py"),
    ("taken.py", "import jaxwear as jw\n\n\nclass Creep2(jw.Effect):\n    name = 'creep'\n"
                 "    parameters = {'creep2_gain': jw.EffectParameter(1.0, 0.0, 0.0, 0.0, 1.0, "
                 "'g')}\n",
     r"taken\.py: line 4: effect name 'creep' is taken by Creep from .*effects/creep\.py"),
]


@pytest.mark.parametrize("name,text,pattern", BAD, ids=[b[0] for b in BAD])
def test_bad_effect_file_exits_2_naming_file_and_line(tmp_path, capsys, name, text, pattern):
    (tmp_path / name).write_text(text)
    study = _study(tmp_path, files=(name,))
    before = registered_effects()
    assert main(["simulate", str(study), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
    assert __import__("re").search(pattern, err), err
    assert registered_effects() == before  # nothing half registered
    assert not (tmp_path / "__pycache__").exists()  # nothing written beside the file


def test_missing_or_malformed_effect_files_name_the_study_line(tmp_path, capsys):
    study = _study(tmp_path, files=("gone.py",))
    assert main(["simulate", str(study), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "study.toml: line 3: model.effect_files: effect file 'gone.py' not found" in err
    (tmp_path / "s2.toml").write_text(study.read_text().replace('["gone.py"]', '"gone.py"'))
    assert main(["simulate", str(tmp_path / "s2.toml"), "--out", str(tmp_path / "o")]) == 2
    assert "s2.toml: line 3: model.effect_files must be a list" in capsys.readouterr().err


def test_loading_is_idempotent_and_conflicts_name_both_files(folder):
    first = jw.load_study(_study(folder, files=("effects.py", "effects.py"), name="a.toml"))
    eff = registered_effects()["pressure_gain"]
    n = len(registered_effects())
    second = jw.load_study(_study(folder / "sub", files=("../effects.py",), name="b.toml"))
    assert registered_effects()["pressure_gain"] is eff and len(registered_effects()) == n
    assert first.params().get("pressure_gain_per_MPa") == 0.0  # loaded, off: base model
    assert first.config.effects == ()
    assert "pressure_gain_per_MPa" in second.params().effect_params
    # a different class under a taken name: refused, naming both files
    (folder / "other.py").write_text(EFFECTS.replace("UniformGain", "Other").split(
        "class PressureGain")[0])
    with pytest.raises(InputError, match=r"other\.py: line 7: effect name 'uniform_gain' is "
                                         r"taken by UniformGain from .*effects\.py"):
        jw.load_study(_study(folder, files=("effects.py", "other.py"), name="c.toml"))
    assert registered_effects()["pressure_gain"] is eff
    # the file edited in place (a notebook): its new version replaces its old effects
    (folder / "effects.py").write_text(EFFECTS.replace("b [1/MPa]", "b per MPa"))
    jw.load_study(folder / "a.toml")
    new = registered_effects()["pressure_gain"]
    assert new is not eff and new.parameters["pressure_gain_per_MPa"].doc == "b per MPa"


def test_effect_file_is_an_input_no_output_replaces(folder):
    study = jw.load_study(_study(folder))
    assert (folder / "effects.py").resolve() in [p.resolve() for p in jw.input_files(study)]
    with pytest.raises(InputError, match="refusing to replace an input"):
        jw.open_outputs(study, folder, planned=["effects.py"])
    assert (folder / "effects.py").read_text() == EFFECTS


def test_the_example_effect_file_loads(tmp_path):
    """calibration/examples/debris_effect.py, as a study beside it would name it."""
    src = ROOT / "calibration" / "examples" / "debris_effect.py"
    (tmp_path / "debris_effect.py").write_text(src.read_text())
    study = jw.load_study(_study(tmp_path, files=("debris_effect.py",), effects=["debris"],
                                 extra="debris_gain = 0.5"))
    assert study.config.effects == ("debris",)
    assert float(study.params().get("debris_gain")) == 0.5


# ------------------------------------------------------------------ issue 41: hooks checked

HOOK = '''import jax.numpy as jnp
import jaxwear as jw


class Bad(jw.Effect):
    name = "bad"
    parameters = {{"bad_gain": jw.EffectParameter(1.0, {default}, 0.0, 0.0, 10.0, "g [-]",
                                                 scale=0.1)}}

    def local_rate(self, p, rate, ctx):
        g = p.effect_params["bad_gain"]
        return {body}
'''

# (case, default strength, local_rate's return, the message's pattern). Before issue 41:
# nan-on exit 1 "contact solve did not converge ... please report"; shape TypeError
# dot_general; raises "ValueError: hook failed" (no file, no line); nan-off as a diagnose
# candidate ~6 min of halved K_d; negative exit 0 with negative depths.
BAD_HOOKS = [
    ("nan-on", 1.0, "jnp.where(g > 0, jnp.nan, 1.0) * rate",
     r"bad\.py: line 5: Bad\.local_rate at default \(bad_gain = 1\) returned NaN"),
    ("nan-on-default-off", 0.0, "jnp.where(g > 0, jnp.nan, 1.0) * rate",
     r"bad\.py: line 5: Bad\.local_rate at on \(off \+ scale\) \(bad_gain = 0\.1\) returned NaN"),
    ("shape", 1.0, "rate[:, :3]",
     r"bad\.py: line 5: Bad\.local_rate at off \(bad_gain = 0\) returned shape \(6, 3\); "
     r"expected .*\(steps, nodes\)"),
    ("raises", 1.0, "(_ for _ in ()).throw(ValueError('hook failed'))",
     r"bad\.py: line 12: Bad\.local_rate at off \(bad_gain = 0\) raised ValueError: hook "
     r"failed"),
    ("nan-off", 0.0, "rate * jnp.nan",
     r"bad\.py: line 5: Bad\.local_rate at off \(bad_gain = 0\) returned NaN at 48 of 48"),
    ("negative", 1.0, "rate * (1.0 - 3.0 * g)",
     r"bad\.py: line 5: Bad\.local_rate at default \(bad_gain = 1\) returned negative wear"),
    ("python-if", 1.0, "rate * (2.0 if g > 5 else 1.0)",  # fine eagerly, not in the loop
     r"bad\.py: line 12: Bad\.local_rate at off \(bad_gain = 0\) raised "
     r"TracerBoolConversionError: Python control flow .* jnp\.where"),
]


@pytest.mark.parametrize("case,default,body,pattern", BAD_HOOKS, ids=[b[0] for b in BAD_HOOKS])
@pytest.mark.parametrize("on", [True, False], ids=["switched-on", "candidate"])
def test_a_bad_hook_is_refused_when_the_file_loads(tmp_path, capsys, case, default, body,
                                                   pattern, on):
    """Each hook is tried on a small cycle at off, default (and realistic) strengths when
    the file is loaded: a bad answer is exit 2 naming the file, the line, the class and
    hook, the strength and what was wrong; nothing is registered, nothing written."""
    (tmp_path / "bad.py").write_text(HOOK.format(default=default, body=body))
    study = _study(tmp_path, files=("bad.py",), effects=["bad"] if on else [])
    before = registered_effects()
    assert main(["simulate", str(study), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
    assert __import__("re").search(pattern, err), err
    assert registered_effects() == before
    assert not (tmp_path / "o").exists()


def test_a_hook_that_fails_later_names_its_file(tmp_path, capsys):
    """A hook that works on the check's 8 nodes and raises on the study's 40: the run's
    one line (exit 1) names the file and line, not only "ValueError: ..."."""
    body = ("rate if ctx.pressure.shape[1] <= 8 else "
            "(_ for _ in ()).throw(ValueError('only 8 nodes'))")
    (tmp_path / "late.py").write_text(HOOK.format(default=1.0, body=body).replace(
        '"bad"', '"late"').replace("bad_gain", "late_gain"))
    study = _study(tmp_path, files=("late.py",), effects=["late"])
    assert main(["simulate", str(study), "--out", str(tmp_path / "o")]) == 1
    err = capsys.readouterr().err
    last = err.strip().splitlines()[-1]  # after the progress line
    assert "Traceback" not in err, err
    assert __import__("re").match(r"jaxwear: .*late\.py: line 12: in \S+: ValueError: only 8 "
                                  r"nodes$", last), err


def test_a_nan_at_an_untried_strength_names_the_effect_file(tmp_path, capsys):
    """NaN only above a strength the load-time check does not try (the study sets 6): the
    run's contact solve fails, and its one line names the effect and its file (it said
    "... please report the study", the file never named)."""
    body = "jnp.where(g > 5, jnp.nan, 1.0) * rate"
    (tmp_path / "bad.py").write_text(HOOK.format(default=1.0, body=body))
    study = _study(tmp_path, files=("bad.py",), effects=["bad"], extra="bad_gain = 6.0")
    assert main(["simulate", str(study), "--out", str(tmp_path / "o")]) == 1
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert "did not converge" in last and "bad (from " in last and "bad.py)" in last, last
    assert not (tmp_path / "o" / "profiles.csv").exists()
