"""Structural candidates: model choices that a study can leave out (design.md §5).

Unlike the effects of the registry, these change a static choice of the model rather than
add a term to the wear rate, so they are not `Effect`s: a study switches them on with
`contact = "unsymmetric"` / `double_layer = true` (or by listing them in `effects`), and
`diagnose` tries them on studies that do not.

- `unsymmetric`: a study with `contact = "symmetric"` treats the worn bore as a circle
  through the loaded node. The unsymmetric Winkler foundation (paper §2.1) sees the real
  worn shape. No parameter: it is tried by a refit with the same parameter count.
- `double_layer`: a single-layer study may be missing the compliance of what the wearing
  layer sits on (paper §4.1). Its strength is the backing's compliance per unit area,
  C_b = L_b / E_w,b, in µm of extra deflection per MPa of pressure; C_b = 0 is the single
  layer exactly (1/k = (L - h)/E_w + C_b, design.md §3).
"""

from __future__ import annotations

from dataclasses import dataclass

from jaxwear._physics.config import ModelConfig
from jaxwear._physics.contact import equivalent_modulus
from jaxwear._physics.effects.parameter import EffectParameter


@dataclass(frozen=True)
class StructuralCandidate:
    """A static model choice that diagnosis can switch on.

    `parameters`: strength parameters (same contract as an effect's, nested at `off`);
    `signature`: what it leaves in data; `doc`: the physics it adds.
    """

    name: str
    parameters: dict
    signature: str
    doc: str

    def applies(self, cfg: ModelConfig) -> bool:
        """True when the configuration does not already include it."""
        if self.name == "unsymmetric":
            return cfg.contact == "symmetric"
        return not cfg.double_layer

    def configure(self, cfg: ModelConfig) -> ModelConfig:
        """The configuration with this candidate switched on."""
        if self.name == "unsymmetric":
            return cfg.replace(contact="unsymmetric")
        return cfg.replace(double_layer=True)

    def set_strength(self, p, values_si: dict):
        """Params (possibly batched, traced) carrying the strength `values_si` [SI]."""
        if self.name != "double_layer":
            return p

        compliance = values_si["backing_compliance_um_per_MPa"]  # [m/Pa]
        # The backing's thickness that gives this compliance with the backing material the
        # study states (the Winkler series spring only sees L_b/E_w,b).
        return p.replace(backing_thickness=compliance * equivalent_modulus(
            p.backing_modulus, p.backing_poisson))


UNSYMMETRIC = StructuralCandidate(
    name="unsymmetric", parameters={},
    signature="a symmetric-contact study over-predicts the peak and under-predicts the spread "
              "of each wear zone; the worn zone does not widen with revolutions",
    doc="unsymmetric Winkler contact on the worn bore (paper §2.1): the pressure follows "
        "the real worn shape, so wear zones widen towards their flanks")

DOUBLE_LAYER = StructuralCandidate(
    name="double_layer",
    parameters={"backing_compliance_um_per_MPa": EffectParameter(
        1e-12, 0.0, 0.0, 0.0, 10.0,
        "C_b = L_b/E_w,b: compliance of a backing under the wearing layer [µm/MPa]",
        scale=0.1, realistic=1.0)},
    signature="wider, shallower wear zones than the layer's own stiffness gives, in every "
              "experiment; the same K_d",
    doc="series spring of a backing layer (paper §4.1): a softer foundation spreads the "
        "contact over a wider arc")

STRUCTURAL_CANDIDATES = {c.name: c for c in (UNSYMMETRIC, DOUBLE_LAYER)}
