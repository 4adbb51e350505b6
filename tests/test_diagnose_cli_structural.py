"""The structural candidates named from the command line on held-out data (issue 41,
item 2): `python -m jaxwear diagnose STUDY --json FILE` in a subprocess, as a user runs it.

The data are not jaxwear's: `benchmarks/hidden_physics.py` (an independent NumPy
implementation of design.md §1-4, sharing no code with the package) made them at 360 nodes x
360 steps with eq 23's M = 25, five times the study's 64 x 72 (adaptive) in each
direction, with 0.3 µm noise on every point of whole-bore scans every 2° (negative depths
kept), true clearances nominal + N(0, 3 µm) and K_d drawn around the study's start. The
commands that made them are in `tests/data/heldout41/README.md`; the truth (truth.json)
is beside each study and not referenced by it.

- `unsymmetric/`: the paper's rig matrix (design.md §6), one scan per specimen at its end
  (900 rows, the design of issue 41); the data have the unsymmetric contact, the study
  states `contact = "symmetric"`. This seed reproduced the issue's crash before the fix
  (exit 1 after the base fit: "jaxwear: ValueError: cannot convert float NaN to integer":
  the symmetric fit drives a clearance to 1.9e-6 mm, and the double_layer refit's first
  trial put it at e^1044 x nominal, a NaN work estimate). The failed trials became
  rejected steps (`tests/test_trial_failures.py`); then, with the adaptive steps capped
  at the stability limit, the same walk stopped at 1.3e-8 mm and the diagnosis took
  537 s with the wrong verdict. Now a fitted clearance is bounded by its plausible range
  (0.1 µm to 100 mm): the walk stops there, flagged, whatever the integrator's steps.
- `double_layer/`: the same matrix measured at 2000, 5000 and 10000 revolutions (2880
  rows: with end scans only this backing, C_b = 1 µm/MPa, is at the edge of detection at
  the family-wise level 1e-3: p 3.6e-3 measured on one seed); the data have a backing
  layer in series with the PTFE layer (design.md §3), the study states a single layer.

Measured (2 cores shared with other jobs, load ~14): see the report in the commit message
and `_diagnose`'s printed line (wall and CPU seconds of each command).
"""

from __future__ import annotations

import json
import math
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DATA = Path(__file__).resolve().parent / "data" / "heldout41"
# The target: a verdict in under 2 minutes on 2 cores. Checked on the CPU time of
# the whole command (start-up, compilations, the diagnosis; user + system): what it takes
# on an idle machine whatever else shares this one (the wall time of a test on 2 cores
# shared with other jobs measured 1.3-2.5x its CPU time). Under 120 s of CPU is under 2
# minutes even on one core.
LIMIT_S = 120.0


def _cpu_children() -> float:
    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    return ru.ru_utime + ru.ru_stime


def _diagnose(study: Path, tmp_path: Path):
    out, js = tmp_path / "out", tmp_path / "diagnosis.json"
    env = dict(os.environ, PYTHONPATH=str(ROOT), JAXWEAR_NO_CACHE="1")
    t0, c0 = time.perf_counter(), _cpu_children()
    r = subprocess.run([sys.executable, "-m", "jaxwear", "diagnose", str(study), "--out",
                        str(out), "--json", str(js)], cwd=tmp_path, env=env,
                       capture_output=True, text=True, timeout=5 * LIMIT_S)
    wall, cpu = time.perf_counter() - t0, _cpu_children() - c0
    assert r.returncode == 0, r.stderr[-3000:]
    print(f"{study.parent.name}: wall {wall:.1f} s, CPU {cpu:.1f} s")
    return json.loads(js.read_text()), cpu, r.stderr


@pytest.mark.parametrize("name, strength", [("unsymmetric", None),
                                            ("double_layer", "backing_compliance_um_per_MPa")])
def test_held_out_structural_effect_is_named_from_the_command_line(tmp_path, name, strength):
    study = DATA / name / "study.toml"
    truth = json.loads((DATA / name / "truth.json").read_text())
    before = sorted(p.name for p in study.parent.iterdir())
    doc, cpu, log = _diagnose(study, tmp_path)
    v = doc["verdict"]
    assert v["status"] == "effect_found" and v["missing_effect"] == name, v["summary"]
    assert doc["candidates"][0]["effect"] == name
    assert cpu < LIMIT_S, f"{cpu:.0f} s of CPU"
    # with it the misfit is at the noise level the data were made with (0.3 µm)
    assert doc["after"]["rmse_um"] <= 1.1 * truth["noise_um"], doc["after"]["rmse_um"]
    # (K_d is not checked against the truth: its standard error, 0.3 %, does not carry the
    # 64 x 72 grid's own error, and the unsymmetric fit lands 1.2 % (3.7 SE) above it)
    fitted = doc["candidates"][0]["parameters"]
    if strength is not None:
        c = fitted[strength]
        true = truth["backing_compliance_um_per_MPa"]
        assert c["stderr"] > 0 and abs(c["value"] - true) < 3 * c["stderr"], (c, true)
    if name == "unsymmetric":
        # the symmetric contact cannot fit unsymmetric wear and pulls the clearances down
        # (truth: nominal + N(0, 3 µm)); where the data would take one below the plausible
        # range (0.1 µm) the fit's bound holds it, and the answer says so first
        base = doc["baseline"]["parameters"]
        held = [k for k, x in base.items() if k.startswith("clearance_mm/")
                and math.isclose(x["value"], 1e-4, rel_tol=1e-6)]
        assert all(base[k]["value"] >= 1e-4 * (1 - 1e-9) for k in base
                   if k.startswith("clearance_mm/")), base
        for k in held:
            assert any(f.startswith(f"OUTSIDE THE MODEL: {k} = 0.0001 is held at the lower")
                       for f in doc["outside_model"]), doc["outside_model"]
    # the inputs are untouched, the outputs under --out
    assert sorted(p.name for p in study.parent.iterdir()) == before
    assert (tmp_path / "out" / "diagnosis.json").is_file()
    assert math.isfinite(doc["wall_time_s"])


def test_the_generators_backing_layer_is_jaxwears_double_layer_at_matched_numerics():
    """The generator's double layer (`--backing-compliance-um-per-MPa`, added for this
    study) against jaxwear's (`double_layer = true`, design.md §3: 1/k = (L - h)/E_w +
    L_b/E_w,b) at the same discrete equations (64 x 72, eq 23 with M = 100): a backing
    of compliance C is a steel backing of thickness C E_w,b, E_w,b from eq 15."""
    import numpy as np

    import jaxwear as jw

    sys.path.insert(0, str(ROOT / "benchmarks"))
    import hidden_physics as hp

    c_um_per_mpa, e_gpa, nu = 1.0, 208.0, 0.28
    e_w = (1 - nu) * e_gpa / ((1 + nu) * (1 - 2 * nu))  # eq 15 [GPa]
    thickness_mm = c_um_per_mpa * 1e-12 * e_w * 1e9 * 1e3  # L_b = C E_w,b
    num = hp.Numerics(nodes=64, steps=72, M=100.0)
    cond = hp.Condition("p276", 276.0, 2000.0, 0.05, interruptions=(2000.0,))
    theirs = {b: hp.wear_history(cond, 0.05e-3, 1e-13, hp.Law("null"), num,
                                 backing=b * 1e-12)["depth"][-1] * 1e6
              for b in (0.0, c_um_per_mpa)}
    cfg = jw.ModelConfig(nodes=num.nodes, steps_per_rev=num.steps, double_layer=True)
    res = jw.simulate(jw.preset("rig", K_d_per_Pa=1e-13, clearance_mm=0.05,
                                backing_thickness_mm=thickness_mm, backing_E_GPa=e_gpa,
                                backing_poisson_ratio=nu),
                      cfg, revolutions=2000, snapshots=[2000.0], M=num.M)
    mine = np.asarray(res.snapshots[-1]) * 1e6
    # the backing changes the profile far beyond the agreement asked for
    assert np.max(np.abs(theirs[c_um_per_mpa] - theirs[0.0])) > 0.05 * theirs[0.0].max()
    assert np.max(np.abs(mine - theirs[c_um_per_mpa])) < 1e-6 * mine.max()
