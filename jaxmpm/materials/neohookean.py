"""Compressible neo-Hookean hyperelasticity."""

from __future__ import annotations

import jax.numpy as jnp

from ..core.linalg import det, matmul
from ..core.registry import register_material
from ..core.validate import POISSON, POSITIVE
from .base import ElasticMaterial, identity, lame
from .linear import DENSITY, NU, E


def log_det(F):
    """ln det F, NaN-safe: J <= 0 is reported as an instability by the run; the log stays finite."""
    J = det(F)
    return jnp.log(jnp.where(J > 0, J, 1.0))


class NeoHookean(ElasticMaterial):
    """Compressible neo-Hookean: tau = mu (F F^T - I) + lambda ln(J) I,
    W = mu/2 (tr(F^T F) - D) - mu ln J + lambda/2 (ln J)^2.
    In 2D this is plane strain (F_zz = 1); in 1D, uniaxial strain.

    Args:
        E: Young's modulus, positive (stress units); with ``nu`` it sets the Lame constants
            lambda and mu.
        nu: Poisson's ratio in (-1, 0.5); default 0.3.
        density: the reference density rho_0, positive; default 1.0.
    """

    E: jnp.ndarray
    nu: jnp.ndarray

    def __init__(self, E, nu=0.3, density=1.0):
        self.E = POSITIVE.leaf("NeoHookean", "E", E)
        self.nu = POISSON.leaf("NeoHookean", "nu", nu)
        self.density = POSITIVE.leaf("NeoHookean", "density", density)

    def kirchhoff_stress(self, F):
        lam, mu = lame(self.E, self.nu)
        b = matmul(F, jnp.swapaxes(F, -1, -2))  # b = F F^T
        return mu * (b - identity(F)) + lam * log_det(F)[..., None, None] * identity(F)

    def energy_density(self, F):
        lam, mu = lame(self.E, self.nu)
        lj = log_det(F)
        return 0.5 * mu * (jnp.sum(F * F, axis=(-1, -2)) - F.shape[-1]) - mu * lj + 0.5 * lam * lj**2

    def out_of_plane_stress(self, F, state):
        """An unresolved axis keeps its length (F_zz = 1: plane strain in 2D, uniaxial strain in
        1D), so tau_zz = mu (1 - 1) + lambda ln J."""
        lam, _ = lame(self.E, self.nu)
        return lam * log_det(F)


register_material("neohookean", NeoHookean, parameters=[E, NU, DENSITY])
