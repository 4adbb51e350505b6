"""Validation of `jaxwear design --goal separate` (issue 44, item 5): on studies where two
explanations are tied, does the recommended next experiment tell them apart where a naive
next experiment does not?

    python calibration/design_validation.py [--seeds 1,2] [--out docs/design_validation.md]

For each case and seed:
1. `synthesize` makes a study on part of the paper's rig matrix with the true law hidden
   (its truth at twice the study's nodes and steps and a tenth of its update: no inverse
   crime), noise on every scan row.
2. Both explanations are fitted to it (the fit driver); their difference Δχ² =
   (RSS_rival − RSS_truth)/σ² (σ the fits' noise estimate) is a tie below 2 ln 20.
3. `design --goal separate --between TRUTH,RIVAL` ranks the candidates (the same grid for
   every case) and recommends one.
4. Three next experiments are each made by the generator with the true law (the same seed
   and truth: the study's own rows stay as they were, the new specimen's scans are added)
   and the two explanations refitted: the recommended one; the matrix's next point (the paper's
   experiment the study lacks); a random candidate of the same grid (seeded).
5. A next experiment "separates" when Δχ² after it is >= 2 ln 20 in favour of the truth.

The third case, two variables of the shape (`--between shape:pressure_MPa,
shape:sliding_speed_m_per_s`), takes its data from the independent NumPy generator
`benchmarks/hidden_physics.py` (the `threshold` law: the Archard rate x (1 + a S((p − p0)/
(w p0))), a pressure law outside jaxwear's library and grammar) at 128 x 144 nodes and
steps and M 25; the two rivals are the study's model plus the shape's correction along one
variable (`_analyses.design.shape_rival`), each refitted through the loop; Δχ² is
(RSS_speed − RSS_pressure)/σ², σ the study's noise estimate.

Writes a markdown table (and the numbers as JSON beside it).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from jaxwear._analyses.design import SEPARATE_CHI2, design, model_study, parse_vary  # noqa: E402
from jaxwear._analyses.synth import PAPER_MATRIX, paper_conditions, synthesize  # noqa: E402
from jaxwear._inference.calibrate import fit_study  # noqa: E402
from jaxwear._inference.packing import study_fit_keys  # noqa: E402
from jaxwear._study.effect_files import load_effect_file  # noqa: E402
from jaxwear._study.study import Experiment, load_study  # noqa: E402

sys.path.insert(0, str(ROOT / "benchmarks"))
import hidden_physics as hp  # noqa: E402

from jaxwear._analyses.design.rank import _fit  # noqa: E402
from jaxwear._analyses.design.shape_rival import fit_shape  # noqa: E402

NUM = {"nodes": 64, "steps_per_rev": 72, "revolutions_per_update": 250}
VARY = "speed_rpm=74:414:3,clearance_mm=0.025:0.225:3,revolutions=5000:30000:3"
# The study: the paper's first three experiments, all at 0.05 mm (speed and the load it
# makes vary together); the matrix's next point is its fourth, (230 r/min, 10⁴, 0.10 mm).
STUDY_EXPERIMENTS = 3

CASES = [
    # label, hidden truth, truth's explanation, rival, noise [µm]
    ("two library effects: pressure exponent (true) vs speed dependence",
     ["pressure_exponent=0.2"], "pressure_exponent", "speed_dependence", 1.5),
    ("a library effect vs an outside law: speed dependence (true) vs debris (user file)",
     ["speed_dependence=0.15"], "speed_dependence", "debris", 1.5),
]


# the third case: two variables of the shape on the same three experiments
SHAPE_CASE = ("two variables of the shape: contact pressure (true: a threshold law, "
              "outside the library) vs sliding speed",
              "shape:pressure_MPa", "shape:sliding_speed_m_per_s", 1.5)
SHAPE_LAW = hp.Law("threshold", 0.5)  # the rate x (1 + 0.5 S((p/1.5 MPa − 1)/0.03))
SHAPE_GEN = hp.Numerics(nodes=128, steps=144, M=25.0)  # 2x the study's nodes and steps


def conditions():
    st = paper_conditions(NUM)
    return st.with_experiments(st.experiments[:STUDY_EXPERIMENTS])


def fit_pair(study, truth, rival):
    fits = {}
    for name in (truth, rival):
        st = model_study(study, name)
        fits[name] = fit_study(st, study_fit_keys(st))
    sigma = min(float(f.noise_um) for f in fits.values())
    return (fits[rival].rss - fits[truth].rss) / sigma ** 2, fits


def added(base, base_truth, study_conditions, hidden, seed, noise, exp: Experiment,
          tmp: Path):
    """The study `base` with `exp` added, its scans made by the generator with the same
    seed and the same truth (K_d and the study's clearances are drawn first: checked); the
    study's own rows are kept as they were (the generator's noise draws shift with the
    added specimen's clearance draw, so its other rows are not reused)."""
    cond = study_conditions.with_experiments(list(study_conditions.experiments) + [exp])
    res = synthesize(hidden, cond, noise_um=noise, seed=seed, out=tmp)
    assert res.truth["K_d_per_Pa"] == base_truth["K_d_per_Pa"]
    for k, v in base_truth["clearance_mm"].items():
        assert res.truth["clearance_mm"][k] == v, k
    return base.with_experiments(list(base.experiments) + [res.study.experiments[-1]])


def next_experiments(res, seed):
    """(what, conditions, expected value) of the three next experiments compared: the
    design's recommendation, the paper matrix's next point, a random candidate (seeded)."""
    best = int(res.order[0])
    rng = np.random.default_rng(1000 + seed)
    rand = int(rng.integers(res.plan.size))
    _, n, r, c = PAPER_MATRIX[STUDY_EXPERIMENTS]
    return [("recommended", res.plan.conditions[best], float(res.values[best])),
            ("matrix's next point", {"speed_rpm": n, "clearance_mm": c, "revolutions": r},
             None),
            ("random in the grid", res.plan.conditions[rand], float(res.values[rand]))]


def run_case(label, hidden, truth, rival, noise, seed, rows, tmp):
    t0 = time.perf_counter()
    cond = conditions()
    made = synthesize(hidden, cond, noise_um=noise, seed=seed, out=tmp / f"s{seed}-base")
    base = made.study
    d0, _ = fit_pair(base, truth, rival)
    res = design(base, goal="separate", between=[truth, rival], vary=parse_vary(VARY, base))
    nexts = next_experiments(res, seed)
    for what, cnd, expected in nexts:
        over = {k: v for k, v in cnd.items() if k != "revolutions"}
        over.setdefault("clearance_mm", 0.05)
        exp = Experiment(f"next-{what.split()[0]}", over, revolutions=cnd["revolutions"])
        st = added(base, made.truth, cond, hidden, seed, noise, exp,
                   tmp / f"s{seed}-{what.split()[0]}")
        d1, _ = fit_pair(st, truth, rival)
        rows.append({"case": label, "seed": seed, "noise_um": noise,
                     "delta_chi2_before": d0, "next": what, "conditions": cnd,
                     "expected_chi2": expected, "delta_chi2_after": d1,
                     "separated": bool(d1 >= SEPARATE_CHI2),
                     "tie_before": bool(abs(d0) < SEPARATE_CHI2)})
        print(f"  {label} seed {seed}: {what} {cnd}: Δχ² {d0:.2f} -> {d1:.2f}",
              file=sys.stderr, flush=True)
    print(f"  case done in {time.perf_counter() - t0:.0f} s", file=sys.stderr, flush=True)


def shape_study(conds, seed, noise, tmp: Path):
    """A study of `conds` (hidden_physics Conditions) with the threshold law hidden, at the
    other cases' numerics (64 x 72, the paper integrator at M 250: the generator's M 25 is
    10x finer), and the generator's truth."""
    gen = hp.generate(SHAPE_LAW, conds, seed=seed, noise_um=noise, num=SHAPE_GEN)
    path = hp.write(tmp, gen, conds, study_numerics=(NUM["nodes"], NUM["steps_per_rev"]))
    st = load_study(path)
    return dataclasses.replace(st, integrator="paper",
                               revolutions_per_update=NUM["revolutions_per_update"]), gen.truth


def fit_shape_pair(study, truth, rival):
    """Both shape rivals refitted on `study` (the study's fit, then each correction on top):
    (Δχ² = (RSS_rival − RSS_truth)/σ², base RMSE, {name: RMSE})."""
    st, base = _fit(study, study_fit_keys(study), False, "the study", [])
    fits = {n: fit_shape(st, base, n) for n in (truth, rival)}
    sigma = float(base.noise_um)
    return ((fits[rival].rss - fits[truth].rss) / sigma ** 2, float(base.rmse_um),
            {n: f.rmse_um for n, f in fits.items()}, sigma)


# the same grid with the speeds inside the study's (148-276 r/min): a shape rival's correction
# is flat beyond the states met in the data, so a candidate beyond them differs between the
# rivals by the fitted corrections' edges, which a refit with its data (new knots) absorbs
VARY_IN = "speed_rpm=148:276:3,clearance_mm=0.025:0.225:3,revolutions=5000:30000:3"
IN_RANGE = "recommended, speeds within the study's"


def run_shape_case(label, truth, rival, noise, seed, rows, tmp, in_range=False):
    """One study of the shape case; `in_range`: only the recommended experiment of the
    grid whose speeds lie within the study's (`VARY_IN`)."""
    t0 = time.perf_counter()
    conds = hp.PAPER[:STUDY_EXPERIMENTS]
    base, gtruth = shape_study(conds, seed, noise, tmp / f"shape-s{seed}-base")
    res = design(base, goal="separate", between=[truth, rival],
                 vary=parse_vary(VARY_IN if in_range else VARY, base))
    d0 = float(res.info["chi2_between_now"])
    sigma = float(res.info["noise_um"])
    n_rows = sum(len(e.profile.angle) for e in base.experiments if e.profile is not None)
    b0 = res.info["base_rmse_um"]
    explains = {n: (b0 ** 2 - f["rmse_um"] ** 2) * n_rows / sigma ** 2
                for n, f in res.info["fits"].items()}
    print(f"  {label} seed {seed}: before Δχ² {d0:.2f}; base -> each alone "
          f"{explains}", file=sys.stderr, flush=True)
    nexts = next_experiments(res, seed)
    if in_range:
        nexts = [(IN_RANGE, *nexts[0][1:])]  # the recommendation, within the speeds
    for what, cnd, expected in nexts:
        tag = "in-range" if what == IN_RANGE else what.split()[0]
        new = hp.Condition(f"next-{tag}", float(cnd["speed_rpm"]),
                           float(cnd["revolutions"]), float(cnd.get("clearance_mm", 0.05)))
        st, t2 = shape_study(tuple(conds) + (new,), seed, noise,
                             tmp / f"shape-s{seed}-{tag}")
        # the same truth (K_d and the study's clearances are drawn first); the study's own
        # rows are kept as they were, the new specimen's scans added
        assert t2["K_d_per_Pa"] == gtruth["K_d_per_Pa"]
        for k, v in gtruth["clearance_mm"].items():
            assert t2["clearance_mm"][k] == v, k
        st = base.with_experiments(list(base.experiments) + [st.experiments[-1]])
        d1, b1, rm, s1 = fit_shape_pair(st, truth, rival)
        rows.append({"case": label, "seed": seed, "noise_um": noise,
                     "delta_chi2_before": d0, "next": what, "conditions": cnd,
                     "expected_chi2": expected, "delta_chi2_after": d1,
                     "separated": bool(d1 >= SEPARATE_CHI2),
                     "tie_before": bool(abs(d0) < SEPARATE_CHI2),
                     "explained_before_chi2": explains, "base_rmse_after_um": b1,
                     "rmse_after_um": rm, "noise_after_um": s1})
        print(f"  {label} seed {seed}: {what} {cnd}: Δχ² {d0:.2f} -> {d1:.2f}",
              file=sys.stderr, flush=True)
    print(f"  case done in {time.perf_counter() - t0:.0f} s", file=sys.stderr, flush=True)


def table(rows) -> str:
    lines = ["| case | seed | Δχ² before (tie < 5.99) | next experiment | conditions "
             "(r/min, mm, rev) | design's expected χ² | Δχ² after | separated |",
             "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        c = r["conditions"]
        cond = (f"{c.get('speed_rpm', float('nan')):g}, {c.get('clearance_mm', 0.05):g}, "
                f"{c['revolutions']:g}")
        exp = "" if r["expected_chi2"] is None else f"{r['expected_chi2']:.1f}"
        lines.append(f"| {r['case']} | {r['seed']} | {r['delta_chi2_before']:.2f} | "
                     f"{r['next']} | {cond} | {exp} | {r['delta_chi2_after']:.2f} | "
                     f"{'yes' if r['separated'] else 'no'} |")
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="1,2")
    ap.add_argument("--cases", default=None, help="indices of CASES to run, e.g. 0,1")
    ap.add_argument("--out", default=str(ROOT / "docs" / "design_validation_table.md"))
    ap.add_argument("--in-range", action="store_true",
                    help="the shape case: only the recommended experiment with the speeds "
                         "within the study's (added to the table's rows)")
    a = ap.parse_args(argv)
    load_effect_file(ROOT / "calibration" / "examples" / "debris_effect.py")
    seeds = [int(s) for s in a.seeds.split(",")]
    every = CASES + [SHAPE_CASE]
    cases = every if a.cases is None else [every[int(i)] for i in a.cases.split(",")]
    # the rows of the studies (case, seed) not run now are kept from the table's JSON
    js = Path(a.out).with_suffix(".json")
    now = {(c[0], s) for c in cases for s in seeds}

    def redone(r):
        return (r["case"], r["seed"]) in now and (not a.in_range or r["next"] == IN_RANGE)

    rows = ([r for r in json.loads(js.read_text()) if not redone(r)] if js.exists() else [])
    with tempfile.TemporaryDirectory() as tmp:
        for case in cases:
            for seed in seeds:
                if case is SHAPE_CASE:
                    run_shape_case(*case, seed, rows, Path(tmp), in_range=a.in_range)
                else:
                    run_case(*case, seed, rows, Path(tmp))
                # after every study: a long run stopped part-way keeps what it measured
                Path(a.out).write_text(table(rows) + "\n")
                js.write_text(json.dumps(rows, indent=1) + "\n")
    print(table(rows))


if __name__ == "__main__":
    main()

