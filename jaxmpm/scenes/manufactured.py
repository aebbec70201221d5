"""Manufactured solutions (the method of manufactured solutions, MMS): a prescribed motion
u(X, t), the body force that makes it exact for a material, the exact fields, and the pieces the
MMS scenes share (``mms``, ``mms_linear``, ``vortex``): the force term, the reference solution,
wall planes, the schedule that lands on t_end, and the deformed start."""

from __future__ import annotations

import dataclasses
import functools
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..core.errors import check
from ..core.limits import require_steps
from ..core.particles import Particles
from ..physics.conditions import Mirror, Slip
from ._common import cast_state


# --------------------------------------------------------------------------- exact motions
@dataclasses.dataclass(frozen=True)
class SeparableMotion:
    """u_i(X, t) = A f_i(X) sin(c pi t + phi_i) for one point X (D,) at time t: a spatial profile
    f (``profile``, per subclass) times a phase-shifted sine."""

    amplitude: float
    c: float
    phases: tuple

    def profile(self, X):
        """f(X), (D,): each subclass names its spatial profile."""
        raise NotImplementedError(f"{type(self).__name__} must define profile(X)")

    def displacement(self, X, t):
        phi = jnp.asarray(self.phases, X.dtype)
        return self.amplitude * self.profile(X) * jnp.sin(self.c * jnp.pi * t + phi)


def _first_piola(material, F):
    """P = tau F^-T (Kirchhoff stress from the material)."""
    return material.kirchhoff_stress(F) @ jnp.linalg.inv(F).T


def exact_fields(motion, material):
    """Point functions of (X, t) built by automatic differentiation of ``motion.displacement``:
    displacement u, velocity du/dt, acceleration d2u/dt2, F = I + du/dX, P and the body force
    b = d2u/dt2 - Div_0 P / rho0 (per unit mass)."""
    u = motion.displacement
    vel = jax.jacfwd(u, argnums=1)
    acc = jax.jacfwd(vel, argnums=1)

    def deformation_gradient(X, t):
        return jnp.eye(X.shape[0], dtype=X.dtype) + jax.jacfwd(u, argnums=0)(X, t)

    def first_piola(X, t):
        return _first_piola(material, deformation_gradient(X, t))

    def body_force(X, t):
        dP = jax.jacfwd(first_piola, argnums=0)(X, t)  # dP_iJ / dX_K
        div = jnp.trace(dP, axis1=1, axis2=2)  # Div_0 P_i = dP_iJ / dX_J
        return acc(X, t) - div / material.density

    return dict(displacement=u, velocity=vel, acceleration=acc, F=deformation_gradient, P=first_piola,
                body_force=body_force)


# --------------------------------------------------------------------------- body force
class ManufacturedForce(eqx.Module):
    """``body_force(x, t)`` for :class:`jaxmpm.Simulation`: the manufactured body force b(X_p, t)
    at each particle's reference position ``X`` (N, D), by automatic differentiation of the exact
    motion (:func:`exact_fields`).  ``x`` only supplies the shape check and the dtype.

    A pytree: the motion is static (a frozen dataclass, compared by value), the material and
    ``X`` are array leaves, so two equal scenes share compiled code without any hashing here."""

    motion: object = eqx.field(static=True)
    material: object
    X: jnp.ndarray
    # X is per particle, in the user's order: a run neither sorts the particles nor steps them in chunks
    # (BodyForce.local, Term.order_free); with_sorting(n) is an error, and "auto" does not sort
    holds_particles = True

    def __init__(self, motion, material, X):
        self.motion = motion
        self.material = material
        self.X = jnp.asarray(np.asarray(X, dtype=np.float64))

    def at(self, X, t):
        """b(X, t) for points X (N, D) (any points, not only the particles')."""
        return _body_force_at(self.motion, self.material, X, t)

    def __call__(self, x, t):
        check(x.shape == self.X.shape,
              f"ManufacturedForce: got positions of shape {x.shape}, but this body force belongs to "
              f"{self.X.shape[0]} particles in {self.X.shape[1]}D (build the scene again for other particles)")
        X = self.X.astype(x.dtype)
        return self.at(X, jnp.asarray(t, x.dtype)).astype(x.dtype)


@functools.partial(jax.jit, static_argnums=0)
def _body_force_at(motion, material, X, t):
    return jax.vmap(exact_fields(motion, material)["body_force"], in_axes=(0, None))(X, t)


class ManufacturedReference:
    """Exact solution of a manufactured scene: ``reference(X, t) -> (u, v)``, the exact
    displacement and velocity (N, D) at reference points X (N, D) and time t.  ``X`` holds the
    particles' reference positions and ``measured`` (N,) marks the particles the errors are taken
    over, so ``reference.errors(time, x, v)`` gives the RMS particle errors per saved frame."""

    def __init__(self, motion, X, measured=None):
        self.motion = motion
        self.X = np.asarray(X, dtype=np.float64)
        self.measured = np.ones(self.X.shape[0], bool) if measured is None else np.asarray(measured, bool)
        fields = exact_fields(motion, None)
        self._u = jax.jit(jax.vmap(fields["displacement"], in_axes=(0, None)))
        self._v = jax.jit(jax.vmap(fields["velocity"], in_axes=(0, None)))

    def __call__(self, X, t):
        X = jnp.asarray(X)
        t = jnp.asarray(t, X.dtype)
        return self._u(X, t), self._v(X, t)

    def positions(self, t):
        """Exact positions X + u(X, t) of all particles, (N, D)."""
        return self.X + np.asarray(self(self.X, t)[0])

    def errors(self, time, x, v, velocity_shift: float = 0.0):
        """RMS over the measured particles of |x_p - x(X_p, t)| and |V_p - v(X_p, t - velocity_shift)|
        for each frame (time (T,), x and v (T, N, D) of all particles).  Returns two (T,) arrays.
        ``velocity_shift = dt/2`` compares V with the exact velocity half a step earlier (USL
        particle velocities are leapfrog half-step velocities)."""
        time = np.asarray(time, dtype=np.float64).reshape(-1)
        keep = self.measured
        X = self.X[keep]
        x = np.asarray(x, dtype=np.float64)[:, keep]
        v = np.asarray(v, dtype=np.float64)[:, keep]
        ex, ev = [], []
        for k, t in enumerate(time):
            u_ex, _ = self(X, t)
            _, v_ex = self(X, t - velocity_shift)
            ex.append(np.sqrt(np.mean(np.sum((x[k] - X - np.asarray(u_ex)) ** 2, axis=-1))))
            ev.append(np.sqrt(np.mean(np.sum((v[k] - np.asarray(v_ex)) ** 2, axis=-1))))
        return np.array(ex), np.array(ev)


# --------------------------------------------------------------------------- boundary selectors
def _plane(axis: int, value: float, outside: bool, tol: float):
    """Node selector x_axis == value (within round-off), or beyond it with ``outside`` (the
    Simulation stores the nodes it selects, so a plain function will do)."""

    def select(x):
        d = x[:, axis] - value
        if not outside:
            return np.abs(d) <= tol
        return d <= tol if value <= 0.5 else d >= -tol

    return select


def walls(dim: int, h: float, outside: bool = False) -> tuple:
    """Zero normal velocity on the planes X_a = 0 and X_a = 1 of every axis a."""
    tol = 1e-9 * h
    return tuple(Slip(_plane(a, v, outside, tol), axis=a) for a in range(dim) for v in (0.0, 1.0))


def mirrors(dim: int) -> tuple:
    """Symmetry planes X_a = 0 and X_a = 1 of every axis a (the body between them)."""
    return tuple(Mirror(f"{'xyz'[a]}{side}", v) for a in range(dim) for side, v in (("-", 0.0), ("+", 1.0)))


# --------------------------------------------------------------------------- helpers
def schedule_exact(t_end: float, dt_max: float, frames: int) -> tuple[float, int, int]:
    """(dt, steps, save_every): ``frames`` frames, dt <= dt_max, steps * dt = t_end exactly."""
    check(t_end > 0, f"t_end = {t_end} must be positive")
    check(isinstance(frames, (int, np.integer)) and frames >= 1, f"frames = {frames!r} must be a positive integer")
    ratio = t_end / (dt_max * frames)
    require_steps(ratio * frames, "shorten t_end or use a larger dt (or cfl)")  # before int() of a huge ratio
    save_every = max(1, int(math.ceil(ratio - 1e-9)))
    steps = save_every * frames
    return t_end / steps, steps, save_every


@functools.partial(jax.jit, static_argnums=0)
def _initial_fields(motion, X):
    """u(X, 0), du/dt(X, 0) and F(X, 0) for points X (N, D), in one compiled call."""
    fields = exact_fields(motion, None)
    t0 = jnp.zeros((), X.dtype)
    return tuple(jax.vmap(fields[k], in_axes=(0, None))(X, t0) for k in ("displacement", "velocity", "F"))


def start_deformed(sim, particles, motion, X, dtype):
    """Initial state for a body that starts at x = X + u(X, 0) with F = I + grad u(X, 0) and
    V = du/dt(X, 0); reference volumes and masses stay those of the lattice X."""
    u0, v0, F0 = _initial_fields(motion, jnp.asarray(X))
    moved = Particles(x=jnp.asarray(X) + u0, v=v0, volume=particles.volume, mass=particles.mass, ppc=particles.ppc)
    state = sim.init(moved)
    state = eqx.tree_at(lambda s: s.F, state, F0.astype(state.F.dtype))
    return cast_state(state, dtype)
