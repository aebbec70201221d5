"""jaxmpm.core.linalg.det: the closed-form determinant of F_p (1x1 to 3x3) every model uses.  Its values are
jnp.linalg.det's; its derivative is the cofactor matrix det(A) A^-T, differentiated term by term -- no LU
factorisation in the gradient program (on a GPU, jax 0.11's jnp.linalg.det derivative launched batched cuBLAS
getrf/trsm kernels: a third of a gradient's kernel time, benchmarks/gpu_profile.py --gradient)."""

import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxmpm.core.linalg import det, matmul


@pytest.mark.parametrize("d", [1, 2, 3, 4])
def test_values_and_cofactor_gradient(d):
    a = jax.random.normal(jax.random.PRNGKey(d), (7, d, d), jnp.float64) + 2.0 * jnp.eye(d)[None]
    np.testing.assert_allclose(det(a), jnp.linalg.det(a), rtol=1e-13)
    if d in (2, 3):  # the same products in the same order as jnp.linalg.det's closed forms
        np.testing.assert_array_equal(det(a), jnp.linalg.det(a))
    cofactor = jax.vmap(jax.grad(det))(a)
    expected = det(a)[:, None, None] * jnp.swapaxes(jnp.linalg.inv(a), -1, -2)  # d det A / dA = det(A) A^-T
    np.testing.assert_allclose(cofactor, expected, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("d", [2, 3])
def test_the_gradient_program_has_no_factorisation(d):
    a = jnp.eye(d) + 0.1
    program = str(jax.make_jaxpr(jax.grad(lambda a: jnp.sum(det(a) ** 2)))(a))
    assert not re.search(r"\b(lu|triangular_solve|lu_pivots_to_permutation)\[", program)


@pytest.mark.parametrize("d", [1, 2, 3, 4])
def test_small_matmul_is_the_matrix_product(d):
    """matmul(A, B) = A @ B for stacks of D x D matrices (F <- dF F), values and both gradients to round-off in
    float64, and no batched dot in the compiled program for D <= 3 (a loop fusion on every core); D = 4 is @."""
    key_a, key_b = jax.random.split(jax.random.key(d))
    a = jax.random.normal(key_a, (7, d, d), jnp.float64)
    b = jax.random.normal(key_b, (7, d, d), jnp.float64)
    np.testing.assert_allclose(matmul(a, b), a @ b, rtol=1e-14, atol=1e-15)
    weights = jnp.arange(d * d, dtype=jnp.float64).reshape(1, d, d)
    got = jax.grad(lambda a, b: jnp.sum(weights * jnp.sin(matmul(a, b))), argnums=(0, 1))(a, b)
    want = jax.grad(lambda a, b: jnp.sum(weights * jnp.sin(a @ b)), argnums=(0, 1))(a, b)
    for g, w in zip(got, want):
        np.testing.assert_allclose(g, w, rtol=1e-13, atol=1e-14)
    hlo = jax.jit(matmul).lower(a, b).compile().as_text()
    assert ("dot(" in hlo) == (d > 3), d
    with pytest.raises(TypeError):  # mismatched inner dimensions: @'s error, not a silent broadcast
        matmul(a, b[..., :1, :] if d > 1 else jnp.ones((7, 2, 2)))
