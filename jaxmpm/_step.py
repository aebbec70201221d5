"""The three pure steps of one MPM time step (DESIGN.md "One time step"), single velocity field.

``p2g``        particle -> grid: lumped mass m_i, momentum p_i, force f_i (001 eqs. 20-25)
``grid_solve`` v = p/m, a = f/m, v_tilde = v + a dt with velocity boundary conditions
``g2p``        the scheme's particle update, then (USL/MUSL) the strain update
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp

from ._boundary import Constraint
from ._schemes import GridSolution
from ._shapes import StencilBase as Stencil, evaluated_once
from ._transfer import Transfer, force_contributions, safe_divide, scatter_planar


class GridFields(eqx.Module):
    """What P2G puts on the grid."""

    transfer: Transfer  # S, S+, S+S and the lumped nodal mass
    momentum: jnp.ndarray | None  # p_i (n, D); None when only the updated momentum was scattered
    force: jnp.ndarray | None = None  # f_i (n, D); None when P2G was asked for no force (USF)
    updated_momentum: jnp.ndarray | None = None  # p_i + f_i dt, when scattered in place of p and f


def folds_force(sim) -> bool:
    """Whether P2G may scatter the updated momentum p + f dt in place of p and f ((1 + D) numbers
    per stencil slot instead of 1 + 2D): when nothing downstream needs v and a apart -- a scheme
    that reads only v_tilde (APIC, TPIC), no damping in the model (``damping=False``), and a USL
    or MUSL update (USF needs v before the force)."""
    return sim.update != "USF" and sim.damping is None and not sim.scheme.uses_lumped_velocity


def update_deformation(F, grad_v, dt):
    """F <- (I + grad v dt) F."""
    eye = jnp.eye(F.shape[-1], dtype=F.dtype)
    return (eye + grad_v * dt) @ F


def force_contributions_of(sim, state, stencil: Stencil):
    """Per-slot -V0_p tau_p . G_pi + S_pi M_p b_p, planar (D, K, N)  (001 eq. 20, 003 eq. 2.10)."""
    tau = sim.material.kirchhoff_stress(state.F)
    body = jnp.broadcast_to(sim.gravity.astype(state.x.dtype), state.x.shape)
    if sim.body_force is not None:
        body = body + sim.body_force(state.x, state.time)
    return force_contributions(stencil, state.volume0[:, None, None] * tau, state.mass[:, None] * body)


def p2g(sim, state, force: bool = True, dt=None) -> GridFields:
    """Lumped mass m_i = sum_p S_pi M_p, momentum p_i = sum_p S_pi M_p V_p (003 eq. 2.1) plus the
    scheme's affine terms (APIC/TPIC), and (``force=True``) the nodal force of :func:`nodal_force`,
    all in one scatter-add of (1 + 2D) numbers per stencil slot.  With ``dt`` (see
    :func:`folds_force`) the momentum and force are scattered as one updated momentum p + f dt."""
    stencil = sim.shape.stencil(sim.grid, state.x)
    d = state.x.shape[1]

    def columns(stencil, state, dt):
        mass = (stencil.weight * state.mass)[None]
        momentum = sim.scheme.momentum_contributions(stencil, state)
        if dt is not None:
            return jnp.concatenate([mass, momentum + dt * force_contributions_of(sim, state, stencil)])
        if force:
            return jnp.concatenate([mass, momentum, force_contributions_of(sim, state, stencil)])
        return jnp.concatenate([mass, momentum])

    # evaluated into its own buffer (vectorised over particles), then scattered as (node, columns) rows
    nodal = scatter_planar(stencil.index, evaluated_once(columns, stencil, state, dt), sim.grid.num_nodes)
    transfer = Transfer(stencil, state.mass, nodal[:, 0], sim.grid.num_nodes)
    if dt is not None:
        return GridFields(transfer=transfer, momentum=None, updated_momentum=nodal[:, 1:])
    return GridFields(transfer=transfer, momentum=nodal[:, 1:1 + d], force=nodal[:, 1 + d:] if force else None)


def nodal_force(sim, state, transfer: Transfer):
    """f_i = -sum_p V0_p tau_p . G_pi + sum_p S_pi M_p b_p  (001 eq. 20, 003 eq. 2.10)."""
    return scatter_planar(transfer.stencil.index, force_contributions_of(sim, state, transfer.stencil),
                          transfer.num_nodes)


def grid_solve(fields: GridFields, force, dt, constraint: Constraint) -> GridSolution:
    """v = p/m, a = f/m (0 where m = 0), v_tilde = v + a dt, with velocity conditions imposed.
    From a folded P2G (:func:`folds_force`) only v_tilde = (p + f dt)/m exists (v, a are None);
    it is the same v_tilde: the conditions act on v + a dt in both cases."""
    m = fields.transfer.nodal_mass
    if fields.updated_momentum is not None:
        return GridSolution(v=None, a=None, v_tilde=constraint.apply(safe_divide(fields.updated_momentum, m)))
    if constraint.wall is not None:  # one-sided walls act on v_tilde, as contact (jm.Wall)
        v, a, v_tilde = constraint.contact(constraint.apply_two_sided(safe_divide(fields.momentum, m)),
                                           constraint.zero(safe_divide(force, m)), dt)
        return GridSolution(v=v, a=a, v_tilde=v_tilde)
    v = constraint.apply(safe_divide(fields.momentum, m))
    a = constraint.zero(safe_divide(force, m))
    return GridSolution(v=v, a=a, v_tilde=constraint.apply(v + a * dt))


def step(sim, state, dt):
    """One full time step; returns the new state.  Pure: jit, grad and vmap apply."""
    dt = jnp.asarray(dt, state.x.dtype)
    constraint = sim.constraint(state.x.dtype)
    if sim.update == "USF":  # stress first, with the start-of-step velocity
        fields = p2g(sim, state, force=False)
        transfer = fields.transfer
        v0 = constraint.apply(safe_divide(fields.momentum, transfer.nodal_mass))
        v_strain = sim.scheme.strain_grid_velocity(v0, transfer, constraint)
        state = eqx.tree_at(lambda s: s.F, state, update_deformation(state.F, transfer.velocity_gradient(v_strain), dt))
        force = nodal_force(sim, state, transfer)
    else:  # USL, MUSL: the stress of the step's start, scattered with the mass and momentum
        fields = p2g(sim, state, dt=dt if folds_force(sim) else None)
        transfer, force = fields.transfer, fields.force

    grid = grid_solve(fields, force, dt, constraint)
    return g2p(sim, state, transfer, constraint, grid, dt)


def g2p(sim, state, transfer: Transfer, constraint: Constraint, grid: GridSolution, dt):
    """Particle update by the scheme, then the USL-/MUSL strain update."""
    upd = sim.scheme.update(state.v, state.x, transfer, constraint, grid, sim.damping, dt)
    extra = sim.scheme.particle_state(state, upd, transfer, grid)
    F = state.F
    if sim.update == "USL":  # USL-: the velocity the update just used
        F = update_deformation(F, transfer.velocity_gradient(upd.strain_velocity), dt)
    elif sim.update == "MUSL":  # USL+: re-extrapolate p = S^T M V^{n+1} (003 §2.1.6), affine terms included
        updated = eqx.tree_at(lambda s: (s.v, s.affine), state, (upd.velocity, extra), is_leaf=lambda x: x is None)
        v_new = constraint.apply(safe_divide(sim.scheme.momentum(transfer, updated), transfer.nodal_mass))
        v_strain = sim.scheme.strain_grid_velocity(v_new, transfer, constraint)
        F = update_deformation(F, transfer.velocity_gradient(v_strain), dt)
    F = sim.material.keep_deformation(F)  # F itself except for fluids (VolumetricFluid: J^(1/D) I)
    return eqx.tree_at(
        lambda s: (s.x, s.v, s.F, s.time, s.step, s.dissipated, s.affine),
        state,
        (upd.position, upd.velocity, F, state.time + dt, state.step + 1, state.dissipated + upd.dissipated, extra),
        is_leaf=lambda x: x is None,
    )
