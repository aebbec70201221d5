"""``bars_impact``: two identical 1D elastic bars meet at +-v0 and bounce apart (issue 12).

Bars of length L, Young's modulus E, density rho, c = sqrt(E/rho): the left one on [-L, 0] moving
at +v0, the right one on [0, L] at -v0, touching at x = 0 at t = 0.  Exact solution (1D waves):
a compression wave of stress -rho c v0 runs from the interface into each bar, reflects at the free
end as an unloading wave, and when it is back at the interface, at t = 2L/c, both bars are
stress-free with their velocities exchanged: the left bar leaves at -v0 and the right one at +v0.
The contact force per unit area is rho c v0 for 0 < t < 2L/c, and 0 after.

With ``contact="frictionless"`` (default) each bar is its own material (ids 0 left, 1 right) and
:class:`jaxmpm.Contact` lets them separate; ``contact="stick"`` glues the two fields on shared
nodes (it reduces to the single field), and ``contact="none"`` is the single-field model, in which
the bars cannot separate: they vibrate as one free-free bar of length 2L.  1D only.

Defaults: L = 1, E = 100, rho = 1, v0 = 0.1 (c = 10, contact duration 0.2), 32 cells along one
bar, 2 particles per cell, dt = 0.1 h/c, t_end = 4L/c.  Linear shape functions, measured against
uGIMP with FLIP and frictionless contact (tests/test_contact_scenes.py): exit velocities 5.1 % of
v0 short of the exchange (uGIMP 6.6 %), contact duration +1.6 % of 2L/c (uGIMP +1.9 %).  The
exchange converges at about order 0.75 in h: ``shape="ugimp", cells=256`` gives 1.45 % (FLIP),
1.40 % (XPIC(2)), 1.25 % (FMPM(2)); linear shapes invert a free end from 128 cells.  The grid
holds room for the bars to fly apart until t_end (|v0| t_end + 2 cells beyond each end).
"""

from __future__ import annotations

import math

import numpy as np

from ..core.grid import Grid
from ..core.particles import Box, fill, joined
from ..materials import LinearElastic
from ..model.simulation import Simulation
from ..physics.damping import Damping
from ..schemes import FLIP
from ..transfer.shapes import Linear
from ._common import Setup, cast_state, contact_model, material_ids, resolve_dtype, schedule
from ._options import checked_options

E, RHO, LENGTH, V0 = 100.0, 1.0, 1.0, 0.1


@checked_options
def bars_impact(
    scheme=None,
    shape=None,
    cells: int = 32,
    ppc: int = 2,
    cfl: float = 0.1,
    t_end: float | None = None,
    update: str = "USL",
    damping: Damping | None = None,
    dtype=None,
    frames: int = 200,
    E: float = E,
    density: float = RHO,
    v0: float = V0,
    length: float = LENGTH,
    contact: str = "frictionless",
) -> Setup:
    """Two bars of ``length`` with ``cells`` cells each and ``ppc`` particles per cell, meeting at
    +-``v0``; dt = cfl * h / c, t_end = 4 L / c unless given.  ``contact``: "frictionless"
    (default), "stick" or "none" (one velocity field); "coulomb" is frictionless in 1D."""
    dtype = resolve_dtype(dtype)
    scheme = FLIP() if scheme is None else scheme
    shape = Linear() if shape is None else shape
    h = length / cells
    c = math.sqrt(E / density)
    duration = 2.0 * length / c
    if t_end is None:
        t_end = 2.0 * duration
    dt = cfl * h / c
    steps, save_every = schedule(t_end, dt, frames)  # first: a run too long is refused before the grid is sized
    # room for the bars to fly apart: each end moves at most |v0| t_end, plus two cells; the grid
    # starts a whole number of cells left of -L so that x = 0 (the interface) is a node
    room = h * (math.ceil(abs(v0) * steps * dt / h) + 2)
    grid = Grid.covering((-length - room,), (length + room,), h, shape=shape)
    left = fill(grid, Box((-length,), (0.0,)), ppc=ppc, velocity=(v0,))
    right = fill(grid, Box((0.0,), (length,)), ppc=ppc, velocity=(-v0,))
    particles = joined(left, right, ppc=ppc)
    terms, multimaterial = contact_model(contact, 0.0)
    sim = Simulation(grid=grid, shape=shape, material=LinearElastic(E=E, nu=0.0, density=density),
                     scheme=scheme, damping=damping, update=update, terms=terms)
    fields = {"material": material_ids((left.x.shape[0], right.x.shape[0]))} if multimaterial else None
    state = cast_state(sim.init(particles, fields=fields), dtype)
    params = dict(E=E, density=density, length=length, v0=v0, c=c, contact_duration=duration,
                  exit_velocities=[-v0, v0], cells_along_bar=cells, ppc=ppc, cfl=cfl, dt=dt, t_end=steps * dt,
                  n_first=int(left.x.shape[0]), contact=contact,
                  contact_stress=density * c * abs(v0))

    def reference(t):
        """Exact mean velocities (left bar, right bar) at times t, shape (..., 2): the contact
        stress rho c v0 decelerates each bar uniformly for 2L/c (v -> -v), then they fly apart."""
        s = np.clip(np.asarray(t, dtype=float) / duration, 0.0, 1.0)
        vl = v0 * (1.0 - 2.0 * s)
        return np.stack([vl, -vl], axis=-1)

    return Setup("bars_impact", sim, state, dt, steps, save_every, params, reference, particles, fields)
