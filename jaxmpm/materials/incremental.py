"""Small-strain incremental (hypoelastic) isotropic elasticity: NairnMPM's ``Isotropic`` material."""

from __future__ import annotations

import jax.numpy as jnp

from ..core.registry import register_material
from ..core.validate import POISSON, POSITIVE
from .base import Increment, InelasticMaterial, hooke, identity, lame, trace
from .linear import DENSITY, NU, E


class IncrementalElastic(InelasticMaterial):
    """NairnMPM's ``Isotropic`` material in its default small-rotation mode (``largeRotation`` 0):
    isotropic Hooke's law integrated increment by increment on the Kirchhoff stress, with a
    first-order rotation of the previous stress; the Kirchhoff stress tau and the stored energy
    per reference volume are the particle's state.

    Each strain update, from the mechanical increment dF (:class:`jaxmpm.materials.Increment`)::

        G     = dF - I                       = grad v dt under the default kinematics
        d_eps = (G + G^T) / 2                the strain increment
        W     = (G - G^T) / 2                the rotation increment
        tau  <- tau + W tau - tau W + lambda tr(d_eps) I + 2 mu d_eps       (1D: tau <- tau + E G)
        w    <- w + (tau_old + tau_new) : d_eps / 2                          (1D: (tau_old + tau_new) G / 2)

    and in 2D (plane strain) the out-of-plane (Kirchhoff) stress szz <- szz + lambda tr(d_eps), in the state
    (``state["szz"]``; it enters neither the force nor the energy).  NairnMPM has no 1D analysis;
    the 1D line is the same rule for uniaxial stress (no rotation, stiffness E), as in
    :class:`LinearElastic`.

    Where each line comes from (NairnMPM 19.0, repository nairnj/nairn-mpm-fea, commit 7f47b022):

    * G: NairnMPM 19.0, MPM_Classes/MatPoint2D.cpp, MatPoint3D.cpp, MatPointAS.cpp (UpdateStrain) --
      the particle's velocity gradient extrapolated from the grid, G_ij = dv_i/dx_j, scaled by the
      time step (axisymmetric: G_thetatheta = v_r dt / r); the material's F is updated as
      (I + G) F (Materials/ElasticMPM.cpp, HypoIncrementDeformation), jaxmpm's default
      ``kinematics="linear"``, for which G = dF - I is exact.
    * The small-rotation path: NairnMPM 19.0, Materials/MoreIsotropicMat.cpp (MPMConstitutiveLaw:
      SRConstitutiveLaw2D in 2D and axisymmetric, SRConstitutiveLaw3D in 3D); largeRotation
      defaults to 0 (Common/Materials/Elastic.cpp, the Elastic constructor).
    * d_eps and the stress increment: NairnMPM 19.0, Materials/MoreIsotropicMat.cpp
      (SRConstitutiveLaw2D, SRConstitutiveLaw3D) -- normal strains G_ii and engineering shears
      G_ij + G_ji times the isotropic stiffness (Common/Materials/Elastic.cpp, SetAnalysisProps:
      plane strain C11 = lambda + 2 mu, C12 = C13 = lambda, C66 = mu; 3D and axisymmetric the full
      matrix, the hoop strain G_thetatheta coupling through lambda), that is lambda tr(d_eps) I
      + 2 mu d_eps.
    * The rotation: NairnMPM 19.0, Materials/MaterialBaseMPM.cpp (Hypo2DCalculations,
      Hypo3DCalculations) -- with the rotational strains G_ji - G_ij = 2 W_ji, the components of
      W tau_old - tau_old W added to the stress: the first-order (Jaumann) rotation, not an exact
      or Hughes-Winget one; in 2D and axisymmetric only the in-plane (x-y, r-z) part, the out-of-plane
      (hoop) stress is not rotated, which is what the 3D formula gives for W with zero third row
      and column.
    * szz: NairnMPM 19.0, Materials/MoreIsotropicMat.cpp (SRConstitutiveLaw2D, plane strain
      branch) -- szz += C13 G_xx + C23 G_yy = lambda tr(d_eps).
    * The energy w: NairnMPM 19.0, Materials/MoreIsotropicMat.cpp (SRConstitutiveLaw2D,
      SRConstitutiveLaw3D: the work increment, trapezoidal in the stress, the old and the updated
      one, against the total strain increment; in plane strain no zz term, the out-of-plane strain
      increment being zero unless generalized plane strain is asked for); accumulated
      per particle by MPM_Classes/MPMBase.cpp (AddWorkEnergyAndResidualEnergy, GetStrainEnergy:
      work less residual -- thermal -- energy) and summed as m_p times it for the global archive
      "Strain Energy" (Global_Quantities/GlobalQuantity.cpp).

    Physics.  NairnMPM stores the specific stress s = sigma / rho = tau / rho_0 (tau = J sigma
    the Kirchhoff stress; MPM_Classes/MatPoint2D.cpp, GetFintPlusFext: f = -m_p s . grad S;
    System/ArchiveData.cpp archives rho s), and its stiffness is divided by the reference density
    (Elastic.cpp, FillUnrotatedElasticProperties).  With m_p = rho_0 V0_p its force is jaxmpm's
    -V0_p tau . G (001 eq. 20) with tau = rho_0 s: the rate law is integrated on tau directly (no
    factor J, unlike :class:`HypoElastic`, which integrates the Cauchy stress).  Its strain energy
    m_p (work per unit mass) is V0_p w, w the work per reference volume above, which
    :meth:`stored_energy_density` returns; along a path with no rotation (G symmetric) the
    trapezoidal rule is exact (tau linear in the summed d_eps) and w = tau : C^-1 tau / 2.

    The update is first order in the rotation: a pure spin increment (G skew, e.g.
    dF = I + W dt) leaves a zero stress zero but rotates a prestress by I + W, which keeps its
    trace but grows its norm at O(|W|^2) per step; a dF that is an exact rotation R gives d_eps = sym(R) - I
    = O(theta^2).  Under ``kinematics="exponential"`` G = dF - I = grad v dt + O(dt^2).  With a
    transport term's isotropic thermal stretch removed from dF (s_old / s_new), sym G is, to first
    order, the total strain increment less the residual (thermal) one, so w plays the part of
    NairnMPM's work less residual energy.  For small strains the law agrees with
    :class:`LinearElastic` and :class:`HypoElastic` to O(eps^2).

    Args:
        E: Young's modulus, positive (stress units).
        nu: Poisson's ratio in (-1, 0.5); default 0.0 (unused in 1D, uniaxial stress).
        density: the reference density rho_0, positive; default 1.0.
    """

    E: jnp.ndarray
    nu: jnp.ndarray
    uniaxial = True

    def __init__(self, E, nu=0.0, density=1.0):
        self.E = POSITIVE.leaf("IncrementalElastic", "E", E)
        self.nu = POISSON.leaf("IncrementalElastic", "nu", nu)
        self.density = POSITIVE.leaf("IncrementalElastic", "density", density)

    def initial_state(self, particles):
        n, d = jnp.shape(particles.x)
        d = d + getattr(particles, "axisymmetric", False)  # axisymmetric: 3x3 in (r, z, theta), 001 §7
        dtype = jnp.result_type(float)
        state = {"stress": jnp.zeros((n, d, d), dtype), "energy": jnp.zeros((n,), dtype)}
        if d == 2:
            state["szz"] = jnp.zeros((n,), dtype)
        return state

    def stress(self, F, state):
        return state["stress"]  # tau itself: NairnMPM's rho_0 * (stress per unit mass)

    def out_of_plane_stress(self, F, state):
        """In 2D the state's out-of-plane stress szz; 1D (uniaxial stress): 0."""
        return state["szz"] if "szz" in state else super().out_of_plane_stress(F, state)

    def update_state(self, increment: Increment, state):
        dF = increment.dF
        G = dF - identity(dF)
        tau = state["stress"]
        d_eps = 0.5 * (G + jnp.swapaxes(G, -1, -2))
        if dF.shape[-1] == 1:
            new = tau + self.E * G
        else:
            W = 0.5 * (G - jnp.swapaxes(G, -1, -2))
            new = tau + W @ tau - tau @ W + hooke(self.E, self.nu, d_eps)
        out = {"stress": new, "energy": state["energy"] + 0.5 * jnp.sum((tau + new) * d_eps, axis=(-1, -2))}
        if "szz" in state:
            lam, _ = lame(self.E, self.nu)
            out["szz"] = state["szz"] + lam * trace(d_eps)
        return out

    def stored_energy_density(self, F, state):
        """The accumulated work sum (tau_old + tau_new) : d_eps / 2 per reference volume (class docstring)."""
        return state["energy"]


register_material("incremental", IncrementalElastic, parameters=[E, NU, DENSITY])
