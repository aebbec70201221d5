"""``mms(velocity="linear")``: a manufactured solution whose velocity is linear in space.

003 §2.3.4 says that the "new PIC" of FMPM(1) (003 eq. 2.40) is more stable than the PIC of
XPIC(1) (003 eq. 2.38), "especially for problems where PIC works well such as MMS with linear
velocities".  003 does not describe that MMS; this is the simplest one with a velocity field linear
in space (PIC's lumped projection S+ reproduces a linear field on a uniform particle lattice, so
PIC loses little there).  1D bar on [0, 1] (reference position X), uniform stretch about X = 0:

    u(X, t) = A X sin(c pi t + phi),      c = sqrt(E / rho0)
    v(X, t) = A c pi X cos(c pi t + phi)                    (linear in X, and in x = (1 + g) X)
    F(t)    = 1 + A sin(c pi t + phi)                        (uniform: Div_0 P = 0)

Material: the ``mms`` scene's compressible neo-Hookean in uniaxial strain, P = mu (F - 1/F) +
lambda ln(F) / F.  Because P is uniform the momentum equation rho0 d2u/dt2 = Div_0 P + rho0 b needs
the body force (per unit mass)

    b(X, t) = d2u/dt2 = -A (c pi)^2 X sin(c pi t + phi)

-- evaluated, as in ``mms``, by :class:`~jaxmpm.scenes.mms.ManufacturedForce` (``jax.jacfwd`` of
the exact motion, the library's own stress) at each particle's reference position -- and two
boundary conditions that the exact solution satisfies:

* X = 0: u = 0, the grid nodes on and below x = 0 get zero velocity (:class:`jaxmpm.Slip`, as the
  ``mms`` walls; exact for linear shape functions);
* X = 1: the traction P(F(t)) of the exact solution (force per unit area; in 1D Cauchy = P), a
  :class:`jaxmpm.Traction` on the "x+" face of the last particle (001 eqs. 12, 21).  Unlike the
  sine MMS, where u = 0 on both walls, a linear displacement cannot vanish at X = 1: the end moves
  by A sin(...) and carries the uniform stress.

Parameters as ``mms``: E = 1e4, nu = 0.3, rho0 = 1, A = 0.05 (a 5 % stretch), c = 100, one period
2/c = 0.02; phi = 0 (the bar starts undeformed, V = A c pi X).  The time step is the ``mms`` one,
dt = cfl h / (c_d + A c pi) (A c pi is the largest exact speed, at X = 1).
"""

from __future__ import annotations

import dataclasses
import math

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ..core.errors import check
from ..core.grid import Grid
from ..core.particles import Box, fill
from ..materials import NeoHookean
from ..model.simulation import Simulation
from ..physics.conditions import Slip
from ..physics.loads import Traction
from ..schemes import FLIP
from ..transfer.shapes import Linear
from ._common import Setup, resolve_dtype
from .manufactured import (
    ManufacturedForce,
    ManufacturedReference,
    SeparableMotion,
    _plane,
    exact_fields,
    schedule_exact,
    start_deformed,
)


@dataclasses.dataclass(frozen=True)
class UniformStretch(SeparableMotion):
    """u_i(X, t) = A X_i sin(c pi t + phi_i): velocity linear in X."""

    def profile(self, X):
        return X


class ExactTraction(eqx.Module):
    """T(t) = P(X, t) N on the face X_axis = 1 (outward normal N = e_axis) of the exact solution:
    the load of :class:`jaxmpm.Traction` that keeps the free end on the manufactured motion
    (001 eq. 12 with the exact first Piola stress; in 1D the reference and current areas agree)."""

    motion: object = eqx.field(static=True)
    material: object
    axis: int = eqx.field(static=True)

    def __call__(self, t):
        t = jnp.asarray(t)
        dim = len(self.motion.phases)
        X = jnp.ones((dim,), t.dtype)  # P is uniform: any point of the face
        P = exact_fields(self.motion, self.material)["P"](X, t)
        return P[:, self.axis]


@dataclasses.dataclass(frozen=True)
class _FaceParticles:
    """Selector of the particles whose reference position lies beyond ``value`` on ``axis`` (the
    last particle layer of a face); hashable by value, so equal scenes share compiled code."""

    axis: int
    value: float

    def __call__(self, x):
        return x[:, self.axis] > self.value


def linear_mms(dim, cells, ppc, shape, scheme, amplitude, phases, t_end, cfl, dt, update, damping, boundary,
               dtype, frames, E, nu, density) -> Setup:
    """The body of ``mms(velocity="linear")`` (the options are those of :func:`jaxmpm.scenes.mms.mms`,
    already checked by its decorator)."""
    check(dim == 1, f"mms: velocity='linear' is built in 1D only (got dim = {dim}); use dim=1")
    check(boundary == "walls",
          f"mms: velocity='linear' has its own boundary (X = 0 held, X = 1 loaded by the exact traction); "
          f"leave boundary at 'walls', got {boundary!r}")
    check(isinstance(cells, (int, np.integer)) and cells >= 1, f"mms: cells = {cells!r} must be a positive integer")
    check(0 <= amplitude < 0.5, f"mms: velocity='linear' needs amplitude in [0, 0.5) so that F = 1 + A sin(...) "
                                f"stays >= 1/2, got {amplitude}")
    dtype = resolve_dtype(dtype)
    scheme = FLIP() if scheme is None else scheme
    shape = Linear() if shape is None else shape
    phases = (0.0,) * dim if phases is None else tuple(float(p) for p in phases)
    check(len(phases) == dim, f"mms: phases has {len(phases)} entries; give one per axis ({dim})")
    h = 1.0 / cells
    grid = Grid.covering((0.0,) * dim, (1.0,) * dim, h, shape=shape, pad=1.5 * amplitude + h)
    material = NeoHookean(E=E, nu=nu, density=density)
    c = math.sqrt(E / density)
    motion = UniformStretch(amplitude=float(amplitude), c=c, phases=phases)
    particles = fill(grid, Box((0.0,) * dim, (1.0,) * dim), ppc=ppc)
    X = np.asarray(particles.x, dtype=np.float64)
    held = tuple(Slip(_plane(a, 0.0, True, 1e-9 * h), axis=a) for a in range(dim))  # u = 0 on X = 0
    last = 1.0 - 1.0 / (cells * ppc)  # between the last two particle layers
    loads = tuple(Traction(_FaceParticles(a, last), ExactTraction(motion, material, a), "xyz"[a] + "+",
                           name=f"exact_traction_{'xyz'[a]}") for a in range(dim))
    sim = Simulation(grid=grid, shape=shape, material=material, scheme=scheme, damping=damping, update=update,
                     boundary=held, body_force=ManufacturedForce(motion, material, X), terms=loads)
    state = start_deformed(sim, particles, motion, X, dtype)
    if t_end is None:
        t_end = 2.0 / c
    if dt is None:
        dt = cfl * h / (float(material.wave_speed(dim)) + amplitude * c * math.pi)
    dt, steps, save_every = schedule_exact(t_end, dt, frames)
    reference = ManufacturedReference(motion, X)
    lam, mu = (float(v) for v in material.lame())
    params = dict(dim=dim, cells=cells, ppc=ppc, h=h, amplitude=amplitude, phases=list(phases), E=E, nu=nu,
                  lam=lam, mu=mu, density=density, c=c, cfl=cfl, dt=dt, t_end=t_end, boundary=boundary,
                  velocity="linear")
    return Setup("mms", sim, state, dt, steps, save_every, params, reference, particles)
