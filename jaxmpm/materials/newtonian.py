"""A weakly compressible Newtonian viscous fluid: a pressure of the volume ratio J and a viscous
stress 2 eta dev D of the rate of deformation (water in a dam break)."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ..core.errors import check
from ..core.linalg import det
from ..core.registry import Parameter, register_material
from ..core.validate import NON_NEGATIVE, POSITIVE, concrete
from .base import Increment, InelasticMaterial, identity, trace
from .fluid import volumetric_part
from .linear import DENSITY

#: the equations of state p(J) of :class:`NewtonianFluid`
EQUATIONS_OF_STATE = ("linear", "tait")


def deviator(D):
    """dev D = D - tr(D) / 3 I of the 3D tensor whose unresolved normal components are zero (plane
    strain in 2D, uniaxial strain in 1D), in the resolved components (N, d, d); each unresolved
    normal component of the deviator is -tr(D) / 3."""
    return D - (trace(D) / 3.0)[..., None, None] * identity(D)


def deviator_norm2(D):
    """dev D : dev D of that 3D tensor (N,): the resolved components' sum plus (3 - d) (tr D / 3)^2."""
    dev = deviator(D)
    return jnp.sum(dev * dev, axis=(-1, -2)) + (3 - D.shape[-1]) * (trace(D) / 3.0) ** 2


class NewtonianFluid(InelasticMaterial):
    """A weakly compressible Newtonian fluid: Cauchy stress sigma = -p(J) I + 2 eta dev D, with
    J = det F the volume ratio rho_0 / rho, D = sym(L) the rate of deformation (L the velocity
    gradient) and dev D = D - tr(D) / 3 I its deviator (Stokes' hypothesis: no bulk viscosity).
    The step sees the Kirchhoff stress tau = J sigma.

    The pressure (``eos``), K the bulk modulus at rest, rho_0 c_0^2 with c_0 the speed of sound:

    * ``"linear"``: p = -K (J - 1), linear in the volume change; stored energy W = K (J - 1)^2 / 2.
    * ``"tait"``: Tait's equation p = B ((1/J)^gamma - 1) = B ((rho / rho_0)^gamma - 1) with
      B = K / gamma (Monaghan 1994, "Simulating free surface flows with SPH", J. Comput. Phys.
      110; gamma = 7 for water after Batchelor 1967), so that dp/drho = c_0^2 at rest for every gamma; stored energy
      W = B (J - 1 + (J^(1 - gamma) - 1) / (gamma - 1)) (B (J - 1 - ln J) at gamma = 1, where the
      law is :class:`VolumetricFluid`'s tau = K (J - 1) I).

    Each W satisfies tau = J W'(J) I for the pressure part; the viscous part stores nothing.

    The viscous stress.  Each strain update sets D = sym(L) of the step's mechanical increment
    (:meth:`jaxmpm.materials.Increment.velocity_gradient`: L = (dF - I) / dt under the default
    kinematics, log(dF) / dt under ``kinematics="exponential"``), kept in the state
    (``state["strain_rate"]``) for the stress of the next P2G: the explicit (forward Euler)
    viscous update.  Each update adds
    the energy dissipated over it, J sigma_v : D dt = 2 eta J dev D : dev D dt per reference
    volume (``state["viscous_dissipation"]``), whose sum over the particles is the total
    ``viscous_dissipation`` in ``History.totals`` (:meth:`totals`).

    Dimensions.  3D and axisymmetric (3x3 in (r, z, theta)): as written.  2D is plane strain,
    D_zz = 0: dev D is the deviator of the 3D tensor (D - tr(D) / 3 I in the plane, -tr(D) / 3
    out of it), so a 2D dilation D = a I has the viscous stress 2 eta (a / 3) I in the plane
    and tau_zz = J (-p - 4 eta a / 3) (:meth:`out_of_plane_stress`).  1D is uniaxial strain
    (D_yy = D_zz = 0): sigma_xx = -p + (4/3) eta D_xx.  The pressure of a frame (mean of the
    three normal stresses) is then p(J) exactly.

    Like :class:`VolumetricFluid`, the fluid keeps F <- J^(1/D) I after each step
    (:meth:`keep_deformation`): its stress needs J only, and the unbounded shear of a flow would
    otherwise spoil det F.

    Time step: besides the CFL limit h / (c_0 + |V|), c_0 = sqrt(K / rho_0), the explicit viscous
    update is stable for dt <= 3 rho_0 h^2 / (16 d eta) (:meth:`time_step_limit`).

    Args:
        K: the bulk modulus at rest rho_0 c_0^2, positive (stress units).  Weak compressibility
            wants c_0 >= 10 max |V| (density changes below 1%; Monaghan 1994).
        eta: the dynamic viscosity, >= 0 (stress x time; water 1e-3 Pa s); default 0.0.
        density: the reference density rho_0, positive; default 1.0.
        eos: the equation of state, "linear" (default) or "tait".
        gamma: Tait's exponent, positive; default 7.0 (water).  Only used by ``eos="tait"``.
    """

    K: jnp.ndarray
    eta: jnp.ndarray
    gamma: jnp.ndarray
    eos: str = eqx.field(static=True)
    saved_state = ("viscous_dissipation",)

    def __init__(self, K, eta=0.0, density=1.0, eos="linear", gamma=7.0):
        self.K = POSITIVE.leaf("NewtonianFluid", "K", K, fix="the bulk modulus rho_0 c_0^2")
        self.eta = NON_NEGATIVE.leaf("NewtonianFluid", "eta", eta, fix="the dynamic viscosity; 0 is inviscid")
        self.density = POSITIVE.leaf("NewtonianFluid", "density", density)
        check(eos in EQUATIONS_OF_STATE,
              f"NewtonianFluid: eos = {eos!r}; choose 'linear' (p = -K (J - 1)) or 'tait' (p = K/gamma (J^-gamma - 1))")
        self.eos = eos
        self.gamma = POSITIVE.leaf("NewtonianFluid", "gamma", gamma, fix="Tait's exponent, 7 for water")

    # ---------------------------------------------------------------- pressure
    def pressure(self, J):
        """p(J) of the equation of state (class docstring), (N,)."""
        if self.eos == "linear":
            return -self.K * (J - 1.0)
        return self.K / self.gamma * (J ** (-self.gamma) - 1.0)

    def volume_ratio(self, p):
        """J(p), the inverse of the equation of state: the volume ratio at pressure p (e.g. to start
        a column at hydrostatic pressure)."""
        if self.eos == "linear":
            return 1.0 - p / self.K
        return (1.0 + self.gamma * p / self.K) ** (-1.0 / self.gamma)

    def volumetric_energy(self, J):
        """W(J) per reference volume with -p(J) = W'(J) (class docstring), (N,)."""
        if self.eos == "linear":
            return 0.5 * self.K * (J - 1.0) ** 2
        one = jnp.abs(self.gamma - 1.0) < 1e-12
        gm1 = jnp.where(one, 1.0, self.gamma - 1.0)  # a NaN-free derivative at gamma = 1
        tail = jnp.where(one, -jnp.log(J), (J ** (1.0 - jnp.where(one, 2.0, self.gamma)) - 1.0) / gm1)
        return self.K / self.gamma * (J - 1.0 + tail)

    # ------------------------------------------------------------------- state
    def initial_state(self, particles):
        n, d = jnp.shape(particles.x)
        d = d + getattr(particles, "axisymmetric", False)  # axisymmetric: 3x3 in (r, z, theta), 001 §7
        dtype = jnp.result_type(float)
        return {"strain_rate": jnp.zeros((n, d, d), dtype), "viscous_dissipation": jnp.zeros((n,), dtype)}

    def update_state(self, increment: Increment, state):
        """D = sym(L) of the increment; the dissipation 2 eta J dev D : dev D dt added."""
        L = increment.velocity_gradient()
        D = 0.5 * (L + jnp.swapaxes(L, -1, -2))
        J = det(increment.F)
        rate = 2.0 * self.eta * J * deviator_norm2(D)  # J sigma_v : D, per reference volume
        return {"strain_rate": D, "viscous_dissipation": state["viscous_dissipation"] + rate * increment.dt}

    # ------------------------------------------------------------------ stress
    def viscous_stress(self, D):
        """sigma_v = 2 eta dev D in the resolved components (N, d, d)."""
        return 2.0 * self.eta * deviator(D)

    def stress(self, F, state):
        """tau = J (-p(J) I + 2 eta dev D), D the state's rate of deformation."""
        J = det(F)
        sigma = -self.pressure(J)[..., None, None] * identity(F) + self.viscous_stress(state["strain_rate"])
        return J[..., None, None] * sigma

    def out_of_plane_stress(self, F, state):
        """tau_zz (and tau_yy in 1D) = J (-p - 2 eta tr(D) / 3): D has no unresolved normal component."""
        if F.shape[-1] == 3:
            return None
        J = det(F)
        return J * (-self.pressure(J) - 2.0 * self.eta * trace(state["strain_rate"]) / 3.0)

    def stored_energy_density(self, F, state):
        """The volumetric energy W(J) only (class docstring); the viscous stress stores nothing."""
        return self.volumetric_energy(det(F))

    def keep_deformation(self, F):
        """F <- J^(1/D) I after each step (as :meth:`VolumetricFluid.keep_deformation`)."""
        return volumetric_part(F)

    # ------------------------------------------------------- time step, totals
    def wave_speed(self, dim: int):
        """The speed of sound at rest c_0 = sqrt(K / rho_0) (every dimension: a fluid has no
        shear stiffness)."""
        return jnp.sqrt(self.K / self.density)

    def time_step_limit(self, h, dim: int):
        """The explicit viscous limit dt <= 3 rho_0 h^2 / (16 d eta), d = ``dim`` (None when eta is
        a concrete 0): half the forward-time centred-space diffusion limit h^2 / (2 d nu) (von
        Neumann analysis, e.g. LeVeque 2007, "Finite Difference Methods for ODEs and PDEs", §9.1)
        of the stiffest mode of the viscous operator, the longitudinal one, whose diffusivity is
        nu = (4/3) eta / rho_0 (rho dv/dt = eta lap v + (eta / 3) grad div v); its largest
        eigenvalue lambda = 4 d nu / h^2 is that of linear shape functions with a lumped mass (the
        finite-difference one; smoother shapes have smaller ones).  Halved because the viscous
        stress acts through the step: with the stress of the updated grid velocity and a particle
        increment that the next P2G projects back with a factor mu (the mode's consistent-to-lumped
        mass ratio, 1/3 for the 1D checkerboard of linear shapes, -> 0 at worst) FLIP's recursion
        is stable for dt lambda <= 2 / (2 - mu), not 2: 0.6 of the diffusion limit for that mode
        (measured: a 1D FLIP column stable at 0.55, unstable at 0.7; PIC stable to 0.95).  SPH's
        counterpart is Morris et al. 1997's dt <= 0.125 h^2 / nu."""
        eta = concrete(self.eta)
        if eta is not None and np.all(eta == 0.0):  # inviscid: no limit (traced: keep it)
            return None
        return 3.0 * self.density * h**2 / (16.0 * dim * self.eta)

    def totals(self, state, volume0) -> dict:
        """``viscous_dissipation``: the energy the viscous stress has dissipated, sum_p V0_p w_p."""
        return {"viscous_dissipation": jnp.sum(volume0 * state["viscous_dissipation"])}


K = Parameter("K", lambda m: m.K, "bulk modulus at rest rho_0 c_0^2 (NewtonianFluid)", "positive", valid=POSITIVE)
ETA = Parameter("eta", lambda m: m.eta, "dynamic viscosity (NewtonianFluid)", "positive", valid=NON_NEGATIVE)
GAMMA = Parameter("gamma", lambda m: m.gamma, "Tait's exponent (NewtonianFluid, eos='tait')", "positive",
                  valid=POSITIVE, acts=lambda m: None if m.eos == "tait" else
                  f"is Tait's exponent, and this fluid's equation of state is {m.eos!r}: build it with "
                  "jm.NewtonianFluid(..., eos='tait')")

register_material("newtonian", NewtonianFluid, parameters=[K, ETA, DENSITY, GAMMA])
