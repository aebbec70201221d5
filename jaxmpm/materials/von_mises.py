"""von Mises (J2) elastoplasticity with linear isotropic hardening, in Hencky strain."""

from __future__ import annotations

import math

import jax.numpy as jnp

from ..core.registry import Parameter, register_material
from ..core.safe import safe_norm
from ..core.validate import NON_NEGATIVE, POISSON, POSITIVE
from ..transfer.backend import materialise
from .linear import DENSITY, NU, E
from .plastic import HenckyPlastic, deviator

SQRT_3_2 = math.sqrt(1.5)


class VonMises(HenckyPlastic):
    """von Mises (J2) plasticity with linear isotropic hardening: yield function

        f(tau, alpha) = q - (sigma_y + H alpha),   q = sqrt(3/2) |dev tau|

    on the Kirchhoff stress (the von Mises equivalent stress), alpha the equivalent plastic strain.
    The flow is associated (along dev tau) and isochoric.  With the Hencky law dev tau = 2 mu dev eps,
    so the return is radial in principal strain space and exact in one step (Simo 1992;
    de Souza Neto et al. 2008, the radial return with linear hardening):

        q* = 2 mu sqrt(3/2) |dev eps*|,  f* = q* - (sigma_y + H alpha)
        d_gamma = max(f*, 0) / (3 mu + H)
        eps = eps* - d_gamma sqrt(3/2) dev eps* / |dev eps*|,   alpha <- alpha + d_gamma

    so that after the return q = sigma_y + H alpha exactly.  In simple shear the shear stress
    plateaus at tau_xy = sigma_y / sqrt(3) (H = 0).

    Args:
        E: Young's modulus, positive (stress units).
        nu: Poisson's ratio in (-1, 0.5); default 0.3.
        yield_stress: the initial yield stress sigma_y in uniaxial tension, positive (stress units).
        hardening: the linear isotropic hardening modulus H >= 0 (stress units); 0 is perfect
            plasticity.
        density: the reference density rho_0, positive; default 1.0.
    """

    yield_stress: jnp.ndarray
    hardening: jnp.ndarray
    saved_state = ("plastic_strain",)

    def __init__(self, E, nu=0.3, yield_stress=1.0, hardening=0.0, density=1.0):
        self.E = POSITIVE.leaf("VonMises", "E", E, fix="Young's modulus, positive (stress units)")
        self.nu = POISSON.leaf("VonMises", "nu", nu)
        self.yield_stress = POSITIVE.leaf("VonMises", "yield_stress", yield_stress,
                                          fix="the uniaxial yield stress sigma_y, positive (stress units)")
        self.hardening = NON_NEGATIVE.leaf(
            "VonMises", "hardening", hardening, fix="H >= 0: softening (H < 0) makes the return ill-posed")
        self.density = POSITIVE.leaf("VonMises", "density", density,
                                     fix="the reference density rho_0, positive (mass per volume)")

    def initial_plastic_state(self, n, dtype):
        return {"plastic_strain": jnp.zeros((n,), dtype)}

    def yield_function(self, tau, plastic_strain):
        """f = sqrt(3/2) |dev tau| - (sigma_y + H alpha) on principal Kirchhoff stresses (..., 3)."""
        return SQRT_3_2 * safe_norm(deviator(tau)[0]) - (self.yield_stress + self.hardening * plastic_strain)

    def return_mapping(self, eps_trial, plastic):
        mu = self.E / (2.0 * (1.0 + self.nu))
        alpha = plastic["plastic_strain"]
        dev, mean = deviator(eps_trial)
        dev_norm = safe_norm(dev)
        q_trial = 2.0 * mu * SQRT_3_2 * dev_norm
        f_trial = q_trial - (self.yield_stress + self.hardening * alpha)
        d_gamma = jnp.maximum(f_trial, 0.0) / (3.0 * mu + self.hardening)
        # eps = eps* - d_gamma sqrt(3/2) dev eps* / |dev eps*| = mean + shrink dev eps*, the radial
        # return; shrink once per particle (a stage boundary), not per principal strain
        sheared = dev_norm > 0  # else d_gamma = 0 (sigma_y > 0): shrink = 1
        shrink = materialise(1.0 - d_gamma * SQRT_3_2 / jnp.where(sheared, dev_norm, 1.0))
        return mean[..., None] + shrink[..., None] * dev, {"plastic_strain": alpha + d_gamma}


YIELD_STRESS = Parameter("yield_stress", lambda m: m.yield_stress, "initial yield stress", "positive", valid=POSITIVE)
HARDENING = Parameter("hardening", lambda m: m.hardening, "linear isotropic hardening modulus", "positive",
                      valid=NON_NEGATIVE)

register_material("von_mises", VonMises, parameters=[E, NU, YIELD_STRESS, HARDENING, DENSITY])
