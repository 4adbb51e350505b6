"""The adaptive wear integrator (design.md §4, the wear history as an ODE; issue 9).

Independent references: the paper's update at M = 1 (eq 23 one cycle at a time, the
finest the model allows; its own Euler error is ~1e-4 of the peak here), the Archard
volume identity with the pair's weights, central finite differences of the same float64
function, and a separate run stopped at a snapshot count.
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import central_fd

import jaxwear as jw
from jaxwear._physics.adaptive import DEFAULT_WEAR_TOLERANCE_UM, _adaptive_trace
from jaxwear._physics.config import boom_config
from jaxwear._physics.wear import build_schedule, wear_loop

CFG_RIG = jw.ModelConfig(nodes=64, steps_per_rev=72)
CFG_BOOM = boom_config(nodes=64, steps_per_rev=72)
KD_BOOM = 3.8e-13  # the fitted boom K_d of issue 9, where M = 100 was 25 % off
PEAK_REL = 5e-4  # 0.05 % of the peak depth


def boom(**kw):
    return jw.preset("boom", K_d_per_Pa=KD_BOOM, **kw)


CASES = {
    "rig": (jw.preset("rig"), CFG_RIG, {"revolutions": 10000}),
    "boom": (boom(), CFG_BOOM, {"hours": 25}),
    "stiff": (boom(layer_E_GPa=1030.0), CFG_BOOM, {"hours": 25}),  # layer modulus x10
}


@pytest.mark.parametrize("case", list(CASES))
def test_default_numerics_match_one_cycle_updates(case):
    """Default tolerance: within 0.05 % of the peak of M = 1 at every node; the reported
    error estimate is within the tolerance; the volume identity holds with the pair's
    weights."""
    p, cfg, run = CASES[case]
    ref = np.asarray(jw.simulate(p, cfg, M=1, **run).depth)
    res = jw.simulate(p, cfg, **run)
    d = np.asarray(res.depth)
    assert np.max(np.abs(d - ref)) <= PEAK_REL * np.max(ref)
    assert 0 < float(res.error_estimate) <= DEFAULT_WEAR_TOLERANCE_UM * 1e-6
    assert int(res.steps) > 0
    assert float(res.worn_volume) == pytest.approx(float(res.archard_volume), rel=1e-12)


def test_few_attempts_thrown_away_on_a_smooth_run():
    """The step controller (a PI controller after accepted steps, `adaptive._PI`) rarely
    proposes a step that is then rejected where the wear grows smoothly: on the rig at
    most 15 % of the attempts, each of which costs three cycle evaluations. The plain
    controller, 0.9 r^(-1/3), threw away 14 of 41 here (34 %): from a ratio of ~0.25 it
    grew a step 1.5x to a ratio of ~2.5."""
    p, cfg, run = CASES["rig"]
    res = jw.simulate(p, cfg, **run)
    attempts = int(res.steps) + int(res.rejected_steps)
    assert int(res.rejected_steps) <= 0.15 * attempts
    assert 0 < float(res.error_estimate) <= DEFAULT_WEAR_TOLERANCE_UM * 1e-6


def test_paper_integrator_flags_unstable_amplification():
    """eq 23 at M = 100 on the boom (the issue's silent 25 %): the reported Euler error
    estimate is of the size of the actual error, not hidden."""
    p, cfg, run = CASES["boom"]
    ref = np.asarray(jw.simulate(p, cfg, M=1, **run).depth)
    res = jw.simulate(p, cfg, M=100, **run)
    actual = np.max(np.abs(np.asarray(res.depth) - ref))
    assert actual > 0.05 * np.max(ref)
    assert float(res.error_estimate) > 0.2 * actual


def test_snapshots_and_order():
    """Snapshots land on the requested counts (in the order asked): a snapshot equals a
    run stopped there, to the tolerance."""
    p = jw.preset("rig")
    res = jw.simulate(p, CFG_RIG, revolutions=4000, snapshots=(4000, 1500))
    short = jw.simulate(p, CFG_RIG, revolutions=1500)
    tol = 2 * DEFAULT_WEAR_TOLERANCE_UM * 1e-6
    np.testing.assert_allclose(np.asarray(res.snapshots[1]), np.asarray(short.depth), atol=tol)
    np.testing.assert_array_equal(np.asarray(res.snapshots[0]), np.asarray(res.depth))


def test_early_stop_is_the_same_run_cut_short():
    """`Schedule.stopping_at` (the posterior draws' life forecast): the loop ends at the
    first piece end past `stop_after` whose depth reached `stop_depth`; snapshots up to it
    are those of the full run (the same controller, so identical), later ones +inf, and
    it takes fewer steps with a finite error estimate. Never before `stop_after`."""
    p = jw.preset("rig")
    counts = [1000.0 * k for k in range(1, 9)]
    full_s = build_schedule(p, CFG_RIG, revolutions=8000, snapshots=counts)
    full = wear_loop(p, CFG_RIG, full_s)
    mx = np.asarray(full.snapshots).max(axis=1)
    stop_depth = 0.5 * (mx[3] + mx[4])  # reached between 4000 and 5000 rev
    res = wear_loop(p, CFG_RIG, full_s.stopping_at(stop_depth, 2000.0))
    snaps = np.asarray(res.snapshots)
    np.testing.assert_array_equal(snaps[:5], np.asarray(full.snapshots)[:5])
    assert snaps[4].max() >= stop_depth and np.all(np.isinf(snaps[5:]))
    assert int(res.steps) < int(full.steps) and np.isfinite(float(res.error_estimate))
    late = wear_loop(p, CFG_RIG, full_s.stopping_at(stop_depth, 6000.0))  # not before 6000
    np.testing.assert_array_equal(np.asarray(late.snapshots)[:6],
                                  np.asarray(full.snapshots)[:6])
    assert np.all(np.isinf(np.asarray(late.snapshots)[6:]))


def test_tighter_tolerance_converges():
    """Halving the tolerance changes the answer by less than the looser tolerance."""
    p, cfg, run = CASES["rig"]
    a = np.asarray(jw.simulate(p, cfg, tolerance_um=0.02, **run).depth)
    b = np.asarray(jw.simulate(p, cfg, tolerance_um=0.005, **run).depth)
    assert np.max(np.abs(a - b)) <= 0.02e-6


KEYS = ("K_d_per_Pa", "clearance_mm", "speed_rpm", "spring_N_per_m", "layer_E_GPa",
        "running_in_amplitude")
CFG_RUN_IN = jw.ModelConfig(nodes=64, steps_per_rev=72, effects=("running_in",))


def _objective(p0, cfg, sched, keys, replay=None):
    def f(x):
        p = p0.with_values(dict(zip(keys, x)))
        if replay is None:
            res = wear_loop(p, cfg, sched)
        else:
            res = _adaptive_trace(p, cfg, sched, None, replay)[0]
        h = res.depth * 1e6
        return jnp.sum(h**3) / jnp.sum(h**2)  # smooth peak-weighted depth [µm]
    return f


@pytest.fixture(scope="module")
def rig_gradient():
    p0 = jw.preset("rig", running_in_amplitude=1.0, running_in_distance_m=20.0)
    x0 = np.array([float(p0.get(k)) for k in KEYS])
    sched = build_schedule(p0, CFG_RUN_IN, revolutions=2000)
    assert sched.adaptive
    f = _objective(p0, CFG_RUN_IN, sched, KEYS)
    vg = jax.jit(jax.value_and_grad(f))
    # Step sizes are held fixed under differentiation: the gradient is that of the
    # solution on the steps the controller chose at x0, a smooth function of x, which
    # the replay of those steps evaluates away from x0 (no controller).
    trace = jax.jit(lambda p: _adaptive_trace(p, CFG_RUN_IN, sched, None)[1])(p0)
    frozen = jax.jit(_objective(p0, CFG_RUN_IN, sched, KEYS, replay=trace))
    return (x0, (lambda x: float(vg(jnp.asarray(x))[0])), np.asarray(vg(jnp.asarray(x0))[1]),
            f, (lambda x: float(frozen(jnp.asarray(x)))))


@pytest.mark.parametrize("i", range(len(KEYS)), ids=KEYS)
def test_gradient_through_adaptive_loop_matches_finite_differences(rig_gradient, i):
    """Reverse mode through the adaptive loop (default tolerance) = central FD of the
    solution on the chosen steps; the replay reproduces the adaptive answer at x0."""
    x0, value, grad, _, frozen = rig_gradient
    assert frozen(x0) == pytest.approx(value(x0), rel=1e-13)
    assert grad[i] != 0.0
    assert grad[i] == pytest.approx(central_fd(frozen, x0, i), rel=1e-5)


def test_forward_mode_and_vmap(rig_gradient):
    """jacfwd (calibration) equals reverse mode; vmap over parameters equals single runs."""
    x0, value, grad, f, _ = rig_gradient
    fwd = np.asarray(jax.jit(jax.jacfwd(f))(jnp.asarray(x0)))
    assert fwd == pytest.approx(grad, rel=1e-9)
    xs = jnp.stack([x0, x0 * np.array([1.2, 1, 1, 1, 1, 1])])
    batched = np.asarray(jax.jit(jax.vmap(f))(xs))
    assert batched[0] == pytest.approx(value(x0), rel=1e-12)
    assert batched[1] == pytest.approx(value(np.asarray(xs[1])), rel=1e-12)


BOOM_STUDY = """[model]
preset = "boom"
effects = ["running_in"]
duty_cycle = [{{amplitude_deg = 20, duration_h = 1}}, {{amplitude_deg = 1, duration_h = 4}}]
[model.parameters]
K_d_per_Pa = 1.5e-14
running_in_distance_m = 20.0
[numerics]
nodes = 48
steps_per_rev = 72
{extra}
[[experiment]]
name = "boom"
history = "boom.csv"
"""


def test_boom_calibration_right_by_default(tmp_path):
    """The paper's boom data (Table 5, not model output) fitted with the default numerics
    (no integrator, no M) reach the K_d and running-in amplitude of the study tuned by
    hand (eq 23 at M = 10, stable for this joint), within their standard errors; the
    integration error at the fitted values is reported and within the tolerance."""
    from pathlib import Path

    from jaxwear._inference.calibrate import calibrate
    from jaxwear._study.study import load_study

    src = Path(__file__).resolve().parents[1] / "calibration" / "boom" / "boom.csv"
    (tmp_path / "boom.csv").write_text(src.read_text())
    fits = {}
    for name, extra in (("default", ""), ("tuned", "revolutions_per_update = 10")):
        path = tmp_path / f"{name}.toml"
        path.write_text(BOOM_STUDY.format(extra=extra))
        study = load_study(path)
        assert study.integrator == ("adaptive" if name == "default" else "paper")
        # 3 parameters on 5 rows, running-in's pair nearly degenerate (only a·S_r is
        # determined): eq 23's fit at M = 10 walks that valley for ~50 cheap evaluations
        # (30 left it 2 SE short of the minimum, RMSE 2.17 against 1.97 µm)
        fits[name] = calibrate(study, "K_d", max_evaluations=80)
    a, b = fits["default"], fits["tuned"]
    assert a.names == b.names and "running_in_amplitude" in a.names
    for i, n in enumerate(a.names):
        se = max(a.stderr[i], b.stderr[i])
        assert abs(a.values[i] - b.values[i]) <= se, n
    # one-sided: eq 23 at M = 10 is near its stability limit at the fitted K_d (more so in
    # running-in's first cycles), so its objective is rough at the round-off level and the
    # tuned fit can stall short of the minimum (measured on an AMD EPYC host at the tests'
    # LLVM O1: every step rejected up to λ 2e3 at RMSE 2.51 µm; 1.965 µm at O2, as the
    # default's); the default (error-controlled) fit must do at least as well
    assert a.rmse_um <= 1.05 * b.rmse_um
    integ = a.to_json()["integration"]
    assert integ["integrator"] == "adaptive"
    assert 0 < integ["error_estimate_um"] <= integ["tolerance_um"]
    assert b.to_json()["integration"]["integrator"] == "paper"


def test_a_raised_attempt_count_compiles_nothing_and_changes_nothing(tmp_path):
    """The fits' programs take the adaptive loop's attempt count as a traced bound
    (`Schedule.with_dynamic_attempts`, a while loop): the boom at 15x its start K_d needs
    more attempts (the stiff layer's stability limit), and the raise reuses the compiled
    Jacobian (before: one more compilation in every boom fit). The while loop gives the
    static scan's answer to rounding, and a bound too small truncates it as the scan does
    (error estimate inf)."""
    from pathlib import Path

    from jaxwear._inference.calibrate import build_problem, parse_fit
    from jaxwear._inference.evaluation import evaluate
    from jaxwear._inference.residual import traces, traces_since
    from jaxwear._study.study import load_study

    p, cfg, run = CASES["boom"]
    sched = build_schedule(p, cfg, **run)
    static = jax.jit(lambda q, s: wear_loop(q, cfg, s))
    a = static(p, sched)
    b = static(p, sched.with_dynamic_attempts())
    np.testing.assert_allclose(np.asarray(b.depth), np.asarray(a.depth), rtol=1e-12,
                               atol=1e-12 * float(jnp.max(a.depth)))
    assert int(b.steps) == int(a.steps) and float(b.error_estimate) <= \
        DEFAULT_WEAR_TOLERANCE_UM * 1e-6
    short = static(p, dataclasses.replace(sched.with_dynamic_attempts(),
                                          attempt_limit=jnp.asarray(int(a.steps) // 2)))
    assert not np.isfinite(float(short.error_estimate))

    src = Path(__file__).resolve().parents[1] / "calibration" / "boom" / "boom.csv"
    (tmp_path / "boom.csv").write_text(src.read_text())
    (tmp_path / "s.toml").write_text(BOOM_STUDY.format(extra=""))
    study = load_study(tmp_path / "s.toml")
    pb = build_problem(study, parse_fit(study, "K_d"))
    u = np.zeros(len(pb.names))
    ev0, used0 = evaluate(pb, u)
    before = traces()
    u[pb.names.index("K_d_per_Pa")] += np.log(15.0)
    ev1, used1 = evaluate(used0, u)
    assert used1.schedule.attempts > used0.schedule.attempts  # the raise happened
    assert traces_since(before) == {"jacobian": 0, "forward": 0}
    assert np.isfinite(ev1.error_um) and np.all(np.isfinite(ev1.J))
    assert np.max(ev1.pred) > 5 * np.max(ev0.pred)  # depth nearly ∝ K_d


def test_attempt_estimate_in_one_call_is_the_per_experiment_estimate(tmp_path):
    """`attempts_needed` takes every experiment's stiffness bound from one compiled call
    (`_experiment_rates`; eager, the parameters and load histories cost ~0.2 s per
    evaluation); it must equal the estimate from each experiment's own parameters and
    schedule (`adaptive_attempts`), here on a rig study of two speeds and clearances and
    at K_d x 50, where the stability limit, not accuracy, sets the count."""
    from jaxwear._inference.attempts import attempts_needed
    from jaxwear._inference.packing import parse_fit
    from jaxwear._inference.residual import build_model
    from jaxwear._physics.adaptive import adaptive_attempts

    res = jw.synthesize([], "paper", noise_um=0.3, seed=3,
                        numerics=dict(nodes=48, steps_per_rev=48))
    study = dataclasses.replace(res.study.with_experiments(res.study.experiments[:2]),
                                integrator="adaptive")
    model = build_model(study, parse_fit(study, "K_d,clearance"))
    assert model.schedule.adaptive
    for kd_factor in (1.0, 50.0):
        u = np.zeros(len(model.names))
        u[model.names.index("K_d_per_Pa")] = np.log(kd_factor)
        pb = model.batched_params(jnp.asarray(u))
        want = 0
        for i in range(len(model.exp_names)):
            p_i = jax.tree.map(lambda x: x[i], pb)
            one = dataclasses.replace(jax.tree.map(lambda x: x[i], model.schedule),
                                      attempts=1)
            want = max(want, adaptive_attempts(p_i, model.cfg, one))
        assert attempts_needed(model, u) == want
    assert want > adaptive_attempts(jax.tree.map(lambda x: x[0], model.params), model.cfg,
                                    dataclasses.replace(jax.tree.map(
                                        lambda x: x[0], model.schedule), attempts=1))


def test_running_in_is_integrated_on_its_clock(monkeypatch):
    """Running-in at a = 100, S_r = 0.046 m on the boom (the wear rate 101x at the start,
    decaying within the first cycle; the data fix only a·S_r): stepping in the clock
    τ = ∫ (1 + a e^(−S/S_r)) dN the fast start costs no steps (about as many as at a = 1
    with the same a·S_r), where stepping in cycles with the factor in the rate (the clock
    switched off) takes over twice as many; and both agree within the tolerance, against the
    latter at a tenth of it."""
    import jaxwear._physics.adaptive as adaptive

    cfg = boom_config(nodes=48, steps_per_rev=72, effects=("running_in",))
    tol = DEFAULT_WEAR_TOLERANCE_UM

    def run(a, clock=True, tolerance=tol):
        p = boom(running_in_amplitude=a, running_in_distance_m=4.58 / a)
        # stepping in cycles needs more attempts than the estimate (which knows no factor)
        sched = build_schedule(p, cfg, hours=6, snapshots=[1, 5, 6], tolerance_um=tolerance,
                               attempts=None if clock else 8192)
        if not clock:
            monkeypatch.setattr(adaptive, "_clock_effect", lambda p, effects: None)
        try:  # a fresh trace each time: the clock is chosen while tracing
            r = jax.jit(lambda p: wear_loop(p, cfg, sched))(p)
            if clock and not np.isfinite(float(r.error_estimate)):
                # as `simulate` does: the estimate (448 attempts) is this run's edge, and
                # round-off moves the controller across it (legacy emitters 456 attempts
                # at O2, fusion emitters 469-475)
                r = jax.jit(lambda p: wear_loop(p, cfg, sched.more_attempts()))(p)
        finally:
            monkeypatch.undo()
        assert np.isfinite(float(r.error_estimate))
        return np.asarray(r.snapshots) * 1e6, int(r.steps)

    fast, n_fast = run(100.0)
    slow, n_slow = run(1.0)
    plain, n_plain = run(100.0, clock=False)
    ref, _ = run(100.0, clock=False, tolerance=tol / 10)
    assert n_fast <= 1.5 * n_slow, (n_fast, n_slow)
    assert n_plain > 2 * n_fast, (n_plain, n_fast)
    assert np.max(np.abs(fast - ref)) <= tol
    assert np.max(np.abs(plain - ref)) <= tol
    # the running-in is over long before 1 h: only a·S_r matters (the excess wear in
    # metres of steady sliding), so a = 1 with S_r 100x longer differs early, not by much
    assert 0 < np.max(np.abs(fast - slow)) < 0.5 * fast.max()
