"""Affine transfers: APIC (002 eqs. 3-4) and TPIC (004, "Taylor PIC"); the rigid transfer of RPIC
(002 §4) is :mod:`jaxmpm.schemes.rpic`.

Both carry one extra (D, D) matrix per particle in ``State.scheme_state`` and put an affine velocity
field around each particle on the grid:

* :class:`APIC`   p_i = sum_p S_pi M_p (V_p + B_p D_p^-1 (x_i - X_p))        002 eq. (3)
                  V_p = sum_i S_pi v~_i,  B_p = sum_i S_pi v~_i (x_i - X_p)^T  002 eq. (4)
* :class:`TPIC`   p_i = sum_p S_pi M_p (V_p + grad v_p (x_i - X_p))          004 "Taylor PIC"
                  V_p = sum_i S_pi v~_i,  grad v_p = sum_i v~_i (x) G_pi
* both            X_p += V_p dt

D_p = sum_i S_pi (x_i - X_p)(x_i - X_p)^T (002 eq. 3).  For the quadratic and cubic B-splines it is
h^2/4 I and h^2/3 I at every position (``shape.inertia_factor()``; the sum equals it to round-off), and
the stencil carries that constant (``TensorStencil.inertia_diagonal``): B_p D_p^-1 divides B_p's columns
by c h_a^2, with no sums, no inverse and nothing to differentiate.  For uGIMP it is summed from the
stencil: it depends on the position but stays positive definite (>= l_p h^2/2 per axis).  For
multilinear (``Linear``) shape functions D_p = diag(r_a (1 - r_a) h_a^2), with r_a the particle's
fractional cell position, is singular when a particle lies on a grid line; there the identity
S_pi D_p^-1 (x_i - X_p) = G_pi (exact for tensor-product tent functions: per axis
r (1 - r) h^2 N'(r)/h = N(r) (x_i - X_p)) is used instead, which is the same number away from grid
lines and finite on them (tests/test_affine.py checks the identity).

Grid and particle damping act on V exactly as in the other schemes,
V_p = S v~ - (alpha_g S v + alpha_p V^n) dt (000 eq. 2.77); B_p / grad v_p are not damped.
"""

from __future__ import annotations

import jax.numpy as jnp

from ..core.errors import check
from ..core.measures import angular_momentum as _particle_angular_momentum
from ..core.registry import register_scheme
from ..transfer.backend import materialise
from ..transfer.contractions import Affine, Divergence, Weighted
from ..transfer.kernels.xla import per_slot
from ..transfer.operators import Transfer, to_particle_major
from ..transfer.shapes import rows
from .base import ParticleDamping, ParticleUpdate, Scheme

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


def _planar_inverse(A):
    """Inverse of the planar (D, D, N) matrices (D = 1, 2, 3) by the adjugate, elementwise."""
    d = A.shape[0]
    if d == 1:
        return 1.0 / A
    A = [rows(r) for r in rows(A)]  # A[i][j]: the (N,) rows, taken as one unstack per axis
    if d == 2:
        det = A[0][0] * A[1][1] - A[0][1] * A[1][0]
        return _stack2([[A[1][1], -A[0][1]], [-A[1][0], A[0][0]]]) / det[None, None]
    cof = [[A[(i + 1) % 3][(j + 1) % 3] * A[(i + 2) % 3][(j + 2) % 3]
            - A[(i + 1) % 3][(j + 2) % 3] * A[(i + 2) % 3][(j + 1) % 3] for j in range(3)] for i in range(3)]
    det = sum(A[0][j] * cof[0][j] for j in range(3))
    return _stack2([[cof[j][i] for j in range(3)] for i in range(3)]) / det[None, None]  # adj(A) = cof^T


def _planar_matmul(A, B):
    """A @ B for planar (D, D, N) matrices."""
    d = A.shape[0]
    A, B = [rows(r) for r in rows(A)], [rows(r) for r in rows(B)]
    return _stack2([[sum(A[i][k] * B[k][j] for k in range(d)) for j in range(d)] for i in range(d)])


def _planar_matvec(A, x):
    """A_p x_pk for planar A (D, D, N) and slot vectors x (D, K, N): (D, K, N)."""
    d = A.shape[0]
    A, x = [rows(r) for r in rows(A)], rows(x)
    return jnp.stack([sum(A[i][j][None] * x[j] for j in range(d)) for i in range(d)])


def _inertia_planar(stencil):
    return stencil.inertia()


def _inertia_diagonal(stencil):
    """(c h_a^2 per axis) where the stencil's D_p is that constant at every position (the B-splines, 002 eq. 3:
    ``TensorStencil.inertia_diagonal``), else None."""
    return getattr(stencil, "inertia_diagonal", None)


def inertia_tensor(stencil):
    """D_p = sum_i S_pi (x_i - X_p)(x_i - X_p)^T, shape (N, D, D)  (002 eq. 3)."""
    return from_planar(_inertia_planar(stencil))


def small_inverse(A):
    """Inverse of a batch (N, D, D) of 1x1, 2x2 or 3x3 matrices by the adjugate (elementwise; much
    faster on CPU than a batched LAPACK call)."""
    return from_planar(_planar_inverse(to_planar(A)))


def affine_weights(stencil):
    """a_pi = S_pi D_p^-1 (x_i - X_p), planar (D, K, N): APIC's P2G weight of B_p (002 eq. 3).

    Multilinear stencils (2 nodes per axis) use the exact identity a_pi = G_pi, which has no
    0/0 when a particle sits on a grid line (see the module docstring)."""
    if stencil.nodes_per_axis == 2:
        return stencil.gradient
    diagonal = _inertia_diagonal(stencil)
    if diagonal is not None:  # D_p^-1 (x_i - X_p) = (x_i - X_p)_a / (c h_a^2)
        return per_slot(stencil.weight, stencil.offset / jnp.asarray(diagonal, stencil.dtype)[:, None, None])
    return per_slot(stencil.weight, _planar_matvec(_planar_inverse(_inertia_planar(stencil)), stencil.offset))


def apic_affine_part(stencil, mass, B):
    """The affine part of APIC's P2G (002 eq. 3), sum_p S_pi M_p B_p D_p^-1 (x_i - X_p), as a
    contraction: ``Affine(M B D^-1)``, D^-1 per particle; for multilinear stencils
    ``Divergence(M B)`` by the identity S_pi D_p^-1 (x_i - X_p) = G_pi (module docstring)."""
    if stencil.nodes_per_axis == 2:
        return Divergence(mass[:, None, None] * B)
    diagonal = _inertia_diagonal(stencil)
    if diagonal is not None:  # B-splines: D_p = diag(c h_a^2), so B_p D_p^-1 divides B_p's columns
        C = materialise(to_planar(B) / jnp.asarray(diagonal, B.dtype)[None, :, None])
    else:
        C = materialise(_planar_matmul(to_planar(B), _planar_inverse(_inertia_planar(stencil))))  # B_p D_p^-1, once
    return Affine(from_planar(mass[None, None, :] * C))  # M_p B_p D_p^-1, formed planar


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
    """Shared G2P of APIC, TPIC and RPIC: V = S v~ - A_damp dt, X += V dt."""

    def initial_state(self, particles):
        """Zero affine matrices (a uniform start); see :func:`with_velocity_gradient`."""
        return _zero_affine(particles)

    uses_lumped_velocity = False  # the update reads v_tilde, and v only for grid damping
    local_update = True  # gathers of v_tilde (and v) and one affine moment per particle

    def update(self, V, X, transfer: Transfer, constraint, grid, damping: ParticleDamping, dt):
        V_new = transfer.gather(grid.v_tilde)  # 002 eq. (4)
        if damping.acts:
            Sv = transfer.gather(grid.v) if damping.reads_grid_velocity else None
            V_new = V_new - damping.acceleration(Sv, V) * dt  # 000 eq. (2.77)
        X_new = X + V_new * dt
        # 000 eq. (2.43) measures work against the lumped FLIP update; under APIC/TPIC part of the
        # motion lives in the affine field, which the particle kinetic energy does not carry, so
        # the budget would not close (measured: 0.877 on the bar): report "not computed" (NaN)
        diss = jnp.full((), jnp.nan, V.dtype)
        return ParticleUpdate(V_new, X_new, grid.v_tilde, diss)


class APIC(_AffineScheme):
    """Affine Particle-in-Cell (Jiang et al., 002 eqs. 3-4); ``State.scheme_state`` holds B_p.

    Preserves affine grid velocity fields through G2P + P2G (002 prop. 5.1) and conserves linear
    and angular momentum in both transfers (002 props. 5.2-5.5), the particles' angular momentum
    being sum_p X_p x M_p V_p + sum_p M_p (B_p^T : eps) (002 def. 5.1).
    """

    def momentum_contributions(self, stencil, state):
        """S_pi M_p (V_p + B_p D_p^-1 (x_i - X_p)), summed over p into p_i  (002 eq. 3)."""
        return (Weighted(state.mass[:, None] * state.v), apic_affine_part(stencil, state.mass, state.scheme_state))

    def next_state(self, state, update, transfer: Transfer, grid):
        """B_p = sum_i S_pi v~_i (x_i - X_p)^T  (002 eq. 4)."""
        return transfer.affine_moment(grid.v_tilde)

    def state_for_velocity_gradient(self, stencil, state, L):
        """B_p = L_p D_p (002 prop. 5.1 then starts from an exactly affine grid field; Linear too:
        B G_pi = L D_p G_pi = L S_pi (x_i - X_p))."""
        return L @ inertia_tensor(stencil)

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

    def momentum_contributions(self, stencil, state):
        """S_pi M_p (V_p + grad v_p (x_i - X_p)), summed over p into p_i  (004)."""
        return (Weighted(state.mass[:, None] * state.v), Affine(state.mass[:, None, None] * state.scheme_state))

    def next_state(self, state, update, transfer: Transfer, grid):
        """grad v_p = sum_i v~_i (x) G_pi  (004)."""
        return transfer.velocity_gradient(grid.v_tilde)

    def state_for_velocity_gradient(self, stencil, state, L):
        """grad v_p = L_p."""
        return L


def _without_beta(cls, name):
    def parse(arg, beta=None):
        check(beta is None, f"scheme {name!r}: {name} has no FLIP fraction; drop beta (--beta)")
        return cls()
    return parse


register_scheme("apic", APIC, parse=_without_beta(APIC, "apic"), spec="apic")
register_scheme("tpic", TPIC, parse=_without_beta(TPIC, "tpic"), spec="tpic")
