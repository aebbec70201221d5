"""Gravity and body forces, f_i += sum_p S_pi M_p b_p (001 eq. 20)."""

from __future__ import annotations

from typing import Callable

import jax.numpy as jnp

from ..core.errors import check
from ..core.registry import Parameter, register_term
from ..core.validate import FINITE
from ..transfer.backend import materialise
from ..transfer.contractions import Weighted
from .term import Term


class BodyForce(Term):
    """Body force per unit mass b = g + b(x, t) on every particle: f_i += sum_p S_pi M_p b_p
    (001 eq. 20).  A :class:`jaxmpm.Simulation` adds one from its ``gravity`` and ``body_force``.

    Args:
        gravity: the uniform acceleration g, (D,) (a differentiable leaf, the registered
            parameter ``gravity``).
        field: an optional callable b(x, t) -> (N, D) of the current positions and time (a
            function or an equinox module); None (the default): gravity alone.
    """

    gravity: jnp.ndarray
    field: Callable | None = None

    @property
    def local(self) -> bool:
        """M_p b(x_p, t) per particle (jaxmpm.model.chunks), unless the field holds per-particle arrays of its
        own (``field.holds_particles``, :class:`jaxmpm.scenes.manufactured.ManufacturedForce`): a chunk's
        positions would not match them."""
        return not getattr(self.field, "holds_particles", False)

    @property
    def order_free(self) -> bool:
        """Whether the particles may be sorted (Term.order_free): not where the field holds per-particle arrays
        in the user's order."""
        return self.local

    def __init__(self, gravity, field: Callable | None = None):
        example = "the acceleration's D components, e.g. (0.0, -9.81)"
        self.gravity = FINITE.leaf("BodyForce", "gravity", gravity, fix=example)
        check(self.gravity.ndim == 1,
              f"BodyForce: gravity must be a vector of the grid's D components, e.g. (0.0, -9.81); "
              f"got shape {self.gravity.shape}")
        check(field is None or callable(field), "Simulation: body_force must be a callable b(x, t) -> (N, D)")
        self.field = field

    def acceleration(self, state):
        """b_p = g + b(X_p, t), (N, D)."""
        body = jnp.broadcast_to(self.gravity.astype(state.x.dtype), state.x.shape)
        if self.field is not None:
            body = body + self.field(state.x, state.time)
        return body

    def p2g_quantities(self, sim, state, stencil):
        return {"force": Weighted(materialise(state.mass[:, None] * self.acceleration(state)))}


register_term("body_force", BodyForce, doc="gravity and body force sum_p S_pi M_p b_p (001 eq. 20)",
              parameters=[Parameter("gravity", lambda t: t.gravity, "gravity vector", valid="finite")])
