"""Run by tests/test_parallel_slabs.py in a process of its own with N forced CPU devices: slabs that
move with the particles (load balance), against one device, float64.  Prints one JSON line.

1. Unequal slabs: P2G with one halo exchange and G2P on slabs of deliberately unequal widths (the
   boundaries a runtime argument), every window plane a device completes against the global sums.
2. A granular column collapse (``column_collapse``) run by ``ShardedSimulation(...,
   rebalance_every=K)``: the column stands in the first slab and spreads along x as it collapses,
   so fixed equal slabs would need a buffer for every particle on the first device.  Measured: the
   particles and their mass the devices hold after every step (the rollout's census), the
   boundaries of every rebalance, the capacity fixed slabs would need for the same run (from the
   one-device trajectory), the final state against one device; the same with frames.
3. The error when no boundaries fit the buffers."""

import json
import os
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from jax.sharding import Mesh  # noqa: E402
from jax.sharding import PartitionSpec as P  # noqa: E402

import jaxmpm as jm  # noqa: E402
from jaxmpm.parallel import ShardedSimulation, Slabs  # noqa: E402
from jaxmpm.transfer.contractions import Weighted  # noqa: E402
from jaxmpm.transfer.kernels.windowed import use_window  # noqa: E402
from jaxmpm.transfer.operators import gather, p2g  # noqa: E402

D = int(os.environ.get("SLAB_DEVICES", "3"))
assert len(jax.devices()) == D, jax.devices()
STEPS = int(sys.argv[1]) if len(sys.argv) > 1 else 800
EVERY = int(sys.argv[2]) if len(sys.argv) > 2 else 200
HEADROOM = int(sys.argv[3]) if len(sys.argv) > 3 else 40
tic = time.perf_counter()
out = {"devices": D}


def rel_err(a, b):
    a, b = np.asarray(a), np.asarray(b)
    return float(np.max(np.abs(a - b)) / np.max(np.abs(b)))


# ---------------------------------------------------------------- 1. unequal slabs, one exchange
shape = jm.QuadraticBSpline()
cells = (40, 6)
grid = jm.Grid(lower=(0.0, 0.0), upper=(4.0, 0.6), cells=cells)
slabs = Slabs(grid, D, 2, axis_name="x", max_cells=40 - 5 * (D - 1))
# the first slab as narrow as allowed, the middle ones a little wider, the last the rest
bounds = np.asarray([0] + [5 + 7 * k for k in range(D - 1)] + [40], np.int32)
slabs.check_bounds(bounds)
mesh = Mesh(np.array(jax.devices()), ("x",))
rng = np.random.default_rng(0)
N, C = 400, 400
x = rng.uniform(0.2, np.asarray(grid.upper) - 0.2, size=(N, 2))
x[: N // 2, 0] = rng.uniform(0.2, 1.0, size=N // 2)  # crowd the narrow slabs
v, m = rng.normal(size=(N, 2)), rng.uniform(0.5, 1.5, size=N)


def fields(stencil, m, v):
    nodal = p2g(stencil, {"mass": Weighted(m), "momentum": Weighted(m[:, None] * v)}, grid.num_nodes)
    mass = nodal["mass"]
    vel = jnp.where(mass[:, None] > 0, nodal["momentum"] / jnp.where(mass > 0, mass, 1.0)[:, None], 0.0)
    return nodal, gather(stencil, vel)


owner = np.asarray(slabs.owner(jnp.asarray(x), 0.0, 0.1, bounds))
bx, bv, bm = np.zeros((D, C, 2)), np.zeros((D, C, 2)), np.zeros((D, C))
valid, ids = np.zeros((D, C), bool), -np.ones((D, C), int)
for k in range(D):
    mine = np.flatnonzero(owner == k)
    bx[k] = [(bounds[k] + bounds[k + 1]) / 2 * 0.1, 0.3]  # parked at the slab's centre, mass 0
    bx[k, :len(mine)], bv[k, :len(mine)], bm[k, :len(mine)] = x[mine], v[mine], m[mine]
    valid[k, :len(mine)], ids[k, :len(mine)] = True, mine


def local_fields(x, v, m, b):
    with use_window(slabs.device_window(jax.lax.axis_index("x"), bounds=b)):
        nodal, vel = fields(shape.stencil(grid, x[0]), m[0], v[0])
    return {name: a[None] for name, a in nodal.items()}, vel[None]


windowed = jax.jit(jax.shard_map(local_fields, mesh=mesh, in_specs=(P("x"),) * 3 + (P(),),
                                 out_specs=(P("x"), P("x"))))
g_nodal, g_vel = jax.jit(lambda x, v, m: fields(shape.stencil(grid, x), m, v))(x, v, m)
s_nodal, s_vel = windowed(bx, bv, bm, jnp.asarray(bounds))
err, vel_err = 0.0, 0.0
for k in range(D):  # the planes [b_k - H, b_{k+1} + H] of window k: complete sums
    planes = (bounds[k + 1] - bounds[k] + 5) * slabs.plane_nodes
    for name in ("mass", "momentum"):
        want = np.asarray(slabs.window(g_nodal[name], k, bounds=jnp.asarray(bounds)))[:planes]
        err = max(err, rel_err(np.asarray(s_nodal[name][k])[:planes], want))
    vel_err = max(vel_err, rel_err(np.asarray(s_vel[k])[valid[k]], np.asarray(g_vel)[ids[k][valid[k]]]))
out["seconds_unequal"] = time.perf_counter() - tic
out["unequal"] = {"bounds": bounds.tolist(), "p2g_rel_err": err, "g2p_rel_err": vel_err,
                  "particles_per_slab": np.bincount(owner, minlength=D).tolist()}

# ---------------------------------------------------------------- 2. a column collapse, rebalanced
setup = jm.scene("column_collapse", cells=8)
sim, state, dt = setup.sim, setup.state, setup.dt
n = int(state.x.shape[0])
out.update(particles=n, steps=STEPS, every=EVERY, cells_x=sim.grid.cells[0])
probe = ShardedSimulation(sim, rebalance_every=EVERY)
equal = jnp.asarray(probe.slabs.equal_bounds())


def fixed_fullest(s):
    """The particles of the fullest equal slab: what a fixed slab's buffer must hold."""
    return jnp.max(jnp.bincount(probe.slabs.owner(s.x, sim.grid.lower[0], sim.grid.spacing[0], equal), length=D))


def one_step(s, _):
    s = sim.step(s, dt)
    return s, (fixed_fullest(s), s.x)


one, (fullest, path) = jax.jit(lambda s: jax.lax.scan(one_step, s, None, length=STEPS))(state)
out["seconds_one_device"] = time.perf_counter() - tic
out["fixed_capacity_needed"] = int(max(int(fixed_fullest(state)), int(jnp.max(fullest))))

# buffers for the most even slabs at the start and a little headroom: tight enough that the spreading
# flow fills a slab before the K steps are up, and the run rebalances early
cell = np.clip(np.asarray(probe.slabs.cell(state.x, sim.grid.lower[0], sim.grid.spacing[0])), 0,
               sim.grid.cells[0] - 1)
start = probe.slabs.balanced_bounds(np.bincount(cell, minlength=sim.grid.cells[0]))
start_fullest = int(max(np.sum((cell >= a) & (cell < b)) for a, b in zip(start[:-1], start[1:])))
capacity = start_fullest + HEADROOM
sharded = ShardedSimulation(sim, rebalance_every=EVERY, capacity=capacity)
many = sharded.run(state, dt, STEPS)
stats = sharded.stats
out["seconds_run"] = time.perf_counter() - tic
out["run"] = {"capacity": capacity, "max_cells": sharded.slabs.max_cells, "census_particles": stats["particles"],
              "census_mass": stats["mass"], "total_mass": float(jnp.sum(state.mass)),
              "mass_exact": bool(np.array_equal(np.asarray(many.mass), np.asarray(state.mass))),
              "rebalances": stats["rebalances"], "bounds": stats["bounds"], "migrated": stats["migrated"],
              "steps_done": stats["steps"], "final_step": int(many.step),
              **{f"{q}_rel_err": rel_err(getattr(many, q), getattr(one, q)) for q in ("x", "v", "F")}}
p_one, p_many = (np.asarray(jnp.sum(s.mass[:, None] * s.v, 0)) for s in (one, many))
out["run"]["momentum_diff"] = float(np.max(np.abs(p_many - p_one)) / float(jnp.sum(state.mass)))

# the same with frames, K steps apart (the rollout compiled above, once per frame; the slabs moved
# between frames, and early within one)
FRAMES_STEPS, SAVE = 2 * EVERY, EVERY
framed = sharded
final, history = framed.run(state, dt, FRAMES_STEPS, SAVE)
reference = [state.x] + [path[t - 1] for t in range(SAVE, FRAMES_STEPS + 1, SAVE)]
out["frames"] = {"count": int(history.x.shape[0]), "reference_count": len(reference),
                 "x_per_frame": [rel_err(history.x[i], reference[i]) for i in range(len(reference))],
                 "final_step": int(final.step), "rebalances": framed.stats["rebalances"],
                 "bounds": framed.stats["bounds"], "census_particles": framed.stats["particles"]}

out["seconds_frames"] = time.perf_counter() - tic

# ---------------------------------------------------------------- 3. no boundaries fit
try:
    ShardedSimulation(sim, rebalance_every=EVERY, capacity=start_fullest - 1).run(state, dt, 10)
    out["no_fit_error"] = None
except jm.InputError as error:
    out["no_fit_error"] = str(error)

# ---------------------------------------------------------------- 4. a grid that equal slabs cannot split
# disks on 28 cells along x over 3 devices: refused with fixed slabs (the message names rebalance_every),
# run with moving ones, particles crossing the faces, equal to one device
disks = jm.scene("disks", spacing=0.045, speed=1.0)
try:
    ShardedSimulation(disks.sim)
    out["uneven_fixed_error"] = None
except jm.InputError as error:
    out["uneven_fixed_error"] = str(error)
uneven = ShardedSimulation(disks.sim, rebalance_every=50)
uneven_final = uneven.run(disks.state, disks.dt, 100)
uneven_one = jax.jit(lambda s: jax.lax.fori_loop(0, 100, lambda i, s: disks.sim.step(s, disks.dt), s))(disks.state)
out["uneven"] = {"cells": disks.sim.grid.cells[0], "bounds": uneven.stats["bounds"],
                 "migrated": uneven.stats["migrated"], "x_rel_err": rel_err(uneven_final.x, uneven_one.x),
                 "v_rel_err": rel_err(uneven_final.v, uneven_one.v)}
out["seconds"] = time.perf_counter() - tic
print(json.dumps(out))
