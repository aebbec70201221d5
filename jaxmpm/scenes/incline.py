"""``incline``: an elastic block slides down a rigid collider incline under gravity (issue 31).

2D, plane strain.  The incline is a :class:`jaxmpm.Collider` half-space whose surface runs
through the origin down along t = (cos theta, -sin theta) (``angle`` theta in degrees), outward
normal n = (sin theta, cos theta), with Coulomb friction mu (``friction``; 0 is free slip:
Stomakhin et al. 2013 §8).  Gravity is (0, -g), g = ``params["gravity"]``.  The block, L x H =
0.2 x 0.1, linear elastic (E = 1e6, nu = 0.3, rho = 1000: stiff, so its deformation is small
against the slide), lies on the surface, its particles on the rotated lattice of the block's own
frame (the lowest row a quarter cell above the surface).

Exact displacement along the incline (rigid block, Coulomb friction):
s(t) = a t^2 / 2 with a = g (sin theta - mu cos theta) when tan theta > mu, else 0 (it stays);
``setup.reference(t)`` gives s(t), ``params["acceleration"]`` a.  The grid acts on the nodes
inside the solid, so the block starts with a short transient (its bottom nodes are stopped, the
block settles by about one percent of a cell); after it the centre of mass follows a to within
1 % (tests/test_collider.py) away from the friction angle.

h = 0.025, 2x2 particles per cell, uGIMP shape functions, dt = cfl h / c (c the P-wave speed,
cfl 0.5), t_end = 0.3.  Measured (FLIP, the centre of mass's acceleration fitted after 0.03):
theta = 30 deg, mu = 0: a = 4.905 (exact to 1e-14); mu = 0.2: +0.019 %; theta = 45, mu = 0.3:
+0.017 %; near the friction angle (mu = 0.5, a = 0.657) +3 % (PIC: +0.45 %).  Linear shape
functions go unstable within 20 steps (USL: the block's rotated lattice leaves nodes with tiny
mass; MUSL is stable).  Where tan theta < mu FLIP creeps (mu = 0.7: 9 mm by t_end): gravity
switched on at t = 0 sets the undamped block ringing and the ringing breaks the friction cone
(vibration ratcheting, as in the ``slide`` scene); PIC holds it (0.3 mm, the initial settling).
"""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np

from ..core.errors import check
from ..core.grid import Grid
from ..core.particles import Box, fill
from ..materials import LinearElastic
from ..model.simulation import Simulation
from ..physics.collider import Collider, HalfSpace
from ..physics.damping import Damping
from ..schemes import FLIP
from ..transfer.shapes import UGIMP
from ._common import Setup, cast_state, resolve_dtype, schedule
from ._options import checked_options

BLOCK = (0.2, 0.1)  # length along the incline, height along its normal
START = 0.05  # the block's upper end, along the incline from the origin


def incline_frame(angle: float):
    """(t, n): the unit vector down the incline and its outward normal, for ``angle`` degrees."""
    a = math.radians(angle)
    return np.array([math.cos(a), -math.sin(a)]), np.array([math.sin(a), math.cos(a)])


@checked_options
def incline(
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
    angle: float = 30.0,
    friction: float = 0.2,
    gravity: float = 9.81,
) -> Setup:
    """The block on the collider incline of ``angle`` degrees with Coulomb friction ``friction``
    under gravity (0, -``gravity``); dt = cfl * h / c unless ``dt`` is given."""
    dtype = resolve_dtype(dtype)
    check(np.ndim(gravity) == 0 and gravity >= 0,
          f"incline: gravity = {gravity!r} must be one number >= 0, its magnitude g (it points down, -y)")
    check(spacing <= BLOCK[1] / 2, f"incline: spacing = {spacing} must be at most half the block's height "
                                   f"{BLOCK[1]:g}; use a smaller spacing")
    scheme = FLIP() if scheme is None else scheme
    shape = UGIMP(ppc=ppc) if shape is None else shape
    tangent, normal = incline_frame(angle)
    sin, cos = math.sin(math.radians(angle)), math.cos(math.radians(angle))
    acceleration = gravity * (sin - friction * cos) if sin > friction * cos else 0.0
    travel = 0.5 * gravity * sin * t_end * t_end  # the frictionless slide: room on the grid for any mu
    # the block in its own frame (s along the incline, h along the normal), filled on a lattice of
    # that frame and turned onto the incline
    frame = Grid((0.0, 0.0), BLOCK, (max(1, round(BLOCK[0] / spacing)), max(1, round(BLOCK[1] / spacing))))
    local = fill(frame, Box((0.0, 0.0), BLOCK), ppc=ppc)
    s, h = np.asarray(local.x[:, 0]) + START, np.asarray(local.x[:, 1])
    x = s[:, None] * tangent + h[:, None] * normal
    corners = np.array([s0 * tangent + h0 * normal for s0 in (START, START + BLOCK[0] + travel)
                        for h0 in (-2 * spacing, BLOCK[1])])
    grid = Grid.covering(corners.min(axis=0), corners.max(axis=0), spacing, shape=shape, pad=spacing)
    particles = type(local)(x=jnp.asarray(x), v=jnp.zeros_like(local.v), volume=local.volume, mass=None, ppc=ppc)
    surface = Collider(HalfSpace((0.0, 0.0), tuple(normal)), condition="friction", friction=friction, name="incline")
    sim = Simulation(grid=grid, shape=shape, material=LinearElastic(E=E, nu=nu, density=density), scheme=scheme,
                     damping=damping, update=update, gravity=(0.0, -gravity), terms=[surface])
    state = cast_state(sim.init(particles), dtype)
    if dt is None:
        dt = float(sim.stable_dt(state, cfl))  # cfl h / c (at rest)
    steps, save_every = schedule(t_end, dt, frames)

    def reference(t):
        """Exact displacement of the block along the incline: a t^2 / 2 (0 when tan theta <= mu)."""
        return 0.5 * acceleration * np.asarray(t, dtype=float) ** 2

    params = dict(E=E, nu=nu, density=density, spacing=spacing, ppc=ppc, cfl=cfl, dt=dt, t_end=steps * dt,
                  angle=angle, friction=friction, gravity=gravity, acceleration=acceleration,
                  slides=acceleration > 0, tangent=tangent.tolist(), normal=normal.tolist(),
                  block=list(BLOCK), start=START)
    return Setup("incline", sim, state, dt, steps, save_every, params, reference, particles)
