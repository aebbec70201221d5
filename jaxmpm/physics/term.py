"""Physics terms: the pieces a time step is assembled from, beside the scheme.

A term contributes up to three things to the step of 003 §2.1 (see ``jaxmpm.model.step``):

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
                             the scheme places it in its update (000 eq. 3.28, 003 eq. 2.17);
                             variants: the momentum approach (001 §5.2.2), grid damping in the
                             nodal force (001 eqs. 58-60), alpha(t) and alpha(t, x_p) (001 §5.3)

Register a new term with :func:`jaxmpm.register_term` so that its parameters reach
:func:`jaxmpm.set_params`, calibration and the HDF5 attributes.
"""

from __future__ import annotations

from typing import Callable

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ..core.errors import check
from ..core.fields import GridSolution
from ..core.registry import Parameter, register_term
from ..schemes.base import flip_energy_increment
from ..transfer.operators import particle_force_contributions, safe_divide, stress_divergence_contributions
from ..core.validate import DAMPING, concrete


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
    from F every step anyway).  Cost: one more scatter (D^2 columns), m - 1 S+S and one gather.

    On an axisymmetric grid (001 §7) tau is 3x3 in (r, z, theta) and the force is 001 eq. 120,
    f_i = -sum_p V0_p (tau_rz . G_pi + tau_thth T_pi e_r), V0_p per radian: see
    :func:`axisymmetric_stress_divergence`."""

    xpic: int = eqx.field(static=True, default=0)

    def __init__(self, xpic: int = 0):
        check(isinstance(xpic, int) and not isinstance(xpic, bool) and xpic >= 0,
              f"StressDivergence: xpic = {xpic!r}; give the XPIC order m >= 1 of the stress smoothing, or 0 (off)")
        self.xpic = xpic

    def p2g_columns(self, sim, state, stencil):
        tau = sim.material.particle_stress(sim.elastic_deformation(state), state.material_state)
        if self.xpic:
            check(sim.constraint(tau.dtype).mirror is None,
                  "StressDivergence(xpic=m): the stress smoothing does not fold in a jm.Mirror's images; "
                  "use xpic=0 with mirror planes")
            tau = xpic_stress(stencil, state.mass, tau, self.xpic, sim.field_nodes)
        if sim.grid.axisymmetric:
            return {"force": axisymmetric_stress_divergence(stencil, state.volume0, tau)}
        return {"force": stress_divergence_contributions(stencil, state.volume0[:, None, None] * tau)}


def axisymmetric_stress_divergence(stencil, volume0, tau):
    """Per-slot internal force of 001 eq. 120 (with eq. 118, m_p/rho_0 tau = V0_p tau), planar (2, K, N):
    -V0_p [tau_rr tau_rz; tau_rz tau_zz] . G_pi - V0_p (tau_thth, 0) T_pi, G_pi the r-weighted
    gradient (001 eq. 115), T_pi the hoop shape function (001 eq. 116), tau (N, 3, 3) in
    (r, z, theta) order."""
    from ..transfer.shapes import AxisymmetricStencil

    check(isinstance(stencil, AxisymmetricStencil),
          "StressDivergence: an axisymmetric grid needs the axisymmetric stencil of a jm shape function "
          "(contact's multimaterial stencil has no hoop term: run axisymmetric models without jm.Contact)")
    planar = stress_divergence_contributions(stencil, volume0[:, None, None] * tau[:, :2, :2])  # 001 eq. (120)
    hoop = jnp.stack([-volume0 * tau[:, 2, 2], jnp.zeros_like(volume0)], axis=-1)  # (N, 2)
    return planar + particle_force_contributions(stencil.hoop_view(), hoop)  # - V0 tau_thth T_pi e_r


def xpic_stress(stencil, mass, tau, order: int, num_nodes: int):
    """tau~_p = (S sigma(m))_p, the XPIC(m)-smoothed particle stress (000 eqs. 3.67-3.75)."""
    from ..schemes.xpic import _series
    from ..transfer.operators import Transfer

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


DAMPING_APPROACHES = ("velocity", "momentum", "force")


class Schedule(eqx.Module):
    """A piecewise-linear time factor s(t) through the points (``times``, ``factors``), held
    constant beyond the ends; ``factors`` are differentiable leaves (a calibrated schedule)."""

    times: jnp.ndarray
    factors: jnp.ndarray

    def __init__(self, times, factors):
        t = np.asarray(times, dtype=float)
        f = np.asarray(factors, dtype=float) if concrete(factors) is not None else None
        check(t.ndim == 1 and t.size >= 1 and np.all(np.isfinite(t)) and np.all(np.diff(t) > 0),
              f"Damping: schedule times = {t.tolist()!r}; give a 1D array of increasing finite times")
        check(np.shape(factors) == t.shape,
              f"Damping: schedule has {t.size} times but factors of shape {np.shape(factors)}; give one factor per time")
        check(f is None or bool(np.all(np.isfinite(f)) and np.all(f >= 0)),
              "Damping: schedule factors must be finite and >= 0 (alpha(t) = alpha s(t) is a damping rate)")
        self.times = jnp.asarray(t, dtype=jnp.result_type(float))
        self.factors = jnp.asarray(factors, dtype=jnp.result_type(float))

    def __call__(self, t):
        return jnp.interp(t, self.times.astype(t.dtype), self.factors.astype(t.dtype))


class Damping(Term):
    """Grid and particle damping alpha_g, alpha_p in 1/time (001 §5.1.2):
    A_damp = alpha_g S v + alpha_p V^n (000 eq. 2.77), subtracted in the scheme's update.

    Variants (001 §5.1.2-5.3), all differentiable in ``grid``/``particle`` (and a schedule's factors):

    * ``approach="velocity"`` (default): the above, damping in the particle update (001 eqs. 31-33).
    * ``approach="momentum"``: grid damping proportional to the grid momentum p_i, extrapolated as
      momentum (001 §5.2.2, eqs. 72-73): A_damp = alpha_g p_{g->p}/m_{g->p} + alpha_p V^n with
      p_{g->p} = sum_i S_ip p_i and m_{g->p} = sum_i S_ip m_i (the velocity of eqs. 67, 76).
    * ``approach="force"``: grid damping applied to the nodal force, f** = f - alpha_g p_i, so
      a** = a - alpha_g v_i and v~** = v~ - alpha_g v_i dt (001 eqs. 58-60, 97-98); the particle
      update then damps only alpha_p V^n (001 eqs. 61-65).  Every later use of a and v~ (FMPM's
      series, APIC's B_p, the USL strain update, contact) sees the damped grid.
    * ``schedule``: alpha(t) = alpha s(t) for both rates (001 eq. 30, "may evolve in time"), s a
      callable s(t) -> scalar or a pair (times, factors) for a piecewise-linear :class:`Schedule`;
      evaluated at the step's start t^n.
    * ``region``: alpha(x) = alpha w(x_p), w a callable w(x) (N, D) -> (N,) of the current particle
      positions (001 §5.3, eq. 107: alpha_g(t, x_p) replaces alpha_g(t, x_i) of eq. 106).  Under
      ``approach="force"`` the nodal rate is the mass-weighted extrapolation
      alpha_i = sum_p S_ip M_p alpha(t, x_p) / m_i of the particle property (001 §5.3, last
      paragraph) in place of alpha_g(t, x_i) of 001 eq. (105).
    """

    grid: jnp.ndarray
    particle: jnp.ndarray
    schedule: Callable | None = None
    region: Callable | None = None
    approach: str = eqx.field(static=True, default="velocity")

    def __init__(self, grid=0.0, particle=0.0, *, approach: str = "velocity", schedule=None, region=None):
        self.grid = DAMPING.leaf("Damping", "grid (alpha_g)", grid)
        self.particle = DAMPING.leaf("Damping", "particle (alpha_p)", particle)
        check(approach in DAMPING_APPROACHES,
              f"Damping: approach = {approach!r}; choose one of {', '.join(DAMPING_APPROACHES)}")
        self.approach = approach
        if isinstance(schedule, (tuple, list)):
            check(len(schedule) == 2, "Damping: schedule = (times, factors), or a callable s(t)")
            schedule = Schedule(*schedule)
        check(schedule is None or callable(schedule),
              "Damping: schedule must be a callable s(t) -> factor or a pair (times, factors)")
        check(region is None or callable(region), "Damping: region must be a callable w(x) (N, D) -> (N,)")
        self.schedule = schedule
        self.region = region

    @property
    def varies(self) -> bool:
        """Whether the rates depend on time or position (001 §5.3)."""
        return self.schedule is not None or self.region is not None

    def acceleration(self, Sv, V):
        check(self.approach == "velocity" and not self.varies,
              "Damping.acceleration: this damping depends on the step (approach, schedule or region); "
              "use damping_at(damping, state, transfer, grid).acceleration")
        return self.grid * Sv + self.particle * V  # 000 eq. (2.77)

    def factor(self, time, x):
        """s(t) w(x_p), (N, 1): the rates' time and position factor (001 eqs. 30, 107)."""
        f = jnp.ones((x.shape[0], 1), x.dtype)
        if self.schedule is not None:
            f = f * jnp.asarray(self.schedule(time), x.dtype)  # 001 eq. (30): alpha(t)
        if self.region is not None:
            f = f * jnp.asarray(self.region(x), x.dtype)[:, None]  # 001 eq. (107): alpha(t, x_p)
        return f

    def at(self, state, transfer, grid):
        """The damping of the step that starts at ``state``: ``self`` when the rates are constants of
        the velocity approach (the default; nothing changes), else :class:`StepDamping`."""
        if self.approach == "velocity" and not self.varies:
            return self
        f = self.factor(state.time, state.x) if self.varies else 1.0
        alpha_p = self.particle * f
        if self.approach == "force":  # grid damping already in a and v~ (001 eqs. 61-62)
            return StepDamping(None, alpha_p, None)
        extrapolated = None
        if self.approach == "momentum":  # 001 eqs. (72)-(73), (76): p_{g->p} / m_{g->p}
            m = transfer.nodal_mass
            extrapolated = safe_divide(transfer.gather(m[:, None] * grid.v), transfer.gather(m))
        return StepDamping(self.grid * f, alpha_p, extrapolated)

    def p2g_columns(self, sim, state, stencil):
        if self.approach != "force" or not self.varies:
            return {}
        # sum_p S_pi M_p s(t) w(x_p): the nodal rate's numerator (001 §5.3, particle property)
        return {"damping_rate": stencil.weight * (state.mass * self.factor(state.time, state.x)[:, 0])}

    def grid_action(self, sim, fields, solution, dt):
        if self.approach != "force":
            return solution
        rate = self.grid
        if self.varies:
            rate = self.grid * safe_divide(fields["damping_rate"], fields.transfer.nodal_mass)[:, None]
        damp = sim.constraint(solution.v.dtype).zero(rate * solution.v)  # alpha_g p_i / m_i (001 eq. 60)
        return GridSolution({**solution.values, "a": solution.a - damp,  # 001 eqs. (58), (60), (97)
                             "v_tilde": solution.v_tilde - damp * dt,  # 001 eqs. (59), (98)
                             "grid_damping": damp})

    def particle_action(self, sim, old, new, transfer, solution, dt):
        """Under ``approach="force"`` the scheme measures its dissipation (000 eq. 2.43) against a
        FLIP update with the damped a**; add the grid damping's work, so that ``dissipated`` is the
        difference to the undamped FLIP update as for the other approaches."""
        if self.approach != "force":
            return new
        Sv, Sa_damped = transfer.gather(solution.v), transfer.gather(solution.a)
        Sa = Sa_damped + transfer.gather(solution["grid_damping"])  # undamped S a

        def flip(A):  # M_p (S a dt) . (S v + S a dt / 2), 000 eq. (2.42)
            return jnp.sum(transfer.particle_mass * flip_energy_increment(A, Sv, dt))

        return eqx.tree_at(lambda s: s.dissipated, new, new.dissipated + flip(Sa) - flip(Sa_damped))


class StepDamping(eqx.Module):
    """The damping of one step, resolved by :meth:`Damping.at`: rates alpha_g, alpha_p (scalars or
    (N, 1) per particle) and, for the momentum approach, the extrapolated grid velocity
    p_{g->p}/m_{g->p} that alpha_g multiplies in place of S v."""

    grid: jnp.ndarray | None
    particle: jnp.ndarray
    extrapolated: jnp.ndarray | None

    def acceleration(self, Sv, V):
        """A_damp = alpha_g(t, x_p) S v + alpha_p(t, x_p) V^n (001 eqs. 33, 40, 107; 000 eq. 2.77),
        with p_{g->p}/m_{g->p} for S v under the momentum approach (001 eqs. 72, 79)."""
        particle = self.particle * V
        if self.grid is None:  # approach="force": alpha_g is in the nodal force (001 eqs. 61-62)
            return particle
        grid_velocity = Sv if self.extrapolated is None else self.extrapolated
        return self.grid * grid_velocity + particle


def damping_acceleration(damping: Damping | None, Sv, V):
    """A_damp = alpha_g S v + alpha_p V^n (000 eq. 2.77); zero when the model has no damping."""
    return 0.0 if damping is None else damping.acceleration(Sv, V)


def damping_at(damping: Damping | None, state, transfer, grid):
    """The damping the scheme applies in the step that starts at ``state`` (:meth:`Damping.at`:
    time- and position-dependent rates, 001 §5.3; the momentum and force approaches, 001 §5.1.2,
    §5.2.2); None when the model has none."""
    return None if damping is None else damping.at(state, transfer, grid)


register_term("stress", StressDivergence, doc="internal force -sum_p V0_p tau_p . G_pi (001 eq. 20)")
register_term("body_force", BodyForce, doc="gravity and body force sum_p S_pi M_p b_p (001 eq. 20)",
              parameters=[Parameter("gravity", lambda t: t.gravity, "gravity vector", valid="finite")])
register_term("damping", Damping, doc="grid and particle damping (000 eq. 2.77)",
              parameters=[Parameter("alpha_g", lambda t: t.grid, "grid damping alpha_g (1/time)", "positive",
                                    valid=DAMPING),
                          Parameter("alpha_p", lambda t: t.particle, "particle damping alpha_p (1/time)",
                                    "positive", valid=DAMPING)])
