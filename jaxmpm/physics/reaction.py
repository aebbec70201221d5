"""Reaction forces of the velocity conditions, as a diagnostic (issue 16; 003 §2.4).

On a node whose velocity a condition sets (jm.Fixed, jm.Slip, jm.Prescribed, jm.Wall), the
condition exerts the force that turns the unconstrained update into the constrained one:

    R_i dt = m_i v~_i - (p_i + f_i dt)

(v~ the updated velocity after the conditions; p + f dt the updated momentum P2G assembled).  On
free nodes R_i = 0.  :class:`Reaction` records each particle's share M_p (S R/m)_p in the field
``reaction_force`` (their sum over the particles is sum_i R_i over the nodes with mass) and the
total sum_i R_i per frame in ``History.totals["reaction"]``.  A body at rest on a fixed floor has
R = its weight.  A reader (the grid solve's last phase): it sees the grid after every force, the
momentum exchange and the conditions, whatever the order of the terms.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp

from ..core.fields import ParticleField
from ..core.registry import register_term
from ..transfer.operators import safe_divide
from .term import Term


class Reaction(Term):
    """The reaction force of the velocity conditions (module docstring)."""

    def particle_fields(self) -> tuple:
        return (ParticleField("reaction_force", shape=("D",), initial=0.0,
                              doc="the particle's share M_p (S R/m)_p of the conditions' reaction force"),)

    def read_grid(self, sim, fields, solution, dt):
        """R_i dt = m_i v~_i - (p_i + f_i dt), p and f as the conditions found them (after the
        nodal forces and the momentum exchange)."""
        m = fields.mass
        updated = fields.updated_momentum
        if updated is None:  # p + f dt
            updated = fields.momentum + fields.force * dt
        safe_dt = jnp.where(dt > 0, dt, 1.0)
        impulse = jnp.where((m > 0)[:, None], m[:, None] * solution.v_tilde - updated, 0.0)
        return {"reaction_acceleration": safe_divide(impulse, m) / safe_dt}

    def particle_action(self, sim, old, new, transfer, solution, dt):
        share = transfer.particle_share(solution["reaction_acceleration"])
        return eqx.tree_at(lambda s: s.fields, new, {**new.fields, "reaction_force": share})

    def totals(self, sim, state) -> dict:
        return {"reaction": jnp.sum(state.fields["reaction_force"], axis=0)}


register_term("reaction", Reaction, doc="reaction force of the velocity conditions, a diagnostic")
