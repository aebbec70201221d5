"""Physics terms: the pieces a time step is assembled from, beside the scheme.

A term acts at the stages of the step of 003 §2.1 (``jaxmpm.model.step``) through hooks that all
default to "nothing":

* P2G -- ``p2g_quantities(sim, state, stencil)``: per-particle quantities tagged with their
  contraction (:mod:`jaxmpm.transfer.contractions`), by the nodal field they add to ("force",
  or a name of the term's own); the transfer layer scatters every term's quantities in one pass,
  quantities of one name summed.  ``nodal_force(sim, state, nodal)``: a nodal force the
  term assembles by its own quadrature (a traction), added to the scattered force.
* the grid solve, an ordered pipeline of phases (module ``jaxmpm.model.step``):

  1. **forces** -- ``grid_force(sim, fields, dt)``: nodal forces from the assembled grid (force-form
     damping, 001 eqs. 58-60).  Added up: the order of the terms does not matter.
  2. **exchange** -- ``exchange_momentum(sim, fields, p)``: momentum exchange between the
     velocity fields (contact, 003 eqs. 3.9-3.12), applied to p and to p + f dt (003 eq. 3.19).
     At most one term of a model exchanges momentum (checked when the model is built).  Its
     ``exchange_increments(...)`` may give XPIC/FMPM's series a hook that applies the exchange to
     every increment of the series (contact's NairnMPM rule) in place of the separate series term.
  3. **velocity conditions** -- the model's :class:`jaxmpm.Constraint`, one operator.
  4. **colliders** -- ``collide(sim, fields, v, dt, time)``: a rigid solid's condition on the updated
     velocity v_tilde at the step's start time (:class:`jaxmpm.Collider`), in term order, each on
     the one before's result; the pipeline keeps v + a dt = v_tilde (a takes the change, the
     convention of the one-sided jm.Wall) and records the term's named results.  USF's and MUSL's
     lumped velocities meet the same hook (their results dropped), as they meet the walls.
  5. **readers** -- ``read_grid(sim, fields, solution, dt)``: named results for later stages
     (reaction forces, a transport's nodal fields).  They add names; they cannot change v, a or
     v_tilde, and a name two terms add is an error.

* G2P -- ``particle_damping(sim, state, transfer, solution)``: the term's part of the damping
  acceleration the scheme subtracts (:class:`jaxmpm.schemes.ParticleDamping`);
  ``particle_action(sim, old, new, transfer, solution, dt)``: a change to the new particle state
  after the scheme's update (in term order).

Declarations: ``particle_fields()`` (:class:`jaxmpm.ParticleField`, carried by the state and
saved), ``velocity_fields()`` (> 1: the term splits the grid into that many velocity fields, each
particle on the one ``field_index(state)`` names -- multimaterial contact), ``grid_reads(sim)``
(the lumped quantities it needs apart -- "v", "a", "momentum", "force" -- so that P2G may fold
momentum and force into p + f dt only when no part needs them), ``folded_columns()`` (its P2G
fields that a symmetry plane folds like the mass).  Coupling hooks: ``stretch(state)`` (an
isotropic stretch the material sees removed: thermal expansion), ``time_step_limit(sim, state)``
and ``totals(sim, state)`` (sums saved with every frame).

Register a new term with :func:`jaxmpm.register_term` so that its parameters reach
:func:`jaxmpm.set_params`, calibration and the HDF5 attributes.
"""

from __future__ import annotations

import equinox as eqx

from ..core.registry import TERMS
from ..transfer.contractions import PerSlot


class Term(eqx.Module):
    """Base class of physics terms (see the module docstring); every hook defaults to nothing."""

    # the term's particle hooks (P2G quantities, damping, particle actions) read each particle and the
    # grid at its own nodes alone, its particle sums add over the particles, its grid hooks read the
    # assembled nodal fields only (no transfer over the particles there), and it has no nodal force of
    # its own quadrature and no exchange: the step may then run over the particles in chunks
    # (jaxmpm.model.chunks).  False (the default) keeps a term's step whole.
    local = False
    # True where everything the term knows per particle travels with the state (its fields): the run may then
    # sort the particles by cell (jaxmpm.run.sorting).  False for a term holding per-particle arrays of its own
    # in the user's particle order (the manufactured force's reference positions): sorting would hand each
    # particle another's.
    order_free = True

    # ------------------------------------------------------------------ declarations
    def particle_fields(self) -> tuple:
        """The :class:`jaxmpm.ParticleField` this term declares."""
        return ()

    def check_fields(self, fields: dict) -> None:
        """Raise :class:`jaxmpm.InputError` when an initial field value is invalid (``sim.init``)."""

    def velocity_fields(self) -> int:
        """The velocity fields per node this term needs (> 1: multimaterial mode); 1: the model's one."""
        return 1

    def field_index(self, state):
        """(N,) integer: the velocity field of each particle, when :meth:`velocity_fields` > 1."""
        return None

    def grid_reads(self, sim) -> frozenset:
        """The lumped grid quantities this term needs apart: "v", "a", "momentum", "force"."""
        return frozenset()

    def folded_columns(self) -> tuple:
        """Names of this term's P2G fields that a symmetry plane (jm.Mirror) folds like the mass
        (mass-weighted particle sums on the velocity field's nodes)."""
        return ()

    # ------------------------------------------------------------------ P2G
    def p2g_quantities(self, sim, state, stencil) -> dict:
        """{nodal field name: contraction, or a tuple of them} (:mod:`jaxmpm.transfer.contractions`)."""
        columns = self.p2g_columns(sim, state, stencil)
        return {name: PerSlot(c) for name, c in columns.items()}

    def p2g_columns(self, sim, state, stencil) -> dict:
        """Deprecated: per-slot columns, planar (C, K, N) or (K, N); use :meth:`p2g_quantities`."""
        return {}

    def nodal_force(self, sim, state, nodal):
        """A nodal force (field_nodes, D) the term assembles by its own quadrature (a surface
        integral: jm.Traction), added to the scattered force; ``nodal`` P2G's nodal sums by name
        (``nodal["mass"]``, the term's own columns).  None: none."""
        return None

    # ------------------------------------------------------------------ grid phases
    def grid_force(self, sim, fields, dt) -> dict | None:
        """Phase "forces": {"force": a nodal force added to f, other names: results kept in the
        grid solution}, or None."""
        return None

    def exchange_momentum(self, sim, fields, p):
        """Phase "exchange": (p after the exchange, the change) for nodal momenta ``p`` (field_nodes,
        D) on the velocity fields, or None when the term exchanges nothing."""
        return None

    def exchange_updated_momentum(self, sim, fields, p_plus, dt):
        """The exchange on the updated momenta p + f dt (the second application, 003 eq. 3.19);
        by default :meth:`exchange_momentum` on them.  A law whose second call differs (contact's
        extrapolated separation) overrides it; ``fields`` holds the step's p and f."""
        return self.exchange_momentum(sim, fields, p_plus)

    series_correction = False  # an exchanging term: XPIC/FMPM subtract its series term (003 eqs. 3.18, 3.22)

    def exchange_increments(self, sim, fields, p, change, dt, updated: bool):
        """The exchange on the increments of the XPIC/FMPM series, an object with ``initial()`` and
        ``adjust(increment, carry) -> (change, carry)`` that :func:`jaxmpm.transfer.series.exchange_increments`
        calls on every increment (contact's ``series="incremental"``, NairnMPM's rule), cached from the
        exchange that took momenta ``p`` to ``p + change`` (``updated``: the second application, on
        p + f dt); or None (default): the series subtracts the exchange's series term instead, with
        ``series_correction`` (003 eqs. 3.18, 3.22)."""
        return None

    def in_conventions(self, conventions: str) -> "Term":
        """The term in another code's rules (``Simulation(conventions=...)``): itself by default."""
        return self

    def collide(self, sim, fields, v, dt, time):
        """Phase "colliders": (the nodal velocity ``v`` (field_nodes, D) after this term's rigid
        solid acts on it at ``time``, {name: array} results), or None (the default): no solid."""
        return None

    def read_grid(self, sim, fields, solution, dt) -> dict:
        """Phase "readers": {name: array} added to the grid solution."""
        return {}

    # ------------------------------------------------------------------ G2P
    def particle_damping(self, sim, state, transfer, solution):
        """This term's damping of the particle update (:class:`jaxmpm.schemes.ParticleDamping`), or None."""
        return None

    def particle_action(self, sim, old, new, transfer, solution, dt):
        """The new particle state after this term (default: unchanged)."""
        return new

    # ------------------------------------------------------------------ coupling
    def stretch(self, state):
        """An isotropic stretch (N,) the term imposes on the particles (thermal or moisture
        expansion), or None: the material then sees F_e = F / stretch."""
        return None

    def time_step_limit(self, sim, state):
        """The largest stable dt this term allows (e.g. conduction), or None: no limit.  Written in
        jnp: :meth:`jaxmpm.Simulation.stable_dt` evaluates it inside one compiled program."""
        return None

    def totals(self, sim, state) -> dict:
        """{name: scalar} sums over the particles saved with every frame (``History.totals``)."""
        return {}

    def attributes(self) -> dict:
        """{name: str or number}: how the term is set up, written as HDF5 root attributes (its
        float parameters are written from the registry)."""
        return {}

    # ------------------------------------------------------------------ deprecated hooks
    def grid_action(self, sim, fields, solution, dt):
        """Deprecated: a whole-solution rewrite, which composed by overwriting (issue 27).  A term
        that still overrides it runs it in the readers phase; use the phase hooks instead."""
        return solution


TERMS.base = Term  # register_term accepts its subclasses only


def overrides(term, hook: str) -> bool:
    """Whether ``term``'s class defines ``hook`` itself (not the :class:`Term` default)."""
    return getattr(type(term), hook) is not getattr(Term, hook)
