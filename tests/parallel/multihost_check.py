"""Run twice by tests/test_parallel_slabs.py, as processes 0 and 1 of one JAX job on localhost
(``jax.distributed.initialize``, CPU collectives over gloo), 2 forced CPU devices each: one
ShardedSimulation over the 4 global devices against the same model on one local device, float64;
the run saves frames into one HDF5 file that process 0 alone writes (argument 3: its path); then
jm.ensemble spreads 4 members over the 4 global devices and gathers them on both processes.
Prints one JSON line per process."""

import json
import os
import sys

pid, port, path = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3]
# devices per process, the caller's other flags kept
os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=2").strip()
import jax  # noqa: E402

jax.config.update("jax_cpu_collectives_implementation", "gloo")
jax.distributed.initialize(coordinator_address=f"127.0.0.1:{port}", num_processes=2, process_id=pid)
jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jaxmpm as jm  # noqa: E402
from jaxmpm.io.hdf5 import read_state  # noqa: E402
from jaxmpm.parallel import ShardedSimulation  # noqa: E402

STEPS = 200
setup = jm.scene("disks", spacing=0.045, speed=1.0, scheme="xpic:3")  # 28 cells: 4 slabs of 7
sim, state, dt = setup.sim, setup.state, setup.dt
# every process's devices: one global mesh; fixed slabs need room for the disks' particles as they move
sharded = ShardedSimulation(sim, capacity=400)
writer = jm.H5Writer(path, sim, state, dt=dt) if jax.process_index() == 0 else None  # one process writes
many, history = sharded.run(state, dt, STEPS, STEPS // 2, writer=writer)
if writer is not None:
    writer.close()
local = jax.local_devices()[0]
with jax.default_device(local):  # the reference: this process's first device alone
    one = jax.jit(lambda s: jax.lax.fori_loop(0, STEPS, lambda i, s: sim.step(s, dt), s))(state)
out = {"process": pid, "global_devices": len(jax.devices()), "local_devices": len(jax.local_devices()),
       "migrated": sharded.stats["migrated"],
       "x_rel_err": float(np.max(np.abs(np.asarray(many.x) - np.asarray(one.x))) / np.max(np.abs(np.asarray(one.x)))),
       "v_rel_err": float(np.max(np.abs(np.asarray(many.v) - np.asarray(one.v))) / np.max(np.abs(np.asarray(one.v)))),
       "mass_diff": float(jnp.sum(many.mass) - jnp.sum(one.mass)),
       "x_checksum": float(np.sum(np.asarray(many.x) * np.arange(1, many.x.size + 1).reshape(many.x.shape))),
       "history": history is not None}
# jm.ensemble over every process's devices (4 members, one per global device), gathered on every process,
# against the same ensemble on this process's first device alone
E = jnp.linspace(0.8, 1.2, 4) * float(sim.material.E)
members = jm.ensemble(sim, state, dt, 20, 10, params={"E": E}, save_particles=True, progress=False)
alone = jm.ensemble(sim, state, dt, 20, 10, params={"E": E}, save_particles=True, progress=False, devices=[local])
out["ensemble_x_err"] = float(jnp.max(jnp.abs(members[0].x - alone[0].x)))
out["ensemble_history_err"] = float(jnp.max(jnp.abs(members[1].x - alone[1].x)))
out["ensemble_members"] = int(members[0].x.shape[0])
out["ensemble_spread"] = bool(members[0].x.is_fully_addressable and (members[0].x - state.x[None]).any())
if pid == 0:  # the file: the initial frame, the middle one and the final state's, with that state saved
    saved = jm.load_h5(path)
    out["file_frames"] = int(saved["time"].shape[0])
    out["file_x_rel_err"] = float(np.max(np.abs(saved["particles/x"][-1] - np.asarray(one.x)))
                                  / np.max(np.abs(np.asarray(one.x))))
    out["file_state_step"] = int(read_state(path, state)[0].step)
print(json.dumps(out))
