"""Load history of one cycle, in the bushing frame: what the contact and wear need per step.

A cycle is one crank revolution (crank-slider), one swing (oscillating joint) or one period
of a load file (your own joint). The history has a leading `regimes` axis: the crank-slider
has one regime; the oscillating joint and the load history have one per duty block (each
amplitude, each file, is its own cycle). Every driver's load is multiplied by `load_scale`.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from jaxwear._core import pytree
from jaxwear._core.types import Array, Float
from jaxwear._physics.config import ModelConfig
from jaxwear._physics.load_cycle import resample
from jaxwear._physics.mechanism import _safe_atan2, crank_slider_forces
from jaxwear._physics.params import Params


class LoadHistory(pytree.Struct):
    """Per-step load and motion of one cycle, for each regime (a duty block, or the one
    cycle of a crank). Arrays (regimes, steps) unless said:

    - `load`: |W| [N]; `angle`: θ_W, the load's direction in the bushing frame [rad];
    - `slide`: dS_i = R_p |Δφ_i| [m]; `dt`: Δt_i [s]; `sense`: sign of the pin's rotation
      relative to the bushing (±1);
    - `period` (regimes,): the cycle's duration [s];
    - `gamma_change`: the SCLA's last-pass |Δγ| [rad] (0 for other algorithms);
    - `fx`, `fy`: the joint force's components in the ground frame [N];
    - `shape_pre`: the shape correction's constant parts (None without one);
    - `swept` (regimes, steps, nodes) [1/rad]: the deposit's kernel
      (`effects.shape.swept_kernel`), where an effect declares `uses_swept_kernel`.
    """

    load: Float[Array, "regimes steps"]  # |W| [N]
    angle: Float[Array, "regimes steps"]  # θ_W, bushing frame [rad]
    slide: Float[Array, "regimes steps"]  # dS_i = R_p |Δφ_i| [m]
    dt: Float[Array, "regimes steps"]  # Δt_i [s]
    sense: Float[Array, "regimes steps"]  # sign of the pin's rotation relative to the bushing
    period: Float[Array, " regimes"]  # cycle duration [s]
    gamma_change: Float[Array, "regimes steps"]  # SCLA last-pass |Δγ| [rad]
    fx: Float[Array, "regimes steps"]  # joint force components, ground frame [N]
    fy: Float[Array, "regimes steps"]
    shape_pre: object = None  # the shape correction's constant parts (`effects.shape`)
    swept: object = None  # (regimes, steps, nodes) swept kernel, where an effect uses it


def _crank_slider(p: Params, cfg: ModelConfig) -> LoadHistory:
    n = cfg.steps_per_rev
    period = 2 * jnp.pi / p.speed
    t = jnp.arange(n) * (period / n)
    jf = crank_slider_forces(p, t, cfg.algorithm, cfg.scla_passes, cfg.gamma0_rad)
    mag = jnp.sqrt(jnp.where(jf.fx**2 + jf.fy**2 > 0, jf.fx**2 + jf.fy**2, 1.0))
    mag = jnp.where(jf.fx**2 + jf.fy**2 > 0, mag, 0.0)
    gamma = _safe_atan2(jf.fy, jf.fx)
    rel_rate = jf.kin.phi2_d  # pin (slider, no rotation) relative to bushing (coupler, ψ = -Φ2)
    if cfg.bushing == "coupler":
        angle = gamma + jf.kin.phi2  # θ_W = γ - ψ
        sense = jnp.sign(rel_rate)
    else:  # bushing in the slider: the coupler's pin loads it with -F_C, frame fixed
        angle = gamma + jnp.pi
        sense = -jnp.sign(rel_rate)
    dt = jnp.full_like(t, period / n)
    slide = p.pin_radius * jnp.abs(rel_rate) * dt
    angle = jnp.mod(angle + jnp.pi, 2 * jnp.pi) - jnp.pi
    return LoadHistory(load=mag[None], angle=angle[None], slide=slide[None], dt=dt[None],
                       sense=sense[None], period=period[None],
                       gamma_change=jf.gamma_change[None], fx=jf.fx[None], fy=jf.fy[None])


def _oscillating(p: Params, cfg: ModelConfig) -> LoadHistory:
    n = cfg.steps_per_rev
    period = p.swing_period
    t = jnp.arange(n) * (period / n)
    amps = jnp.deg2rad(jnp.array([b.amplitude_deg for b in cfg.duty_cycle]))[:, None]
    omega = 2 * jnp.pi / period
    phi = amps * jnp.sin(omega * t)
    phi_d = amps * omega * jnp.cos(omega * t)
    # The load is fixed in the ground frame; the bushing turns with the arm by φ.
    angle = p.load_angle - phi
    dt = jnp.broadcast_to(period / n, phi.shape)
    slide = p.pin_radius * jnp.abs(phi_d) * dt
    load = jnp.broadcast_to(p.load, phi.shape)
    zeros = jnp.zeros_like(phi)
    return LoadHistory(load=load, angle=angle, slide=slide, dt=dt, sense=-jnp.sign(phi_d),
                       period=jnp.broadcast_to(period, (amps.shape[0],)), gamma_change=zeros,
                       fx=load * jnp.cos(angle), fy=load * jnp.sin(angle))


def _from_files(p: Params, cfg: ModelConfig) -> LoadHistory:
    # Each duty block's file on the loop's steps (host arrays, cached per resolution: the
    # file is data, not a parameter); only the pin radius enters from `p`.
    steps = [resample(b.load, cfg.steps_per_rev) for b in cfg.duty_cycle]

    def stack(name):
        return jnp.asarray(np.stack([getattr(r, name) for r in steps]))

    load, angle, dt = stack("load"), stack("angle"), stack("dt")
    zeros = jnp.zeros_like(load)
    return LoadHistory(load=load, angle=angle, slide=p.pin_radius * stack("rotation"), dt=dt,
                       sense=jnp.sign(stack("net")),
                       period=jnp.asarray([r.period for r in steps]), gamma_change=zeros,
                       fx=load * jnp.cos(angle), fy=load * jnp.sin(angle))


def load_history(p: Params, cfg: ModelConfig) -> LoadHistory:
    """The cycle's load history for the configured driver (design.md §1-2), its load times
    `load_scale`."""
    if cfg.driver == "oscillating":
        hist = _oscillating(p, cfg)
    elif cfg.driver == "load_history":
        hist = _from_files(p, cfg)
    else:
        hist = _crank_slider(p, cfg)
    s = p.load_scale
    return pytree.replace(hist, load=s * hist.load, fx=s * hist.fx, fy=s * hist.fy)


def block_periods(p: Params, cfg: ModelConfig) -> list[float]:
    """Duration of one cycle of each duty block [s] (host floats): the swing period of the
    oscillating joint, each file's period for a load history."""
    if cfg.driver == "load_history":
        return [b.load.period for b in cfg.duty_cycle]
    return [float(p.swing_period)] * len(cfg.duty_cycle)
