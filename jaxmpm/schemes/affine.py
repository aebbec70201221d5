"""Affine transfers: APIC (002 eqs. 3-4) and TPIC (004, "Taylor PIC"); and the rigid transfer of
RPIC (002 §4, eqs. 1-2), which carries a per-particle angular momentum L_p (:class:`RPIC`).

Both carry one extra (D, D) matrix per particle in ``State.scheme_state`` and put an affine velocity
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

import jax.numpy as jnp

from ..transfer.backend import materialise
from ..core.measures import angular_momentum as _particle_angular_momentum
from ..core.errors import check
from ..core.registry import register_scheme
from .base import ParticleUpdate, Scheme
from ..transfer.shapes import StencilBase as Stencil
from ..transfer.shapes import rows
from ..core.state import with_scheme_state
from ..transfer.operators import Transfer, nodal_values, per_slot, sum_over_stencil, to_particle_major


# Per-particle (D, D) matrices are handled "planar" here, as (D, D, N) (see Stencil): every entry
# is a row of N numbers, so the small matrix algebra below is elementwise on contiguous vectors.
def to_planar(A):
    """(N, D, D) -> (D, D, N)."""
    return jnp.moveaxis(A, 0, -1)


def from_planar(A):
    """(D, D, N) -> (N, D, D)."""
    return to_particle_major(A)


def _stack2(rows):
    return jnp.stack([jnp.stack(r) for r in rows])


def _weighted_moment(w, a, b):
    """sum_k w_pk a_pk b_pk^T for planar a (D, K, N), b (D', K, N): (D, D', N)."""
    return _stack2([[sum_over_stencil(w * a[i] * b[j]) for j in range(len(b))] for i in range(len(a))])


def _planar_inverse(A):
    """Inverse of the planar (D, D, N) matrices (D = 1, 2, 3) by the adjugate, elementwise."""
    d = A.shape[0]
    if d == 1:
        return 1.0 / A
    if d == 2:
        det = A[0, 0] * A[1, 1] - A[0, 1] * A[1, 0]
        return _stack2([[A[1, 1], -A[0, 1]], [-A[1, 0], A[0, 0]]]) / det
    cof = [[A[(i + 1) % 3, (j + 1) % 3] * A[(i + 2) % 3, (j + 2) % 3]
            - A[(i + 1) % 3, (j + 2) % 3] * A[(i + 2) % 3, (j + 1) % 3] for j in range(3)] for i in range(3)]
    det = sum(A[0, j] * cof[0][j] for j in range(3))
    return _stack2([[cof[j][i] for j in range(3)] for i in range(3)]) / det  # adj(A) = cof^T


def _planar_matmul(A, B):
    """A @ B for planar (D, D, N) matrices."""
    d = A.shape[0]
    return _stack2([[sum(A[i, k] * B[k, j] for k in range(d)) for j in range(d)] for i in range(d)])


def _planar_matvec(A, x):
    """A_p x_pk for planar A (D, D, N) and slot vectors x (D, K, N): (D, K, N)."""
    d = A.shape[0]
    A, x = [rows(r) for r in rows(A)], rows(x)
    return jnp.stack([sum(A[i][j][None] * x[j] for j in range(d)) for i in range(d)])


def _inertia_planar(stencil: Stencil):
    return stencil.inertia()


def inertia_tensor(stencil: Stencil):
    """D_p = sum_i S_pi (x_i - X_p)(x_i - X_p)^T, shape (N, D, D)  (002 eq. 3)."""
    return from_planar(_inertia_planar(stencil))


def small_inverse(A):
    """Inverse of a batch (N, D, D) of 1x1, 2x2 or 3x3 matrices by the adjugate (elementwise; much
    faster on CPU than a batched LAPACK call)."""
    return from_planar(_planar_inverse(to_planar(A)))


def affine_weights(stencil: Stencil):
    """a_pi = S_pi D_p^-1 (x_i - X_p), planar (D, K, N): APIC's P2G weight of B_p (002 eq. 3).

    Multilinear stencils (2 nodes per axis) use the exact identity a_pi = G_pi, which has no
    0/0 when a particle sits on a grid line (see the module docstring)."""
    if stencil.nodes_per_axis == 2:
        return stencil.gradient
    return per_slot(stencil.weight, _planar_matvec(_planar_inverse(_inertia_planar(stencil)), stencil.offset))


def apic_node_velocity(stencil: Stencil, B):
    """c_pi = B_p D_p^-1 (x_i - X_p) S_pi, planar (D, K, N): the affine part of APIC's P2G (002 eq. 3)."""
    B = to_planar(B)
    if stencil.nodes_per_axis == 2:
        return _planar_matvec(B, stencil.gradient)  # S_pi D_p^-1 (x_i - X_p) = G_pi
    C = materialise(_planar_matmul(B, _planar_inverse(_inertia_planar(stencil))))  # B_p D_p^-1, once per particle
    return per_slot(stencil.weight, _planar_matvec(C, stencil.offset))


def taylor_node_velocity(stencil: Stencil, C):
    """c_pi = S_pi C_p (x_i - X_p), planar (D, K, N)."""
    return per_slot(stencil.weight, _planar_matvec(materialise(to_planar(C)), stencil.offset))


def affine_momentum_contributions(stencil: Stencil, mass, velocity, per_node_velocity):
    """M_p (S_pi V_p + c_pi) per slot, planar (D, K, N), with c_pi the affine part at node i."""
    return mass * (per_slot(stencil.weight, materialise(velocity.T)) + per_node_velocity)


def affine_velocity_moment(stencil: Stencil, v):
    """B_p = sum_i S_pi v_i (x_i - X_p)^T, shape (N, D, D)  (002 eq. 4)."""
    return from_planar(_weighted_moment(stencil.weight, nodal_values(stencil, v), stencil.offset))


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

    def initial_state(self, particles):
        """Zero affine matrices (a uniform start); see :func:`with_velocity_gradient`."""
        return _zero_affine(particles)

    uses_lumped_velocity = False  # the update reads v_tilde, and v only for grid damping

    def update(self, V, X, transfer: Transfer, constraint, grid, damping, dt):
        V_new = transfer.gather(grid.v_tilde)  # 002 eq. (4)
        if damping is not None:
            V_new = V_new - damping.acceleration(transfer.gather(grid.v), V) * dt  # 000 eq. (2.77)
        X_new = X + V_new * dt
        # 000 eq. (2.43) measures work against the lumped FLIP update; under APIC/TPIC part of the
        # motion lives in the affine field, which the particle kinetic energy does not carry, so
        # the budget would not close (measured: 0.877 on the bar): report "not computed" (NaN)
        diss = jnp.full((), jnp.nan, V.dtype)
        return ParticleUpdate(V_new, X_new, grid.v_tilde, diss)


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


def rigid_inertia(stencil: Stencil, mass):
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
    return from_planar(mass * (trace * eye - D))


def rigid_angular_velocity(K, L):
    """omega_p = K_p^{-1} L_p  (002 eq. 1), (N, R).  K_p is positive semi-definite; a zero diagonal
    entry (a particle on a grid line of the multilinear stencil, where every r_pj is parallel to
    that axis) has a zero row and column, and then L_p's component is 0 and omega's does not act
    (omega x r = 0): that entry is set to 1, which keeps the transfer exact there."""
    r = K.shape[-1]
    if r == 0:
        return L
    diag = jnp.diagonal(K, axis1=-2, axis2=-1)
    K = K + jnp.where(diag == 0.0, 1.0, 0.0)[..., None] * jnp.eye(r, dtype=K.dtype)
    if r == 1:
        return L / K[:, :, 0]
    return jnp.einsum("nab,nb->na", small_inverse(K), L)


def rigid_node_velocity(stencil: Stencil, omega):
    """c_pi = S_pi omega_p x (x_i - X_p), planar (D, K, N): the rigid part of RPIC's P2G (002 eq. 1)."""
    r, w = stencil.offset, stencil.weight
    d = r.shape[0]
    if d == 1:
        return jnp.zeros_like(r)
    om = materialise(omega.T)[:, None, :]  # (R, 1, N)
    if d == 2:
        return w * jnp.stack([-om[0] * r[1], om[0] * r[0]])
    return w * jnp.stack([om[1] * r[2] - om[2] * r[1], om[2] * r[0] - om[0] * r[2], om[0] * r[1] - om[1] * r[0]])


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

    def momentum_contributions(self, stencil: Stencil, state):
        """S_pi M_p (V_p + (K_p^{-1} L_p) x (x_i - X_p)), summed over p into p_i  (002 eq. 1)."""
        omega = rigid_angular_velocity(rigid_inertia(stencil, state.mass), state.scheme_state)
        return affine_momentum_contributions(stencil, state.mass, state.v, rigid_node_velocity(stencil, omega))

    def next_state(self, state, update, transfer: Transfer, grid):
        """L_p = sum_i S_pi (x_i - X_p) x M_p v~_i  (002 eq. 2)."""
        return transfer.particle_mass[:, None] * axial_vector(affine_velocity_moment(transfer.stencil, grid.v_tilde))

    def angular_momentum(self, state):
        """sum_p (X_p x M_p V_p + L_p)  (002 def. 4.1); (1,) in 1D (zero) and 2D, (3,) in 3D."""
        total = _particle_angular_momentum(state)
        if state.scheme_state.shape[-1] == 0:
            return total
        return total + jnp.sum(state.scheme_state, axis=0)


class APIC(_AffineScheme):
    """Affine Particle-in-Cell (Jiang et al., 002 eqs. 3-4); ``State.scheme_state`` holds B_p.

    Preserves affine grid velocity fields through G2P + P2G (002 prop. 5.1) and conserves linear
    and angular momentum in both transfers (002 props. 5.2-5.5), the particles' angular momentum
    being sum_p X_p x M_p V_p + sum_p M_p (B_p^T : eps) (002 def. 5.1).
    """

    def momentum_contributions(self, stencil: Stencil, state):
        """S_pi M_p (V_p + B_p D_p^-1 (x_i - X_p)), summed over p into p_i  (002 eq. 3)."""
        return affine_momentum_contributions(stencil, state.mass, state.v, apic_node_velocity(stencil, state.scheme_state))

    def next_state(self, state, update, transfer: Transfer, grid):
        """B_p = sum_i S_pi v~_i (x_i - X_p)^T  (002 eq. 4)."""
        return affine_velocity_moment(transfer.stencil, grid.v_tilde)

    def angular_momentum(self, state):
        """sum_p X_p x M_p V_p + sum_p M_p (B_p^T : eps)  (002 def. 5.1)."""
        return _particle_angular_momentum(state) + affine_angular_momentum(state.mass, state.scheme_state)


class TPIC(_AffineScheme):
    """Taylor Particle-in-Cell (Nakamura et al. 2023, as written in 004); ``State.scheme_state`` holds
    the particle velocity gradient grad v_p.

    p_i = sum_p S_pi M_p (V_p + grad v_p (x_i - X_p)),  V_p = sum_i S_pi v~_i,
    grad v_p = sum_i v~_i (x) G_pi.  (004's code snippet writes the G2P of grad v_p with
    S_pi (x_i - X_p), APIC's B_p; its formula, used here, has G_pi.)  It reproduces affine grid
    fields (the gradient of a linear field is exact) and conserves linear momentum; its angular
    momentum is not exactly conserved (sum_p M_p (grad v_p D_p)^T : eps changes in G2P), so
    :meth:`angular_momentum` reports the particles' sum_p X_p x M_p V_p only.
    """

    def momentum_contributions(self, stencil: Stencil, state):
        """S_pi M_p (V_p + grad v_p (x_i - X_p)), summed over p into p_i  (004)."""
        return affine_momentum_contributions(stencil, state.mass, state.v, taylor_node_velocity(stencil, state.scheme_state))

    def next_state(self, state, update, transfer: Transfer, grid):
        """grad v_p = sum_i v~_i (x) G_pi  (004)."""
        return transfer.velocity_gradient(grid.v_tilde)


def with_velocity_gradient(sim, state, gradient):
    """``state`` with the affine field set for a particle velocity field of gradient ``gradient``
    ((D, D) or (N, D, D)): B_p = L_p D_p under APIC (D_p from the stencil; 002 prop. 5.1 then
    starts from an exactly affine grid field), grad v_p = L_p under TPIC, and under RPIC
    L_p = K_p omega with omega the rotation of the skew part of L_p (the rigid part, 002 prop.
    4.1: L_p = K_p omega for a rigid field); unchanged otherwise."""
    if not isinstance(sim.scheme, (APIC, TPIC, RPIC)):
        return state
    d = state.x.shape[-1]  # the grid's dimension (F is 3x3 on an r-z grid; the affine state is d x d)
    L = jnp.asarray(gradient, state.x.dtype)
    check(L.shape[-2:] == (d, d), f"with_velocity_gradient: gradient has shape {L.shape}; give a ({d}, {d}) "
          f"matrix or one per particle ({state.x.shape[0]}, {d}, {d}), in the grid's coordinates")
    L = jnp.broadcast_to(L, (state.x.shape[0], d, d))
    if isinstance(sim.scheme, RPIC):  # omega x r = W r, W = (L - L^T)/2: omega_z = W_yx = (L_yx - L_xy)/2, ...
        omega = axial_vector(0.5 * L)
        K = rigid_inertia(sim.shape.stencil(sim.grid, state.x), state.mass)
        return with_scheme_state(state, jnp.einsum("nab,nb->na", K, omega))
    if isinstance(sim.scheme, TPIC):
        affine = L
    else:  # Linear too: B G_pi = L D_p G_pi = L S_pi (x_i - X_p)
        affine = L @ inertia_tensor(sim.shape.stencil(sim.grid, state.x))
    return with_scheme_state(state, affine)


def _without_beta(cls, name):
    def parse(arg, beta=None):
        check(beta is None, f"scheme {name!r}: {name} has no FLIP fraction; drop beta (--beta)")
        return cls()
    return parse


register_scheme("apic", APIC, parse=_without_beta(APIC, "apic"), spec="apic")
register_scheme("tpic", TPIC, parse=_without_beta(TPIC, "tpic"), spec="tpic")
register_scheme("rpic", RPIC, parse=_without_beta(RPIC, "rpic"), spec="rpic")
