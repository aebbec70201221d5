"""The weakly compressible fluid of Taichi's mpm88, and the stress-free material."""

from __future__ import annotations

import jax.numpy as jnp

from ..core.linalg import det
from ..core.registry import register_material
from ..core.validate import POSITIVE
from .base import ElasticMaterial, isotropic
from .linear import DENSITY, E
from .neohookean import log_det


def volumetric_part(F):
    """J^(1/D) I, J = det F: the deformation a fluid keeps after each step (its stress depends on J
    alone); F itself where J <= 0, so that the instability check still sees it."""
    J = det(F)
    positive = J > 0
    d = F.shape[-1]
    J = jnp.where(positive, J, 1.0)
    # in 2D a square root, correctly rounded (the power it replaced agrees to the last bit or one unit in it,
    # tests/test_derivative_rules.py): a reverse pass evaluates 0.5 / sqrt(J) where the power's derivative
    # evaluated J ** -0.5 for every entry of F's cotangent (mpm88 8k: that fusion 114 -> 40 us a step)
    iso = isotropic(jnp.sqrt(J) if d == 2 else J ** (1.0 / d), d)
    return jnp.where(positive[..., None, None], iso, F)  # J <= 0 stays visible to the instability check


class VolumetricFluid(ElasticMaterial):
    """The weakly compressible fluid of Taichi's mpm88: Kirchhoff stress tau = E (J - 1) I
    (mpm88: ``stress = -dt * 4 * E * p_vol * (J - 1) / dx**2``, i.e. V0 tau D^-1 with D = dx^2/4),
    J = det F.  Stored energy W(J) = E (J - 1 - ln J), so that tau = J W'(J) I; bulk modulus E,
    wave speed sqrt(E / rho).  After each step F is reset to J^(1/D) I (:meth:`keep_deformation`).

    Args:
        E: the bulk modulus, positive (stress units).
        density: the reference density rho_0, positive; default 1.0.
    """

    E: jnp.ndarray

    def __init__(self, E, density=1.0):
        self.E = POSITIVE.leaf("VolumetricFluid", "E", E)
        self.density = POSITIVE.leaf("VolumetricFluid", "density", density)

    def kirchhoff_stress(self, F):
        J = det(F)
        return isotropic(self.E * (J - 1.0), F.shape[-1])

    def energy_density(self, F):
        J = det(F)
        return self.E * (J - 1.0 - log_det(F))

    def out_of_plane_stress(self, F, state):
        """The stress is isotropic: tau_zz = E (J - 1) too."""
        return self.E * (det(F) - 1.0)

    def keep_deformation(self, F):
        """F <- J^(1/D) I after each step (Taichi mpm99's fluid reset): the stress depends on J
        only, so this changes no stress, but it drops the shear a fluid accumulates without bound,
        which otherwise makes det F of a float32 F meaningless within t ~ 0.3 of mpm88 (|F| ~ 1e3
        and growing; J = det F then comes out <= 0)."""
        return volumetric_part(F)

    def wave_speed(self, dim: int):
        return jnp.sqrt(self.E / self.density)


class NoStress(ElasticMaterial):
    """No stress at all: tau = 0, W = 0 (force-free particles, e.g. the ``spin`` scene's freely
    flying disk).  Only the density is needed; the wave speed is 0, so the stable time step is set
    by the particle speed alone.

    Args:
        density: the reference density rho_0, positive; default 1.0.
    """


    def __init__(self, density=1.0):
        self.density = POSITIVE.leaf("NoStress", "density", density)

    def kirchhoff_stress(self, F):
        return jnp.zeros_like(F)

    def energy_density(self, F):
        return jnp.zeros(F.shape[:-2], F.dtype)

    def wave_speed(self, dim: int):
        return jnp.zeros((), self.density.dtype)


register_material("fluid", VolumetricFluid, parameters=[E, DENSITY])
register_material("nostress", NoStress, parameters=[DENSITY])
