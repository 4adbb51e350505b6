"""The packing of u: the traced values (`Packing.values`, elementwise over the columns)
against the host's (`Packing.values_np`), with a product pair (a strength per another
column: `effects.product_pairs`) and log and linear columns."""

import jax
import jax.numpy as jnp
import numpy as np

import jaxwear as jw
from jaxwear._analyses.diagnose import Model

SMALL = dict(nodes=48, steps_per_rev=48, revolutions_per_update=500)


def test_traced_values_match_the_hosts_with_a_product_pair():
    res = jw.synthesize([], "paper", noise_um=0.3, seed=2, numerics=SMALL)
    m = Model(res.study)  # every candidate: running-in's amplitude is per its distance
    pk = m.packing
    assert pk._pairs(), "the extended model has a product pair"
    logs = {c.log for c in pk.columns}
    assert logs == {True, False}
    u = np.random.default_rng(3).normal(0.0, 0.3, pk.size)
    got = np.asarray(jax.jit(pk.values)(jnp.asarray(u)))
    np.testing.assert_allclose(got, pk.values_np(u), rtol=2e-16 * 8, atol=0.0)
    # and its derivative: the host's d values / d u (`value_jacobian`, pair included)
    J = np.asarray(jax.jacfwd(pk.values)(jnp.asarray(u)))
    np.testing.assert_allclose(J, pk.value_jacobian(u), rtol=1e-14, atol=1e-300)
