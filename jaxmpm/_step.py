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
from ._transfer import Transfer, safe_divide


class GridFields(eqx.Module):
    """What P2G puts on the grid."""

    transfer: Transfer  # S, S+, S+S and the lumped nodal mass
    momentum: jnp.ndarray  # p_i (n, D)


def update_deformation(F, grad_v, dt):
    """F <- (I + grad v dt) F."""
    eye = jnp.eye(F.shape[-1], dtype=F.dtype)
    return (eye + grad_v * dt) @ F


def p2g(sim, state) -> GridFields:
    """Lumped mass m_i = sum_p S_pi M_p and momentum p_i = sum_p S_pi M_p V_p (003 eq. 2.1),
    plus the scheme's affine terms (APIC/TPIC)."""
    stencil = sim.shape.stencil(sim.grid, state.x)
    transfer = Transfer.build(stencil, state.mass, sim.grid.num_nodes)
    return GridFields(transfer=transfer, momentum=sim.scheme.momentum(transfer, state))


def nodal_force(sim, state, transfer: Transfer):
    """f_i = -sum_p V0_p tau_p . G_pi + sum_p S_pi M_p b_p  (001 eq. 20, 003 eq. 2.10)."""
    tau = sim.material.kirchhoff_stress(state.F)
    body = jnp.broadcast_to(sim.gravity.astype(state.x.dtype), state.x.shape)
    if sim.body_force is not None:
        body = body + sim.body_force(state.x, state.time)
    return transfer.divergence(state.volume0[:, None, None] * tau, state.mass[:, None] * body)  # one scatter


def grid_solve(fields: GridFields, force, dt, constraint: Constraint) -> GridSolution:
    """v = p/m, a = f/m (0 where m = 0), v_tilde = v + a dt, with velocity conditions imposed."""
    m = fields.transfer.nodal_mass
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
    fields = p2g(sim, state)
    transfer = fields.transfer
    F = state.F
    if sim.update == "USF":  # stress first, with the start-of-step velocity
        v0 = constraint.apply(safe_divide(fields.momentum, transfer.nodal_mass))
        v_strain = sim.scheme.strain_grid_velocity(v0, transfer, constraint)
        F = update_deformation(F, transfer.velocity_gradient(v_strain), dt)
        state = eqx.tree_at(lambda s: s.F, state, F)
    force = nodal_force(sim, state, transfer)
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
