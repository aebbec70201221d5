"""Named float parameters of a :class:`Simulation`, for calibration and ensembles.

``set_params(sim, beta=0.5, alpha_g=0.1)`` returns a new simulation; ``get_params(sim, "beta")``
reads them.  The names come from the registry (``jaxmpm.core.registry``): every registered scheme,
material, shape and term declares its parameters, each a path to an array leaf, so ``jax.grad``
and ``jax.vmap`` reach it.  :data:`PARAMETERS` lists them all.

Names are scoped by the part that owns them: ``"material.E"``, ``"contact.friction"``,
``"damping.alpha_g"`` (terms by their registered name).  The bare name (``E``, ``friction``) works
wherever one part of the model has it; where two do (a material's and the contact's friction),
the bare name is an error that names the scoped ones: ``set_params(sim, **{"contact.friction": 0.3})``.
"""

from __future__ import annotations

from collections.abc import Mapping

import jax.numpy as jnp
import numpy as np

from .errors import check
from .registry import TERMS, all_parameters, owner_registry, parameter_part, resolve_parameter
from .validate import fail, traced


class _ParameterTable(Mapping):
    """{name: (where(sim) -> leaf, description)} over every registered parameter, by its bare name
    (live: a part registered later shows up); a scoped name ("contact.friction") is looked up too."""

    def __getitem__(self, name):
        p = all_parameters()[name]
        return (lambda sim: _where(sim, name)(sim)), p.doc

    def __contains__(self, name):
        return name in all_parameters()

    def __iter__(self):
        return iter(_bare_names())

    def __len__(self):
        return len(_bare_names())


def _bare_names() -> list:
    return [name for name in all_parameters() if "." not in name]


PARAMETERS = _ParameterTable()


def _with_owner(sim, name):
    """``sim`` itself, or -- when ``name`` belongs to a term the model does not have, e.g. damping
    in a model built with ``damping=False`` -- a copy with that term added at its neutral
    default, so that the parameter can be read, set and differentiated."""
    if resolve_parameter(sim, name) is not None:
        return sim
    owner = owner_registry(name)
    if owner is not None and owner[0] is TERMS:
        for cls in owner[2]:
            try:
                return sim.with_term(cls())
            except TypeError:  # needs arguments: no neutral default
                continue
    return sim


def _where(sim, name):
    known = all_parameters()
    # a model made with a class since replaced under its name keeps that class's parameters
    check(name in known or resolve_parameter(sim, name) is not None,
          f"unknown parameter {name!r}; choose one of {', '.join(k for k in known if '.' not in k)} "
          "(or scoped, e.g. 'material.E')")
    found = resolve_parameter(sim, name)
    if found is None:
        from ..core.registry import sim_parameters

        check(False, f"parameter {name!r} does not exist for scheme {type(sim.scheme).__name__} / "
                     f"material {type(sim.material).__name__}; this model has {', '.join(sim_parameters(sim))}")
    return found[0]


def get_params(sim, *names) -> dict:
    """{name: value} for the named parameters: ``get_params(sim, "beta", "E")``.

    Args:
        sim: the :class:`jaxmpm.Simulation` to read.
        *names: parameter names, bare (``"E"``) or scoped (``"material.E"``, ``"contact.friction"``);
            :data:`jaxmpm.PARAMETERS` lists them.  A term's parameter reads as its neutral default
            when the model has no such term (damping in a model built with ``damping=False``).
    """
    out = {}
    for n in names:
        check(isinstance(n, str), f"get_params: {n!r} is not a parameter name; name each as a string, e.g. "
                                  "get_params(sim, 'E', 'beta') (jm.PARAMETERS lists them)")
        s = _with_owner(sim, n)
        out[n] = _where(s, n)(s)
    return out


def check_value(sim, name, value, owner: str = "set_params", label: str | None = None):
    """Raise InputError unless a concrete ``value`` of parameter ``name`` lies in the range its
    registration declares (``Parameter.valid``) and, for a vector leaf such as gravity, has the
    shape of the model's leaf.  A traced value passes unchecked."""
    where, p = resolve_parameter(sim, name)
    _check_acts(sim, name, p, owner, label)
    old_shape = np.shape(where(sim))
    # a vector leaf (gravity) takes one value per grid axis, traced values too (their shapes are known); a
    # number only where it has one axis: in 2D a number had set every axis to it, and an ensemble's batch of one
    # vector [0, -9.8] had run as two members
    allowed = {old_shape, ()} if old_shape == (1,) else {old_shape}
    if old_shape and np.shape(value) not in allowed:
        batch = f"; an ensemble takes one per member: shape (members, {old_shape[0]})" if "ensemble" in owner else ""
        fail(owner, f"{label or name} has shape {np.shape(value)}; this model's {name} has shape {old_shape} "
                    f"(one value per grid axis{batch})")
    if traced(value):
        return
    p.check(owner, value, label or name)


def _check_acts(sim, name, p, owner: str, label: str | None) -> None:
    """Raise InputError where parameter ``name`` (registered as ``p``) does not act in this model
    (``Parameter.acts``: e.g. a contact's friction under the stick law), whatever its value, traced too: its
    gradient would be 0."""
    if p.acts is None:
        return
    reason = p.acts(parameter_part(sim, name))
    check(reason is None, f"{owner}: {label or name} {reason}")


def set_params(sim, **values):
    """A copy of ``sim`` with the named parameters replaced: ``set_params(sim, beta=0.5, E=2e6)``.

    Args:
        sim: the :class:`jaxmpm.Simulation` to copy.
        **values: ``name=value`` for each parameter, by bare or scoped name (scoped ones through
            ``**{"contact.friction": 0.3}``).  Values may be traced (``jax.grad``, ``jax.vmap``);
            concrete ones are checked against the parameter's valid range (nu in (-1, 0.5), beta
            in [0, 1], ...).  A term the model lacks is added at its neutral default first.
    """
    import equinox as eqx

    for name, value in values.items():
        sim = _with_owner(sim, name)
        where = _where(sim, name)
        check_value(sim, name, value)
        old = where(sim)
        sim = eqx.tree_at(where, sim, jnp.asarray(value, dtype=jnp.result_type(old)))
    check_material(sim, "set_params")
    return sim


def check_material(sim, owner: str) -> None:
    """The conditions the material's parameters must meet together (``Material.check_parameters``: e.g.
    Drucker-Prager's dilatancy angle <= friction angle), checked where they are concrete."""
    checker = getattr(sim.material, "check_parameters", None)
    if checker is not None:
        checker(owner)


def default_bounds(name, sim=None):
    """The calibration bounds a registered parameter declares (None if unknown or unbounded); with
    ``sim``, of the part of that model the name resolves to."""
    found = None if sim is None else resolve_parameter(sim, name)
    p = found[1] if found is not None else all_parameters().get(name)
    return None if p is None else p.bounds
