"""Affine transfers: APIC (002 eqs. 3-4) and TPIC (004, "Taylor PIC").

Both carry one extra (D, D) matrix per particle in ``State.affine`` and put an affine velocity
field around each particle on the grid:

* :class:`APIC`   p_i = sum_p S_pi M_p (V_p + B_p D_p^-1 (x_i - X_p))        002 eq. (3)
                  V_p = sum_i S_pi v~_i,  B_p = sum_i S_pi v~_i (x_i - X_p)^T  002 eq. (4)
* :class:`TPIC`   p_i = sum_p S_pi M_p (V_p + grad v_p (x_i - X_p))          004 "Taylor PIC"
                  V_p = sum_i S_pi v~_i,  grad v_p = sum_i v~_i (x) G_pi
* both            X_p += V_p dt

D_p = sum_i S_pi (x_i - X_p)(x_i - X_p)^T (002 eq. 3) is computed from the stencil.  For the
quadratic and cubic B-splines it equals h^2/4 I and h^2/3 I (``shape.inertia_factor()``) to
round-off; for uGIMP it depends on the position but stays positive definite (>= l_p h^2/2 per
axis).  For multilinear (``Linear``) shape functions D_p = diag(r_a (1 - r_a) h_a^2), with r_a the
particle's fractional cell position, is singular when a particle lies on a grid line; there the
identity S_pi D_p^-1 (x_i - X_p) = G_pi (exact for tensor-product tent functions: per axis
r (1 - r) h^2 N'(r)/h = N(r) (x_i - X_p)) is used instead, which is the same number away from grid
lines and finite on them (tests/test_affine.py checks the identity).

Grid and particle damping act on V exactly as in the other schemes,
V_p = S v~ - (alpha_g S v + alpha_p V^n) dt (000 eq. 2.77); B_p / grad v_p are not damped.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp

from ._diagnostics import angular_momentum as _particle_angular_momentum
from ._schemes import ParticleUpdate, Scheme
from ._shapes import Stencil
from ._transfer import Transfer, scatter_weighted, sum_over_stencil


def nodes_per_axis(stencil: Stencil) -> int:
    """K1 for a tensor-product stencil of K = K1^D nodes (static)."""
    k, d = stencil.weight.shape[1], stencil.offset.shape[-1]
    return int(round(k ** (1.0 / d)))


def _matvec(A, x):
    """A @ x over the trailing axes, unrolled over the (1-3 long) summed axis: on CPU this fuses
    into one elementwise kernel, where einsum/matmul of tiny matrices do not."""
    return sum(A[..., :, b] * x[..., b, None] for b in range(x.shape[-1]))


def _matmul(A, B):
    """A @ B for batches of tiny matrices, unrolled like :func:`_matvec`."""
    return sum(A[..., :, b, None] * B[..., None, b, :] for b in range(A.shape[-1]))


def _outer_sum(w, a, b):
    """sum_k w_pk a_pk b_pk^T, shape (N, D, D)."""
    wa = w[..., None] * a  # unrolled over the tiny (D, D) axes: fuses on CPU, a batched dot does not
    return jnp.stack([jnp.stack([sum_over_stencil(wa[..., i] * b[..., j]) for j in range(b.shape[-1])], -1)
                      for i in range(a.shape[-1])], -2)


def inertia_tensor(stencil: Stencil):
    """D_p = sum_i S_pi (x_i - X_p)(x_i - X_p)^T, shape (N, D, D)  (002 eq. 3)."""
    return _outer_sum(stencil.weight, stencil.offset, stencil.offset)


def small_inverse(A):
    """Inverse of a batch of 1x1, 2x2 or 3x3 matrices by the adjugate (elementwise; much faster on
    CPU than a batched LAPACK call)."""
    d = A.shape[-1]
    if d == 1:
        return 1.0 / A
    if d == 2:
        a, b, c, e = A[..., 0, 0], A[..., 0, 1], A[..., 1, 0], A[..., 1, 1]
        det = a * e - b * c
        return jnp.stack([jnp.stack([e, -b], -1), jnp.stack([-c, a], -1)], -2) / det[..., None, None]
    cof = jnp.stack([jnp.cross(A[..., 1, :], A[..., 2, :]), jnp.cross(A[..., 2, :], A[..., 0, :]),
                     jnp.cross(A[..., 0, :], A[..., 1, :])], -1)  # A^-1 = adj(A) / det, adj(A) = these columns
    det = jnp.sum(A[..., 0, :] * cof[..., :, 0], -1)
    return cof / det[..., None, None]


def affine_weights(stencil: Stencil):
    """a_pi = S_pi D_p^-1 (x_i - X_p), shape (N, K, D): APIC's P2G weight of B_p (002 eq. 3).

    Multilinear stencils (2 nodes per axis) use the exact identity a_pi = G_pi, which has no
    0/0 when a particle sits on a grid line (see the module docstring)."""
    if nodes_per_axis(stencil) == 2:
        return stencil.gradient
    d_inv = small_inverse(inertia_tensor(stencil))
    return stencil.weight[..., None] * _matvec(d_inv[:, None], stencil.offset)


def apic_node_velocity(stencil: Stencil, B):
    """c_pi = B_p D_p^-1 (x_i - X_p) S_pi, shape (N, K, D): the affine part of APIC's P2G (002 eq. 3)."""
    if nodes_per_axis(stencil) == 2:
        return _matvec(B[:, None], stencil.gradient)  # S_pi D_p^-1 (x_i - X_p) = G_pi
    C = _matmul(B, small_inverse(inertia_tensor(stencil)))  # B_p D_p^-1
    return taylor_node_velocity(stencil, C)


def taylor_node_velocity(stencil: Stencil, C):
    """c_pi = S_pi C_p (x_i - X_p), shape (N, K, D)."""
    return stencil.weight[..., None] * _matvec(C[:, None], stencil.offset)


def affine_momentum(transfer: Transfer, velocity, per_node_velocity):
    """p_i = sum_p M_p (S_pi V_p + c_pi), with c_pi (N, K, D) the affine part at node i."""
    st = transfer.stencil
    contrib = transfer.particle_mass[:, None, None] * (st.weight[..., None] * velocity[:, None, :] + per_node_velocity)
    return scatter_weighted(st, contrib, transfer.num_nodes)


def affine_velocity_moment(stencil: Stencil, v):
    """B_p = sum_i S_pi v_i (x_i - X_p)^T, shape (N, D, D)  (002 eq. 4)."""
    return _outer_sum(stencil.weight, v[stencil.index], stencil.offset)


def affine_angular_momentum(mass, B):
    """sum_p M_p (B_p^T : eps), the particles' affine angular momentum (002 def. 5.1), with
    (A : eps)_g = A_ab eps_abg, so (B^T : eps)_g = B_ba eps_abg.  (1,) in 2D, (3,) in 3D."""
    d = B.shape[-1]
    mB = mass[:, None, None] * B
    if d == 1:
        return jnp.zeros((1,), B.dtype)
    if d == 2:
        return jnp.sum(mB[:, 1, 0] - mB[:, 0, 1], keepdims=True)
    return jnp.stack([
        jnp.sum(mB[:, 2, 1] - mB[:, 1, 2]),
        jnp.sum(mB[:, 0, 2] - mB[:, 2, 0]),
        jnp.sum(mB[:, 1, 0] - mB[:, 0, 1]),
    ])


def _zero_affine(particles):
    x = jnp.asarray(particles.x)
    n, d = x.shape
    return jnp.zeros((n, d, d), x.dtype)


class _AffineScheme(Scheme):
    """Shared G2P of APIC and TPIC: V = S v~ - A_damp dt, X += V dt."""

    def initial_affine(self, particles):
        """Zero affine matrices (a uniform start); see :func:`with_velocity_gradient`."""
        return _zero_affine(particles)

    def update(self, V, X, transfer: Transfer, constraint, grid, damping, dt):
        Sv = transfer.gather(grid.v)
        V_new = transfer.gather(grid.v_tilde) - damping.acceleration(Sv, V) * dt  # 002 eq. (4), 000 eq. (2.77)
        X_new = X + V_new * dt
        # 000 eq. (2.43) measures work against the lumped FLIP update; under APIC/TPIC part of the
        # motion lives in the affine field, which the particle kinetic energy does not carry, so
        # the budget would not close (measured: 0.877 on the bar): report "not computed" (NaN)
        diss = jnp.full((), jnp.nan, V.dtype)
        return ParticleUpdate(V_new, X_new, grid.v_tilde, diss)


class APIC(_AffineScheme):
    """Affine Particle-in-Cell (Jiang et al., 002 eqs. 3-4); ``State.affine`` holds B_p.

    Preserves affine grid velocity fields through G2P + P2G (002 prop. 5.1) and conserves linear
    and angular momentum in both transfers (002 props. 5.2-5.5), the particles' angular momentum
    being sum_p X_p x M_p V_p + sum_p M_p (B_p^T : eps) (002 def. 5.1).
    """

    def momentum(self, transfer: Transfer, state):
        """p_i = sum_p S_pi M_p (V_p + B_p D_p^-1 (x_i - X_p))  (002 eq. 3)."""
        return affine_momentum(transfer, state.v, apic_node_velocity(transfer.stencil, state.affine))

    def particle_state(self, state, update, transfer: Transfer, grid):
        """B_p = sum_i S_pi v~_i (x_i - X_p)^T  (002 eq. 4)."""
        return affine_velocity_moment(transfer.stencil, grid.v_tilde)

    def angular_momentum(self, state):
        """sum_p X_p x M_p V_p + sum_p M_p (B_p^T : eps)  (002 def. 5.1)."""
        return _particle_angular_momentum(state) + affine_angular_momentum(state.mass, state.affine)


class TPIC(_AffineScheme):
    """Taylor Particle-in-Cell (Nakamura et al. 2023, as written in 004); ``State.affine`` holds
    the particle velocity gradient grad v_p.

    p_i = sum_p S_pi M_p (V_p + grad v_p (x_i - X_p)),  V_p = sum_i S_pi v~_i,
    grad v_p = sum_i v~_i (x) G_pi.  (004's code snippet writes the G2P of grad v_p with
    S_pi (x_i - X_p), APIC's B_p; its formula, used here, has G_pi.)  It reproduces affine grid
    fields (the gradient of a linear field is exact) and conserves linear momentum; its angular
    momentum is not exactly conserved (sum_p M_p (grad v_p D_p)^T : eps changes in G2P), so
    :meth:`angular_momentum` reports the particles' sum_p X_p x M_p V_p only.
    """

    def momentum(self, transfer: Transfer, state):
        """p_i = sum_p S_pi M_p (V_p + grad v_p (x_i - X_p))  (004)."""
        return affine_momentum(transfer, state.v, taylor_node_velocity(transfer.stencil, state.affine))

    def particle_state(self, state, update, transfer: Transfer, grid):
        """grad v_p = sum_i v~_i (x) G_pi  (004)."""
        return transfer.velocity_gradient(grid.v_tilde)


def with_velocity_gradient(sim, state, gradient):
    """``state`` with the affine field set for a particle velocity field of gradient ``gradient``
    ((D, D) or (N, D, D)): B_p = L_p D_p under APIC (D_p from the stencil; 002 prop. 5.1 then
    starts from an exactly affine grid field), grad v_p = L_p under TPIC; unchanged otherwise."""
    if not isinstance(sim.scheme, (APIC, TPIC)):
        return state
    L = jnp.broadcast_to(jnp.asarray(gradient, state.x.dtype), state.F.shape)
    if isinstance(sim.scheme, TPIC):
        affine = L
    else:  # Linear too: B G_pi = L D_p G_pi = L S_pi (x_i - X_p)
        affine = L @ inertia_tensor(sim.shape.stencil(sim.grid, state.x))
    return eqx.tree_at(lambda s: s.affine, state, affine, is_leaf=lambda x: x is None)
