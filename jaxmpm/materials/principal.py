"""Isotropic functions of a deformation gradient, evaluated on its singular values, with exact and
NaN-free derivatives.

A plastic return mapping in Hencky strain works on the singular values of the elastic deformation
gradient, F = U diag(sigma) V^T: the principal logarithmic strains are eps = ln sigma, the law maps
them to new ones, and F_new = U diag(exp(eps_new)) V^T (Klar et al. 2016, Stomakhin et al.
2013).  Such a map G(F) = U diag(g(sigma)) V^T is an isotropic matrix function; so is the
Kirchhoff stress, tau = U diag(t(sigma)) U^T = G(F) F^T with g_i = t_i / sigma_i.

Differentiating through a singular value decomposition breaks where singular values coincide
(autodiff's rule divides by sigma_i^2 - sigma_j^2), and they coincide at the very start of every run
(F = I) and in every state of equal principal stretches.  :func:`principal_map` therefore carries
its own derivative, the closed form of an isotropic function's derivative in the rotated frame
(dF^ = U^T dF V; Stomakhin et al. 2012 "Energetically consistent invertible elasticity"; Xu,
Sin, Zhu & Barbic 2015 "Nonlinear material design using principal stretches"):

    dG^_ii                   = sum_k dg_i/dsigma_k dF^_kk       (+ the parameters' part)
    (dG^_ij + dG^_ji) / 2    = (g_i - g_j) / (sigma_i - sigma_j) (dF^_ij + dF^_ji) / 2
    (dG^_ij - dG^_ji) / 2    = (g_i + g_j) / (sigma_i + sigma_j) (dF^_ij - dF^_ji) / 2

and where sigma_i and sigma_j (nearly) coincide the divided difference is replaced by its limit
dg_i/dsigma_i - dg_i/dsigma_j, which a permutation-symmetric g makes exact.  Nothing is clamped, so
the derivative is the true one at equal singular values as well (tested against central
differences at F = I and at repeated stretches).
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

from ..core.linalg import matmul


def svd(F):
    """(U, sigma, V) with F = U diag(sigma) V^T, sigma >= 0, for a batch (..., D, D).

    Written out for the small matrices of a deformation gradient, branch-free and vectorised over
    the particles (a library SVD runs one LAPACK call per particle on the CPU: measured 26x slower
    plastic steps on mpm88): 1D trivial; 2D and 3D by cyclic Jacobi rotations of F^T F (Golub & Van
    Loan 2013, the symmetric Schur rotation and cyclic Jacobi) with U = F V diag(1 / sigma).  Only
    values are computed here; derivatives are :func:`principal_map`'s.
    """
    D = F.shape[-1]
    if D == 1:
        sign = jnp.where(F[..., 0, 0] < 0, -1.0, 1.0).astype(F.dtype)[..., None, None]
        return sign, jnp.abs(F[..., 0, :]), jnp.ones_like(F)
    if D in (2, 3):
        return _jacobi_svd(F)
    U, sigma, Vt = jnp.linalg.svd(F)
    return U, sigma, jnp.swapaxes(Vt, -1, -2)


def _jacobi_svd(F):
    """Cyclic Jacobi on A = F^T F (each rotation zeroes one off-diagonal entry; in 2D one rotation
    diagonalises A, in 3D convergence is quadratic and four sweeps reach round-off: the same values as six), sigma =
    sqrt(eig A), U = F V / sigma.  Square roots and divisions only, no trigonometry, and written
    entry by entry (elementwise over the particles: no small-matrix products to lower)."""
    D = F.shape[-1]
    A = jnp.swapaxes(F, -1, -2) @ F
    a = {(i, j): A[..., i, j] for i in range(D) for j in range(i, D)}  # the upper triangle
    one, zero = jnp.ones_like(A[..., 0, 0]), jnp.zeros_like(A[..., 0, 0])
    v = {(i, j): one if i == j else zero for i in range(D) for j in range(D)}

    def entry(i, j):
        return a[(min(i, j), max(i, j))]

    for _ in range(1 if D == 2 else 4):
        for p, q in ((0, 1),) if D == 2 else ((0, 1), (0, 2), (1, 2)):
            apq, app, aqq = a[(p, q)], a[(p, p)], a[(q, q)]
            rotate = apq != 0
            tau = (aqq - app) / (2.0 * jnp.where(rotate, apq, 1.0))
            t = jnp.where(tau >= 0, 1.0, -1.0) / (jnp.abs(tau) + jnp.sqrt(1.0 + tau * tau))
            c = jnp.where(rotate, 1.0 / jnp.sqrt(1.0 + t * t), 1.0)
            s = jnp.where(rotate, t * c, 0.0)
            # A <- J^T A J, V <- V J with J = I but J_pp = J_qq = c, J_pq = s, J_qp = -s
            others = [(r, entry(r, p), entry(r, q)) for r in range(D) if r not in (p, q)]
            a[(p, p)] = c * c * app - 2.0 * c * s * apq + s * s * aqq
            a[(q, q)] = s * s * app + 2.0 * c * s * apq + c * c * aqq
            a[(p, q)] = zero
            for r, arp, arq in others:
                a[(min(r, p), max(r, p))] = c * arp - s * arq
                a[(min(r, q), max(r, q))] = s * arp + c * arq
            for r in range(D):
                vrp, vrq = v[(r, p)], v[(r, q)]
                v[(r, p)], v[(r, q)] = c * vrp - s * vrq, s * vrp + c * vrq
    sigma = jnp.sqrt(jnp.maximum(jnp.stack([a[(i, i)] for i in range(D)], -1), 0.0))
    V = jnp.stack([jnp.stack([v[(i, j)] for j in range(D)], -1) for i in range(D)], -2)
    U = (F @ V) / jnp.where(sigma > 0, sigma, 1.0)[..., None, :]
    return U, sigma, V


def _tolerance(dtype):
    """Relative gap below which two singular values count as equal: sqrt(eps), where the divided
    difference's round-off (eps |g| / gap) and the limit's truncation (gap |g''|) balance."""
    return math.sqrt(float(np.finfo(dtype).eps))


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def principal_map(fn, F, args):
    """G = U diag(g) V^T and ``aux``, where ``(g, aux) = fn(sigma, args)`` on the singular values of F.

    Args:
        fn: ``fn(sigma, args) -> (g, aux)``, elementwise over the leading (particle) axes: sigma
            (..., D) the singular values, g (..., D) the new values (or a tuple of such arrays:
            several isotropic functions of one decomposition), and ``aux`` any pytree of
            invariants (plastic strain, dissipation: functions of sigma and args only).  It must be
            symmetric under a permutation of the singular values (isotropy), and a static callable
            (a module-level function or an unbound method), not a closure over traced values.
        F: (..., D, D) deformation gradients.
        args: a pytree of arrays ``fn`` depends on (the material's parameters, the particle's
            plastic state); derivatives flow to them.

    Returns:
        (G (..., D, D), or a tuple of them where ``g`` is a tuple, and aux).
    """
    U, sigma, V = svd(F)
    g, aux = fn(sigma, args)
    if isinstance(g, tuple):
        return tuple(_compose(U, gk, V) for gk in g), aux
    return _compose(U, g, V), aux


def _compose(U, g, V):
    return matmul(U, g[..., :, None] * jnp.swapaxes(V, -1, -2))


@principal_map.defjvp
def _principal_map_jvp(fn, primals, tangents):
    F, args = primals
    dF, dargs = tangents
    U, sigma, V = svd(F)
    dF_hat = matmul(matmul(jnp.swapaxes(U, -1, -2), dF), V)
    d_sigma = jnp.diagonal(dF_hat, axis1=-2, axis2=-1)
    (g, aux), (dg, daux) = jax.jvp(fn, (sigma, args), (d_sigma, dargs))

    D = F.shape[-1]
    eye = jnp.eye(D, dtype=sigma.dtype)
    # the Jacobians dg_i/dsigma_k, one column per forward-mode pass (D <= 3): only where two
    # singular values coincide are they used
    columns = [jax.jvp(lambda s: fn(s, args)[0], (sigma,), (jnp.broadcast_to(eye[k], sigma.shape),))[1]
               for k in range(D)]
    s_i, s_j = sigma[..., :, None], sigma[..., None, :]
    gap = s_i - s_j
    equal = jnp.abs(gap) <= _tolerance(sigma.dtype) * (s_i + s_j)
    total = s_i + s_j
    sym = 0.5 * (dF_hat + jnp.swapaxes(dF_hat, -1, -2))
    skew = 0.5 * (dF_hat - jnp.swapaxes(dF_hat, -1, -2))
    diagonal = jnp.broadcast_to(eye, dF_hat.shape)

    def tangent(g, dg, jac):
        g_i, g_j = g[..., :, None], g[..., None, :]
        limit = jnp.diagonal(jac, axis1=-2, axis2=-1)[..., :, None] - jac  # dg_i/dsigma_i - dg_i/dsigma_j
        stretch = jnp.where(equal, limit, (g_i - g_j) / jnp.where(equal, 1.0, gap))
        spin = jnp.where(total > 0, (g_i + g_j) / jnp.where(total > 0, total, 1.0), 0.0)
        dG_hat = (1.0 - diagonal) * (stretch * sym + spin * skew) + dg[..., :, None] * diagonal
        return matmul(matmul(U, dG_hat), jnp.swapaxes(V, -1, -2))

    if isinstance(g, tuple):
        jacs = [jnp.stack([c[k] for c in columns], axis=-1) for k in range(len(g))]
        return ((tuple(_compose(U, gk, V) for gk in g), aux),
                (tuple(tangent(gk, dgk, jk) for gk, dgk, jk in zip(g, dg, jacs)), daux))
    return (_compose(U, g, V), aux), (tangent(g, dg, jnp.stack(columns, axis=-1)), daux)


def principal_stress(fn, F, args):
    """The symmetric isotropic tensor U diag(t) U^T of F = U diag(sigma) V^T, with ``(t, aux) =
    fn(sigma, args)`` (a Kirchhoff stress from principal stretches), and ``aux``.  Computed as
    G(F) F^T with G = U diag(t / sigma) V^T, so that :func:`principal_map`'s derivative serves it.
    ``fn`` follows :func:`principal_map`'s rules; sigma must be positive (J > 0)."""
    G, aux = _principal_stress_map(fn, F, args)
    return matmul(G, jnp.swapaxes(F, -1, -2)), aux


def _principal_stress_map(fn, F, args):
    return principal_map(_StressValues(fn), F, args)


class _StressValues:
    """g = t / sigma of a principal-stress function ``fn`` (hashable by ``fn``, so that the
    custom derivative sees one static callable per law)."""

    def __init__(self, fn):
        self.fn = fn

    def __call__(self, sigma, args):
        t, aux = self.fn(sigma, args)
        return t / sigma, aux

    def __eq__(self, other):
        return isinstance(other, _StressValues) and other.fn == self.fn

    def __hash__(self):
        return hash((_StressValues, self.fn))
