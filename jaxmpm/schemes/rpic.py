"""RPIC, the rigid Particle-in-Cell transfer (Jiang et al., 002 §4, eqs. 1-2): a per-particle
angular momentum L_p carried beside V_p, a rigid velocity field V_p + omega_p x (x_i - X_p) around
each particle on the grid.
"""

from __future__ import annotations

import jax.numpy as jnp

from ..core.measures import angular_momentum as _particle_angular_momentum
from ..core.registry import register_scheme
from ..transfer.contractions import Affine, Weighted
from ..transfer.operators import Transfer
from .affine import _AffineScheme, _inertia_planar, _without_beta, from_planar, small_inverse


# ------------------------------------------------------------------------------------ RPIC (002 §4)
def rotation_components(dim: int) -> int:
    """Components of an angular velocity / angular momentum: 0 in 1D, 1 (z) in 2D, 3 in 3D."""
    return dim * (dim - 1) // 2


def axial_vector(A):
    """(A^T : eps) per particle for (N, D, D) matrices A: (N, R).  For A = sum_i S_pi v_i r_pi^T
    this is sum_i S_pi r_pi x v_i (002 §5.3: u x v = (v u^T)^T : eps); 2D keeps the z component."""
    d = A.shape[-1]
    if d == 1:
        return A[:, :0, 0]
    if d == 2:
        return (A[:, 1, 0] - A[:, 0, 1])[:, None]
    return jnp.stack([A[:, 2, 1] - A[:, 1, 2], A[:, 0, 2] - A[:, 2, 0], A[:, 1, 0] - A[:, 0, 1]], axis=-1)


def rigid_inertia(stencil, mass):
    """K_p = sum_j S_pj M_p r_pj^* r_pj^{*T}, r_pj = x_j - X_p  (002 eq. 1), (N, R, R).

    With r^* r^{*T} = |r|^2 I - r r^T this is M_p (tr D_p I - D_p), D_p = sum_j S_pj r_pj r_pj^T
    (002 eq. 3); in 2D its z-z entry M_p tr D_p."""
    D = _inertia_planar(stencil)  # (D, D, N)
    d = D.shape[0]
    if d == 1:
        return jnp.zeros((mass.shape[0], 0, 0), mass.dtype)
    trace = sum(D[a, a] for a in range(d))
    if d == 2:
        return (mass * trace)[:, None, None]
    eye = jnp.eye(3, dtype=D.dtype)[:, :, None]
    return from_planar(mass[None, None] * (trace[None, None] * eye - D))


def rigid_angular_velocity(K, L):
    """omega_p = K_p^{-1} L_p  (002 eq. 1), (N, R).  K_p is positive semi-definite; a zero diagonal
    entry (a particle on a grid line of the multilinear stencil, where every r_pj is parallel to
    that axis) has a zero row and column, and then L_p's component is 0 and omega's does not act
    (omega x r = 0): that entry is set to 1, which keeps the transfer exact there."""
    r = K.shape[-1]
    if r == 0:
        return L
    diag = jnp.diagonal(K, axis1=-2, axis2=-1)
    K = K + jnp.where(diag == 0.0, 1.0, 0.0)[..., None] * jnp.eye(r, dtype=K.dtype)[None]
    if r == 1:
        return L / K[:, :, 0]
    return jnp.einsum("nab,nb->na", small_inverse(K), L)


def skew(omega, dim: int):
    """W with W r = omega x r, (N, D, D): 0 in 1D, [[0, -w], [w, 0]] in 2D (omega = w e_z), the
    cross-product matrix in 3D."""
    n = omega.shape[0]
    if dim == 1:
        return jnp.zeros((n, 1, 1), omega.dtype)
    if dim == 2:
        w, z = omega[:, 0], jnp.zeros_like(omega[:, 0])
        return jnp.stack([jnp.stack([z, -w], -1), jnp.stack([w, z], -1)], -2)
    w0, w1, w2 = omega[:, 0], omega[:, 1], omega[:, 2]
    z = jnp.zeros_like(w0)
    return jnp.stack([jnp.stack([z, -w2, w1], -1), jnp.stack([w2, z, -w0], -1), jnp.stack([-w1, w0, z], -1)], -2)


class RPIC(_AffineScheme):
    """Rigid Particle-in-Cell (Jiang et al., 002 §4, eqs. 1-2); ``State.scheme_state`` holds the
    particles' angular momenta L_p, (N, R): R = 1 (z) in 2D, 3 in 3D, 0 in 1D (there RPIC is PIC
    with X += V dt, 000 eqs. 2.64-2.65).

        K_p = sum_j S_pj M_p r_pj^* r_pj^{*T},  r_pj = x_j - X_p                         002 eq. (1)
        m_i v_i = sum_p S_pi M_p (V_p + (K_p^{-1} L_p) x (x_i - X_p))                   002 eq. (1)
        V_p = sum_i S_pi v~_i,  L_p = sum_i S_pi (x_i - X_p) x M_p v~_i                 002 eq. (2)
        X_p += V_p dt                       (the position update of 002's proof of prop. 4.5)

    Preserves rigid grid velocity fields v + omega x x through G2P + P2G (002 prop. 4.1) and
    conserves linear and angular momentum in both transfers (002 props. 4.2-4.5), the particles'
    angular momentum being sum_p (X_p x M_p V_p + L_p) (002 def. 4.1).  Damping acts on V_p as
    in APIC (000 eq. 2.77); L_p is not damped.  (002 states RPIC in 3D; in 2D only the z
    component of L and omega exists, the same formulas with r^* acting on (x, y, 0).)
    """

    def initial_state(self, particles):
        """Zero angular momenta (N, R); see :func:`with_velocity_gradient` for a spinning start."""
        x = jnp.asarray(particles.x)
        return jnp.zeros((x.shape[0], rotation_components(x.shape[1])), x.dtype)

    def momentum_contributions(self, stencil, state):
        """S_pi M_p (V_p + (K_p^{-1} L_p) x (x_i - X_p)), summed over p into p_i  (002 eq. 1):
        omega x r = W r with W the skew matrix of omega."""
        omega = rigid_angular_velocity(rigid_inertia(stencil, state.mass), state.scheme_state)
        return (Weighted(state.mass[:, None] * state.v),
                Affine(state.mass[:, None, None] * skew(omega, state.x.shape[-1])))

    def next_state(self, state, update, transfer: Transfer, grid):
        """L_p = sum_i S_pi (x_i - X_p) x M_p v~_i  (002 eq. 2)."""
        return transfer.particle_mass[:, None] * axial_vector(transfer.affine_moment(grid.v_tilde))

    def state_for_velocity_gradient(self, stencil, state, L):
        """L_p = K_p omega, omega the rotation of the skew part W = (L - L^T)/2 of L (omega x r = W r:
        omega_z = W_yx = (L_yx - L_xy)/2, ...); the rigid part of the field (002 prop. 4.1)."""
        omega = axial_vector(0.5 * L)
        return jnp.einsum("nab,nb->na", rigid_inertia(stencil, state.mass), omega)

    def angular_momentum(self, state):
        """sum_p (X_p x M_p V_p + L_p)  (002 def. 4.1); (1,) in 1D (zero) and 2D, (3,) in 3D."""
        total = _particle_angular_momentum(state)
        if state.scheme_state.shape[-1] == 0:
            return total
        return total + jnp.sum(state.scheme_state, axis=0)


register_scheme("rpic", RPIC, parse=_without_beta(RPIC, "rpic"), spec="rpic")
