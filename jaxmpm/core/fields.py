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

from .errors import InputError, check
from .validate import concrete, show, traced

_DECLARED = object()  # ParticleField.initial_value: no value given, the declared one


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
    """What P2G puts on the grid, by name, with the step's :class:`~jaxmpm.Transfer`.

    Args:
        transfer: the step's :class:`jaxmpm.Transfer` (S, S+, S+S and the lumped nodal mass).
        values: ``{name: nodal array}``, e.g. ``{"momentum": p_i (n, D), "force": f_i (n, D)}``;
            None (the default) for none.
        **named: more fields by keyword (``momentum=p``); one given as None is left out.
    """

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
    velocity conditions imposed); v and a are None after a folded P2G (only v_tilde exists).

    Args:
        values: ``{name: nodal array}`` (``"v"``, ``"a"``, ``"v_tilde"``, the terms' results);
            None (the default) for none.
        **named: more results by keyword (``v=..., v_tilde=...``).
    """

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
    """A named per-particle field declared by a physics term (``Term.particle_fields``), carried in
    ``State.fields[name]``.

    Args:
        name: the field's name, an identifier that is not a core field (x, v, F, mass, volume0,
            time, step, dissipated); it names the HDF5 dataset ``/particles/<name>``.
        shape: the shape per particle: ``()`` (the default) for a scalar; an entry ``"D"`` is the
            grid's dimension (a force: ``("D",)``).
        initial: the initial value: a number (default 0.0) or ``f(x) -> (N, *shape)`` of the
            positions x (N, D).  ``Simulation.init(particles, fields={name: ...})`` overrides it.
        save: whether saved frames keep it (HDF5 ``/particles/<name>``, the XDMF sidecar,
            ``History.fields``); default True.
        doc: a one-line description, for the reader (default "").
    """

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

    def initial_value(self, x, value=_DECLARED, where: str | None = None):
        """The initial (N, *shape) array for particles at ``x`` (N, D), in the positions' dtype: the
        declared ``initial``, or ``value`` given in its place (``Simulation.init``'s ``fields=``) --
        a number, one value for every particle (``shape``), one per particle (N, *shape), or
        ``f(x)`` returning one of those for the positions.  Anything else -- text, complex or
        non-finite numbers, another shape, a callable that raises -- is an InputError naming
        ``where`` (default: this field's ``initial``)."""
        if value is _DECLARED:
            value, where = self.initial, f"ParticleField {self.name!r}: initial"
        n = x.shape[0]
        shape = self.shape_in(x.shape[1])
        expected = f"{(n,) + shape} (one value per particle)" + (f", {shape} (one for all)" if shape else "")
        if callable(value):
            positions = concrete(x)
            try:
                value = value(x if positions is None else positions)
            except Exception as err:  # the user's function: its failure, named, in one line
                reason = " ".join(str(err).split())[:120]
                raise InputError(f"{where}: calling it on the positions x, shape {tuple(x.shape)}, raised "
                                 f"{type(err).__name__}{': ' + reason if reason else ''}; give f(x) -> an array of "
                                 f"shape {expected} or a number") from None
            where = f"{where}(x)"
        if traced(value):  # computed under jit/grad/vmap: the shape only
            value = jnp.asarray(value)
            check(value.shape in ((), (n,) + shape, shape),
                  f"{where} has shape {value.shape}; give an array of shape {expected} or a number")
            return jnp.broadcast_to(value.astype(x.dtype), (n,) + shape)
        check(value is not None and not isinstance(value, (str, bytes, dict)),
              f"{where} = {show(value)}: give real numbers, an array of shape {expected}, or a number")
        try:
            array = np.asarray(value)
        except (ValueError, TypeError):  # ragged lists
            array = np.asarray(None)
        check(array.dtype.kind in "biuf", f"{where} = {show(value)} has dtype {array.dtype}; give real numbers "
                                          f"(complex, text and objects are not field values), shape {expected}")
        check(array.shape in ((), (n,) + shape, shape),
              f"{where} has shape {array.shape}; give an array of shape {expected} or a number")
        finite = np.isfinite(array)
        if not finite.all():
            first = f" (first at index {tuple(int(i) for i in np.argwhere(~finite)[0])})" if array.ndim else ""
            check(False, f"{where} holds {int(array.size - finite.sum())} NaN or infinite value(s){first}; give "
                         "finite numbers")
        return jnp.broadcast_to(jnp.asarray(array, x.dtype), (n,) + shape)


# fields every state has (State's own attributes); a declared field may not shadow them
CORE_FIELDS = ("x", "v", "F", "mass", "volume0", "time", "step", "dissipated")
