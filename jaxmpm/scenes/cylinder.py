"""``cylinder``: a thick-walled cylinder under internal pressure, axisymmetric (001 §7), settled
by damping to Lamé's static solution.

The wall a <= r <= b (inner = 1, outer = 2) of a long cylinder, linear elastic (E = 1000,
nu = 0.3, rho = 1), modelled on an axisymmetric r-z grid (``jm.Grid(..., axisymmetric=True)``):
masses, volumes and forces are per radian.  The cylinder is in plane strain (eps_zz = 0): the
model is a slab one cell high in z whose nodes all have v_z = 0 (rollers on both faces), so the
solution is independent of z.  ``cells`` cells through the wall, ``ppc`` particles per cell per
axis.  The pressure p (``pressure`` = 0.1: strains ~ 2e-4, small enough for the linear theory) acts
on the inner surface as a jm.Traction (p, 0) on the "x-" faces of the innermost particles (per
radian: times the surface's radius, 001 eq. 108), weighted by the grid basis N_i at the surface
(``basis="grid"``, 001 eq. 21), switched on at t = 0; grid damping alpha_g (default omega_0 =
sqrt(E / (rho (1 - nu^2))) / r_mean, about the wall's breathing frequency) settles the motion by
t = 1.  dt = cfl h / c, c the P-wave speed.

Exact (Lamé; plane strain; e.g. Timoshenko & Goodier, *Theory of Elasticity*, 3rd ed., ch. 4):

    u_r(r)      = p a^2 / (E (b^2 - a^2)) (1 + nu) ((1 - 2 nu) r + b^2 / r)
    sigma_rr(r) = p a^2 / (b^2 - a^2) (1 - b^2 / r^2)
    sigma_tt(r) = p a^2 / (b^2 - a^2) (1 + b^2 / r^2)

``setup.reference(r)`` returns {"u_r", "sigma_rr", "sigma_tt"} at radii r (the particles'
reference radii: small strain).  Measured (experiments/axisymmetric.py, results in
experiments/results/axisymmetric.md), largest error over the particles at 32 cells: u_r 0.92 %
(uGIMP) and 0.92 % (linear), sigma_tt 0.93 % and 1.08 %.  The u_r of the particle positions lags
the deformation by alpha_g dt (0.94 % here): jaxmpm's damping acts in the particle update (000
eq. 2.77) while F follows the undamped grid velocity; R_p (F_thth - 1) is within 0.03 %.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ..core.errors import check
from ..core.grid import Grid
from ..core.particles import Box, fill
from ..materials import LinearElastic
from ..model.simulation import Simulation
from ..physics.conditions import Slip
from ..physics.damping import Damping
from ..physics.loads import Traction
from ..schemes import FLIP
from ..transfer.shapes import UGIMP
from ._common import Setup, cast_state, resolve_dtype, schedule
from ._options import checked_options


@dataclasses.dataclass(frozen=True)
class Below:
    """The particles with x_axis < ``limit`` (the loaded inner face's layer), a module-level callable
    compared and hashed by value: the traction's ``where`` is static, so a lambda per build would
    compile the rollout again on every build.

    Args:
        axis: the coordinate compared (0: the radius).
        limit: the particles below it are picked.
    """

    axis: int
    limit: float

    def __call__(self, x):
        return x[:, self.axis] < self.limit


def lame(r, inner: float, outer: float, pressure: float, E: float, nu: float) -> dict:
    """Lamé's plane-strain thick-walled cylinder under internal pressure (module docstring)."""
    r = np.asarray(r, dtype=float)
    k = pressure * inner**2 / (outer**2 - inner**2)
    return {"u_r": k / E * (1.0 + nu) * ((1.0 - 2.0 * nu) * r + outer**2 / r),
            "sigma_rr": k * (1.0 - outer**2 / r**2),
            "sigma_tt": k * (1.0 + outer**2 / r**2)}


@checked_options
def cylinder(
    scheme=None,
    shape=None,
    cells: int = 32,
    ppc: int = 2,
    cfl: float = 0.5,
    t_end: float = 1.0,
    update: str = "USL",
    damping: Damping | None = None,
    dtype=None,
    frames: int = 50,
    E: float = 1000.0,
    nu: float = 0.3,
    density: float = 1.0,
    inner: float = 1.0,
    outer: float = 2.0,
    pressure: float = 0.1,
) -> Setup:
    """The cylinder with ``cells`` cells through the wall; ``damping`` defaults to grid damping
    alpha_g = 2 c_s / r_mean (module docstring)."""
    dtype = resolve_dtype(dtype)
    check(0 < inner < outer, f"cylinder: need 0 < inner ({inner}) < outer ({outer})")
    scheme = FLIP() if scheme is None else scheme
    shape = UGIMP(ppc=ppc) if shape is None else shape
    h = (outer - inner) / cells
    lam = E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))
    mu = E / (2.0 * (1.0 + nu))
    c = math.sqrt((lam + 2.0 * mu) / density)
    omega0 = math.sqrt(E / (density * (1.0 - nu * nu))) / (0.5 * (inner + outer))  # the breathing mode, about
    if damping is None:
        damping = Damping(grid=omega0)
    u_max = float(lame(inner, inner, outer, abs(pressure), E, nu)["u_r"])
    grid = Grid.covering((inner, 0.0), (outer, h), h, shape=shape, pad=(2.0 * u_max + h, 0.0), axisymmetric=True)
    particles = fill(grid, Box((inner, 0.0), (outer, h)), ppc=ppc)
    plane_strain = Slip(lambda x: np.ones(x.shape[0], dtype=bool), axis=1)  # v_z = 0 at every node: eps_zz = 0
    load = Traction(Below(0, inner + h / ppc), (pressure, 0.0), "x-", name="pressure", basis="grid")
    sim = Simulation(grid=grid, shape=shape, material=LinearElastic(E=E, nu=nu, density=density),
                     scheme=scheme, damping=damping, update=update, boundary=plane_strain, terms=(load,))
    state = cast_state(sim.init(particles), dtype)
    dt = cfl * h / c
    steps, save_every = schedule(t_end, dt, frames)

    def reference(r):
        """Lamé's u_r, sigma_rr and sigma_tt at radii ``r`` (module docstring)."""
        return lame(r, inner, outer, pressure, E, nu)

    params = dict(E=E, nu=nu, density=density, inner=inner, outer=outer, pressure=pressure, cells=cells, ppc=ppc,
                  cfl=cfl, t_end=steps * dt, alpha_g=omega0)
    return Setup("cylinder", sim, state, dt, steps, save_every, params, reference, particles)
