"""Particle updates.  Every scheme is the generic update of 000 §2.3 / 003 §2.3:

    V^{n+1} = V^n + A dt,      X^{n+1} = X^n + VV dt + 1/2 A dt^2

* :class:`XPIC` (with :class:`FLIP` and :class:`PIC` as its order-1 members) -- 000 eqs. (3.28)-(3.29);
  the position update (the choice of VV) is its ``position=`` option, 000 §2.3-2.4 (``POSITION_UPDATES``)
* :class:`FMPM` -- 003 eqs. (2.13), (2.17), (2.26)
* order 0: XPIC(0) = FMPM(0) = FLIP (003 Table 2.1)

Both use one series, :func:`mass_matrix_series`, sum_{r=1}^{m} (-1)^{r+1} C(m,r) (S+S)^{r-1} u.
"""

from __future__ import annotations


import equinox as eqx
import jax
import jax.numpy as jnp

from ..physics.conditions import Constraint
from ..core.errors import check
from ..core.fields import GridSolution
from ..core.registry import Parameter, register_scheme, scheme_from_name
from .base import ParticleUpdate, Scheme, dissipated_energy
from ..physics.term import Damping, damping_acceleration
from ..transfer.operators import Transfer
from ..core.validate import FRACTION, positive_int

BOUNDARY_MODES = ("iterates", "result", "lumped", "unlumped1", "unlumped2", "unlumped2_mtilde", "partial",
                  "collection", "series_start", "pinv_start")
# the modes of 003 §1.5 (eqs. 1.51-1.69) and §2.4 (eqs. 2.54-2.56, "Collection of Boundary Conditions")
# that need p+/m before the velocity conditions (``free`` of :func:`mass_matrix_series`)
UNLUMPED_MODES = BOUNDARY_MODES[3:]
COLLECTION_ITERATIONS = 24  # conjugate-gradient steps of boundary="collection" (exact after n_BC steps)
SERIES_FORMS = ("binomial", "neumann")
# the effective velocity VV of the position update X^{n+1} = X^n + [VV + (V^{n+1} - V^n)/2] dt
# (000 eq. 2.22), one value per update of 000 §2.3-2.4 -- see XPIC.position_update
POSITION_UPDATES = ("Sv", "PV", "first_order", "V", "Sv_first_order", "PV_first_order", "V_end", "second_order")
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


def _check_beta(beta, owner: str):
    return FRACTION.leaf(owner, "beta", beta)


def mass_matrix_series(
    u, order: int, transfer: Transfer, constraint: Constraint, boundary: str = "iterates", form: str = "binomial",
    free=None,
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
      * the variants of 003 §1.5 and §2.4 (``UNLUMPED_MODES``, :func:`unlumped_series`):
        ``"unlumped1"`` (eqs. 2.54-2.55), ``"unlumped2"`` (eq. 2.56), ``"unlumped2_mtilde"``
        (eq. 2.56 with m~ for m~_k, 003's remark), ``"partial"`` and ``"collection"`` (the
        "Collection of Boundary Conditions", options 2 and 1), ``"series_start"`` (eqs.
        1.51-1.56), ``"pinv_start"`` (eqs. 1.57-1.69).  They need ``free``, the lumped velocity
        p+/m before the conditions (``u`` is it with the conditions imposed, the lumped method).
    """
    if boundary in UNLUMPED_MODES:
        return unlumped_series(u, free, order, transfer, constraint, boundary, form)
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


def _full_series(x, order: int, transfer: Transfer, form: str):
    """m~_k^{-1} m x = sum_{l=1}^{k} C_kl (S+S)^{l-1} x, no conditions (003 eqs. 1.23, 1.70); m~_0^{-1} = 0."""
    if order == 0:
        return jnp.zeros_like(x)
    return _series(x, order, transfer, lambda w: w, form)


def unlumped_series(u, free, order: int, transfer: Transfer, constraint: Constraint, boundary: str, form: str):
    """The grid velocity v+' = m~_k^{-1}(p+ + f^(BC) dt) of a velocity-condition variant of 003 §1.5
    and §2.4 (``boundary`` in ``UNLUMPED_MODES``).

    ``free`` is w = p+/m, the lumped velocity before the conditions; ``u`` the lumped method's
    velocity (conditions imposed, 003 eq. 2.52); dv = u - w its change (003 eq. 1.53, Dv^(L); the
    lumped boundary momentum is f^(L) dt = m dv).  With series_k(x) = m~_k^{-1} m x and
    m^{-1} m~ = S+S (003 eq. 1.6):

    * ``"unlumped1"``  f dt = m~ m^{-1} f^(L) dt = m~ dv (003 eqs. 2.54-2.55):
      v = m~_k^{-1}(p+ + m~ dv) = series_k(w + S+S dv)
    * ``"unlumped2"``  f dt = m~_k Dv, Dv = (v^(b) - (m~_k^{-1} p+)_b) on the conditions (003 eq. 2.56):
      v = v+ + Dv with v+ = series_k(w) (003's step 3: the velocity method on v+)
    * ``"unlumped2_mtilde"``  the same Dv with m~ for m~_k (003's remark after eq. 2.56):
      v = v+ + series_k(S+S Dv)
    * ``"partial"``  collection, option 2: force from the lumped mass, f dt = m Dv: v = v+ + series_k(Dv)
    * ``"collection"``  collection, option 1: f dt = m x on the conditions' components only, with
      (m~_k^{-1} m x)_b = Dv_b (003 eq. 2.47 for all conditions at once): v = v+ + series_k(x); x by
      conjugate gradients (:func:`_collection_solve`)
    * ``"series_start"``  003 eq. (1.56): v = m~_k^{-1} p^(0) + (m~_k^{-1} - k m^{-1}) Dp^(L)
      = series_k(u) - k dv
    * ``"pinv_start"``  003 eq. (1.69): v = m~_k^{-1}(p^(0) + Dp^(L)) - (m~_{k-1}^{-1} + m^{-1}) Dp^(L)
      = series_k(u) - series_{k-1}(dv) - dv
    """
    check(free is not None,
          f"boundary = {boundary!r} needs the lumped velocity before the velocity conditions, p+/m "
          "(free=...); the series alone sees only the velocity after them")
    check(constraint.wall is None or boundary not in ("unlumped2_mtilde", "partial", "collection"),
          f"boundary = {boundary!r} solves for forces on two-sided conditions (Fixed, Slip, Prescribed); "
          "with jm.Wall use boundary='unlumped1' or 'unlumped2'")
    check(constraint.normal is None and constraint.mirror is None,
          f"boundary = {boundary!r} acts on grid-axis components (Fixed, Slip(face), Prescribed, Wall); "
          "an inclined jm.Slip(normal=...) or a jm.Mirror needs boundary='iterates'")
    dv = u - free  # 003 eq. (1.53): Dv^(L) = v^(L) - v^(L0)
    if boundary == "unlumped1":
        return _full_series(free + transfer.s_plus_s(dv), order, transfer, form)  # 003 eqs. (2.54)-(2.55)
    if boundary == "series_start":
        return _full_series(u, order, transfer, form) - order * dv  # 003 eq. (1.56)
    if boundary == "pinv_start":  # 003 eq. (1.69)
        return _full_series(u, order, transfer, form) - _full_series(dv, order - 1, transfer, form) - dv
    v_plus = _full_series(free, order, transfer, form)  # 003 eq. (2.48): v+ = m~_k^{-1} p+
    if boundary == "unlumped2":
        return constraint.apply(v_plus)  # 003 eq. (2.56), step 3: v+ + Dv
    on = constraint.mask & (transfer.nodal_mass > 0)[:, None]  # the conditions' components that carry mass
    target = jnp.where(on, constraint.value - v_plus, 0.0)  # 003 eqs. (2.47), (2.56): v^(b) - v+_b
    if boundary == "unlumped2_mtilde":
        return v_plus + _full_series(transfer.s_plus_s(target), order, transfer, form)  # m~_k^{-1} m~ Dv
    if boundary == "partial":
        return v_plus + _full_series(target, order, transfer, form)  # m~_k^{-1} m Dv
    return v_plus + _collection_solve(target, on, lambda x: _full_series(x, order, transfer, form),
                                      transfer.nodal_mass)


def _collection_solve(target, on, series, mass, iterations: int = COLLECTION_ITERATIONS):
    """series(x) for the x supported on the components ``on`` that solves (series(x))_on = target_on,
    series(x) = m~_k^{-1} m x: the "Collection of Boundary Conditions", option 1 (003 §2.4), whose
    boundary momenta are m x.  Conjugate gradients in the lumped-mass inner product <a, b> = sum m a.b,
    in which the operator x -> (m~_k^{-1} m x)_on is symmetric positive definite (eigenvalues in
    [1, k)): exact after as many steps as there are constrained components, a fixed ``iterations``
    steps (a ``fori_loop``, differentiable) in place of 003's n_BC + 1 series and dense solve."""
    def dot(a, b):
        return jnp.sum(mass[:, None] * a * b)

    rho0 = dot(target, target)
    floor = rho0 * jnp.finfo(target.dtype).eps ** 2  # converged: stop updating (no 0/0)

    def body(_, carry):
        correction, residual, direction, rho = carry
        image = series(direction)
        curvature = dot(direction, jnp.where(on, image, 0.0))
        active = (rho > floor) & (curvature > 0)
        alpha = jnp.where(active, rho / jnp.where(active, curvature, 1.0), 0.0)
        correction = correction + alpha * image
        residual = residual - alpha * jnp.where(on, image, 0.0)
        rho_new = dot(residual, residual)
        beta = jnp.where(active, rho_new / jnp.where(active, rho, 1.0), 0.0)
        return correction, residual, residual + beta * direction, jnp.where(active, rho_new, rho)

    zero = jnp.zeros_like(target)
    correction, *_ = jax.lax.fori_loop(0, iterations, body, (zero, target, target, rho0))
    return correction


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
        check(boundary in BOUNDARY_MODES[:3],
              f"{type(self).__name__}: boundary = {boundary!r}; choose one of {', '.join(BOUNDARY_MODES[:3])}"
              + ("; the unlumped variants of 003 §2.4 are FMPM's (jm.FMPM(boundary=...))"
                 if boundary in UNLUMPED_MODES else ""))
        check(series in SERIES_FORMS,
              f"{type(self).__name__}: series = {series!r}; choose one of {', '.join(SERIES_FORMS)}")
        self.position = position
        self.boundary = boundary
        self.series = series

    def update(self, V, X, transfer: Transfer, constraint: Constraint, grid: GridSolution, damping: Damping, dt):
        Sv = transfer.gather(grid.v)
        Sa = transfer.gather(grid.a)
        beta = self.beta
        if self.order == 0:
            Svm, beta = Sv, 1.0  # P = I: FLIP (003 Table 2.1, "FMPM(0)/XPIC(0)")
        elif self.order == 1:
            Svm = Sv  # v(1) = v
        else:
            vm = mass_matrix_series(grid.v, self.order, transfer, constraint, self.boundary, self.series)
            correction = contact_series(grid, self.order, transfer, constraint, self.boundary, self.series)
            Svm = transfer.gather(vm if correction is None else vm - correction)  # 003 eq. (3.18)
        A_damp = damping_acceleration(damping, Sv, V)  # 000 eq. (2.77)
        V_new = beta * V + (1.0 - beta) * Svm + (Sa - A_damp) * dt  # 000 eq. (3.28)
        PV = beta * Sv + (1.0 - beta) * Svm  # the blend's P V (000 eq. 2.74)
        X_new = self.position_update(X, V, V_new, Sv, Sa, PV, A_damp, transfer, grid, dt)
        diss = dissipated_energy(transfer.particle_mass, Sa, Sv, V_new - V, X_new - X, dt)
        return ParticleUpdate(V_new, X_new, grid.v_tilde, diss)

    def position_update(self, X, V, V_new, Sv, Sa, PV, A_damp, transfer: Transfer, grid: GridSolution, dt):
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
        return X + (Sv + 0.5 * (Sa - A_damp) * dt) * dt  # "second_order": 000 eq. (2.71), damped


class FLIP(XPIC):
    """FLIP/PIC blend (000 eqs. 2.84-2.86): ``FLIP()`` is pure FLIP, ``FLIP(beta=0.99)`` the classic blend.

    ``FLIP(position="V_end")`` is "Modified FLIP #2" (000 eqs. 2.54-2.56, X += V^{n+1} dt) and
    ``FLIP(beta=alpha, position="V_end")`` the PIC/FLIP blend of Stomakhin et al. (003 §2.3.4);
    ``FLIP(position="V")`` is 000 eq. (2.49)'s second form.  All position options: :class:`XPIC`."""

    def __init__(self, beta=1.0, position: str = "Sv"):
        super().__init__(order=1, beta=beta, position=position)


class PIC(XPIC):
    """PIC: the blend with beta = 0 (000 eq. 2.85 with beta = 0).  ``PIC(position="second_order")``
    is the second-order PIC of 000 eqs. (2.70)-(2.72), ``PIC(position="first_order")`` "Modified
    PIC #1" (000 eqs. 2.64-2.65)."""

    def __init__(self, position: str = "Sv"):
        super().__init__(order=1, beta=0.0, position=position)


class FMPM(Scheme):
    """FMPM(k), full-mass-matrix MPM (003 §2.2-2.3.1, Table 2.1):

        v+ = m~_k^{-1} p+ = sum_{l=1}^{k} (-1)^{l+1} C(k,l) (S+S)^{l-1} v_tilde   (003 eqs. 1.23, 2.13)
        V^{n+1} = S v+ - A_damp dt,    X^{n+1} = X^n + (V^{n+1} + V^n) dt / 2     (003 eq. 2.17)

    ``beta`` (default 0) is jaxmpm's generalisation, not the seeds': a FLIP fraction
    V^{n+1} = beta (V^n + S a dt) + (1 - beta) S v+ - A_damp dt.  FMPM(1) is the "new PIC" of
    003 eq. (2.40).  The strain update uses the full-mass velocities.

    FMPM(0) is FLIP (003 Table 2.1, "FMPM(0)/XPIC(0)": V += a dt, X += (S v_tilde - a dt/2) dt,
    the second-order FLIP of 000 eqs. 2.48-2.49 with VV = S v), computed by the same update as
    ``FLIP()``; its strain update uses the lumped velocities, as FLIP's.
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
        if self.order == 0:
            return v  # FMPM(0) = FLIP: lumped velocities
        check(self.boundary not in UNLUMPED_MODES,
              f"FMPM: boundary = {self.boundary!r} is built for the USL update (its series starts from p+/m "
              "before the conditions); USF/MUSL/USAVG re-extrapolate velocities that have no such start: "
              "use update='USL' or boundary='iterates'")
        return mass_matrix_series(v, self.order, transfer, constraint, self.boundary, self.series)  # 003 eq. (2.3)

    def update(self, V, X, transfer, constraint, grid, damping, dt):
        if self.order == 0:  # 003 Table 2.1: FMPM(0) = XPIC(0) = FLIP
            return XPIC(order=0).update(V, X, transfer, constraint, grid, damping, dt)
        Sv = transfer.gather(grid.v)
        Sa = transfer.gather(grid.a)
        v_plus = mass_matrix_series(grid.v_tilde, self.order, transfer, constraint, self.boundary, self.series,
                                    free=grid.values.get("v_tilde_unconstrained"))  # 003 eq. (2.13)
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
