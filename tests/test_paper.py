"""The paper's qualitative claims (§1.3 Fig. 3, §2.2 Figs 8-9), checked numerically.

Small grids (90 nodes × 72 steps) and the measures of `calibration/paper/metrics.py`, which
the validation page (`docs/paper/`) uses too. Each test names the claim and the independent
reason it must hold; none compares with numbers taken from the code's own output.

The wear runs follow the paper's Figs 8-9 set-up: Table 1 with k = 1800 N/m, Table 3 joint,
15 000 revolutions, here with K_d = 1e-13 1/Pa and M = 100.
"""

import importlib.util
from pathlib import Path

import numpy as np
import pytest

import jaxwear as jw

_path = Path(__file__).resolve().parents[1] / "calibration" / "paper" / "metrics.py"
_spec = importlib.util.spec_from_file_location("paper_metrics", _path)
pm = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(pm)

NODES, STEPS = 90, 72
SNAPSHOTS = (2500, 5000, 7500, 10000, 12500, 15000)
MAP_REVOLUTIONS = (1, 5001, 10001, 15001)  # paper Figs 8-9 (a)-(d)


@pytest.fixture(scope="module")
def worn():
    """Wear runs of both contact models: {contact: (params, config, snapshots (6, nodes) [m])}."""
    p = jw.preset("rig", spring_N_per_m=1800.0)
    out = {}
    for contact in ("symmetric", "unsymmetric"):
        cfg = jw.ModelConfig(contact=contact, nodes=NODES, steps_per_rev=STEPS)
        res = jw.simulate(p, cfg, revolutions=15000, snapshots=SNAPSHOTS, M=100)
        out[contact] = (p, cfg, np.asarray(res.snapshots))
    return out


def _profile_before(snaps, rev):
    """Profile on which revolution `rev` runs: the one worn by the previous rev - 1."""
    return np.zeros(NODES) if rev == 1 else snaps[SNAPSHOTS.index(rev - 1)]


@pytest.fixture(scope="module")
def asymmetry(worn):
    """Mirror asymmetry index per step, {(contact, revolution): (steps,)}, load on nodes."""
    out = {}
    for contact, (p, cfg, snaps) in worn.items():
        for rev in MAP_REVOLUTIONS:
            pressure, idx, _ = pm.pressure_map(p, cfg, _profile_before(snaps, rev))
            assert np.all(pressure >= 0.0)
            out[contact, rev] = pm.mirror_asymmetry(pressure, idx)
    return out


def test_scla_does_not_depend_on_start_angle():
    """Fig. 3: any start angle γ0 gives the same force.

    Reason: the first pass makes γ the force direction up to O(ξ/L2) = 2.5e-4 rad whatever
    γ0 was, so start angles differ only at second order in ξ/L2 after the second pass: far
    below the first-order effect of the clearance itself (SCLA against the ideal joint).
    """
    p = jw.preset("rig", spring_N_per_m=0.0)  # Table 1
    forces = [pm.joint_force(p, STEPS, "scla", g)[0]
              for g in np.radians([0.0, 45.0, 90.0, 180.0, 270.0])]
    ideal = pm.joint_force(p, STEPS, "ideal")[0]
    spread = max(float(np.max(np.abs(f - forces[0]))) for f in forces)
    clearance_effect = float(np.max(np.abs(forces[0] - ideal)))
    assert clearance_effect > 0.0
    assert spread < 0.05 * clearance_effect
    assert spread < 1e-5 * float(np.max(forces[0]))


def test_mirror_index_of_known_distributions():
    """The asymmetry index is 0 for a mirror image about the load node, 1 for a one-sided
    distribution, and ½ when half the load sits in one unmatched node."""
    n = 12
    sym = np.zeros((1, n))
    sym[0, [2, 3, 4]] = [1.0, 2.0, 1.0]  # symmetric about node 3
    one_sided = np.zeros((1, n))
    one_sided[0, [4, 5]] = [1.0, 2.0]  # entirely right of node 3
    half = np.zeros((1, n))
    half[0, [3, 4]] = [1.0, 1.0]
    centre = np.array([3])
    assert pm.mirror_asymmetry(sym, centre)[0] == pytest.approx(0.0, abs=1e-15)
    assert pm.mirror_asymmetry(one_sided, centre)[0] == pytest.approx(1.0)
    assert pm.mirror_asymmetry(half, centre)[0] == pytest.approx(0.5)
    assert pm.mirror_asymmetry(np.zeros((1, n)), centre)[0] == 0.0


def test_traditional_model_stays_symmetric(asymmetry):
    """Fig. 8: the traditional Winkler pressure is symmetric at every revolution.

    Reason: it takes the bore as a circle through the loaded node (one gap and one stiffness
    for all nodes), so the pressure depends on cos(θ_j - θ_W) only, worn or not.
    """
    for rev in MAP_REVOLUTIONS:
        assert np.max(asymmetry["symmetric", rev]) < 1e-9, rev


def test_unsymmetric_model_is_symmetric_on_the_unworn_bore(asymmetry):
    """Fig. 9(a): before any wear the unsymmetric pressure is symmetric too.

    Reason: a round bore with the load on a node is mirror-symmetric about the load, and the
    contact equilibrium is the gradient of a strictly convex potential with one minimiser,
    which must then be symmetric itself.
    """
    assert np.max(asymmetry["unsymmetric", 1]) < 1e-6


def test_unsymmetric_asymmetry_grows_with_wear(asymmetry):
    """Figs 9(b)-(d): "with the wear revolution increasing, the asymmetry of the pressure
    distribution becomes more and more severe".

    Reason: the asymmetry comes from the bore's departure from a circle, which is the wear
    depth; it grows with every revolution, so the asymmetry must grow too.
    """
    mean = [float(np.mean(asymmetry["unsymmetric", r])) for r in MAP_REVOLUTIONS]
    peak = [float(np.max(asymmetry["unsymmetric", r])) for r in MAP_REVOLUTIONS]
    assert all(b > a for a, b in zip(mean, mean[1:])), mean
    assert all(b > a for a, b in zip(peak, peak[1:])), peak
    assert peak[-1] > 0.1  # a tenth of the load without a mirror partner: visibly one-sided
    # ...and it is the worn bore, not the load, that makes the difference: the traditional
    # model sees the same loads on its own worn bore and stays symmetric.
    assert peak[-1] > 1e6 * np.max(asymmetry["symmetric", 15001])


def test_asymmetry_is_largest_at_the_wear_area_boundary(worn, asymmetry):
    """§2.2: the most severe asymmetry appears where the load sits at "the boundary of the
    wear area".

    Reason: inside a wear zone (or on unworn bore) the bore around θ_W is locally almost
    symmetric; at a boundary one side is worn and the other is not.
    """
    p, cfg, snaps = worn["unsymmetric"]
    _, _, angle = pm.pressure_map(p, cfg, snaps[-1])
    edges = pm.wear_area_edges_deg(snaps[-1])
    assert len(edges) >= 2
    dist = np.array([np.min(pm.angular_distance_deg(a, edges)) for a in np.degrees(angle)])
    a15 = asymmetry["unsymmetric", 15001]
    near = dist <= 15.0
    assert near.any() and (~near).any()
    assert np.mean(a15[near]) > 1.3 * np.mean(a15[~near])
    assert dist[np.argmax(a15)] <= 20.0


def test_wear_area_expands_only_with_the_unsymmetric_model(worn):
    """Figs 8-9: "with the traditional Winkler model, the wear area does not expand"; the
    unsymmetric model "leads to the expanding of the wear area".

    Reason: the traditional model's contact arc per step depends on the load and the local
    stiffness only, so every revolution wears the same pattern and the profile grows without
    widening; a worn groove that conforms to the pin (unsymmetric model) spreads the contact.
    """
    width = {c: [pm.wear_area_nodes(h) for h in snaps] for c, (_, _, snaps) in worn.items()}
    sym, uns = width["symmetric"], width["unsymmetric"]
    assert max(sym) - min(sym) <= 1, sym
    assert all(b >= a for a, b in zip(uns, uns[1:])), uns
    assert uns[-1] - uns[0] >= 4, uns  # ≥ 20° wider between 2 500 and 15 000 revolutions
    assert uns[-1] > max(sym)
