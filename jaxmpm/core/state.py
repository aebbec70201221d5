"""The particle state: a core every model has, plus the state each part of the model owns.

* core: positions ``x`` (N, D), velocities ``v`` (N, D), deformation gradients ``F`` (N, D, D),
  masses, reference volumes, time, step count, cumulative dissipated energy
* ``scheme_state``: the scheme's per-particle state (APIC's B_p, TPIC's grad v_p; None for the
  others) -- :meth:`Scheme.initial_state`
* ``material_state``: the material's (None for the elastic materials; e.g. a plastic strain)
  -- :meth:`Material.initial_state`
* ``fields``: named per-particle fields declared by physics terms (:class:`jaxmpm.ParticleField`),
  ``{name: (N, ...)}``; runs save them per frame and HDF5 writes each as ``/particles/<name>``.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp

from .linalg import det


class State(eqx.Module):
    """Particle state: a core every model has, plus the state each part of the model owns.  A
    pytree: ``jax.grad``, ``jax.vmap`` and ``lax.scan`` carry it whole.  :meth:`Simulation.init`
    builds it; :meth:`Simulation.step` returns the next one.

    Args:
        x: positions X_p, (N, D).
        v: velocities V_p, (N, D).
        F: deformation gradients F_p, (N, D, D); (N, 3, 3) in (r, z, theta) on an axisymmetric
            grid.
        mass: masses M_p, (N,).
        volume0: reference volumes V0_p, (N,); the current volume is V0_p det F_p (``volume``).
        time: the simulated time, a scalar.
        step: the number of steps taken, an int32 scalar.
        dissipated: the cumulative energy the scheme and damping dissipated, a scalar.
        scheme_state: the scheme's per-particle state (APIC's B_p, TPIC's grad v_p), or None
            (the default) for the others (:meth:`Scheme.initial_state`).
        material_state: the material's per-particle state (e.g. the stress of HypoElastic and
            IncrementalElastic), or None (the default) for the elastic materials
            (:meth:`Material.initial_state`).
        fields: ``{name: (N, ...)}``, the per-particle fields the physics terms declare
            (:class:`jaxmpm.ParticleField`); runs save them per frame and HDF5 writes each as
            ``/particles/<name>``.  Default ``{}``.
    """

    x: jnp.ndarray
    v: jnp.ndarray
    F: jnp.ndarray
    mass: jnp.ndarray
    volume0: jnp.ndarray
    time: jnp.ndarray
    step: jnp.ndarray
    dissipated: jnp.ndarray
    scheme_state: object = None
    material_state: object = None
    fields: dict = eqx.field(default_factory=dict)

    @property
    def affine(self):
        """The affine matrices of APIC (B_p) and TPIC (grad v_p): ``scheme_state`` under those schemes."""
        return self.scheme_state

    @property
    def volume(self):
        """Current volume V0 det F."""
        return self.volume0 * det(self.F)


def per_particle(leaf, n: int) -> bool:
    """Whether a leaf of a state of ``n`` particles holds one row per particle (x, v, F, the masses,
    the scheme's, material's and terms' per-particle arrays), not a scalar such as the time."""
    return getattr(leaf, "ndim", 0) >= 1 and leaf.shape[0] == n


def with_scheme_state(state: State, value) -> State:
    """``state`` with its scheme state replaced (e.g. APIC's B_p).

    Args:
        state: the :class:`State` to copy.
        value: the new ``scheme_state`` (a pytree, or None).
    """
    return eqx.tree_at(lambda s: s.scheme_state, state, value, is_leaf=lambda x: x is None)


def with_fields(state: State, **fields) -> State:
    """``state`` with the named per-particle fields replaced or added.

    Args:
        state: the :class:`State` to copy.
        **fields: ``name=array`` (N, ...) for each field.
    """
    return eqx.tree_at(lambda s: s.fields, state, {**state.fields, **fields})
