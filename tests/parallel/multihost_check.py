"""Run twice by tests/test_parallel_slabs.py, as processes 0 and 1 of one JAX job on localhost
(``jax.distributed.initialize``, CPU collectives over gloo), 2 forced CPU devices each: one
ShardedSimulation over the 4 global devices against the same model on one local device, float64.
Prints one JSON line per process."""

import json
import os
import sys

pid, port = int(sys.argv[1]), int(sys.argv[2])
os.environ["XLA_FLAGS"] = "--xla_force_host_platform_device_count=2"  # devices per process
import jax  # noqa: E402

jax.config.update("jax_cpu_collectives_implementation", "gloo")
jax.distributed.initialize(coordinator_address=f"127.0.0.1:{port}", num_processes=2, process_id=pid)
jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jaxmpm as jm  # noqa: E402
from jaxmpm.parallel import ShardedSimulation  # noqa: E402

STEPS = 200
setup = jm.scene("disks", spacing=0.045, speed=1.0, scheme="xpic:3")  # 28 cells: 4 slabs of 7
sim, state, dt = setup.sim, setup.state, setup.dt
# every process's devices: one global mesh; fixed slabs need room for the disks' particles as they move
sharded = ShardedSimulation(sim, capacity=400)
many = sharded.run(state, dt, STEPS)
local = jax.local_devices()[0]
with jax.default_device(local):  # the reference: this process's first device alone
    one = jax.jit(lambda s: jax.lax.fori_loop(0, STEPS, lambda i, s: sim.step(s, dt), s))(state)
out = {"process": pid, "global_devices": len(jax.devices()), "local_devices": len(jax.local_devices()),
       "migrated": sharded.stats["migrated"],
       "x_rel_err": float(np.max(np.abs(np.asarray(many.x) - np.asarray(one.x))) / np.max(np.abs(np.asarray(one.x)))),
       "v_rel_err": float(np.max(np.abs(np.asarray(many.v) - np.asarray(one.v))) / np.max(np.abs(np.asarray(one.v)))),
       "mass_diff": float(jnp.sum(many.mass) - jnp.sum(one.mass)),
       "x_checksum": float(np.sum(np.asarray(many.x) * np.arange(1, many.x.size + 1).reshape(many.x.shape)))}
print(json.dumps(out))
