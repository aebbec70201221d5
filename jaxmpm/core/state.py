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


class State(eqx.Module):
    """Particle state (see the module docstring).  A pytree: ``jax.grad``, ``jax.vmap`` and
    ``lax.scan`` carry it whole."""

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
        return self.volume0 * jnp.linalg.det(self.F)


def with_scheme_state(state: State, value) -> State:
    """``state`` with its scheme state replaced (e.g. APIC's B_p)."""
    return eqx.tree_at(lambda s: s.scheme_state, state, value, is_leaf=lambda x: x is None)


def with_fields(state: State, **fields) -> State:
    """``state`` with the named per-particle fields replaced or added."""
    return eqx.tree_at(lambda s: s.fields, state, {**state.fields, **fields})
