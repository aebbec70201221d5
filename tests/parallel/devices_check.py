"""Run by tests/test_particle_devices.py in a process of its own with 2 forced CPU devices: steps whose
particles are shared among the devices, each holding the whole grid (jaxmpm.model.devices), against the
same model on one device, float64: whole runs with frames (mpm88 under APIC, the disks under FLIP), the
gradient of a rollout's loss with respect to E, an ensemble, what ``jm.backend_info`` reports, a share of the
particles that would not fit a device's memory, and the error for more devices than the process has.  Prints one
JSON line."""

import json
import os
import time

import jax

jax.config.update("jax_enable_x64", True)
import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jaxmpm as jm  # noqa: E402
import jaxmpm.transfer.backend  # noqa: E402

out = {"devices": len(jax.devices())}
start = time.perf_counter()


def rel(a, b):
    a, b = np.asarray(a), np.asarray(b)
    return float(np.max(np.abs(a - b)) / max(float(np.max(np.abs(b))), 1e-300))


def compare(name, setup, steps, chunk):
    sim, state, dt = setup.sim, setup.state, setup.dt
    one = sim.with_particle_devices(1).with_chunks(0)
    shared = sim.with_particle_devices(2).with_chunks(chunk)
    info = jm.backend_info(shared, state)
    a, ha = one.run(state, dt, steps, save_every=steps // 4, progress=False)
    b, hb = shared.run(state, dt, steps, save_every=steps // 4, progress=False)
    row = {q: rel(getattr(b, q), getattr(a, q)) for q in ("x", "v", "F")}
    row["frames_x"] = rel(hb.x, ha.x)
    row["frames"] = int(np.asarray(hb.x).shape[0])
    row["kinetic"] = rel(hb.kinetic, ha.kinetic)
    p_a, p_b = (np.asarray(jnp.sum(s.mass[:, None] * s.v, 0)) for s in (a, b))
    row["momentum_diff"] = float(np.max(np.abs(p_b - p_a)) / float(jnp.sum(state.mass)))
    row["mass_diff"] = float(jnp.sum(b.mass) - jnp.sum(a.mass))
    row["dissipated"] = [float(a.dissipated), float(b.dissipated)]
    row["devices_used"] = info["particle_devices"]
    row["reason"] = info["devices_reason"]
    row["sharded_output"] = len(b.x.sharding.device_set)
    out[name] = row


compare("mpm88_apic", jm.scene("mpm88", n_particles=2048, dtype="f64"), 40, 512)
compare("disks_flip", jm.scene("disks"), 40, 0)

# the gradient of a rollout's loss with respect to E: the shared step's derivatives are the whole step's
setup = jm.scene("bar")
sim, state, dt = setup.sim, setup.state, setup.dt


def loss(E, model):
    _, history = jm.set_params(model, E=E).run(state, dt, 20, save_every=10, progress=False)
    return jnp.sum(history.kinetic)


E = jnp.asarray(float(sim.material.E))
shared = sim.with_particle_devices(2)
fd = (loss(E * (1 + 1e-6), shared) - loss(E * (1 - 1e-6), shared)) / (2e-6 * E)
values = {d: jax.value_and_grad(loss)(E, sim.with_particle_devices(d)) for d in (1, 2)}
out["grad"] = {"loss_rel": rel(values[2][0], values[1][0]), "grad_rel": rel(values[2][1], values[1][1]),
               "grad": float(values[1][1]), "fd_rel": rel(fd, values[2][1])}

# an ensemble: jm.ensemble shards its members over the devices, and each member's step stays on its device
Es = jnp.asarray([0.9, 1.1]) * E
ens = {d: jm.ensemble(sim.with_particle_devices(d), state, dt, 20, save_every=10, params={"E": Es},
                     progress=False) for d in (1, 2)}
out["ensemble_rel"] = rel(ens[2][1].kinetic, ens[1][1].kinetic)
out["ensemble_vmapped_rel"] = rel(jax.vmap(lambda e: loss(e, sim.with_particle_devices(2)))(Es),
                                  jax.vmap(lambda e: loss(e, sim.with_particle_devices(1)))(Es))

# the table's choice: below its size one device, from it every device
big = jm.scene("mpm88", n_particles=65536, dtype="f64")
out["auto_small"] = jm.backend_info(setup.sim, setup.state)["particle_devices"]
out["auto_large"] = jm.backend_info(big.sim, big.state)["particle_devices"]
out["auto_large_reason"] = jm.backend_info(big.sim, big.state)["devices_reason"]
prime = jm.scene("mpm88", n_particles=2062, dtype="f64")  # 1031 a device, a prime: no chunks of about 512
shared = prime.sim.with_particle_devices(2).with_chunks(512)
out["prime_reason"] = jm.backend_info(shared, prime.state)["devices_reason"]
one = prime.sim.with_particle_devices(1)
out["prime_x"] = rel(shared.step(prime.state, prime.dt).x, one.step(prime.state, prime.dt).x)
odd = jm.scene("mpm88", n_particles=2047, dtype="f64")
out["odd_reason"] = jm.backend_info(odd.sim.with_particle_devices(2), odd.state)["devices_reason"]
# a device's share of the particles goes in chunks where its temporaries would not fit: 2 CPU devices share the
# host's memory (4 MiB here), so each counts on half of it (issue 32 item 7)
memory = jm.scene("mpm88", n_particles=2048, dtype="f64")
shared, one = memory.sim.with_particle_devices(2), memory.sim.with_particle_devices(1).with_chunks(0)
os.environ["JAXMPM_MEMORY_BYTES"] = str(4 * 2**20)
jaxmpm.transfer.backend.SMALLEST_CHUNK = 128
out["memory_reason"] = jm.backend_info(shared, memory.state)["devices_reason"]
out["memory_x"] = rel(shared.step(memory.state, memory.dt).x, one.step(memory.state, memory.dt).x)


def kinetic_after_a_step(model, v):  # its derivatives go in the chunks too, on one device
    new = model.step(eqx.tree_at(lambda s: s.v, memory.state, v), memory.dt)
    return jnp.sum(new.mass[:, None] * new.v ** 2)


out["memory_grad"] = rel(jax.grad(kinetic_after_a_step, argnums=1)(shared, memory.state.v),
                         jax.grad(kinetic_after_a_step, argnums=1)(one, memory.state.v))
del os.environ["JAXMPM_MEMORY_BYTES"]
out["memory_fits_reason"] = jm.backend_info(shared, memory.state)["devices_reason"]
try:
    sim.with_particle_devices(3).step(state, dt)
    out["too_many"] = None
except jm.InputError as e:
    out["too_many"] = str(e)
out["seconds"] = time.perf_counter() - start
print(json.dumps(out))
