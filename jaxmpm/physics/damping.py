"""Grid and particle damping (000 eq. 2.77; 001 §5.1.2-5.3)."""

from __future__ import annotations

from typing import Callable

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ..core.errors import check
from ..core.registry import Parameter, register_term
from ..core.validate import DAMPING, concrete
from ..schemes.base import ParticleDamping, RateDamping, flip_energy_increment
from ..transfer.contractions import Weighted
from ..transfer.operators import safe_divide
from .term import Term

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
              f"Damping: schedule has {t.size} times but factors of shape {np.shape(factors)}; "
              "give one factor per time")
        check(f is None or bool(np.all(np.isfinite(f)) and np.all(f >= 0)),
              "Damping: schedule factors must be finite and >= 0 (alpha(t) = alpha s(t) is a damping rate)")
        self.times = jnp.asarray(t, dtype=jnp.result_type(float))
        self.factors = jnp.asarray(factors, dtype=jnp.result_type(float))

    def __call__(self, t):
        return jnp.interp(t, self.times.astype(t.dtype), self.factors.astype(t.dtype))


class Damping(Term, ParticleDamping):
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

    Args:
        grid: alpha_g, the grid damping rate in 1/time, >= 0 (default 0.0); a differentiable
            leaf (the parameter ``alpha_g``).
        particle: alpha_p, the particle damping rate in 1/time, >= 0 (default 0.0; the
            parameter ``alpha_p``).
        approach: "velocity" (default), "momentum" or "force", the variants above.
        schedule: the time factor s(t): a callable s(t) -> scalar, a pair (times, factors) of a
            piecewise-linear :class:`Schedule` (factors >= 0), or None (the default: constant).
        region: the position factor w: a callable w(x) (N, D) -> (N,) of the particle
            positions, or None (the default: everywhere).
    """

    local = True  # rates per particle, gathers at its own nodes, sums over particles (jaxmpm.model.chunks)
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

    def factor(self, time, x):
        """s(t) w(x_p), (N, 1): the rates' time and position factor (001 eqs. 30, 107)."""
        f = jnp.ones((x.shape[0], 1), x.dtype)
        if self.schedule is not None:
            f = f * jnp.asarray(self.schedule(time), x.dtype)  # 001 eq. (30): alpha(t)
        if self.region is not None:
            f = f * jnp.asarray(self.region(x), x.dtype)[:, None]  # 001 eq. (107): alpha(t, x_p)
        return f

    def acceleration(self, Sv, V):
        """A_damp = alpha_g S v + alpha_p V^n of constant rates, velocity approach (000 eq. 2.77):
        such a term is itself the :class:`jaxmpm.ParticleDamping` its steps apply."""
        check(self.approach == "velocity" and not self.varies,
              "Damping.acceleration: this damping depends on the step (approach, schedule or region); "
              "its step's damping is particle_damping(sim, state, transfer, solution)")
        return self.grid * Sv + self.particle * V  # 000 eq. (2.77)

    # ------------------------------------------------------------------ the term's hooks
    def grid_reads(self, sim) -> frozenset:
        return frozenset({"momentum"}) if self.approach == "force" else frozenset({"v"})

    def folded_columns(self) -> tuple:
        return ("damping_rate",)

    def p2g_quantities(self, sim, state, stencil):
        if self.approach != "force" or not self.varies:
            return {}
        # sum_p S_pi M_p s(t) w(x_p): the nodal rate's numerator (001 §5.3, particle property)
        return {"damping_rate": Weighted(state.mass * self.factor(state.time, state.x)[:, 0])}

    def grid_force(self, sim, fields, dt):
        """``approach="force"``: f** = f - alpha_g p_i (001 eqs. 58-60, 97-98), alpha_g the nodal
        rate (001 eq. 105; with a region the extrapolated particle property, 001 §5.3)."""
        if self.approach != "force":
            return None
        rate = self.grid
        if self.varies:
            rate = self.grid * safe_divide(fields["damping_rate"], fields.mass)[:, None]
        p = fields.momentum
        damp = sim.constraint(p.dtype).zero(rate * safe_divide(p, fields.mass))  # alpha_g p_i / m_i (001 eq. 60)
        return {"force": -rate * p, "grid_damping": damp}

    def particle_damping(self, sim, state, transfer, solution):
        """The damping of the particle update (001 §5.1.2-5.3): alpha_g S v + alpha_p V^n, with
        time- and position-dependent rates (001 eqs. 30, 107); under the momentum approach
        p_{g->p}/m_{g->p} for S v (001 eqs. 72-73, 76); under the force approach alpha_p V^n only
        (the grid part is in the nodal force, 001 eqs. 61-62)."""
        if self.approach == "velocity" and not self.varies:
            return RateDamping(self.grid, self.particle)
        f = self.factor(state.time, state.x) if self.varies else 1.0
        alpha_p = self.particle * f
        if self.approach == "force":
            return RateDamping(None, alpha_p)
        extrapolated = None
        if self.approach == "momentum":  # 001 eqs. (72)-(73), (76): p_{g->p} / m_{g->p}
            m = transfer.nodal_mass
            extrapolated = safe_divide(transfer.gather(m[:, None] * solution.v), transfer.gather(m))
        return RateDamping(self.grid * f, alpha_p, extrapolated)

    def attributes(self) -> dict:
        return {"damping approach": self.approach, "damping varies": int(self.varies)}  # a schedule or region

    def at(self, state, transfer, grid):
        """The damping of the step that starts at ``state`` (:meth:`particle_damping`)."""
        return self.particle_damping(None, state, transfer, grid)

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


register_term("damping", Damping, doc="grid and particle damping (000 eq. 2.77)",
              parameters=[Parameter("alpha_g", lambda t: t.grid, "grid damping alpha_g (1/time)", "positive",
                                    valid=DAMPING),
                          Parameter("alpha_p", lambda t: t.particle, "particle damping alpha_p (1/time)",
                                    "positive", valid=DAMPING)])
