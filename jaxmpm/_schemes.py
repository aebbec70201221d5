"""Particle updates.  Every scheme is the generic update of 000 §2.3 / 003 §2.3:

    V^{n+1} = V^n + A dt,      X^{n+1} = X^n + VV dt + 1/2 A dt^2

* :class:`XPIC` (with :class:`FLIP` and :class:`PIC` as its order-1 members) -- 000 eqs. (3.28)-(3.29)
* :class:`FMPM` -- 003 eqs. (2.13), (2.17), (2.26)

Both use one series, :func:`mass_matrix_series`, sum_{r=1}^{m} (-1)^{r+1} C(m,r) (S+S)^{r-1} u.
"""

from __future__ import annotations


import equinox as eqx
import jax
import jax.numpy as jnp

from ._boundary import Constraint
from ._errors import check
from ._fields import GridSolution
from ._registry import Parameter, register_scheme, scheme_from_name
from ._scheme_base import ParticleUpdate, Scheme, dissipated_energy
from ._terms import Damping, damping_acceleration
from ._transfer import Transfer
from ._validate import FRACTION, positive_int

BOUNDARY_MODES = ("iterates", "result", "lumped")
SERIES_FORMS = ("binomial", "neumann")
POSITION_UPDATES = ("Sv", "PV", "first_order")
MAX_SAFE_ORDER = 40


def _check_order(order, name: str) -> int:
    order = positive_int(name, "order", order, fix="it is a static loop length")
    if order > MAX_SAFE_ORDER:
        from ._warn import warn  # attributed to the user's line, not an equinox __init__

        warn(
            f"{name}: order {order} > {MAX_SAFE_ORDER}; XPIC is known to turn unstable at very high "
            "orders (OSParticulas documentation): the binomial series cancels terms of size C(m, m/2) and "
            "loses that many digits. Use series='neumann' (same result, stable) or an order of 2-10.",
            UserWarning,
        )
    return int(order)


def _check_beta(beta, owner: str):
    return FRACTION.leaf(owner, "beta", beta)


def mass_matrix_series(
    u, order: int, transfer: Transfer, constraint: Constraint, boundary: str = "iterates", form: str = "binomial"
):
    """sum_{r=1}^{m} (-1)^{r+1} C(m, r) (S+S)^{r-1} u.

    Applied to the lumped velocity v this is XPIC's v(m) (000 eq. 3.25); applied to the updated
    lumped velocity it is FMPM's v+ = m~_k^{-1} p+ (003 eqs. 1.23, 2.3-2.5).

    ``form="binomial"`` (default) is the recursion of 000 eqs. (3.23)-(3.25):

        u_1 = m u,   u_r = ((m - r + 1)/r) S+S u_{r-1},   result = sum_r (-1)^{r+1} u_r

    ``form="neumann"`` evaluates the same polynomial as the truncated Neumann series of the full
    mass matrix inverse, sum_{j=0}^{m-1} (I - S+S)^j u (the identity
    sum_r (-1)^{r+1} C(m,r) A^{r-1} = sum_{j<m} (I - A)^j; 003 eq. 1.23 with m^{-1} m~ = S+S).
    Same cost (one S+S per order) but no alternating binomial coefficients: at high order the
    binomial form cancels terms as large as C(m, m/2) |u| (1.3e14 |u| at m = 50) and loses that
    many digits to round-off; the Neumann form does not.

    Velocity boundary conditions (003 §1.5, eqs. 1.49-1.50), ``boundary``:
      * ``"iterates"`` (default): every iterate has its constrained components zeroed -- the
        constrained system; prescribed non-zero velocities g enter through the coupling term
        S+S g, so the limit is the constrained full-mass solve (003 eq. 1.49).
      * ``"result"``: conditions imposed only on the result (003 eq. 2.53 read literally);
        known to gain energy for orders >= 3 (docs/design.md).
      * ``"lumped"``: the lumped method (003 eq. 2.52): conditions only on the input momenta.
    """
    if order == 1:
        return u
    if boundary != "iterates":
        total = _series(u, order, transfer, lambda w: w, form)  # noqa: E731
        return constraint.apply(total) if boundary == "result" else total
    # the constrained system (003 eqs. 1.49-1.50): Z zeroes the constrained components,
    # v = g + sum_{j<m} (I - Z S+S)^j Z u - sum_{j<m-1} (I - Z S+S)^j Z S+S g,
    # the order-m Richardson iterate of Z (S+S v - u) = 0 from v_0 = g + Z u; for g = 0 (Fixed,
    # Slip) it is the series of Z u; the g-terms keep a body moving with a moving wall exactly
    total = _series(constraint.zero(u), order, transfer, constraint.zero, form)
    if constraint.inhomogeneous:
        g = constraint.prescribed(u)
        coupling = constraint.zero(transfer.s_plus_s(g))
        total = total + g - _series(coupling, order - 1, transfer, constraint.zero, form)
    return total


def contact_series(grid: GridSolution, order: int, transfer: Transfer, constraint: Constraint, boundary: str,
                   form: str):
    """(m~_{k-1}^a)^{-1} Dp^a = the order k-1 series of Dv^a = Dp^a / m^a, the contact term XPIC(k)
    and FMPM(k) subtract in multimaterial mode (003 eqs. 3.16-3.18, 3.22; m~_0^{-1} = 0 by 003
    eq. 3.15 at k = 1).  None without contact.  Homogeneous: Dv^a is zero on constrained
    components and stays so (no prescribed-velocity terms, unlike :func:`mass_matrix_series`)."""
    dv = grid.values.get("contact_dv")
    if dv is None or order == 1:
        return None
    project = constraint.zero if boundary == "iterates" else (lambda w: w)  # noqa: E731
    return _series(project(dv), order - 1, transfer, project, form)


def _series(start, order: int, transfer: Transfer, project, form: str):
    """sum_{r=1}^{m} (-1)^{r+1} C(m, r) (P S+S)^{r-1} start, P the projection on free components."""
    if order == 1:
        return start
    if form == "binomial":

        def body(r, carry):
            term, total = carry
            term = project((order - r + 1) / r * transfer.s_plus_s(term))  # 000 eq. (3.23)
            sign = jnp.where(r % 2 == 1, 1.0, -1.0)
            return term, total + sign * term  # 000 eq. (3.22)

        first = order * start  # 000 eq. (3.24)
        _, total = jax.lax.fori_loop(2, order + 1, body, (first, first))
        return total

    def body(j, carry):
        term, total = carry
        term = term - project(transfer.s_plus_s(term))  # (I - P S+S)^j start
        return term, total + term

    _, total = jax.lax.fori_loop(1, order, body, (start, start))
    return total


class XPIC(Scheme):
    """XPIC(m) with FLIP fraction beta, 000 eqs. (3.25)-(3.29):

        V^{n+1} = beta V^n + (1 - beta) S v(m) + (S a - A_damp) dt
        X^{n+1} = X^n + [S v + (V^{n+1} - V^n)/2] dt                       (position="Sv")
                  X^n + [beta S v + (1-beta) S v(m) + (V^{n+1} - V^n)/2] dt  (position="PV")
                  X^n + S v_tilde dt                                         (position="first_order")

    m = 1 is the FLIP/PIC blend of 000 eqs. (2.84)-(2.86); beta = 1 FLIP, beta = 0 PIC.
    """

    beta: jnp.ndarray
    order: int = eqx.field(static=True)
    position: str = eqx.field(static=True)
    boundary: str = eqx.field(static=True)
    series: str = eqx.field(static=True)

    def __init__(self, order: int = 2, beta=0.0, position: str = "Sv", boundary: str = "iterates",
                 series: str = "binomial"):
        self.order = _check_order(order, type(self).__name__)
        self.beta = _check_beta(beta, type(self).__name__)
        check(position in POSITION_UPDATES,
              f"{type(self).__name__}: position = {position!r}; choose one of {', '.join(POSITION_UPDATES)}")
        check(boundary in BOUNDARY_MODES,
              f"{type(self).__name__}: boundary = {boundary!r}; choose one of {', '.join(BOUNDARY_MODES)}")
        check(series in SERIES_FORMS,
              f"{type(self).__name__}: series = {series!r}; choose one of {', '.join(SERIES_FORMS)}")
        self.position = position
        self.boundary = boundary
        self.series = series

    def update(self, V, X, transfer: Transfer, constraint: Constraint, grid: GridSolution, damping: Damping, dt):
        Sv = transfer.gather(grid.v)
        Sa = transfer.gather(grid.a)
        if self.order == 1:
            Svm = Sv  # v(1) = v
        else:
            vm = mass_matrix_series(grid.v, self.order, transfer, constraint, self.boundary, self.series)
            correction = contact_series(grid, self.order, transfer, constraint, self.boundary, self.series)
            Svm = transfer.gather(vm if correction is None else vm - correction)  # 003 eq. (3.18)
        beta = self.beta
        V_new = beta * V + (1.0 - beta) * Svm + (Sa - damping_acceleration(damping, Sv, V)) * dt  # 000 eq. (3.28)
        if self.position == "Sv":
            X_new = X + (Sv + 0.5 * (V_new - V)) * dt  # 000 eq. (3.29), VV = S v
        elif self.position == "PV":
            X_new = X + (beta * Sv + (1.0 - beta) * Svm + 0.5 * (V_new - V)) * dt  # 000 eq. (3.29), VV = P V
        else:
            X_new = X + transfer.gather(grid.v_tilde) * dt  # 000 "Modified FLIP #1"
        diss = dissipated_energy(transfer.particle_mass, Sa, Sv, V_new - V, X_new - X, dt)
        return ParticleUpdate(V_new, X_new, grid.v_tilde, diss)


class FLIP(XPIC):
    """FLIP/PIC blend (000 eqs. 2.84-2.86): ``FLIP()`` is pure FLIP, ``FLIP(beta=0.99)`` the classic blend."""

    def __init__(self, beta=1.0, position: str = "Sv"):
        super().__init__(order=1, beta=beta, position=position)


class PIC(XPIC):
    """PIC: the blend with beta = 0 (000 eq. 2.85 with beta = 0)."""

    def __init__(self, position: str = "Sv"):
        super().__init__(order=1, beta=0.0, position=position)


class FMPM(Scheme):
    """FMPM(k), full-mass-matrix MPM (003 §2.2-2.3.1, Table 2.1):

        v+ = m~_k^{-1} p+ = sum_{l=1}^{k} (-1)^{l+1} C(k,l) (S+S)^{l-1} v_tilde   (003 eqs. 1.23, 2.13)
        V^{n+1} = S v+ - A_damp dt,    X^{n+1} = X^n + (V^{n+1} + V^n) dt / 2     (003 eq. 2.17)

    ``beta`` (default 0) is jaxmpm's generalisation, not the seeds': a FLIP fraction
    V^{n+1} = beta (V^n + S a dt) + (1 - beta) S v+ - A_damp dt.  FMPM(1) is the "new PIC" of
    003 eq. (2.40).  The strain update uses the full-mass velocities.
    """

    beta: jnp.ndarray
    order: int = eqx.field(static=True)
    boundary: str = eqx.field(static=True)
    series: str = eqx.field(static=True)

    def __init__(self, order: int = 2, beta=0.0, boundary: str = "iterates", series: str = "binomial"):
        self.order = _check_order(order, "FMPM")
        self.beta = _check_beta(beta, "FMPM")
        check(boundary in BOUNDARY_MODES, f"FMPM: boundary = {boundary!r}; choose one of {', '.join(BOUNDARY_MODES)}")
        check(series in SERIES_FORMS, f"FMPM: series = {series!r}; choose one of {', '.join(SERIES_FORMS)}")
        self.boundary = boundary
        self.series = series

    def strain_grid_velocity(self, v, transfer, constraint):
        return mass_matrix_series(v, self.order, transfer, constraint, self.boundary, self.series)  # 003 eq. (2.3)

    def update(self, V, X, transfer, constraint, grid, damping, dt):
        Sv = transfer.gather(grid.v)
        Sa = transfer.gather(grid.a)
        v_plus = mass_matrix_series(grid.v_tilde, self.order, transfer, constraint, self.boundary, self.series)  # 003 eq. (2.13)
        correction = contact_series(grid, self.order, transfer, constraint, self.boundary, self.series)
        if correction is not None:
            v_plus = v_plus - correction  # 003 eq. (3.22)
        beta = self.beta
        V_new = beta * (V + Sa * dt) + (1.0 - beta) * transfer.gather(v_plus) - damping_acceleration(damping, Sv, V) * dt
        X_new = X + 0.5 * (V_new + V) * dt  # 003 eq. (2.17)
        diss = dissipated_energy(transfer.particle_mass, Sa, Sv, V_new - V, X_new - X, dt)
        return ParticleUpdate(V_new, X_new, v_plus, diss)


def _number(arg: str, spec: str, kind=float):
    """The part of a scheme spec after ':' as a number, or a clear error."""
    try:
        value = kind(arg)
    except ValueError:
        what = "the order must be a positive integer" if kind is int else "the part after ':' must be a number"
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


def _parse_fmpm(arg, beta=None):
    return FMPM(order=_number(arg, f"fmpm:{arg}", int) if arg else 2, beta=0.0 if beta is None else beta)


BETA = Parameter("beta", lambda s: s.beta, "the scheme's FLIP fraction (FLIP, XPIC, FMPM)", (0.0, 1.0),
                 valid=FRACTION)
register_scheme("flip", FLIP, parse=_parse_flip, spec="flip", parameters=[BETA])
register_scheme("pic", PIC, parse=_parse_pic, spec="pic", parameters=[BETA])
register_scheme("blend", FLIP, parse=_parse_blend, spec="blend:B", parameters=[BETA])
register_scheme("xpic", XPIC, parse=_parse_xpic, spec="xpic:M", parameters=[BETA])
register_scheme("fmpm", FMPM, parse=_parse_fmpm, spec="fmpm:K", parameters=[BETA])

__all__ = ["XPIC", "FLIP", "PIC", "FMPM", "Damping", "GridSolution", "ParticleUpdate", "Scheme",
           "damping_acceleration", "dissipated_energy", "mass_matrix_series", "scheme_from_name"]
