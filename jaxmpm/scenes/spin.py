"""``spin``: a disk set spinning rigidly, V = omega x (X - c), about its centre c.

Unit square, h = 1/32, disk R = 0.3 at (0.5, 0.5), omega = 1, quadratic B-splines, 2x2 particles
per cell.  ``stress=False`` (default) switches the stress off (material :class:`NoStress`,
tau = 0): each particle then flies off along a straight line at constant speed, so the exact
total kinetic energy and angular momentum are constant (the exact velocity field stays affine,
v(x, t) = W (I + W t)^-1 (x - c), W = omega [[0, -1], [1, 0]]), which is what APIC preserves
(002 prop. 5.1, props. 5.4-5.5) and PIC smears away.  With ``stress=True`` the disk is
neo-Hookean (E, nu, density) and spins as an elastic body; angular momentum is again conserved.

The free flight reaches the grid edge at t = sqrt((0.5 - h/2)^2 / R^2 - 1) / omega ~ 1.27, so the
force-free default is t_end = 1; the elastic default is one revolution, 2 pi / omega.
Under APIC/TPIC the affine field starts consistent with the rigid rotation
(:func:`jaxmpm.with_velocity_gradient`, ``affine_start=True``).
"""

from __future__ import annotations

import math

import numpy as np

from ..core.errors import check
from ..core.grid import Grid
from ..core.particles import Disk, fill
from ..materials import NeoHookean, NoStress
from ..model.simulation import Simulation
from ..physics.damping import Damping
from ..schemes import FLIP, with_velocity_gradient
from ..transfer.shapes import QuadraticBSpline
from ._common import Setup, cast_state, resolve_dtype, schedule
from ._options import checked_options


@checked_options
def spin(
    scheme=None,
    shape=None,
    spacing: float = 1.0 / 32.0,
    ppc: int = 2,
    radius: float = 0.3,
    omega: float = 1.0,
    stress: bool = False,
    E: float | None = None,
    nu: float | None = None,
    density: float = 1.0,
    cfl: float = 0.25,
    dt: float | None = None,
    t_end: float | None = None,
    update: str = "USL",
    damping: Damping | None = None,
    dtype=None,
    frames: int = 200,
    affine_start: bool = True,
) -> Setup:
    """The spinning disk; dt = cfl * h / (c + omega R) unless ``dt`` is given (c = 0 without stress).  ``E``
    (default 100) and ``nu`` (default 0.3) are the neo-Hookean disk's with ``stress=True``; without stress
    they are an error."""
    check(stress or (E is None and nu is None),
          "spin: E and nu are the neo-Hookean disk's; give stress=True (jaxmpm run spin --stress) with them, or "
          "leave them out: without stress the disk is stress-free (NoStress)")
    E = 100.0 if E is None else E
    nu = 0.3 if nu is None else nu
    dtype = resolve_dtype(dtype)
    scheme = FLIP() if scheme is None else scheme
    shape = QuadraticBSpline() if shape is None else shape
    centre = (0.5, 0.5)
    grid = Grid.covering((0.0, 0.0), (1.0, 1.0), spacing, shape=shape)
    spin_matrix = np.array([[0.0, -omega], [omega, 0.0]])  # V = W (X - c) = omega e_z x (X - c)

    def rigid(x):
        return (x - np.array(centre)) @ spin_matrix.T

    particles = fill(grid, Disk(centre, radius), ppc=ppc, velocity=rigid)
    material = NeoHookean(E=E, nu=nu, density=density) if stress else NoStress(density=density)
    sim = Simulation(grid=grid, shape=shape, material=material, scheme=scheme, damping=damping, update=update)
    state = cast_state(sim.init(particles), dtype)
    if affine_start:
        state = with_velocity_gradient(sim, state, spin_matrix)
    if dt is None:
        c = float(material.wave_speed(2))
        check(c + abs(omega) * radius > 0, "spin: omega = 0 without stress sets no time scale; give dt")
        dt = cfl * grid.h / (c + abs(omega) * radius)
    if t_end is None:
        check(omega != 0 or not stress, "spin: omega = 0 has no period (the default t_end); give t_end")
        t_end = 2.0 * math.pi / abs(omega) if stress else 1.0
    steps, save_every = schedule(t_end, dt, frames)
    params = dict(spacing=spacing, ppc=ppc, radius=radius, omega=omega, centre=list(centre), stress=bool(stress),
                  E=E if stress else 0.0, nu=nu, density=density, cfl=cfl, dt=dt, t_end=steps * dt)
    return Setup("spin", sim, state, dt, steps, save_every, params, None, particles)
