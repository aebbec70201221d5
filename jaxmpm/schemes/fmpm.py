"""FMPM(k), full-mass-matrix MPM (003 §2.2-2.3.1, Table 2.1):

    v+ = m~_k^{-1} p+ = sum_{l=1}^{k} (-1)^{l+1} C(k,l) (S+S)^{l-1} v_tilde   (003 eqs. 1.23, 2.13)
    V^{n+1} = S v+ - A_damp dt,    X^{n+1} = X^n + (V^{n+1} + V^n) dt / 2     (003 eq. 2.17)

with the velocity-condition variants of 003 §1.5 and §2.4 (``boundary=``), all evaluated by the
transfer layer's series (:mod:`jaxmpm.transfer.series`).
"""

from __future__ import annotations

import copy

import equinox as eqx
import jax.numpy as jnp

from ..core.errors import check
from ..core.registry import register_scheme
from ..transfer.series import (
    BOUNDARY_MODES,
    SERIES_FORMS,
    UNLUMPED_MODES,
    exchange_series,
    incremental_series,
    mass_matrix_series,
)
from .base import ParticleUpdate, Scheme, dissipated_energy
from .xpic import BETA, XPIC, _check_beta, _check_order, _number, check_damping_velocity, check_preset_option


class FMPM(Scheme):
    """FMPM(k), full-mass-matrix MPM (003 §2.2-2.3.1, Table 2.1):

        v+ = m~_k^{-1} p+ = sum_{l=1}^{k} (-1)^{l+1} C(k,l) (S+S)^{l-1} v_tilde   (003 eqs. 1.23, 2.13)
        V^{n+1} = S v+ - A_damp dt,    X^{n+1} = X^n + (V^{n+1} + V^n) dt / 2     (003 eq. 2.17)

    ``damping_velocity``: the grid damping's u in alpha_g u, "lumped" (default, S v) or "updated"
    (S v+, NairnMPM's rule).  ``beta`` (default 0) is jaxmpm's generalisation, not the seeds': a FLIP fraction
    V^{n+1} = beta (V^n + S a dt) + (1 - beta) S v+ - A_damp dt.  FMPM(1) is the "new PIC" of
    003 eq. (2.40).  The strain update uses the full-mass velocities.

    FMPM(0) is FLIP (003 Table 2.1, "FMPM(0)/XPIC(0)": V += a dt, X += (S v_tilde - a dt/2) dt,
    the second-order FLIP of 000 eqs. 2.48-2.49 with VV = S v), computed by the same update as
    ``FLIP()``; its strain update uses the lumped velocities, as FLIP's.

    Args:
        order: k, the series order, an integer >= 0 (default 2; static): 0 is FLIP, 1 the "new
            PIC"; above 40 warns (round-off, use ``series="neumann"``).
        beta: a FLIP fraction in [0, 1] (default 0.0, the seeds' FMPM); an array leaf.
        boundary: the velocity conditions of the series (:func:`jaxmpm.mass_matrix_series`):
            "iterates" (default), "result", "lumped" or a variant of 003 §1.5 and §2.4
            ("unlumped1", "unlumped2", "unlumped2_mtilde", "partial", "collection",
            "series_start", "pinv_start"; USL only).
        series: "binomial" (default) or "neumann", the same polynomial summed two ways.
        damping_velocity: the grid damping's u: "lumped" (default, S v) or "updated" (S v+).
    """

    beta: jnp.ndarray
    order: int = eqx.field(static=True)
    boundary: str = eqx.field(static=True)
    series: str = eqx.field(static=True)
    damping_velocity: str = eqx.field(static=True, default="lumped")

    def __init__(self, order: int = 2, beta=0.0, boundary: str = "iterates", series: str = "binomial",
                 damping_velocity: str = "lumped"):
        self.order = _check_order(order, "FMPM")
        self.beta = _check_beta(beta, "FMPM")
        check(boundary in BOUNDARY_MODES, f"FMPM: boundary = {boundary!r}; choose one of {', '.join(BOUNDARY_MODES)}")
        check(series in SERIES_FORMS, f"FMPM: series = {series!r}; choose one of {', '.join(SERIES_FORMS)}")
        self.boundary = boundary
        self.series = series
        self.damping_velocity = check_damping_velocity(damping_velocity, "FMPM")

    def in_conventions(self, conventions: str):
        """``conventions="nairnmpm"``: NairnMPM 19.0 damps FMPM(k >= 1) with its full-mass velocity,
        A_damp = alpha_g S v+ + alpha_p V^n (``damping_velocity="updated"``; MPM_Classes/MatPoint2D
        MoveParticle); the rest of its FMPM is jaxmpm's.  FMPM(0) is FLIP's."""
        if conventions != "nairnmpm" or self.order == 0:
            return self
        check_preset_option("FMPM", "damping_velocity", self.damping_velocity, "lumped", "updated")
        new = copy.copy(self)
        object.__setattr__(new, "damping_velocity", "updated")  # static: the scheme's hash changes
        return new

    def time_step_factor(self) -> float:
        """1 / sqrt(k): FMPM(k)'s stable time step is at least the lumped-mass (CFL) one over sqrt(k).

        The update accelerates the particles through m~_k^{-1} = sum_{j<k} (I - m^{-1} m~)^j m^{-1}
        (003 eqs. 1.12-1.13, 1.23) in place of the lumped m^{-1}.  With X = m^{-1/2} m~ m^{-1/2},
        whose eigenvalues lie in [0, 1] (m - m~ is diagonally dominant), m~_k^{-1} =
        m^{-1/2} p_k(X) m^{-1/2} with p_k(x) = sum_{j<k} (1 - x)^j <= k, so m~_k^{-1} <= k m^{-1}:
        the highest frequency of m~_k^{-1} K is at most sqrt(k) times that of m^{-1} K for any
        stiffness K, and the explicit step's limit 2 / omega_max shrinks by at most sqrt(k).  The
        bound is reached by a mode that the particles barely see (x -> 0), as the checkerboard in
        2D and 3D with smooth shapes: for quadratic B-splines in 2D, x = (2/15)^2 for a uniform
        body.  Measured on mpm88 (2048 particles, float64, 200 steps), the largest stable dt of
        FMPM(k) over FMPM(1)'s was 0.77, 0.55 and 0.44 for k = 2, 4, 8 (1 / sqrt(k): 0.71, 0.50,
        0.35; tests/test_matrix_forms.py).  FMPM(0) is FLIP: 1."""
        return 1.0 if self.order <= 1 else 1.0 / float(self.order) ** 0.5

    def strain_grid_velocity(self, v, transfer, constraint, exchange_dv=None):
        """The full-mass velocity of the strain update, m~_k^{-1} p' (003 eq. 2.3) of the lumped
        velocity ``v`` (USF's start-of-step or MUSL's re-extrapolated one, after the momentum
        exchange and the conditions); with velocity fields that exchanged momentum, minus the
        exchange's series term m~_{k-1}^{-1} Dp (003 §2.1.2, eqs. 3.16-3.22) for ``exchange_dv`` =
        Dp/m, or the series with the exchange on its increments for ``exchange_dv`` the exchanging
        term's hook (``Term.exchange_increments``: contact's ``series="incremental"``, NairnMPM's
        XPIC_STRAIN_UPDATE)."""
        if self.order == 0:
            return v  # FMPM(0) = FLIP: lumped velocities
        check(self.boundary not in UNLUMPED_MODES,
              f"FMPM: boundary = {self.boundary!r} is built for the USL update (its series starts from p+/m "
              "before the conditions); USF/MUSL/USAVG re-extrapolate velocities that have no such start: "
              "use update='USL' or boundary='iterates'")
        if hasattr(exchange_dv, "adjust"):  # the exchange on the series' increments (contact's "incremental")
            return incremental_series(v, self.order, transfer, constraint, exchange_dv, self.boundary)[0]
        v_full = mass_matrix_series(v, self.order, transfer, constraint, self.boundary, self.series)  # 003 eq. (2.3)
        correction = exchange_series(exchange_dv, self.order, transfer, constraint, self.boundary, self.series)
        return v_full if correction is None else v_full - correction

    def update(self, V, X, transfer, constraint, grid, damping, dt):
        if self.order == 0:  # 003 Table 2.1: FMPM(0) = XPIC(0) = FLIP
            return XPIC(order=0).update(V, X, transfer, constraint, grid, damping, dt)
        Sv = transfer.gather(grid.v)
        Sa = transfer.gather(grid.a)
        if grid.get("exchange_series") is not None:
            # the exchange on every increment of the series from v~ (contact's series="incremental", NairnMPM's
            # rule); the law's changes stay velocities (NairnMPM adds no force for FMPM)
            v_plus, _ = incremental_series(grid.v_tilde, self.order, transfer, constraint, grid["exchange_series"],
                                           self.boundary)
        else:
            v_plus = mass_matrix_series(grid.v_tilde, self.order, transfer, constraint, self.boundary, self.series,
                                        free=grid.values.get("v_tilde_unconstrained"))  # 003 eq. (2.13)
            correction = exchange_series(grid.get("exchange_dv"), self.order, transfer, constraint, self.boundary,
                                         self.series)
            if correction is not None:
                v_plus = v_plus - correction  # 003 eq. (3.22)
        beta = self.beta
        Sv_plus = transfer.gather(v_plus)
        damped = Sv if self.damping_velocity == "lumped" else Sv_plus  # "updated": NairnMPM's S v+
        V_new = beta * (V + Sa * dt) + (1.0 - beta) * Sv_plus - damping.acceleration(damped, V) * dt
        X_new = X + 0.5 * (V_new + V) * dt  # 003 eq. (2.17)
        diss = dissipated_energy(transfer.particle_mass, Sa, Sv, V_new - V, X_new - X, dt)
        return ParticleUpdate(V_new, X_new, v_plus, diss)


def _parse_fmpm(arg, beta=None):
    return FMPM(order=_number(arg, f"fmpm:{arg}", int) if arg else 2, beta=0.0 if beta is None else beta)


register_scheme("fmpm", FMPM, parse=_parse_fmpm, spec="fmpm:K", parameters=[BETA])
