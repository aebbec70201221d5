"""Determinants of the small matrices MPM carries (F_p, dF_p: 1x1 to 3x3), in closed form; and the
stack of identities a state starts from.

``jnp.linalg.det`` evaluates 2x2 and 3x3 determinants by these same products, but since jax 0.11 its
derivative solves with an LU factorisation (``_cofactor_solve``): on a GPU a batched cuBLAS getrf and two
triangular solves per use, with their pointer set-up kernels and copies -- a third of the GPU kernel time of
a gradient through mpm88 at 8k particles on an H100 (benchmarks/gpu_profile.py --gradient).  The
polynomial below is differentiated by JAX term by term, exact and elementwise.  Its values are
``jnp.linalg.det``'s to the bit for D = 2 and 3 (the same products, in the same order); rows and
columns of an axisymmetric F (3x3 in r, z, theta) are no different.
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp


@partial(jax.jit, static_argnums=(0, 1, 2))
def identities(n: int, d: int, dtype):
    """n identity matrices d x d (an initial F or Fe), as one program: ``jnp.eye`` and its broadcast, run
    eagerly, compiled seven small programs in a new process (``jnp.dtype(dtype)``: a hashable dtype)."""
    return jnp.broadcast_to(jnp.eye(d, dtype=dtype), (n, d, d))


def det(a):
    """det A of a stack of 1x1, 2x2 or 3x3 matrices (..., D, D) -> (...), by cofactor expansion;
    larger matrices go to ``jnp.linalg.det``."""
    d = a.shape[-1]
    if d > 3:
        return jnp.linalg.det(a)
    a = [jnp.unstack(row, axis=-1) for row in jnp.unstack(a, axis=-2)]  # a[i][j]: one unstack per axis
    if d == 1:
        return a[0][0]
    if d == 2:
        return a[0][0] * a[1][1] - a[0][1] * a[1][0]
    return (a[0][0] * a[1][1] * a[2][2] + a[0][1] * a[1][2] * a[2][0]
            + a[0][2] * a[1][0] * a[2][1] - a[0][2] * a[1][1] * a[2][0]
            - a[0][0] * a[1][2] * a[2][1] - a[0][1] * a[1][0] * a[2][2])


def matmul(a, b):
    """A B of two stacks of small matrices (..., D, D) @ (..., D, E), D <= 3, as sums of elementwise products
    (k = 0, 1, ... in order); larger matrices go to ``@``.  XLA:CPU runs a batched ``@`` of 2x2 or 3x3 matrices
    as a batched dot on one thread (F <- dF F over 131k particles in float64: 36 us a call of 16k particles),
    where this is a loop fusion that runs on every core and may fuse with the matrices' producers.  Not for a
    product whose entries feed a long elementwise chain: XLA may then fuse the product into each of its uses
    (the Jacobi SVD of jaxmpm.materials.principal keeps ``@``; elementwise, the 3x3 Taylor bar ran 2.5x slower)."""
    d = a.shape[-1]
    if d > 3 or a.ndim < 2 or b.ndim < 2 or b.shape[-2] != d:  # @ itself (or its error for mismatched shapes)
        return a @ b
    out = a[..., :, 0, None] * b[..., None, 0, :]
    for k in range(1, d):
        out = out + a[..., :, k, None] * b[..., None, k, :]
    return out
