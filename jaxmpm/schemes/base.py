"""What every particle-update scheme is: the :class:`Scheme` interface and its result.

Every scheme is the generic update of 000 §2.3 / 003 §2.3,

    V^{n+1} = V^n + A dt,      X^{n+1} = X^n + VV dt + 1/2 A dt^2,

each family in its own module of this package (``xpic``: XPIC/FLIP/PIC; ``fmpm``: FMPM;
``affine``: APIC and TPIC; ``rpic``: RPIC) and registered with :func:`jaxmpm.register_scheme`.  A
scheme owns its per-particle state (``State.scheme_state``: APIC's B_p, TPIC's grad v_p, RPIC's
L_p) through :meth:`Scheme.initial_state` and :meth:`Scheme.next_state`.

Damping reaches the update through :class:`ParticleDamping`, the acceleration
A_damp = alpha_g S v + alpha_p V^n every scheme subtracts (000 eq. 2.77): the model resolves the
step's damping from its terms (``jm.Damping`` and any term with a ``particle_damping`` hook) and
passes :data:`NO_DAMPING` when there is none, so a scheme never asks whether damping exists.
"""

from __future__ import annotations

import abc

import equinox as eqx
import jax.numpy as jnp

from ..core.errors import check
from ..core.measures import angular_momentum
from ..core.registry import SCHEMES
from ..core.state import with_scheme_state
from ..core.validate import compiled_when_concrete
from ..transfer.contractions import Weighted
from ..transfer.operators import Transfer


class ParticleDamping(eqx.Module):
    """The damping one step applies in the particle update: A_damp, subtracted from the
    acceleration (000 eq. 2.77; 001 §5.1.2-5.3).  ``acts``: False when A_damp = 0 (a scheme may
    then skip it); ``reads_grid_velocity``: whether :meth:`acceleration` uses S v (a scheme that
    reads only v_tilde gathers S v only then)."""

    acts = True
    reads_grid_velocity = True

    @abc.abstractmethod
    def acceleration(self, Sv, V):
        """A_damp per particle from the extrapolated grid velocity S v and V^n (both (N, D))."""


class NoDamping(ParticleDamping):
    """No damping: A_damp = 0."""

    acts = False
    reads_grid_velocity = False

    def acceleration(self, Sv, V):
        return 0.0


NO_DAMPING = NoDamping()


class RateDamping(ParticleDamping):
    """A_damp = alpha_g u + alpha_p V^n with u = S v, or the extrapolated velocity p_{g->p}/m_{g->p}
    (``extrapolated``, 001 eqs. 72-73, 76) when given; ``grid`` None: no grid part (it acts on the
    nodal force instead, 001 eqs. 61-62).  Rates are scalars or per particle (N, 1) (001 eqs. 30, 107)."""

    grid: jnp.ndarray | None
    particle: jnp.ndarray
    extrapolated: jnp.ndarray | None = None

    @property
    def reads_grid_velocity(self) -> bool:
        return self.grid is not None and self.extrapolated is None

    def acceleration(self, Sv, V):
        """001 eqs. (33), (40), (107); 000 eq. (2.77)."""
        particle = self.particle * V
        if self.grid is None:
            return particle
        return self.grid * (Sv if self.extrapolated is None else self.extrapolated) + particle


class CombinedDamping(ParticleDamping):
    """The sum of several terms' damping accelerations."""

    parts: tuple

    @property
    def reads_grid_velocity(self) -> bool:
        return any(p.reads_grid_velocity for p in self.parts)

    def acceleration(self, Sv, V):
        total = self.parts[0].acceleration(Sv, V)
        for part in self.parts[1:]:
            total = total + part.acceleration(Sv, V)
        return total


def combine_damping(parts) -> ParticleDamping:
    """One :class:`ParticleDamping` for the terms' contributions (None entries dropped)."""
    parts = tuple(p for p in parts if p is not None)
    if not parts:
        return NO_DAMPING
    return parts[0] if len(parts) == 1 else CombinedDamping(parts)


class ParticleUpdate(eqx.Module):
    """What a scheme's ``update`` returns: the particles' new velocities and positions, the grid
    velocity of a USL- strain update and the energy the update dissipated.

    Args:
        velocity: V^{n+1}, (N, D).
        position: X^{n+1}, (N, D).
        strain_velocity: the nodal velocity the USL- (and USAVG-) strain update uses, (n, D).
        dissipated: the energy the update removed this step relative to FLIP (a scalar;
            :func:`dissipated_energy`, 000 eq. 2.43).
    """

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
    ``update(V, X, transfer, constraint, grid, damping, dt) -> ParticleUpdate`` (``damping`` a
    :class:`ParticleDamping`; ``grid`` the :class:`jaxmpm.GridSolution`) and may override the
    hooks below."""

    # the update reads the lumped v and a (not only v_tilde = v + a dt); schemes that read only
    # v_tilde (APIC, TPIC) let P2G scatter p + f dt in place of p and f when nothing else needs them
    uses_lumped_velocity = True
    # the update reads the grid only at each particle's own stencil nodes (gathers; no S+ S series over
    # all particles): the step may then run over the particles in chunks (jaxmpm.model.chunks)
    local_update = False

    @abc.abstractmethod
    def update(self, V, X, transfer: Transfer, constraint, grid, damping: ParticleDamping, dt) -> ParticleUpdate:
        """The particle update of one step (000 eq. 2.22 / 003 eq. 2.17 in the scheme's form)."""

    def in_conventions(self, conventions: str) -> "Scheme":
        """The scheme in another code's conventions (``Simulation(conventions=...)``): "jaxmpm"
        returns it unchanged; "nairnmpm" sets the options in which NairnMPM 19.0 differs
        (:meth:`jaxmpm.XPIC.in_conventions`).  Schemes NairnMPM does not have, or computes alike,
        return themselves."""
        return self

    def time_step_factor(self) -> float:
        """The factor the particle update puts on the CFL limit h / max_p(c + |V_p|): 1 (the
        default) for an update whose velocities are the lumped-mass ones; below 1 where the update
        accelerates the particles through another mass matrix (FMPM(k): :meth:`jaxmpm.FMPM.time_step_factor`).
        :meth:`jaxmpm.Simulation.time_step_limits` lists it as the scheme's own limit."""
        return 1.0

    def strain_grid_velocity(self, v, transfer: Transfer, constraint, exchange_dv=None):
        """Grid velocity used for the strain update, from lumped velocities (USF, MUSL: after the
        momentum exchange and the conditions; ``exchange_dv`` the exchange's change Dp/m, for a
        scheme whose strain velocity is a series, 003 eqs. 3.16-3.22)."""
        return v

    def momentum_contributions(self, stencil, state):
        """The P2G column of the nodal momentum p_i = sum_p S_pi M_p V_p (003 eq. 2.1): a
        contraction or a tuple of them (:mod:`jaxmpm.transfer.contractions`); APIC/TPIC/RPIC add
        their affine part.  P2G scatters it together with the mass and the force."""
        return Weighted(state.mass[:, None] * state.v)

    def momentum(self, transfer: Transfer, state):
        """Nodal momentum p_i (one scatter of :meth:`momentum_contributions`)."""
        return transfer.p2g({"momentum": self.momentum_contributions(transfer.stencil, state)})["momentum"]

    def angular_momentum(self, state):
        """sum_p X_p x M_p V_p (000 ch. 5); APIC adds its particle term (002 def. 5.1)."""
        return angular_momentum(state)

    def initial_state(self, particles):
        """The scheme's per-particle state at the start (APIC's B_p, TPIC's grad v_p); None here."""
        return None

    def next_state(self, state, update: ParticleUpdate, transfer: Transfer, grid):
        """The scheme's per-particle state after the step (``state`` is the start of the step)."""
        return state.scheme_state

    def state_for_velocity_gradient(self, stencil, state, L):
        """The scheme state of particles moving with the velocity field of gradient L (N, D, D)
        (:func:`with_velocity_gradient`); the scheme's state unchanged by default."""
        return state.scheme_state


SCHEMES.base = Scheme  # register_scheme accepts its subclasses only


def with_velocity_gradient(sim, state, gradient):
    """``state`` with the scheme state set for a particle velocity field of gradient ``gradient``
    ((D, D) or (N, D, D)): B_p = L_p D_p under APIC (D_p from the stencil), grad v_p = L_p under
    TPIC, and under RPIC L_p = K_p omega with omega the rotation of the skew part of L_p (the rigid
    part, 002 prop. 4.1); unchanged for schemes without such a state
    (:meth:`Scheme.state_for_velocity_gradient`).

    Args:
        sim: the :class:`jaxmpm.Simulation` (its scheme, shape and grid).
        state: the :class:`jaxmpm.State`, e.g. from ``sim.init``.
        gradient: the velocity gradient L, (D, D) for all particles or (N, D, D), in the grid's
            coordinates.
    """
    d = state.x.shape[-1]  # the grid's dimension (F is 3x3 on an r-z grid; the affine state is d x d)
    L = jnp.asarray(gradient, state.x.dtype)
    check(L.shape[-2:] == (d, d), f"with_velocity_gradient: gradient has shape {L.shape}; give a ({d}, {d}) "
          f"matrix or one per particle ({state.x.shape[0]}, {d}, {d}), in the grid's coordinates")
    if type(sim.scheme).state_for_velocity_gradient is Scheme.state_for_velocity_gradient:
        return state  # no scheme state of this kind: nothing to set
    L = jnp.broadcast_to(L, (state.x.shape[0], d, d))
    # concrete inputs (a scene's set-up): one compiled program, instead of the stencil's forty small
    # ones op by op on a first call
    return with_scheme_state(state, _scheme_state_for(sim, state, L))


@compiled_when_concrete
def _scheme_state_for(sim, state, L):
    stencil = sim.shape.stencil(sim.grid, state.x)
    return sim.scheme.state_for_velocity_gradient(stencil, state, L)
