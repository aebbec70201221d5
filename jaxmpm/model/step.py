"""One MPM time step as the stages of 003 §2.1, with the model's physics terms plugged in.

``step`` reads as the algorithm:

1. shape functions S_pi, G_pi at the particles               (001 eqs. 16-17)
2. ``p2g``: the nodal fields the scheme and the terms request, in one scatter-add --
   lumped mass m_i, momentum p_i (003 eq. 2.1, plus APIC/TPIC's affine terms) and the terms'
   columns (force f_i: stress divergence and body force, 001 eq. 20, 003 eq. 2.10)
3. ``grid_solve``: v = p/m, a = f/m, v_tilde = v + a dt, velocity conditions; terms' grid actions
4. ``g2p``: the scheme's particle update (000 eq. 3.28, 003 eq. 2.17, 002 eq. 4); terms' particle
   actions; the strain update (USL-: the update's grid velocity; MUSL: re-extrapolated, 003
   §2.1.6) and the material's state update

USF computes the strain increment before the forces (from the start-of-step velocities);
USAVG-/USAVG+ do both, each over dt/2: USF's before the forces, then USL-'s resp. MUSL's (003 §2.2).
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp

from ..physics.conditions import Constraint
from ..physics.contact import material_stencil
from ..core.fields import GridFields, GridSolution
from ..transfer.shapes import StencilBase as Stencil
from ..physics.term import damping_at
from ..transfer.operators import Transfer, safe_divide, scatter_columns


def folds_force(sim) -> bool:
    """Whether P2G may scatter the updated momentum p + f dt in place of p and f ((1 + D) numbers
    per stencil slot instead of 1 + 2D): when nothing downstream needs v and a apart -- a scheme
    that reads only v_tilde (APIC, TPIC), no damping in the model (``damping=False``), and a USL
    or MUSL update (USF needs v before the force)."""
    return (sim.update in ("USL", "MUSL") and sim.damping is None and not sim.scheme.uses_lumped_velocity
            and sim.material_fields == 1)  # contact needs p and f apart (003 eqs. 3.19-3.22)


def strain_dt(sim, dt):
    """The strain update's time step: dt, or dt/2 under USAVG-/USAVG+, which update the stress
    twice per step, before the forces and after the particle update (003 §2.2, steps 2 and 6)."""
    return 0.5 * dt if sim.update in ("USAVG-", "USAVG+") else dt


def update_deformation(F, grad_v, dt, kinematics: str = "linear"):
    """F <- dF F with dF = I + grad v dt (``kinematics="linear"``, the first-order increment) or
    dF = exp(grad v dt) (``"exponential"``, 001 eq. 26: exact for a velocity gradient constant over
    the step, so a pure spin gives an exact rotation, det dF = 1)."""
    if kinematics == "exponential":
        from jax.scipy.linalg import expm

        return expm(grad_v * dt) @ F  # 001 eq. (26)
    eye = jnp.eye(F.shape[-1], dtype=F.dtype)
    return (eye + grad_v * dt) @ F


def strain_rate(sim, transfer: Transfer, v):
    """The velocity gradient the strain update uses, (grad v)_p = sum_i v_i (x) G_pi (003 eq. 2.7);
    on an axisymmetric grid the 3x3 (r, z, theta) gradient of 001 eq. 113 with the hoop rate
    v_r / r = sum_i v_ri T_ip in its (theta, theta) slot (T the hoop shape function, 001 eq. 116):
    the rate whose power is that of the hoop force, so the strain energy stays consistent."""
    grad = transfer.velocity_gradient(v)
    if not sim.grid.axisymmetric:
        return grad
    from ..transfer.operators import gather

    hoop = gather(transfer.stencil.hoop_view(), v[:, 0])  # sum_i v_ri T_ip, (N,)
    zero = jnp.zeros_like(grad[:, :, :1])
    top = jnp.concatenate([grad, zero], axis=2)  # (N, 2, 3)
    bottom = jnp.concatenate([jnp.swapaxes(zero, 1, 2), hoop[:, None, None]], axis=2)  # (N, 1, 3)
    return jnp.concatenate([top, bottom], axis=1)


def term_columns(sim, state, stencil: Stencil) -> dict:
    """The terms' per-slot columns, summed by name in term order."""
    columns = {}
    for term in sim.terms:
        for name, c in term.p2g_columns(sim, state, stencil).items():
            columns[name] = columns[name] + c if name in columns else c
    return columns


def p2g(sim, state, force: bool = True, dt=None) -> GridFields:
    """Lumped mass m_i = sum_p S_pi M_p, momentum p_i = sum_p S_pi M_p V_p (003 eq. 2.1) plus the
    scheme's affine terms (APIC/TPIC), and (``force=True``) the terms' columns (the nodal force),
    all in one scatter-add.  With ``dt`` (see :func:`folds_force`) momentum and force are
    scattered as one updated momentum p + f dt."""
    stencil = particle_stencil(sim, state)

    def columns(stencil, state, dt):
        out = {"mass": stencil.weight * state.mass,
               "momentum": sim.scheme.momentum_contributions(stencil, state)}
        if force or dt is not None:
            out.update(term_columns(sim, state, stencil))
        if dt is not None:
            out["updated_momentum"] = out.pop("momentum") + dt * out.pop("force")
        return out

    nodal = scatter_columns(stencil, columns, sim.field_nodes, stencil, state, dt)
    if force or dt is not None:
        nodal = with_surface_forces(sim, state, nodal, nodal["mass"], dt)
    images = sim.constraint(state.x.dtype).mirror  # jm.Mirror: fold in the particles' mirror images
    if images is not None:
        nodal = images.fold_columns(nodal)
    transfer = Transfer(stencil, state.mass, nodal.pop("mass"), sim.field_nodes, images)
    return GridFields(transfer, nodal)


def with_surface_forces(sim, state, nodal: dict, nodal_mass, dt=None) -> dict:
    """The nodal fields with the terms' own nodal forces (``Term.nodal_force``: tractions, 001
    eq. 21) added to the force, or dt times them to a folded updated momentum."""
    extra = [f for f in (term.nodal_force(sim, state, nodal_mass) for term in sim.terms) if f is not None]
    if not extra:
        return nodal
    total = sum(extra[1:], extra[0])
    if "updated_momentum" in nodal:
        return {**nodal, "updated_momentum": nodal["updated_momentum"] + dt * total}
    return {**nodal, "force": nodal["force"] + total}


def particle_stencil(sim, state, x=None, shape=None):
    """S_pi, G_pi at the particles (001 eqs. 16-17), or at points ``x`` (N, D) that stand for them
    (a traction's edge points), with ``shape`` in place of the model's (a traction's grid basis);
    in multimaterial mode each particle's nodes are those of its material's velocity field
    (jaxmpm.physics.contact)."""
    stencil = (sim.shape if shape is None else shape).stencil(sim.grid, state.x if x is None else x)
    if sim.material_fields == 1:
        return stencil
    return material_stencil(stencil, state.fields["material"].astype(stencil.index.dtype), sim.grid.num_nodes)


def nodal_terms(sim, state, transfer: Transfer) -> dict:
    """The terms' nodal fields alone (USF: after the strain update), in one scatter-add."""
    nodal = scatter_columns(transfer.stencil, lambda s: term_columns(sim, s, transfer.stencil), transfer.num_nodes,
                            state)
    nodal = with_surface_forces(sim, state, nodal, transfer.nodal_mass)
    return nodal if transfer.images is None else transfer.images.fold_columns(nodal)  # as in p2g


def grid_solve(fields: GridFields, force, dt, constraint: Constraint) -> GridSolution:
    """v = p/m, a = f/m (0 where m = 0), v_tilde = v + a dt, with velocity conditions imposed.
    From a folded P2G (:func:`folds_force`) only v_tilde = (p + f dt)/m exists (v, a are None);
    it is the same v_tilde: the conditions act on v + a dt in both cases."""
    m = fields.transfer.nodal_mass
    if fields.updated_momentum is not None:
        return GridSolution(v=None, a=None, v_tilde=constraint.apply(safe_divide(fields.updated_momentum, m)))
    v_lumped, a_lumped = safe_divide(fields.momentum, m), safe_divide(force, m)
    # p+/m before any condition: FMPM's unlumped boundary variants start from it (003 §2.4)
    unconstrained = v_lumped + a_lumped * dt
    if constraint.wall is not None:  # one-sided walls act on v_tilde, as contact (jm.Wall)
        v, a, v_tilde = constraint.contact(constraint.apply_two_sided(v_lumped), constraint.zero(a_lumped), dt)
        return GridSolution(v=v, a=a, v_tilde=v_tilde, v_tilde_unconstrained=unconstrained)
    v = constraint.apply(v_lumped)
    a = constraint.zero(a_lumped)
    return GridSolution(v=v, a=a, v_tilde=constraint.apply(v + a * dt), v_tilde_unconstrained=unconstrained)


def step(sim, state, dt):
    """One full time step; returns the new state.  Pure: jit, grad and vmap apply."""
    dt = jnp.asarray(dt, state.x.dtype)
    constraint = sim.constraint(state.x.dtype)
    if sim.update in ("USF", "USAVG-", "USAVG+"):  # stress first, with the start-of-step velocity
        fields = p2g(sim, state, force=False)
        transfer = fields.transfer
        v0 = constraint.apply(safe_divide(fields.momentum, transfer.nodal_mass))
        v_strain = sim.scheme.strain_grid_velocity(v0, transfer, constraint)
        F = update_deformation(state.F, strain_rate(sim, transfer, v_strain), strain_dt(sim, dt), sim.kinematics)
        material_state = sim.material.update_state(F, state.material_state, strain_dt(sim, dt))
        state = eqx.tree_at(lambda s: (s.F, s.material_state), state, (F, material_state),
                            is_leaf=lambda x: x is None)
        fields = GridFields(transfer, {**fields.values, **nodal_terms(sim, state, transfer)})
    else:  # USL, MUSL: the stress of the step's start, scattered with the mass and momentum
        fields = p2g(sim, state, dt=dt if folds_force(sim) else None)
    transfer = fields.transfer

    solution = grid_solve(fields, fields.force, dt, constraint)
    for term in sim.terms:
        solution = term.grid_action(sim, fields, solution, dt)
    return g2p(sim, state, transfer, constraint, solution, dt)


def g2p(sim, state, transfer: Transfer, constraint: Constraint, grid: GridSolution, dt):
    """Particle update by the scheme, the terms' particle actions, then the USL-/MUSL strain
    update and the material's state update."""
    damping = damping_at(sim.damping, state, transfer, grid)  # alpha(t, x), 001 §5.3 (default: sim.damping)
    upd = sim.scheme.update(state.v, state.x, transfer, constraint, grid, damping, dt)
    scheme_state = sim.scheme.next_state(state, upd, transfer, grid)
    F = state.F
    if sim.update in ("USL", "USAVG-"):  # USL-: the velocity the update just used (USAVG-: for dt/2)
        F = update_deformation(F, strain_rate(sim, transfer, upd.strain_velocity), strain_dt(sim, dt), sim.kinematics)
    elif sim.update in ("MUSL", "USAVG+"):  # USL+: re-extrapolate p = S^T M V^{n+1} (003 §2.1.6), affine terms too
        updated = eqx.tree_at(lambda s: (s.v, s.scheme_state), state, (upd.velocity, scheme_state),
                              is_leaf=lambda x: x is None)
        v_new = constraint.apply(safe_divide(transfer.fold(sim.scheme.momentum(transfer, updated)),
                                             transfer.nodal_mass))
        v_strain = sim.scheme.strain_grid_velocity(v_new, transfer, constraint)
        F = update_deformation(F, strain_rate(sim, transfer, v_strain), strain_dt(sim, dt), sim.kinematics)
    material_state = state.material_state
    if sim.update != "USF":  # (USF updated the material state before the forces; USAVG+- do both halves)
        material_state = sim.material.update_state(F, material_state, strain_dt(sim, dt))
    F = sim.material.keep_deformation(F)  # F itself except for fluids (VolumetricFluid: J^(1/D) I)
    new = eqx.tree_at(
        lambda s: (s.x, s.v, s.F, s.time, s.step, s.dissipated, s.scheme_state, s.material_state),
        state,
        (upd.position, upd.velocity, F, state.time + dt, state.step + 1, state.dissipated + upd.dissipated,
         scheme_state, material_state),
        is_leaf=lambda x: x is None,
    )
    for term in sim.terms:
        new = term.particle_action(sim, state, new, transfer, grid, dt)
    return new
