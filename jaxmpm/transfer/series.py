"""The mass-matrix series of the seeds, one operator on the transfer layer.

With S+S the XPIC / FMPM kernel (``Transfer.s_plus_s``: gather to the particles, mass-weighted
scatter back, 000 eq. 3.19), every use of the full mass matrix in the seeds is one polynomial,

    series_m(u) = sum_{r=1}^{m} (-1)^{r+1} C(m, r) (P S+S)^{r-1} u          000 eqs. (3.22)-(3.25)

(P a projection on the free components of a velocity field, or the identity), which is
m~_m^{-1} m u, the order-m approximation of the consistent mass matrix's inverse applied to the
lumped momenta (003 eqs. 1.23, 2.3-2.5).  Its users:

* XPIC(m)'s v(m) and FMPM(k)'s v+ (``jaxmpm.schemes``): :func:`mass_matrix_series`, with the
  velocity conditions of 003 §1.5 and §2.4 (``boundary``: constrained iterates, the result, the
  lumped method, the unlumped variants and the collection solve);
* the momentum exchange between velocity fields (contact): :func:`exchange_series`, the term
  m~_{k-1}^{-1} Dp of 003 eqs. (3.16)-(3.22); or, NairnMPM's form, the exchange applied to every
  increment of the series (:func:`incremental_series`, :func:`exchange_increments`);
* the XPIC stress smoothing (000 §3.7, ``jaxmpm.physics.stress``) and the XPIC transport update
  (000 §3.6, ``jaxmpm.physics.transport``): :func:`series` itself.

Velocity conditions enter through a ``constraint`` with ``zero``, ``apply``, ``prescribed``,
``mask``, ``value``, ``wall``, ``normal``, ``mirror`` and ``inhomogeneous``
(:class:`jaxmpm.Constraint`); this module does not import it.
"""

from __future__ import annotations

import jax.numpy as jnp

from ..core.errors import check
from .backend import fori_loop

BOUNDARY_MODES = ("iterates", "result", "lumped", "unlumped1", "unlumped2", "unlumped2_mtilde", "partial",
                  "collection", "series_start", "pinv_start")


# XPIC's own mode (not FMPM's): NairnMPM 19.0's start of the XPIC series (``unconstrained_series``)
XPIC_BOUNDARY_MODES = BOUNDARY_MODES[:3] + ("unconstrained_start",)


# the modes of 003 §1.5 (eqs. 1.51-1.69) and §2.4 (eqs. 2.54-2.56, "Collection of Boundary Conditions")
# that need p+/m before the velocity conditions (``free`` of :func:`mass_matrix_series`)
UNLUMPED_MODES = BOUNDARY_MODES[3:]


COLLECTION_ITERATIONS = 24  # conjugate-gradient steps of boundary="collection" (exact after n_BC steps)


SERIES_FORMS = ("binomial", "neumann")


def series(start, order: int, transfer, project=None, form: str = "binomial"):
    """sum_{r=1}^{m} (-1)^{r+1} C(m, r) (P S+S)^{r-1} start, m = ``order`` >= 1, P = ``project`` (a
    function on nodal fields, the projection on free components; None: the identity), in the
    ``form`` "binomial" (000 eqs. 3.22-3.24) or "neumann" (the same polynomial as
    sum_{j<m} (I - P S+S)^j start; see :func:`mass_matrix_series`).  A ``fori_loop`` of
    ``transfer.s_plus_s``: differentiable, and its length is static.

    Args:
        start: the nodal field the series acts on, (n, C).
        order: m >= 1, the number of terms (static; 1 returns ``start``).
        transfer: the step's :class:`jaxmpm.Transfer` (its ``s_plus_s``).
        project: a function on nodal fields applied after every S+S (the projection on the free
            components of a velocity field), or None (the default) for the identity.
        form: "binomial" (the default) or "neumann", the same polynomial summed two ways.
    """
    if project is None:
        project = _identity
    if order == 1:
        return start
    if form == "binomial":

        def body(r, carry):
            term, total = carry
            term = project((order - r + 1) / r * transfer.s_plus_s(term))  # 000 eq. (3.23)
            sign = jnp.where(r % 2 == 1, 1.0, -1.0)
            return term, total + sign * term  # 000 eq. (3.22)

        first = order * start  # 000 eq. (3.24)
        _, total = fori_loop(2, order + 1, body, (first, first))
        return total

    def body(j, carry):
        term, total = carry
        term = term - project(transfer.s_plus_s(term))  # (I - P S+S)^j start
        return term, total + term

    _, total = fori_loop(1, order, body, (start, start))
    return total


def _identity(w):
    return w


def full_series(x, order: int, transfer, form: str = "binomial"):
    """m~_k^{-1} m x = sum_{l=1}^{k} C_kl (S+S)^{l-1} x, no conditions (003 eqs. 1.23, 1.70); m~_0^{-1} = 0."""
    if order == 0:
        return jnp.zeros_like(x)
    return series(x, order, transfer, None, form)


def mass_matrix_series(
    u, order: int, transfer, constraint, boundary: str = "iterates", form: str = "binomial",
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
      * ``"unconstrained_start"`` (XPIC only): NairnMPM's series, which starts from the lumped
        velocity before the conditions (``free`` = p/m) and zeroes only the increments
        (:func:`unconstrained_series`).

    Args:
        u: the lumped nodal velocity with the velocity conditions imposed, (n, D).
        order: m >= 1, the series order (XPIC's m, FMPM's k; static).
        transfer: the step's :class:`jaxmpm.Transfer`.
        constraint: the velocity conditions (:class:`jaxmpm.Constraint`).
        boundary: how the conditions enter, one of the modes above (default "iterates").
        form: "binomial" (the default) or "neumann".
        free: the lumped velocity before the conditions, p+/m (or p/m); needed by the
            unlumped modes and "unconstrained_start", else None (the default).
    """
    if boundary in UNLUMPED_MODES:
        return unlumped_series(u, free, order, transfer, constraint, boundary, form)
    if order == 1:
        return u
    if boundary == "unconstrained_start":
        return unconstrained_series(u, free, order, transfer, constraint, form)
    if boundary != "iterates":
        total = series(u, order, transfer, None, form)
        return constraint.apply(total) if boundary == "result" else total
    # the constrained system (003 eqs. 1.49-1.50): Z zeroes the constrained components,
    # v = g + sum_{j<m} (I - Z S+S)^j Z u - sum_{j<m-1} (I - Z S+S)^j Z S+S g,
    # the order-m Richardson iterate of Z (S+S v - u) = 0 from v_0 = g + Z u; for g = 0 (Fixed,
    # Slip) it is the series of Z u; the g-terms keep a body moving with a moving wall exactly
    total = series(constraint.zero(u), order, transfer, constraint.zero, form)
    if constraint.inhomogeneous:
        g = constraint.prescribed(u)
        coupling = constraint.zero(transfer.s_plus_s(g))
        total = total + g - series(coupling, order - 1, transfer, constraint.zero, form)
    return total


def unconstrained_series(u, free, order: int, transfer, constraint, form: str = "binomial"):
    """NairnMPM 19.0's XPIC(m) series on constrained nodes (NairnMPM_Class/XPICExtrapolationTask,
    Nodes/MatVelocityField XPICSupport): it starts from the lumped velocity before the conditions,
    w = ``free`` = p/m on every node, and zeroes on the constrained components only the increments,

        v(m) = sum_{j=0}^{m-1} [Z (I - S+S)]^j w                (Z: zero the constrained components)

    Split w = Z w + g_w (g_w = w - Z w, the constrained components' unconstrained values): the sum
    is the constrained system of :func:`mass_matrix_series` (003 eqs. 1.49-1.50) with g_w in place
    of the prescribed velocity g,

        v(m) = g_w + sum_{j<m} (I - Z S+S)^j Z w - sum_{j<m-1} (I - Z S+S)^j Z S+S g_w,

    so the constrained nodes' unconstrained velocities couple into the free ones as a prescribed
    velocity would.  The result's constrained components are those of ``u`` (the grid velocity with
    its conditions): the conditions hold on v(m) + a dt as in every other mode."""
    check(free is not None, "boundary = 'unconstrained_start' needs the lumped velocity before the velocity "
                            "conditions, p/m (free=...)")
    check(constraint.wall is None and constraint.normal is None and constraint.mirror is None,
          "boundary = 'unconstrained_start' (NairnMPM's XPIC series) acts on grid-axis components (Fixed, "
          "Slip(face), Prescribed); with jm.Wall, an inclined jm.Slip or a jm.Mirror use boundary='iterates'")
    g_w = free - constraint.zero(free)
    total = series(constraint.zero(free), order, transfer, constraint.zero, form)
    coupling = constraint.zero(transfer.s_plus_s(g_w))
    total = total - series(coupling, order - 1, transfer, constraint.zero, form)
    return total + (u - constraint.zero(u))  # total: free components; u: the constrained


def exchange_series(dv, order: int, transfer, constraint, boundary: str = "iterates", form: str = "binomial"):
    """(m~_{k-1}^a)^{-1} Dp^a = the order k-1 series of Dv^a = Dp^a / m^a, the momentum exchange's
    term XPIC(k) and FMPM(k) subtract when velocity fields exchange momentum (contact: 003 eqs.
    3.16-3.18, 3.22; m~_0^{-1} = 0 by 003 eq. 3.15 at k = 1).  None when there is no exchange
    (``dv`` None) or k = 1.  Homogeneous: Dv^a is zero on constrained components and stays so (no
    prescribed-velocity terms, unlike :func:`mass_matrix_series`).

    Args:
        dv: Dv^a = Dp^a / m^a, the velocity change of the momentum exchange, (n, D); or None.
        order: k, the scheme's series order (the series has order k - 1).
        transfer: the step's :class:`jaxmpm.Transfer`.
        constraint: the velocity conditions (:class:`jaxmpm.Constraint`).
        boundary: the scheme's boundary mode: under "iterates" (the default) and
            "unconstrained_start" every iterate has its constrained components zeroed; under
            the others the series runs without the conditions.
        form: "binomial" (the default) or "neumann".
    """
    if dv is None or order == 1:
        return None
    project = constraint.zero if boundary in ("iterates", "unconstrained_start") else None
    return series(dv if project is None else project(dv), order - 1, transfer, project, form)


# the series modes whose increments are the constrained iterates Z (I - S+S) D, where an exchange can act
INCREMENTAL_MODES = ("iterates", "unconstrained_start")


def exchange_increments(start, order: int, transfer, project, exchange):
    """The series sum_{k=1}^{m} D_k summed as increments with an exchange acting on each, m = ``order``:

        D_1 = start,   D_k = R_k + E_k,   R_k = P (I - S+S) D_{k-1},   (E_k, c_k) = exchange.adjust(R_k, c_{k-1})

    (c_1 = ``exchange.initial()``; P = ``project``, None the identity).  Without an exchange (E_k = 0)
    this is :func:`series` in the "neumann" form, sum_{j<m} (P (I - S+S))^j start.  Returns the sum
    and sum_k E_k, the exchange's share of it.  NairnMPM 19.0's XPIC/FMPM loop
    (NairnMPM_Class/XPICExtrapolationTask Execute, GetDeltaV, UpdateXStar; Nodes/MatVelocityField
    XPICSupport): D_k from S+S of the previous increment, the velocity conditions zeroed, then the
    contact law on the increment (``exchange``: :class:`jaxmpm.physics.contact.ContactIncrements`).  A
    ``fori_loop`` of ``order - 1`` steps carrying the exchange's state: differentiable, static length."""
    if project is None:
        project = _identity
    zero = jnp.zeros_like(start)
    if order == 1:
        return start, zero

    def body(_, carry):
        term, total, exchanged, state = carry
        term = project(term - transfer.s_plus_s(term))  # R_k = P (I - S+S) D_{k-1}
        change, state = exchange.adjust(term, state)
        term = term + change
        return term, total + term, exchanged + change, state

    _, total, exchanged, _ = fori_loop(1, order, body, (start, start, zero, exchange.initial()))
    return total, exchanged


def incremental_series(u, order: int, transfer, constraint, exchange, boundary: str = "iterates", free=None):
    """XPIC(m)'s v(m) or FMPM(k)'s v+ with the momentum exchange on every increment of the series
    (contact's ``series="incremental"``, NairnMPM's rule), in place of :func:`mass_matrix_series`
    minus :func:`exchange_series`.  ``u`` is the lumped velocity after the exchange with the
    conditions; the series (:func:`exchange_increments`, P = ``constraint.zero``) starts from

    * ``boundary="iterates"``: Z u + g (g the prescribed velocities; = u where u meets the
      conditions), the constrained system of :func:`mass_matrix_series` (the same sum without an
      exchange: the increments Z (I - S+S) D stay in the range of Z);
    * ``boundary="unconstrained_start"`` (XPIC): ``free`` = p/m before the conditions, as
      :func:`unconstrained_series`.

    Returns (v, e): v the sum with the constrained components of ``u`` (the conditions hold on the
    result, as in every mode; the exchange acts after the zeroing, NairnMPM's order, so it may move
    a constrained component inside the series), e = Z sum_k E_k the exchange's share (XPIC takes it as
    a force, NairnMPM's ``AddFtotScaled``)."""
    check(boundary in INCREMENTAL_MODES,
          f"boundary = {boundary!r} with the exchange on the series' increments (jm.Contact(series='incremental')): "
          f"it is built for the constrained iterates; use boundary={' or '.join(map(repr, INCREMENTAL_MODES))}, "
          "or jm.Contact(series='separate')")
    if boundary == "unconstrained_start":
        check(free is not None, "boundary = 'unconstrained_start' needs the lumped velocity before the velocity "
                                "conditions, p/m (free=...)")
        check(constraint.wall is None and constraint.normal is None and constraint.mirror is None,
              "boundary = 'unconstrained_start' (NairnMPM's XPIC series) acts on grid-axis components (Fixed, "
              "Slip(face), Prescribed); with jm.Wall, an inclined jm.Slip or a jm.Mirror use boundary='iterates'")
        start = free
    else:
        start = constraint.zero(u)
        if constraint.inhomogeneous:
            start = start + constraint.prescribed(u)
    total, exchanged = exchange_increments(start, order, transfer, constraint.zero, exchange)
    return constraint.zero(total) + (u - constraint.zero(u)), constraint.zero(exchanged)


def unlumped_series(u, free, order: int, transfer, constraint, boundary: str, form: str = "binomial"):
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
        return full_series(free + transfer.s_plus_s(dv), order, transfer, form)  # 003 eqs. (2.54)-(2.55)
    if boundary == "series_start":
        return full_series(u, order, transfer, form) - order * dv  # 003 eq. (1.56)
    if boundary == "pinv_start":  # 003 eq. (1.69)
        return full_series(u, order, transfer, form) - full_series(dv, order - 1, transfer, form) - dv
    v_plus = full_series(free, order, transfer, form)  # 003 eq. (2.48): v+ = m~_k^{-1} p+
    if boundary == "unlumped2":
        return constraint.apply(v_plus)  # 003 eq. (2.56), step 3: v+ + Dv
    on = constraint.mask & (transfer.nodal_mass > 0)[:, None]  # the conditions' components that carry mass
    target = jnp.where(on, constraint.value - v_plus, 0.0)  # 003 eqs. (2.47), (2.56): v^(b) - v+_b
    if boundary == "unlumped2_mtilde":
        return v_plus + full_series(transfer.s_plus_s(target), order, transfer, form)  # m~_k^{-1} m~ Dv
    if boundary == "partial":
        return v_plus + full_series(target, order, transfer, form)  # m~_k^{-1} m Dv
    return v_plus + collection_solve(target, on, lambda x: full_series(x, order, transfer, form),
                                      transfer.nodal_mass)


def collection_solve(target, on, series, mass, iterations: int = COLLECTION_ITERATIONS):
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
    correction, *_ = fori_loop(0, iterations, body, (zero, target, target, rho0))
    return correction
