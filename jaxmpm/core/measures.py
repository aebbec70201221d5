"""Energies and momenta of a particle state (docs/design.md "Diagnostics")."""

from __future__ import annotations

import jax.numpy as jnp

from .validate import POSITIVE


def kinetic_energy(state):
    """1/2 sum_p M_p |V_p|^2."""
    return 0.5 * jnp.sum(state.mass * jnp.sum(state.v**2, axis=-1))


def strain_energy(state, material, F=None):
    """sum_p V0_p W(F_p), W the material's stored-energy density (of F and the material state);
    ``F`` the elastic part when a term imposes a stretch (``Simulation.elastic_deformation``)."""
    F = state.F if F is None else F
    return jnp.sum(state.volume0 * material.stored_energy_density(F, state.material_state))


def linear_momentum(state):
    """sum_p M_p V_p, shape (D,)."""
    return jnp.sum(state.mass[:, None] * state.v, axis=0)


def angular_momentum(state):
    """sum_p X_p x M_p V_p (000 ch. 5): shape (1,) in 1D (always 0) and 2D, (3,) in 3D.

    Under APIC the particles' affine term sum_p M_p (B_p^T : eps) of 002 def. 5.1 is added
    by the scheme through ``state.scheme_state`` when present.
    """
    x, p = state.x, state.mass[:, None] * state.v
    d = x.shape[-1]
    if d == 1:
        return jnp.zeros((1,), x.dtype)
    if d == 2:
        return jnp.sum(x[:, 0] * p[:, 1] - x[:, 1] * p[:, 0], keepdims=True)
    return jnp.sum(jnp.cross(x, p), axis=0)


def by_material(state, material, ids, count: int) -> dict:
    """Per-material sums (multimaterial mode, ``ids`` the particles' material ids 0..count-1):
    kinetic and strain energy (count,), linear momentum (count, D) and, when the state carries
    the contact force field, the contact force on each material (count, D)."""
    one_hot = (ids.astype(jnp.int32)[:, None] == jnp.arange(count, dtype=jnp.int32)[None, :]).astype(state.x.dtype)
    kinetic = 0.5 * state.mass * jnp.sum(state.v**2, axis=-1)
    strain = state.volume0 * material.stored_energy_density(state.F, state.material_state)
    out = dict(kinetic=kinetic @ one_hot, strain=strain @ one_hot,
               momentum=one_hot.T @ (state.mass[:, None] * state.v))
    if "contact_force" in state.fields:
        out["contact_force"] = one_hot.T @ state.fields["contact_force"]
    return out


def stable_dt(grid, material, velocity, cfl: float = 1.0):
    """dt = CFL h / max_p (c + |V_p|), c the dilatational wave speed (docs/design.md).  A concrete
    ``cfl`` must be a finite number > 0 (a traced one passes unchecked)."""
    POSITIVE.check("stable_dt", "cfl", cfl, fix="the Courant number, e.g. 0.5")
    c = material.wave_speed(grid.dim)
    speed = c + jnp.max(jnp.sqrt(jnp.sum(velocity**2, axis=-1)))
    return cfl * grid.h / speed
