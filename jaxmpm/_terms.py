"""Physics terms: the pieces a time step is assembled from, beside the scheme.

A term contributes up to three things to the step of 003 §2.1 (see ``jaxmpm._step``):

* ``p2g_columns(sim, state, stencil)`` -- named per-slot columns, planar (C, K, N), that P2G adds
  into the nodal field of that name in its one scatter-add (terms writing the same name are
  summed slot by slot, in the model's term order);
* ``grid_action(sim, fields, solution, dt)`` -- a change to the grid solution (default: none);
* ``particle_action(sim, old, new, transfer, solution, dt)`` -- a change to the new particle
  state after the scheme's update (default: none);

and it may declare per-particle fields (``particle_fields()``, :class:`jaxmpm.ParticleField`) that
the state then carries and runs save.  ``nodal_force(sim, state, nodal_mass)`` adds a nodal force the term
assembles itself (a surface traction).  Three hooks couple a term to the rest of the model:
``stretch(state)`` (an isotropic stretch the material sees removed from F: thermal expansion),
``time_step_limit(sim, state)`` (read by ``Simulation.stable_dt``) and ``totals(sim, state)``
(sums saved with every frame, ``History.totals``).  The terms of today's single-field engine:

* :class:`StressDivergence`  f_i += -sum_p V0_p tau_p . G_pi          (001 eq. 20, 003 eq. 2.10);
                             ``xpic=m``: of the XPIC(m)-smoothed stress (000 §3.7)
* :class:`BodyForce`         f_i += sum_p S_pi M_p b_p, b = g + b(x, t) (001 eq. 20)
* :class:`Damping`           A_damp = alpha_g S v + alpha_p V^n        (000 eq. 2.77, 001 §5.1.2);
                             the scheme places it in its update (000 eq. 3.28, 003 eq. 2.17)

Register a new term with :func:`jaxmpm.register_term` so that its parameters reach
:func:`jaxmpm.set_params`, calibration and the HDF5 attributes.
"""

from __future__ import annotations

from typing import Callable

import equinox as eqx
import jax.numpy as jnp

from ._errors import check
from ._registry import Parameter, register_term
from ._transfer import particle_force_contributions, stress_divergence_contributions
from ._validate import DAMPING


class Term(eqx.Module):
    """Base class of physics terms (see the module docstring); every hook defaults to nothing."""

    def particle_fields(self) -> tuple:
        """The :class:`jaxmpm.ParticleField` this term declares."""
        return ()

    def p2g_columns(self, sim, state, stencil) -> dict:
        """{nodal field name: per-slot contributions, planar (C, K, N) or (K, N)}."""
        return {}

    def grid_action(self, sim, fields, solution, dt):
        """The grid solution after this term (default: unchanged)."""
        return solution

    def particle_action(self, sim, old, new, transfer, solution, dt):
        """The new particle state after this term (default: unchanged)."""
        return new

    def check_fields(self, fields: dict) -> None:
        """Raise :class:`jaxmpm.InputError` when an initial field value is invalid (``sim.init``)."""

    def nodal_force(self, sim, state, nodal_mass):
        """A nodal force (field_nodes, D) the term assembles by its own means (a surface integral:
        jm.Traction), added to the scattered force; ``nodal_mass`` the step's lumped mass.  None:
        none."""
        return None

    def stretch(self, state):
        """An isotropic stretch (N,) the term imposes on the particles (thermal or moisture
        expansion), or None: the material then sees F_e = F / stretch."""
        return None

    def time_step_limit(self, sim, state):
        """The largest stable dt this term allows (e.g. conduction), or None: no limit."""
        return None

    def totals(self, sim, state) -> dict:
        """{name: scalar} sums over the particles saved with every frame (``History.totals``)."""
        return {}


class StressDivergence(Term):
    """Internal force f_i = -sum_p V0_p tau_p . G_pi (001 eq. 20, 003 eq. 2.10), tau the
    material's Kirchhoff stress.

    ``xpic=m`` (default 0: off) forms the force from the XPIC(m)-smoothed stress of 000 §3.7,
    tau~ = m S (sigma - sigma*) = S sigma(m), sigma = S+ tau the mass-weighted nodal stress and
    sigma(m) the XPIC series sum_k (-1)^(k+1) C(m,k) (S+S)^(k-1) sigma (000 eqs. 3.67-3.75; the
    seed's three nodal tensors prev/next/tilde are the recursion's term, next term and sum).  It
    removes the stress's null-space part (000 eq. 3.64) before the force extrapolation (the seed's
    eq. 3.76 variant: the particles keep their own stress, which a total-strain law recomputes
    from F every step anyway).  Cost: one more scatter (D^2 columns), m - 1 S+S and one gather."""

    xpic: int = eqx.field(static=True, default=0)

    def __init__(self, xpic: int = 0):
        check(isinstance(xpic, int) and not isinstance(xpic, bool) and xpic >= 0,
              f"StressDivergence: xpic = {xpic!r}; give the XPIC order m >= 1 of the stress smoothing, or 0 (off)")
        self.xpic = xpic

    def p2g_columns(self, sim, state, stencil):
        tau = sim.material.particle_stress(sim.elastic_deformation(state), state.material_state)
        if self.xpic:
            tau = xpic_stress(stencil, state.mass, tau, self.xpic, sim.field_nodes)
        return {"force": stress_divergence_contributions(stencil, state.volume0[:, None, None] * tau)}


def xpic_stress(stencil, mass, tau, order: int, num_nodes: int):
    """tau~_p = (S sigma(m))_p, the XPIC(m)-smoothed particle stress (000 eqs. 3.67-3.75)."""
    from ._schemes import _series
    from ._transfer import Transfer

    transfer = Transfer.build(stencil, mass, num_nodes)
    n, d = tau.shape[0], tau.shape[-1]
    sigma = transfer.s_plus(tau.reshape(n, d * d))  # 000 eq. (3.70)/(3.72): sigma_1 = S+ Sigma
    smoothed = _series(sigma, order, transfer, lambda w: w, "binomial")  # 000 eqs. (3.73)-(3.74)
    return transfer.gather(smoothed).reshape(n, d, d)  # 000 eq. (3.75)


class BodyForce(Term):
    """Body force per unit mass b = g + b(x, t) on every particle: f_i += sum_p S_pi M_p b_p
    (001 eq. 20).  ``gravity`` (D,) is a differentiable leaf; ``field`` an optional callable
    b(x, t) -> (N, D) of the current positions and time (a function or an equinox module)."""

    gravity: jnp.ndarray
    field: Callable | None = None

    def __init__(self, gravity, field: Callable | None = None):
        self.gravity = gravity
        check(field is None or callable(field), "Simulation: body_force must be a callable b(x, t) -> (N, D)")
        self.field = field

    def acceleration(self, state):
        """b_p = g + b(X_p, t), (N, D)."""
        body = jnp.broadcast_to(self.gravity.astype(state.x.dtype), state.x.shape)
        if self.field is not None:
            body = body + self.field(state.x, state.time)
        return body

    def p2g_columns(self, sim, state, stencil):
        return {"force": particle_force_contributions(stencil, state.mass[:, None] * self.acceleration(state))}


class Damping(Term):
    """Grid and particle damping alpha_g, alpha_p in 1/time (001 §5.1.2):
    A_damp = alpha_g S v + alpha_p V^n (000 eq. 2.77), subtracted in the scheme's update."""

    grid: jnp.ndarray
    particle: jnp.ndarray

    def __init__(self, grid=0.0, particle=0.0):
        self.grid = DAMPING.leaf("Damping", "grid (alpha_g)", grid)
        self.particle = DAMPING.leaf("Damping", "particle (alpha_p)", particle)

    def acceleration(self, Sv, V):
        return self.grid * Sv + self.particle * V  # 000 eq. (2.77)


def damping_acceleration(damping: Damping | None, Sv, V):
    """A_damp = alpha_g S v + alpha_p V^n (000 eq. 2.77); zero when the model has no damping."""
    return 0.0 if damping is None else damping.acceleration(Sv, V)


register_term("stress", StressDivergence, doc="internal force -sum_p V0_p tau_p . G_pi (001 eq. 20)")
register_term("body_force", BodyForce, doc="gravity and body force sum_p S_pi M_p b_p (001 eq. 20)",
              parameters=[Parameter("gravity", lambda t: t.gravity, "gravity vector", valid="finite")])
register_term("damping", Damping, doc="grid and particle damping (000 eq. 2.77)",
              parameters=[Parameter("alpha_g", lambda t: t.grid, "grid damping alpha_g (1/time)", "positive",
                                    valid=DAMPING),
                          Parameter("alpha_p", lambda t: t.particle, "particle damping alpha_p (1/time)",
                                    "positive", valid=DAMPING)])
