"""Derivative rules that change only how a gradient is computed (jaxmpm.transfer.backend, the structured
adjoint): each gives the values and derivatives, forward and reverse, of the same code differentiated
by JAX itself (``adjoint="autodiff"``), and the helpers
written for a cheaper transpose give the values of the expressions they replace (bit for bit; the fluid's
square root to one unit in the last place).

* ``scatter_planar`` of (C, K, N) columns: its tangent is one scalar scatter per component behind a stage
  boundary, so that in reverse mode each component of the nodal cotangent is gathered planar (K, N);
* ``to_particle_major``: its tangent is held planar, so that the cotangent of a G2P result is evaluated once
  before the per-slot products read it;
* ``isotropic`` (s I stacked) and the fluid's square root (J ** (1/2)).

Timings are in benchmarks/README.md ("Cotangents evaluated once where they are read").
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxmpm.core.linalg import det
from jaxmpm.materials.base import isotropic
from jaxmpm.materials.fluid import volumetric_part
from jaxmpm.transfer.backend import use_adjoint
from jaxmpm.transfer.kernels.xla import scatter_planar, to_particle_major

K, N, NODES = 9, 40, 25


def derivatives(fn, x, tangent, cotangent):
    """(value, JVP, VJP) of ``fn`` at ``x``, in one compiled program."""
    def both(x, tangent, cotangent):
        value, jvp = jax.jvp(fn, (x,), (tangent,))
        return value, jvp, jax.vjp(fn, x)[1](cotangent)[0]
    return jax.jit(both)(x, tangent, cotangent)


def assert_same(fn, x, out_shape, seed):
    """``fn``'s value, JVP and VJP under the structured rules equal those of JAX's own autodiff of it."""
    keys = jax.random.split(jax.random.PRNGKey(seed), 2)
    tangent = jax.random.normal(keys[0], x.shape, x.dtype)
    cotangent = jax.random.normal(keys[1], out_shape, x.dtype)
    with use_adjoint("structured"):
        ruled = derivatives(fn, x, tangent, cotangent)
    with use_adjoint("autodiff"):
        expected = derivatives(fn, x, tangent, cotangent)
    for got, want in zip(ruled, expected):
        np.testing.assert_allclose(got, want, rtol=1e-14, atol=1e-14)


@pytest.mark.parametrize("components", [None, 3])
def test_the_planar_scatter_rule_has_the_plain_derivatives(components):
    index = jax.random.randint(jax.random.PRNGKey(0), (K, N), 0, NODES)
    shape = (K, N) if components is None else (components, K, N)
    c = jax.random.normal(jax.random.PRNGKey(1), shape, jnp.float64)
    out_shape = (NODES,) if components is None else (NODES, components)
    assert_same(lambda c: scatter_planar(index, c, NODES), c, out_shape, seed=2)


@pytest.mark.parametrize("shape", [(2, N), (2, 2, N)])
def test_the_particle_major_rule_has_the_plain_derivatives(shape):
    planar = jax.random.normal(jax.random.PRNGKey(3), shape, jnp.float64)
    out_shape = (shape[-1],) + shape[:-1]
    assert_same(to_particle_major, planar, out_shape, seed=4)


@pytest.mark.parametrize("d", [1, 2, 3])
def test_isotropic_is_s_times_the_identity(d):
    s = jax.random.normal(jax.random.PRNGKey(d), (5, 7), jnp.float64)
    eye = jnp.eye(d, dtype=s.dtype)
    np.testing.assert_array_equal(isotropic(s, d), s[..., None, None] * eye[None, None])
    # its transpose: the cotangent of s is the trace of the matrix cotangent
    ct = jax.random.normal(jax.random.PRNGKey(10 + d), (5, 7, d, d), jnp.float64)
    np.testing.assert_allclose(jax.vjp(lambda s: isotropic(s, d), s)[1](ct)[0], jnp.trace(ct, axis1=-2, axis2=-1),
                               rtol=1e-14)  # the diagonal summed in another order


def test_the_fluids_square_root_is_the_power_it_replaced():
    """volumetric_part in 2D: sqrt(J) I, the values of J ** (1/2) I it replaced to the last bit or one unit in
    it (XLA's vectorised power is not always correctly rounded, the square root is); F itself where J <= 0."""
    F = jnp.eye(2)[None] + 0.3 * jax.random.normal(jax.random.PRNGKey(5), (4000, 2, 2), jnp.float64)

    def with_power(F):
        J = det(F)
        iso = (jnp.where(J > 0, J, 1.0) ** 0.5)[:, None, None] * jnp.eye(2)[None]
        return jnp.where((J > 0)[:, None, None], iso, F)

    got, expected = jax.jit(volumetric_part)(F), jax.jit(with_power)(F)
    assert bool(jnp.any(det(F) <= 0)) and bool(jnp.any(det(F) > 0))
    np.testing.assert_allclose(got, expected, rtol=2.3e-16, atol=0)
