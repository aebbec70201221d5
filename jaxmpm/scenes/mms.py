"""``mms``: the axis-aligned manufactured solution of Wallstedt & Guilkey (2008) on [0, 1]^D.

Motion (reference position X in [0, 1]^D, D = 1, 2, 3), one independent wave per axis:

    u_i(X, t) = A sin(pi X_i) sin(c pi t + phi_i),      c = sqrt(E / rho0)

so x = X + u is axis-aligned, F = diag(1 + A pi cos(pi X_i) sin(c pi t + phi_i)) and J = prod F_ii.
Material: compressible neo-Hookean (:class:`jaxmpm.NeoHookean`; plane strain in 2D, uniaxial
strain in 1D), P = tau F^-T = mu (F - F^-T) + lambda ln(J) F^-T.  The exact solution needs the
body force (per unit mass, reference configuration)

    b = d^2u/dt^2 - (1/rho0) Div_0 P.

Closed form (derived by hand; the test checks it against the autodiff force): P is diagonal,
P_ii = mu (F_ii - 1/F_ii) + lambda ln(J) / F_ii, and only F_ii depends on X_i, so with
dF_ii/dX_i = -pi^2 u_i and d(ln J)/dX_i = (dF_ii/dX_i) / F_ii,

    dP_ii/dX_i = -pi^2 u_i [mu + (mu + lambda (1 - ln J)) / F_ii^2]
    b_i = pi^2 u_i [mu/rho0 - c^2 - (lambda (ln J - 1) - mu) / (rho0 F_ii^2)]

(the formula of the Uintah implementation of this problem, ``MMS.cc``, "AxisAligned").  jaxmpm
evaluates b by automatic differentiation of the exact displacement field (``jax.jacfwd`` for F,
Div_0 P and d^2u/dt^2), with P from the library's own ``NeoHookean.kirchhoff_stress``:
:class:`ManufacturedForce`.  The same machinery drives the ``vortex`` scene.

Parameters (as in the Uintah "AxisAligned" problem, Kamojjala's implementation of the paper):
E = 1e4 (mu = 3846.15, bulk 8333.33, i.e. nu = 0.3), rho0 = 1, A = 0.05, so c = 100 and one period
of the motion is 2/c = 0.02.  (E = 1e7, rho0 = 1000 gives the same c and the same body force per
unit mass: only E/rho0 enters.)  Phases: the paper's phi = (0, 2 pi/3, 4 pi/3) by default, so in
2D/3D the body starts deformed: particles are placed at X + u(X, 0) with F = I + grad u(X, 0) and
V = du/dt(X, 0) (reference volumes and masses rho0 V0 stay those of the undeformed lattice).
In 1D phi = 0: the bar starts undeformed with V = A c pi sin(pi X).

Where the body force is evaluated: at each particle's REFERENCE position X_p (as in Uintah, which
uses x_p - u_p).  ``Simulation(body_force=...)`` calls ``body_force(x, t)`` with current positions;
:class:`ManufacturedForce` holds the particles' reference positions (the particle order never
changes) and evaluates b(X_p, t), ignoring x except for its shape and dtype.  This is exact, needs
no change to the core, and is a plain static callable (hashable by value, so equal scenes share
compiled code).  The alternative -- inverting x = X + u(X, t) by Newton's method -- would
evaluate b at the numerically perturbed X and only works while the map is invertible.

Boundary: u = 0 on X_i = 0 and X_i = 1.  Three treatments (``boundary``):

* ``"walls"`` (default): the body is [0, 1]^D and the grid nodes on and beyond the planes X_a = 0, 1
  get zero normal velocity (:class:`jaxmpm.Slip` with a plane selector, like the ``bar`` scene's
  x <= 0; the tangential exact velocity there is not zero in 2D/3D).  Exact for linear shape
  functions.  B-splines reach past the wall (uGIMP too, once particle domains do): zeroing the
  outer nodes instead of mirroring them (v_-k = -v_k, what the odd exact solution does) leaves
  v(0) = N(1) v_1 != 0 and an O(h) error in the particles next to the wall, which spreads, so
  B-splines converge at first order (Steffen, Wallstedt, Guilkey, Kirby & Berzins 2008 show how
  the boundary treatment changes MPM's spatial convergence).  Leaving the outer nodes free is
  worse still (measured, 1D quadratic B-splines, cfl 0.2: errors 0.80 A and 0.49 A at 16 and 32
  cells, against 0.22 A and 0.10 A with the outer nodes zeroed).
* ``"extended"``: the body is [-1/2, 3/2]^D -- the exact solution continued oddly through the
  walls, which is the mirror done with real material -- and the wall planes keep their Slip
  condition (exact there).  The outer faces X_i = -1/2, 3/2 are free surfaces, where the exact
  stress vanishes only if the axes do not couple: F_ii = 1 there, but P_ii carries lambda ln J from
  the other axes, so this mode needs dim = 1 or nu = 0.  The errors (``reference.errors``) are then
  measured on the particles inside [0, 1]^D only.  Needs an even number of cells (a node on X = 0).
* ``"mirror"``: the body is [0, 1]^D and the planes X_a = 0, 1 are symmetry planes
  (:class:`jaxmpm.Mirror`): the particles' mirror images are folded onto the grid, so the nodes
  beyond a wall carry the odd (normal) / even (tangential) reflection of the exact solution's
  symmetry -- the extension done in the core, for any dim and nu (no outer free faces).

Time step: dt = cfl h / (c_d + A c pi) with c_d = sqrt((lambda + 2 mu)/rho0), then shortened so
that a whole number of steps lands exactly on t_end (default: one period 2/c).  Note for error
studies: USL's (V, F) update is a leapfrog, so particle velocities are half-step velocities, and
the FLIP/XPIC position update X += (S v + dV/2) dt (FMPM's X += (V^n + V^n+1) dt/2 likewise) lags
the exact motion by about dt/2: at a fixed CFL both errors are O(h) and cap the observed order at 1
on fine grids; refine dt like h^2 (``cfl`` proportional to h) to see the spatial order.
"""

from __future__ import annotations

import dataclasses
import math

import jax.numpy as jnp
import numpy as np

from ..core.errors import check
from ..core.grid import Grid
from ..core.particles import Box, fill
from ..materials import NeoHookean
from ..model.simulation import Simulation
from ..physics.damping import Damping
from ..schemes import FLIP
from ..transfer.shapes import Linear
from ._common import Setup, resolve_dtype
from ._options import checked_options
from .manufactured import (  # noqa: F401
    ManufacturedForce,
    ManufacturedReference,
    SeparableMotion,
    exact_fields,
    mirrors,
    schedule_exact,
    start_deformed,
    walls,
)
from .mms_linear import linear_mms

E, NU, RHO0, AMPLITUDE = 1.0e4, 0.3, 1.0, 0.05
PHASES = (0.0, 2.0 * math.pi / 3.0, 4.0 * math.pi / 3.0)  # Wallstedt & Guilkey / Uintah "AxisAligned"


@dataclasses.dataclass(frozen=True)
class AxisAligned(SeparableMotion):
    """u_i(X, t) = A sin(pi X_i) sin(c pi t + phi_i)."""

    def profile(self, X):
        return jnp.sin(jnp.pi * X)


# --------------------------------------------------------------------------- the scene
@checked_options
def mms(
    dim: int = 1,
    cells: int = 16,
    ppc: int = 2,
    shape=None,
    scheme=None,
    amplitude: float = AMPLITUDE,
    phases=None,
    t_end: float | None = None,
    cfl: float = 0.2,
    dt: float | None = None,
    update: str = "USL",
    damping: Damping | None = None,
    boundary: str = "walls",
    dtype=None,
    frames: int = 50,
    E: float = E,
    nu: float = NU,
    density: float = RHO0,
    velocity: str = "sine",
) -> Setup:
    """The axis-aligned MMS on [0, 1]^dim with ``cells`` cells per unit length and ``ppc``
    particles per cell per axis; ``phases`` default to (0, 2 pi/3, 4 pi/3)[:dim]; ``t_end`` to one
    period 2/c; ``boundary`` is ``"walls"``, ``"extended"`` or ``"mirror"`` (see the module docstring).
    ``setup.reference(X, t) -> (u, v)`` is the exact solution (``setup.reference.X`` the particles'
    reference positions, ``setup.reference.errors`` the RMS particle errors).  ``velocity="linear"``
    builds instead the 1D uniform-stretch MMS u = A X sin(c pi t) (velocity linear in space, X = 0
    held, X = 1 loaded by the exact traction; :mod:`jaxmpm.scenes.mms_linear`)."""
    check(dim in (1, 2, 3), f"mms: dim = {dim!r}; use 1, 2 or 3")
    check(velocity in ("sine", "linear"), f"mms: velocity = {velocity!r}; use 'sine' (Wallstedt & Guilkey) or "
                                          "'linear' (a uniform stretch, jaxmpm/scenes/mms_linear.py)")
    if velocity == "linear":  # 003 §2.3.4's "MMS with linear velocities"
        return linear_mms(dim, cells, ppc, shape, scheme, amplitude, phases, t_end, cfl, dt, update, damping,
                          boundary, dtype, frames, E, nu, density)
    check(isinstance(cells, (int, np.integer)) and cells >= 1, f"mms: cells = {cells!r} must be a positive integer")
    check(boundary in ("walls", "extended", "mirror"),
          f"mms: boundary = {boundary!r}; use 'walls', 'extended' or 'mirror'")
    check(0 <= amplitude < 1.0 / math.pi,
          f"mms: amplitude = {amplitude} must lie in [0, 1/pi) so that F = 1 + A pi cos(pi X) sin(...) stays > 0")
    extended = boundary == "extended"
    if extended:
        check(cells % 2 == 0, f"mms: boundary='extended' needs an even number of cells (a node on X = 0), got {cells}")
        check(dim == 1 or nu == 0.0,
              f"mms: boundary='extended' with dim = {dim} needs nu = 0 (got {nu}): the outer faces X = -1/2, 3/2 "
              "are traction-free only when the axes do not couple through lambda ln J")
    dtype = resolve_dtype(dtype)
    scheme = FLIP() if scheme is None else scheme
    shape = Linear() if shape is None else shape
    phases = PHASES[:dim] if phases is None else tuple(float(p) for p in phases)
    check(len(phases) == dim, f"mms: phases has {len(phases)} entries; give one per axis ({dim})")
    h = 1.0 / cells
    lo, hi = (-0.5, 1.5) if extended else (0.0, 1.0)
    pad = 1.5 * amplitude if extended else 0.0  # the free outer faces move by up to A
    grid = Grid.covering((lo,) * dim, (hi,) * dim, h, shape=shape, pad=pad)
    material = NeoHookean(E=E, nu=nu, density=density)
    c = math.sqrt(E / density)
    motion = AxisAligned(amplitude=float(amplitude), c=c, phases=phases)
    particles = fill(grid, Box((lo,) * dim, (hi,) * dim), ppc=ppc)
    X = np.asarray(particles.x, dtype=np.float64)
    force = ManufacturedForce(motion, material, X)
    sim = Simulation(grid=grid, shape=shape, material=material, scheme=scheme, damping=damping, update=update,
                     boundary=mirrors(dim) if boundary == "mirror" else walls(dim, h, outside=not extended),
                     body_force=force)
    state = start_deformed(sim, particles, motion, X, dtype)
    if t_end is None:
        t_end = 2.0 / c
    if dt is None:
        dt = cfl * h / (float(material.wave_speed(dim)) + amplitude * c * math.pi)
    dt, steps, save_every = schedule_exact(t_end, dt, frames)
    reference = ManufacturedReference(motion, X, measured=np.all((X > 0.0) & (X < 1.0), axis=-1))
    lam, mu = (float(v) for v in material.lame())
    params = dict(dim=dim, cells=cells, ppc=ppc, h=h, amplitude=amplitude, phases=list(phases), E=E, nu=nu,
                  lam=lam, mu=mu, density=density, c=c, cfl=cfl, dt=dt, t_end=t_end, boundary=boundary)
    return Setup("mms", sim, state, dt, steps, save_every, params, reference, particles)
