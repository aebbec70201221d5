"""``column_collapse``: a granular column collapses on a rough floor (issue 31; Drucker-Prager sand).

2D plane strain.  A column of dry sand, width L0 (``length``) and height H0 = a L0 (``aspect`` a),
stands at rest against the wall x = 0 on the floor y = 0 and is released at t = 0 under gravity
(0, -g).  The wall x = 0 is a free-slip wall (``jm.Slip``): the half of a symmetric collapse, as in
the quasi-2D channel experiments released by lifting a gate (Lube et al. 2005, Lajeunesse et al.
2005).  The floor is rough: its nodes are fixed (``jm.Fixed``, no slip), so the basal resistance is
the sand's own friction in the lowest layer, not a wall friction coefficient.

Sand: :class:`jaxmpm.DruckerPrager`, friction angle phi = 30 degrees (``friction_angle``), no
dilatancy (psi = 0, Klar et al. 2016), cohesion 0 (``cohesion``), bulk density 1800 kg/m^3,
nu = 0.3 and E = 1e6 Pa.  Real sand is stiffer (E ~ 1e7-1e8 Pa); E = 1e6 keeps the P-wave speed
near 27 m/s, so the explicit step dt = cfl h / c stays practical, while the elastic strain under
the column's own weight, rho g H0 / E ~ 7e-3 for H0 = 0.4 m, stays small against the plastic flow.

Quadratic B-splines and APIC (Klar et al. 2016 use both for sand) on cells of h = L0 / ``cells``
(default 8 cells across the column), 2x2 particles per cell; t_end = 5 sqrt(H0 / g) (the flow
stops by about 3 sqrt(H0/g): Lube et al. 2005).

Diagnostics (:func:`deposit`): the final run-out L_inf, the front of the deposit (the furthest
particle plus half a particle spacing), and the final height H_inf (the highest particle plus half
a spacing), normalised as (L_inf - L0) / L0 and H_inf / L0, against the experimental scalings
:func:`runout_scaling` and :func:`height_scaling` (``params["runout_scaling"]`` and
``params["height_scaling"]``).
"""

from __future__ import annotations

import math

import numpy as np

from ..core.errors import check
from ..core.grid import Grid
from ..core.particles import Box, fill
from ..materials import DruckerPrager
from ..model.simulation import Simulation
from ..physics.conditions import Fixed, Slip
from ..physics.damping import Damping
from ..schemes import APIC
from ..transfer.shapes import QuadraticBSpline
from ._common import Setup, cast_state, resolve_dtype, schedule
from ._options import checked_options

# The scalings of the final deposit of a quasi-2D (rectangular channel) granular column collapse as
# quoted from Lube, Huppert, Sparks & Freundt 2005 (Phys. Rev. E 72, 041301) and Lajeunesse,
# Monnier & Homsy 2005 (Phys. Fluids 17, 103302); the breaks between the regimes are only known to
# within a range (a ~ 1.8-3 for the run-out, ~0.7-1.15 for the height), and the coefficients depend
# somewhat on the material and on the base.
RUNOUT_BREAK = 2.3  # a below which (L_inf - L0)/L0 = 1.2 a, above which 1.9 a^(2/3)
HEIGHT_BREAK = 1.15  # a below which H_inf/L0 = a (the top is not reached), above which a^(2/5)


def runout_scaling(aspect):
    """(L_inf - L0) / L0 of the experiments: 1.2 a for a < 2.3, 1.9 a^(2/3) above (Lube et al. 2005)."""
    a = np.asarray(aspect, dtype=float)
    return np.where(a < RUNOUT_BREAK, 1.2 * a, 1.9 * a ** (2.0 / 3.0))


def height_scaling(aspect):
    """H_inf / L0 of the experiments: a for a < 1.15, a^(2/5) above (Lube et al. 2005)."""
    a = np.asarray(aspect, dtype=float)
    return np.where(a < HEIGHT_BREAK, a, a ** 0.4)


def deposit(x, particle_spacing: float) -> tuple[float, float]:
    """(L, H): the front (the largest x) and the height (the largest y) of the material, each the
    outermost particle's coordinate plus half the particle spacing (the edge of the material the
    particle stands for), from positions ``x`` (N, 2)."""
    x = np.asarray(x)
    half = 0.5 * particle_spacing
    return float(x[:, 0].max() + half), float(x[:, 1].max() + half)


@checked_options
def column_collapse(
    scheme=None,
    shape=None,
    aspect: float = 2.0,
    length: float = 0.2,
    cells: int = 8,
    ppc: int = 2,
    cfl: float = 0.5,
    dt: float | None = None,
    t_end: float | None = None,
    update: str = "USL",
    damping: Damping | None = None,
    dtype=None,
    frames: int = 50,
    E: float = 1.0e6,
    nu: float = 0.3,
    density: float = 1800.0,
    friction_angle: float = 30.0,
    cohesion: float = 0.0,
    gravity: float = 9.81,
) -> Setup:
    """The column of aspect ratio ``aspect`` = H0/L0 and width ``length`` = L0, ``cells`` cells
    across it; dt = cfl h / c unless ``dt`` is given, t_end = 5 sqrt(H0/g) unless given."""
    dtype = resolve_dtype(dtype)
    check(np.ndim(gravity) == 0 and gravity > 0,
          f"column_collapse: gravity = {gravity!r} must be one number > 0, its magnitude g (it points down, -y)")
    height = aspect * length
    h = length / cells
    check(height >= h, f"column_collapse: aspect = {aspect:g} makes the column {height:g} tall, less than one cell "
                       f"({h:g}); raise aspect or cells")
    scheme = APIC() if scheme is None else scheme
    shape = QuadraticBSpline() if shape is None else shape
    # room for the run-out: two and a half times the experiments' (FLIP throws particles past 1.5 times
    # at a = 2), and at least three column widths
    reach = length * max(3.0, 1.0 + 2.5 * float(runout_scaling(aspect)))
    grid = Grid.covering((0.0, 0.0), (reach, height + h), h, shape=shape)
    particles = fill(grid, Box((0.0, 0.0), (length, height)), ppc=ppc)
    tolerance = 1e-9 * h
    floor = Fixed(lambda x: x[:, 1] <= tolerance)  # the rough floor y = 0 and the nodes below it
    wall = Slip(lambda x: x[:, 0] <= tolerance, axis=0)  # the symmetry wall x = 0 and the nodes behind it
    sand = DruckerPrager(E=E, nu=nu, friction_angle=friction_angle, dilatancy_angle=0.0, cohesion=cohesion,
                         density=density)
    sim = Simulation(grid=grid, shape=shape, material=sand, scheme=scheme, damping=damping, update=update,
                     boundary=(floor, wall), gravity=(0.0, -gravity))
    state = cast_state(sim.init(particles), dtype)
    if dt is None:
        dt = float(sim.stable_dt(state, cfl))  # cfl h / c at rest
    if t_end is None:
        t_end = 5.0 * math.sqrt(height / gravity)
    steps, save_every = schedule(t_end, dt, frames)
    params = dict(aspect=aspect, length=length, height=height, cells=cells, spacing=h, ppc=ppc,
                  particle_spacing=h / ppc, cfl=cfl, dt=dt, t_end=steps * dt, E=E, nu=nu, density=density,
                  friction_angle=friction_angle, dilatancy_angle=0.0, cohesion=cohesion, gravity=gravity,
                  runout_scaling=float(runout_scaling(aspect)), height_scaling=float(height_scaling(aspect)),
                  floor="fixed (no slip)", wall="slip at x = 0")
    return Setup("column_collapse", sim, state, dt, steps, save_every, params, None, particles)


def normalised_deposit(setup: Setup, x) -> dict:
    """{"runout", "height", "runout_scaling", "height_scaling"}: (L_inf - L0)/L0 and H_inf/L0 of the
    particle positions ``x`` of a ``column_collapse`` setup, with the experiments' values."""
    p = setup.params
    front, top = deposit(x, p["particle_spacing"])
    return {"runout": (front - p["length"]) / p["length"], "height": top / p["length"],
            "runout_scaling": p["runout_scaling"], "height_scaling": p["height_scaling"]}


__all__ = ["column_collapse", "deposit", "height_scaling", "normalised_deposit", "runout_scaling"]
