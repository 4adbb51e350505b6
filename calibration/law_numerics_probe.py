"""Is a law's bias numerical or a definition? (docs/shape_validation.md, "Numerical error
of the law's constants"). jaxwear's law model with the generator's grammar law written as
a `LawSpec`, at the generator's true K_d, clearances and constants (truth.json), its rows
against the generator's noise-free profiles (truth_profiles.csv, interpolated to the scan
angles as the generator does), at each of several numerics; and the Gauss-Newton step
that difference makes with the model's own Jacobian and the clearance priors at σ = 0.3
µm: the bias a fit of noise-free data would have, in standard errors.

    python calibration/law_numerics_probe.py STUDY.toml CASE LEVELS [TRUTH_DIR]

CASE: g_hinge_v or g_dep_power_W (a study written by benchmarks/hidden_physics.py with
that law); LEVELS: e.g. 48x72,96x144; TRUTH_DIR: where truth_profiles.csv is (default:
beside the study; another generation of the same seed at finer numerics, to compare
with a finer truth). Not a test (seconds to a minute per level).
"""

from __future__ import annotations

import csv
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np


def main(argv=None):
    import jaxwear as jw
    from jaxwear._analyses.diagnose._model import Model
    from jaxwear._analyses.diagnose.law.search import LAW_KEYS
    from jaxwear._physics.effects.law import LAW_EFFECT, LawSpec, Term, searching
    from jaxwear._study.resolution import at_level

    argv = sys.argv[1:] if argv is None else argv
    study_path, case = Path(argv[0]), argv[1]
    levels = [tuple(int(x) for x in s.split("x")) for s in argv[2].split(",")]
    tdir = Path(argv[3]) if len(argv) > 3 else study_path.parent
    truth = json.loads((study_path.parent / "truth.json").read_text())
    law = truth["law"]
    prof = {}
    with open(tdir / "truth_profiles.csv") as fh:
        for row in csv.DictReader(fh):
            prof.setdefault((row["experiment"], float(row["revolutions"])), []).append(
                float(row["depth_um"]))

    def interp(vals, ang):  # the generator's periodic linear interpolation
        n = len(vals)
        x = np.mod(np.asarray(ang) * n / 360.0, n)
        i0 = np.floor(x).astype(int) % n
        w = x - np.floor(x)
        return vals[i0] * (1 - w) + vals[(i0 + 1) % n] * w

    def spec(steps):
        if case == "g_hinge_v":
            return LawSpec("factor", (Term("hinge", "sliding_speed_m_per_s",
                                           law["g_v1_m_per_s"], a=law["g_exponent"],
                                           x0=law["g_v0_m_per_s"] / law["g_v1_m_per_s"]),),
                           law["strength"])
        if case == "g_dep_power_W":  # the grammar's D is per step of the model's cycle
            return LawSpec("deposit", (Term("power", "load_N", law["g_W1_N"],
                                            a=law["g_dep_exponent"]),),
                           law["strength"] * law["g_dep_steps"] / steps)
        raise SystemExit(f"case must be g_hinge_v or g_dep_power_W, got {case!r}")

    st0 = jw.load_study(study_path)
    for lev in levels:
        t0 = time.process_time()
        st = at_level(st0, lev)
        vals = spec(lev[1]).values()
        held = {k: v for k, v in vals.items() if k not in LAW_KEYS}
        start = {"K_d_per_Pa": truth["K_d_per_Pa"]}
        start.update({f"clearance_mm/{k}": v for k, v in truth["clearance_mm"].items()})
        start.update({k: vals[k] for k in LAW_KEYS})
        with searching():
            st2 = dataclasses.replace(
                st, config=st.config.replace(effects=tuple(st.config.effects) + (LAW_EFFECT,)),
                parameters={**st.parameters, **held})
            m = Model(st2, keys=["K_d_per_Pa", "clearance_mm", *LAW_KEYS], start=start,
                      candidates=[])
            u = np.zeros(len(m.names))
            ev = m.evaluate(u)
        base = [n for n in m.names if n.startswith(("K_d", "clearance"))]
        pts = [e.snapshot_points for e in st.experiments]
        tr = np.array([interp(np.array(prof[(st.experiments[e].name, pts[e][s])]), x)
                       for e, s, x in zip(m.row_exp, m.row_snap, m.row_x)])
        d = ev.pred - tr
        free = [m.index[k] for k in base + list(spec(lev[1]).free_keys())]
        A = np.vstack([ev.J[:, free] / 0.3, ev.J_prior[:, free]])
        b = np.concatenate([d / 0.3, np.zeros(ev.J_prior.shape[0])])
        du = np.linalg.lstsq(A, -b, rcond=None)[0]
        G = m.value_jacobian(u)[np.ix_(free, free)]
        dv, se = G @ du, np.sqrt(np.diag(G @ np.linalg.inv(A.T @ A) @ G.T))
        print(f"== {lev[0]} x {lev[1]}: model − data RMS {np.sqrt(np.mean(d ** 2)):.4f} µm "
              f"(max {np.abs(d).max():.3f}); CPU {time.process_time() - t0:.1f} s")
        for i, n in enumerate(m.names[j] for j in free):
            if n.startswith("law") or n == "K_d_per_Pa":
                print(f"   {n}: true {m.values(u)[free[i]]:.5g}, step {dv[i]:+.4g} "
                      f"({dv[i] / se[i]:+.2f} SE)")


if __name__ == "__main__":
    main()
