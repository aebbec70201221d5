"""Modified Cam-Clay elastoplasticity in Hencky strain (clay, snow), with an associated closest-point return."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp

from ..core.registry import Parameter, register_material
from ..core.safe import safe_norm
from ..core.validate import NON_NEGATIVE, POISSON, POSITIVE, Range
from ..transfer.backend import materialise, while_loop
from .linear import DENSITY, NU, E
from .plastic import HenckyPlastic, deviator, principal_norm

# beta <= 1: the ellipse's centre (1 - beta) p0 / 2 stays on the compressive side, so that p - p_c grows
# with the plastic volume change (the return's bracket, CamClay._project) and tension is no stronger than
# compression
COHESION_RATIO = Range(0, 1, fix="the cohesion ratio beta in [0, 1]: tensile strength beta p0 (Gaume et al. "
                       "2018); 0 has none")
SQRT_6 = math.sqrt(6.0)
SQRT_2_3 = math.sqrt(2.0 / 3.0)
END_ITERATIONS = 4  # Newton for the bracket's end, where p = p_c (monotone after its first step)
ITERATIONS = 24  # safeguarded Newton on dv (bracketed), then one plain Newton step


class CamClay(HenckyPlastic):
    """Modified Cam-Clay (Roscoe & Burland 1968) in principal Hencky strain, the elliptic yield
    surface of the MPM snow and clay models (Gaume et al. 2018, Methods, "Constitutive model"; Wolper
    et al. 2019 "CD-MPM" §4), with an associated flow and a closest-point return.

    In the invariants of the Kirchhoff stress, p = -tr tau / 3 (compression positive) and
    q = sqrt(3/2) |dev tau| (the von Mises stress),

        f(p, q; p0) = (1 + 2 beta) q^2 + M^2 (p + beta p0)(p - p0) <= 0,

    an ellipse through (-beta p0, 0) and (p0, 0), centre p_c = (1 - beta) p0 / 2, semi-axes
    a = (1 + beta) p0 / 2 along p and M a / sqrt(1 + 2 beta) along q: f = (1 + 2 beta) q^2 +
    M^2 ((p - p_c)^2 - a^2).  With beta = 0 (the default) it is Roscoe & Burland's ellipse through the
    origin, with no strength in tension; beta > 0 adds the cohesion of Gaume et al. (tensile
    strength beta p0).  M is the slope of the critical state line: at the ellipse's top, where
    df/dp = 0, plastic flow is isochoric and for beta = 0 q / p = M.

    Elasticity is the Hencky law of :class:`HenckyPlastic` (constant bulk modulus K = E / (3 (1 -
    2 nu)) and shear modulus mu; p = -K tr(eps), q = 3 mu eps_s with eps_s = sqrt(2/3) |dev eps|),
    as in the MPM snow models, not Cam-Clay's pressure-dependent kappa law.

    **Hardening** from the volumetric plastic strain eps_v^p = ln J_p (negative in compaction),
    exponential as in the natural-strain Cam-Clay (Butterfield 1979, the "ln v - ln p" compression
    law; Borja & Tamagnini 1998, its finite-strain Cam-Clay):

        p0 = p0_init exp(-xi eps_v^p),    xi = 1 / (lambda* - kappa*) >= 0  (``hardening``),

    compaction hardens, dilation softens; xi = 0 is perfect plasticity.  p0 is a closed-form
    function of eps_v^p, so it carries no integration error.  (Gaume et al.'s snow law p0 = K
    sinh(xi max(-eps_v^p, 0)) starts from p0 = 0; the exponential keeps an initial p0 > 0.)

    **Return mapping** (backward Euler, associated: the plastic strain increment d_gamma df/dtau):
    in principal strains df/dtau = -(1/3) df/dp 1 + sqrt(3/2) df/dq n, n = dev tau / |dev tau|, so

        q = q* / (1 + 6 mu (1 + 2 beta) d_gamma)            (dev eps = dev eps* q / q*)
        p = p* + K dv,    dv = -d_gamma df/dp = -2 M^2 d_gamma (p - p_c(p0)),   p0 = p0_n exp(-xi dv)
        f(p, q; p0) = 0

    (the closest-point projection in the elastic energy metric: Simo & Hughes 1998, "Computational
    Inelasticity", ch. 3).  Two unknowns (d_gamma, dv), but given dv everything else is closed-form
    (p0, p, then d_gamma from the second line and q from the first), so the return is one scalar
    equation in dv, solved by a bracketed Newton iteration (:meth:`_project`) that stops when every
    particle's step is at round-off: a closed-form first step, then 1 iteration per step in mpm88, at
    most 24.  Where the trial state is elastic the solver runs on a point outside the ellipse and its
    result is discarded (``jnp.where`` on both sides), so values and derivatives stay finite everywhere.

    Per-particle state (saved fields): ``plastic_strain`` the accumulated equivalent plastic
    strain sum sqrt(2/3) |d eps^p| (volumetric and deviatoric; J2's measure where the flow is
    isochoric), ``volumetric_plastic_strain`` eps_v^p = ln J_p, ``preconsolidation_pressure`` p0.

    Args:
        E: Young's modulus, positive (stress units); with nu it sets K and mu.
        nu: Poisson's ratio in (-1, 0.5); default 0.3.
        M: the slope of the critical state line, positive (sand and clay ~0.8-1.5; M = 6 sin phi /
            (3 - sin phi) in triaxial compression); default 1.0.
        p0: the initial pre-consolidation pressure, positive (stress units): the isotropic
            compressive stress at first yield; default 1.0.
        hardening: xi >= 0, the hardening exponent of p0 with the volumetric plastic strain
            (dimensionless, 1 / (lambda* - kappa*)); default 0, perfect plasticity.
        beta: the cohesion ratio in [0, 1] (Gaume et al. 2018): the tensile strength is beta p0;
            default 0.
        density: the reference density rho_0, positive; default 1.0.
    """

    M: jnp.ndarray
    p0: jnp.ndarray
    hardening: jnp.ndarray
    beta: jnp.ndarray
    saved_state = ("plastic_strain", "volumetric_plastic_strain", "preconsolidation_pressure")

    def __init__(self, E, nu=0.3, M=1.0, p0=1.0, hardening=0.0, beta=0.0, density=1.0):
        self.E = POSITIVE.leaf("CamClay", "E", E)
        self.nu = POISSON.leaf("CamClay", "nu", nu)
        self.M = POSITIVE.leaf("CamClay", "M", M, fix="the critical state line's slope q/p, e.g. 1.2")
        self.p0 = POSITIVE.leaf("CamClay", "p0", p0, fix="the pre-consolidation pressure (stress units, "
                                "compression positive) sets the ellipse's size")
        self.hardening = NON_NEGATIVE.leaf(
            "CamClay", "hardening", hardening, fix="xi >= 0: p0 = p0_init exp(-xi eps_v^p); 0 is perfect plasticity")
        self.beta = COHESION_RATIO.leaf("CamClay", "beta", beta)
        self.density = POSITIVE.leaf("CamClay", "density", density)

    # ------------------------------------------------------------------ moduli and the surface
    def moduli(self):
        """(K, mu): the Hencky law's bulk and shear moduli."""
        return self.E / (3.0 * (1.0 - 2.0 * self.nu)), self.E / (2.0 * (1.0 + self.nu))

    def preconsolidation(self, volumetric_plastic_strain):
        """p0 = p0_init exp(-xi eps_v^p) (Butterfield 1979; Borja & Tamagnini 1998)."""
        return self.p0 * jnp.exp(-self.hardening * volumetric_plastic_strain)

    def yield_function_pq(self, p, q, p0):
        """f = (1 + 2 beta) q^2 + M^2 (p + beta p0)(p - p0) (Gaume et al. 2018, Methods)."""
        return (1.0 + 2.0 * self.beta) * q * q + self.M ** 2 * (p + self.beta * p0) * (p - p0)

    def yield_function(self, tau, preconsolidation_pressure):
        """f on principal Kirchhoff stresses (..., 3): p = -tr tau / 3, q = sqrt(3/2) |dev tau|."""
        dev, mean = deviator(tau)
        return self.yield_function_pq(-mean, math.sqrt(1.5) * safe_norm(dev), preconsolidation_pressure)

    def flow_direction(self, tau, preconsolidation_pressure):
        """df/dtau in principal components (..., 3): -(1/3) df/dp 1 + sqrt(3/2) df/dq n
        (the associated plastic strain rate's direction)."""
        return jax.grad(lambda t: jnp.sum(self.yield_function(t, preconsolidation_pressure)))(tau)

    # ------------------------------------------------------------------ the return
    def initial_plastic_state(self, n, dtype):
        # preconsolidation_pressure is a record: the return recomputes p0 from eps_v^p and the
        # parameter p0, so a p0 changed by set_params (or differentiated) takes effect
        zero = jnp.zeros((n,), dtype)
        return {"plastic_strain": zero, "volumetric_plastic_strain": zero,
                "preconsolidation_pressure": jnp.broadcast_to(self.p0, (n,)).astype(dtype)}

    def return_mapping(self, eps_trial, plastic):
        K, mu = self.moduli()
        ev_p = plastic["volumetric_plastic_strain"]
        p0_n = self.preconsolidation(ev_p)
        dev, mean = deviator(eps_trial)
        p_trial = -3.0 * K * mean
        q_trial = SQRT_6 * mu * principal_norm(dev)
        yields = self.yield_function_pq(p_trial, q_trial, p0_n) > 0.0
        # elastic particles solve on (p_c + 2a, 0), outside the ellipse, and discard the result
        centre, semi = 0.5 * (1.0 - self.beta) * p0_n, 0.5 * (1.0 + self.beta) * p0_n
        p_star = jnp.where(yields, p_trial, centre + 2.0 * semi)
        q_star = jnp.where(yields, q_trial, 0.0)
        d_gamma, dv = self._project(p_star, q_star, p0_n, K, mu)
        d_gamma, dv = jnp.where(yields, d_gamma, 0.0), jnp.where(yields, dv, 0.0)
        # once per particle, not once per principal strain and consumer (a stage boundary: XLA:CPU would
        # repeat the solver's last step in every fusion that reads them)
        d_gamma, dv = materialise((d_gamma, dv))

        shrink = 1.0 / (1.0 + 6.0 * mu * (1.0 + 2.0 * self.beta) * d_gamma)  # q / q*
        eps = dev * shrink[..., None] + (mean - dv / 3.0)[..., None]
        eps = jnp.where(yields[..., None], eps, eps_trial)
        ev_p = ev_p + dv
        return eps, {"plastic_strain": plastic["plastic_strain"] + SQRT_2_3 * principal_norm(eps_trial - eps),
                     "volumetric_plastic_strain": ev_p,
                     "preconsolidation_pressure": self.preconsolidation(ev_p)}

    def _return_point(self, dv, p_star, q_star, p0_n, K, mu):
        """(rho / (M a) - 1, d_gamma) at the return point whose plastic volume change is ``dv``, with
        rho^2 = (1 + 2 beta) q^2 + M^2 (p - p_c)^2, so that f = rho^2 - (M a)^2: the distance of the
        point from the ellipse along its ray from the centre, in units of the semi-axis M a.

        Everything follows from dv in closed form: p0 = p0_n exp(-xi dv), p = p* + K dv, and the flow
        rule's volumetric part dv = -d_gamma df/dp = -2 M^2 d_gamma (p - p_c) gives d_gamma =
        -dv / (2 M^2 (p - p_c)); with c_q = 6 mu (1 + 2 beta), 1 + c_q d_gamma = (2 M^2 (p - p_c) -
        c_q dv) / (2 M^2 (p - p_c)) and q = q* / (1 + c_q d_gamma)."""
        M2 = self.M ** 2
        p0 = p0_n * jnp.exp(-self.hardening * dv)
        offset = p_star + K * dv - 0.5 * (1.0 - self.beta) * p0  # p - p_c
        pull = 2.0 * M2 * offset  # df/dp
        c_q = 6.0 * mu * (1.0 + 2.0 * self.beta)
        shrink = pull - c_q * dv  # pull (1 + c_q d_gamma): > 0 on the bracket
        q = q_star * pull / jnp.where(shrink == 0.0, 1.0, shrink)  # 0 only where dv = p - p_c = 0
        rho2 = (1.0 + 2.0 * self.beta) * q * q + M2 * offset * offset  # elementwise: no short reduction
        rho = jnp.where(rho2 > 0.0, jnp.sqrt(jnp.where(rho2 > 0.0, rho2, 1.0)), 0.0)  # NaN-free derivative at 0
        semi = 0.5 * (1.0 + self.beta) * p0
        return rho / (self.M * semi) - 1.0, self._plastic_multiplier(dv, offset, semi, pull, q_star, c_q)

    def _at_trial(self, p_star, q_star, p0_n, K, mu):
        """(g, dg/d dv) of :meth:`_return_point` at dv = 0, the trial point, in closed form: there
        p0 = p0_n and q = q*, and with d = p* - p_c, rho^2 = (1 + 2 beta) q*^2 + M^2 d^2, dp0/d dv =
        -xi p0, d'(0) = K + xi p_c, q'(0) = c_q q* / (2 M^2 d) (the flow rule's 1 + c_q d_gamma), so
        g'(0) = (rho' + xi rho) / (M a) with rho' = ((1 + 2 beta) q* q' + M^2 d d') / rho."""
        M2, xi = self.M ** 2, self.hardening
        centre, semi = 0.5 * (1.0 - self.beta) * p0_n, 0.5 * (1.0 + self.beta) * p0_n
        offset = p_star - centre
        pull = 2.0 * M2 * offset
        dq = 6.0 * mu * (1.0 + 2.0 * self.beta) * q_star / jnp.where(pull == 0.0, 1.0, pull)
        rho2 = (1.0 + 2.0 * self.beta) * q_star * q_star + M2 * offset * offset
        rho = jnp.sqrt(jnp.where(rho2 > 0.0, rho2, 1.0))
        drho = ((1.0 + 2.0 * self.beta) * q_star * dq + M2 * offset * (K + xi * centre)) / rho
        return rho / (self.M * semi) - 1.0, (drho + xi * rho) / (self.M * semi)

    def _plastic_multiplier(self, dv, offset, semi, pull, q_star, c_q):
        """d_gamma at the root, from whichever relation is well conditioned there: -dv / df/dp near
        the apices, and near the ellipse's top, where both dv and p - p_c vanish, from q on the
        ellipse, q = M sqrt((a^2 - (p - p_c)^2) / (1 + 2 beta)) = q* / (1 + c_q d_gamma)."""
        top = jnp.abs(offset) < 0.5 * semi
        q_top = self.M * jnp.sqrt(jnp.where(top, (semi * semi - offset * offset) / (1.0 + 2.0 * self.beta), 1.0))
        from_q = (q_star / q_top - 1.0) / c_q
        from_dv = -dv / jnp.where(pull == 0.0, 1.0, pull)
        return jnp.where(top, from_q, from_dv)

    def _project(self, p_star, q_star, p0_n, K, mu):
        """(d_gamma, dv) of the closest-point return of a trial (p*, q*) outside the ellipse, with
        hardening, as one scalar equation in the plastic volume change dv (:meth:`_return_point`):
        g(dv) = rho / (M a) - 1 = 0 at p(dv), q(dv), p0(dv), with no inner solve.

        The bracket: the return point lies between the trial point and the ellipse's centre, p - p_c
        keeps the sign of p* - p_c(p0_n) and dv the opposite one (a compaction, p* > p_c, has dv < 0
        and hardens; a dilation softens).  p - p_c = p* + K dv - (1 - beta) p0_n exp(-xi dv) / 2 is
        increasing and concave in dv; where it vanishes, d_gamma -> inf, q -> 0 and g = -1, while
        g(0) > 0 (the trial state is outside).  That end, dv_e, is found by Newton on p - p_c from
        its positive side (concave: the first step lands on the negative side, then monotone: exact
        in one step without hardening or with beta = 1).  Where the return softens a far tensile
        trial onto a shrunken ellipse, the root lies exponentially close to dv_e and bisection steps
        do the converging (24 iterations at most: random trials with strains to 0.5 in one step and
        xi to 20 agree with the nested solver this one replaced, a Newton on ln p0 around a Newton
        on the fixed ellipse, to 1e-12 of the strain).  Newton on g safeguarded by bisection on
        [dv_e, 0] runs until every particle's step is at round-off, then one plain Newton step
        outside the loop makes the derivative the implicit one of the root."""
        xi, half_cohesionless = self.hardening, 0.5 * (1.0 - self.beta) * p0_n

        def offset(dv):  # p - p_c and its slope in dv
            hardened = half_cohesionless * jnp.exp(-xi * dv)
            return p_star + K * dv - hardened, K + xi * hardened

        def g(dv):
            return self._return_point(dv, p_star, q_star, p0_n, K, mu)[0]

        def newton(dv):
            value, slope = jax.jvp(g, (dv,), (jnp.ones_like(dv),))
            return value, dv - value / jnp.where(slope == 0.0, 1.0, slope)

        def safeguarded(bracket):
            dv, inside, outside, _, iteration = bracket  # g(inside) < 0 < g(outside)
            value, step = newton(dv)
            inside, outside = jnp.where(value < 0.0, dv, inside), jnp.where(value < 0.0, outside, dv)
            lo, hi = jnp.minimum(inside, outside), jnp.maximum(inside, outside)
            # Newton where it stays in the bracket and at most halves it (no cycling), else bisection
            accept = (step >= lo) & (step <= hi) & (2.0 * jnp.abs(step - dv) <= hi - lo)
            # |g| <= sqrt(eps) (g is relative): Newton's step from here, then the plain one after the loop,
            # leave an error of order g^2 <= eps
            converged = jnp.abs(value) <= math.sqrt(jnp.finfo(dv.dtype).eps)
            return jnp.where(accept, step, 0.5 * (lo + hi)), inside, outside, jnp.all(converged), iteration + 1

        def searching(bracket):
            return (bracket[4] < ITERATIONS) & ~bracket[3]

        def root(p_star, q_star, p0_n):
            start = p_star - half_cohesionless  # p* - p_c(p0_n): > 0 compaction, < 0 dilation
            # a step changes p0 by at most a factor exp(L), L = ln(max float) / 4 (177 in float64, 22 in
            # float32), so that exp(-xi dv) stays finite; no physical step comes near it
            cap = 0.25 * math.log(jnp.finfo(p_star.dtype).max) / jnp.maximum(xi, 1e-30)
            end = jnp.where(start > 0.0, 0.0, -start / K)  # p - p_c >= 0 there (exp(-xi dv) <= 1 for dv >= 0)
            for _ in range(END_ITERATIONS):
                value, slope = offset(end)
                end = jnp.clip(end - value / slope, -cap, cap)
            end = jnp.where(start == 0.0, 0.0, end)
            zero = jnp.zeros_like(end)
            # the first Newton step, from the trial point (dv = 0), in closed form (no exponential), then
            # the loop until every particle's |g| <= sqrt(eps): one iteration for an MPM step's increments
            value, slope = self._at_trial(p_star, q_star, p0_n, K, mu)
            lo, hi = jnp.minimum(end, 0.0), jnp.maximum(end, 0.0)
            step = -value / jnp.where(slope == 0.0, 1.0, slope)
            accept = (step >= lo) & (step <= hi) & (2.0 * jnp.abs(step) <= hi - lo)
            first = (jnp.where(accept, step, 0.5 * (lo + hi)), end, zero, jnp.asarray(False), 1)
            return while_loop(searching, safeguarded, first)[0]

        dv = jax.lax.stop_gradient(root(*jax.lax.stop_gradient((p_star, q_star, p0_n))))
        dv = jnp.where(dv == 0.0, 0.0, newton(dv)[1])  # dv = 0: only a trial on the ellipse's top (p* = p_c)
        d_gamma = self._return_point(dv, p_star, q_star, p0_n, K, mu)[1]
        return d_gamma, dv

M_SLOPE = Parameter("M", lambda m: m.M, "slope of the critical state line", "positive", valid=POSITIVE)
P0 = Parameter("p0", lambda m: m.p0, "initial pre-consolidation pressure", "positive", valid=POSITIVE)
HARDENING = Parameter("hardening", lambda m: m.hardening, "hardening exponent xi of p0 with ln J_p", "positive",
                      valid=NON_NEGATIVE)
BETA = Parameter("beta", lambda m: m.beta, "cohesion ratio (tensile strength beta p0)", "positive",
                 valid=COHESION_RATIO)

register_material("cam_clay", CamClay, parameters=[E, NU, M_SLOPE, P0, HARDENING, BETA, DENSITY])
