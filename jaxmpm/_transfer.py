"""The transfer operators of the seeds, in one place.

With S_pi the shape function of node i at particle p (000 ch. 1):

* ``gather``        (S u)_p   = sum_i S_pi u_i                      grid -> particle
* ``scatter``       (S^T q)_i = sum_p S_pi q_p                      particle -> grid
* ``s_plus``        (S+ U)_i  = sum_p S_pi M_p U_p / m_i            000 eq. (1.10)
* ``s_plus_s``      S+ S u    = s_plus(gather(u))                   the XPIC / FMPM kernel
* ``velocity_gradient``  (grad v)_p = sum_i v_i (x) G_pi
* ``divergence``         f_i = - sum_p V0_p tau_p . G_pi             (003 eq. 2.10)

Every scheme uses these; none writes its own scatter.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp

from ._shapes import Stencil


def safe_divide(numerator, mass):
    """numerator / mass where mass > 0, else 0 (NaN-safe in both directions of autodiff)."""
    positive = mass > 0
    denom = jnp.where(positive, mass, 1.0)
    if numerator.ndim > mass.ndim:
        positive = positive[..., None]
        denom = denom[..., None]
    return jnp.where(positive, numerator / denom, 0.0)


def sum_over_stencil(a):
    """sum_k a[:, k] for a of shape (N, K, ...), unrolled over the (4-64) stencil nodes: XLA's CPU
    reduction over a short middle axis is several times slower than K-1 fused elementwise adds."""
    total = a[:, 0]
    for k in range(1, a.shape[1]):
        total = total + a[:, k]
    return total


def _scatter_add(index, values, num_nodes: int):
    """sum over rows r of ``values`` (R, ...) into node ``index[r]``."""
    return jnp.zeros((num_nodes,) + values.shape[1:], values.dtype).at[index].add(values)


def gather(stencil: Stencil, u):
    """(S u)_p = sum_i S_pi u_i for nodal ``u`` of shape (n,) or (n, C)."""
    values = u[stencil.index]  # (N, K, ...)
    w = stencil.weight if u.ndim == 1 else stencil.weight[..., None]
    return sum_over_stencil(w * values)


def scatter(stencil: Stencil, q, num_nodes: int):
    """(S^T q)_i = sum_p S_pi q_p for particle ``q`` of shape (N,) or (N, C)."""
    w = stencil.weight if q.ndim == 1 else stencil.weight[..., None]
    contrib = w * q[:, None]  # (N, K, ...)
    return _scatter_add(stencil.index.reshape(-1), contrib.reshape((-1,) + q.shape[1:]), num_nodes)


def scatter_weighted(stencil: Stencil, nodal_values, num_nodes: int):
    """sum_p sum_k c_pk over the stencil for per-(particle, node) contributions c of shape (N, K, C)."""
    flat = nodal_values.reshape((-1,) + nodal_values.shape[2:])
    return _scatter_add(stencil.index.reshape(-1), flat, num_nodes)


def velocity_gradient(stencil: Stencil, v):
    """(grad v)_p[a, b] = sum_i v_i[a] G_pi[b]  (003 eq. 2.7)."""
    values = v[stencil.index]  # (N, K, D)
    g = stencil.gradient
    # unrolled over the (1-3 long) component axes: elementwise products and a sum over K fuse on
    # CPU, where a batched dot_general of (K, D) matrices does not
    return jnp.stack([jnp.stack([sum_over_stencil(values[..., a] * g[..., b]) for b in range(g.shape[-1])], -1)
                      for a in range(values.shape[-1])], -2)


def divergence(stencil: Stencil, weighted_stress, num_nodes: int, particle_force=None):
    """Internal force f_i = - sum_p (V0_p tau_p) . G_pi  (001 eq. 20, 003 eq. 2.10), plus
    sum_p S_pi q_p for an optional particle force ``q`` (N, D) (e.g. M_p b_p), in the same scatter."""
    g = stencil.gradient
    d = g.shape[-1]
    contrib = -jnp.stack([sum(weighted_stress[:, None, a, b] * g[..., b] for b in range(d)) for a in range(d)], -1)
    if particle_force is not None:
        contrib = contrib + stencil.weight[..., None] * particle_force[:, None, :]
    return scatter_weighted(stencil, contrib, num_nodes)


class Transfer(eqx.Module):
    """S, S+ and S+S for one particle configuration (one time step)."""

    stencil: Stencil
    particle_mass: jnp.ndarray  # M_p, (N,)
    nodal_mass: jnp.ndarray  # m_i = sum_p S_pi M_p, (n,)
    num_nodes: int = eqx.field(static=True)

    @classmethod
    def build(cls, stencil: Stencil, particle_mass, num_nodes: int) -> "Transfer":
        m = scatter(stencil, particle_mass, num_nodes)  # lumped nodal mass
        return cls(stencil, particle_mass, m, num_nodes)

    def gather(self, u):
        return gather(self.stencil, u)

    def scatter(self, q):
        return scatter(self.stencil, q, self.num_nodes)

    def momentum(self, velocity):
        """p_i = sum_p S_pi M_p V_p  (003 eq. 2.1)."""
        return self.scatter(self.particle_mass[:, None] * velocity)

    def s_plus(self, U):
        """(S+ U)_i = sum_p S_pi M_p U_p / m_i  (000 eq. 1.10)."""
        return safe_divide(self.momentum(U), self.nodal_mass)

    def s_plus_s(self, u):
        """S+ S u: gather to the particles, then mass-weighted scatter back (000 eq. 3.19)."""
        return self.s_plus(self.gather(u))

    def velocity_gradient(self, v):
        return velocity_gradient(self.stencil, v)

    def divergence(self, weighted_stress, particle_force=None):
        return divergence(self.stencil, weighted_stress, self.num_nodes, particle_force)
