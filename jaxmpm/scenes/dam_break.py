"""``dam_break``: a 2D water column collapses in a tank -- Martin & Moyce 1952's square-based column.

A column of water of width a and height 2a (Martin & Moyce's n^2 = 2) stands at rest against the
left wall of a tank of length ``tank`` a with free-slip walls (left, right, floor; :class:`jaxmpm.Slip`)
and no lid, under gravity g.  At t = 0 the dam is gone and the column collapses; the surge front
x_front(t) runs along the floor and the residual column height h(t) at the left wall drops.
Martin & Moyce's variables: the front Z = x_front / a against T = t sqrt(2 g / a), the height
H = h / (2 a) against tau = t sqrt(g / a).

The water (:class:`jaxmpm.NewtonianFluid`): rho_0 = 1000 kg/m^3, dynamic viscosity eta = 1e-3 Pa s,
Tait's equation of state (gamma = 7) with the speed of sound c_0 = 10 sqrt(2 g (2a)): ten times
the largest velocity of the collapse, the free fall of the column's top, so that the density
varies by about (1/10)^2 = 1% (weak compressibility: Monaghan 1994, J. Comput. Phys. 110).  The
column starts at hydrostatic pressure, p = rho_0 g (2a - y) (J from the inverse equation of
state), so that no pressure wave rings at the start.

Sizes: a = 2.25 in = 0.05715 m, the larger of Martin & Moyce's two columns; h = a / ``cells``
(default 8 cells across the column), 2 x 2 particles per cell, quadratic B-splines, APIC.  The
walls are node planes x = 0, x = tank a and y = 0 with two further node layers beyond each (the
B-spline stencils of the particles next to a wall reach them; the Slip condition holds the
three layers), the grid's top 2 cells above the column.  dt = cfl h / (c_0 + sqrt(2 g 2a)),
cfl = 0.5.  The default t_end is T = 5.5 (t = 0.297 s), where Martin & Moyce's front is at
Z ~ 7.6 and the runs' at up to 8.0, inside the default tank of 10 a (the front must not reach the
far wall: a tank of 8 a stops the front of a 16-cell APIC run at T = 5.45).

The diagnostics are functions of the saved positions (``history.x``, (T, N, 2)):
:func:`surge_front` and :func:`residual_height` (each with half the particle spacing added: the
particles' extent, so that Z = 1 and H = 1 at t = 0), :func:`front_error` (the RMS of Z against
Martin & Moyce's points within the run) and :data:`MARTIN_MOYCE_FRONT`, their measured front for
n^2 = 2.
"""

from __future__ import annotations

import math

import equinox as eqx
import numpy as np

from ..core.device import to_device
from ..core.errors import check
from ..core.grid import Grid
from ..core.particles import Box, fill
from ..materials import NewtonianFluid
from ..model.simulation import Simulation
from ..physics.conditions import Slip
from ..physics.damping import Damping
from ..schemes import APIC
from ..transfer.shapes import QuadraticBSpline
from ._common import Setup, cast_state, resolve_dtype, schedule
from ._options import checked_options

# the equation of state inverted on the particles' pressures, in one compiled program (op by op it
# compiled one small program per operation on a first build)
_volume_ratio = eqx.filter_jit(lambda material, pressure: material.volume_ratio(pressure))

#: Martin & Moyce 1952 (Phil. Trans. R. Soc. Lond. A 244, 312-324), Fig. 3: the surge front of the
#: n^2 = 2 column with a = 2.25 in, as (T = t sqrt(2 g / a), Z = x_front / a).  The paper gives no
#: table of these points; the values are those digitised from Fig. 3 and distributed with PySPH
#: (pypr/pysph, pysph/examples/db_exp_data.py, "mm_data_2"), the set the SPH literature compares with.
#: Their first points agree to ~0.03 in Z with the set Lethe uses (chaos-polymtl/lethe,
#: examples/multiphysics/dam-break), read at the paper's 1/2-inch marks.
MARTIN_MOYCE_FRONT = np.array([
    [0.832, 1.217], [1.219, 1.474], [1.997, 2.292], [2.547, 2.995], [3.345, 4.134], [4.034, 4.944],
    [4.418, 5.881], [5.091, 6.980], [5.685, 7.945], [6.306, 8.966], [6.822, 9.986], [7.439, 10.963],
    [8.031, 11.977], [8.633, 13.005], [9.237, 13.970],
])

#: the same for the smaller column, a = 1.125 in (PySPH's "mm_data_1"): the scale effect of the
#: experiment (surface tension, the release of the dam) is the difference between the two sets
MARTIN_MOYCE_FRONT_SMALL = np.array([
    [0.849, 1.245], [1.212, 1.443], [1.602, 1.884], [2.283, 2.689], [2.950, 3.728], [3.598, 4.528],
    [3.905, 4.999], [4.592, 5.841], [4.961, 6.271], [5.316, 6.717],
])

#: Martin & Moyce's larger column, 2.25 inches
WIDTH = 2.25 * 0.0254


@checked_options
def dam_break(
    scheme=None,
    shape=None,
    cells: int = 8,
    ppc: int = 2,
    cfl: float = 0.5,
    dt: float | None = None,
    t_end: float | None = None,
    frames: int = 100,
    width: float = WIDTH,
    tank: float = 10.0,
    density: float = 1000.0,
    viscosity: float = 1e-3,
    sound_speed: float | None = None,
    gravity: float = 9.81,
    update: str = "USL",
    damping: Damping | None | bool = False,
    dtype=None,
) -> Setup:
    """Martin & Moyce 1952: a 2D water column (a x 2a) collapses in a tank with slip walls; surge
    front and residual height against their measurements.  ``cells`` across the column width a
    (``width``, m), ``tank`` the tank's length in units of a, ``viscosity`` eta (Pa s),
    ``sound_speed`` c_0 (m/s; None: 10 sqrt(2 g 2a)), ``gravity`` g (m/s^2, downward); t_end None:
    T = t sqrt(2 g / a) = 5.5."""
    check(tank >= 2.0, f"dam_break: tank = {tank!r} must be at least 2 (the tank's length in column widths a)")
    check(np.ndim(gravity) == 0 and gravity > 0,
          f"dam_break: gravity = {gravity!r} must be one positive number g (it points down)")
    dtype = resolve_dtype(dtype)
    scheme = APIC() if scheme is None else scheme
    shape = QuadraticBSpline() if shape is None else shape
    a, g = float(width), float(gravity)
    height = 2.0 * a
    h = a / cells
    n_tank = int(round(tank * cells))
    pad = 2  # node layers beyond each wall
    grid = Grid((-pad * h, -pad * h), ((n_tank + pad) * h, height + pad * h), (n_tank + 2 * pad, 2 * cells + 2 * pad))
    top_speed = math.sqrt(2.0 * g * height)  # the free fall of the column's top
    c0 = 10.0 * top_speed if sound_speed is None else float(sound_speed)
    material = NewtonianFluid(K=density * c0**2, eta=viscosity, density=density, eos="tait")
    walls = (Slip("x-", layers=pad + 1), Slip("x+", layers=pad + 1), Slip("y-", layers=pad + 1))
    sim = Simulation(grid=grid, shape=shape, material=material, scheme=scheme, damping=damping, update=update,
                     boundary=walls, gravity=(0.0, -g))
    particles = fill(grid, Box((0.0, 0.0), (a, height)), ppc=ppc)
    state = sim.init(particles)
    # hydrostatic start: p = rho_0 g (2a - y), F = J^(1/2) I with J the volume ratio at p
    y = np.asarray(particles.x)[:, 1]
    J = np.asarray(_volume_ratio(material, density * g * (height - y)))
    state = cast_state(eqx.tree_at(lambda s: s.F, state, to_device(np.sqrt(J)[:, None, None] * np.eye(2))), dtype)
    if dt is None:
        dt = cfl * h / (c0 + top_speed)
    scale = math.sqrt(2.0 * g / a)  # T = t scale
    if t_end is None:
        t_end = 5.5 / scale
    steps, save_every = schedule(t_end, dt, frames)
    params = dict(width=a, height=height, tank=tank * a, cells=cells, ppc=ppc, spacing=h, dt=dt, t_end=steps * dt,
                  density=density, viscosity=viscosity, sound_speed=c0, bulk_modulus=density * c0**2, gamma=7.0,
                  gravity=g, time_scale=scale, particle_spacing=h / ppc)
    return Setup("dam_break", sim, state, dt, steps, save_every, params, None, particles)


# ----------------------------------------------------------------------------------- diagnostics
def surge_front(x, params: dict):
    """Z = x_front / a per frame, x_front = max_p x_p + half the particle spacing (the particles'
    extent), from positions ``x`` (T, N, 2) or (N, 2) and the scene's ``params``."""
    x = np.asarray(x)
    return (x[..., 0].max(axis=-1) + 0.5 * params["particle_spacing"]) / params["width"]


def residual_height(x, params: dict):
    """H = h / (2a) per frame, h the top of the particles within one cell of the left wall (plus
    half the particle spacing), from positions ``x`` (T, N, 2) or (N, 2).  One cell, not one
    particle spacing: the column of particles next to the wall thins as the water drains."""
    x = np.asarray(x)
    at_wall = x[..., 0] < params["spacing"]
    top = np.where(at_wall, x[..., 1], -np.inf).max(axis=-1)
    return (top + 0.5 * params["particle_spacing"]) / params["height"]


def front_error(time, x, params: dict, data=MARTIN_MOYCE_FRONT):
    """(rms, points): the root mean square of Z_run(T) - Z_measured over Martin & Moyce's points
    ``data`` (T, Z) with T within the run, Z_run interpolated linearly between the saved frames
    ``time`` (T,) with positions ``x`` (T, N, 2); and how many points it covers."""
    T = np.asarray(time) * params["time_scale"]
    Z = surge_front(x, params)
    inside = data[:, 0] <= T[-1]
    check(inside.any(), "front_error: the run ends before Martin & Moyce's first point (T = 0.83); run longer")
    diff = np.interp(data[inside, 0], T, Z) - data[inside, 1]
    return float(np.sqrt(np.mean(diff**2))), int(inside.sum())
