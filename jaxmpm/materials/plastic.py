"""Finite-strain elastoplasticity in Hencky (logarithmic) strain: the base of the plastic laws.

The deformation gradient splits multiplicatively, F = F_e F_p; the material keeps the elastic part
F_e in its state (Simo 1992; Klar et al. 2016).  Each strain update:

1. trial:   F_e* = dF F_e                     (dF the mechanical increment, 001 eq. 26)
2. return:  F_e* = U diag(sigma*) V^T,  eps* = ln sigma*   (principal Hencky strains)
            eps  = Z(eps*, plastic state)     the law's return mapping (:meth:`return_mapping`)
            F_e  = U diag(exp eps) V^T
3. stress:  tau = U diag(t) U^T,  t = lambda tr(eps) 1 + 2 mu eps      (Kirchhoff stress of the
            Hencky energy W = mu |eps|^2 + lambda/2 (tr eps)^2; Klar et al. 2016)

Because the Hencky law is linear in eps, the return mapping of a yield surface in principal
Kirchhoff stress is a closed-form projection in eps (Simo 1992, "Algorithms for static and dynamic
multiplicative plasticity"; de Souza Neto, Peric & Owen 2008).  Every law is written in
three principal strains: in 3D and on an axisymmetric grid (F 3x3 in (r, z, theta), 001 §7) they are
F_e's singular values; in 2D (plane strain, total F_zz = 1) and 1D (uniaxial strain) the elastic
stretches along the unresolved axes are part of the state (``stretch_out``), since plastic flow
changes them (F_e,zz = 1 / F_p,zz).

The plastic work of the step, tau : d_eps_p = sum_i t_i (eps*_i - eps_i) with t the returned
stress (the backward-Euler dissipation; de Souza Neto et al. 2008), is kept per particle
(``plastic_dissipation``, per reference volume) and summed over the particles (times V0_p) into
``History.totals["plastic_dissipation"]``.  It is not the energy the return removes,
W(eps*) - W(eps) = tau : d_eps_p + d_eps_p : C : d_eps_p / 2: the second term is the overshoot
of the elastic trial, energy the grid forces never did as work (a sand near its free surface, where
the yield stress tends to zero, would count several times the potential energy it released).

Derivatives flow through :func:`jaxmpm.materials.principal.principal_map` (exact at equal singular
values) and through the law's return mapping (written with NaN-safe branches: ``jnp.where`` on
both sides of a division, never a square root of zero).
"""

from __future__ import annotations

import abc

import jax.numpy as jnp

from ..core.linalg import identities, matmul
from .base import Increment, InelasticMaterial, lame
from .principal import principal_map, principal_stress

OUT_OF_PLANE = "stretch_out"  # the elastic stretches along the unresolved axes (2D: zz; 1D: yy = zz)
DISSIPATION = "plastic_dissipation"
STRESS = "kirchhoff_stress"  # tau of F_e, computed with the return


def hencky_stress(E, nu, eps):
    """Principal Kirchhoff stresses t = lambda tr(eps) 1 + 2 mu eps of principal Hencky strains (..., 3)."""
    lam, mu = lame(E, nu)
    return lam * principal_sum(eps)[..., None] + 2.0 * mu * eps


def hencky_energy(E, nu, eps):
    """W = mu |eps|^2 + lambda/2 (tr eps)^2 per reference volume, (...,)."""
    lam, mu = lame(E, nu)
    tr = jnp.sum(eps, axis=-1)
    return mu * jnp.sum(eps * eps, axis=-1) + 0.5 * lam * tr * tr


def _principal_strains(sigma, out):
    """The three principal Hencky strains: ln of the resolved singular values and of the state's
    out-of-plane stretches (none in 3D)."""
    stretches = sigma if out is None else jnp.concatenate([sigma, out], axis=-1)
    return jnp.log(stretches)


def _returned(sigma, args):
    """principal_map's function for the strain update: the law's return mapping on ln sigma."""
    material, out, plastic = args
    eps_trial = _principal_strains(sigma, out)
    eps, plastic = material.return_mapping(eps_trial, plastic)
    t = hencky_stress(material.E, material.nu, eps)
    dissipated = principal_sum(t * (eps_trial - eps))  # tau : d_eps_p, the plastic work
    stretch = jnp.exp(eps)
    D = sigma.shape[-1]
    new_out = None if out is None else stretch[..., D:]
    # F_e = U diag(stretch) V^T and tau = U diag(t) U^T = [U diag(t / stretch) V^T] F_e^T: two
    # isotropic functions of the one decomposition
    return (stretch[..., :D], t[..., :D] / stretch[..., :D]), (plastic, new_out, dissipated)


def _kirchhoff(sigma, args):
    """principal_stress's function: Hencky principal stresses of the resolved axes, with the full
    three (and the energy) as invariants."""
    material, out = args
    eps = _principal_strains(sigma, out)
    t = hencky_stress(material.E, material.nu, eps)
    return t[..., :sigma.shape[-1]], (t, hencky_energy(material.E, material.nu, eps))


class HenckyPlastic(InelasticMaterial):
    """Base of the elastoplastic laws in Hencky strain (module docstring): a subclass defines
    :meth:`return_mapping` on the principal strains and :meth:`initial_plastic_state`, and declares
    its per-particle plastic variables in ``saved_state``.

    State (``State.material_state``): ``Fe`` the elastic deformation gradient (N, D, D),
    ``kirchhoff_stress`` its Kirchhoff stress (N, D, D), computed with the return,
    ``stretch_out`` the elastic stretches along the unresolved axes (N, 3 - D) in 1D and 2D,
    ``plastic_dissipation`` the energy dissipated per reference volume so far (N,), and the law's
    plastic variables.

    Args:
        E: Young's modulus, positive (stress units).
        nu: Poisson's ratio in (-1, 0.5).
        density: the reference density rho_0, positive.
    """

    E: jnp.ndarray
    nu: jnp.ndarray

    @abc.abstractmethod
    def return_mapping(self, eps_trial, plastic: dict):
        """(eps, plastic): the principal Hencky strains (..., 3) after the return onto the yield
        surface, and the updated plastic variables; elementwise over the particles and symmetric
        under a permutation of the three strains."""

    @abc.abstractmethod
    def initial_plastic_state(self, n: int, dtype) -> dict:
        """The law's plastic variables at the start, ``{name: (n,)}``."""

    # ------------------------------------------------------------------ the protocol
    def initial_state(self, particles):
        n, d = jnp.shape(particles.x)
        d = d + getattr(particles, "axisymmetric", False)  # axisymmetric: 3x3 in (r, z, theta), 001 §7
        dtype = jnp.result_type(float)
        state = {"Fe": identities(n, d, jnp.dtype(dtype)),
                 STRESS: jnp.zeros((n, d, d), dtype), DISSIPATION: jnp.zeros((n,), dtype)}
        if d < 3:
            state[OUT_OF_PLANE] = jnp.ones((n, 3 - d), dtype)
        state.update(self.initial_plastic_state(n, dtype))
        return state

    def _plastic(self, state) -> dict:
        return {k: v for k, v in state.items() if k not in ("Fe", OUT_OF_PLANE, DISSIPATION, STRESS)}

    def update_state(self, increment: Increment, state):
        trial = matmul(increment.dF, state["Fe"])
        out = state.get(OUT_OF_PLANE)
        (Fe, G), (plastic, out, dissipated) = principal_map(_returned, trial, (self, out, self._plastic(state)))
        new = dict(state, Fe=Fe, **plastic)
        new[STRESS] = matmul(G, jnp.swapaxes(Fe, -1, -2))
        new[DISSIPATION] = state[DISSIPATION] + dissipated
        if out is not None:
            new[OUT_OF_PLANE] = out
        return new

    def _principal_stress(self, state):
        return principal_stress(_kirchhoff, state["Fe"], (self, state.get(OUT_OF_PLANE)))

    def stress(self, F, state):
        """The Kirchhoff stress of the elastic part F_e, kept in the state by the strain update
        (one decomposition per step; the total F is not used)."""
        return state[STRESS]

    def principal_kirchhoff_stress(self, state):
        """The three principal Kirchhoff stresses (N, 3) (in 1D and 2D the last ones along the
        unresolved axes)."""
        return self._principal_stress(state)[1][0]

    def out_of_plane_stress(self, F, state):
        """tau_zz in 2D (plane strain; tau_yy = tau_zz in 1D), from the out-of-plane elastic stretch."""
        if OUT_OF_PLANE not in state:
            return None
        return self.principal_kirchhoff_stress(state)[..., -1]

    def stored_energy_density(self, F, state):
        """The Hencky energy of the elastic part, mu |eps|^2 + lambda/2 (tr eps)^2."""
        return self._principal_stress(state)[1][1]

    def totals(self, state, volume0) -> dict:
        """``plastic_dissipation``: the energy plastic flow has dissipated so far, sum V0_p D_p
        (``state`` the material's state, ``volume0`` the reference volumes V0_p: the signature of
        :meth:`jaxmpm.Material.totals`)."""
        return {DISSIPATION: jnp.sum(volume0 * state[DISSIPATION])}


def principal_sum(values):
    """v_1 + v_2 + v_3 of principal values (..., 3), written out: elementwise over the particles, so it
    fuses with the return mapping around it, where XLA:CPU runs a sum over an axis of three as a
    reduction kernel of its own (measured: the von Mises and Drucker-Prager updates 10-20% faster)."""
    return values[..., 0] + values[..., 1] + values[..., 2]


def principal_norm(values):
    """|v| of principal values (..., 3), 0 at 0 with a derivative that is 0 there (not NaN), written
    out like :func:`principal_sum` (no reduction kernel on the CPU)."""
    sq = principal_sum(values * values)
    return jnp.where(sq > 0.0, jnp.sqrt(jnp.where(sq > 0.0, sq, 1.0)), 0.0)


def deviator(eps):
    """The deviatoric part of principal values (..., 3) and their mean."""
    mean = principal_sum(eps) / 3.0
    return eps - mean[..., None], mean
