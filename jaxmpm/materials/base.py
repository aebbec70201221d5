"""What every constitutive model is: the :class:`Material` protocol and its two bases.

A material turns a particle's deformation into its Kirchhoff stress tau = J sigma, so that the
internal force is f_i = -sum_p V0_p tau_p . G_pi (001 eq. 20, 003 eq. 2.10), and reports a stored
energy per reference volume for the strain-energy diagnostic.  The step talks to it through:

* :meth:`Material.stress` ``(F, state) -> tau`` -- at P2G, from the deformation the material sees
  (``F``: the particle's F with the terms' isotropic stretch removed, thermal or moisture
  expansion) and its own ``state``;
* :meth:`Material.update_state` ``(increment, state) -> state`` -- after each strain update, with
  the :class:`Increment` (the mechanical deformation increment dF, thermal stretch removed, and
  dt) and the state the material owns (``State.material_state``: e.g. an elastic F and plastic
  variables; None for the elastic laws);
* :meth:`Material.stored_energy_density`, :meth:`Material.wave_speed`, :meth:`Material.keep_deformation`;
* :meth:`Material.time_step_limit` (a stable-dt bound of the law's own, e.g. viscous diffusion) and
  :meth:`Material.totals` (sums of its state saved per frame in ``History.totals``, e.g. the
  dissipated energy of a viscous or plastic law); both optional.

Two bases implement it: :class:`ElasticMaterial` (stress a function of F; no state) and
:class:`InelasticMaterial` (history-dependent: owns its state, integrates the increments).  A new
law is one file with a subclass of either and one :func:`jaxmpm.register_material` call; the
built-in laws are the other modules of this package.

Dimensions: 1D is uniaxial stress for :class:`~jaxmpm.LinearElastic` and
:class:`~jaxmpm.HypoElastic` (``uniaxial = True``), 2D is plane strain, 3D is full; on an
axisymmetric grid (001 §7) F is 3x3 in (r, z, theta) and every law is its 3D form.
"""

from __future__ import annotations

import abc
import inspect
import warnings

import equinox as eqx
import jax.numpy as jnp

from ..core.errors import check
from ..core.registry import MATERIALS


def identity(F):
    """I broadcast like the batch of matrices ``F``."""
    return jnp.broadcast_to(jnp.eye(F.shape[-1], dtype=F.dtype), F.shape)


def isotropic(s, dim: int):
    """s I, (..., D, D): ``s`` (...) on the diagonal and zeros elsewhere, stacked.  The same values as
    ``s[..., None, None] * identity``; in reverse mode the cotangent of ``s`` is the sum of the diagonal's,
    where the product with a broadcast identity transposes to a reduction over all D x D entries (in a
    rollout XLA hoists the identity out of the loop, so the zeros are not known inside it)."""
    zero = jnp.zeros_like(s)
    return jnp.stack([jnp.stack([s if a == b else zero for b in range(dim)], axis=-1) for a in range(dim)], axis=-2)


def trace(A):
    return jnp.trace(A, axis1=-2, axis2=-1)


def lame(E, nu):
    """(lambda, mu) of Young's modulus and Poisson's ratio."""
    mu = E / (2.0 * (1.0 + nu))
    lam = E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))
    return lam, mu


def hooke(E, nu, strain):
    """Isotropic Hooke's law C : strain = lambda tr(strain) I + 2 mu strain (2D plane strain, 3D);
    E strain in 1D (uniaxial stress)."""
    if strain.shape[-1] == 1:
        return E * strain
    lam, mu = lame(E, nu)
    return lam * trace(strain)[..., None, None] * identity(strain) + 2.0 * mu * strain


class Increment(eqx.Module):
    """One strain update's deformation increment, handed to :meth:`Material.update_state`.

    Args:
        dF: the mechanical increment (N, D, D), F_mech_new = dF F_mech_old with the terms'
            isotropic stretch removed (dF = (I + grad v dt) s_old / s_new, or exp(grad v dt)
            s_old / s_new, 001 eq. 26).
        F: the particle's total deformation gradient after the increment, (N, D, D).
        dt: the time the increment spans.
        kinematics: how dF was formed from the velocity gradient, the model's ``kinematics``:
            "linear" (default, dF = I + grad v dt) or "exponential" (dF = exp(grad v dt)).
    """

    dF: jnp.ndarray
    F: jnp.ndarray
    dt: jnp.ndarray
    kinematics: str = eqx.field(static=True, default="linear")

    def velocity_gradient(self, terms: int = 6):
        """The velocity gradient L (N, D, D) the increment integrates, for a rate law (a viscous
        stress from D = sym L): the inverse of the kinematics that formed dF, so L is the grid's
        grad v (the terms' isotropic stretch removed).  "linear": L = (dF - I) / dt, exact.
        "exponential": L = log(dF) / dt, the principal logarithm by the Gregory series
        log dF = 2 sum_k Z^(2k+1) / (2k+1), Z = (dF - I)(dF + I)^-1 (Higham 2008, "Functions of
        Matrices", ch. 11), ``terms`` terms: with |Z| ~ |L dt| / 2 the truncation is
        ~2 |Z|^(2 terms + 1) / (2 terms + 1), below 3e-9 for |L dt| <= 0.5 with the default 6 (2.9e-9
        measured for a spin of 0.5 rad, against scipy's expm),
        far beyond a step within the CFL limit.  Differentiable; dF + I is invertible for any dF
        near I."""
        eye = identity(self.dF)
        if self.kinematics != "exponential":
            return (self.dF - eye) / self.dt
        Z = jnp.linalg.solve(jnp.swapaxes(self.dF + eye, -1, -2), jnp.swapaxes(self.dF - eye, -1, -2))
        Z = jnp.swapaxes(Z, -1, -2)  # (dF - I)(dF + I)^-1; the two factors commute
        Z2, power, log = Z @ Z, Z, Z
        for k in range(1, terms):
            power = power @ Z2
            log = log + power / (2 * k + 1)
        return 2.0 * log / self.dt


class Material(eqx.Module):
    """The constitutive-model protocol: :meth:`stress` ``(F, state) -> tau`` at P2G,
    :meth:`update_state` after each strain update, :meth:`stored_energy_density` and
    :meth:`wave_speed`.  Subclass :class:`ElasticMaterial` or :class:`InelasticMaterial`; register
    with :func:`jaxmpm.register_material` (docs/extending.md).

    Args:
        density: the reference density rho_0, mass per reference volume (an array leaf, so
            ``jax.grad`` reaches it); :meth:`jaxmpm.Simulation.init` sets the particle masses
            rho_0 V0_p from it unless the particles carry their own.
    """

    density: jnp.ndarray  # the reference density rho_0

    # 1D is uniaxial stress (wave speed sqrt(E / rho)); otherwise uniaxial strain in 1D
    uniaxial = False
    # entries of the material's state (a dict, ``State.material_state``) a run can save per frame,
    # chosen by name like "stress" or "J" (jm.H5Writer(fields=...), --fields): e.g. ("plastic_strain",)
    saved_state = ()

    def initial_state(self, particles):
        """The material's per-particle state at the start (``State.material_state``); None for
        the elastic laws."""
        return None

    def state_fields(self, state) -> dict:
        """The entries of ``state`` that :attr:`saved_state` names, ``{name: (N, ...)}``: the
        per-frame fields the material offers besides the stress (jaxmpm.model.frame_fields)."""
        if not isinstance(state, dict):
            return {}
        return {name: state[name] for name in self.saved_state if name in state}

    def out_of_plane_stress(self, F, state):
        """The Kirchhoff normal stress along each axis the model does not resolve, (N,) -- in 2D
        tau_zz (plane strain), in 1D tau_yy = tau_zz -- or None where the law does not determine
        it.  The pressure of a 1D or 2D frame is the mean of all three normal stresses when it is
        known (jaxmpm.model.frame_fields).  Here: zero for a uniaxial-stress law in 1D, else None."""
        if F.shape[-1] == 1 and self.uniaxial:
            return jnp.zeros(F.shape[:-2], F.dtype)
        return None

    @abc.abstractmethod
    def stress(self, F, state):
        """Kirchhoff stress tau (N, D, D) of each particle from the deformation it sees and its state."""

    @abc.abstractmethod
    def stored_energy_density(self, F, state):
        """Stored energy per reference volume (N,) from the deformation and the state."""

    def update_state(self, increment: Increment, state):
        """The state after one strain update (unchanged for the elastic laws)."""
        return state

    def keep_deformation(self, F):
        """The deformation gradient carried to the next step: F itself for solids;
        :class:`~jaxmpm.VolumetricFluid` overrides it."""
        return F

    def check_parameters(self, owner: str) -> None:
        """Raise InputError where the parameters together break a condition of the law that no single
        parameter's range expresses (e.g. Drucker-Prager's dilatancy angle <= friction angle); concrete
        values only (a traced one passes).  The constructor calls it, and so do :func:`jaxmpm.set_params`
        and :func:`jaxmpm.ensemble` after replacing parameters; ``owner`` names the caller.  None by
        default."""

    def time_step_limit(self, h, dim: int):
        """The largest stable dt the law itself sets besides the CFL limit h / max_p(c + |V_p|), for
        cells of size ``h`` in a ``dim``-D model (e.g. a viscous fluid's diffusion limit
        ~ rho h^2 / eta), or None: no limit of its own (the default).
        :meth:`jaxmpm.Simulation.stable_dt` takes the smallest of the CFL limit, the terms' limits
        and this one (named after the material's class in :meth:`jaxmpm.Simulation.time_step_limits`),
        inside one compiled program: write it in jnp (its arrays may be traced)."""
        return None

    def totals(self, state, volume0) -> dict:
        """{name: scalar}: the material's sums over the particles, saved with every frame in
        ``History.totals`` (HDF5 ``/totals/<name>``) next to the terms' totals -- e.g. the energy a
        viscous or plastic law has dissipated, sum_p V0_p w_p with w_p a density per reference
        volume kept in ``state``; {} by default.

        Args:
            state: the material's state (``State.material_state``).
            volume0: the particles' reference volumes V0_p, (N,).
        """
        return {}

    def wave_speed(self, dim: int):
        """Dilatational wave speed: sqrt(E/rho) for a uniaxial 1D law, sqrt((lambda + 2 mu)/rho)
        otherwise, from the material's ``E`` and ``nu``; a law without them overrides this."""
        check(hasattr(self, "E") and hasattr(self, "nu"),
              f"{type(self).__name__}: define wave_speed(dim) (the dilatational wave speed, for the stable dt)")
        if dim == 1 and self.uniaxial:
            return jnp.sqrt(self.E / self.density)
        lam, mu = lame(self.E, self.nu)
        return jnp.sqrt((lam + 2.0 * mu) / self.density)

    # ------------------------------------------------------------- deprecated names (one release)
    def particle_stress(self, F, state):
        """Deprecated name of :meth:`stress`."""
        return self.stress(F, state)

    def __init_subclass__(cls, **kwargs):
        """A law written against the protocol before core v2 keeps working for a release, with a
        DeprecationWarning: ``particle_stress(F, state)`` serves as :meth:`stress`, and
        ``update_state(F, state, dt)`` (the total F after the update) is called with the
        increment's ``F`` and ``dt``."""
        super().__init_subclass__(**kwargs)
        legacy = []
        if "particle_stress" in cls.__dict__ and "stress" not in cls.__dict__:
            cls.stress = cls.__dict__["particle_stress"]
            legacy.append("particle_stress(F, state) -> stress(F, state)")
        update = cls.__dict__.get("update_state")
        if update is not None and len(inspect.signature(update).parameters) == 4:  # (self, F, state, dt)
            def update_state(self, increment, state, _old=update):
                return _old(self, increment.F, state, increment.dt)

            cls.update_state = update_state
            legacy.append("update_state(F, state, dt) -> update_state(increment, state)")
        if legacy:
            warnings.warn(f"{cls.__name__}: the material protocol changed in core v2 ({'; '.join(legacy)}); "
                          "the old names work for one release (docs/extending.md)", DeprecationWarning, stacklevel=2)

    def lame(self):
        """(lambda, mu) of the material's E and nu."""
        return lame(self.E, self.nu)


MATERIALS.base = Material  # register_material accepts its subclasses only


class ElasticMaterial(Material):
    """A law whose stress is a function of the deformation alone: define
    :meth:`kirchhoff_stress` ``(F)`` and :meth:`energy_density` ``(F)``.  No state.

    Args:
        density: the reference density rho_0 (as for :class:`Material`).
    """

    @abc.abstractmethod
    def kirchhoff_stress(self, F):
        """tau(F), (N, D, D)."""

    @abc.abstractmethod
    def energy_density(self, F):
        """W(F) per reference volume, (N,)."""

    def stress(self, F, state):
        return self.kirchhoff_stress(F)

    def stored_energy_density(self, F, state):
        return self.energy_density(F)


class InelasticMaterial(Material):
    """A history-dependent law: it owns its per-particle state (:meth:`initial_state`, e.g. an
    elastic F and plastic variables), integrates each strain :class:`Increment` in
    :meth:`update_state` (a return mapping, a rate update) and gives the stress and stored energy
    of a state (:meth:`stress`, :meth:`stored_energy_density`, which may ignore ``F``).

    Args:
        density: the reference density rho_0 (as for :class:`Material`).
    """

    @abc.abstractmethod
    def initial_state(self, particles):
        """The state at the start."""

    @abc.abstractmethod
    def update_state(self, increment: Increment, state):
        """The state after the increment."""
