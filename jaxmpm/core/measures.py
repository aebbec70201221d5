"""Energies and momenta of a particle state (docs/design.md "Diagnostics")."""

from __future__ import annotations

import jax.numpy as jnp

from .errors import check
from .grid import Grid
from .validate import POSITIVE, compiled_when_concrete


def kinetic_energy(state):
    """1/2 sum_p M_p |V_p|^2.

    Args:
        state: a :class:`jaxmpm.State` (its masses and velocities).
    """
    return 0.5 * jnp.sum(state.mass * jnp.sum(state.v**2, axis=-1))


def strain_energy(state, material, F=None):
    """sum_p V0_p W(F_p), W the material's stored-energy density (of F and the material state).

    Args:
        state: a :class:`jaxmpm.State` (its reference volumes, F and material state).
        material: the :class:`jaxmpm.Material` whose ``stored_energy_density`` W is summed.
        F: the deformation gradients to use, (N, D, D); None (the default) takes ``state.F``.  Give
            the elastic part when a term imposes a stretch (``Simulation.elastic_deformation``).
    """
    F = state.F if F is None else F
    return jnp.sum(state.volume0 * material.stored_energy_density(F, state.material_state))


def gravitational_potential(state, gravity):
    """-sum_p M_p g . X_p: the potential energy of the particles in a uniform gravity ``g`` (D,),
    zero at the origin.  Only its changes mean something (the origin is arbitrary): with the
    kinetic and strain energy, K + U + V_g is what a run under gravity conserves."""
    return -jnp.sum(state.mass * (state.x @ jnp.asarray(gravity, state.x.dtype)))


def linear_momentum(state):
    """sum_p M_p V_p, shape (D,).

    Args:
        state: a :class:`jaxmpm.State` (its masses and velocities).
    """
    return jnp.sum(state.mass[:, None] * state.v, axis=0)


def angular_momentum(state):
    """sum_p X_p x M_p V_p (000 ch. 5): shape (1,) in 1D (always 0) and 2D, (3,) in 3D.

    This is the particles' own share only: under APIC the affine term sum_p M_p (B_p^T : eps) of
    002 def. 5.1 is added by the scheme (``sim.scheme.angular_momentum(state)``).

    Args:
        state: a :class:`jaxmpm.State` (its positions, masses and velocities).
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
    """dt = CFL h / max_p (c + |V_p|), c the dilatational wave speed (docs/design.md).
    :meth:`jaxmpm.Simulation.stable_dt` adds the limits of the model's terms (conduction,
    diffusion).

    Args:
        grid: the :class:`jaxmpm.Grid`; h is its smallest cell size.
        material: the :class:`jaxmpm.Material`, whose ``wave_speed`` is c.
        velocity: the particle velocities V_p, (N, D).
        cfl: the Courant number, a finite number > 0 (default 1.0; a traced one passes
            unchecked).
    """
    POSITIVE.real("stable_dt", "cfl", cfl, fix="the Courant number, e.g. 0.5")  # one number (a traced one passes)
    check(isinstance(grid, Grid), f"stable_dt: grid = {type(grid).__name__}; give the jm.Grid (a model's stable time "
                                  "step with its terms' limits: sim.stable_dt(state))")
    check(hasattr(material, "wave_speed"), f"stable_dt: material = {type(material).__name__}; give the jm.Material "
                                           "whose wave speed bounds the time step (sim.material)")
    # concrete (a scene's dt): one compiled program instead of the eight small ones op by op
    return _cfl_limit(material, velocity, grid.dim, cfl * grid.h)


@compiled_when_concrete
def _cfl_limit(material, velocity, dim: int, scale):
    """CFL h / max_p (c + |V_p|), ``scale`` = CFL h."""
    c = material.wave_speed(dim)
    speed = c + jnp.max(jnp.sqrt(jnp.sum(velocity**2, axis=-1)))
    return scale / speed
