"""Constitutive models.  Each returns the Kirchhoff stress tau = J sigma from the deformation
gradient F, so the internal force is f_i = -sum_p V0_p tau_p . G_pi (001 eq. 20, 003 eq. 2.10),
and a stored-energy density W(F) per reference volume for the strain-energy diagnostic.

Dimensions: 1D is uniaxial stress for :class:`LinearElastic` and :class:`HypoElastic`, 2D is plane
strain, 3D is full; on an axisymmetric grid (001 §7) F is 3x3 in (r, z, theta) and every law is
its 3D form.  :class:`HypoElastic` keeps its Cauchy stress as per-particle state (an
objective rate update); the others are functions of F.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp

from ..core.registry import Parameter, register_material
from ..core.validate import POISSON, POSITIVE


def _identity(F):
    return jnp.broadcast_to(jnp.eye(F.shape[-1], dtype=F.dtype), F.shape)


def _trace(A):
    return jnp.trace(A, axis1=-2, axis2=-1)


def _hooke(material, strain):
    """Isotropic Hooke's law C : strain = lambda tr(strain) I + 2 mu strain (2D plane strain, 3D);
    E strain in 1D (uniaxial stress).  ``material`` has E and nu."""
    if strain.shape[-1] == 1:
        return material.E * strain
    lam, mu = material.lame()
    return lam * _trace(strain)[..., None, None] * _identity(strain) + 2.0 * mu * strain


class Material(eqx.Module):
    """Base class: ``density`` (reference), ``kirchhoff_stress(F)``, ``energy_density(F)``; a
    material with per-particle state overrides :meth:`initial_state`, :meth:`particle_stress` and
    :meth:`update_state`.  Register new materials with :func:`jaxmpm.register_material`."""

    density: jnp.ndarray

    def lame(self):
        mu = self.E / (2.0 * (1.0 + self.nu))
        lam = self.E * self.nu / ((1.0 + self.nu) * (1.0 - 2.0 * self.nu))
        return lam, mu

    def initial_state(self, particles):
        """The material's per-particle state at the start (``State.material_state``); None for
        the elastic materials, e.g. a plastic strain for a plastic one."""
        return None

    def particle_stress(self, F, material_state):
        """Kirchhoff stress of each particle from F and the material state (the elastic materials
        need F only: :meth:`kirchhoff_stress`)."""
        return self.kirchhoff_stress(F)

    def stored_energy_density(self, F, material_state):
        """Stored energy per reference volume from F and the material state (the elastic
        materials: :meth:`energy_density` of F)."""
        return self.energy_density(F)

    def update_state(self, F, material_state, dt):
        """The material state after the strain update to ``F`` (unchanged for elastic materials)."""
        return material_state

    def keep_deformation(self, F):
        """The deformation gradient carried to the next step: F itself for solids (no operation).
        :class:`VolumetricFluid` overrides it."""
        return F

    def wave_speed(self, dim: int):
        """Dilatational wave speed: sqrt(E/rho) in 1D, sqrt((lambda + 2 mu)/rho) otherwise."""
        if dim == 1 and isinstance(self, (LinearElastic, HypoElastic)):
            return jnp.sqrt(self.E / self.density)
        lam, mu = self.lame()
        return jnp.sqrt((lam + 2.0 * mu) / self.density)


class LinearElastic(Material):
    """Small-strain linear elasticity, eps = sym(F) - I.

    tau = lambda tr(eps) I + 2 mu eps (2D plane strain, 3D); tau = E eps in 1D (uniaxial stress).
    """

    E: jnp.ndarray
    nu: jnp.ndarray

    def __init__(self, E, nu=0.0, density=1.0):
        self.E = POSITIVE.leaf("LinearElastic", "E", E)
        self.nu = POISSON.leaf("LinearElastic", "nu", nu)
        self.density = POSITIVE.leaf("LinearElastic", "density", density)

    def strain(self, F):
        return 0.5 * (F + jnp.swapaxes(F, -1, -2)) - _identity(F)

    def kirchhoff_stress(self, F):
        return _hooke(self, self.strain(F))

    def energy_density(self, F):
        eps = self.strain(F)
        return 0.5 * jnp.sum(self.kirchhoff_stress(F) * eps, axis=(-1, -2))


class HypoElastic(Material):
    """Hypoelastic (rate form) linear elasticity with an objective update; the Cauchy stress sigma
    is the particle's state and tau = J sigma (stress on the current volume).

    Each step, from the increment dF = F F_prev^-1 (F_prev, the previous F, is state too):

        d_eps = (dF^T dF - I) / 2                              the strain increment
        Q     = (I - W/2)^-1 (I + W/2),  W = skew(dF - I)      the increment's rotation (Hughes-Winget)
        sigma <- Q sigma Q^T + lambda tr(d_eps) I + 2 mu d_eps  (1D: + E d_eps)

    d_eps vanishes for a rotation increment, so a rigidly rotating body builds no stress: exactly
    with ``Simulation(kinematics="exponential")`` (dF = exp(W dt) is a rotation), to O(dt^2) per
    step with the default dF = I + grad v dt.  :class:`LinearElastic`'s total strain sym F - I is
    not objective: a rotation by theta gives eps = (cos theta - 1) I.  For small strains the two
    laws agree to O(eps^2).  The thermal stretch of a transport term (jaxmpm.physics.transport) is not
    applied to this law."""

    E: jnp.ndarray
    nu: jnp.ndarray

    def __init__(self, E, nu=0.0, density=1.0):
        self.E = POSITIVE.leaf("HypoElastic", "E", E)
        self.nu = POISSON.leaf("HypoElastic", "nu", nu)
        self.density = POSITIVE.leaf("HypoElastic", "density", density)

    def initial_state(self, particles):
        n, d = jnp.shape(particles.x)
        d = d + getattr(particles, "axisymmetric", False)  # axisymmetric: 3x3 in (r, z, theta), 001 §7
        dtype = jnp.result_type(float)
        return {"stress": jnp.zeros((n, d, d), dtype), "F": jnp.broadcast_to(jnp.eye(d, dtype=dtype), (n, d, d))}

    def particle_stress(self, F, material_state):
        return jnp.linalg.det(F)[..., None, None] * material_state["stress"]  # tau = J sigma

    def update_state(self, F, material_state, dt):
        dF = F @ jnp.linalg.inv(material_state["F"])
        eye = _identity(F)
        d_eps = 0.5 * (jnp.swapaxes(dF, -1, -2) @ dF - eye)
        W = 0.5 * ((dF - eye) - jnp.swapaxes(dF - eye, -1, -2))
        Q = jnp.linalg.solve(eye - 0.5 * W, eye + 0.5 * W)  # orthogonal for skew W
        sigma = Q @ material_state["stress"] @ jnp.swapaxes(Q, -1, -2) + _hooke(self, d_eps)
        return {"stress": sigma, "F": F}

    def stored_energy_density(self, F, material_state):
        """J sigma : C^-1 sigma / 2, the complementary energy per reference volume."""
        sigma = material_state["stress"]
        d = sigma.shape[-1]
        if d == 1:
            strain = sigma / self.E
        else:
            lam, mu = self.lame()
            strain = (sigma - lam / (d * lam + 2.0 * mu) * _trace(sigma)[..., None, None] * _identity(sigma)) / (2 * mu)
        return 0.5 * jnp.linalg.det(F) * jnp.sum(sigma * strain, axis=(-1, -2))


class NeoHookean(Material):
    """Compressible neo-Hookean: tau = mu (F F^T - I) + lambda ln(J) I,
    W = mu/2 (tr(F^T F) - D) - mu ln J + lambda/2 (ln J)^2.
    In 2D this is plane strain (F_zz = 1); in 1D, uniaxial strain."""

    E: jnp.ndarray
    nu: jnp.ndarray

    def __init__(self, E, nu=0.3, density=1.0):
        self.E = POSITIVE.leaf("NeoHookean", "E", E)
        self.nu = POISSON.leaf("NeoHookean", "nu", nu)
        self.density = POSITIVE.leaf("NeoHookean", "density", density)

    @staticmethod
    def _log_j(F):
        J = jnp.linalg.det(F)
        # NaN-safe: J <= 0 is reported as an instability by the run; keep the log finite here
        return jnp.log(jnp.where(J > 0, J, 1.0))

    def kirchhoff_stress(self, F):
        lam, mu = self.lame()
        b = F @ jnp.swapaxes(F, -1, -2)
        return mu * (b - _identity(F)) + lam * self._log_j(F)[..., None, None] * _identity(F)

    def energy_density(self, F):
        lam, mu = self.lame()
        lj = self._log_j(F)
        return 0.5 * mu * (jnp.sum(F * F, axis=(-1, -2)) - F.shape[-1]) - mu * lj + 0.5 * lam * lj**2


class NoStress(Material):
    """No stress at all: tau = 0, W = 0 (force-free particles, e.g. the ``spin`` scene's freely
    flying disk).  Only the density is needed; the wave speed is 0, so the stable time step is set
    by the particle speed alone."""

    def __init__(self, density=1.0):
        self.density = POSITIVE.leaf("NoStress", "density", density)

    def kirchhoff_stress(self, F):
        return jnp.zeros_like(F)

    def energy_density(self, F):
        return jnp.zeros(F.shape[:-2], F.dtype)

    def wave_speed(self, dim: int):
        return jnp.zeros((), self.density.dtype)


class VolumetricFluid(Material):
    """The weakly compressible fluid of Taichi's mpm88: Kirchhoff stress tau = E (J - 1) I
    (mpm88: ``stress = -dt * 4 * E * p_vol * (J - 1) / dx**2``, i.e. V0 tau D^-1 with D = dx^2/4),
    J = det F.  Stored energy W(J) = E (J - 1 - ln J), so that tau = J W'(J) I; bulk modulus E,
    wave speed sqrt(E / rho)."""

    E: jnp.ndarray

    def __init__(self, E, density=1.0):
        self.E = POSITIVE.leaf("VolumetricFluid", "E", E)
        self.density = POSITIVE.leaf("VolumetricFluid", "density", density)

    def kirchhoff_stress(self, F):
        J = jnp.linalg.det(F)
        return (self.E * (J - 1.0))[..., None, None] * _identity(F)

    def energy_density(self, F):
        J = jnp.linalg.det(F)
        return self.E * (J - 1.0 - NeoHookean._log_j(F))

    def keep_deformation(self, F):
        """F <- J^(1/D) I after each step (Taichi mpm99's fluid reset): the stress depends on J
        only, so this changes no stress, but it drops the shear a fluid accumulates without bound,
        which otherwise makes det F of a float32 F meaningless within t ~ 0.3 of mpm88 (|F| ~ 1e3
        and growing; J = det F then comes out <= 0)."""
        J = jnp.linalg.det(F)
        positive = J > 0
        iso = (jnp.where(positive, J, 1.0) ** (1.0 / F.shape[-1]))[..., None, None] * _identity(F)
        return jnp.where(positive[..., None, None], iso, F)  # J <= 0 stays visible to the instability check

    def wave_speed(self, dim: int):
        return jnp.sqrt(self.E / self.density)


E = Parameter("E", lambda m: m.E, "Young's modulus (bulk modulus of VolumetricFluid)", "positive", valid=POSITIVE)
NU = Parameter("nu", lambda m: m.nu, "Poisson's ratio", (-1.0, 0.5), valid=POISSON)
DENSITY = Parameter("density", lambda m: m.density, "reference density (re-run sim.init for particle masses)",
                    "positive", valid=POSITIVE)
register_material("linear", LinearElastic, parameters=[E, NU, DENSITY])
register_material("hypoelastic", HypoElastic, parameters=[E, NU, DENSITY])
register_material("neohookean", NeoHookean, parameters=[E, NU, DENSITY])
register_material("fluid", VolumetricFluid, parameters=[E, DENSITY])
register_material("nostress", NoStress, parameters=[DENSITY])
