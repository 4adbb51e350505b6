"""Hidden physics for validation without inverse crime (issue 25; docs/hidden_physics.md).

An independent generator of complete studies (design.md §6: study.toml, one profile CSV per
experiment, truth.json beside them and not referenced) whose data carry wear laws that
jaxwear's library does not have, computed at numerics finer than any fit uses. Plain NumPy,
built on `numpy_reference.py` (its kinematics, forces and constants); it shares no code with
jaxwear: the two meet only in the files.

    python benchmarks/hidden_physics.py --law impact --seed 1 --out DIR
        [--strength S] [--set KEY=VALUE ...] [--conditions paper|other|FILE.toml]
        [--noise-um 0.3] [--nodes 180 --steps 360 --M 25] [--study-numerics auto|NxS]
        [--clearance-sd-um 3] [--kd-sd 0.15]
        [--backing-compliance-um-per-MPa 0] [--study-contact symmetric]

Laws (`LAWS`; each with a strength, 0 = the base model): `impact` (wear deposited at the
load direction where it turns fast, resolved along the swept arc), `threshold` (the wear
rate jumps above a contact pressure), `two_variable` (the rate jumps above a pressure x
sliding-speed product, the PV limit), `null` (nothing hidden), and the others of `Law`'s
docstring, among them two laws with memory: `fatigue` (a per-node damage that gives way) and
`film` (a per-node protective film that forms out of contact and wears off). Conditions:
`paper` (the rig matrix of design.md §6), `other` (other speeds, clearances, revolutions,
spring rates and crank lengths, so that crank speed and load turn rate are not confounded)
or a TOML file.

The wear loop is design.md §3-4 (Winkler springs of the worn layer, unsymmetric contact,
Archard wear with eq 23's M revolutions per update and a partial block where a snapshot
or the end asks for it); the contact is solved for all steps of a revolution at once by a
batched semi-smooth Newton method with backtracking on the convex potential (relative force
residual < 1e-10), warm-started from the previous update.

Structural choices (design.md §3, §5), for the diagnosis of a study that leaves them out:
`--backing-compliance-um-per-MPa C` puts a backing layer of compliance C = L_b/E_w,b
under the wearing one (the double elastic layer, springs in series: 1/k_j = (L - h_j)/E_w
+ C; 0 = a single layer), and `--study-contact symmetric` writes a study that states the
traditional symmetric contact (the data keep the unsymmetric one).

Exit codes: 0 done, 2 bad input (one line), 1 anything else.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import sys
import tempfile
import time
import tomllib
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import numpy_reference as ref  # noqa: E402

TWO_PI = 2.0 * math.pi
DEG = math.pi / 180.0
LAWS = ("impact", "threshold", "two_variable", "null", "pv_tanh", "worn_soft",
        "running_pressure", "impact_load", "fatigue", "film", "damage_step",
        "g_power_p", "g_exp_h", "g_hinge_v", "g_step_S", "g_step_p_power_v",
        "g_dep_power_W", "bump_v", "thermal")
# laws of jaxwear's grammar (issue 48 item 6: recovery), written here from their formulas
# (docs/design.md §7 `shape.law`) in plain NumPy: each kind along a variable, and a product
GRAMMAR_FACTOR_LAWS = ("g_power_p", "g_exp_h", "g_hinge_v", "g_step_S", "g_step_p_power_v")
# the grammar's deposit form (a deposit per step of the cycle where the pin presses)
GRAMMAR_DEPOSIT_LAWS = ("g_dep_power_W",)
GRAMMAR_LAWS = GRAMMAR_FACTOR_LAWS + GRAMMAR_DEPOSIT_LAWS
# laws whose structure neither jaxwear's shape basis nor its law grammar contains exactly
# (issue 43 item 5): two variables at once, the surface's own state, an event's size
# depending on two quantities
FACTOR_LAWS = ("threshold", "two_variable", "pv_tanh", "worn_soft", "running_pressure",
               "bump_v", *GRAMMAR_FACTOR_LAWS)
# laws with memory (issue 48 item 4): a hidden per-node state that each revolution drives,
# of other forms than jaxwear's grammar (`effects.law_memory`)
MEMORY_LAWS = ("fatigue", "film", "damage_step")
# laws outside the grammar's kinds (issue 48 item 6): a rate that is not monotone in its
# variable (`bump_v`), and a rate of a quantity jaxwear's model does not have, the
# bushing's bulk temperature (`thermal`)
OUTSIDE_LAWS = ("bump_v", "thermal")


class BadInput(ValueError):
    """Bad input: exit 2 with this one-line message."""


# ---- laws ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class Law:
    """A hidden wear law and its constants (units in the names).

    - `impact`: per instant, depth += C max(ω - ω0, 0) (max(ω - ω0, 0)/ω_ref)^(q-1) dt
      K(θ - θ_W), ω = |dθ_W/dt| the load direction's turn rate, K a periodic Gaussian of unit
      peak and width `impact_width_deg` around the load direction; C = `strength` [nm per
      radian of sweep beyond ω0, at ω_ref], the sweep resolved to `sweep_deg` per sub-step.
    - `threshold`: K_d → K_d (1 + a S((p - p0)/(w p0))), S the logistic function, a =
      `strength`, p0 = `threshold_MPa`, w = `threshold_width`.
    - `two_variable`: K_d → K_d (1 + a S((p v - PV0)/(w PV0))), v the sliding speed, a =
      `strength`, PV0 = `pv_MPa_m_per_s`, w = `pv_width`.
    - `null`: nothing.
    - `pv_tanh`: K_d → K_d (1 + a (p/p1) tanh(v/v1)), a = `strength`, p1 = `pv_p_MPa`,
      v1 = `pv_v_m_per_s`: a rate factor of two variables at once (a product, and tanh is
      not in jaxwear's grammar).
    - `worn_soft`: K_d → K_d (1 + a h²/(h² + h1²)), h the depth already worn at the node,
      h1 = `soft_depth_um`: a softer sublayer under the surface (a rate depending on the
      surface's own state, by a Hill function, not in the grammar).
    - `running_pressure`: K_d → K_d (1 + a (p/p1)² / (1 + S/S1)), S the sliding distance,
      p1 = `rp_p_MPa`, S1 = `rp_distance_m`: running-in that is stronger at high pressure
      (two variables, a hyperbolic decay).
    - `impact_load`: `impact` whose size at each event is also ∝ tanh(|W|/W1), W1 =
      `impact_load_N`: an event's size depending on two quantities at the event (the turn
      rate and the load).
    - `fatigue`: a damage D per node (0 new) that each revolution adds to, with an
      endurance limit: dD/dN = max(p_max/p_e − 1, 0)^m / N_f, p_max the node's peak
      pressure over the revolution, p_e = `fatigue_endurance_MPa`, m = `fatigue_exponent`,
      N_f = `fatigue_cycles`; K_d → K_d (1 + a (1 − exp(−D³))) (a Weibull-like giving way:
      the grammar's damage is a power law of its driver and a logistic step).
    - `film`: a protective film f per node (0 new) that forms while the node is out of
      contact and wears off with its contact work, by second-order formation and a power
      of the work: df/dN = k_f (1 − f)² sqrt(t_off/t1) − k_r f (w/w1)^1.5, t_off the
      node's time out of contact per revolution [s], w = Σ_i p_ij dS_i its contact work
      [kJ/m²], k_f = `film_formation`, k_r = `film_removal` (per revolution), t1 =
      `film_time_s`, w1 = `film_work_kJ_per_m2`; K_d → K_d (1 − a f), a = `strength` < 1
      (the grammar's film is first order in both and divides the rate by 1 + A s).
    - `damage_step`: the grammar's own damage (for recovery): dD/dN = (p_max/p_r)^m /
      N_f, p_r = `damage_ref_MPa`, m = `fatigue_exponent`, N_f = `fatigue_cycles`; K_d →
      K_d (1 + a S((D − 1)/w)), S the logistic function, w = `damage_width`.
    - the grammar's laws (`GRAMMAR_LAWS`), K_d → K_d (1 + a Φ), a = `strength`:
      `g_power_p` Φ = (p/p1)^q (p1 = `g_p1_MPa`, q = `g_exponent`); `g_exp_h` Φ =
      exp((h − h1)/h_e) (h the depth worn at the node, h1 = `g_h1_um`, h_e = `g_he_um`);
      `g_hinge_v` Φ = (max(v − v0, 0)/v1)^q (v0 = `g_v0_m_per_s`, v1 = `g_v1_m_per_s`);
      `g_step_S` Φ = S((S − S0)/w) (the logistic of the sliding distance, S0 = `g_S0_m`,
      w = `g_Sw_m`); `g_step_p_power_v` Φ = S((p − p0)/w_p) (v/v1)^q' (p0 = `g_p0_MPa`,
      w_p = `g_pw_MPa`, q' = `g_exponent2`): two states together.
    - `g_dep_power_W`: the grammar's deposit form (`GRAMMAR_DEPOSIT_LAWS`): D nm·rad per
      step of a cycle of N_s = `g_dep_steps` steps, times Φ = (|W|/W1)^q (W1 =
      `g_W1_N`, q = `g_dep_exponent`, D = `strength`), laid where the pin presses (a
      Gaussian bump of `g_dep_width_deg` at the load direction, at least 1.5 node spacings,
      normalised to 1 over the bore in radians). Written per crank angle (N_s/2π steps per
      radian of crank) over the load direction resolved as it turns (`resolved_sweep`), so
      that the deposit per revolution is the grammar's at N_s steps and does not depend
      on the generator's own steps: the grammar's D is per step of the study (N_s its
      steps per revolution).
    - `bump_v`: K_d → K_d (1 + a exp(−((v − v0)/w)²)), v the sliding speed, v0 =
      `bump_v0_m_per_s`, w = `bump_width_m_per_s`: a rate that rises and falls again with
      the speed (a resonance, a lubrication regime between two others); every kind of
      jaxwear's grammar is monotone in its variable.
    - `thermal`: the bushing's bulk temperature rise θ = T − T0 [K] (one per specimen, 0
      at the start: the joint at ambient), driven by the joint's frictional power P = μ
      mean_i(|W_i| v_i) [W] over the revolution through a thermal resistance R_th
      (`thermal_resistance_K_per_W`) and a heat capacity C (`thermal_capacity_J_per_K`):
      dθ/dt = (P − θ/R_th)/C, a time constant R_th C in seconds, not in revolutions;
      K_d → K_d (1 + a (exp(θ/θ_e) − 1)) (Arrhenius-like near T0, θ_e =
      `thermal_scale_K`), μ = `thermal_friction`. A quantity the model has no state for:
      its steady value follows the load and speed of the whole revolution, its warm-up
      the clock.
    The states of the three laws with memory move by explicit Euler over each update of M
    revolutions (the profile and the state frozen within it); `thermal`'s θ by the exact
    solution over the update's seconds at its constant power, the rate at θ at the
    update's middle.
    """

    name: str = "null"
    strength: float = 0.0
    turn_threshold_deg_per_s: float = 5000.0
    turn_reference_deg_per_s: float = 1.0e4
    impact_exponent: float = 2.0
    impact_width_deg: float = 5.0
    threshold_MPa: float = 1.5
    threshold_width: float = 0.03
    pv_MPa_m_per_s: float = 0.08
    pv_width: float = 0.05
    pv_p_MPa: float = 1.5
    pv_v_m_per_s: float = 0.02
    soft_depth_um: float = 3.0
    rp_p_MPa: float = 1.5
    rp_distance_m: float = 20.0
    impact_load_N: float = 40.0
    fatigue_endurance_MPa: float = 0.7
    fatigue_exponent: float = 2.0
    fatigue_cycles: float = 6000.0
    film_formation: float = 3.0e-4
    film_removal: float = 3.0e-4
    film_time_s: float = 0.1
    film_work_kJ_per_m2: float = 8.0
    damage_ref_MPa: float = 2.0
    damage_width: float = 0.15
    g_p1_MPa: float = 1.5
    g_exponent: float = 2.0
    g_h1_um: float = 5.0
    g_he_um: float = 6.0
    g_v0_m_per_s: float = 0.04
    g_v1_m_per_s: float = 0.04
    g_S0_m: float = 40.0
    g_Sw_m: float = 5.0
    g_p0_MPa: float = 1.5
    g_pw_MPa: float = 0.1
    g_exponent2: float = 1.0
    g_W1_N: float = 150.0
    g_dep_exponent: float = 2.0
    g_dep_steps: float = 72.0
    g_dep_width_deg: float = 5.0
    bump_v0_m_per_s: float = 0.05
    bump_width_m_per_s: float = 0.007
    thermal_friction: float = 0.15
    thermal_resistance_K_per_W: float = 10.0
    thermal_capacity_J_per_K: float = 60.0
    thermal_scale_K: float = 10.0

    def __post_init__(self):
        if self.name not in LAWS:
            raise BadInput(f"--law must be one of {list(LAWS)}, got {self.name!r}")
        for k, v in asdict(self).items():
            if k != "name" and not (isinstance(v, (int, float)) and math.isfinite(v)):
                raise BadInput(f"law constant {k} must be a finite number, got {v!r}")
        if self.strength < 0:
            raise BadInput(f"--strength must be >= 0, got {self.strength:g}")
        positive = ("turn_reference_deg_per_s", "impact_exponent", "impact_width_deg",
                    "threshold_MPa", "threshold_width", "pv_MPa_m_per_s", "pv_width",
                    "pv_p_MPa", "pv_v_m_per_s", "soft_depth_um", "rp_p_MPa",
                    "rp_distance_m", "impact_load_N", "fatigue_endurance_MPa",
                    "fatigue_exponent", "fatigue_cycles", "film_formation", "film_removal",
                    "film_time_s", "film_work_kJ_per_m2", "damage_ref_MPa", "damage_width",
                    "g_p1_MPa", "g_he_um", "g_v1_m_per_s", "g_Sw_m", "g_pw_MPa", "g_W1_N",
                    "g_dep_steps", "g_dep_width_deg", "bump_width_m_per_s", "thermal_friction",
                    "thermal_resistance_K_per_W", "thermal_capacity_J_per_K",
                    "thermal_scale_K")
        for k in positive:
            if not getattr(self, k) > 0:
                raise BadInput(f"law constant {k} must be > 0, got {getattr(self, k):g}")
        if self.turn_threshold_deg_per_s < 0:
            raise BadInput("turn_threshold_deg_per_s must be >= 0")
        if self.name == "film" and not self.strength < 1:
            raise BadInput(f"the film's strength a must be < 1 (K_d (1 − a f) stays "
                           f"positive), got {self.strength:g}")

    def memory_step(self, pressure, slide, dt, state):
        """(dstate per revolution (nodes,), rate factor (nodes,) or None) of a law with
        memory at `state` (nodes,), from p [Pa] (steps, nodes), dS_i [m] (steps,) and the
        step Δt [s]; (None, None) for the others."""
        if self.name not in MEMORY_LAWS or self.strength == 0:
            return None, None
        if self.name == "damage_step":
            d = (pressure.max(axis=0) * 1e-6 / self.damage_ref_MPa) ** self.fatigue_exponent
            return d / self.fatigue_cycles, 1.0 + self.strength * _logistic(
                (state - 1.0) / self.damage_width)
        if self.name == "fatigue":
            over = np.maximum(pressure.max(axis=0) * 1e-6 / self.fatigue_endurance_MPa - 1.0,
                              0.0)
            d = over ** self.fatigue_exponent / self.fatigue_cycles
            return d, 1.0 + self.strength * (1.0 - np.exp(-np.maximum(state, 0.0) ** 3))
        t_off = dt * np.sum(pressure < 1.0, axis=0)  # the solve's p is exactly 0 off contact
        work = slide @ pressure * 1e-3  # J/m² -> kJ/m²
        d = (self.film_formation * (1.0 - state) ** 2 * np.sqrt(t_off / self.film_time_s)
             - self.film_removal * state * (work / self.film_work_kJ_per_m2) ** 1.5)
        return d, 1.0 - self.strength * state

    def rate_factor(self, pressure, speed, depth=None, sliding=0.0):
        """Factor of the local Archard rate, (steps, nodes) from p [Pa] (steps, nodes), v
        [m/s] (steps,), the worn profile h [m] (nodes,) the revolution wears on and the
        sliding distance S [m] at its start; None for laws that leave the rate alone."""
        if self.strength == 0 or self.name not in FACTOR_LAWS:
            return None
        p_mpa = pressure * 1e-6
        if self.name == "threshold":
            x = (p_mpa / self.threshold_MPa - 1.0) / self.threshold_width
        elif self.name == "two_variable":
            x = (p_mpa * speed[:, None] / self.pv_MPa_m_per_s - 1.0) / self.pv_width
        elif self.name == "pv_tanh":
            return 1.0 + self.strength * (p_mpa / self.pv_p_MPa) * np.tanh(
                speed[:, None] / self.pv_v_m_per_s)
        elif self.name == "worn_soft":
            h2 = (np.zeros(pressure.shape[1]) if depth is None else depth * 1e6) ** 2
            return np.broadcast_to(1.0 + self.strength * h2 / (h2 + self.soft_depth_um ** 2),
                                   pressure.shape)
        elif self.name == "bump_v":
            return 1.0 + self.strength * np.exp(
                -((speed[:, None] - self.bump_v0_m_per_s) / self.bump_width_m_per_s) ** 2
            ) * np.ones_like(p_mpa)
        elif self.name == "running_pressure":
            return 1.0 + self.strength * (p_mpa / self.rp_p_MPa) ** 2 / (
                1.0 + sliding / self.rp_distance_m)
        else:
            return 1.0 + self.strength * np.broadcast_to(
                self.grammar_phi(p_mpa, speed, depth, sliding), pressure.shape)
        return 1.0 + self.strength * _logistic(x)

    def thermal_rise(self, rise_K, power_W, seconds):
        """θ [K] after `seconds` at the constant frictional power `power_W` [W] from
        `rise_K`: the exact solution of dθ/dt = (P − θ/R_th)/C."""
        steady = self.thermal_resistance_K_per_W * power_W
        tau = self.thermal_resistance_K_per_W * self.thermal_capacity_J_per_K
        return steady + (rise_K - steady) * math.exp(-seconds / tau)

    def thermal_factor(self, rise_K):
        """The rate factor 1 + a (exp(θ/θ_e) − 1) at the temperature rise θ [K]; 1 for
        the other laws."""
        if self.name != "thermal" or self.strength == 0:
            return 1.0
        return 1.0 + self.strength * math.expm1(rise_K / self.thermal_scale_K)

    def grammar_phi(self, p_mpa, speed, depth, sliding):
        """Φ of a grammar law (`GRAMMAR_LAWS`) from p [MPa] (steps, nodes), v [m/s]
        (steps,), h [m] (nodes,) or None, S [m]."""
        v = speed[:, None]
        if self.name == "g_power_p":
            return (p_mpa / self.g_p1_MPa) ** self.g_exponent
        if self.name == "g_exp_h":
            h_um = (np.zeros(p_mpa.shape[1]) if depth is None else depth * 1e6)[None, :]
            return np.exp((h_um - self.g_h1_um) / self.g_he_um)
        if self.name == "g_hinge_v":
            return (np.maximum(v - self.g_v0_m_per_s, 0.0) / self.g_v1_m_per_s) \
                ** self.g_exponent
        if self.name == "g_step_S":
            return np.full((1, 1), _logistic((sliding - self.g_S0_m) / self.g_Sw_m))
        # g_step_p_power_v
        return _logistic((p_mpa - self.g_p0_MPa) / self.g_pw_MPa) \
            * (v / self.g_v1_m_per_s) ** self.g_exponent2


DEFAULT_STRENGTH = {"impact": 0.05, "threshold": 1.0, "two_variable": 1.0, "null": 0.0,
                    "pv_tanh": 1.0, "worn_soft": 1.5, "running_pressure": 2.0,
                    "impact_load": 0.16, "fatigue": 1.5, "film": 0.6, "damage_step": 1.5,
                    "g_power_p": 1.0, "g_exp_h": 0.5, "g_hinge_v": 1.5, "g_step_S": 0.8,
                    "g_step_p_power_v": 1.0, "g_dep_power_W": 2e-3, "bump_v": 1.5,
                    "thermal": 0.5}


def _logistic(x):
    return 0.5 * (1.0 + np.tanh(0.5 * x))  # 1/(1 + e^-x) without overflow


# ---- conditions ---------------------------------------------------------------------------


@dataclass(frozen=True)
class Condition:
    """One experiment (a specimen): nominal values, as the study states them."""

    name: str
    speed_rpm: float
    revolutions: float
    clearance_mm: float
    spring_N_per_m: float = 1009.4
    crank_length_mm: float = ref.L1 * 1e3
    interruptions: tuple = ()  # revolutions at which it is measured (besides the end)

    def measure_points(self) -> list[float]:
        pts = [r for r in (self.interruptions or (2000.0, 5000.0, 10000.0))
               if r < self.revolutions - 1e-9]
        return sorted(set(float(r) for r in pts) | {float(self.revolutions)})


PAPER = (  # design.md §6: the rig matrix of the paper (§3.3)
    Condition("n276-r10000", 276.0, 10000.0, 0.05),
    Condition("n276-r15000", 276.0, 15000.0, 0.05),
    Condition("n148-r10000", 148.0, 10000.0, 0.05),
    Condition("n230-r10000-c010", 230.0, 10000.0, 0.10),
    Condition("n230-r10000-c015", 230.0, 10000.0, 0.15),
)
# Other conditions: speeds 150-300 r/min, clearances 0.05-0.12 mm, 6000-12000 revolutions,
# springs 0-1800 N/m and crank lengths 50-90 mm. The crank length and the spring move the
# speed at which the load reverses (docs/hidden_physics.md): a slow test with reversals and
# a fast one without separate the crank speed from the load turn rate.
OTHER = (
    Condition("o300-r8000-L50", 300.0, 8000.0, 0.06, crank_length_mm=50.0),
    Condition("o180-r12000-L90", 180.0, 12000.0, 0.05, crank_length_mm=90.0),
    Condition("o260-r10000-k1800", 260.0, 10000.0, 0.08, spring_N_per_m=1800.0),
    Condition("o210-r10000-k1800-L50", 210.0, 10000.0, 0.05, spring_N_per_m=1800.0,
              crank_length_mm=50.0),
    Condition("o150-r6000-k0", 150.0, 6000.0, 0.12, spring_N_per_m=0.0),
)

_COND_KEYS = {"name", "speed_rpm", "revolutions", "clearance_mm", "spring_N_per_m",
              "crank_length_mm", "interruptions"}
_IGNORED_KEYS = {"profile", "angle_offset_deg"}  # a jaxwear study's data: replaced by ours


def read_conditions(path) -> tuple[tuple[Condition, ...], float]:
    """Experiments of a conditions file (a jaxwear study file, or one with only the keys of
    `Condition`), and the study's K_d start [1/Pa] (default 1e-13)."""
    path = Path(path)
    try:
        raw = tomllib.loads(path.read_text(encoding="utf-8-sig"))
    except OSError as e:
        raise BadInput(f"{path}: cannot read the conditions file ({e.strerror or e})") from None
    except tomllib.TOMLDecodeError as e:
        raise BadInput(f"{path}: TOML syntax error: {e}") from None
    model = raw.get("model", {})
    if model.get("preset", "rig") != "rig":
        raise BadInput(f"{path}: model.preset must be \"rig\" (the crank-slider), got "
                       f"{model.get('preset')!r}")
    params = dict(model.get("parameters", {}))
    kd = _num(path, "model.parameters.K_d_per_Pa", params.pop("K_d_per_Pa", 1e-13), pos=True)
    shared = {}
    for k in ("spring_N_per_m", "crank_length_mm"):
        if k in params:
            shared[k] = _num(path, f"model.parameters.{k}", params.pop(k))
    if params:
        raise BadInput(f"{path}: model.parameters: {sorted(params)} not supported by the "
                       f"generator; expected K_d_per_Pa, spring_N_per_m, crank_length_mm")
    exps = raw.get("experiment", [])
    if not isinstance(exps, list) or not exps:
        raise BadInput(f"{path}: no [[experiment]] tables")
    out = []
    for i, e in enumerate(exps):
        where = f"experiment[{i}]"
        unknown = set(e) - _COND_KEYS - _IGNORED_KEYS
        if unknown:
            raise BadInput(f"{path}: {where}: unknown key(s) {sorted(unknown)}; expected "
                           f"{sorted(_COND_KEYS)}")
        for k in ("speed_rpm", "revolutions", "clearance_mm"):
            if k not in e:
                raise BadInput(f"{path}: {where}: missing key {k!r}")
        kw = dict(shared)
        for k in ("speed_rpm", "revolutions", "clearance_mm", "spring_N_per_m",
                  "crank_length_mm"):
            if k in e:
                kw[k] = _num(path, f"{where}.{k}", e[k], pos=k != "spring_N_per_m")
        if kw.get("spring_N_per_m", 0.0) < 0:
            raise BadInput(f"{path}: {where}.spring_N_per_m must be >= 0")
        if not kw.get("crank_length_mm", ref.L1 * 1e3) < ref.L2 * 1e3:
            raise BadInput(f"{path}: {where}.crank_length_mm must be < the coupler's "
                           f"{ref.L2 * 1e3:g} mm")
        inter = tuple(_num(path, f"{where}.interruptions", r, pos=True)
                      for r in e.get("interruptions", ()))
        name = e.get("name", f"experiment{i + 1}")
        if not isinstance(name, str) or not name or "/" in name or "," in name:
            raise BadInput(f"{path}: {where}.name must be a string without '/' or ','")
        out.append(Condition(name, interruptions=inter, **kw))
    names = [c.name for c in out]
    if len(set(names)) != len(names):
        raise BadInput(f"{path}: experiment names repeat: {names}")
    return tuple(out), kd


def _num(path, where, v, pos=False):
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise BadInput(f"{path}: {where} must be a finite number, got {v!r}")
    if pos and not v > 0:
        raise BadInput(f"{path}: {where} must be > 0, got {v!r}")
    return float(v)


# ---- load over one revolution -------------------------------------------------------------


def load_at(phi1, omega, clearance, spring, l1, passes=2, gamma0=0.0):
    """SCLA (design.md §1, `scla_passes` = 2, γ0 = 0) at crank angles `phi1` [rad] (any array):
    each instant is independent (a stationary clearance link), so any sampling of the
    revolution gives the same values there. Returns F_C (…, 2) [N], θ_W [rad] (bushing in
    the coupler eye: θ_W = γ + Φ2) and Φ̇2 [rad/s]."""
    phi1 = np.asarray(phi1, float)
    gamma = np.full(phi1.shape, float(gamma0))
    x0 = ref.L2 - l1  # spring relaxed at inner dead centre (design.md §1)
    for _ in range(passes):
        kin = ref.kinematics(phi1, omega, gamma, clearance, l1)
        fx, fy = ref.pin_force(phi1, omega, *kin, spring, x0, l1)
        gamma = np.arctan2(fy, fx)
    return np.stack([fx, fy], axis=-1), gamma + kin[0], kin[1]


@dataclass(frozen=True)
class Cycle:
    """One revolution on the step grid t_i = i T/n (design.md §1): load vector W (steps, 2)
    [N], sliding per step dS_i [m], sliding speed v_i [m/s], step Δt [s]."""

    load: np.ndarray
    slide: np.ndarray
    speed: np.ndarray
    dt: float


def cycle(cond: Condition, clearance: float, steps: int) -> Cycle:
    omega = TWO_PI * cond.speed_rpm / 60.0
    phi1 = TWO_PI * np.arange(steps) / steps
    force, theta_w, phi2_d = load_at(phi1, omega, clearance, cond.spring_N_per_m,
                                     cond.crank_length_mm * 1e-3)
    mag = np.hypot(force[:, 0], force[:, 1])
    load = mag[:, None] * np.stack([np.cos(theta_w), np.sin(theta_w)], axis=1)
    r_p = ref.R_B - clearance  # the clearance changes the pin, not the bore
    dt = TWO_PI / omega / steps
    speed = r_p * np.abs(phi2_d)
    return Cycle(load, speed * dt, speed, dt)


def resolved_sweep(cond: Condition, clearance: float, sweep_deg: float, start: int = 720):
    """The load direction over one revolution, sampled so that it turns by at most
    `sweep_deg` between samples: a uniform start grid of `start` crank angles, each interval
    that turns more split evenly, repeated until none does (at a reversal the direction
    sweeps 105-156° within 6-15 crank degrees). Returns per interval the time Δt [s], the
    turn rate |dθ_W/dt| [rad/s] and the load direction at its midpoint [rad]."""
    omega = TWO_PI * cond.speed_rpm / 60.0
    l1 = cond.crank_length_mm * 1e-3
    phi = TWO_PI * np.arange(start + 1) / start  # closed: the last point is the first
    for _ in range(60):
        _, theta, _ = load_at(phi, omega, clearance, cond.spring_N_per_m, l1)
        turn = np.abs(np.angle(np.exp(1j * np.diff(theta))))
        parts = np.ceil(turn / (sweep_deg * DEG)).astype(int)
        if parts.max() <= 1:
            break
        frac = [np.arange(k) / k for k in parts]
        phi = np.concatenate([phi[i] + f * (phi[i + 1] - phi[i]) for i, f in enumerate(frac)]
                             + [phi[-1:]])
    else:
        raise RuntimeError("the load direction could not be resolved (a load through zero?)")
    dphi = np.diff(phi)
    mid = theta[:-1] + 0.5 * np.angle(np.exp(1j * np.diff(theta)))
    return dphi / omega, turn / (dphi / omega), mid


def impact_deposit(law: Law, cond: Condition, clearance: float, nodes: int,
                   sweep_deg: float) -> np.ndarray:
    """Depth [m] that the `impact` law deposits per revolution at each node (N,). It does
    not depend on the wear: a revolution's impacts are one fixed vector per experiment."""
    if law.name not in ("impact", "impact_load") or law.strength == 0:
        return np.zeros(nodes)
    dt, rate, where = resolved_sweep(cond, clearance, sweep_deg)
    over = np.maximum(rate - law.turn_threshold_deg_per_s * DEG, 0.0)
    # per radian of sweep beyond ω0 at ω_ref: C (ω - ω0) ((ω - ω0)/ω_ref)^(q-1) dt
    weight = over * (over / (law.turn_reference_deg_per_s * DEG)) ** (law.impact_exponent - 1)
    weight = law.strength * 1e-9 * weight * dt
    if law.name == "impact_load":
        # the load at each resolved interval: by the direction's own sampling (the
        # interval's midpoint in crank angle, from its time and the crank speed)
        omega = TWO_PI * cond.speed_rpm / 60.0
        phi_mid = np.cumsum(dt * omega) - 0.5 * dt * omega
        force, _, _ = load_at(phi_mid, omega, clearance, cond.spring_N_per_m,
                              cond.crank_length_mm * 1e-3)
        weight = weight * np.tanh(np.hypot(force[:, 0], force[:, 1]) / law.impact_load_N)
    keep = weight > 0
    theta = TWO_PI * np.arange(nodes) / nodes
    gap = np.angle(np.exp(1j * (theta[None, :] - where[keep, None])))
    kernel = np.exp(-0.5 * (gap / (law.impact_width_deg * DEG)) ** 2)
    return weight[keep] @ kernel


def grammar_deposit(law: Law, cond: Condition, clearance: float, nodes: int,
                    sweep_deg: float) -> np.ndarray:
    """Depth [m] the grammar's deposit law (`GRAMMAR_DEPOSIT_LAWS`) lays per revolution at
    each node (N,): Σ over the resolved intervals of D 1e-9 (N_s/2π) Δφ Φ(|W|) g(θ_j −
    θ_W), Δφ the interval's crank angle [rad], θ_W the load direction at its midpoint,
    g a Gaussian bump normalised so that Σ_j g Δθ = 1 [1/rad] (`Law`'s docstring). Does
    not depend on the wear: one fixed vector per experiment."""
    if law.name not in GRAMMAR_DEPOSIT_LAWS or law.strength == 0:
        return np.zeros(nodes)
    dt, _, where = resolved_sweep(cond, clearance, sweep_deg)
    omega = TWO_PI * cond.speed_rpm / 60.0
    dphi = dt * omega
    phi_mid = np.cumsum(dphi) - 0.5 * dphi
    force, _, _ = load_at(phi_mid, omega, clearance, cond.spring_N_per_m,
                          cond.crank_length_mm * 1e-3)
    w_mag = np.hypot(force[:, 0], force[:, 1])
    phi = (w_mag / law.g_W1_N) ** law.g_dep_exponent
    weight = law.strength * 1e-9 * (law.g_dep_steps / TWO_PI) * dphi * phi
    d_node = TWO_PI / nodes
    width = max(law.g_dep_width_deg * DEG, 1.5 * d_node)
    theta = d_node * np.arange(nodes)
    gap = np.angle(np.exp(1j * (theta[None, :] - where[:, None])))
    bump = np.exp(-0.5 * (gap / width) ** 2)
    bump /= bump.sum(axis=1, keepdims=True) * d_node
    return weight @ bump


# ---- contact: all steps of a revolution at once -------------------------------------------


def contact_batch(normals, gap, k, area, load, e0=None, tol=1e-10):
    """Pressures p (steps, nodes) [Pa] from Σ_j p_ij A n_j = W_i for every step i at once
    (design.md §3, unsymmetric), and the pin offsets e (steps, 2) [m].

    Semi-smooth Newton on the convex potential Π_i(e) = Σ_j ½ kA max(e·n_j - g_j, 0)² -
    W_i·e, backtracking on Π where a full step does not decrease it; started from `e0`
    (the previous update's offsets) where that touches the bore, else from the 1-D solution
    along the load (`numpy_reference._solve_1d`, vectorised here)."""
    steps = load.shape[0]
    ka = k * area
    w_mag = np.hypot(load[:, 0], load[:, 1])
    live = w_mag > 0
    c, s = normals[:, 0], normals[:, 1]
    e = np.zeros((steps, 2)) if e0 is None else np.array(e0, float)
    touching = np.any(e @ normals.T - gap > 0, axis=1)
    cold = live & ~touching
    if cold.any():
        u = load[cold] / w_mag[cold, None]
        e[cold] = _solve_1d_batch(u @ normals.T, gap, ka, w_mag[cold])[:, None] * u
    e[~live] = 0.0
    rows = np.flatnonzero(live)
    for _ in range(100):
        if rows.size == 0:
            break
        er, wr = e[rows], load[rows]
        d = er[:, :1] * c + er[:, 1:] * s - gap
        act = d > 0
        kd = np.where(act, d, 0.0) * ka
        grad = np.stack([kd @ c, kd @ s], axis=1) - wr
        gnorm = np.hypot(grad[:, 0], grad[:, 1])
        done = gnorm < tol * w_mag[rows]
        rows, er, wr, d, act, kd, grad = (rows[~done], er[~done], wr[~done], d[~done],
                                          act[~done], kd[~done], grad[~done])
        if rows.size == 0:
            break
        kact = np.where(act, ka, 0.0)
        h11, h12, h22 = kact @ (c * c), kact @ (c * s), kact @ (s * s)
        shift = 1e-12 * (h11 + h22)  # one active node gives a rank-1 Hessian
        h11, h22 = h11 + shift, h22 + shift
        det = h11 * h22 - h12 * h12
        step = -np.stack([h22 * grad[:, 0] - h12 * grad[:, 1],
                          h11 * grad[:, 1] - h12 * grad[:, 0]], axis=1) / det[:, None]
        pi0 = 0.5 * np.sum(kd * np.where(act, d, 0.0), axis=1) - np.sum(wr * er, axis=1)
        slope = np.sum(grad * step, axis=1)
        t = np.ones(rows.size)
        todo = np.arange(rows.size)
        for _ in range(50):
            trial = er[todo] + t[todo, None] * step[todo]
            dt_ = trial[:, :1] * c + trial[:, 1:] * s - gap
            pos = np.maximum(dt_, 0.0)
            pi = 0.5 * (pos * pos) @ ka - np.sum(wr[todo] * trial, axis=1)
            kpos = pos * ka
            g_new = np.stack([kpos @ c, kpos @ s], axis=1) - wr[todo]
            # Armijo on Π; near the root Π is flat to round-off, so a step that lands within
            # tolerance is accepted as it stands
            ok = ((pi <= pi0[todo] + 1e-4 * t[todo] * slope[todo])
                  | (np.hypot(g_new[:, 0], g_new[:, 1]) < tol * w_mag[rows[todo]]))
            todo = todo[~ok]
            if todo.size == 0:
                break
            t[todo] *= 0.5
        e[rows] = er + t[:, None] * step
    else:
        raise RuntimeError("unsymmetric contact: Newton did not converge in 100 iterations")
    p = k * np.maximum(e @ normals.T - gap, 0.0)  # eq 14
    p[~live] = 0.0
    return p, e


def _solve_1d_batch(cosb, gap, ka, w_mag):
    """`numpy_reference._solve_1d` for many loads at once: s ≥ 0 per row with Σ_j kA
    max(s cosβ_j - g_j, 0) cosβ_j = |W| (convex, increasing, piecewise linear in s)."""
    with np.errstate(divide="ignore"):
        ratio = np.where(cosb > 0, gap / np.where(cosb > 0, cosb, 1.0), np.inf)
    s = ratio.min(axis=1)
    for _ in range(100):
        d = s[:, None] * cosb - gap
        act = d >= 0
        f = np.sum(np.where(act, ka * d * cosb, 0.0), axis=1) - w_mag
        if np.all(np.abs(f) <= 1e-10 * w_mag):
            break
        slope = np.sum(np.where(act, ka * cosb * cosb, 0.0), axis=1)
        s = s - f / slope
    return s  # a start: the 2-D Newton method converges from it either way


# ---- the wear history ---------------------------------------------------------------------


@dataclass(frozen=True)
class Numerics:
    """The generator's numerics: bore nodes, steps per revolution, eq 23's M, and the
    largest turn of the load direction between two sub-steps of the impact sweep [deg]."""

    nodes: int = 180
    steps: int = 360
    M: float = 25.0
    sweep_deg: float = 0.25

    def __post_init__(self):
        if not (self.nodes >= 8 and self.steps >= 8 and self.M > 0 and self.sweep_deg > 0):
            raise BadInput(f"numerics must have nodes, steps >= 8, M > 0, sweep_deg > 0: "
                           f"{self}")


def wear_history(cond: Condition, clearance: float, K_d: float, law: Law,
                 num: Numerics = Numerics(), backing: float = 0.0) -> dict:
    """Wear of one specimen: Archard (design.md §4) with eq 23's updates of M revolutions
    (profile frozen within one), ending exactly at every measurement point, plus the law.
    `backing` [m/Pa]: compliance L_b/E_w,b of a backing layer in series (design.md §3's double
    layer; 0: the single layer).

    **Returns:** `depth` (points, nodes) [m] at `points` (revolutions), `theta` (nodes,)
    [rad], `hidden_volume` and `volume` [m³] at the end (the law's share of the worn
    volume), `updates`."""
    cyc = cycle(cond, clearance, num.steps)
    theta = TWO_PI * np.arange(num.nodes) / num.nodes
    normals = np.stack([np.cos(theta), np.sin(theta)], axis=1)
    area = ref.R_B * (TWO_PI / num.nodes) * ref.WIDTH
    deposit = (impact_deposit(law, cond, clearance, num.nodes, num.sweep_deg)
               + grammar_deposit(law, cond, clearance, num.nodes, num.sweep_deg))
    points = cond.measure_points()
    h = np.zeros(num.nodes)
    state = np.zeros(num.nodes)  # a law with memory's per-node state (0: a new surface)
    hidden = np.zeros(num.nodes)
    # the `thermal` law's bulk temperature rise [K] and the joint's frictional power [W]
    # (the load and the sliding do not depend on the wear here: one value per specimen)
    rise = 0.0
    power = law.thermal_friction * float(np.mean(np.hypot(*cyc.load.T) * cyc.speed))
    rev_s = 60.0 / cond.speed_rpm
    e = None
    done, updates, out = 0.0, 0, []
    for target in points:
        while done < target - 1e-9:
            block = min(num.M, target - done)
            # eq 14, the worn (thinner) layer, in series with a backing (design.md §3)
            k = 1.0 / ((ref.LAYER - h) / ref.E_W + backing)
            p, e = contact_batch(normals, clearance + h, k, area, cyc.load, e)
            rate = K_d * p * cyc.slide[:, None]  # eq 21 per step and node
            factor = law.rate_factor(p, cyc.speed, h, done * float(cyc.slide.sum()))
            base = rate.sum(axis=0)
            dh = base if factor is None else (rate * factor).sum(axis=0)
            dstate, mfactor = law.memory_step(p, cyc.slide, cyc.dt, state)
            if dstate is not None:
                dh = dh * mfactor
                state = state + block * dstate
            if law.name == "thermal":
                # the rate at θ at the update's middle (second order in its length), θ
                # carried to its end exactly
                dh = dh * law.thermal_factor(law.thermal_rise(rise, power,
                                                              0.5 * block * rev_s))
                rise = law.thermal_rise(rise, power, block * rev_s)
            dh = dh + deposit
            hidden += block * (dh - base)
            h = h + block * dh  # eq 23
            done += block
            updates += 1
            if np.any(h >= ref.LAYER):
                raise BadInput(f"{cond.name}: the layer is worn through at revolution "
                               f"{done:g}; choose a smaller strength or K_d")
        out.append(h.copy())
    return {"depth": np.array(out), "points": points, "theta": theta,
            "volume": float(h.sum() * area), "hidden_volume": float(hidden.sum() * area),
            "updates": updates}


# ---- the study ----------------------------------------------------------------------------


@dataclass
class Generated:
    truth: dict
    profiles: dict = field(default_factory=dict)  # name -> (points, depth (points, nodes) m)
    scans: dict = field(default_factory=dict)  # name -> rows (angle_deg, depth_um, revs)


def generate(law: Law, conditions, *, seed: int = 0, noise_um: float = 0.3,
             num: Numerics = Numerics(), kd_start: float = 1e-13, kd_sd: float = 0.15,
             K_d: float | None = None, clearance_sd_um: float = 3.0,
             scan_step_deg: float = 2.0, backing_um_per_MPa: float = 0.0,
             verbose: bool = False) -> Generated:
    """Data of `conditions` (Conditions) with `law` hidden: true K_d = `K_d` or the start
    value times a log-normal factor (σ = `kd_sd`), each true clearance nominal + N(0,
    `clearance_sd_um`), whole-bore scans every `scan_step_deg` with N(0, `noise_um`) on
    every point (negative depths included), at every measurement point. A backing layer of
    compliance `backing_um_per_MPa` [µm/MPa] (0: none) under the wearing one."""
    if not (noise_um >= 0 and clearance_sd_um >= 0 and kd_sd >= 0 and scan_step_deg > 0):
        raise BadInput("noise, clearance spread and K_d spread must be >= 0, the scan step "
                       "> 0")
    if not (math.isfinite(backing_um_per_MPa) and backing_um_per_MPa >= 0):
        raise BadInput(f"--backing-compliance-um-per-MPa must be a finite number >= 0, got "
                       f"{backing_um_per_MPa!r}")
    rng = np.random.default_rng(seed)
    kd = float(K_d) if K_d is not None else kd_start * math.exp(kd_sd * rng.standard_normal())
    truth = {"generator": "benchmarks/hidden_physics.py", "law": asdict(law),
             "K_d_per_Pa": kd, "K_d_start_per_Pa": kd_start, "clearance_mm": {},
             "clearance_nominal_mm": {}, "clearance_sd_um": clearance_sd_um,
             "noise_um": noise_um, "seed": seed, "numerics": asdict(num),
             "scan_step_deg": scan_step_deg,
             "backing_compliance_um_per_MPa": backing_um_per_MPa,
             "hidden_volume_fraction": {},
             "peak_depth_um": {}, "updates": {}, "seconds": {}}
    gen = Generated(truth)
    clearances = {c.name: c.clearance_mm + 1e-3 * clearance_sd_um * rng.standard_normal()
                  for c in conditions}
    for cond in conditions:
        cl = clearances[cond.name]
        if not 0 < cl < ref.R_B * 1e3:
            raise BadInput(f"{cond.name}: true clearance {cl:g} mm outside (0, bore radius)")
        t0 = time.perf_counter()
        res = wear_history(cond, cl * 1e-3, kd, law, num,
                           backing=backing_um_per_MPa * 1e-12)  # µm/MPa = 1e-12 m/Pa
        sec = time.perf_counter() - t0
        if verbose:
            print(f"hidden_physics: {cond.name}: {res['updates']} updates, peak "
                  f"{res['depth'][-1].max() * 1e6:.3f} µm, hidden share of the volume "
                  f"{res['hidden_volume'] / res['volume']:.1%} ({sec:.1f} s)",
                  file=sys.stderr, flush=True)
        truth["clearance_mm"][cond.name] = cl
        truth["clearance_nominal_mm"][cond.name] = cond.clearance_mm
        truth["hidden_volume_fraction"][cond.name] = res["hidden_volume"] / res["volume"]
        truth["peak_depth_um"][cond.name] = float(res["depth"][-1].max() * 1e6)
        truth["updates"][cond.name] = res["updates"]
        truth["seconds"][cond.name] = sec
        gen.profiles[cond.name] = (res["points"], res["depth"])
        ang = np.arange(0.0, 360.0, scan_step_deg)
        rows = []
        for pt, depth in zip(res["points"], res["depth"]):
            d = _interp_periodic(depth * 1e6, ang)
            y = d + noise_um * rng.standard_normal(len(ang))  # every point, zero mean
            rows += list(zip(ang, y, [pt] * len(ang)))
        gen.scans[cond.name] = rows
    return gen


def _interp_periodic(values, angle_deg):
    """Periodic linear interpolation of node values (node j at 360 j/N degrees)."""
    n = len(values)
    x = np.mod(np.asarray(angle_deg, float) * n / 360.0, n)
    i0 = np.floor(x).astype(int) % n
    w = x - np.floor(x)
    return values[i0] * (1 - w) + values[(i0 + 1) % n] * w


def _toml(v) -> str:
    if isinstance(v, str):
        return json.dumps(v)
    return f"{v:.10g}" if isinstance(v, float) and not float(v).is_integer() else f"{v:g}"


def study_text(conditions, kd_start: float, study_numerics, clearance_sd_um: float,
               spring: float = 1009.4, contact: str | None = None) -> str:
    """study.toml (design.md §6): nominal clearances, the K_d start, the numerics a user would
    choose (`study_numerics` None: none, so jaxwear chooses them by the error), the
    clearance tolerance; `contact` the contact the study states (None: the default)."""
    lines = ["# Written by benchmarks/hidden_physics.py: data with physics outside jaxwear's",
             "# library, at finer numerics than any fit uses. The truth is in truth.json",
             "# (not referenced by this study).", "[model]", 'preset = "rig"']
    if contact is not None:
        lines.append(f"contact = {_toml(contact)}")
    lines += ["[model.parameters]", f"K_d_per_Pa = {kd_start:g}",
             f"spring_N_per_m = {_toml(spring)}"]
    if study_numerics is not None:
        nodes, steps = study_numerics
        lines += ["[numerics]", f"nodes = {nodes}", f"steps_per_rev = {steps}"]
    lines += ["[fit]", f"clearance_tolerance_um = {_toml(float(clearance_sd_um))}"]
    for c in conditions:
        lines += ["", "[[experiment]]", f"name = {_toml(c.name)}",
                  f"speed_rpm = {_toml(c.speed_rpm)}", f"revolutions = {_toml(c.revolutions)}",
                  f"clearance_mm = {_toml(c.clearance_mm)}"]
        if c.spring_N_per_m != spring:
            lines.append(f"spring_N_per_m = {_toml(c.spring_N_per_m)}")
        if abs(c.crank_length_mm - ref.L1 * 1e3) > 1e-12:
            lines.append(f"crank_length_mm = {_toml(c.crank_length_mm)}")
        lines.append(f"profile = {_toml(c.name + '.csv')}")
    return "\n".join(lines) + "\n"


def check_outputs(out, conditions, inputs=()) -> Path:
    """`out` as a Path; BadInput if it is a file or a file `write` makes there would
    replace one of `inputs` (checked before any work, and again when writing)."""
    out = Path(out)
    names = [f"{c.name}.csv" for c in conditions] + ["truth.json", "truth_profiles.csv",
                                                       "study.toml"]
    keep = {Path(p).resolve() for p in inputs}
    for n in names:
        if (out / n).resolve() in keep:
            raise BadInput(f"{out / n}: refusing to replace an input; choose another --out")
    if out.exists() and not out.is_dir():
        raise BadInput(f"{out}: --out must be a folder")
    return out


def write(out, gen: Generated, conditions, *, kd_start=1e-13, study_numerics=None,
          inputs=(), contact: str | None = None) -> Path:
    """study.toml, one profile CSV per experiment (`angle_deg,depth_um,revolutions`),
    truth.json and truth_profiles.csv (noise-free node values) in `out`. Refuses (BadInput)
    a file that would replace one of `inputs`; each file is written to a temporary name
    and renamed, the study last (its data are beside it when it appears)."""
    out = check_outputs(out, conditions, inputs)
    out.mkdir(parents=True, exist_ok=True)
    for c in conditions:
        _atomic(out / f"{c.name}.csv", "angle_deg,depth_um,revolutions\n" + "".join(
            f"{a:g},{d:.4f},{r:g}\n" for a, d, r in gen.scans[c.name]))
    rows = ["experiment,revolutions,angle_deg,depth_um\n"]
    for name, (points, depth) in gen.profiles.items():
        deg = 360.0 * np.arange(depth.shape[1]) / depth.shape[1]
        rows += [f"{name},{pt:g},{a:g},{d * 1e6:.9g}\n" for pt, prof in zip(points, depth)
                 for a, d in zip(deg, prof)]
    _atomic(out / "truth_profiles.csv", "".join(rows))
    _atomic(out / "truth.json", json.dumps(gen.truth, indent=2) + "\n")
    spring = conditions[0].spring_N_per_m if conditions else 1009.4
    _atomic(out / "study.toml", study_text(conditions, kd_start, study_numerics,
                                           gen.truth["clearance_sd_um"], spring, contact))
    return out / "study.toml"


def _atomic(path: Path, text: str) -> None:
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".part")
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


# ---- command line -------------------------------------------------------------------------


def _parse_numerics(text: str):
    if text in ("auto", "none"):
        return None
    try:
        nodes, steps = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise BadInput(f"--study-numerics must be auto or NODESxSTEPS (e.g. 90x72), got "
                       f"{text!r}") from None
    if nodes < 8 or steps < 8:
        raise BadInput("--study-numerics: nodes and steps must be >= 8")
    return nodes, steps


def _law_from(args) -> Law:
    kw = {"name": args.law, "strength": (DEFAULT_STRENGTH.get(args.law, 0.0)
                                         if args.strength is None else args.strength)}
    fields = set(asdict(Law())) - {"name", "strength"}
    for item in args.set:
        key, _, val = item.partition("=")
        if key not in fields:
            raise BadInput(f"--set {item}: unknown law constant {key!r}; expected one of "
                           f"{sorted(fields)}")
        try:
            kw[key] = float(val)
        except ValueError:
            raise BadInput(f"--set {item}: {val!r} is not a number") from None
    return Law(**kw)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--law", required=True, help=f"one of {', '.join(LAWS)}")
    ap.add_argument("--strength", type=float, default=None,
                    help=f"the law's strength (defaults {DEFAULT_STRENGTH})")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="a law constant, e.g. turn_threshold_deg_per_s=3000")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", required=True, help="output folder")
    ap.add_argument("--conditions", default="paper", help="paper, other or a TOML file")
    ap.add_argument("--noise-um", type=float, default=0.3)
    ap.add_argument("--nodes", type=int, default=Numerics.nodes)
    ap.add_argument("--steps", type=int, default=Numerics.steps)
    ap.add_argument("--M", type=float, default=Numerics.M, help="revolutions per update")
    ap.add_argument("--sweep-deg", type=float, default=Numerics.sweep_deg,
                    help="largest load turn between impact sub-steps [deg]")
    ap.add_argument("--study-numerics", default="auto",
                    help="numerics the study states: auto (none: jaxwear chooses) or NxS")
    ap.add_argument("--clearance-sd-um", type=float, default=3.0)
    ap.add_argument("--kd-sd", type=float, default=0.15)
    ap.add_argument("--kd", type=float, default=None, help="true K_d [1/Pa] (default drawn)")
    ap.add_argument("--scan-step-deg", type=float, default=2.0)
    ap.add_argument("--backing-compliance-um-per-MPa", type=float, default=0.0,
                    help="compliance L_b/E_w,b of a backing layer in the data (0: none)")
    ap.add_argument("--study-contact", choices=("symmetric", "unsymmetric"), default=None,
                    help="the contact the written study states (default: none stated)")
    args = ap.parse_args(argv)
    try:
        law = _law_from(args)
        num = Numerics(args.nodes, args.steps, args.M, args.sweep_deg)
        study_num = _parse_numerics(args.study_numerics)
        inputs = []
        if args.conditions == "paper":
            conds, kd_start = PAPER, 1e-13
        elif args.conditions == "other":
            conds, kd_start = OTHER, 1e-13
        else:
            if not Path(args.conditions).is_file():
                raise BadInput(f"--conditions {args.conditions}: not paper, other or a file")
            conds, kd_start = read_conditions(args.conditions)
            inputs.append(args.conditions)
        check_outputs(args.out, conds, inputs)
        t0 = time.perf_counter()
        gen = generate(law, conds, seed=args.seed, noise_um=args.noise_um, num=num,
                       kd_start=kd_start, kd_sd=args.kd_sd, K_d=args.kd,
                       clearance_sd_um=args.clearance_sd_um,
                       scan_step_deg=args.scan_step_deg,
                       backing_um_per_MPa=args.backing_compliance_um_per_MPa, verbose=True)
        gen.truth["study_numerics"] = "auto" if study_num is None else list(study_num)
        gen.truth["seconds_total"] = time.perf_counter() - t0
        path = write(args.out, gen, conds, kd_start=kd_start, study_numerics=study_num,
                     inputs=inputs, contact=args.study_contact)
    except BadInput as e:
        print(f"hidden_physics: error: {e}", file=sys.stderr)
        return 2
    n = sum(len(r) for r in gen.scans.values())
    print(f"wrote {path} ({len(conds)} experiments, {n} rows; law {law.name}, strength "
          f"{law.strength:g}; {gen.truth['seconds_total']:.1f} s); truth in "
          f"{path.parent / 'truth.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
