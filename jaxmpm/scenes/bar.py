"""``bar``: a 1D fixed-free elastic bar vibrating in its first mode.

E = 100, rho = 1, L = 25, v0 = 0.1, beta1 = pi/(2L), omega = beta1 sqrt(E/rho),
V(x, 0) = v0 sin(beta1 x), x = 0 fixed.  Exact centre-of-mass velocity (modal solution of the
1D wave equation): v_cm(t) = v0 / (beta1 L) cos(omega t).

The fixed end (``boundary``): ``"fixed"`` (default) zeroes the velocity on the nodes at and below
x = 0 (:class:`jaxmpm.Fixed`), exact for linear shapes; B-splines reach the node beyond the end,
whose zero velocity is not the odd continuation of the solution (u(-x) = -u(x)), and lose an
O(h) error there.  ``"mirror"`` makes x = 0 a symmetry plane (:class:`jaxmpm.Mirror`): the bar's
mirror image continues it oddly, so B-splines see the exact solution's symmetry.
"""

from __future__ import annotations

import math

import numpy as np

from ..core.errors import check
from ..core.grid import Grid
from ..core.particles import Box, fill
from ..materials import LinearElastic
from ..model.simulation import Simulation
from ..physics.conditions import Fixed, Mirror
from ..physics.damping import Damping
from ..schemes import FLIP
from ..transfer.shapes import Linear
from ._common import Setup, cast_state, resolve_dtype, schedule
from ._options import checked_options

E, RHO, LENGTH, V0 = 100.0, 1.0, 25.0, 0.1


@checked_options
def bar(
    scheme=None,
    shape=None,
    cells: int = 16,
    ppc: int = 2,
    cfl: float = 0.1,
    t_end: float = 40.0,
    update: str = "USL",
    damping: Damping | None = None,
    dtype=None,
    frames: int = 200,
    E: float = E,
    density: float = RHO,
    v0: float = V0,
    length: float = LENGTH,
    boundary: str = "fixed",
) -> Setup:
    """The fixed-free bar with ``cells`` cells along its length and ``ppc`` particles per cell;
    dt = cfl * h / c; ``boundary`` "fixed" or "mirror" (module docstring)."""
    check(boundary in ("fixed", "mirror"), f"bar: boundary = {boundary!r}; use 'fixed' (jm.Fixed on x <= 0) or "
                                           "'mirror' (x = 0 a symmetry plane, jm.Mirror: for B-splines)")
    dtype = resolve_dtype(dtype)
    scheme = FLIP() if scheme is None else scheme
    shape = Linear() if shape is None else shape
    h = length / cells
    beta1 = math.pi / (2.0 * length)
    c = math.sqrt(E / density)
    omega = beta1 * c
    amplitude = v0 / omega  # the free end's: a strain of about v0 / c along the bar, the small-strain model's
    check(amplitude <= length, f"bar: the free end would swing by v0 / omega = {amplitude:.3g} (v0 = {v0:g}, "
                               f"omega = pi/(2L) sqrt(E/rho) = {omega:.3g}), more than the bar's length {length:g}: "
                               "beyond a small-strain vibration; lower v0, or raise E or lower density")
    # room for the free end: its amplitude v0/omega (0.159 by default) plus one cell
    grid = Grid.covering((0.0,), (length + h + 2.0 * amplitude,), h, shape=shape)
    particles = fill(grid, Box((0.0,), (length,)), ppc=ppc, velocity=lambda x: v0 * np.sin(beta1 * x))
    tol = 1e-9 * length
    fixed = Fixed(where=lambda x: x[:, 0] <= tol) if boundary == "fixed" else Mirror("x-", 0.0)
    sim = Simulation(grid=grid, shape=shape, material=LinearElastic(E=E, nu=0.0, density=density),
                     scheme=scheme, damping=damping, update=update, boundary=fixed)
    state = cast_state(sim.init(particles), dtype)
    dt = cfl * h / c
    steps, save_every = schedule(t_end, dt, frames)

    def reference(t):
        """Exact centre-of-mass velocity v0/(beta1 L) cos(omega t)."""
        return v0 / (beta1 * length) * np.cos(omega * np.asarray(t))

    params = dict(E=E, density=density, length=length, v0=v0, beta1=beta1, omega=omega, cells_along_bar=cells,
                  ppc=ppc, cfl=cfl, t_end=steps * dt, boundary=boundary)
    return Setup("bar", sim, state, dt, steps, save_every, params, reference, particles)
