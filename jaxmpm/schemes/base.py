"""What every particle-update scheme is: the :class:`Scheme` interface and its result.

Every scheme is the generic update of 000 §2.3 / 003 §2.3,

    V^{n+1} = V^n + A dt,      X^{n+1} = X^n + VV dt + 1/2 A dt^2,

written in its own module (``_schemes``: XPIC/FLIP/PIC and FMPM; ``_affine``: APIC, TPIC and
RPIC) and registered with :func:`jaxmpm.register_scheme`.  A scheme owns its per-particle state
(``State.scheme_state``: APIC's B_p, TPIC's grad v_p, RPIC's L_p) through
:meth:`Scheme.initial_state` and :meth:`Scheme.next_state`.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp

from ..core.measures import angular_momentum
from ..transfer.shapes import StencilBase as Stencil
from ..transfer.operators import Transfer, momentum_contributions, scatter_planar


class ParticleUpdate(eqx.Module):
    velocity: jnp.ndarray  # V^{n+1}
    position: jnp.ndarray  # X^{n+1}
    strain_velocity: jnp.ndarray  # grid velocity for a USL- strain update
    dissipated: jnp.ndarray  # energy dissipated by the update this step (scalar)


def flip_energy_increment(Sa, Sv, dt):
    """(S a dt) . (S v + S a dt / 2) per particle: the FLIP update's energy change per unit mass
    (000 eq. 2.42), the reference :func:`dissipated_energy` measures against."""
    return jnp.sum((Sa * dt) * (Sv + 0.5 * Sa * dt), axis=-1)


def dissipated_energy(mass, Sa, Sv, dV, dX, dt):
    """Energy removed by a particle update relative to the non-dissipative FLIP update.

    From the generic form (000 eq. 2.41), Delta E_p = M_p (A dt) . (VV + A dt / 2) with
    A dt = Delta V and VV dt = Delta X - Delta V dt / 2, so Delta E_p = M_p Delta V . Delta X / dt.
    The FLIP reference is M_p (S a dt) . (S v + S a dt / 2) (000 eq. 2.42); their difference is
    000 eq. (2.43), which reduces to 000 eq. (2.44) when VV = S v.  Valid for every position update,
    including FMPM's VV = V^n (003 eq. 2.26).
    """
    safe_dt = jnp.where(dt > 0, dt, 1.0)
    flip = flip_energy_increment(Sa, Sv, dt)
    actual = jnp.sum(dV * dX, axis=-1) / safe_dt
    return jnp.sum(mass * (flip - actual))


class Scheme(eqx.Module):
    """Base class of particle updates.  A subclass defines
    ``update(V, X, transfer, constraint, grid, damping, dt) -> ParticleUpdate`` and may override
    the hooks below."""

    # the update reads the lumped v and a (not only v_tilde = v + a dt); schemes that read only
    # v_tilde (APIC, TPIC) let P2G scatter p + f dt in place of p and f when there is no damping
    uses_lumped_velocity = True

    def update(self, V, X, transfer: Transfer, constraint, grid, damping, dt) -> ParticleUpdate:
        raise NotImplementedError(f"{type(self).__name__} must define update(...)")

    def strain_grid_velocity(self, v, transfer: Transfer, constraint):
        """Grid velocity used for the strain update, from lumped velocities (USF, MUSL)."""
        return v

    def momentum_contributions(self, stencil: Stencil, state):
        """S_pi M_p V_p per stencil slot, planar (D, K, N), summed over p into p_i (003 eq. 2.1);
        APIC/TPIC add their affine terms.  P2G scatters it together with the mass and the force."""
        return momentum_contributions(stencil, state.mass, state.v)

    def momentum(self, transfer: Transfer, state):
        """Nodal momentum p_i (one scatter of :meth:`momentum_contributions`)."""
        return scatter_planar(transfer.stencil.index, self.momentum_contributions(transfer.stencil, state),
                              transfer.num_nodes)

    def angular_momentum(self, state):
        """sum_p X_p x M_p V_p (000 ch. 5); APIC adds its particle term (002 def. 5.1)."""
        return angular_momentum(state)

    def initial_state(self, particles):
        """The scheme's per-particle state at the start (APIC's B_p, TPIC's grad v_p); None here."""
        return None

    def next_state(self, state, update: ParticleUpdate, transfer: Transfer, grid):
        """The scheme's per-particle state after the step (``state`` is the start of the step)."""
        return state.scheme_state
