"""XPIC(m) and its order-1 members, the FLIP/PIC blend (000 eqs. 2.84-2.86, 3.25-3.29):

    V^{n+1} = beta V^n + (1 - beta) S v(m) + (S a - A_damp) dt          000 eq. (3.28)
    X^{n+1} = X^n + [VV + (V^{n+1} - V^n)/2] dt                          000 eq. (2.22)

v(m) is the mass-matrix series of the lumped velocity (:func:`jaxmpm.mass_matrix_series`,
``jaxmpm.transfer.series``); the position update (the choice of VV) is the ``position=`` option,
000 §2.3-2.4 (``POSITION_UPDATES``); order 0 is FLIP (003 Table 2.1).
"""

from __future__ import annotations

import copy

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..core.errors import check
from ..core.registry import Parameter, register_scheme
from ..core.validate import FRACTION, positive_int
from ..transfer.operators import Transfer
from ..transfer.series import (
    SERIES_FORMS,
    UNLUMPED_MODES,
    XPIC_BOUNDARY_MODES,
    exchange_series,
    incremental_series,
    mass_matrix_series,
)
from .base import ParticleDamping, ParticleUpdate, Scheme, dissipated_energy

# the effective velocity VV of the position update X^{n+1} = X^n + [VV + (V^{n+1} - V^n)/2] dt
# (000 eq. 2.22), one value per update of 000 §2.3-2.4 -- see XPIC.position_update
POSITION_UPDATES = ("Sv", "PV", "first_order", "V", "Sv_first_order", "PV_first_order", "V_end", "second_order",
                    "PV_tilde")


MAX_SAFE_ORDER = 40


def _check_order(order, name: str) -> int:
    """A static order >= 0; order 0 is FLIP (003 Table 2.1, "FMPM(0)/XPIC(0)")."""
    order = positive_int(name, "order", order, low=0, fix="it is a static loop length; 0 is FLIP (003 Table 2.1)")
    if order > MAX_SAFE_ORDER:
        from ..core.warn import warn  # attributed to the user's line, not an equinox __init__

        warn(
            f"{name}: order {order} > {MAX_SAFE_ORDER}; XPIC is known to turn unstable at very high "
            "orders (OSParticulas documentation): the binomial series cancels terms of size C(m, m/2) and "
            "loses that many digits. Use series='neumann' (same result, stable) or an order of 2-10.",
            UserWarning,
        )
    return int(order)


# the grid velocity u of the grid damping alpha_g u in A_damp = alpha_g u + alpha_p V^n (000 eq. 2.77):
# "lumped" u = S v (000 eq. 2.77, the default); "updated" u = the scheme's updated grid velocity --
# S(v(m) + a dt) for XPIC and PIC, S v+ for FMPM (NairnMPM 19.0, MPM_Classes/MatPoint2D MoveParticle)
DAMPING_VELOCITIES = ("lumped", "updated")


def check_damping_velocity(value, owner: str) -> str:
    check(value in DAMPING_VELOCITIES,
          f"{owner}: damping_velocity = {value!r}; choose 'lumped' (alpha_g S v, 000 eq. 2.77) or 'updated' "
          "(alpha_g times the updated grid velocity, NairnMPM's rule)")
    return value


def check_preset_option(owner: str, name: str, value, default, preset) -> None:
    """A scheme option the preset sets must be left at its default (or already be the preset's)."""
    check(value in (default, preset),
          f"{owner}: {name} = {value!r} with conventions='nairnmpm', which sets {name}={preset!r} "
          f"(NairnMPM's rule); drop {name}= or use conventions='jaxmpm'")


def _is_one(beta) -> bool:
    """Whether a concrete beta is 1 (pure FLIP); a traced beta counts as a blend."""
    if isinstance(beta, jax.core.Tracer):
        return False
    return bool(np.all(np.asarray(beta) == 1.0))


def _check_beta(beta, owner: str):
    return FRACTION.leaf(owner, "beta", beta)


class XPIC(Scheme):
    """XPIC(m) with FLIP fraction beta, 000 eqs. (3.25)-(3.29):

        V^{n+1} = beta V^n + (1 - beta) S v(m) + (S a - A_damp) dt          000 eq. (3.28)
        X^{n+1} = X^n + [VV + (V^{n+1} - V^n)/2] dt                          000 eq. (2.22)

    m = 1 is the FLIP/PIC blend of 000 eqs. (2.84)-(2.86); beta = 1 FLIP, beta = 0 PIC.  With
    P = I - (I - S S+)^m (000 eq. 3.12) and the blend's P V = beta S v + (1 - beta) S v(m)
    (000 eq. 2.74), ``position`` picks VV, the updates of 000 §2.3-2.4 (A_damp = alpha_g S v +
    alpha_p V^n, 000 eq. 2.77; every option keeps the velocity update above):

    * ``"Sv"`` (default): VV = S v                                       000 eqs. (2.28)-(2.29), (3.29)
    * ``"PV"``: VV = P V (the blend's)                                    000 eqs. (2.35)-(2.37), (2.74)
    * ``"V"``: VV = V^n, X += (V^n + V^{n+1})/2 dt, any P                  000 eqs. (2.26)-(2.27)
    * ``"first_order"``: X += S v_tilde dt                                000 eq. (2.52) "Modified FLIP
      #1" (= eq. 2.65 "Modified PIC #1" at beta = 0; 003 eq. 2.28 with psi = 0).  Kept as it was:
      it is *not* 000 eq. (2.34) once P != I or with damping (stored reference values use it)
    * ``"Sv_first_order"``: VV = S v + S a dt/2, X += [S v_tilde - (I - P) V^n/2 - A_damp dt/2] dt
                                                                           000 eqs. (2.33)-(2.34)
    * ``"PV_first_order"``: VV = P V + S a dt/2                           000 eqs. (2.39)-(2.40)
    * ``"V_end"``: X += V^{n+1} dt ("Modified FLIP #2")                  000 eqs. (2.54)-(2.56);
      with beta this is the Stomakhin et al. PIC/FLIP blend (003 §2.3.4): V^{n+1} =
      alpha(V^n + S a dt) + (1 - alpha) S v_tilde is the blend's velocity update with beta = alpha
    * ``"second_order"``: X += S v dt + (S a - A_damp) dt^2/2, the grid trajectory  000 eqs.
      (2.70)-(2.72) ("second-order PIC" with ``PIC(position="second_order")``)
    * ``"PV_tilde"``: VV = P V + S a dt; for XPIC and PIC (beta = 0) X += [S(v(m) + a dt) + (V^{n+1} -
      V^n)/2] dt, NairnMPM 19.0's XPIC/PIC position update (MPM_Classes/MatPoint2D MoveParticle);
      not 000 eq. (2.22)'s second order: VV carries a full a dt

    ``damping_velocity`` is the u of the grid damping alpha_g u: "lumped" (default, S v, 000 eq.
    2.77) or "updated" (P V + S a dt: S(v(m) + a dt) at beta = 0, NairnMPM's rule).

    ``boundary`` is the series' velocity conditions (:func:`jaxmpm.mass_matrix_series`):
    "iterates" (default), "result", "lumped", or "unconstrained_start", NairnMPM's start of the
    series from the lumped velocity before the conditions (:func:`jaxmpm.transfer.series.unconstrained_series`).

    Decisions where the seed is not explicit: 000 eq. (2.34) writes A_damp without its dt; eq.
    (2.33), which it expands, fixes it to A_damp dt.  000 eqs. (2.54)-(2.56) and (2.70)-(2.71)
    are written undamped for P = I resp. P = S S+: "V_end" keeps X += V^{n+1} dt literally for
    every P, beta and damping (the Stomakhin form), and "second_order" puts the damped
    acceleration in the grid trajectory (for PIC this is VV = (S v + V^n)/2 of 000 eq. 2.72 with
    damping, through eq. 2.22).

    ``order=0`` is FLIP: 003 Table 2.1 lists "FMPM(0)/XPIC(0)" as dV = a dt, V += dV,
    X += (S v_tilde - dV/2) dt, i.e. P = I with VV = S v, FLIP of 000 eqs. (2.48)-(2.49).  (000
    eq. 3.12 does not define it: (I - S S+)^0 = I would give P = 0.)  P = I makes beta irrelevant
    (beta V + (1 - beta) P V = V); it is taken as 1, so ``XPIC(0, position=...)`` is
    ``FLIP(position=...)`` exactly.

    Args:
        order: m, the series order, an integer >= 0 (default 2; static, a loop length): 1 is the
            FLIP/PIC blend, 0 is FLIP; above 40 warns (round-off, use ``series="neumann"``).
        beta: the FLIP fraction in [0, 1] (default 0.0): 1 FLIP, 0 PIC; an array leaf
            (:func:`jaxmpm.set_params`, ``jax.grad``).
        position: the position update, the VV of the list above (default "Sv").
        boundary: the series' velocity conditions: "iterates" (default), "result", "lumped" or
            "unconstrained_start".
        series: how the series is summed: "binomial" (default, 000 eqs. 3.23-3.25) or "neumann"
            (the same polynomial, stable at high order; :func:`jaxmpm.mass_matrix_series`).
        damping_velocity: the u of the grid damping alpha_g u: "lumped" (default) or "updated".
    """

    beta: jnp.ndarray
    order: int = eqx.field(static=True)
    position: str = eqx.field(static=True)
    boundary: str = eqx.field(static=True)
    series: str = eqx.field(static=True)
    damping_velocity: str = eqx.field(static=True, default="lumped")

    @property
    def local_update(self) -> bool:
        """Orders 0 and 1 (FLIP, PIC and their blends) gather the grid at each particle's own nodes;
        higher orders run the S+ S series over all particles."""
        return self.order <= 1

    def __init__(self, order: int = 2, beta=0.0, position: str = "Sv", boundary: str = "iterates",
                 series: str = "binomial", damping_velocity: str = "lumped"):
        self.order = _check_order(order, type(self).__name__)
        self.beta = _check_beta(beta, type(self).__name__)
        check(position in POSITION_UPDATES,
              f"{type(self).__name__}: position = {position!r}; choose one of {', '.join(POSITION_UPDATES)}")
        check(boundary in XPIC_BOUNDARY_MODES,
              f"{type(self).__name__}: boundary = {boundary!r}; choose one of {', '.join(XPIC_BOUNDARY_MODES)}"
              + ("; the unlumped variants of 003 §2.4 are FMPM's (jm.FMPM(boundary=...))"
                 if boundary in UNLUMPED_MODES else ""))
        check(series in SERIES_FORMS,
              f"{type(self).__name__}: series = {series!r}; choose one of {', '.join(SERIES_FORMS)}")
        self.position = position
        self.boundary = boundary
        self.series = series
        self.damping_velocity = check_damping_velocity(damping_velocity, type(self).__name__)

    def in_conventions(self, conventions: str):
        """``conventions="nairnmpm"``: NairnMPM 19.0's position update and series start (the third
        convention, the reaction on constrained nodes, is the Simulation's ``constrained_force``):

        * ``position``: "Sv" for FLIP (order 0, or beta = 1: X += [S v + dV/2] dt with the lumped
          v, NairnMPM's ``vm`` = S(v+ - a dt)), "PV_tilde" otherwise (XPIC and PIC:
          X += [S(v(m) + a dt) + dV/2] dt);
        * ``boundary``: "unconstrained_start" for order >= 2 (the series from p/m before the
          conditions, only its increments zeroed);
        * ``damping_velocity``: "lumped" for FLIP (alpha_g S v), "updated" otherwise (alpha_g
          S(v(m) + a dt), NairnMPM's MoveParticle damps with the velocity it moves the particle by).

        A position or boundary given explicitly and different from these is an InputError (the
        preset would silently override it)."""
        if conventions != "nairnmpm":
            return self
        flip = self.order == 0 or _is_one(self.beta)
        position = "Sv" if flip else "PV_tilde"
        boundary = "unconstrained_start" if self.order >= 2 else self.boundary
        damping_velocity = "lumped" if flip else "updated"
        name = type(self).__name__
        check_preset_option(name, "damping_velocity", self.damping_velocity, "lumped", damping_velocity)
        check_preset_option(name, "position", self.position, "Sv", position)
        check_preset_option(name, "boundary", self.boundary, "iterates", boundary)
        new = copy.copy(self)
        object.__setattr__(new, "position", position)  # static fields: the scheme's hash changes, jit retraces
        object.__setattr__(new, "boundary", boundary)
        object.__setattr__(new, "damping_velocity", damping_velocity)
        return new

    def update(self, V, X, transfer: Transfer, constraint, grid, damping: ParticleDamping, dt):
        Sv = transfer.gather(grid.v)
        Sa = transfer.gather(grid.a)
        beta = self.beta
        if self.order == 0:
            Svm, beta = Sv, 1.0  # P = I: FLIP (003 Table 2.1, "FMPM(0)/XPIC(0)")
        elif self.order == 1:
            Svm = Sv  # v(1) = v
        elif grid.get("exchange_series") is not None:
            # the exchange on every increment of the series (contact's series="incremental", NairnMPM's rule):
            # the sum v + sum_k D_k holds the law's changes e = sum_k E_k, which are a force, a += e/dt
            # (NairnMPM's AddFtotScaled), and v(m) is the rest: v(m) + a dt = v~ + sum_k D_k, NairnMPM's v*
            total, exchanged = incremental_series(grid.v, self.order, transfer, constraint, grid["exchange_series"],
                                                  self.boundary, free=grid.get("v_unconstrained"))
            Svm = transfer.gather(total - exchanged)
            Sa = Sa + transfer.gather(exchanged) / jnp.where(dt > 0, dt, 1.0)
        else:
            vm = mass_matrix_series(grid.v, self.order, transfer, constraint, self.boundary, self.series,
                                    free=grid.get("v_unconstrained"))
            if constraint.reaction and self.boundary != "unconstrained_start":
                # constrained_force="reaction": v(m) keeps p/m where the reaction a = (g - p/m)/dt acts, so
                # that v(m) + a dt = g on the constrained components as in the default form
                vm = constraint.zero(vm) + (grid.v - constraint.zero(grid.v))
            correction = exchange_series(grid.get("exchange_dv"), self.order, transfer, constraint, self.boundary,
                                         self.series)
            Svm = transfer.gather(vm if correction is None else vm - correction)  # 003 eq. (3.18)
        PV = beta * Sv + (1.0 - beta) * Svm  # the blend's P V (000 eq. 2.74)
        damped = Sv if self.damping_velocity == "lumped" else PV + Sa * dt  # "updated": NairnMPM's S(v(m) + a dt)
        A_damp = damping.acceleration(damped, V)  # 000 eq. (2.77)
        V_new = beta * V + (1.0 - beta) * Svm + (Sa - A_damp) * dt  # 000 eq. (3.28)
        X_new = self.position_update(X, V, V_new, Sv, Sa, PV, A_damp, transfer, grid, dt)
        diss = dissipated_energy(transfer.particle_mass, Sa, Sv, V_new - V, X_new - X, dt)
        return ParticleUpdate(V_new, X_new, grid.v_tilde, diss)

    def position_update(self, X, V, V_new, Sv, Sa, PV, A_damp, transfer: Transfer, grid, dt):
        """X^{n+1} = X^n + [VV + (V^{n+1} - V^n)/2] dt (000 eq. 2.22) for the chosen VV (class docstring)."""
        half_dV = 0.5 * (V_new - V)
        position = self.position
        if position == "Sv":
            return X + (Sv + half_dV) * dt  # 000 eq. (2.29), VV = S v
        if position == "PV":
            return X + (PV + half_dV) * dt  # 000 eqs. (2.37), (2.74), VV = P V
        if position == "first_order":
            return X + transfer.gather(grid.v_tilde) * dt  # 000 eq. (2.52) "Modified FLIP #1"
        if position == "V":
            return X + 0.5 * (V + V_new) * dt  # 000 eq. (2.27), VV = V^n
        if position == "Sv_first_order":
            return X + (Sv + 0.5 * Sa * dt + half_dV) * dt  # 000 eqs. (2.33)-(2.34), VV = S v + S a dt/2
        if position == "PV_first_order":
            return X + (PV + 0.5 * Sa * dt + half_dV) * dt  # 000 eqs. (2.39)-(2.40), VV = P V + S a dt/2
        if position == "V_end":
            return X + V_new * dt  # 000 eq. (2.55) "Modified FLIP #2"; the Stomakhin blend (003 §2.3.4)
        if position == "PV_tilde":
            return X + (PV + Sa * dt + half_dV) * dt  # NairnMPM 19.0 (MatPoint2D MoveParticle): S(v(m) + a dt)
        return X + (Sv + 0.5 * (Sa - A_damp) * dt) * dt  # "second_order": 000 eq. (2.71), damped


class FLIP(XPIC):
    """FLIP/PIC blend (000 eqs. 2.84-2.86): ``FLIP()`` is pure FLIP, ``FLIP(beta=0.99)`` the classic blend.

    ``FLIP(position="V_end")`` is "Modified FLIP #2" (000 eqs. 2.54-2.56, X += V^{n+1} dt) and
    ``FLIP(beta=alpha, position="V_end")`` the PIC/FLIP blend of Stomakhin et al. (003 §2.3.4);
    ``FLIP(position="V")`` is 000 eq. (2.49)'s second form.  All position options: :class:`XPIC`.

    Args:
        beta: the FLIP fraction in [0, 1] (default 1.0, pure FLIP; 0 is PIC).
        position: the position update (default "Sv"; the options of :class:`XPIC`).
        damping_velocity: the u of the grid damping alpha_g u: "lumped" (default, S v) or
            "updated" (NairnMPM's rule).
    """

    def __init__(self, beta=1.0, position: str = "Sv", damping_velocity: str = "lumped"):
        super().__init__(order=1, beta=beta, position=position, damping_velocity=damping_velocity)


class PIC(XPIC):
    """PIC: the blend with beta = 0 (000 eq. 2.85 with beta = 0).  ``PIC(position="second_order")``
    is the second-order PIC of 000 eqs. (2.70)-(2.72), ``PIC(position="first_order")`` "Modified
    PIC #1" (000 eqs. 2.64-2.65).

    Args:
        position: the position update (default "Sv"; the options of :class:`XPIC`).
        damping_velocity: the u of the grid damping alpha_g u: "lumped" (default, S v) or
            "updated" (S(v + a dt), NairnMPM's rule).
    """

    def __init__(self, position: str = "Sv", damping_velocity: str = "lumped"):
        super().__init__(order=1, beta=0.0, position=position, damping_velocity=damping_velocity)


def _number(arg: str, spec: str, kind=float):
    """The part of a scheme spec after ':' as a number, or a clear error."""
    try:
        value = kind(arg)
    except ValueError:
        what = "the order must be a non-negative integer" if kind is int else "the part after ':' must be a number"
        check(False, f"scheme {spec!r}: {what}, got {arg!r}")
    return value


def _parse_flip(arg, beta=None):
    return FLIP(beta=1.0 if beta is None else beta)


def _parse_pic(arg, beta=None):
    check(beta is None, "scheme 'pic' has beta = 0 by definition; drop beta (--beta) or use blend:B")
    return PIC()


def _parse_blend(arg, beta=None):
    check(not (arg and beta is not None), f"scheme 'blend:{arg}' already sets beta; drop beta (--beta)")
    return FLIP(beta=_number(arg, f"blend:{arg}") if arg else (0.99 if beta is None else beta))


def _parse_xpic(arg, beta=None):
    return XPIC(order=_number(arg, f"xpic:{arg}", int) if arg else 2, beta=0.0 if beta is None else beta)


BETA = Parameter("beta", lambda s: s.beta, "the scheme's FLIP fraction (FLIP, XPIC, FMPM)", (0.0, 1.0),
                 valid=FRACTION)
register_scheme("flip", FLIP, parse=_parse_flip, spec="flip", parameters=[BETA])
register_scheme("pic", PIC, parse=_parse_pic, spec="pic", parameters=[BETA])
register_scheme("blend", FLIP, parse=_parse_blend, spec="blend:B", parameters=[BETA])
register_scheme("xpic", XPIC, parse=_parse_xpic, spec="xpic:M", parameters=[BETA])
