"""Hypoelastic (rate form) linear elasticity with an objective stress update."""

from __future__ import annotations

import jax.numpy as jnp

from ..core.linalg import det
from ..core.registry import register_material
from ..core.validate import POISSON, POSITIVE
from .base import Increment, InelasticMaterial, hooke, identity, lame, trace
from .linear import DENSITY, NU, E


class HypoElastic(InelasticMaterial):
    """Hypoelastic (rate form) linear elasticity with an objective update; the Cauchy stress sigma
    is the particle's state and tau = J sigma (stress on the current volume).

    Each strain update, from the mechanical increment dF (:class:`jaxmpm.materials.Increment`, the
    thermal stretch of a transport term removed):

        d_eps = (dF^T dF - I) / 2                              the strain increment
        Q     = (I - W/2)^-1 (I + W/2),  W = skew(dF - I)      the increment's rotation (Hughes-Winget)
        sigma <- Q sigma Q^T + lambda tr(d_eps) I + 2 mu d_eps  (1D: + E d_eps)

    d_eps vanishes for a rotation increment, so a rigidly rotating body builds no stress: exactly
    with ``Simulation(kinematics="exponential")`` (dF = exp(W dt) is a rotation), to O(dt^2) per
    step with the default dF = I + grad v dt.  :class:`LinearElastic`'s total strain sym F - I is
    not objective: a rotation by theta gives eps = (cos theta - 1) I.  For small strains the two
    laws agree to O(eps^2).

    Args:
        E: Young's modulus, positive (stress units).
        nu: Poisson's ratio in (-1, 0.5); default 0.0 (unused in 1D, uniaxial stress).
        density: the reference density rho_0, positive; default 1.0.
    """

    E: jnp.ndarray
    nu: jnp.ndarray
    uniaxial = True

    def __init__(self, E, nu=0.0, density=1.0):
        self.E = POSITIVE.leaf("HypoElastic", "E", E)
        self.nu = POISSON.leaf("HypoElastic", "nu", nu)
        self.density = POSITIVE.leaf("HypoElastic", "density", density)

    def initial_state(self, particles):
        n, d = jnp.shape(particles.x)
        d = d + getattr(particles, "axisymmetric", False)  # axisymmetric: 3x3 in (r, z, theta), 001 §7
        return {"stress": jnp.zeros((n, d, d), jnp.result_type(float))}

    def stress(self, F, state):
        return det(F)[..., None, None] * state["stress"]  # tau = J sigma

    def update_state(self, increment: Increment, state):
        dF = increment.dF
        eye = identity(dF)
        d_eps = 0.5 * (jnp.swapaxes(dF, -1, -2) @ dF - eye)
        W = 0.5 * ((dF - eye) - jnp.swapaxes(dF - eye, -1, -2))
        Q = jnp.linalg.solve(eye - 0.5 * W, eye + 0.5 * W)  # orthogonal for skew W
        return {"stress": Q @ state["stress"] @ jnp.swapaxes(Q, -1, -2) + hooke(self.E, self.nu, d_eps)}

    def stored_energy_density(self, F, state):
        """J sigma : C^-1 sigma / 2, the complementary energy per reference volume."""
        sigma = state["stress"]
        d = sigma.shape[-1]
        if d == 1:
            strain = sigma / self.E
        else:
            lam, mu = lame(self.E, self.nu)
            strain = (sigma - lam / (d * lam + 2.0 * mu) * trace(sigma)[..., None, None] * identity(sigma)) / (2 * mu)
        return 0.5 * det(F) * jnp.sum(sigma * strain, axis=(-1, -2))


register_material("hypoelastic", HypoElastic, parameters=[E, NU, DENSITY])
