"""One USL step with its particles shared among the process's devices, each holding the whole grid.

P2G is a sum over the particles and G2P a map over them (003 §2.1), so ``d`` devices may each take
N/d of the particles:

1. P2G: each device sums its share's contributions onto its own copy of the grid (in chunks, as
   :mod:`jaxmpm.model.chunks` steps one device's particles), and the copies are added, one all-reduce
   of the nodal sums (``lax.psum``; 003 eq. 2.1, 001 eq. 20);
2. the grid solve: every device solves the same grid (:func:`jaxmpm.model.step.grid_phases`);
3. G2P: each device updates its own particles from its grid (000 eq. 3.28, 002 eq. 4).

No particle moves between devices and no halo is exchanged: a device's particles may lie anywhere on
the grid.  This is the layout for several devices that share memory -- the CPU devices of one process
(``jax.config.update("jax_num_cpu_devices", n)`` before JAX starts).  XLA:CPU runs each device's
program on a thread of its own, so the whole step runs on ``d`` threads at once, its scatter and the
small kernels that one program runs one after another included; one device splits only its large
kernels among its threads (benchmarks/README.md, "Particles shared among CPU devices").  Grids too
large to copy on every device are :class:`jaxmpm.parallel.ShardedSimulation`'s (slabs of the grid).

The added sums are those of one device to round-off, not bit for bit (as for chunks); the dissipated
energy is the sum of the devices' shares.  Derivatives run on one device (:func:`step_on_devices`), in
chunks as a step in chunks differentiates them, or the whole step: differentiated through the devices, a
rollout's gradient was the same to 5e-15 and 4-15% slower (mpm88, 2 CPU devices, 8k and 131k particles).

Which steps: those that may step in chunks (:func:`jaxmpm.model.chunks.chunk_obstacle`), with a
particle count that the device count divides; :func:`device_obstacle` names what keeps a model on one
device.  The count comes from the backend's table (:data:`jaxmpm.transfer.backend.DEVICE_TABLE`) or
``Simulation(particle_devices=...)``, and :func:`jaxmpm.backend_info` reports it.
"""

from __future__ import annotations

import equinox as eqx
import jax
import numpy as np
from jax.sharding import Mesh
from jax.sharding import PartitionSpec as P

from .chunks import _particle_part, _with_particle_part, chunk_obstacle, chunked_step, with_step_derivatives

AXIS = "particles"


def local_devices() -> list:
    """The process's devices of JAX's default backend, the ones a step may share its particles among."""
    return jax.local_devices()


def device_obstacle(sim, state, devices: int, kernel: str) -> str | None:
    """Why ``sim`` cannot share ``state``'s particles among ``devices`` devices on ``kernel``, or None (the
    process has them: :meth:`jaxmpm.Simulation._device_row` checks the count)."""
    n = state.x.shape[0]
    if jax.process_count() > 1:  # neither measured nor tested across processes (jaxmpm.parallel's slabs are)
        return f"the run spans {jax.process_count()} processes (jax.distributed): the step stays on one device"
    manual = jax.sharding.get_abstract_mesh().manual_axes
    if manual:  # jm.ensemble's members or ShardedSimulation's slabs, already one device's share
        return f"the step is traced inside a shard_map over {', '.join(map(str, manual))}: each device steps its own"
    if n % devices:
        return f"{n} particles do not divide among {devices} devices"
    # a device's share steps in chunks (one chunk where it is small), so it meets their conditions
    return chunk_obstacle(sim, state, max(1, n // devices), kernel)


def step_on_devices(sim, state, dt, devices: int, per_chunk: int, derivative_chunk: int = 0):
    """One step whose forward run shares the particles of ``state`` among the first ``devices`` local
    devices, each stepping its share in chunks of about ``per_chunk`` particles (0: its share at once).
    JVPs and gradients run on one device, in chunks of about ``derivative_chunk`` particles each recomputed in
    the reverse pass (as :func:`jaxmpm.model.chunks.step_in_chunks`; 0: the whole step).  ``device_obstacle``
    must be None."""
    mesh = Mesh(np.asarray(local_devices()[:devices]), (AXIS,))
    share = state.x.shape[0] // devices
    part_specs = jax.tree_util.tree_map(lambda _: P(AXIS), _particle_part(state))

    def forward(sim, state, dt):
        arrays, static = eqx.partition(sim, eqx.is_array)

        def shared(arrays, part, clock, dt):  # one device: its share of the particles, the whole grid
            local = _with_clock(_with_particle_part(state, part), clock)
            new = chunked_step(eqx.combine(arrays, static), local, dt, per_chunk or share, axis_name=AXIS)
            return _particle_part(new), _clock(new)

        mapped = jax.shard_map(shared, mesh=mesh, in_specs=(P(), part_specs, P(), P()),
                               out_specs=(part_specs, P()))
        part, clock = mapped(arrays, _particle_part(state), _clock(state), dt)
        return _with_clock(_with_particle_part(state, part), clock)

    return with_step_derivatives(forward, sim, state, dt, derivative_chunk)


def _clock(state):
    return state.time, state.step, state.dissipated


def _with_clock(state, clock):
    return eqx.tree_at(lambda s: (s.time, s.step, s.dissipated), state, clock)
