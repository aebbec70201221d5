"""A Simulation stepped on many devices: slabs of the grid, particles in fixed-capacity buffers.

:class:`ShardedSimulation` wraps a :class:`jaxmpm.Simulation` and runs its unchanged step inside
``jax.shard_map`` over a one-axis ``Mesh``: each device steps the particles of its slab on its
window of the grid (:mod:`jaxmpm.transfer.kernels.windowed`; one halo exchange per P2G, the
velocity conditions cut to the window), then the particles that crossed a slab face move to the
neighbour (:func:`~jaxmpm.parallel.migration.migrate`).  Free buffer slots hold a parked
placeholder particle (zero mass and volume at the slab's centre, reset every step), so shapes
never change and one compiled program serves the whole run.

A run stops stepping at the first step where a particle did not fit (more movers than the
exchange slots, a full buffer, or a particle crossing more than one slab), with the state of the
step before, and :meth:`ShardedSimulation.run` raises an error naming the capacity option: no
particle is dropped silently.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import multihost_utils
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

from ..core.errors import check
from ..core.state import State
from ..physics.body_force import BodyForce
from ..physics.contact import Contact
from ..physics.damping import Damping
from ..physics.stress import StressDivergence
from ..transfer.kernels.windowed import use_window
from .migration import migrate
from .slabs import Slabs, halo_for

# The terms whose grid work is P2G, G2P and node-by-node operations, which the windows serve as they
# are; the others keep per-node data or sum over nodes (colliders, transport, tractions, reactions).
SUPPORTED_TERMS = (StressDivergence, BodyForce, Damping, Contact)


def _per_particle(leaf, n: int) -> bool:
    return getattr(leaf, "ndim", 0) >= 1 and leaf.shape[0] == n


class ShardedSimulation:
    """``sim`` on the devices of a one-axis mesh, its grid cut into slabs along x.

    Args:
        sim: the :class:`jaxmpm.Simulation` (any scheme; terms that keep per-node data of their own
            -- colliders, transport, tractions, mirror planes -- are not supported yet).
        devices: the devices (default ``jax.devices()``); ``sim.grid.cells[0]`` must be a multiple
            of their number.
        halo: the halo in node planes (default: the shape function's nodes per axis minus one).
        capacity: particle slots per device (default: 1.15 x the particles of the fullest slab at
            the start, plus 16; every slot costs a particle's step, parked or not).
        exchange: slots per step for the particles moving to each neighbour (default: a tenth of
            ``capacity``, at least 8).
    """

    def __init__(self, sim, devices=None, halo: int | None = None, capacity: int | None = None,
                 exchange: int | None = None, axis_name: str = "slabs"):
        devices = list(jax.devices() if devices is None else devices)
        unsupported = sorted({type(t).__name__ for t in sim.terms if not isinstance(t, SUPPORTED_TERMS)})
        check(not unsupported, f"ShardedSimulation: {', '.join(unsupported)} not supported on several devices yet "
              f"(supported terms: {', '.join(t.__name__ for t in SUPPORTED_TERMS)}); run this model on one device")
        self.sim = sim
        self.mesh = Mesh(np.array(devices), (axis_name,))
        self.slabs = Slabs(sim.grid, len(devices), halo if halo is not None else halo_for(sim.shape), axis_name)
        self.capacity = capacity
        self.exchange = exchange
        self.axis_name = axis_name
        self._programs = {}
        self.stats = {}

    @property
    def devices(self) -> int:
        return self.slabs.devices

    # ------------------------------------------------------------------ distribute and collect
    def owner(self, x):
        """The device of each particle (its cell's slab), from positions (N, D)."""
        grid = self.sim.grid
        return self.slabs.owner(x, grid.lower[0], grid.spacing[0])

    def distribute(self, state: State):
        """Sharded buffers of ``state``: (buffers, valid, ids), each per-particle array (D C, ...)
        laid out device by device and sharded over the mesh, ``valid`` (D C,) and ``ids`` (D C,)
        the particle's index in ``state`` (-1 in free slots)."""
        n = state.x.shape[0]
        owner = np.asarray(self.owner(state.x))
        counts = np.bincount(owner, minlength=self.devices)
        # every slot is stepped, parked or not: the headroom costs its share of the step (one device
        # needs none)
        capacity = self.capacity or (n if self.devices == 1 else int(math.ceil(1.15 * counts.max())) + 16)
        check(counts.max() <= capacity, f"ShardedSimulation: a slab starts with {counts.max()} particles, more than "
              f"capacity = {capacity}; raise capacity")
        self.capacity = capacity
        self.exchange = self.exchange or max(8, capacity // 10)
        slots = np.zeros(self.devices * capacity, dtype=np.int64)  # a real particle or the placeholder
        valid = np.zeros(self.devices * capacity, dtype=bool)
        ids = -np.ones(self.devices * capacity, dtype=np.int64)
        for k in range(self.devices):
            mine = np.flatnonzero(owner == k)
            slots[k * capacity:k * capacity + len(mine)] = mine
            valid[k * capacity:k * capacity + len(mine)] = True
            ids[k * capacity:k * capacity + len(mine)] = mine
        # free slots hold copies of particle 0 until the run parks them (zero mass and volume)
        buffers = jax.tree_util.tree_map(lambda a: jnp.asarray(a)[slots] if _per_particle(a, n) else a, state)
        sharding = NamedSharding(self.mesh, P(self.axis_name))
        rows = self.devices * capacity

        def put(a):  # a global array, each process filling its devices' rows (several hosts: jax.distributed)
            if not _per_particle(a, rows):
                return np.asarray(a) if isinstance(a, jax.Array) else a  # replicated: the same on every process
            host = np.asarray(a)
            return jax.make_array_from_callback(host.shape, sharding, lambda index: host[index])

        return jax.tree_util.tree_map(put, buffers), put(valid), put(ids)

    def collect(self, buffers, valid, ids, n: int) -> State:
        """The particles of sharded ``buffers`` back in their original order (N of them), as host
        arrays on every process."""
        valid, ids = _host(valid), _host(ids)
        check(int(valid.sum()) == n and np.array_equal(np.sort(ids[valid]), np.arange(n)),
              f"ShardedSimulation: the buffers hold {int(valid.sum())} particles, expected {n}")
        order = np.empty(n, dtype=np.int64)
        order[ids[valid]] = np.flatnonzero(valid)
        rows = self.devices * self.capacity
        return jax.tree_util.tree_map(lambda a: jnp.asarray(_host(a)[order]) if _per_particle(a, rows) else a, buffers)

    def _park_x(self, dtype, device):
        """Parking positions (rows, D): the centre of each slot's slab (and of the grid across)."""
        grid = self.sim.grid
        centre = np.asarray([(lo + hi) / 2 for lo, hi in zip(grid.lower, grid.upper)], dtype=float)
        x = np.tile(centre, (len(device), 1))
        x[:, 0] = grid.lower[0] + (np.asarray(device) + 0.5) * self.slabs.cells_per_slab * grid.spacing[0]
        return jnp.asarray(x, dtype)

    # ------------------------------------------------------------------ the run
    def run(self, state: State, dt, steps: int) -> State:
        """``steps`` steps of ``dt`` from ``state`` on the mesh; the final state in the particles'
        original order.  Raises if particles did not fit their buffers (naming the option)."""
        n = state.x.shape[0]
        buffers, valid, ids = self.distribute(state)
        buffers, valid, ids, done, overflow, migrated = self.rollout(steps)(self.sim, buffers, valid, ids,
                                                                              jnp.asarray(dt))
        done, overflow, migrated = (int(_local(a)) for a in (done, overflow, migrated))
        self.stats = {"steps": done, "migrated": migrated}
        check(overflow == 0, f"ShardedSimulation: at step {done + 1}, {overflow} particle(s) did not fit: raise "
              f"capacity (now {self.capacity} per device) or exchange (now {self.exchange} per step and face); "
              f"the state after step {done} was kept")
        return self.collect(buffers, valid, ids, n)

    def rollout(self, steps: int):
        """The jitted sharded rollout of ``steps`` steps (one program per step count):
        ``rollout(steps)(sim, buffers, valid, ids, dt)`` -> (buffers, valid, ids, steps done, particles
        that did not fit, migrations), each count (D,) with every entry the same.  ``sim`` is an argument
        (a model of the same structure: other parameters, or differentiated, without recompiling);
        each step is rematerialised in reverse mode (``jax.checkpoint``).  Call :meth:`distribute`
        first (it fixes the capacity)."""
        check(self.capacity is not None, "ShardedSimulation.rollout: call distribute(state) first (it sets capacity)")
        key = (steps, self.capacity, self.exchange)
        if key not in self._programs:
            self._programs[key] = self._build(steps)
        return self._programs[key]

    def _build(self, steps: int):
        slabs, axis = self.slabs, self.axis_name
        capacity, exchange, D = self.capacity, self.exchange, self.devices
        rows = D * capacity

        def local(sim, buffers, valid, ids, dt):
            k = jax.lax.axis_index(axis)
            park = self._park_x(buffers.x.dtype, np.zeros(capacity, int))
            park = park.at[:, 0].add(k.astype(park.dtype) * slabs.cells_per_slab * self.sim.grid.spacing[0])
            placeholder = [leaf[0] for leaf in _particles(buffers, capacity)]  # any finite particle

            def reset(state, valid):
                """Free slots back to the parked placeholder: zero mass and volume at the slab's centre."""
                leaves = [jnp.where(_expand(valid, a), a, p) for a, p in zip(_particles(state, capacity), placeholder)]
                state = _with_particles(state, leaves, capacity)
                return _replace(state, x=jnp.where(valid[:, None], state.x, park),
                                mass=jnp.where(valid, state.mass, 0.0), volume0=jnp.where(valid, state.volume0, 0.0))

            @jax.checkpoint
            def body(carry, _):
                state, valid, ids, done, overflow, migrated = carry
                with use_window(slabs.device_window(k, sim.velocity_fields)):
                    new = sim.step(state, dt)
                # the energy the scheme dissipated is a sum over particles: every device's share
                new = _replace(new, dissipated=state.dissipated + jax.lax.psum(new.dissipated - state.dissipated, axis))
                particles = {"state": _particles(new, capacity), "ids": ids}
                moved, new_valid, lost, moving = migrate(particles, valid, self.owner(new.x), exchange, axis, D)
                new = _with_particles(new, moved["state"], capacity)
                new = reset(new, new_valid)
                ok = (overflow == 0) & (lost == 0)
                keep = lambda a, b: jnp.where(ok, a, b)  # noqa: E731  (stop at the first loss)
                state = jax.tree_util.tree_map(keep, new, state)
                return (state, keep(new_valid, valid), keep(moved["ids"], ids), done + ok.astype(jnp.int32),
                        jnp.where(overflow == 0, lost, overflow),
                        migrated + jnp.where(ok, moving, 0).astype(jnp.int32)), None

            buffers = reset(buffers, valid)
            zero = jnp.zeros((), jnp.int32)
            (buffers, valid, ids, done, overflow, migrated), _ = jax.lax.scan(
                body, (buffers, valid, ids, zero, zero, zero), None, length=steps)
            return buffers, valid, ids, done[None], overflow[None], migrated[None]

        def spec(a):
            return P(axis) if getattr(a, "ndim", 0) >= 1 and a.shape[0] == rows else P()

        def program(sim, buffers, valid, ids, dt):
            specs = jax.tree_util.tree_map(spec, buffers)
            replicated = jax.tree_util.tree_map(lambda _: P(), sim)
            mapped = jax.shard_map(local, mesh=self.mesh, in_specs=(replicated, specs, P(axis), P(axis), P()),
                                   out_specs=(specs, P(axis), P(axis), P(axis), P(axis), P(axis)), check_vma=False)
            return mapped(sim, buffers, valid, ids, dt)

        return jax.jit(program)


def _host(a):
    """A global array's values on this process (gathered from every process when several run)."""
    if isinstance(a, jax.Array) and not a.is_fully_addressable:
        return np.asarray(multihost_utils.process_allgather(a, tiled=True))
    return np.asarray(a)


def _local(a):
    """The first entry a process can read of a count that every device holds the same."""
    if isinstance(a, jax.Array):
        return np.asarray(a.addressable_shards[0].data).reshape(-1)[0]
    return np.asarray(a).reshape(-1)[0]


def _expand(mask, a):
    """``mask`` (C,) broadcast against a per-particle array (C, ...)."""
    mask = jnp.asarray(mask)
    return mask.reshape(mask.shape + (1,) * (a.ndim - 1))


def _replace(state: State, **changes) -> State:
    for name, value in changes.items():
        state = eqx.tree_at(lambda s, name=name: getattr(s, name), state, value)
    return state


def _particles(state: State, capacity: int) -> list:
    """The per-particle leaves of ``state`` (the ones migration moves)."""
    return [leaf for leaf in jax.tree_util.tree_leaves(state) if _per_particle(leaf, capacity)]


def _with_particles(state: State, leaves: list, capacity: int) -> State:
    flat, tree = jax.tree_util.tree_flatten(state)
    it = iter(leaves)
    return jax.tree_util.tree_unflatten(tree, [next(it) if _per_particle(leaf, capacity) else leaf for leaf in flat])


