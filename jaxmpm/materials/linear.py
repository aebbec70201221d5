"""Small-strain linear elasticity (Hooke's law on sym(F) - I)."""

from __future__ import annotations

import jax.numpy as jnp

from ..core.registry import Parameter, register_material
from ..core.validate import POISSON, POSITIVE
from .base import ElasticMaterial, hooke, identity, lame, trace

E = Parameter("E", lambda m: m.E, "Young's modulus (bulk modulus of VolumetricFluid)", "positive", valid=POSITIVE)
NU = Parameter("nu", lambda m: m.nu, "Poisson's ratio", (-1.0, 0.5), valid=POISSON)
DENSITY = Parameter("density", lambda m: m.density, "reference density (re-run sim.init for particle masses)",
                    "positive", valid=POSITIVE, through_init=True)


class LinearElastic(ElasticMaterial):
    """Small-strain linear elasticity, eps = sym(F) - I.

    tau = lambda tr(eps) I + 2 mu eps (2D plane strain, 3D); tau = E eps in 1D (uniaxial stress).
    The strain is not objective: a rigid rotation by theta gives eps = (cos theta - 1) I
    (:class:`HypoElastic` is).

    Args:
        E: Young's modulus, positive (stress units).
        nu: Poisson's ratio in (-1, 0.5); default 0.0 (unused in 1D).
        density: the reference density rho_0, positive; default 1.0.
    """

    E: jnp.ndarray
    nu: jnp.ndarray
    uniaxial = True

    def __init__(self, E, nu=0.0, density=1.0):
        self.E = POSITIVE.leaf("LinearElastic", "E", E)
        self.nu = POISSON.leaf("LinearElastic", "nu", nu)
        self.density = POSITIVE.leaf("LinearElastic", "density", density)

    def strain(self, F):
        return 0.5 * (F + jnp.swapaxes(F, -1, -2)) - identity(F)

    def kirchhoff_stress(self, F):
        return hooke(self.E, self.nu, self.strain(F))

    def energy_density(self, F):
        eps = self.strain(F)
        return 0.5 * jnp.sum(self.kirchhoff_stress(F) * eps, axis=(-1, -2))

    def out_of_plane_stress(self, F, state):
        """Plane strain (eps_zz = 0): tau_zz = lambda tr(eps); 1D (uniaxial stress): 0."""
        if F.shape[-1] == 2:
            lam, _ = lame(self.E, self.nu)
            return lam * trace(self.strain(F))
        return super().out_of_plane_stress(F, state)


register_material("linear", LinearElastic, parameters=[E, NU, DENSITY])
