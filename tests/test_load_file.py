"""Your own joint's load file (design.md §2, preset "load_history"): the resampling onto the wear
loop's steps.

Independent references: the exact integrals of a piecewise-linear angle and a held load
(sums over the file's rows by hand), the identity when the file's rows are the steps, and
the wear of one cycle against finer resamplings (the file's own rows as steps being the
exact model of the file). The file checks (bad input) are in test_fuzz_inputs.py.
Run time: ~25 s (four one-cycle wear increments compiled at 36 to 720 steps).
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxwear as jw
from jaxwear._physics.cycle import cycle_increment
from jaxwear._physics.load_cycle import resample

ROWS, PERIOD = 720, 6.0


def fine_cycle(rows=ROWS, sub=1):
    """A loader-pin-like cycle: a swing with a reversal-rich harmonic (six reversals), the
    load turning with the swing and a narrow inertia peak (0.4 % of the period wide, a third
    of a 72-step) while the pin slides fast. `sub` keeps every sub-th row (point sampling
    of the same motion)."""
    t = np.arange(rows) * (PERIOD / rows)
    w = 2 * np.pi / PERIOD
    phi = 40 * np.sin(w * t) + 12 * np.sin(3 * w * t)
    mag = 6000 + 3000 * np.sin(w * t) ** 2 + 9000 * np.exp(-0.5 * ((t - 0.3 * PERIOD)
                                                                    / (0.004 * PERIOD)) ** 2)
    theta = np.radians(80.0 - phi)
    t, mag, theta, phi = t[::sub], mag[::sub], theta[::sub], phi[::sub]
    return jw.make_cycle(t, mag * np.cos(theta), mag * np.sin(theta), phi)


def by_hand(cycle):
    """Per file row: |Δφ| and Δφ to the next row (the last to the first, one period on),
    and the load magnitude."""
    dphi = np.diff(cycle.angle)
    return np.abs(dphi), dphi, np.hypot(cycle.force[:, 0], cycle.force[:, 1])


def test_rows_as_steps_is_the_identity():
    c = fine_cycle(rows=72)
    r = resample(c, 72)
    adphi, dphi, mag = by_hand(c)
    np.testing.assert_allclose(r.rotation, adphi, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(r.net, dphi, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(r.load, mag, rtol=1e-12)
    np.testing.assert_allclose(np.cos(r.angle - np.arctan2(c.force[:, 1], c.force[:, 0])), 1,
                               atol=1e-12)
    np.testing.assert_allclose(r.dt, PERIOD / 72, rtol=1e-13)


@pytest.mark.parametrize("steps", [36, 72, 100, 1000])
def test_sliding_reversals_and_work_are_kept_at_any_steps(steps):
    """Total sliding, net rotation and the Archard work Σ|W| dS of the file, exactly, at
    steps that do not divide the rows (100) or are finer than them (1000); a step that holds
    a reversal slides more than its net rotation."""
    c = fine_cycle()
    r = resample(c, steps)
    adphi, dphi, mag = by_hand(c)
    assert np.sum(r.rotation) == pytest.approx(np.sum(adphi), rel=1e-12)
    assert np.sum(r.net) == pytest.approx(np.sum(dphi), abs=1e-12)
    assert np.sum(r.load * r.rotation) == pytest.approx(np.sum(mag * adphi), rel=1e-12)
    reversals = np.flatnonzero(np.sign(dphi) != np.sign(np.roll(dphi, -1)))
    assert len(reversals) == 6
    # the step holding each reversal (row k's end, at time (k + 1) T / rows)
    t_rev = (reversals + 1) * PERIOD / ROWS
    i = np.minimum((t_rev / (PERIOD / steps)).astype(int), steps - 1)
    inside = (t_rev / (PERIOD / steps)) % 1 > 1e-9  # not on a step boundary
    assert np.all(r.rotation[i[inside]] > np.abs(r.net[i[inside]]) * (1 + 1e-9))


CFG = jw.ModelConfig(driver="load_history", nodes=64, steps_per_rev=72,
                     duty_cycle=(jw.DutyBlock(0.0, np.inf, fine_cycle()),))
P = jw.preset("load_history", K_d_per_Pa=1e-14)


def one_cycle(cycle, steps):
    """Wear of the first cycle [µm] (nodes,) on the unworn bore at `steps` steps."""
    cfg = CFG.replace(steps_per_rev=steps, duty_cycle=(jw.DutyBlock(0.0, np.inf, cycle),))
    hist = jw.load_history(P, cfg)
    dh, _, _ = jax.jit(cycle_increment, static_argnums=1)(P, cfg, hist, 0,
                                                          jnp.zeros(cfg.nodes), jnp.zeros(()))
    return np.asarray(dh) * 1e6


@pytest.fixture(scope="module")
def increments():
    c = fine_cycle()
    exact = one_cycle(c, ROWS)  # the file's rows as steps: the file's model itself
    out = {n: one_cycle(c, n) for n in (36, 72, 144)}
    out["sampled 72"] = one_cycle(fine_cycle(sub=ROWS // 72), 72)
    return exact, out


def test_wear_converges_to_the_files_own_rows(increments):
    """One cycle's wear at 36, 72, 144 steps against the file at its own 720 rows: the error
    falls as the steps are refined, and at the loop's default-sized 72 steps it is within
    2 % of the peak."""
    exact, out = increments
    peak = exact.max()
    err = {n: np.abs(out[n] - exact).max() / peak for n in (36, 72, 144)}
    assert err[144] < err[72] < err[36]
    assert err[72] < 0.02, err
    # total worn volume per cycle is K_d Σ (Σ_j p_j A_j) dS: kept to the contact's arc
    # (Σ p A differs from |W| only by the spread of the normals), far better than the peak
    for n in (36, 72, 144):
        assert abs(out[n].sum() / exact.sum() - 1) < 2e-3, n


def test_resampling_beats_point_sampling(increments):
    """The same motion sampled at 72 points (each row's load held for its step, its rotation
    the row-to-row change: what a coarse export gives) misses part of the narrow load peak's
    work: its worn volume per cycle is 0.4 % short, the resampled fine file's within 1e-4
    (the work is kept; what remains is the contact arc's), and its profile error is twice
    the resampled one's."""
    exact, out = increments
    vol = {k: out[k].sum() / exact.sum() - 1 for k in (72, "sampled 72")}
    assert abs(vol[72]) < 1e-4 and abs(vol["sampled 72"]) > 10 * abs(vol[72]), vol
    peak = exact.max()
    err_resampled = np.abs(out[72] - exact).max() / peak
    err_sampled = np.abs(out["sampled 72"] - exact).max() / peak
    assert err_sampled > 2 * err_resampled, (err_sampled, err_resampled)
