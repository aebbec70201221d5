"""``rings``: two elastic rings collide head-on and bounce apart.

Domain (-20, 20) x (-7.5, 7.5), h = 0.1, rings of inner radius 3 and outer radius 4 centred at
(-5, 0) and (5, 0) moving at V = (+30, 0) and (-30, 0), compressible neo-Hookean E = 100e6,
nu = 0.2, rho = 1e3 (plane strain), quadratic B-splines, 2x2 particles per cell,
dt = CFL h / (c + max|V|) with CFL 0.8, t_end = 0.6.  No boundary conditions or gravity, so the
exact total energy (kinetic + neo-Hookean strain) and linear momentum (zero) are constant; the
energy a scheme loses is its dissipation (docs/design.md "Scenes").
"""

from __future__ import annotations

from ..core.errors import check
from ..core.grid import Grid
from ..core.particles import Ring, fill, joined
from ..materials import NeoHookean
from ..model.simulation import Simulation
from ..physics.damping import Damping
from ..schemes import FLIP
from ..transfer.shapes import QuadraticBSpline
from ._common import Setup, cast_state, contact_model, contact_normal_param, material_ids, resolve_dtype, schedule
from ._options import checked_options

LOWER, UPPER = (-20.0, -7.5), (20.0, 7.5)


@checked_options
def rings(
    scheme=None,
    shape=None,
    spacing: float = 0.1,
    ppc: int = 2,
    cfl: float = 0.8,
    dt: float | None = None,
    t_end: float = 0.6,
    update: str = "USL",
    damping: Damping | None = None,
    dtype=None,
    frames: int = 200,
    E: float = 100e6,
    nu: float = 0.2,
    density: float = 1e3,
    speed: float = 30.0,
    inner: float = 3.0,
    outer: float = 4.0,
    separation: float = 10.0,
    contact: str = "none",
    friction: float = 0.0,
    normal="average",
) -> Setup:
    """Two rings ``separation`` apart (centre to centre) approaching at +-``speed``;
    dt = cfl * h / (c + speed) unless ``dt`` is given.  ``contact``: "none" (one velocity field) or
    a law ("stick", "frictionless", "coulomb" with ``friction`` mu), each ring its own material
    (id 0 for the left ring, 1 for the right; jaxmpm/physics/contact.py); ``normal``: the contact
    normal (jm.Contact's options; None: the library default "first"): "average" here, symmetric in
    the two rings of a head-on impact."""
    dtype = resolve_dtype(dtype)
    scheme = FLIP() if scheme is None else scheme
    shape = QuadraticBSpline() if shape is None else shape
    cells = tuple(round((hi - lo) / spacing) for lo, hi in zip(LOWER, UPPER))
    check(min(cells) >= 1, f"rings: spacing = {spacing} is wider than the domain "
                           f"{UPPER[0] - LOWER[0]:g} x {UPPER[1] - LOWER[1]:g}; use a smaller spacing")
    grid = Grid(LOWER, UPPER, cells)
    half = 0.5 * separation
    a = fill(grid, Ring((-half, 0.0), inner, outer), ppc=ppc, velocity=(speed, 0.0))
    b = fill(grid, Ring((half, 0.0), inner, outer), ppc=ppc, velocity=(-speed, 0.0))
    particles = joined(a, b, ppc=ppc)
    material = NeoHookean(E=E, nu=nu, density=density)
    terms, multimaterial = contact_model(contact, friction, normal)
    sim = Simulation(grid=grid, shape=shape, material=material, scheme=scheme, damping=damping, update=update,
                     terms=terms)
    fields = {"material": material_ids((a.x.shape[0], b.x.shape[0]))} if multimaterial else None
    state = cast_state(sim.init(particles, fields=fields), dtype)
    if dt is None:
        dt = float(sim.stable_dt(state, cfl))  # cfl h / (c + max|V|)
    steps, save_every = schedule(t_end, dt, frames)
    params = dict(E=E, nu=nu, density=density, spacing=spacing, ppc=ppc, speed=speed, inner=inner, outer=outer,
                  centres=[[-half, 0.0], [half, 0.0]], n_first=int(a.x.shape[0]), cfl=cfl, dt=dt,
                  t_end=steps * dt, contact=contact, friction=friction if contact == "coulomb" else 0.0,
                  normal=contact_normal_param(terms))
    return Setup("rings", sim, state, dt, steps, save_every, params, None, particles, fields)
