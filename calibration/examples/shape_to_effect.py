"""From the shape of the missing wear to a physical law, and the error falling
(docs/effects.md, "Add it, watch the error fall").

    python calibration/examples/shape_to_effect.py [--out DIR] [--full]

1. A rig study whose data carry physics jaxwear does not have: impact wear at the force
   reversals (wear deposited where the load points while it swings round, not in
   proportion to sliding), made by an independent generator at finer numerics
   (`benchmarks/hidden_physics.py`, law `impact`; 0.3 µm noise on whole-bore scans).
2. `diagnose --shape`: no candidate explains it; the shape says extra wear not tied to
   sliding (a deposit), following the load's turn rate, made at the reversals, and writes
   `missing_wear.py`.
3. `missing_wear.py` loaded in the study (`[model] effect_files`), its gain calibrated:
   the error falls.
4. The user's physical law in its place (`impact_law.py` below, 20 lines): the deposit
   per step grows with the turn rate beyond ω0, read off the shape's plot; calibrated,
   the error falls as far, with one constant in place of a spline.

By default a small grid (CI runs it); `--full` uses the paper's five experiments.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import jaxwear as jw

ROOT = Path(__file__).resolve().parents[2]

# ---- 4. the user's law, written from the shape's plot (step 2 prints ω0) ------------------
LAW = '''"""Impact wear at the force reversals: a deposit where the load points, growing with how
fast the load direction turns beyond OMEGA0 (read off `diagnose --shape`)."""

import jax.numpy as jnp

import jaxwear as jw
from jaxwear.effects import state_variables, swept_kernel

OMEGA0 = {omega0:.6g}  # deg/s: where the shape's deposit rises


class ImpactWear(jw.Effect):
    name = "impact_wear"
    parameters = {{"impact_wear_nm": jw.EffectParameter(
        1e-9, 0.0, 0.0, 0.0, 1e4, "C: depth x arc per radian of load sweep beyond OMEGA0 "
        "[nm·rad/rad]", scale=0.01)}}
    signature = "extra wear at the force reversals, where the load swings round fast"
    uses_swept_kernel = True  # ctx.swept: the deposit's kernel, computed once per run

    def local_rate(self, p, rate, ctx):
        w = state_variables(ctx.pressure, ctx.slide, ctx.dt, ctx.sliding_distance,
                            ctx.load_angle)["load_turn_rate_deg_per_s"][:, 0]
        swept = jnp.radians(jnp.maximum(w - OMEGA0, 0.0)) * ctx.dt  # rad beyond OMEGA0
        e = p.effect_params["impact_wear_nm"] * swept  # [m·rad] per step
        kernel = ctx.swept  # swept_kernel(ctx.load_angle, nodes), once per run
        return rate + e[:, None] * kernel
'''
# -------------------------------------------------------------------------------------------


def make_study(out: Path, full: bool) -> Path:
    """The impact study (step 1): the independent generator, finer than the study."""
    args = [sys.executable, str(ROOT / "benchmarks" / "hidden_physics.py"), "--law", "impact",
            "--seed", "7", "--out", str(out)]
    if not full:
        cond = out.parent / "conditions.toml"
        cond.write_text('[model]\npreset = "rig"\n' + "".join(
            f'[[experiment]]\nname = "{n}"\nspeed_rpm = {s}\nrevolutions = {r}\n'
            f'clearance_mm = {c}\n' for n, s, r, c in (
                ("n276-r10000", 276, 10000, 0.05), ("n148-r10000", 148, 10000, 0.05),
                ("n230-r10000-c010", 230, 10000, 0.10))))
        args += ["--conditions", str(cond), "--nodes", "96", "--steps", "144", "--M", "100",
                 "--study-numerics", "48x72"]
    p = subprocess.run(args, capture_output=True, text=True)
    if p.returncode:
        raise SystemExit(p.stderr)
    return out / "study.toml"


def with_effect(study: Path, effect: Path, name: str, out: Path) -> Path:
    """A copy of the study that loads `effect` and switches `name` on."""
    shutil.copytree(study.parent, out)
    shutil.copy(effect, out / effect.name)
    text = (out / "study.toml").read_text().replace(
        "[model]\n", f'[model]\neffect_files = ["{effect.name}"]\neffects = ["{name}"]\n', 1)
    (out / "study.toml").write_text(text)
    return out / "study.toml"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=None, help="keep the studies, reports and plots here")
    ap.add_argument("--full", action="store_true", help="the paper's five experiments")
    args = ap.parse_args(argv)
    tmp = None if args.out else tempfile.TemporaryDirectory()
    try:
        return _run(Path(args.out or tmp.name), args.full)
    finally:
        if tmp is not None:
            tmp.cleanup()


def _run(work: Path, full: bool):
    work.mkdir(parents=True, exist_ok=True)
    study = make_study(work / "impact", full)
    # 2. what is missing, and its shape
    d = jw.diagnose(jw.load_study(study), shape=True, verbose=True)
    jw.write_diagnosis(d, work / "diagnose")
    shp = d.shape
    print("verdict:", d.status, "| shape:", shp.best, shp.form)
    print(shp.sentence)
    if shp.best is None:
        raise SystemExit("the shape found nothing")
    # 3. the fitted shape as an effect file, its gain calibrated
    file = work / "diagnose" / "missing_wear.py"
    fitted = jw.calibrate(jw.load_study(with_effect(study, file, "missing_wear",
                                                    work / "with_missing_wear")))
    # 4. the user's law: ω0 read off the deposit along the turn rate
    v = shp.variable("load_turn_rate_deg_per_s", "deposit")
    omega0 = v.threshold()
    print(f"read off the shape: the deposit rises above ω0 ≈ {omega0:.0f} deg/s")
    law_file = work / "impact_law.py"
    law_file.write_text(LAW.format(omega0=omega0))
    law = jw.calibrate(jw.load_study(with_effect(study, law_file, "impact_wear",
                                                 work / "with_law")))
    base = d.base.rmse
    print(f"{'':34s}{'RMSE [µm]':>10s}")
    print(f"{'base model':34s}{base:10.3f}")
    print(f"{'+ the shape, refitted (diagnose)':34s}{shp.rmse_after_um:10.3f}")
    print(f"{'+ missing_wear.py, calibrated':34s}{fitted.rmse_um:10.3f}")
    print(f"{'+ impact_law.py, calibrated':34s}{law.rmse_um:10.3f}")
    print(f"{'noise level':34s}{d.noise_um:10.3f}")
    return d, fitted, law, omega0


if __name__ == "__main__":
    main()
