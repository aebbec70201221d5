"""``mpm88``: Taichi's 88-line MPM demo (``python -m taichi example mpm88``).

8192 particles uniformly random in the box [0.2, 0.6]^2 (a fixed NumPy seed instead of
``ti.random()``), V = (0, -1), on the unit square with 128 cells per axis (dx = 1/128),
dt = 2e-4, quadratic B-splines, particle volume (dx/2)^2 and density 1, gravity 9.8 downward,
weakly compressible fluid tau = E (J - 1) I with E = 400 (:class:`jaxmpm.VolumetricFluid`),
APIC transfer, and mpm88's sticky walls ``bound = 3`` cells wide: on nodes i < 3 a velocity
component v_x < 0 is zeroed, on nodes i > n - 3 a v_x > 0 (likewise y) -- one-sided walls,
:class:`jaxmpm.Wall` with ``layers=3``, acting on the updated grid velocity as in mpm88.
No damping in the model (``damping=False``; pass ``jm.Damping(...)`` to add it): with APIC
and no damping, P2G scatters the updated momentum p + f dt, as mpm88 does
(:func:`jaxmpm.folds_force`).

Differences from mpm88, by design:
* mpm88 is MLS-MPM: its force is -sum_p V0 tau D^-1 (x_i - X_p) S_pi with D = dx^2/4, which for
  quadratic B-splines is APIC with that force.  jaxmpm's step uses the standard
  f_i = -sum_p V0 tau G_pi (001 eq. 20) for every scheme, so the force, and with it the
  velocity gradient of the strain update (sum_i v_i (x) G_pi, not mpm88's C_p = B_p D^-1), is
  the gradient form.  Both are consistent discretisations of the same equations; the gradient
  form keeps one step function for all schemes.
* J = det F with F <- (I + grad v dt) F, where mpm88 updates J <- J (1 + dt tr C); after each
  step the fluid resets F to J^(1/2) I (:meth:`VolumetricFluid.keep_deformation`), so F carries
  only mpm88's one number J (without the reset the shear piles up in F, |F| ~ 5e3 by t = 0.28,
  and a float32 det F turns <= 0).
* The grid has 129 nodes per axis (mpm88: 128); particles never reach the extra node layer
  (it lies inside the wall), and ``Wall(face, layers=3)`` covers the same nodes as mpm88's
  ``i < 3`` and ``i > 125``.
"""

from __future__ import annotations

import numpy as np

from ..core.errors import check
from ..core.grid import Grid
from ..core.particles import Particles
from ..materials import VolumetricFluid
from ..model.simulation import Simulation
from ..physics.conditions import Wall
from ..physics.damping import Damping
from ..schemes import APIC
from ..transfer.shapes import QuadraticBSpline
from ._common import Setup, cast_state, resolve_dtype, schedule
from ._options import checked_options


@checked_options
def mpm88(
    scheme=None,
    shape=None,
    n_particles: int = 8192,
    n_grid: int = 128,
    dt: float = 2e-4,
    t_end: float = 1.0,
    E: float = 400.0,
    density: float = 1.0,
    gravity: float | tuple = 9.8,
    bound: int = 3,
    speed: float = 1.0,
    seed: int = 0,
    update: str = "USL",
    damping: Damping | None | bool = False,
    dtype=None,
    frames: int = 200,
) -> Setup:
    """The mpm88 scene; ``n_particles`` random points in [0.2, 0.6]^2 (NumPy seed ``seed``);
    ``gravity`` its magnitude g, downward, or the vector (gx, gy)."""
    dtype = resolve_dtype(dtype)
    downward = np.ndim(gravity) == 0
    check(downward or len(gravity) == 2,
          f"mpm88: gravity = {gravity!r} has {np.size(gravity)} components but the scene is 2D; give g (downward) "
          "or gx, gy")
    scheme = APIC() if scheme is None else scheme
    shape = QuadraticBSpline() if shape is None else shape
    grid = Grid((0.0, 0.0), (1.0, 1.0), (n_grid, n_grid))
    dx = 1.0 / n_grid
    rng = np.random.default_rng(seed)
    x = rng.random((n_particles, 2)) * 0.4 + 0.2
    p_vol = (dx * 0.5) ** 2
    particles = Particles(x=np.asarray(x), v=np.tile([0.0, -speed], (n_particles, 1)),
                          volume=np.full(n_particles, p_vol), mass=None, ppc=2)
    walls = tuple(Wall(face, layers=bound) for face in ("x-", "x+", "y-", "y+"))
    sim = Simulation(grid=grid, shape=shape, material=VolumetricFluid(E=E, density=density), scheme=scheme,
                     damping=damping, update=update, boundary=walls,
                     gravity=(0.0, -gravity) if downward else tuple(gravity))
    state = cast_state(sim.init(particles), dtype)
    steps, save_every = schedule(t_end, dt, frames)
    params = dict(n_particles=n_particles, n_grid=n_grid, dx=dx, dt=dt, E=E, density=density, p_vol=p_vol,
                  gravity=gravity if downward else list(gravity), bound=bound, speed=speed, seed=seed, t_end=steps * dt)
    return Setup("mpm88", sim, state, dt, steps, save_every, params, None)
