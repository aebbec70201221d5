"""Reverse-mode gradients through whole rollouts, against central finite differences in float64
(docs/design.md "Verification standards").  The XPIC(m)/FMPM(k) series are fixed-length fori_loops,
so these gradients pass through them."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from cases import central_difference

import jaxmpm as jm

STEPS = 50


def noisy_bar(scheme):
    """The bar with particle-scale noise (20% of v0) on its first-mode velocities: the null-space
    component that beta keeps or removes, so d/d beta is a first-order effect (on the smooth mode
    alone it is ~6e-7 of the loss, below what finite differences resolve to 1e-6)."""
    setup = jm.scene("bar", scheme=scheme)
    noise = 0.02 * np.random.default_rng(0).standard_normal(setup.state.v.shape)
    return setup, eqx.tree_at(lambda s: s.v, setup.state, setup.state.v + noise)


def final_kinetic_energy(scheme, where):
    setup, state = noisy_bar(scheme)

    @jax.jit
    def loss(value):
        sim = eqx.tree_at(where, setup.sim, value)
        final, _ = sim.run(state, setup.dt, STEPS, STEPS)
        return jm.kinetic_energy(final)

    return loss


@pytest.mark.parametrize(
    "scheme, where, x0",
    [
        (jm.XPIC(order=3, beta=0.3), lambda s: s.scheme.beta, 0.3),
        (jm.FMPM(order=3), lambda s: s.damping.grid, 0.1),
        (jm.FMPM(order=2, beta=0.2), lambda s: s.scheme.beta, 0.2),
        (jm.XPIC(order=2), lambda s: s.damping.particle, 0.05),
    ],
    ids=["xpic3-beta", "fmpm3-alpha_g", "fmpm2-beta", "xpic2-alpha_p"],
)
def test_gradient_matches_finite_differences(scheme, where, x0):
    loss = final_kinetic_energy(scheme, where)
    x = jnp.asarray(x0)
    grad = jax.grad(loss)(x)
    # five points x, x +- 5e-5, x +- 1e-4: the O(eps^2) truncation term of the plain central
    # difference is gone (one Richardson step)
    fd = central_difference(loss, x, 5e-5, order=4)
    assert jnp.isfinite(grad)
    assert abs(grad - fd) <= 1e-6 * abs(fd), (grad, fd)
