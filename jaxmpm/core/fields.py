"""Fields by name: the nodal fields P2G assembles and the grid solve produces, and the
per-particle fields physics terms declare.

* :class:`GridFields`   what P2G put on the grid: ``fields["momentum"]``, ``fields["force"]``, ...
                        plus the :class:`~jaxmpm.Transfer` (S, S+, S+S, lumped mass) of the step
* :class:`GridSolution` what the grid solve made of them: ``v``, ``a``, ``v_tilde``, ... by name
* :class:`ParticleField` a named per-particle field a term declares (carried in ``State.fields``,
                        saved per frame as ``/particles/<name>`` in HDF5)

Names are the physics: ``mass``, ``momentum``, ``force``, ``updated_momentum`` (p + f dt),
``v``, ``a``, ``v_tilde``; terms add their own (later per-material momenta, heat, ...).
"""

from __future__ import annotations

from typing import Callable

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .errors import check


class _Named(eqx.Module):
    """A mapping of names to arrays (a pytree), read as ``fields["name"]`` or ``fields.get(name)``."""

    values: dict

    def __getitem__(self, name):
        check(name in self.values, f"{type(self).__name__}: no field {name!r}; it holds {', '.join(self.values)}")
        return self.values[name]

    def get(self, name, default=None):
        return self.values.get(name, default)

    def __contains__(self, name):
        return name in self.values

    @property
    def names(self) -> tuple:
        return tuple(self.values)


class GridFields(_Named):
    """What P2G puts on the grid, by name, with the step's :class:`~jaxmpm.Transfer`."""

    transfer: object  # jaxmpm.Transfer: S, S+, S+S and the lumped nodal mass

    def __init__(self, transfer, values: dict | None = None, **named):
        self.transfer = transfer
        self.values = {**(values or {}), **{k: v for k, v in named.items() if v is not None}}

    # the single-field names, as attributes
    @property
    def momentum(self):
        """p_i (n, D), or None when only the updated momentum was scattered."""
        return self.get("momentum")

    @property
    def force(self):
        """f_i (n, D), or None when P2G was asked for no force (USF)."""
        return self.get("force")

    @property
    def updated_momentum(self):
        """p_i + f_i dt, when scattered in place of p and f (:func:`jaxmpm.folds_force`)."""
        return self.get("updated_momentum")

    @property
    def mass(self):
        """The lumped nodal mass m_i (n,)."""
        return self.transfer.nodal_mass

    def replace(self, **values) -> "GridFields":
        """A copy with the named fields replaced or added."""
        return GridFields(self.transfer, {**self.values, **values})


class GridSolution(_Named):
    """Grid results of one step, by name: lumped v = p/m, a = f/m and v_tilde = v + a dt (with the
    velocity conditions imposed); v and a are None after a folded P2G (only v_tilde exists)."""

    def __init__(self, values: dict | None = None, **named):
        self.values = {**(values or {}), **named}

    @property
    def v(self):
        return self.values.get("v")

    @property
    def a(self):
        return self.values.get("a")

    @property
    def v_tilde(self):
        return self.values.get("v_tilde")


class ParticleField(eqx.Module):
    """A named per-particle field declared by a physics term: ``shape`` per particle (``()`` for a
    scalar), its ``initial`` value (a number or ``f(x) -> (N, *shape)``) and whether frames
    ``save`` it (HDF5 ``/particles/<name>``, the XDMF sidecar, ``History.fields``)."""

    name: str = eqx.field(static=True)
    shape: tuple = eqx.field(static=True, default=())
    initial: float | Callable = eqx.field(static=True, default=0.0)
    save: bool = eqx.field(static=True, default=True)
    doc: str = eqx.field(static=True, default="")

    def __check_init__(self):
        check(isinstance(self.name, str) and self.name.isidentifier(),
              f"ParticleField: name = {self.name!r} must be an identifier (it names an HDF5 dataset)")
        check(self.name not in CORE_FIELDS,
              f"ParticleField: {self.name!r} is a core particle field; choose another name")

    def shape_in(self, dim: int) -> tuple:
        """The per-particle shape in ``dim`` dimensions: an entry "D" is the grid's dimension
        (a vector field such as a force has ``shape=("D",)``)."""
        return tuple(dim if s == "D" else s for s in self.shape)

    def initial_value(self, x):
        """The initial (N, *shape) array for particles at ``x`` (N, D)."""
        n = x.shape[0]
        shape = self.shape_in(x.shape[1])
        value = self.initial(np.asarray(x)) if callable(self.initial) else self.initial
        value = jnp.asarray(value, x.dtype)
        check(value.shape in ((), (n,) + shape, shape),
              f"ParticleField {self.name!r}: initial value has shape {value.shape}; expected {(n,) + shape}")
        return jnp.broadcast_to(value, (n,) + shape)


# fields every state has (State's own attributes); a declared field may not shadow them
CORE_FIELDS = ("x", "v", "F", "mass", "volume0", "time", "step", "dissipated")
