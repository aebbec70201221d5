"""``disks``: two elastic disks collide and separate (Sulsky, Chen & Schreyer 1994, §6).

Unit square, h = 0.05, disks R = 0.2 centred at (0.2, 0.2) and (0.8, 0.8) moving at +-(0.1, 0.1),
linear elastic E = 1000, nu = 0.3, rho = 1000, plane strain, 2x2 particles per cell, dt = 1e-3,
t_end = 4.  Checked: linear momentum (zero, conserved), energy history.

Defaults chosen from measurements (issue notes, README): uGIMP shape functions, because with
linear ones the run is at the mercy of cell crossing -- FLIP, FMPM(4) and FMPM(8) invert particles
(J <= 0) or not depending on round-off (1e-13 perturbations of the initial velocity flip the
outcome); and a grid padded by two cells beyond the unit square, because the rebounding disks
reach its edge by t = 4.  ``shape=jm.Linear(), pad=0`` gives Sulsky's original setting.

``contact="stick"|"frictionless"|"coulomb"`` (issue 12) gives each disk its own velocity field
and couples them with :class:`jaxmpm.Contact`; the default "none" is the single-field model above.
"""

from __future__ import annotations

from ..core.grid import Grid
from ..core.particles import Disk, fill, joined
from ..materials import LinearElastic
from ..model.simulation import Simulation
from ..physics.damping import Damping
from ..schemes import FLIP
from ..transfer.shapes import UGIMP
from ._common import Setup, cast_state, contact_model, contact_normal_param, material_ids, resolve_dtype, schedule
from ._options import checked_options


@checked_options
def disks(
    scheme=None,
    shape=None,
    spacing: float = 0.05,
    ppc: int = 2,
    dt: float = 1e-3,
    t_end: float = 4.0,
    update: str = "USL",
    damping: Damping | None = None,
    dtype=None,
    frames: int = 200,
    E: float = 1000.0,
    nu: float = 0.3,
    density: float = 1000.0,
    speed: float = 0.1,
    pad: float | None = None,
    contact: str = "none",
    friction: float = 0.0,
    separation: float | None = 1.0,
    normal="average",
) -> Setup:
    """``contact``: "none" (one velocity field, Sulsky's setting) or a contact law -- "stick",
    "frictionless", "coulomb" (with ``friction`` mu) -- with each disk its own material (ids 0 for
    the disk at (0.2, 0.2), 1 for the other; jaxmpm/_contact.py).  ``separation`` (cells) is the
    contact's separation criterion: 1.0 by default, measured (docs/contact.md): without it the
    disks interact from a cell apart and FLIP's energy dips to 0.896 in contact, as in single-field
    mode; with 1.0 the minimum is 0.959; 0.5 gains energy (1.059), 0 loses it (0.81).  ``normal``:
    the contact normal (jm.Contact's options; None: the library default "first"): "average" here,
    symmetric in the two disks of a head-on impact (the measurements above; FLIP frictionless
    minimum 0.951 with "first", jaxmpm/physics/contact.py)."""
    dtype = resolve_dtype(dtype)
    scheme = FLIP() if scheme is None else scheme
    shape = UGIMP(ppc=ppc) if shape is None else shape
    pad = 2 * spacing if pad is None else pad
    grid = Grid.covering((0.0, 0.0), (1.0, 1.0), spacing, shape=shape, pad=pad)
    a = fill(grid, Disk((0.2, 0.2), 0.2), ppc=ppc, velocity=(speed, speed))
    b = fill(grid, Disk((0.8, 0.8), 0.2), ppc=ppc, velocity=(-speed, -speed))
    particles = joined(a, b, ppc=ppc)
    terms, multimaterial = contact_model(contact, friction, normal, separation=separation)
    sim = Simulation(grid=grid, shape=shape, material=LinearElastic(E=E, nu=nu, density=density),
                     scheme=scheme, damping=damping, update=update, terms=terms)
    fields = {"material": material_ids((a.x.shape[0], b.x.shape[0]))} if multimaterial else None
    state = cast_state(sim.init(particles, fields=fields), dtype)
    steps, save_every = schedule(t_end, dt, frames)
    params = dict(E=E, nu=nu, density=density, spacing=spacing, ppc=ppc, speed=speed, radius=0.2,
                  centres=[[0.2, 0.2], [0.8, 0.8]], n_first=int(a.x.shape[0]), t_end=steps * dt, pad=pad,
                  contact=contact, friction=friction if contact == "coulomb" else 0.0,
                  separation=separation if contact != "none" else None,
                  normal=contact_normal_param(terms))
    return Setup("disks", sim, state, dt, steps, save_every, params, None, particles, fields)
