"""Run by tests/test_parallel_slabs.py in a process of its own with N forced CPU devices
(``XLA_FLAGS=--xla_force_host_platform_device_count=N``): the slab decomposition's P2G with one halo
exchange, G2P, their gradients and particle migration against one device, float64.  Prints one JSON
line of measured errors and counts; the test asserts on them."""

import json
import os
import sys

import jax

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from jax.sharding import Mesh  # noqa: E402
from jax.sharding import PartitionSpec as P  # noqa: E402

import jaxmpm as jm  # noqa: E402
from jaxmpm.parallel import Slabs, halo_for, migrate  # noqa: E402
from jaxmpm.transfer.contractions import Weighted  # noqa: E402
from jaxmpm.transfer.kernels.windowed import use_window  # noqa: E402
from jaxmpm.transfer.operators import gather, p2g  # noqa: E402

D = int(os.environ.get("SLAB_DEVICES", "4"))
assert len(jax.devices()) == D, jax.devices()
dim = int(sys.argv[1]) if len(sys.argv) > 1 else 2
shape = {"quadratic": jm.QuadraticBSpline(), "cubic": jm.CubicBSpline(), "linear": jm.Linear()}[
    sys.argv[2] if len(sys.argv) > 2 else "quadratic"]
cells = (8 * D,) + (6,) * (dim - 1)
grid = jm.Grid(lower=(0.0,) * dim, upper=tuple(float(c) * 0.1 for c in cells), cells=cells)
H = halo_for(shape)
slabs = Slabs(grid, D, H, axis_name="x")
mesh = Mesh(np.array(jax.devices()), ("x",))

rng = np.random.default_rng(0)
N, C = 400, 200  # particles; buffer capacity per device
margin = 2 * 0.1
x = rng.uniform(margin, np.asarray(grid.upper) - margin, size=(N, dim))
v = rng.normal(size=(N, dim))
m = rng.uniform(0.5, 1.5, size=N)


def global_fields(x, v, m):
    stencil = shape.stencil(grid, x)
    nodal = p2g(stencil, {"mass": Weighted(m), "momentum": Weighted(m[:, None] * v)}, grid.num_nodes)
    mass = nodal["mass"]
    vel = jnp.where(mass[:, None] > 0, nodal["momentum"] / jnp.where(mass > 0, mass, 1.0)[:, None], 0.0)
    return nodal, gather(stencil, vel)


# distribute: particles into per-device buffers (invalid slots: mass 0 at the slab's centre)
owner = np.asarray(slabs.owner(jnp.asarray(x), 0.0, 0.1))
bx, bv, bm, valid, ids = (np.zeros((D, C, dim)), np.zeros((D, C, dim)), np.zeros((D, C)), np.zeros((D, C), bool),
                          -np.ones((D, C), int))
for k in range(D):
    mine = np.flatnonzero(owner == k)
    bx[k] = np.asarray(grid.lower) + 0.5 * np.asarray(grid.upper)
    bx[k, :, 0] = (k + 0.5) * slabs.cells_per_slab * 0.1
    bx[k, :len(mine)], bv[k, :len(mine)], bm[k, :len(mine)] = x[mine], v[mine], m[mine]
    valid[k, :len(mine)], ids[k, :len(mine)] = True, mine


def local_fields(x, v, m):
    """The same P2G and G2P, traced on this device's window: the library's windowed kernel shifts the
    node numbers, scatters into the window and completes the sums with one exchange per P2G."""
    x, v, m = x[0], v[0], m[0]  # this device's buffer
    with use_window(slabs.device_window(jax.lax.axis_index("x"))):
        stencil = shape.stencil(grid, x)
        nodal = p2g(stencil, {"mass": Weighted(m), "momentum": Weighted(m[:, None] * v)}, grid.num_nodes)
        mass = nodal["mass"]
        vel = jnp.where(mass[:, None] > 0, nodal["momentum"] / jnp.where(mass > 0, mass, 1.0)[:, None], 0.0)
        return {name: a[None] for name, a in nodal.items()}, gather(stencil, vel)[None]


sharded = jax.jit(jax.shard_map(local_fields, mesh=mesh, in_specs=(P("x"), P("x"), P("x")),
                                out_specs=(P("x"), P("x"))))
out = {}
g_nodal, g_vel = jax.jit(global_fields)(x, v, m)
s_nodal, s_vel = sharded(bx, bv, bm)
err = 0.0
for k in range(D):  # every window plane inside the grid equals the global planes
    for name in ("mass", "momentum"):
        want = np.asarray(slabs.window(g_nodal[name], k))
        err = max(err, float(np.max(np.abs(np.asarray(s_nodal[name][k]) - want))) / float(np.max(np.abs(want))))
out["p2g_rel_err"] = err
vel_err = 0.0
for k in range(D):
    sel = valid[k]
    vel_err = max(vel_err, float(np.max(np.abs(np.asarray(s_vel[k])[sel] - np.asarray(g_vel)[ids[k][sel]]))))
out["g2p_abs_err"] = vel_err / float(np.max(np.abs(np.asarray(g_vel))))

# gradients: d/d(x, v) of a weighted sum of the gathered velocities, through the exchange
w = rng.normal(size=(N, dim))
bw = np.zeros((D, C, dim))
for k in range(D):
    bw[k, valid[k]] = w[ids[k][valid[k]]]


def g_loss(x, v):
    return jnp.sum(global_fields(x, v, m)[1] * w)


def s_loss(bx, bv):
    return jnp.sum(sharded(bx, bv, bm)[1] * bw)


gx, gv = jax.jit(jax.grad(g_loss, argnums=(0, 1)))(x, v)
sx, sv = jax.jit(jax.grad(s_loss, argnums=(0, 1)))(bx, bv)
grad_err = 0.0
for k in range(D):
    sel = valid[k]
    for s_, g_ in ((sx, gx), (sv, gv)):
        grad_err = max(grad_err, float(np.max(np.abs(np.asarray(s_[k])[sel] - np.asarray(g_)[ids[k][sel]])))
                       / float(np.max(np.abs(np.asarray(g_)))))
out["grad_rel_err"] = grad_err

# the compiled program's collectives: only neighbour permutes of the overlap planes
hlo = sharded.lower(bx, bv, bm).compile().as_text()
collectives = [line for line in hlo.splitlines()
               if any(op in line for op in ("collective-permute-start(", "collective-permute(", "all-reduce(",
                                            "all-gather(", "all-to-all(", "reduce-scatter("))]
out["collectives"] = [line.split("=")[1].split("{")[0].strip() + " " + line.split("(")[0].split()[-1]
                      for line in collectives]
out["overlap_elements"] = slabs.overlap_planes * slabs.plane_nodes
out["grid_nodes"] = grid.num_nodes

# migration: every particle moves by less than a cell; owners change; nothing is lost
dx = rng.uniform(-0.09, 0.09, size=(N, dim))
moved = np.clip(x + dx, margin, np.asarray(grid.upper) - margin)
new_owner = np.asarray(slabs.owner(jnp.asarray(moved), 0.0, 0.1))
bmoved, bdest = bx.copy(), np.zeros((D, C), int)
for k in range(D):
    sel = valid[k]
    bmoved[k, sel] = moved[ids[k][sel]]
    bdest[k] = k
    bdest[k, sel] = new_owner[ids[k][sel]]


def local_migrate(x, ident, valid, dest):
    (x, ident), valid, overflow, _ = migrate((x[0], ident[0]), valid[0], dest[0], exchange=32, axis_name="x",
                                             devices=D)
    return x[None], ident[None], valid[None], overflow[None]


mig = jax.jit(jax.shard_map(local_migrate, mesh=mesh, in_specs=(P("x"),) * 4, out_specs=(P("x"),) * 4))
mx, mid, mvalid, overflow = (np.asarray(a) for a in mig(bmoved, ids, valid, bdest))
held = np.sort(mid[mvalid])
out["migrated"] = int(np.sum(new_owner != owner))
out["ids_kept"] = bool(np.array_equal(held, np.arange(N)))
out["on_owner"] = bool(all(np.all(np.asarray(slabs.owner(jnp.asarray(mx[k][mvalid[k]]), 0.0, 0.1)) == k)
                           for k in range(D)))
out["positions_kept"] = bool(all(np.allclose(mx[k][mvalid[k]], moved[mid[k][mvalid[k]]], rtol=0, atol=0)
                                 for k in range(D)))
out["overflow"] = int(overflow[0])
# a buffer too small for the movers: reported, not dropped
small = jax.jit(jax.shard_map(lambda *a: (lambda r: (r[0][0][None], r[0][1][None], r[1][None], r[2][None]))(
    migrate((a[0][0], a[1][0]), a[2][0], a[3][0], exchange=1, axis_name="x", devices=D)),
    mesh=mesh, in_specs=(P("x"),) * 4, out_specs=(P("x"),) * 4))
sx_, sid, svalid, soverflow = (np.asarray(a) for a in small(bmoved, ids, valid, bdest))
out["small_overflow"] = int(soverflow[0])
out["small_ids_unique"] = bool(len(np.unique(sid[svalid])) == int(svalid.sum()) == N)
print(json.dumps(out))
