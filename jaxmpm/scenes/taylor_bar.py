"""``taylor_bar``: a copper rod hits a rigid frictionless wall (the Taylor impact test), von Mises
plasticity; final length and foot ("mushroom") radius.

The rod (length L0 = 25.4 mm, diameter D0 = 7.6 mm, copper: E = 117 GPa, nu = 0.35, rho = 8930
kg/m^3, sigma_y = 400 MPa, linear hardening H = 100 MPa) flies at v0 = 190 m/s along its axis into
a wall at z = 0; t_end = 80 us, by when it has stopped.  This is the copper rod of Wilkins & Guinan
1973 (J. Appl. Phys. 44, 1200) as the MPM literature models it (e.g. Sulsky, Zhou & Schreyer 1995,
Comput. Phys. Commun. 87, 236; Zhang, Chen & Liu 2016, "The Material Point Method", Academic Press):
a bilinear J2 law in place of the test's measured flow curve.  The literature's computed final
length is about 16.2-16.5 mm and foot radius about 7.0-7.5 mm (the values the issue quotes; not
confirmed here against the papers themselves, see experiments/results/taylor_bar.md).

Model: ``geometry="axisymmetric"`` (default) on an r-z grid (x = r, y = z; ``jm.Grid(...,
axisymmetric=True)``, 001 §7), the axis r = 0 a symmetry line (``Slip("x-")``: v_r = 0), the wall
the grid face z = 0 (``Slip("y-")``: v_z = 0, free slip).  ``geometry="3d"``: a quarter of the rod
on a 3D grid with the symmetry planes x = 0 and y = 0 (``Slip``), the wall z = 0.  ``cells`` cells
across the radius R0 (default 4: ``jaxmpm run taylor_bar`` takes seconds), ``ppc`` particles per cell
per axis, linear shape functions by default (a grid starting on the axis needs no nodes at r < 0),
dt = cfl h / c with c the P-wave speed.

Diagnostics (``setup.reference(x)``, particle positions x (N, D)): the final length (the largest z
plus half a particle spacing) and the foot radius (the largest radius of the particles in the
bottom layer, plus half a spacing), in metres, against the literature's values in ``LITERATURE``.
"""

from __future__ import annotations

import math

import equinox as eqx
import numpy as np

from ..core.errors import check
from ..core.grid import Grid
from ..core.particles import Box, Region, fill
from ..materials import VonMises
from ..model.simulation import Simulation
from ..physics.conditions import Slip
from ..schemes import FLIP
from ..transfer.shapes import Linear
from ._common import Setup, cast_state, resolve_dtype, schedule
from ._options import checked_options

#: the MPM literature's copper rod at t = 80 us (the issue's values; see the module docstring)
LITERATURE = {"length": (16.2e-3, 16.5e-3), "foot_radius": (7.0e-3, 7.5e-3)}
GEOMETRIES = ("axisymmetric", "3d")


class QuarterRod(Region):
    """The quarter x, y >= 0 of the rod x^2 + y^2 < R^2, 0 <= z < L (3D).

    Args:
        radius: R, positive.
        length: L, positive.
    """

    radius: float = eqx.field(static=True)
    length: float = eqx.field(static=True)

    def __init__(self, radius: float, length: float):
        self.radius = float(radius)
        self.length = float(length)

    def contains(self, x):
        x = np.asarray(x)
        return (x[:, 0] ** 2 + x[:, 1] ** 2 < self.radius ** 2) & (x[:, 2] >= 0.0) & (x[:, 2] < self.length) & \
            (x[:, 0] >= 0.0) & (x[:, 1] >= 0.0)

    def bounds(self):
        return (0.0, 0.0, 0.0), (self.radius, self.radius, self.length)


def shape_of(x, spacing: tuple) -> dict:
    """Final length and foot radius of the rod from particle positions x (N, 2) (r, z) or (N, 3):
    the highest particle's z and the widest bottom-layer particle's radius, each plus half the
    initial particle spacing ``spacing`` = (radial, axial) (the particles are volume centres)."""
    x = np.asarray(x)
    z = x[:, -1]
    r = x[:, 0] if x.shape[1] == 2 else np.hypot(x[:, 0], x[:, 1])
    bottom = z < z.min() + spacing[1]
    return {"length": float(z.max() + 0.5 * spacing[1]), "foot_radius": float(r[bottom].max() + 0.5 * spacing[0])}


@checked_options
def taylor_bar(
    scheme=None,
    shape=None,
    geometry: str = "axisymmetric",
    cells: int = 4,
    ppc: int = 2,
    cfl: float = 0.5,
    t_end: float = 80e-6,
    update: str = "MUSL",
    dtype=None,
    frames: int = 40,
    E: float = 117e9,
    nu: float = 0.35,
    density: float = 8930.0,
    yield_stress: float = 400e6,
    hardening: float = 100e6,
    v0: float = 190.0,
    length: float = 25.4e-3,
    radius: float = 3.8e-3,
) -> Setup:
    """Taylor impact: a copper rod (von Mises) at v0 into a rigid frictionless wall; final length and foot radius."""
    dtype = resolve_dtype(dtype)
    check(geometry in GEOMETRIES, f"taylor_bar: geometry = {geometry!r}; choose one of {', '.join(GEOMETRIES)}")
    scheme = FLIP() if scheme is None else scheme
    shape = Linear() if shape is None else shape
    h = radius / cells
    h_z = length / max(1, round(length / h))  # the rod's length a whole number of cells, as its radius
    spread = 2.5 * radius  # room for the foot (about twice R0)
    if geometry == "axisymmetric":
        grid = Grid.covering((0.0, 0.0), (spread, length), (h, h_z), shape=shape, axisymmetric=True)
        particles = fill(grid, Box((0.0, 0.0), (radius, length)), ppc=ppc, velocity=(0.0, -v0))
        walls = (Slip("x-"), Slip("y-"))  # the axis (v_r = 0), the wall (v_z = 0)
    else:
        grid = Grid.covering((0.0, 0.0, 0.0), (spread, spread, length), (h, h, h_z), shape=shape)
        particles = fill(grid, QuarterRod(radius, length), ppc=ppc, velocity=(0.0, 0.0, -v0))
        walls = (Slip("x-"), Slip("y-"), Slip("z-"))  # two symmetry planes, the wall
    check(grid.lower[0] == 0.0, f"taylor_bar: shape {type(shape).__name__} needs nodes at r < 0; use "
                                "shape='linear' (the grid must start on the axis)")
    material = VonMises(E=E, nu=nu, yield_stress=yield_stress, hardening=hardening, density=density)
    sim = Simulation(grid=grid, shape=shape, material=material, scheme=scheme, update=update, boundary=walls)
    state = cast_state(sim.init(particles), dtype)
    c = math.sqrt(E * (1.0 - nu) / ((1.0 + nu) * (1.0 - 2.0 * nu)) / density)
    dt = cfl * min(h, h_z) / c
    steps, save_every = schedule(t_end, dt, frames)
    spacing = (h / ppc, h_z / ppc)

    def reference(x):
        """{"length", "foot_radius"} of the particles at x, and the literature's ranges (module docstring)."""
        return {**shape_of(x, spacing), "literature": LITERATURE}

    params = dict(E=E, nu=nu, density=density, yield_stress=yield_stress, hardening=hardening, v0=v0, length=length,
                  radius=radius, cells=cells, ppc=ppc, cfl=cfl, t_end=steps * dt, geometry=geometry)
    return Setup("taylor_bar", sim, state, dt, steps, save_every, params, reference, particles)
