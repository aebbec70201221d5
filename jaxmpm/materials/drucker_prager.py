"""Drucker–Prager elastoplasticity in Hencky strain: friction, cohesion, dilatancy, apex return.

The return mapping of Klar, Gast, Pradhana, Fu, Schroeder, Jiang & Teran 2016 ("Drucker-Prager
elastoplasticity for sand animation", ACM TOG 35(4) 103, §7 and its appendix), which
works on the principal Hencky strains eps = ln sigma of the elastic deformation gradient, generalised
to a cohesion c > 0 (the cone's apex moves to the tensile side, to the mean stress c cot phi) and to a
dilatancy angle psi != 0 (a volumetric part in the plastic flow), with the apex (tension cut-off)
return of de Souza Neto, Peric & Owen 2008 ("Computational methods for plasticity", ch. 8, the Drucker-Prager return).

Yield function and plastic potential on the principal Kirchhoff stresses t (tension positive;
de Souza Neto et al. 2008 §6.4.6):

    f(t) = sqrt(J2) + eta p - xi c,      g(t) = sqrt(J2) + eta_bar p,
    p = tr(t)/3,  sqrt(J2) = |dev t| / sqrt(2)

with the constants matched to Mohr-Coulomb (phi, psi, c) in plane strain (docstring of
:func:`plane_strain_match`): a plane-strain collapse load of the Drucker-Prager model equals the
Mohr-Coulomb one, the natural match for the 2D plane-strain scenes (column collapse).  The apex lies
at p = xi c / eta = c cot phi whatever the match.

With the Hencky law, dev t = 2 mu dev eps and p = K tr(eps) (K = lambda + 2 mu / 3), the return in
principal strain is closed form, one step (de Souza Neto et al. 2008 ch. 8; Klar et al. 2016 §7):

* f(trial) <= 0: inside the cone, no change (Klar's case "inside the cone");
* else the return along the flow direction dg/dt = dev t / (2 sqrt(J2)) + eta_bar / 3 I:

      d_gamma = f(trial) / (mu + K eta eta_bar)
      eps = eps* - d_gamma (n / sqrt(2) + eta_bar / 3 (1, 1, 1)),   n = dev eps* / |dev eps*|

  (psi = 0: isochoric, along the deviator only: Klar's case "project along the deviatoric
  direction"); after it f = 0 exactly;
* unless that return overshoots the cone's axis (mu d_gamma > sqrt(J2*): the trial state lies beyond
  the apex, in the cone of the flow directions there), then it goes to the apex itself,
  dev eps = 0, tr eps = c cot phi / K (Klar's case "expansion -> project to the tip": with c = 0
  and psi = 0 exactly their test tr eps* > 0).

Plastic variables: ``plastic_strain``, the equivalent plastic strain sum sqrt(2/3) |dev d eps_p|
(the von Mises measure, as :class:`jaxmpm.VonMises` keeps it), and
``volumetric_plastic_strain``, sum tr(d eps_p) (positive: dilation).

Optional hardening (or softening) of the friction angle with the equivalent plastic strain alpha,

    phi(alpha) = phi_0 + d_phi (1 - exp(-alpha / alpha_ref)),

a saturating law in the spirit of Klar et al. 2016's hardening (their phi_F = h0 + (h1 q - h3) exp(-h2 q)),
explicit as theirs is: a step uses phi at the start of the step.  ``friction_hardening`` d_phi = 0
(the default) turns it off.

Derivatives: every branch is a closed form in eps*, phi, psi, c, selected by ``jnp.where`` with the
divisions guarded on both sides (NaN-free at dev eps* = 0 and at phi = 0), so gradients with
respect to the strain path and the parameters are exact inside the cone, on it, at the apex and
through the onset of yield (tests/test_drucker_prager.py against central differences).
"""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np

from ..core.registry import Parameter, register_material
from ..core.safe import safe_norm
from ..core.validate import NON_NEGATIVE, POISSON, POSITIVE, Range, concrete, fail
from ..transfer.backend import materialise
from .base import lame
from .linear import DENSITY, NU, E
from .plastic import HenckyPlastic, deviator

SQRT2 = math.sqrt(2.0)
SQRT_2_3 = math.sqrt(2.0 / 3.0)
ANGLE = Range(0, 90, high_open=True, fix="an angle in degrees in [0, 90)")


def plane_strain_match(phi, psi):
    """(eta, xi, eta_bar): the Drucker-Prager constants matched to Mohr-Coulomb in plane strain,
    for friction angle ``phi`` and dilatancy angle ``psi`` in radians.

    In plane strain the plastic strain rate out of plane vanishes.  With g = sqrt(J2) + eta_bar p
    that fixes the out-of-plane stress, s_zz = -(2/3) eta_bar sqrt(J2); writing the in-plane
    principal stresses as m +- r (centre m, radius r of Mohr's circle) then
    sqrt(J2) = r / sqrt(1 - eta_bar^2 / 3) and p = m - eta_bar sqrt(J2) / 3, and f = 0 becomes
    r = (xi c - eta m) sqrt(1 - eta_bar^2/3) / (1 - eta eta_bar / 3).  Equal to Mohr-Coulomb's
    r = c cos phi - m sin phi for every m, and the in-plane dilation rate tr(d eps_p) /
    (d eps_1 - d eps_3) = eta_bar / sqrt(1 - eta_bar^2/3) equal to Mohr-Coulomb's sin psi:

        eta_bar = sqrt(3) sin psi / sqrt(3 + sin^2 psi)
        eta     = sqrt(3) sqrt(3 + sin^2 psi) sin phi / (3 + sin phi sin psi),  xi = eta cot phi

    psi = phi gives the associated plane-strain match eta = 3 tan phi / sqrt(9 + 12 tan^2 phi) of
    de Souza Neto et al. 2008 §6.4.6; psi = 0 gives eta = sin phi, xi = cos phi (the
    out-of-plane stress is then the mean of the in-plane ones, and Drucker-Prager is Mohr-Coulomb
    in plane strain: the same generalisation to non-associated flow as Vermeer & de Borst 1984
    discuss for Mohr-Coulomb and Drucker-Prager in plane strain)."""
    sin_phi, sin_psi = jnp.sin(phi), jnp.sin(psi)
    root = jnp.sqrt(3.0 + sin_psi * sin_psi)
    scale = math.sqrt(3.0) * root / (3.0 + sin_phi * sin_psi)
    return scale * sin_phi, scale * jnp.cos(phi), math.sqrt(3.0) * sin_psi / root


class DruckerPrager(HenckyPlastic):
    """Non-associated Drucker-Prager plasticity (sand, soil) in Hencky strain with cohesion, dilatancy
    and the apex (tension cut-off) return (module docstring; Klar et al. 2016 §7, generalised).

    Yield function on the Kirchhoff stress, tension positive, p = tr(tau)/3:
    f = sqrt(J2) + eta p - xi c, the constants matched to Mohr-Coulomb in plane strain
    (:func:`plane_strain_match`: psi = 0 gives eta = sin phi, xi = cos phi).  In simple shear
    under a normal stress sigma_n the shear stress plateaus at Davis's (1968) value
    tau = (sigma_n + c cot phi) sin phi cos psi / (1 - sin phi sin psi): c + sigma_n tan phi for
    associated flow (psi = phi), c cos phi + sigma_n sin phi for isochoric flow (psi = 0).

    Args:
        E: Young's modulus, positive (stress units).
        nu: Poisson's ratio in (-1, 0.5); default 0.3.
        friction_angle: the internal friction angle phi in degrees, in [0, 90); default 30.
        dilatancy_angle: the dilatancy angle psi in degrees, 0 <= psi <= phi; default 0
            (isochoric plastic flow, as in Klar et al. 2016); psi = phi is associated flow.
        cohesion: the cohesion c >= 0 (stress units); default 0 (dry sand).  The cone's apex lies
            at the mean stress c cot phi (tension).
        density: the reference density rho_0, positive; default 1.0.
        friction_hardening: the change d_phi of the friction angle, in degrees, as the equivalent
            plastic strain alpha grows: phi(alpha) = phi + d_phi (1 - exp(-alpha / alpha_ref))
            (negative: softening, from a peak to a critical-state angle); default 0, off.
            phi + d_phi must lie in [psi, 90).
        hardening_strain: alpha_ref, the equivalent plastic strain over which the friction angle
            moves 63 % of the way to phi + d_phi; positive, default 0.1.
    """

    friction_angle: jnp.ndarray
    dilatancy_angle: jnp.ndarray
    cohesion: jnp.ndarray
    friction_hardening: jnp.ndarray
    hardening_strain: jnp.ndarray
    saved_state = ("plastic_strain", "volumetric_plastic_strain")

    def __init__(self, E, nu=0.3, friction_angle=30.0, dilatancy_angle=0.0, cohesion=0.0, density=1.0,
                 friction_hardening=0.0, hardening_strain=0.1):
        owner = "DruckerPrager"
        self.E = POSITIVE.leaf(owner, "E", E, fix="Young's modulus, positive (stress units)")
        self.nu = POISSON.leaf(owner, "nu", nu)
        self.friction_angle = ANGLE.leaf(owner, "friction_angle", friction_angle,
                                         fix="the friction angle phi in degrees, in [0, 90); dry sand ~30-35")
        self.dilatancy_angle = ANGLE.leaf(owner, "dilatancy_angle", dilatancy_angle,
                                          fix="the dilatancy angle psi in degrees, 0 <= psi <= friction_angle")
        self.cohesion = NON_NEGATIVE.leaf(owner, "cohesion", cohesion,
                                          fix="c >= 0 (stress units); 0 is a cohesionless (dry) sand")
        self.density = POSITIVE.leaf(owner, "density", density,
                                     fix="the reference density rho_0, positive (mass per volume)")
        self.friction_hardening = Range(-90, 90, low_open=True, high_open=True).leaf(
            owner, "friction_hardening", friction_hardening,
            fix="the change of the friction angle in degrees (0: no hardening)")
        self.hardening_strain = POSITIVE.leaf(owner, "hardening_strain", hardening_strain,
                                              fix="the equivalent plastic strain scale of the hardening, e.g. 0.1")
        self.check_parameters(owner)

    def check_parameters(self, owner: str) -> None:
        """psi <= phi, and the hardened angle phi + d_phi in [psi, 90) (concrete values only; per particle where
        they are arrays, naming the first particle that breaks it)."""
        phi, psi, dphi = (concrete(v) for v in (self.friction_angle, self.dilatancy_angle, self.friction_hardening))
        if phi is None or psi is None or dphi is None:
            return
        phi, psi, dphi = np.broadcast_arrays(np.asarray(phi), np.asarray(psi), np.asarray(dphi))

        def first(wrong):  # (the first offending index, how the message names it: nothing for scalars)
            i = np.unravel_index(np.argmax(wrong), wrong.shape)
            return i, "" if wrong.ndim == 0 else f" (first at index {i[0] if len(i) == 1 else i})"

        wrong = psi > phi
        if wrong.any():
            i, at = first(wrong)
            fail(owner, f"dilatancy_angle = {float(psi[i]):g} must be <= friction_angle = {float(phi[i]):g}{at}",
                 "psi <= phi: psi = 0 is isochoric flow (Klar et al. 2016), psi = phi associated flow")
        final = phi + dphi
        wrong = (final < psi) | (final >= 90.0)
        if wrong.any():
            i, at = first(wrong)
            fail(owner, f"friction_hardening = {float(dphi[i]):g} takes the friction angle to {float(final[i]):g} "
                        f"degrees; it must stay in [dilatancy_angle, 90){at}",
                 "choose friction_hardening with dilatancy_angle <= friction_angle + friction_hardening < 90")

    def initial_plastic_state(self, n, dtype):
        return {"plastic_strain": jnp.zeros((n,), dtype), "volumetric_plastic_strain": jnp.zeros((n,), dtype)}

    # ------------------------------------------------------------------ the cone
    def friction_angle_at(self, plastic_strain):
        """phi(alpha) in radians: the friction angle after an equivalent plastic strain alpha."""
        degrees = self.friction_angle + self.friction_hardening * -jnp.expm1(-plastic_strain / self.hardening_strain)
        return jnp.deg2rad(degrees)

    def cone(self, plastic_strain):
        """(eta, xi, eta_bar) at the equivalent plastic strain ``plastic_strain`` (plane-strain match)."""
        return plane_strain_match(self.friction_angle_at(plastic_strain), jnp.deg2rad(self.dilatancy_angle))

    def apex_pressure(self, plastic_strain=0.0):
        """The mean stress of the cone's apex, xi c / eta = c cot phi (tension positive; 0 when c = 0)."""
        eta, xi, _ = self.cone(plastic_strain)
        positive = eta > 0
        return jnp.where(positive, xi * self.cohesion / jnp.where(positive, eta, 1.0), 0.0)

    def yield_function(self, tau, plastic_strain=0.0):
        """f = sqrt(J2) + eta p - xi c on principal Kirchhoff stresses (..., 3), tension positive."""
        eta, xi, _ = self.cone(plastic_strain)
        dev, p = deviator(tau)
        return safe_norm(dev) / SQRT2 + eta * p - xi * self.cohesion

    # ------------------------------------------------------------------ the return
    def return_mapping(self, eps_trial, plastic):
        lam, mu = lame(self.E, self.nu)
        K = lam + 2.0 * mu / 3.0
        alpha = plastic["plastic_strain"]
        # the cone at each particle's plastic strain, evaluated once per particle: a stage boundary,
        # or XLA recomputes its sine and cosine in every consumer (and per principal strain)
        eta, xi, eta_bar = materialise(tuple(jnp.broadcast_to(c, jnp.shape(alpha)) for c in self.cone(alpha)))
        dev, mean = deviator(eps_trial)
        dev_norm = safe_norm(dev)
        sqrt_j2 = SQRT2 * mu * dev_norm  # sqrt(J2) = |2 mu dev eps| / sqrt(2)
        f_trial = sqrt_j2 + eta * K * 3.0 * mean - xi * self.cohesion
        d_gamma = jnp.maximum(f_trial, 0.0) / (mu + K * eta * eta_bar)  # de Souza Neto et al. 2008 ch. 8
        # beyond the apex: the return would carry the deviator through zero (Klar: "project to the tip").  A cone
        # of eta = 0 (phi = 0) is a cylinder with no apex: there, with c = 0, mu d_gamma = sqrt(J2) exactly, and a
        # comparison of the two decided by the last bit sent particles to a tip that is not there (pressure lost)
        positive = eta > 0
        beyond = positive & (mu * d_gamma > sqrt_j2)
        apex_volume = jnp.where(positive, xi * self.cohesion / (K * jnp.where(positive, eta, 1.0)), 0.0)
        # eps = eps* - d_gamma (n / sqrt(2) + eta_bar / 3 (1, 1, 1)) on the cone, the apex beyond it:
        # a new mean strain and the deviator scaled, eps = mean + shrink dev eps* (0 at the apex)
        sheared = dev_norm > 0  # dev eps* = 0 and not beyond the apex: d_gamma = 0, shrink = 1
        shrink = jnp.where(beyond, 0.0, 1.0 - d_gamma / (SQRT2 * jnp.where(sheared, dev_norm, 1.0)))
        new_mean = jnp.where(beyond, apex_volume / 3.0, mean - eta_bar * d_gamma / 3.0)
        # the plastic strain increment d eps_p = eps* - eps: its deviatoric size and its trace
        d_dev = jnp.where(beyond, dev_norm, d_gamma / SQRT2)
        d_vol = jnp.where(beyond, 3.0 * mean - apex_volume, eta_bar * d_gamma)
        new_mean, shrink = materialise((new_mean, shrink))  # once per particle, not per principal strain
        eps = new_mean[..., None] + shrink[..., None] * dev
        return eps, {"plastic_strain": alpha + SQRT_2_3 * d_dev,
                     "volumetric_plastic_strain": plastic["volumetric_plastic_strain"] + d_vol}


FRICTION_ANGLE = Parameter("friction_angle", lambda m: m.friction_angle, "internal friction angle phi in degrees",
                           (0.0, 90.0), valid=ANGLE)
DILATANCY_ANGLE = Parameter("dilatancy_angle", lambda m: m.dilatancy_angle, "dilatancy angle psi in degrees",
                            (0.0, 90.0), valid=ANGLE)
COHESION = Parameter("cohesion", lambda m: m.cohesion, "cohesion c", "positive", valid=NON_NEGATIVE)

register_material("drucker_prager", DruckerPrager,
                  parameters=[E, NU, FRICTION_ANGLE, DILATANCY_ANGLE, COHESION, DENSITY])
