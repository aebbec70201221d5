"""Run by tests/test_parallel_slabs.py in a process of its own with forced CPU devices: the terms that
act on the grid's nodes by their positions or numbers -- rigid colliders (jm.Collider), tractions
(jm.Traction), the conditions' reaction (jm.Reaction), symmetry planes (jm.Mirror), heat and
diffusion with held and flux nodes and across contact interfaces (jm.Heat, jm.Diffusion), symmetry planes
and mirrored held nodes normal to x (the slabs' axis) -- stepped by
jaxmpm.parallel.ShardedSimulation on 4 devices (equal slabs, and slabs that move) against the same
model on one device, float64, in small scenes whose bodies and solids cross the slab faces.  Prints
one JSON line."""

import json
import sys

import jax

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jaxmpm as jm  # noqa: E402
from jaxmpm.parallel import ShardedSimulation  # noqa: E402

DEVICES = int(sys.argv[1]) if len(sys.argv) > 1 else 4
STEPS = 40
H = 1.0 / 32  # 32 cells along x: slabs of 16 or 8 cells, their faces at x = 0.5 (and 0.25, 0.75)
out = {}


def impact():
    """A disk thrown down and right onto a fixed floor (the reaction), a static inclined half-space in
    its way (friction) and a box sweeping left across the slab face x = 0.5 (slip): two colliders."""
    shape = jm.UGIMP(ppc=2)
    grid = jm.Grid((0.0, 0.0), (1.0, 0.5), (32, 16))
    particles = jm.fill(grid, jm.Disk((0.3, 0.16), 0.1), ppc=2, velocity=(1.0, -0.5))
    box = jm.Collider(jm.SolidBox((0.53, 0.05), (0.62, 0.4)), condition="slip", velocity=(-1.5, 0.0), name="box")
    ramp = jm.Collider(jm.HalfSpace((0.33, 0.0), (-1.0, 1.0)), friction=0.3, name="ramp")
    sim = jm.Simulation(grid, shape, jm.LinearElastic(E=1e4, nu=0.3, density=1000.0), "flip", gravity=(0.0, -10.0),
                        boundary=jm.Fixed("y-", layers=3), terms=[box, ramp, jm.Reaction()])
    return sim, sim.init(particles), 2e-3


def beam():
    """A beam along x, held at its left end, pulled at its right end (x+) and pressed on its top face,
    which spans every slab (y+): two tractions; and a point force on its middle particles."""
    shape = jm.QuadraticBSpline()
    grid = jm.Grid((0.0, 0.0), (1.0, 0.25), (32, 8))
    particles = jm.fill(grid, jm.Box((0.1, 0.0625), (0.9, 0.1875)), ppc=2)
    end = jm.Traction(lambda x: x[:, 0] > 0.9 - H / 2, (2e3, 0.0), "x+", name="end")
    top = jm.Traction(lambda x: x[:, 1] > 0.1875 - H / 2, lambda t: jnp.stack([0.0 * t, -4e4 * t]), "y+", name="top")
    point = jm.ParticleForce(lambda x: np.abs(x[:, 0] - 0.5) < H, (0.0, 5.0))
    sim = jm.Simulation(grid, shape, jm.LinearElastic(E=1e5, nu=0.3, density=1000.0), "apic",
                        boundary=jm.Fixed(lambda x: x[:, 0] <= 0.1 + 1e-9), terms=[end, top, point])
    return sim, sim.init(particles), 1e-3


def symmetric():
    """The upper half of a block on the symmetry plane y = 2 h (jm.Mirror: the lower half is its image),
    moving right across the slab faces and pressed onto the plane."""
    grid = jm.Grid((0.0, 0.0), (1.0, 0.5), (32, 16))
    particles = jm.fill(grid, jm.Box((0.2, 2 * H), (0.45, 0.2)), ppc=2, velocity=(1.5, -0.5))
    sim = jm.Simulation(grid, jm.UGIMP(ppc=2), jm.LinearElastic(E=1e4, nu=0.3, density=1000.0), "flip",
                        boundary=jm.Mirror("y-", 2 * H))
    return sim, sim.init(particles), 2e-3


def heated():
    """A block moving right across the slab faces through a band of nodes held hot (jm.Dirichlet), with
    a heat flux into its top (jm.Neumann), conduction with thermal expansion and an XPIC(2) update."""
    grid = jm.Grid((0.0, 0.0), (1.0, 0.25), (32, 8))
    particles = jm.fill(grid, jm.Box((0.1, 0.0625), (0.55, 0.1875)), ppc=2, velocity=(1.5, 0.0))
    hot = jm.Dirichlet(lambda x: np.abs(x[:, 0] - 0.5) < 0.04, 100.0)
    flux = jm.Neumann(lambda x: x[:, 1] > 0.1875 - 1e-9, 2e3)
    heat = jm.Heat(50.0, heat_capacity=1.0, expansion=1e-4, boundary=(hot, flux), update="xpic:2",
                   initial=10.0)
    sim = jm.Simulation(grid, jm.UGIMP(ppc=2), jm.LinearElastic(E=1e4, nu=0.3, density=1000.0), "flip",
                        terms=[heat])
    return sim, sim.init(particles), 2e-3


def heated_contact():
    """Two blocks, the left one hot and wet, pushed together across a slab face: contact's two velocity
    fields; heat on the nodes the fields share (a perfect interface), moisture crossing the interface
    by a mass-transfer coefficient (each field against the rest)."""
    grid = jm.Grid((0.0, 0.0), (1.0, 0.25), (32, 8))
    a = jm.fill(grid, jm.Box((0.2, 0.0625), (0.45, 0.1875)), ppc=2, velocity=(0.5, 0.0))
    b = jm.fill(grid, jm.Box((0.5, 0.0625), (0.75, 0.1875)), ppc=2, velocity=(-0.5, 0.0))
    particles = type(a)(x=jnp.concatenate([a.x, b.x]), v=jnp.concatenate([a.v, b.v]),
                        volume=jnp.concatenate([a.volume, b.volume]), mass=None, ppc=2)
    left = lambda x: np.where(x[:, 0] < 0.475, 1.0, 0.0)  # noqa: E731
    heat = jm.Heat(50.0, heat_capacity=1.0, initial=lambda x: 50.0 * left(x))
    moisture = jm.Diffusion(1e-2, interface=1.0, initial=left)
    sim = jm.Simulation(grid, jm.UGIMP(ppc=2), jm.LinearElastic(E=1e4, nu=0.3, density=1000.0), "flip",
                        terms=[jm.Contact(law="frictionless"), heat, moisture])
    ids = jnp.concatenate([jnp.zeros(a.x.shape[0]), jnp.ones(b.x.shape[0])])
    return sim, sim.init(particles, fields={"material": ids}), 2e-3


def symmetric_x():
    """The right half of a block on the symmetry plane x = 0 normal to the slabs' axis (jm.Mirror("x-"):
    the left half is its image, its ghost node planes at the grid's low end, in the first slab's
    window), thrown down and squeezed onto the plane across the slab face x = 0.1875."""
    grid = jm.Grid((-2 * H, 0.0), (1.0 - 2 * H, 0.5), (32, 16))
    particles = jm.fill(grid, jm.Box((0.0, 0.1), (0.4, 0.3)), ppc=2,
                        velocity=lambda x: np.stack([-2.5 * x[:, 0], -0.5 + 0 * x[:, 0]], 1))
    sim = jm.Simulation(grid, jm.QuadraticBSpline(), jm.LinearElastic(E=1e4, nu=0.3, density=1000.0), "flip",
                        gravity=(0.0, -10.0), boundary=jm.Mirror("x-", 0.0))
    return sim, sim.init(particles), 2e-3


def held_mirrored():
    """heat1d in 2D: a strip [0, 30 h] whose ends are held at T = 0 by odd extension beyond them
    (jm.Dirichlet(..., mirror=...) at x = 0 and x = 30 h: ghost planes at both ends of the grid),
    T0 a sine, XPIC(2) transport; the strip sways along x, its middle crossing the slab faces."""
    grid = jm.Grid((-H, 0.0), (1.0 - H, 0.25), (32, 8))
    length = 30 * H
    particles = jm.fill(grid, jm.Box((0.0, 0.0625), (length, 0.1875)), ppc=2,
                        velocity=lambda x: np.stack([0.5 * np.sin(np.pi * x[:, 0] / length), 0 * x[:, 0]], 1))
    x = grid.node_coordinates()[:, 0]
    ends = [jm.Dirichlet(jm.NodeSet(side * (x - at) >= -1e-9), 0.0, mirror=(0, at)) for at, side in ((0.0, -1),
                                                                                                     (length, 1))]
    heat = jm.Heat(0.1, heat_capacity=1.0, boundary=ends, update="xpic:2",
                   initial=lambda x: np.sin(np.pi * np.asarray(x)[:, 0] / length))
    sim = jm.Simulation(grid, jm.QuadraticBSpline(), jm.LinearElastic(E=10.0, nu=0.3, density=1.0), "flip",
                        terms=[heat])
    return sim, sim.init(particles), 2e-3


def totals(sim, state):
    return {name: float(value) if np.ndim(value) == 0 else np.asarray(value).tolist()
            for name, value in sim.totals(state).items()
            if "force" in name or name in ("reaction", "thermal_energy", "solute")}


# each scene on equal slabs; the colliders and the symmetry plane also on slabs that move (their windows
# start at runtime boundaries), rebalanced every 10 steps
for name, scene, moving in (("impact", impact, True), ("beam", beam, False), ("symmetric", symmetric, True),
                            ("heated", heated, True), ("heated_contact", heated_contact, False),
                            ("symmetric_x", symmetric_x, False), ("held_mirrored", held_mirrored, False)):
    sim, state, dt = scene()
    one = jax.jit(lambda s, sim=sim, dt=dt: jax.lax.fori_loop(0, STEPS, lambda i, s: sim.step(s, dt), s))(state)
    one_totals = totals(sim, one)
    row = {"finite": bool(np.all(np.isfinite(np.asarray(one.x)))), "totals": one_totals,
           "moved": float(np.max(np.abs(np.asarray(one.x - state.x)))),
           "transported": {k: float(np.max(np.abs(np.asarray(one.fields[k] - state.fields[k]))))
                           for k in ("temperature", "concentration") if k in state.fields}}
    for slabs in ("equal", "moving") if moving else ("equal",):
        options = dict(rebalance_every=10, capacity=int(state.x.shape[0]), exchange=64) if slabs == "moving" else {}
        sharded = ShardedSimulation(sim, devices=jax.devices()[:DEVICES], **options)
        many = sharded.run(state, dt, STEPS)
        many_totals = totals(sim, many)
        row[slabs] = {
            "x_abs_err": float(np.max(np.abs(np.asarray(many.x) - np.asarray(one.x)))),
            "v_abs_err": float(np.max(np.abs(np.asarray(many.v) - np.asarray(one.v)))),
            "v_scale": float(np.max(np.abs(np.asarray(one.v)))),
            "fields_abs_err": max([float(np.max(np.abs(np.asarray(many.fields[k]) - np.asarray(one.fields[k]))))
                                   for k in one.fields], default=0.0),
            "totals_abs_err": max([float(np.max(np.abs(np.asarray(many_totals[k]) - np.asarray(one_totals[k]))))
                                   for k in one_totals], default=0.0),
            "migrated": sharded.stats["migrated"],
            "rebalances": sharded.stats["rebalances"],
        }
    out[name] = row

# a symmetry plane across the slabs' axis x whose ghost band (6 node planes below x = 0, their mirrors up to
# plane 12) a slab face would cut is refused, naming the edge slab's width: 4 slabs of 8 cells (the first
# window's complete planes end at 10), not 2 of 16
grid = jm.Grid((-6 * H, 0.0), (1.0 - 6 * H, 0.5), (32, 16))
wide_band = jm.Simulation(grid, jm.QuadraticBSpline(), jm.LinearElastic(E=1.0, nu=0.0, density=1.0), "flip",
                          boundary=jm.Mirror("x-", 0.0))
ShardedSimulation(wide_band, devices=jax.devices()[:2])
# ... and on slabs that move, which may be as narrow as 2 H + 1 = 5 cells, symmetric_x's band (to plane 4)
for key, model, options in (("mirror_x_error", wide_band, {}),
                            ("mirror_x_moving_error", symmetric_x()[0], dict(rebalance_every=10))):
    try:
        ShardedSimulation(model, devices=jax.devices()[:4], **options)
        out[key] = None
    except jm.InputError as error:
        out[key] = str(error)

# default buffers: disks at speed 1 on 4 slabs that move (26 cells along x).  A plane of 16 particles of a
# lattice crosses a face at once; the default exchange, a tenth of the capacity (13 slots), stopped the run
# at step 13, long before the impact.  It now holds a cell column's particles.
disks = jm.scene("disks", speed=1.0)
sharded = ShardedSimulation(disks.sim, devices=jax.devices()[:4], rebalance_every=50)
reached = sharded.run(disks.state, disks.dt, 100)
one = jax.jit(lambda s: jax.lax.fori_loop(0, 100, lambda i, s: disks.sim.step(s, disks.dt), s))(disks.state)
out["disks_default_buffers"] = {"exchange": sharded.exchange, "capacity": sharded.capacity,
                                "migrated": sharded.stats["migrated"], "step": int(reached.step),
                                "x_abs_err": float(np.max(np.abs(np.asarray(reached.x) - np.asarray(one.x))))}
print(json.dumps(out))
