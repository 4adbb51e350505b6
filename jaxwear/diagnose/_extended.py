"""The extended model: the study's base parameters and every candidate strength in one
vector u, evaluated (rows and Jacobian) by one compiled function."""

from __future__ import annotations

from dataclasses import dataclass

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._config import ModelConfig
from .._params import Params
from .._schedule import Schedule
from .._wear import wear_loop
from ..effects import STRUCTURAL_CANDIDATES, get_effect, product_pairs, registered_effects


@dataclass(frozen=True)
class Column:
    """One entry of the extended parameter vector u.

    `key`: study key (or structural strength key); `experiment`: index for a per-experiment
    parameter (clearances), else None; `log`: u is ln(value/start), else
    u = (value - start)/scale; `group`: "" for the base model's parameters, else the name of
    the candidate it belongs to; `lower`, `upper`: bounds in the key's unit.
    """

    key: str
    experiment: int | None
    log: bool
    scale: float
    to_si: float
    group: str
    lower: float
    upper: float
    strength: bool = False  # a nested strength (score-tested at its off value)


class Extended(eqx.Module):
    """The study's model with every candidate switched on; u ↦ snapshots [µm].

    Candidate strengths at their `off` values (u = 0 for them) give the base model.
    """

    cfg: ModelConfig = eqx.field(static=True)
    columns: tuple = eqx.field(static=True)
    params: Params  # batched over experiments
    schedule: Schedule  # batched
    start: jax.Array  # (P,) start values, key units

    def values(self, u):
        """Values in the keys' units; a strength with its `per` parameter is fitted as their
        product (`EffectParameter.per`, as calibrate's `Problem.values`)."""
        out = []
        for i, c in enumerate(self.columns):
            out.append(self.start[i] * jnp.exp(u[i]) if c.log else self.start[i] + c.scale * u[i])
        for i, j in product_pairs([c.key for c in self.columns]):
            out[i] = out[i] * jnp.exp(-u[j])
        return jnp.stack(out)

    def batched_params(self, u) -> Params:
        vals = self.values(u)
        p = self.params
        n_exp = self.schedule.cycles.shape[0]
        updates: dict = {}
        structural: dict = {}
        for i, c in enumerate(self.columns):
            si = vals[i] * c.to_si
            if c.group in STRUCTURAL_CANDIDATES:
                structural.setdefault(c.group, {})[c.key] = jnp.broadcast_to(si, (n_exp,))
            elif c.experiment is None:
                updates[c.key] = jnp.broadcast_to(si, (n_exp,))
            else:
                cur = updates.get(c.key, p.get(c.key))
                updates[c.key] = jnp.asarray(cur).at[c.experiment].set(si)
        p = p.with_values(updates)
        for name, vals_si in structural.items():
            p = STRUCTURAL_CANDIDATES[name].set_strength(p, vals_si)
        return p

    def snapshots(self, u):
        res = jax.lax.map(lambda ps: wear_loop(ps[0], self.cfg, ps[1]),
                          (self.batched_params(u), self.schedule))
        return res.snapshots * 1e6, res


@eqx.filter_jit
def _evaluate_ext(ext: Extended, u):
    def g(v):
        snaps, res = ext.snapshots(v)
        return snaps, (snaps, jnp.max(res.max_residual), jnp.max(res.worn_through_cycle),
                       res.sliding_distance, jnp.max(res.error_estimate) * 1e6,
                       jnp.max(res.steps))

    J, (snaps, mres, worn, sliding, err, steps) = jax.jacfwd(g, has_aux=True)(u)
    return snaps, J, mres, worn, sliding, err, steps


@eqx.filter_jit
def _predict_ext(ext: Extended, u):
    """Snapshots [µm], worn-through cycle and error estimate [µm] at u, no Jacobian."""
    snaps, res = ext.snapshots(u)
    return snaps, jnp.max(res.worn_through_cycle), jnp.max(res.error_estimate) * 1e6


@dataclass(frozen=True)
class Eval:
    """Extended model at u: rows and prior rows in µm, their Jacobian w.r.t. u."""

    u: np.ndarray
    pred: np.ndarray  # (rows,)
    r: np.ndarray  # data residuals, model - measured (rows,)
    J: np.ndarray  # (rows, P)
    r_prior: np.ndarray  # (n_prior,)
    J_prior: np.ndarray  # (n_prior, P)
    snaps: np.ndarray  # (E, S, N)
    max_residual: float
    worn: float
    sliding_m: np.ndarray  # (E,) total sliding distance of each experiment [m]
    error_um: float = 0.0  # integration error estimate, largest experiment [µm] (0: eq 23)
    steps: int = 0  # accepted integration steps (updates), largest experiment
    J_snaps: np.ndarray | None = None  # d snapshots / d u (E, S, N, P) [µm]

    @property
    def usable(self) -> bool:
        return bool(np.all(np.isfinite(self.r)) and np.all(np.isfinite(self.J))
                    and self.worn < 0 and np.isfinite(self.error_um))


def candidate_names(cfg: ModelConfig) -> list[str]:
    """Candidates a study can be missing: registered effects it does not switch on, then
    the structural choices it does not make."""
    names = [n for n in registered_effects() if n not in cfg.effects]
    names += [n for n, c in STRUCTURAL_CANDIDATES.items() if c.applies(cfg)]
    return names


def _candidate_parameters(name):
    if name in STRUCTURAL_CANDIDATES:
        return STRUCTURAL_CANDIDATES[name].parameters
    return get_effect(name).parameters
