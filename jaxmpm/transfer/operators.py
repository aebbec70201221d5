"""The transfer operators of the seeds, in one place.

With S_pi the shape function of node i at particle p (000 ch. 1):

* ``gather``        (S u)_p   = sum_i S_pi u_i                      grid -> particle
* ``scatter``       (S^T q)_i = sum_p S_pi q_p                      particle -> grid
* ``s_plus``        (S+ U)_i  = sum_p S_pi M_p U_p / m_i            000 eq. (1.10)
* ``s_plus_s``      S+ S u    = s_plus(gather(u))                   the XPIC / FMPM kernel
* ``velocity_gradient``  (grad v)_p = sum_i v_i (x) G_pi;  ``gradient`` of a scalar, sum_i u_i G_pi
* ``divergence``         f_i = - sum_p V0_p tau_p . G_pi             (003 eq. 2.10)

Every scheme uses these; none writes its own scatter.
"""

from __future__ import annotations

from functools import partial

import equinox as eqx
import jax
import jax.numpy as jnp
from jax.custom_derivatives import SymbolicZero

from .backend import derivative_rule, evaluate_once, hold_tangent, materialise, scatter_row_width
from .shapes import StencilBase as Stencil
from .shapes import rows


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


def _sum_over_stencil(a):
    """sum_k a[..., k, :] for planar a of shape (..., K, N), unrolled over the (4-64) stencil
    slots: K-1 elementwise adds of contiguous particle rows, which XLA fuses with their producers."""
    total = a[..., 0, :]
    for k in range(1, a.shape[-2]):
        total = total + a[..., k, :]
    return total


_sum_over_stencil_ruled = jax.custom_jvp(_sum_over_stencil)


@_sum_over_stencil_ruled.defjvp
def _sum_over_stencil_jvp(primals, tangents):
    # the same sum as one reduction: its transpose broadcasts the cotangent to the K slots, where
    # that of the unrolled sum pads each row into its own (K, N) array of zeros and adds them up
    (a,), (a_dot,) = primals, tangents
    return _sum_over_stencil_ruled(a), jnp.sum(a_dot, axis=-2)


sum_over_stencil = derivative_rule(_sum_over_stencil, _sum_over_stencil_ruled)


def _per_slot(w, q):
    """w[k, p] q[c, p] (or w[k, p] q[c, k, p]) for slot values w (K, N) and per-particle values q
    (C, N) (or per-slot values q (C, K, N)): planar (C, K, N)."""
    return w * (q if q.ndim == 3 else q[:, None, :])


_per_slot_ruled = jax.custom_jvp(_per_slot)


@partial(_per_slot_ruled.defjvp, symbolic_zeros=True)
def _per_slot_jvp(primals, tangents):
    # the same product, row by row: the transposes of the broadcasts are reductions over the short
    # slot and component axes, which XLA's CPU backend runs slowly; those of row products are
    # multiplies and adds (the forward keeps the broadcast, which fuses better)
    (w, q), (w_dot, q_dot) = primals, tangents

    def slots(a):  # (K, N) -> K rows; a per-slot (K, N) array stays whole (no broadcast needed)
        return [a] if q.ndim == 3 else rows(a)

    def spread(row_terms):  # K row products -> (K, N)
        return row_terms[0] if q.ndim == 3 else jnp.stack(row_terms)

    terms = []
    if not isinstance(w_dot, SymbolicZero):
        terms.append([spread([wd * qc for wd in slots(w_dot)]) for qc in rows(q)])
    if not isinstance(q_dot, SymbolicZero):
        terms.append([spread([wk * qd for wk in slots(w)]) for qd in rows(q_dot)])
    out = _per_slot_ruled(w, q)
    if not terms:
        return out, jnp.zeros_like(out)
    return out, jnp.stack([sum(t[c] for t in terms) for c in range(q.shape[0])])


per_slot = derivative_rule(_per_slot, _per_slot_ruled)


def _scatter_planar(index, contributions, num_nodes: int):
    """sum_p sum_k c[..., k, p] into node ``index[k, p]``: ``contributions`` (K, N) -> (n,) or
    (C, K, N) -> (n, C).  The one scatter-add of the library; its rows are (node, components)."""
    if contributions.ndim == 2:
        rows = contributions.reshape(-1)
    else:
        rows = contributions.reshape(contributions.shape[0], -1).T
    width = rows.shape[1] if rows.ndim == 2 else 1
    padded = scatter_row_width(width)  # backend tuning: zero columns that XLA:CPU adds faster
    if padded > width:
        rows = jnp.concatenate([rows, jnp.zeros((rows.shape[0], padded - width), rows.dtype)], axis=1)
    dims = jax.lax.ScatterDimensionNumbers(update_window_dims=tuple(range(1, rows.ndim)), inserted_window_dims=(0,),
                                           scatter_dims_to_operand_dims=(0,))
    # in-bounds by construction: shape functions clip node numbers onto the grid (jm.Stencil)
    nodal = jax.lax.scatter_add(jnp.zeros((num_nodes,) + rows.shape[1:], rows.dtype), index.reshape(-1, 1), rows, dims,
                                mode=jax.lax.GatherScatterMode.PROMISE_IN_BOUNDS)
    return nodal[:, :width] if padded > width else nodal


_scatter_planar_ruled = jax.custom_jvp(_scatter_planar, nondiff_argnums=(2,))


@_scatter_planar_ruled.defjvp
def _scatter_planar_jvp(num_nodes, primals, tangents):
    # the same scatter of the tangents, behind a stage boundary: in reverse mode the nodal
    # cotangent is evaluated once, then gathered (the scatter's transpose); without it XLA fuses
    # the cotangent's computation into the gather and repeats it for every stencil slot
    (index, c), (_, c_dot) = primals, tangents
    out = _scatter_planar_ruled(index, c, num_nodes)
    return out, hold_tangent(_scatter_planar(index, c_dot, num_nodes), out)


scatter_planar = derivative_rule(_scatter_planar, _scatter_planar_ruled)


def scatter_columns(stencil: Stencil, columns, num_nodes: int, *args) -> dict:
    """P2G of named columns in ONE scatter-add.  ``columns(*args)`` returns {name: per-slot
    contributions, planar (K, N) or (C, K, N)}; the result is {name: nodal (n,) or (n, C)}.  The
    columns are evaluated into one buffer (a stage boundary, see jaxmpm.transfer.backend) and scattered
    as (node, all columns) rows."""
    layout = {}  # name -> (width, scalar), in the order the columns are stacked

    def stacked(*a):
        cols = columns(*a)
        layout.clear()
        layout.update({name: (1 if c.ndim == 2 else c.shape[0], c.ndim == 2) for name, c in cols.items()})
        return jnp.concatenate([c[None] if c.ndim == 2 else c for c in cols.values()])

    nodal = scatter_planar(stencil.index, evaluate_once(stacked, *args), num_nodes)
    out, start = {}, 0
    for name, (width, scalar) in layout.items():
        out[name] = nodal[:, start] if scalar else nodal[:, start:start + width]
        start += width
    return out


def nodal_values(stencil: Stencil, u):
    """u_i at every stencil slot: (n,) -> (K, N), (n, C) -> a list of C arrays (K, N).  One gather
    of scalars per component (from the transposed (C, n) nodal array): on CPU this is faster than
    gathering (K N, C) rows and transposing them, and consumers read each component directly."""
    index = stencil.index  # on the grid (shape functions clip it), so no bounds handling
    if u.ndim == 1:
        return materialise(u).at[index].get(mode="promise_in_bounds")
    # the nodal field is evaluated once first: XLA would otherwise fuse its whole computation
    # (v = p/m, boundary conditions) into the gather and repeat it for every slot
    return materialise([uc.at[index].get(mode="promise_in_bounds") for uc in materialise(u.T)])


def gather_planar(stencil: Stencil, u):
    """(S u)_p for nodal ``u`` (n,) or (n, C), planar result (N,) or (C, N)."""
    values = nodal_values(stencil, u)
    if u.ndim == 1:
        return sum_over_stencil(stencil.weight * values)
    w = stencil.weight
    return jnp.stack([sum_over_stencil(w * vc) for vc in values])


def gather(stencil: Stencil, u):
    """(S u)_p = sum_i S_pi u_i for nodal ``u`` of shape (n,) or (n, C); result (N,) or (N, C)."""
    Su = gather_planar(stencil, u)
    return Su if u.ndim == 1 else to_particle_major(Su)


def to_particle_major(planar):
    """(C..., N) -> (N, C...), evaluated first: otherwise XLA moves the whole planar computation
    into the transpose, where it runs element by element instead of on particle vectors."""
    return jnp.moveaxis(materialise(planar), -1, 0)


def scatter(stencil: Stencil, q, num_nodes: int):
    """(S^T q)_i = sum_p S_pi q_p for particle ``q`` of shape (N,) or (N, C)."""
    contributions = stencil.weight * q if q.ndim == 1 else per_slot(stencil.weight, q.T)  # (K, N) or (C, K, N)
    return scatter_planar(stencil.index, contributions, num_nodes)


def velocity_gradient(stencil: Stencil, v):
    """(grad v)_p[a, b] = sum_i v_i[a] G_pi[b]  (003 eq. 2.7), shape (N, D, D)."""
    values = nodal_values(stencil, v)  # D arrays (K, N)
    g = rows(stencil.gradient)
    d = len(g)
    planar = jnp.stack([jnp.stack([sum_over_stencil(values[a] * g[b]) for b in range(d)]) for a in range(d)])
    return to_particle_major(planar)


def scalar_gradient(stencil: Stencil, u):
    """(grad u)_p[b] = sum_i u_i G_pi[b] of a nodal scalar ``u`` (n,) (001 eq. 137), shape (N, D)."""
    values = nodal_values(stencil, u)  # (K, N)
    g = rows(stencil.gradient)
    return to_particle_major(jnp.stack([sum_over_stencil(values * g[b]) for b in range(len(g))]))


def stress_divergence_contributions(stencil: Stencil, weighted_stress):
    """Per-slot internal force -(V0_p tau_p) . G_pi (001 eq. 20, 003 eq. 2.10), planar (D, K, N)."""
    g = rows(stencil.gradient)
    d = len(g)
    tau = [rows(t) for t in rows(materialise(jnp.moveaxis(weighted_stress, 0, -1))[:, :, None, :])]  # (D, D, 1, N)
    return -jnp.stack([sum(tau[a][b] * g[b] for b in range(d)) for a in range(d)])


def particle_force_contributions(stencil: Stencil, particle_force):
    """Per-slot S_pi q_p of a particle force ``q`` (N, D) (e.g. M_p b_p), planar (D, K, N)."""
    return per_slot(stencil.weight, materialise(particle_force.T))


def force_contributions(stencil: Stencil, weighted_stress, particle_force=None):
    """Per-slot internal force -(V0_p tau_p) . G_pi (001 eq. 20, 003 eq. 2.10) plus S_pi q_p for an
    optional particle force ``q`` (N, D) (e.g. M_p b_p); planar (D, K, N)."""
    contrib = stress_divergence_contributions(stencil, weighted_stress)
    if particle_force is not None:
        contrib = contrib + particle_force_contributions(stencil, particle_force)
    return contrib


def divergence(stencil: Stencil, weighted_stress, num_nodes: int, particle_force=None):
    """Internal force f_i = - sum_p (V0_p tau_p) . G_pi  (001 eq. 20, 003 eq. 2.10), plus
    sum_p S_pi q_p for an optional particle force ``q`` (N, D), in the same scatter."""
    return scatter_planar(stencil.index, force_contributions(stencil, weighted_stress, particle_force), num_nodes)


def momentum_contributions(stencil: Stencil, mass, velocity):
    """Per-slot momentum S_pi M_p V_p, planar (D, K, N)."""
    return per_slot(stencil.weight, (mass[:, None] * velocity).T)


class Transfer(eqx.Module):
    """S, S+ and S+S for one particle configuration (one time step)."""

    stencil: Stencil
    particle_mass: jnp.ndarray  # M_p, (N,)
    nodal_mass: jnp.ndarray  # m_i = sum_p S_pi M_p, (n,)
    num_nodes: int = eqx.field(static=True)
    images: object = None  # mirror planes (jaxmpm.physics.conditions.MirrorMap): nodal sums fold in the particles' images

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
        return scatter_planar(self.stencil.index, momentum_contributions(self.stencil, self.particle_mass, velocity),
                              self.num_nodes)

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

    def divergence(self, weighted_stress, particle_force=None):
        return divergence(self.stencil, weighted_stress, self.num_nodes, particle_force)
