"""Modified Cam-Clay elastoplasticity in Hencky strain (clay, snow), with an associated closest-point return."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp

from ..core.registry import Parameter, register_material
from ..core.safe import safe_norm
from ..core.validate import NON_NEGATIVE, POISSON, POSITIVE
from .linear import DENSITY, NU, E
from .plastic import HenckyPlastic, deviator

SQRT_6 = math.sqrt(6.0)
SQRT_2_3 = math.sqrt(2.0 / 3.0)
PREDICTOR_ITERATIONS = 12  # Newton on the fixed ellipse (monotone, from below): round-off by ~6
HARDENING_ITERATIONS = 16  # safeguarded Newton on ln p0 (bracketed), then one plain Newton step


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
    Inelasticity", ch. 3).  Two unknowns (d_gamma, dv).  First the fixed-ellipse problem (p0 = p0_n): p - p_c =
    (p* - p_c) / (1 + 2 K M^2 d_gamma), and psi(d_gamma) = 1 / rho - 1 / (M a) with rho^2 = (1 +
    2 beta) q^2 + M^2 (p - p_c)^2 is increasing and concave in d_gamma >= 0 (1 / rho is a power
    mean of exponent -2 of functions linear in d_gamma), so Newton from d_gamma = 0 converges
    monotonically from below and is exact in one step where the two metrics coincide; then a few
    Newton steps on the coupled pair add the hardening.  Where the trial state is elastic the
    solver runs on a point outside the ellipse and its result is discarded (``jnp.where`` on both
    sides), so values and derivatives stay finite everywhere.

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
        beta: the cohesion ratio >= 0 (Gaume et al. 2018): the tensile strength is beta p0;
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
        self.beta = NON_NEGATIVE.leaf("CamClay", "beta", beta, fix="the cohesion ratio: tensile strength beta p0")
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
        q_trial = SQRT_6 * mu * safe_norm(dev)
        yields = self.yield_function_pq(p_trial, q_trial, p0_n) > 0.0
        # elastic particles solve on (p_c + 2a, 0), outside the ellipse, and discard the result
        centre, semi = 0.5 * (1.0 - self.beta) * p0_n, 0.5 * (1.0 + self.beta) * p0_n
        p_star = jnp.where(yields, p_trial, centre + 2.0 * semi)
        q_star = jnp.where(yields, q_trial, 0.0)
        d_gamma, dv = self._project(p_star, q_star, p0_n, K, mu)
        d_gamma, dv = jnp.where(yields, d_gamma, 0.0), jnp.where(yields, dv, 0.0)

        shrink = 1.0 / (1.0 + 6.0 * mu * (1.0 + 2.0 * self.beta) * d_gamma)  # q / q*
        eps = dev * shrink[..., None] + (mean - dv / 3.0)[..., None]
        eps = jnp.where(yields[..., None], eps, eps_trial)
        ev_p = ev_p + dv
        return eps, {"plastic_strain": plastic["plastic_strain"] + SQRT_2_3 * safe_norm(eps_trial - eps),
                     "volumetric_plastic_strain": ev_p,
                     "preconsolidation_pressure": self.preconsolidation(ev_p)}

    def _fixed_ellipse(self, p_star, q_star, p0, K, mu):
        """(d_gamma, dv): the closest-point return onto the ellipse of a given p0 (no hardening).
        Newton on psi(d_gamma) = 1/rho - 1/(M a), increasing and concave: monotone from below; its
        last step is taken outside the loop, so that the derivative is that of the root."""
        M2 = self.M ** 2
        c_q = 6.0 * mu * (1.0 + 2.0 * self.beta)  # q = q* / (1 + c_q d_gamma)
        c_p = 2.0 * K * M2  # p - p_c = (p* - p_c) / (1 + c_p d_gamma)
        centre, radius = 0.5 * (1.0 - self.beta) * p0, self.M * 0.5 * (1.0 + self.beta) * p0  # p_c, M a
        u_q0, u_p0 = jnp.sqrt(1.0 + 2.0 * self.beta) * q_star, self.M * (p_star - centre)

        def step(x, u_q0, u_p0, c_q, c_p, radius):
            w_q, w_p = 1.0 + c_q * x, 1.0 + c_p * x
            u_q, u_p = u_q0 / w_q, u_p0 / w_p
            rho2 = u_q * u_q + u_p * u_p
            psi = 1.0 / jnp.sqrt(rho2) - 1.0 / radius
            dpsi = (u_q * u_q * c_q / w_q + u_p * u_p * c_p / w_p) / (rho2 * jnp.sqrt(rho2))
            return jnp.maximum(x - psi / dpsi, 0.0)

        # the iterations on constants (no tangent carried through the loop: under jax.jvp, as in
        # _project's Newton on ln p0, only the last step is differentiated)
        frozen = jax.lax.stop_gradient((u_q0, u_p0, c_q, c_p, radius))
        x = jax.lax.fori_loop(0, PREDICTOR_ITERATIONS, lambda _, x: step(x, *frozen), jnp.zeros_like(p_star))
        x = step(jax.lax.stop_gradient(x), u_q0, u_p0, c_q, c_p, radius)
        return x, -2.0 * M2 * x * (p_star - centre) / (1.0 + c_p * x)

    def _project(self, p_star, q_star, p0_n, K, mu):
        """(d_gamma, dv) of the closest-point return of a trial (p*, q*) outside the ellipse, with
        hardening.  The final p0 = P fixes the ellipse, and on a fixed ellipse the return is
        :meth:`_fixed_ellipse`'s, giving dv(P); consistency is h(s) = s - ln p0_n + xi dv(e^s) = 0
        in s = ln P.  Compaction (h(ln p0_n) = xi dv(p0_n) < 0) puts a root in [ln p0_n, ln P_in],
        P_in the ellipse through the trial point (dv = 0 there, h > 0); dilation puts one in
        [ln p0_n - xi dv_max, ln p0_n], since dv < dv_max = (max(p_c(p0_n), 0) - p*) / K for
        P <= p0_n.  Newton from the fixed-ellipse estimate s_n - xi dv(p0_n), safeguarded by
        bisection on that bracket, then one plain Newton step outside the loop, so that the
        derivative is the implicit one of the root."""
        s_n = jnp.log(p0_n)
        xi = self.hardening

        def h(s):
            return s - s_n + xi * self._fixed_ellipse(p_star, q_star, jnp.exp(s), K, mu)[1]

        def newton(s):
            value, slope = jax.jvp(h, (s,), (jnp.ones_like(s),))
            return value, s - value / slope

        def safeguarded(_, bracket):
            s, lo, hi = bracket
            value, step = newton(s)
            lo, hi = jnp.where(value < 0.0, s, lo), jnp.where(value < 0.0, hi, s)
            # Newton where it stays in the bracket and at most halves it (no cycling), else bisection
            accept = (step >= lo) & (step <= hi) & (2.0 * jnp.abs(step - s) <= hi - lo)
            return jnp.where(accept, step, 0.5 * (lo + hi)), lo, hi

        def root(p_star, q_star, p0_n):
            v_n = self._fixed_ellipse(p_star, q_star, p0_n, K, mu)[1]
            compacts = v_n < 0.0
            dv_max = jnp.maximum(0.5 * (1.0 - self.beta) * p0_n, 0.0) - p_star
            # P_in: f(p*, q*; P) = M^2 (C - b P - beta P^2) = 0, the positive root
            b = (1.0 - self.beta) * p_star
            C = p_star * p_star + (1.0 + 2.0 * self.beta) * q_star * q_star / self.M ** 2
            disc = jnp.sqrt(b * b + 4.0 * self.beta * C)
            p_in = jnp.where(b > 0.0, 2.0 * C / jnp.where(b > 0.0, b + disc, 1.0),
                             (disc - b) / jnp.where(b > 0.0, 1.0, 2.0 * self.beta))
            lo = jnp.where(compacts, s_n, s_n - xi * jnp.maximum(dv_max, 0.0) / K)
            hi = jnp.where(compacts, jnp.log(jnp.maximum(p_in, p0_n)), s_n)
            # a step changes p0 by at most a factor exp(L), L = ln(max float) / 8 (89 in float64, 11 in
            # float32), so that the solver's powers of p* / p0 stay finite; no physical step comes near it
            cap = 0.125 * math.log(jnp.finfo(s_n.dtype).max)
            lo, hi = jnp.maximum(lo, s_n - cap), jnp.minimum(hi, s_n + cap)
            start = jnp.clip(s_n - xi * v_n, lo, hi)  # p0 hardened by the fixed-ellipse dv
            return jax.lax.fori_loop(0, HARDENING_ITERATIONS, safeguarded, (start, lo, hi))[0]

        s = root(*jax.lax.stop_gradient((p_star, q_star, p0_n)))
        s = newton(jax.lax.stop_gradient(s))[1]
        return self._fixed_ellipse(p_star, q_star, jnp.exp(s), K, mu)

M_SLOPE = Parameter("M", lambda m: m.M, "slope of the critical state line", "positive", valid=POSITIVE)
P0 = Parameter("p0", lambda m: m.p0, "initial pre-consolidation pressure", "positive", valid=POSITIVE)
HARDENING = Parameter("hardening", lambda m: m.hardening, "hardening exponent xi of p0 with ln J_p", "positive",
                      valid=NON_NEGATIVE)
BETA = Parameter("beta", lambda m: m.beta, "cohesion ratio (tensile strength beta p0)", "positive",
                 valid=NON_NEGATIVE)

register_material("cam_clay", CamClay, parameters=[E, NU, M_SLOPE, P0, HARDENING, BETA, DENSITY])
