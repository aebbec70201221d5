"""The transfer operators of the seeds, in one place.

With S_pi the shape function of node i at particle p (000 ch. 1):

* ``gather``        (S u)_p   = sum_i S_pi u_i                      grid -> particle
* ``scatter``       (S^T q)_i = sum_p S_pi q_p                      particle -> grid
* ``s_plus``        (S+ U)_i  = sum_p S_pi M_p U_p / m_i            000 eq. (1.10)
* ``s_plus_s``      S+ S u    = s_plus(gather(u))                   the XPIC / FMPM kernel
* ``velocity_gradient``  (grad v)_p = sum_i v_i (x) G_pi;  ``gradient`` of a scalar, sum_i u_i G_pi
* ``affine_moment``      B_p = sum_i S_pi v_i (x_i - X_p)^T          002 eq. (4)
* ``p2g``           named nodal sums of tagged per-particle quantities (jaxmpm.transfer.contractions)

Every scheme and term uses these; none writes its own scatter or gather.  The work is done by the
kernel of the backend policy in force (:mod:`jaxmpm.transfer.kernels`); the mass-matrix series
built on ``s_plus_s`` is :mod:`jaxmpm.transfer.series`.
"""

from __future__ import annotations

from functools import partial

import equinox as eqx
import jax
import jax.numpy as jnp
from jax.custom_derivatives import SymbolicZero

from .backend import derivative_rule
from .contractions import Divergence, Weighted
from .kernels import kernel
from .kernels.windowed import active_window
from .kernels.xla import scatter_planar, to_particle_major  # noqa: F401  (re-exported)


def _safe_divide(numerator, mass):
    """numerator / mass where mass > 0, else 0 (NaN-safe in both directions of autodiff)."""
    positive = mass > 0
    denom = jnp.where(positive, mass, 1.0)
    if numerator.ndim > mass.ndim:
        positive = positive[..., None]
        denom = denom[..., None]
    return jnp.where(positive, numerator / denom, 0.0)


_safe_divide_ruled = jax.custom_jvp(_safe_divide)


@partial(_safe_divide_ruled.defjvp, symbolic_zeros=True)
def _safe_divide_jvp(primals, tangents):
    # d(q/m) = (dq - (q/m) dm)/m where m > 0.  With components (q of shape (..., C), m of (...,))
    # the dm term is formed one component at a time: the transpose of broadcasting dm over the
    # components is a reduction over that short trailing axis, which XLA's CPU backend runs slowly
    # (0.3 ms per mpm88 step); that of the per-component products is C multiplies and adds
    (numerator, mass), (numerator_dot, mass_dot) = primals, tangents
    out = _safe_divide_ruled(numerator, mass)
    positive = mass > 0
    denom = jnp.where(positive, mass, 1.0)
    wide = numerator.ndim > mass.ndim
    terms = []
    if not isinstance(numerator_dot, SymbolicZero):
        terms.append(_safe_divide(numerator_dot, mass))
    if not isinstance(mass_dot, SymbolicZero):
        rate = jnp.where(positive, mass_dot / denom, 0.0)
        terms.append(-jnp.stack([out[..., c] * rate for c in range(out.shape[-1])], axis=-1) if wide
                     else -out * rate)
    return out, sum(terms[1:], terms[0]) if terms else jnp.zeros_like(out)


safe_divide = derivative_rule(_safe_divide, _safe_divide_ruled)


def p2g(stencil, columns: dict, num_nodes: int) -> dict:
    """{name: nodal sum} of P2G columns (each a contraction or a tuple of them), by the active kernel."""
    return kernel().p2g(stencil, columns, num_nodes)


def gather(stencil, u):
    """(S u)_p = sum_i S_pi u_i: a nodal field interpolated to the particles (grid -> particle).

    Args:
        stencil: the particles' stencil (:class:`jaxmpm.StencilBase`, e.g.
            ``shape.stencil(grid, x)``).
        u: the nodal field, (n,) or (n, C).

    Returns:
        (N,) or (N, C).
    """
    return kernel().gather(stencil, u)


def slot_values(stencil, u):
    """u_i at every slot of the stencil, (K, N) for a nodal ``u`` (n,): the value at each of each
    particle's nodes (on the sharded path read from the device's window of the grid, the stencil's
    node numbers shifted into it: :meth:`jaxmpm.transfer.kernels.windowed.Window.local_stencil`)."""
    window = active_window()
    return u[stencil.index if window is None else window.local_stencil(stencil).index]


def scatter(stencil, q, num_nodes: int):
    """(S^T q)_i = sum_p S_pi q_p: a particle quantity summed onto the nodes (particle -> grid).

    Args:
        stencil: the particles' stencil (:class:`jaxmpm.StencilBase`).
        q: the particle quantity, (N,) or (N, C).
        num_nodes: n, the number of grid nodes (``grid.num_nodes``).

    Returns:
        (n,) or (n, C).
    """
    return p2g(stencil, {"q": Weighted(q)}, num_nodes)["q"]


def velocity_gradient(stencil, v):
    """(grad v)_p[a, b] = sum_i v_i[a] G_pi[b]  (003 eq. 2.7), shape (N, D, D)."""
    return kernel().velocity_gradient(stencil, v)


def scalar_gradient(stencil, u):
    """(grad u)_p[b] = sum_i u_i G_pi[b] of a nodal scalar ``u`` (n,) (001 eq. 137), shape (N, D)."""
    return kernel().scalar_gradient(stencil, u)


def affine_moment(stencil, v):
    """B_p = sum_i S_pi v_i (x_i - X_p)^T, shape (N, D, D)  (002 eq. 4)."""
    return kernel().affine_moment(stencil, v)


def divergence(stencil, weighted_stress, num_nodes: int, particle_force=None):
    """Internal force f_i = - sum_p (V0_p tau_p) . G_pi  (001 eq. 20, 003 eq. 2.10), plus
    sum_p S_pi q_p for an optional particle force ``q`` (N, D), in the same scatter."""
    force = (Divergence(-weighted_stress),) + (() if particle_force is None else (Weighted(particle_force),))
    return p2g(stencil, {"force": force}, num_nodes)["force"]


class Transfer(eqx.Module):
    """S, S+ and S+S for one particle configuration (one time step): the operators every scheme
    and term uses (:meth:`gather`, :meth:`scatter`, :meth:`s_plus`, :meth:`s_plus_s`, ...).
    :meth:`build` makes one from a stencil and the particle masses.

    Args:
        stencil: the particles' stencil (:class:`jaxmpm.StencilBase`).
        particle_mass: M_p, (N,).
        nodal_mass: the lumped nodal mass m_i = sum_p S_pi M_p, (n,).
        num_nodes: n, the number of nodal rows (the grid's nodes times the velocity fields).
        images: the mirror planes' map (``jaxmpm.physics.conditions.MirrorMap``) whose images
            the nodal sums of :meth:`s_plus` fold in (:class:`jaxmpm.Mirror`), or None (the
            default).
    """

    stencil: object  # the particles' stencil (jaxmpm.StencilBase)
    particle_mass: jnp.ndarray  # M_p, (N,)
    nodal_mass: jnp.ndarray  # m_i = sum_p S_pi M_p, (n,)
    num_nodes: int = eqx.field(static=True)
    # mirror planes (jaxmpm.physics.conditions.MirrorMap): nodal sums fold in the particles' images
    images: object = None

    @classmethod
    def build(cls, stencil, particle_mass, num_nodes: int) -> "Transfer":
        m = scatter(stencil, particle_mass, num_nodes)  # lumped nodal mass
        return cls(stencil, particle_mass, m, num_nodes)

    def gather(self, u):
        return gather(self.stencil, u)

    def scatter(self, q):
        return scatter(self.stencil, q, self.num_nodes)

    def momentum(self, velocity):
        """p_i = sum_p S_pi M_p V_p  (003 eq. 2.1)."""
        return scatter(self.stencil, self.particle_mass[:, None] * velocity, self.num_nodes)

    def particle_share(self, a):
        """M_p (S a)_p: each particle's share of the nodal force m_i a_i (a nodal force per mass);
        summed over the particles it is sum_i m_i a_i over the nodes with mass."""
        return self.particle_mass[:, None] * self.gather(a)

    def s_plus(self, U):
        """(S+ U)_i = sum_p S_pi M_p U_p / m_i  (000 eq. 1.10); with mirror planes the sum includes
        the particles' images (m_i is then the folded mass too)."""
        return safe_divide(self.fold(self.momentum(U)), self.nodal_mass)

    def fold(self, q):
        """A nodal sum of the particles plus that of their mirror images (jm.Mirror), or ``q``."""
        return q if self.images is None else self.images.fold(q)

    def s_plus_s(self, u):
        """S+ S u: gather to the particles, then mass-weighted scatter back (000 eq. 3.19)."""
        return self.s_plus(self.gather(u))

    def velocity_gradient(self, v):
        return velocity_gradient(self.stencil, v)

    def gradient(self, u):
        """(grad u)_p = sum_i u_i G_pi of a nodal scalar, (N, D)."""
        return scalar_gradient(self.stencil, u)

    def affine_moment(self, v):
        """B_p = sum_i S_pi v_i (x_i - X_p)^T, (N, D, D) (002 eq. 4)."""
        return affine_moment(self.stencil, v)

    def p2g(self, columns: dict) -> dict:
        """{name: nodal sum} of P2G columns over this step's particles (:func:`p2g`)."""
        return p2g(self.stencil, columns, self.num_nodes)

    def divergence(self, weighted_stress, particle_force=None):
        return divergence(self.stencil, weighted_stress, self.num_nodes, particle_force)
