"""``slide``: an elastic block slides on an elastic slab under tilted gravity (issue 12).

2D, plane strain.  A slab [0, 1] x [0, 0.1] whose base nodes (y <= 0) are fixed, and a block
[0.1, 0.3] x [0.1, 0.2] resting on it, both linear elastic (E = 1e6, nu = 0.3, rho = 1000: stiff,
so their deformation, ~1e-4, is small against the slide).  Gravity g = 9.8 is tilted by theta
(degrees, default 30): gravity = g (sin theta, -cos theta), so the slab's top is an incline along
+x.  The slab is material 0, the block material 1, coupled by :class:`jaxmpm.Contact` with the
law ``contact`` ("coulomb" with ``friction`` mu = 0.2 by default; "frictionless" is mu = 0;
"stick" and "none" -- the single field -- glue the block to the slab).

Exact block displacement along x (rigid block on a rigid incline, Coulomb friction):
x(t) = g (sin theta - mu cos theta) t^2 / 2 when tan theta > mu, else 0 (it stays stuck);
``setup.reference(t)`` gives it and ``params["acceleration"]`` the factor g (sin - mu cos)
(with ``speed``, below, also when it is negative).

h = 0.025, 2x2 particles per cell, dt = cfl h / c (c the P-wave speed, cfl 0.5), t_end = 0.3
(0.315 after rounding to the 20 frames: the frictionless block slides 0.24, almost 10 cells).
The grid spans the slab and the block with room for the frictionless slide until t_end.

Defaults chosen from measurements (FLIP, the displacement at t_end against the exact one; tests/
test_contact_scenes.py):

* uGIMP shape functions: with linear ones every sliding run inverts a block particle (J <= 0) by
  t = 0.07, about when the block's front column of particles first crosses a node line (FLIP and
  PIC alike).
* the contact normal of jm.Contact's default, ``normal="first"``: the slab's (material 0's) mass
  gradient -- the slab is flat, so its normal is the incline's.  mu = 0: -0.00 %, mu = 0.2:
  +1.1 %; but mu = 0.7 creeps to 6.3 % of the frictionless displacement (PIC: +0.57 % and 0.74 %):
  gravity switched on at t = 0 sets the undamped slab ringing, and its surface velocity breaks the
  friction cone at most contact nodes each step (vibration ratcheting).  With gravity raised over
  ``ramp=0.05`` (a quasi-static load) FLIP holds at 0.13 % and the frictionless block follows the
  ramped exact solution to -0.1 %.  ``normal="average"`` tilts the normals at the block's corners,
  which then act as obstacles: -12 % (mu = 0) and -24 % (mu = 0.2), while mu = 0.7 stays at
  0.53 %.  ``normal="max_gradient"``: -0.00 % and +1.3 % (here the slab's top lies on a node
  line; where it lies half a cell off it ploughs, jaxmpm/physics/contact.py).

``speed`` launches the block along +x: x(t) = v0 t + A t^2 / 2 (A = g (sin theta - mu cos theta),
kinetic friction) until a decelerating block stops, at t = v0 / |A|, after which it stays
(``setup.reference``, ``params["stop"]``).  With ``theta=0`` it is a block braked by friction on
a flat slab, deceleration mu g: the check of the contact normal in tests/test_contact_scenes.py.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ..core.errors import check
from ..core.grid import Grid
from ..core.particles import Box, fill, joined
from ..materials import LinearElastic
from ..model.simulation import Simulation
from ..physics.conditions import Fixed
from ..physics.damping import Damping
from ..schemes import FLIP
from ..transfer.shapes import UGIMP
from ._common import Setup, cast_state, contact_model, contact_normal_param, material_ids, resolve_dtype, schedule
from ._options import checked_options

SLAB = ((0.0, 0.0), (1.0, 0.1))


class RampedGravity(eqx.Module):
    """Gravity raised linearly from 0 to ``gravity`` over ``ramp`` (a body force b(x, t))."""

    gravity: jnp.ndarray
    ramp: jnp.ndarray  # a leaf: another ramp compiles nothing new

    def __call__(self, x, t):
        return jnp.broadcast_to(self.gravity.astype(x.dtype) * jnp.minimum(t / self.ramp.astype(x.dtype), 1.0),
                                x.shape)
BLOCK = ((0.1, 0.1), (0.3, 0.2))


@checked_options
def slide(
    scheme=None,
    shape=None,
    spacing: float = 0.025,
    ppc: int = 2,
    cfl: float = 0.5,
    dt: float | None = None,
    t_end: float = 0.3,
    update: str = "USL",
    damping: Damping | None = None,
    dtype=None,
    frames: int = 20,
    E: float = 1e6,
    nu: float = 0.3,
    density: float = 1000.0,
    theta: float = 30.0,
    gravity: float = 9.8,
    contact: str = "coulomb",
    friction: float = 0.2,
    normal=None,
    ramp: float = 0.0,
    speed: float = 0.0,
) -> Setup:
    """The block on the slab with gravity ``gravity`` tilted by ``theta`` degrees; ``contact`` and
    ``friction`` as in the module docstring; ``normal``: the contact normal of jm.Contact (None:
    its default "first", the slab's; "max_gradient", "average", or a vector such as
    ``(-sin theta, cos theta)``, the incline's); ``ramp`` > 0 raises gravity linearly from 0 over
    that time (a quasi-static load; 0: switched on at t = 0); ``speed`` launches the block down the
    incline (along +x) at that velocity; dt = cfl * h / c unless ``dt`` is given."""
    dtype = resolve_dtype(dtype)
    check(np.ndim(gravity) == 0, f"slide: gravity = {gravity!r} must be one number, its magnitude g (theta tilts it)")
    check(gravity >= 0, f"slide: gravity = {gravity} must be >= 0 (its magnitude g; theta tilts it)")
    check(speed >= 0, f"slide: speed = {speed} must be >= 0 (the block's initial velocity down the incline)")
    check(speed == 0 or contact in ("coulomb", "frictionless"),
          f"slide: speed = {speed} needs contact='coulomb' or 'frictionless' (with {contact!r} the block is glued)")
    scheme = FLIP() if scheme is None else scheme
    shape = UGIMP(ppc=ppc) if shape is None else shape
    slab_height = SLAB[1][1] - SLAB[0][1]
    check(spacing <= slab_height, f"slide: spacing = {spacing} must be at most the slab's and the block's "
                                  f"height {slab_height:g}; use a smaller spacing")
    angle = math.radians(theta)
    sin, cos = math.sin(angle), math.cos(angle)
    mu = {"coulomb": friction, "frictionless": 0.0}.get(contact, math.inf)  # stick, none: glued
    # the acceleration while the block slides (kinetic friction): launched (speed > 0) or tan theta > mu
    acceleration = gravity * (sin - mu * cos) if sin > mu * cos or speed > 0 else 0.0
    # room on the grid for the frictionless slide until t_end, up to the block's leaving the slab
    # (beyond that it falls off the slab's end and out of the grid)
    travel = min(speed * t_end + 0.5 * gravity * sin * t_end * t_end,  # t_end * t_end: inf, no OverflowError
                 SLAB[1][0] - BLOCK[0][0])
    upper = (max(SLAB[1][0], BLOCK[1][0] + travel) + 2 * spacing, BLOCK[1][1] + 2 * spacing)
    grid = Grid.covering(SLAB[0], upper, spacing, shape=shape)
    slab = fill(grid, Box(*SLAB), ppc=ppc)
    block = fill(grid, Box(*BLOCK), ppc=ppc, velocity=(speed, 0.0))
    particles = joined(slab, block, ppc=ppc)
    base = Fixed(where=lambda x: x[:, 1] <= SLAB[0][1] + 1e-9 * spacing)  # the slab's bottom face (and below)
    terms, multimaterial = contact_model(contact, friction, normal)
    g = (gravity * sin, -gravity * cos)
    load = dict(gravity=g)
    if ramp != 0:
        load = dict(body_force=RampedGravity(jnp.asarray(g), jnp.asarray(ramp, dtype=jnp.result_type(float))))
    sim = Simulation(grid=grid, shape=shape, material=LinearElastic(E=E, nu=nu, density=density),
                     scheme=scheme, damping=damping, update=update, boundary=base, terms=terms, **load)
    fields = {"material": material_ids((slab.x.shape[0], block.x.shape[0]))} if multimaterial else None
    state = cast_state(sim.init(particles, fields=fields), dtype)
    if dt is None:
        dt = float(sim.stable_dt(state, cfl))  # cfl h / c (at rest)
    steps, save_every = schedule(t_end, dt, frames)

    def ramped(t):
        """(the load's double and single time integral): t^2/2 and t at once; with a ramp r, t^3/(6 r)
        and t^2/(2 r) for t < r, t^2/2 - r t/2 + r^2/6 and t - r/2 after."""
        if ramp == 0:
            return 0.5 * t**2, t
        return (np.where(t < ramp, t**3 / (6.0 * ramp), 0.5 * t**2 - 0.5 * ramp * t + ramp**2 / 6.0),
                np.where(t < ramp, t**2 / (2.0 * ramp), t - 0.5 * ramp))

    # a block launched at ``speed`` and decelerated by friction stops when v0 + A q(t) = 0 and stays
    if acceleration < 0:
        stop = -speed / acceleration if ramp == 0 else (
            math.sqrt(-2.0 * ramp * speed / acceleration) if -speed / acceleration < 0.5 * ramp
            else -speed / acceleration + 0.5 * ramp)
    else:
        stop = math.inf

    def reference(t):
        """Exact block displacement along x: v0 t + A t^2 / 2 while it slides, A = g (sin theta - mu cos
        theta) (0 if it does not slide) and v0 = ``speed``; with a ramp r, v0 t + A t^3 / (6 r) for
        t < r and v0 t + A (t^2/2 - r t/2 + r^2/6) after; a decelerating block stops when its velocity
        reaches 0 (and stays: it stops only where tan theta < mu)."""
        t = np.minimum(np.asarray(t, dtype=float), stop)
        return speed * t + acceleration * ramped(t)[0]

    params = dict(E=E, nu=nu, density=density, spacing=spacing, ppc=ppc, cfl=cfl, dt=dt, t_end=steps * dt,
                  theta=theta, gravity=gravity, contact=contact, mu=mu if math.isfinite(mu) else None,
                  acceleration=acceleration, slides=acceleration > 0 or speed > 0, ramp=ramp, speed=speed,
                  normal=contact_normal_param(terms),
                  stop=stop if math.isfinite(stop) else None,
                  slab=[list(SLAB[0]), list(SLAB[1])],
                  block=[list(BLOCK[0]), list(BLOCK[1])], n_first=int(slab.x.shape[0]))
    return Setup("slide", sim, state, dt, steps, save_every, params, reference, particles, fields)
