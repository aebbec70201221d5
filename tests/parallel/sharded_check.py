"""Run by tests/test_parallel_slabs.py in a process of its own with 2 forced CPU devices: a
Simulation stepped by jaxmpm.parallel.ShardedSimulation against the same model on one device,
float64, with particles crossing the slab face both ways; and the gradient of a rollout's loss with
respect to a material parameter through the sharded rollout.  Prints one JSON line."""

import json
import sys

import jax

jax.config.update("jax_enable_x64", True)
import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jaxmpm as jm  # noqa: E402
from jaxmpm.parallel import ShardedSimulation  # noqa: E402

STEPS = int(sys.argv[1]) if len(sys.argv) > 1 else 250
SPEED = 1.0  # the disks meet after about 160 steps and rebound across the slab face
out = {}


def compare(name, setup, steps):
    sim, state, dt = setup.sim, setup.state, setup.dt
    one = jax.jit(lambda s: jax.lax.fori_loop(0, steps, lambda i, s: sim.step(s, dt), s))(state)
    sharded = ShardedSimulation(sim)
    many = sharded.run(state, dt, steps)
    row = {f"{q}_rel_err": float(np.max(np.abs(np.asarray(getattr(many, q)) - np.asarray(getattr(one, q))))
                                 / np.max(np.abs(np.asarray(getattr(one, q))))) for q in ("x", "v", "F")}
    p_one, p_many = (np.asarray(jnp.sum(s.mass[:, None] * s.v, 0)) for s in (one, many))
    row["momentum_diff"] = float(np.max(np.abs(p_many - p_one)) / float(jnp.sum(state.mass)))
    row["mass_diff"] = float(jnp.sum(many.mass) - jnp.sum(one.mass))
    row["dissipated_rel_err"] = float(abs(many.dissipated - one.dissipated) / max(abs(float(one.dissipated)), 1e-300))
    row["dissipated"] = float(one.dissipated)
    row["migrated"] = sharded.stats["migrated"]
    row["ended_elsewhere"] = int(np.sum(np.asarray(sharded.owner(many.x)) != np.asarray(sharded.owner(state.x))))
    out[name] = row


SCHEMES = sys.argv[2].split(",") if len(sys.argv) > 2 else ["apic", "xpic:3+contact"]
for scheme in SCHEMES:
    name, _, contact = scheme.partition("+")
    compare(f"disks_{scheme}", jm.scene("disks", scheme=name, speed=SPEED,
                                        contact="frictionless" if contact else "none"), STEPS)

# the gradient of the final kinetic energy with respect to E, through the sharded rollout past the
# disks' impact (E sets how they rebound)
setup = jm.scene("disks", speed=SPEED)
sim, state, dt = setup.sim, setup.state, setup.dt
steps = STEPS


def with_E(E):
    return eqx.tree_at(lambda s: s.material.E, sim, E)


def energy(s):
    return 0.5 * jnp.sum(s.mass * jnp.sum(s.v * s.v, -1))


def one_loss(E):
    m = with_E(E)
    return energy(jax.lax.fori_loop(0, steps, lambda i, s: m.step(s, dt), state))


sharded = ShardedSimulation(sim)
buffers, valid, ids = sharded.distribute(state)
program = sharded.rollout(steps)


def many_loss(E):
    result = program(with_E(E), buffers, valid, ids, jnp.asarray(dt))
    return energy(result[0])  # free slots have zero mass


E0 = jnp.asarray(sim.material.E)
g_one, g_many = jax.jit(jax.grad(one_loss))(E0), jax.jit(jax.grad(many_loss))(E0)
out["gradient"] = {"one": float(g_one), "many": float(g_many),
                   "rel_err": float(abs(g_many - g_one) / abs(g_one)),
                   "loss_rel_err": float(abs(many_loss(E0) - one_loss(E0)) / abs(one_loss(E0)))}

# too few exchange slots for the movers: the run stops at the first step a particle would not fit
try:
    ShardedSimulation(sim, exchange=1).run(state, dt, steps)
    out["overflow_error"] = None
except jm.InputError as error:
    out["overflow_error"] = str(error)

# the compiled rollout's collectives: halo planes, migrating particles and scalar counts, never the
# whole grid or all particles
hlo = program.lower(sim, buffers, valid, ids, jnp.asarray(dt)).compile().compiled.as_text()
shapes = []
for line in hlo.splitlines():
    for op in ("collective-permute(", "collective-permute-start(", "all-reduce(", "all-reduce-start(",
               "all-gather(", "all-gather-start(", "all-to-all(", "reduce-scatter("):
        if op in line:
            shape = line.split("=", 1)[1].strip().split(" ")[0]
            dims = shape[shape.index("[") + 1:shape.index("]")] if "[" in shape else ""
            size = int(np.prod([int(d) for d in dims.split(",") if d])) if dims else 1
            shapes.append([op.rstrip("(").replace("-start", ""), shape, size])
out["collectives"] = shapes
out["grid_nodes"] = sim.grid.num_nodes
out["particles"] = int(state.x.shape[0])
out["overlap_nodes"] = sharded.slabs.overlap_planes * sharded.slabs.plane_nodes
out["exchange"] = sharded.exchange
print(json.dumps(out))
