"""A Simulation stepped on many devices: slabs of the grid, particles in fixed-capacity buffers.

:class:`ShardedSimulation` wraps a :class:`jaxmpm.Simulation` and runs its unchanged step inside
``jax.shard_map`` over a one-axis ``Mesh``: each device steps the particles of its slab on its
window of the grid (:mod:`jaxmpm.transfer.kernels.windowed`; one halo exchange per P2G, the
velocity conditions cut to the window), then the particles that crossed a slab face move to the
neighbour (:func:`~jaxmpm.parallel.migration.migrate`).  Free buffer slots hold a parked
placeholder particle (zero mass, volume and particle fields at the slab's centre, reset every
step), so shapes never change and one compiled program serves the whole run.

A run stops stepping at the first step where a particle did not fit (more movers than the
exchange slots, a full buffer, or a particle crossing more than one slab), with the state of the
step before, and :meth:`ShardedSimulation.run` raises an error naming the capacity option: no
particle is dropped silently.  It stops the same way at the first unstable step
(:meth:`jaxmpm.Simulation.instability`: NaN, an inverted particle, a particle off the grid) and
raises the :class:`jaxmpm.InstabilityError` a one-device run raises.

With ``save_every``, :meth:`ShardedSimulation.run` saves frames as ``Simulation.run`` does: the one
compiled rollout of ``save_every`` steps is called once per frame, and each frame is made on the
host from the collected particles, in the user's order (:meth:`ShardedSimulation.collect`), by the
driver's own frame function -- so a frame holds what a one-device run's holds, and an
:class:`jaxmpm.H5Writer` (process 0's only: one file) receives the frames and the state reached
as a chunked one-device run publishes them (:mod:`jaxmpm.run.driver`): the file has the usual
layout, survives a kill, and :func:`jaxmpm.resume` continues it on one device.

With ``rebalance_every=K`` the slab boundaries move with the particles (load balance,
:class:`~jaxmpm.parallel.slabs.Slabs` with ``max_cells``): the rollout takes the boundaries as a
runtime argument, and every K steps -- and before a step where a particle would not fit its
buffer -- the run gathers the particles on the host (:meth:`ShardedSimulation.collect`), chooses
the boundaries that equalise the slabs' particle counts (:meth:`Slabs.balanced_bounds`) and
distributes them again (:meth:`ShardedSimulation.distribute`).  When no boundaries fit the
buffers, the run stops with the error naming ``capacity``, the state of the step before kept.

:meth:`ShardedSimulation.run` computes the particle buffers in place of the ones before (JAX's buffer
donation, :data:`DONATE`): a run holds one set of buffers, the run's own (made by ``distribute``), and
never deletes the caller's state, model or time step.  The public ``rollout(steps)`` program keeps its
arguments.
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
from ..core.limits import require_steps
from ..core.state import State, per_particle
from ..core.validate import device_list
from ..physics.body_force import BodyForce
from ..physics.collider import Collider
from ..physics.conditions import Mirror
from ..physics.contact import Contact
from ..physics.damping import Damping
from ..physics.loads import ParticleForce, Traction
from ..physics.reaction import Reaction
from ..physics.stress import StressDivergence
from ..physics.transport import Transport
from ..run.driver import (
    Failure,
    RunInterrupted,
    _chosen_fields,
    _chunk_seconds,
    _Clock,
    _jit_first_frame,
    _Publisher,
    _raise_if_failed,
    _require_frame_memory,
    _StopOnSignal,
    _unshared,
    check_state,
)
from ..run.memory import tree_bytes
from ..transfer.kernels.windowed import use_window
from .migration import migrate
from .slabs import Slabs, halo_for

# The terms whose grid work is P2G, G2P and node-by-node operations, which the windows serve: as they
# are, or with their per-node data cut to the window (colliders' node positions: Simulation.node_positions;
# transport's held and flux nodes: jaxmpm.transfer.kernels.windowed.on_window) and nodal values read at
# the particles' nodes through it (tractions: jaxmpm.transfer.operators.slot_values); the reaction is
# summed over the particles' shares.  Any other term (one of the user's) is refused.
SUPPORTED_TERMS = (StressDivergence, BodyForce, Damping, Contact, Collider, Traction, ParticleForce, Reaction,
                   Transport)


#: larger than any step, cause or particle index: "none" in the reduction of the devices' failure records
_NEVER = np.iinfo(np.int32).max

#: :meth:`ShardedSimulation.run` computes the particle buffers in place of the ones before (JAX's buffer
#: donation: the buffers, ``valid`` and ``ids`` that :meth:`~ShardedSimulation.distribute` made, or the
#: rollout returned); False: every call keeps its arguments (the same numbers, one buffer set more)
DONATE = True


def _no_stats() -> dict:
    """:attr:`ShardedSimulation.stats` before a run's first step: nothing counted yet."""
    return {"steps": 0, "migrated": 0, "rebalances": 0, "particles": None, "mass": None, "bounds": []}


class ShardedSimulation:
    """``sim`` on the devices of a one-axis mesh, its grid cut into slabs along x.

    Args:
        sim: the :class:`jaxmpm.Simulation`: any scheme, and the library's terms
            (:data:`SUPPORTED_TERMS`: the stress, body force, damping, contact, colliders static or
            moving, tractions, point forces, the conditions' reaction, heat and diffusion) with any
            velocity conditions, symmetry planes (jm.Mirror) and a transport's mirrored held nodes
            (jm.Dirichlet(..., mirror=...)) included.  Refused with an InputError: terms of one's
            own, and a mirror across x (the slabs' axis) whose ghost and mirror nodes a slab face
            would put in different windows (the edge slab narrower than the ghost band and the halo).
        devices: the devices (default ``jax.devices()``); ``sim.grid.cells[0]`` must be a multiple
            of their number.
        halo: the halo in node planes (default: the shape function's nodes per axis minus one).
        capacity: particle slots per device (default: 1.15 x the particles of the fullest slab at
            the start, plus 16; every slot costs a particle's step, parked or not).
        exchange: slots per step for the particles moving to each neighbour (default: the most of
            a tenth of ``capacity``, 8, and 1.25 x the particles of the fullest cell column along x
            at the start -- a stable step moves a particle less than a cell -- at most ``capacity``).
        rebalance_every: K, the steps between rebalances: the slab boundaries move to equalise the
            particle counts every K steps (with frames: at the first frame at or after K steps), and
            before any step where a particle would not fit its buffer (see the module docstring).
            Each rebalance gathers and redistributes every particle through the host.  None (the
            default): fixed equal slabs, as before -- rebalancing is a choice for flows that gather
            particles in a few slabs (collapses, dam breaks), and each costs a host round trip.
        max_cells: with ``rebalance_every``, the widest a slab may be, in cells (default: twice the
            equal slab, at most the grid less the narrowest slabs of the others); every device's
            window, and its grid work, is ``max_cells`` + 2 H + 1 node planes.
    """

    def __init__(self, sim, devices=None, halo: int | None = None, capacity: int | None = None,
                 exchange: int | None = None, axis_name: str = "slabs", rebalance_every: int | None = None,
                 max_cells: int | None = None):
        devices = jax.devices() if devices is None else device_list("ShardedSimulation", devices)
        unsupported = sorted({type(t).__name__ for t in sim.terms if not isinstance(t, SUPPORTED_TERMS)})
        check(not unsupported, f"ShardedSimulation: {', '.join(unsupported)} not supported on several devices yet "
              f"(supported terms: {', '.join(t.__name__ for t in SUPPORTED_TERMS)}); run this model on one device")
        bound = sorted({type(t).__name__ for t in sim.terms if not t.order_free})
        check(not bound, f"ShardedSimulation: the term(s) {', '.join(bound)} hold per-particle arrays in the "
                         "particles' order (Term.order_free), which particles moving between devices would mismatch; "
                         "run this model on one device")
        self.sim = sim
        self.mesh = Mesh(np.array(devices), (axis_name,))
        halo = halo if halo is not None else halo_for(sim.shape)
        check(rebalance_every is None or (isinstance(rebalance_every, (int, np.integer))
                                          and not isinstance(rebalance_every, bool) and rebalance_every >= 1),
              f"ShardedSimulation: rebalance_every = {rebalance_every!r} must be a positive integer (the steps "
              "between rebalances) or None (fixed equal slabs)")
        check(max_cells is None or rebalance_every is not None, "ShardedSimulation: max_cells bounds the slabs "
              "that move; pass rebalance_every= (the steps between rebalances) with it, or leave it out")
        self.rebalance_every = None if rebalance_every is None else int(rebalance_every)
        if self.rebalance_every is not None:
            cells, narrow, D = sim.grid.cells[0], 2 * halo + 1, len(devices)
            if max_cells is None:
                max_cells = max(narrow, min(2 * -(-cells // D), cells - (D - 1) * narrow))
            self.slabs = Slabs(sim.grid, D, halo, axis_name, max_cells=max_cells)
        else:
            self.slabs = Slabs(sim.grid, len(devices), halo, axis_name)
        self._check_images()
        self.bounds = None  # the slabs' boundaries (slabs that move), chosen by distribute
        self.capacity = capacity
        self.exchange = exchange
        self.axis_name = axis_name
        self._programs = {}
        self.stats = _no_stats()  # until a run steps (a resumed file with no step left runs none)

    def _check_images(self):
        """An InputError unless every ghost node of a symmetry plane (jm.Mirror) or of a transport's
        mirrored held boundary (jm.Dirichlet(..., mirror=...)) lies in the same windows' complete
        planes as its mirror node.  A window's planes hold complete P2G sums from its slab's face b_k
        - H to b_{k+1} + H (:mod:`~jaxmpm.parallel.slabs`), and the image is folded there node by node
        (:meth:`jaxmpm.physics.conditions.MirrorMap.on_window`): a pair on one x plane (a plane normal
        to y or z) is always whole; a pair across x planes lo < hi (a plane normal to x, at the grid's
        end) is whole when no slab face b puts b - H in (lo, hi] or b + H in [lo, hi), i.e. when the
        edge slab is wider than the ghost band and the halo."""
        sim, slabs = self.sim, self.slabs
        grid, H, D, cells = sim.grid, slabs.halo, slabs.devices, sim.grid.cells[0]
        if D == 1:
            return
        pairs = [(f"the symmetry plane jm.Mirror({c.where!r}, {c.position:g})", *c.plane(grid)[1:3])
                 for c in sim.boundary if isinstance(c, Mirror)]
        for t in sim.terms:
            if isinstance(t, Transport):
                ghosts, mirrors = t.mirror_map(sim)
                pairs.append((f"{type(t).__name__}'s jm.Dirichlet(..., mirror=...)", ghosts % grid.num_nodes,
                              mirrors % grid.num_nodes))
        moving = self.rebalance_every is not None
        faces = slabs.possible_faces(moving)
        for what, ghosts, mirrors in pairs:
            planes = np.stack([np.asarray(ghosts) // slabs.plane_nodes, np.asarray(mirrors) // slabs.plane_nodes])
            lo, hi = planes.min(axis=0), planes.max(axis=0)
            across = lo < hi
            if not across.any():
                continue
            lo, hi = lo[across][:, None], hi[across][:, None]
            split = ((faces - H > lo) & (faces - H <= hi)) | ((faces + H >= lo) & (faces + H < hi))
            if not split.any():
                continue
            face = int(faces[np.flatnonzero(split.any(axis=0))[0]])
            low_end = face <= cells // 2
            width = int(hi.max()) + H + 1 if low_end else cells - (int(lo.min()) - H - 1)
            edge = "first" if low_end else "last"
            now = (f" (now {slabs.cells_per_slab} with {D} devices); raise the grid's cells along x, or use fewer "
                   "devices" if not moving else f", and slabs that move may be as narrow as {slabs.min_cells} cells; "
                   "shard with fixed equal slabs (no rebalance_every)")
            check(False, f"ShardedSimulation: {what} pairs ghost and mirror node planes {int(lo.min())} to "
                  f"{int(hi.max())} along x (the slabs' axis), and a slab face at cell {face} would cut them into "
                  f"different windows (halo {H} planes): the {edge} slab must span at least {width} cells{now}, or "
                  "run the model on one device")

    @property
    def devices(self) -> int:
        return self.slabs.devices

    # ------------------------------------------------------------------ distribute and collect
    def owner(self, x, bounds=None):
        """The device of each particle (its cell's slab), from positions (N, D); ``bounds``: the
        slabs' boundaries (default: :attr:`bounds`, for slabs that move)."""
        grid = self.sim.grid
        return self.slabs.owner(x, grid.lower[0], grid.spacing[0], self.bounds if bounds is None else bounds)

    def distribute(self, state: State):
        """Sharded buffers of ``state``: (buffers, valid, ids), each per-particle array (D C, ...)
        laid out device by device and sharded over the mesh, ``valid`` (D C,) and ``ids`` (D C,)
        the particle's index in ``state`` (-1 in free slots).  With ``rebalance_every``, first the
        boundaries that equalise the slabs' particle counts (:attr:`bounds`)."""
        n = state.x.shape[0]
        grid = self.sim.grid
        cell = np.clip(np.asarray(self.slabs.cell(state.x, grid.lower[0], grid.spacing[0])), 0, grid.cells[0] - 1)
        columns = np.bincount(cell, minlength=grid.cells[0])  # the particles of each cell column along x
        if self.rebalance_every is not None:  # the most even slabs
            self.bounds = self.slabs.balanced_bounds(columns)
        owner = np.asarray(self.owner(state.x))
        counts = np.bincount(owner, minlength=self.devices)
        # every slot is stepped, parked or not: the headroom costs its share of the step (one device
        # needs none)
        capacity = self.capacity or (n if self.devices == 1 else int(math.ceil(1.15 * counts.max())) + 16)
        if self.bounds is not None:
            check(counts.max() <= capacity, f"ShardedSimulation: at step {int(state.step)} the most even slabs "
                  f"(boundaries {self.bounds.tolist()}, {self.slabs.min_cells} to {self.slabs.max_cells} cells) "
                  f"hold up to {counts.max()} particles, more than capacity = {capacity} per device; raise capacity "
                  "(or max_cells)")
        check(counts.max() <= capacity, f"ShardedSimulation: a slab starts with {counts.max()} particles, more than "
              f"capacity = {capacity}; raise capacity")
        self.capacity = capacity
        # a stable step moves a particle less than a cell, so at most one cell column's particles cross
        # a face in a step: particles on a lattice cross a plane at a time (a tenth of the capacity was
        # too few for a disk's 16-particle planes); a quarter more for a column that fills
        self.exchange = self.exchange or min(capacity, max(8, capacity // 10, int(columns.max()) * 5 // 4))
        slots = np.zeros(self.devices * capacity, dtype=np.int64)  # a real particle or the placeholder
        valid = np.zeros(self.devices * capacity, dtype=bool)
        ids = -np.ones(self.devices * capacity, dtype=np.int64)
        for k in range(self.devices):
            mine = np.flatnonzero(owner == k)
            slots[k * capacity:k * capacity + len(mine)] = mine
            valid[k * capacity:k * capacity + len(mine)] = True
            ids[k * capacity:k * capacity + len(mine)] = mine
        # free slots hold copies of particle 0 until the run parks them (zero mass and volume)
        buffers = jax.tree_util.tree_map(lambda a: jnp.asarray(a)[slots] if per_particle(a, n) else a, state)
        sharding = NamedSharding(self.mesh, P(self.axis_name))
        rows = self.devices * capacity
        on_cpu = self.mesh.devices.flat[0].platform == "cpu"

        def put(a):  # a global array, each process filling its devices' rows (several hosts: jax.distributed)
            if not per_particle(a, rows):
                return np.asarray(a) if isinstance(a, jax.Array) else a  # replicated: the same on every process
            host = np.asarray(a)
            array = jax.make_array_from_callback(host.shape, sharding, lambda index: host[index])
            # a CPU device may hold the host array's memory itself (no copy), which XLA does not compute in
            # place (the run's donation would copy instead): each device's rows copied into memory of its own
            return _copied(array) if on_cpu else array

        return jax.tree_util.tree_map(put, buffers), put(valid), put(ids)

    def collect(self, buffers, valid, ids, n: int) -> State:
        """The particles of sharded ``buffers`` back in their original order (N of them): a
        :class:`State` on this process's default device, the same on every process (the time,
        step and other replicated leaves read from this process's copy)."""
        valid, ids = _host(valid), _host(ids)
        check(int(valid.sum()) == n and np.array_equal(np.sort(ids[valid]), np.arange(n)),
              f"ShardedSimulation: the buffers hold {int(valid.sum())} particles, expected {n}")
        order = np.empty(n, dtype=np.int64)
        order[ids[valid]] = np.flatnonzero(valid)
        rows = self.devices * self.capacity
        return jax.tree_util.tree_map(lambda a: jnp.asarray(_host(a)[order]) if per_particle(a, rows)
                                      else _replicated(a), buffers)

    def _park_x(self, dtype, device):
        """Parking positions (rows, D): the centre of each slot's slab (and of the grid across)."""
        grid = self.sim.grid
        centre = np.asarray([(lo + hi) / 2 for lo, hi in zip(grid.lower, grid.upper)], dtype=float)
        x = np.tile(centre, (len(device), 1))
        x[:, 0] = grid.lower[0] + (np.asarray(device) + 0.5) * self.slabs.cells_per_slab * grid.spacing[0]
        return jnp.asarray(x, dtype)

    # ------------------------------------------------------------------ the run
    def run(self, state: State, dt, steps: int, save_every: int | None = None, *, save_particles: bool = True,
            fields: tuple | None = None, writer=None, progress: bool = False, timings: dict | None = None,
            start_step: int | None = None):
        """``steps`` steps of ``dt`` from ``state`` on the mesh.

        Without ``save_every`` (and no ``writer``): the final state, in the particles' original
        order.  With ``save_every``: ``(final_state, history)`` as :meth:`jaxmpm.Simulation.run`
        returns them -- a :class:`jaxmpm.History` of the initial frame and one every ``save_every``
        steps, each in the user's particle order with ``fields`` (stress, J, ...) -- or
        ``(final_state, None)`` when ``writer`` (a :class:`jaxmpm.H5Writer`, on process 0 only)
        holds the frames.  Both ways raise, naming the option, when particles did not fit their
        buffers, and raise :class:`jaxmpm.InstabilityError` at the first unstable step.

        Args:
            state: the initial :class:`jaxmpm.State`.
            dt: the time step.
            steps: the steps to run (a multiple of ``save_every``).
            save_every: the steps between saved frames; None (the default): no frames.
            save_particles: frames hold x, v and the per-particle fields (default True).
            fields: the chosen per-particle fields of each frame, by name (:mod:`jaxmpm.model.frame_fields`);
                with a writer, the writer's; None (the default): none.
            writer: an :class:`jaxmpm.H5Writer` receiving the frames, and the state reached with them,
                as they come (every :data:`jaxmpm.run.driver.CHUNK_SECONDS` or so: a killed run keeps
                its finished frames, and :func:`jaxmpm.resume` continues the file on one device).
                Only process 0 writes (``jax.process_index() == 0``): the others pass None, and
                keep no frames either (they return ``(final_state, None)`` too).
            progress: show a progress bar (default False).
            timings: a dict to fill with the seconds spent compiling and running and the steps run,
                as :func:`jaxmpm.run.driver.run` does; None (the default).
            start_step: with a writer, continue a run (:func:`jaxmpm.resume`): the step of its first
                frame, ``state`` part-way through its schedule of ``steps`` steps from there (the
                frames up to ``state`` are in the writer's file already); None (the default): a run
                from ``state``, as :meth:`jaxmpm.Simulation.run` has it.
        """
        check(start_step is None or writer is not None, "ShardedSimulation.run: start_step continues a run saved "
              "in a file; pass writer= (see jaxmpm.resume)")
        if save_every is None and writer is None:
            check(fields is None and not progress and timings is None, "ShardedSimulation.run: fields=, progress= "
                  "and timings= belong to a run that saves frames; pass save_every= (the steps between frames)")
            n = state.x.shape[0]
            buffers, valid, ids = self.distribute(state)
            self._start_stats(state)
            # one rollout, or with rebalancing rollouts of K steps (and one of the rest), the slabs
            # moved between them
            lengths = [steps]
            if self.rebalance_every is not None and steps > 0:
                chunk = min(self.rebalance_every, steps)
                lengths = [chunk] * (steps // chunk) + ([steps % chunk] if steps % chunk else [])
            for length in lengths:
                buffers, valid, ids = self._advance(self._in_place(length), self.sim, state, buffers, valid, ids,
                                                    jnp.asarray(dt), length)
            return self.collect(buffers, valid, ids, n)
        return self._run_frames(state, dt, steps, save_every, save_particles, fields, writer, progress, timings,
                                start_step)

    def _start_stats(self, state):
        """:attr:`stats` of a run from ``state``, after :meth:`distribute`: the steps done, the particles
        that changed device, the rebalances and the boundaries chosen at each step (slabs that move),
        and the fewest and most particles, and the least and most mass, the devices held together
        after any step (every step's census)."""
        self.stats = _no_stats()
        if self.bounds is not None:
            self.stats["bounds"].append((int(state.step), self.bounds.tolist()))
        self._reached, self._since = int(state.step), 0  # the buffers' step; steps since the slabs moved

    def _advance(self, program, sim, state, buffers, valid, ids, dt, steps: int, held=None):
        """The ``steps`` steps of a compiled rollout (:meth:`_in_place`'s: the buffers given are deleted)
        from the buffers: the buffers reached, with :attr:`stats` counted on; raises at an unstable step
        (``state``: a state of this run, for its time) or a particle that did not fit (the run stopped at
        the step before).  With ``rebalance_every``, the slabs move first when K steps have passed since
        they last did, and when a particle would not fit, the run stops, the slabs move and the run goes on
        from the step before; only when they have just moved does it raise.  ``held``: the buffers'
        particles as a State, when the caller has collected them (a rebalance then needs no gather)."""
        if self.rebalance_every is None:
            buffers, valid, ids, _, overflow = self._call(program, sim, state, buffers, valid, ids, dt)
            self._require_fit(overflow)
            return buffers, valid, ids
        n = int(state.x.shape[0])
        moved = self._since >= self.rebalance_every
        if moved:  # due: the slabs move to the particles
            buffers, valid, ids = self._rebalance(buffers, valid, ids, n, held)
        progress = 0
        while progress < steps:
            buffers, valid, ids, done, overflow = self._call(program, sim, state, buffers, valid, ids, dt,
                                                             *self._moving_args(steps - progress))
            progress, self._since = progress + done, self._since + done
            if progress < steps:  # a particle would not fit at the next step: the slabs move, unless they just did
                if moved and done == 0:
                    self._require_fit(overflow)
                buffers, valid, ids = self._rebalance(buffers, valid, ids, n)
                moved = True
        return buffers, valid, ids

    def _call(self, program, sim, state, buffers, valid, ids, dt, *moving):
        """One call of a compiled rollout of :meth:`_in_place`, the buffers computed in place of ``buffers``,
        ``valid`` and ``ids`` (``moving``: the boundaries and the step limit, for slabs that move): (buffers,
        valid, ids, steps done, particles that did not fit), :attr:`stats` counted on; raises at an unstable
        step."""
        buffers, valid, ids, done, overflow, migrated, *rest = program(
            *self._in_place_args(sim, buffers, valid, ids, dt, *moving))
        failure, census = rest[:3], rest[3:]
        done, overflow, migrated = (int(_local(a)) for a in (done, overflow, migrated))
        stats = self.stats
        stats["steps"], stats["migrated"] = stats["steps"] + done, stats["migrated"] + migrated
        particles, mass = (_host(a).reshape(self.devices, -1).sum(0) for a in census)  # every step, all devices
        if particles.size:
            for name, values in (("particles", particles), ("mass", mass)):
                low, high = values.min().item(), values.max().item()
                stats[name] = [low, high] if stats[name] is None else [min(stats[name][0], low),
                                                                      max(stats[name][1], high)]
        _raise_if_failed(Failure(*(np.int32(_local(a)) for a in failure)), dt, state, None, self.sim.grid)
        self._reached += done
        return buffers, valid, ids, done, overflow

    def _require_fit(self, overflow: int):
        """The error naming ``capacity`` and ``exchange`` when particles did not fit at the next step."""
        first = self._reached + 1
        check(overflow == 0, f"ShardedSimulation: at step {first}, {overflow} particle(s) did not fit: raise "
              f"capacity (now {self.capacity} per device) or exchange (now {self.exchange} per step and face; "
              f"jaxmpm run --capacity C --exchange X); the state after step {first - 1} was kept")

    def _rebalance(self, buffers, valid, ids, n: int, held=None):
        """The slabs moved to the particles: every particle gathered on the host (or ``held``, the
        buffers' particles already gathered), the boundaries that equalise the slabs' counts chosen
        and the particles distributed again -- the buffers, and :attr:`bounds`.  Raises, naming
        ``capacity``, when the fullest of the most even slabs would not fit its buffer."""
        state = self.collect(buffers, valid, ids, n) if held is None else held
        buffers, valid, ids = self.distribute(state)
        self._since = 0
        self.stats["rebalances"] += 1
        self.stats["bounds"].append((int(state.step), self.bounds.tolist()))
        return buffers, valid, ids

    def _moving_args(self, steps: int) -> tuple:
        """The rollout's arguments after dt: none for equal slabs; the boundaries and the step limit
        for slabs that move."""
        if self.rebalance_every is None:
            return ()
        return jnp.asarray(self.bounds, jnp.int32), jnp.asarray(steps, jnp.int32)

    def _run_frames(self, state, dt, steps, save_every, save_particles, fields, writer, progress, timings,
                    start_step=None):
        """:meth:`run` with frames: the compiled rollout of ``save_every`` steps once per frame,
        each frame made from the collected particles and published with the driver's
        :class:`~jaxmpm.run.driver._Publisher` (a chunk of frames and the state reached, about
        every ``CHUNK_SECONDS``), the driver's clock, progress bar and Ctrl-C handling around it."""
        import time

        check(save_every is not None, "ShardedSimulation.run: a writer saves frames; pass save_every= (the steps "
                                      "between frames)")
        check(isinstance(steps, (int, np.integer)) and steps >= 0,
              f"ShardedSimulation.run: steps = {steps!r} must be a non-negative integer")
        check(isinstance(save_every, (int, np.integer)) and save_every >= 1 and steps % save_every == 0,
              f"ShardedSimulation.run: save_every = {save_every!r} must be a positive integer dividing "
              f"steps = {steps}")
        check(writer is None or jax.process_index() == 0,
              f"ShardedSimulation.run: a writer on process {jax.process_index()}; open the H5Writer on process 0 "
              "only (jax.process_index() == 0) and pass writer=None on the others: one process writes the file")
        self.sim.check_state(state, "ShardedSimulation.run")  # a jm.State, made for this model
        check_state(state)
        sim = self.sim.in_precision(state.x.dtype)  # the model computes in its state's precision
        chosen = _chosen_fields(sim, state, () if fields is None else fields, save_particles)
        if writer is not None:  # the writer's fields, named once (as sim.run has it)
            check(fields is None or chosen == writer.fields, f"ShardedSimulation.run: fields = {fields!r} but the "
                  f"writer saves {writer.fields!r}; choose them once, on the writer (jm.H5Writer(..., fields=...))")
            chosen = _chosen_fields(sim, state, writer.fields, save_particles)
        fields = chosen
        n, start = int(state.x.shape[0]), int(state.step) if start_step is None else int(start_step)
        done = int(state.step) - start  # resumed: the steps done before this call, their frames saved
        check(0 <= done <= steps, f"resume: the state is at step {int(state.step)}, outside the run's steps "
              f"{start}..{start + steps}")
        lead = -done % save_every  # resumed between two frames: the steps to the next frame, saved with it
        frames = (steps - done - lead) // save_every
        require_steps(start + steps, "shorten t_end, use a larger dt, or split the run")
        writing = writer is not None  # process 0's writer holds the frames: no process keeps them in memory
        if jax.process_count() > 1:
            writing = bool(multihost_utils.broadcast_one_to_all(np.int32(writing)))
        _require_frame_memory(sim, state, frames, save_particles, not writing, fields)
        dt = jnp.asarray(dt, state.x.dtype)
        buffers, valid, ids = self.distribute(state)
        self._start_stats(state)
        clock = _Clock(steps, done, progress, timings)
        publisher = None if writer is None else _Publisher(
            writer, dict(start_step=start, steps=steps, save_every=save_every), tree_bytes(state))
        seconds = _chunk_seconds()
        pieces, pending = [], []  # frames kept in memory; frames not yet published

        def one_frame(s):
            if writing and writer is None:  # another process writes the frames
                return None
            return _jit_first_frame(sim, s, save_particles, fields)  # with its frame axis, in one program

        def concatenated(chunks):
            return jax.tree_util.tree_map(lambda *a: jnp.concatenate(a), *chunks)

        try:
            with _StopOnSignal() as stop:
                with clock.compiling():  # the rollout of one frame, compiled before the first step
                    program = self._in_place(save_every).lower(*self._in_place_args(
                        sim, buffers, valid, ids, dt, *self._moving_args(save_every))).compile()
                    fresh = done == 0 and (writer is None or writer.frames == 0)  # no frame saved yet
                    first = jax.block_until_ready(one_frame(state)) if fresh else None
                if not writing:
                    pieces.append(first)
                elif writer is not None and fresh:  # before the first step: from here on the file can be continued
                    publisher.publish(first, state)
                published = time.perf_counter()
                clock.start()
                if lead:  # resumed between two frames: on to the next frame, saved with the state there
                    buffers, valid, ids = self._advance(self._in_place(lead), sim, state, buffers, valid, ids, dt,
                                                        lead, held=state)
                    state = self.collect(buffers, valid, ids, n)
                    frame = one_frame(state)
                    if writer is not None:
                        publisher.publish(frame, state, due=True)
                    clock.chunk(lead)
                for k in range(frames):
                    tic = time.perf_counter()
                    try:
                        buffers, valid, ids = self._advance(program, sim, state, buffers, valid, ids, dt, save_every,
                                                            held=state)
                    except BaseException:
                        if pending:  # the frames before the failing one, with the state they reached
                            publisher.publish(concatenated(pending), state, due=True)
                        raise
                    state = self.collect(buffers, valid, ids, n)
                    frame = one_frame(state)
                    if frame is not None:
                        (pieces if writer is None else pending).append(frame)
                    clock.chunk(save_every)
                    clock.tell_if_long(save_every / max(time.perf_counter() - tic, 1e-6), writer)
                    last = k == frames - 1
                    due = last or stop.requested is not None
                    if pending and (due or time.perf_counter() - published >= seconds):
                        publisher.publish(concatenated(pending), state, due=due)
                        pending, published = [], time.perf_counter()
                    if stop.requested is not None and not last:
                        if writing:
                            raise RunInterrupted(state, k + 2 if writer is None else writer.frames, stop.requested)
                        history = concatenated(pieces)
                        raise RunInterrupted(state, len(history), stop.requested, history)
        finally:
            clock.close()
            if writer is not None:
                writer.flush()
        return state, (None if writing else concatenated(pieces))

    def rollout(self, steps: int):
        """The jitted sharded rollout of ``steps`` steps (one program per step count):
        ``rollout(steps)(sim, buffers, valid, ids, dt)`` -> (buffers, valid, ids, steps done, particles
        that did not fit, migrations, first unstable step, its cause, its particle, particles held and
        their mass after each step), each count (D,) with every entry the same; the three after the
        migrations are a :class:`jaxmpm.run.driver.Failure`'s (step -1: none; the particle's index in
        the user's order); the last two (D x steps,): each device's census, step by step.  With
        ``rebalance_every``: ``rollout(steps)(sim, buffers, valid, ids, dt, bounds, limit)``, ``bounds``
        the slabs' boundaries (:attr:`bounds`, (D + 1,) int32, a runtime argument: one program
        serves any) and ``limit`` the steps to take at most (None: all; the rest are not taken).  ``sim`` is an argument
        (a model of the same structure: other parameters, or differentiated, without recompiling;
        its leaves that are not arrays -- a load T(t), a solid's motion u(t) -- are static, as
        ``eqx.filter_jit`` keeps them); each step is rematerialised in reverse mode
        (``jax.checkpoint``); its arguments are kept (:meth:`run` calls :meth:`_in_place`'s program, which
        computes the buffers in place).  Call :meth:`distribute` first (it fixes the capacity)."""
        check(self.capacity is not None, "ShardedSimulation.rollout: call distribute(state) first (it sets capacity)")
        key = (steps, self.capacity, self.exchange)
        if key not in self._programs:
            self._programs[key] = eqx.filter_jit(self._build(steps))
        return self._programs[key]

    def _in_place(self, steps: int):
        """The rollout of ``steps`` steps that :meth:`run` calls, its buffers computed in place of the ones it
        is given: ``_in_place(steps)(kept, particles, valid, ids)`` (:meth:`_in_place_args` splits the
        rollout's arguments so) returns what :meth:`rollout`'s program returns, and deletes ``particles``
        (the buffers' per-particle arrays), ``valid`` and ``ids`` -- the run's own arrays, made by
        :meth:`distribute` or returned by the call before (JAX's buffer donation, :data:`DONATE`).  The rest,
        ``kept`` = (sim, dt, the buffers' replicated leaves, and the boundaries and step limit of slabs that
        move), the caller's arrays among them, is never donated."""
        check(self.capacity is not None, "ShardedSimulation.run: call distribute(state) first (it sets capacity)")
        key = ("in place", DONATE, steps, self.capacity, self.exchange)
        if key not in self._programs:
            rollout = self._build(steps)

            def in_place(kept, particles, valid, ids):
                sim, dt, replicated, *moving = kept
                return rollout(sim, eqx.combine(particles, replicated), valid, ids, dt, *moving)

            self._programs[key] = eqx.filter_jit(in_place, donate="all-except-first" if DONATE else "none")
        return self._programs[key]

    def _in_place_args(self, sim, buffers, valid, ids, dt, *moving) -> tuple:
        """The arguments of :meth:`_in_place`'s program for ``rollout(steps)(sim, buffers, valid, ids, dt,
        *moving)``: the kept ones first, then the donated per-particle buffers, ``valid`` and ``ids``, each array
        once (XLA donates a buffer once: one held by two leaves is copied for the second)."""
        rows = self.devices * self.capacity
        particles, replicated = eqx.partition(buffers, lambda a: per_particle(a, rows))
        return ((sim, dt, replicated, *moving), *_unshared((particles, valid, ids), copy=_copied))

    def _build(self, steps: int):
        """The rollout of ``steps`` steps, not yet compiled: :meth:`rollout` and :meth:`_in_place` jit it."""
        slabs, axis = self.slabs, self.axis_name
        capacity, exchange, D = self.capacity, self.exchange, self.devices
        moving = self.rebalance_every is not None
        rows = D * capacity

        def local(sim, buffers, valid, ids, dt, bounds=None, limit=None):
            k = jax.lax.axis_index(axis)
            park = self._park_x(buffers.x.dtype, np.zeros(capacity, int))
            if bounds is None:
                park = park.at[:, 0].add(k.astype(park.dtype) * slabs.cells_per_slab * self.sim.grid.spacing[0])
            else:  # the centre of this device's slab
                lower, h = self.sim.grid.lower[0], self.sim.grid.spacing[0]
                centre = lower + (bounds[k] + 0.5 * (bounds[k + 1] - bounds[k])) * h
                park = park.at[:, 0].set(centre.astype(park.dtype))
            placeholder = [leaf[0] for leaf in _particles(buffers, capacity)]  # any finite particle

            def reset(state, valid):
                """Free slots back to the parked placeholder: zero mass and volume at the slab's centre, and
                zero in the terms' particle fields (it is no loaded particle: jm.Traction, jm.ParticleForce)."""
                leaves = [jnp.where(_expand(valid, a), a, p) for a, p in zip(_particles(state, capacity), placeholder)]
                state = _with_particles(state, leaves, capacity)
                if state.fields:
                    state = _replace(state, fields={name: jnp.where(_expand(valid, a), a, jnp.zeros((), a.dtype))
                                                    for name, a in state.fields.items()})
                return _replace(state, x=jnp.where(valid[:, None], state.x, park),
                                mass=jnp.where(valid, state.mass, 0.0), volume0=jnp.where(valid, state.volume0, 0.0))

            def unstable(state, ids, fail):
                """This device's failure record (step, cause, particle) after ``state``: the model's own
                check (Simulation.instability), the particle by its user's index; no communication
                (the devices' records are reduced once, after the scan)."""
                code, particle = sim.instability(jax.lax.stop_gradient(state), jax.lax.stop_gradient(dt))
                new = (fail[0] < 0) & (code > 0)
                return tuple(jnp.where(new, a, b).astype(jnp.int32) for a, b in zip((state.step, code, ids[particle]),
                                                                                   fail))

            def first_failure(fail):
                """The devices' records reduced: the first unstable step of any device, the gravest cause
                there (NaN before an inverted particle before one off the grid, as on one device) and
                the smallest user index among the devices' first particles with it (one device names the
                smallest of all)."""
                step = jax.lax.pmin(jnp.where(fail[0] >= 0, fail[0], _NEVER), axis)
                grave = jnp.where(fail[1] == 4, 3, fail[1])  # a fast exit is an exit: ordered as one, and named
                at = fail[0] == step  # by its first particle, as on one device
                cause = jax.lax.pmin(jnp.where(at, grave, _NEVER), axis)
                particle = jax.lax.pmin(jnp.where(at & (grave == cause), fail[2], _NEVER), axis)
                cause = jax.lax.pmax(jnp.where(at & (grave == cause) & (fail[2] == particle), fail[1], 0), axis)
                failed = step < _NEVER
                return tuple(jnp.where(failed, a, -1 if i != 1 else 0).astype(jnp.int32)
                             for i, a in enumerate((step, cause, particle)))

            @jax.checkpoint
            def body(carry, _):
                state, valid, ids, done, overflow, migrated, fail = carry
                with use_window(slabs.device_window(k, sim.velocity_fields, bounds)):
                    new = sim.step(state, dt)
                # the energy the scheme dissipated is a sum over particles: every device's share
                new = _replace(new, dissipated=state.dissipated + jax.lax.psum(new.dissipated - state.dissipated, axis))
                particles = {"state": _particles(new, capacity), "ids": ids}
                moved, new_valid, lost, moving = migrate(particles, valid, self.owner(new.x, bounds), exchange, axis, D)
                new = _with_particles(new, moved["state"], capacity)
                new = reset(new, new_valid)
                checked = unstable(new, moved["ids"], fail)
                if limit is not None:  # a step past the limit is not taken: nothing of it counts
                    active = done < limit
                    lost = jnp.where(active, lost, 0)
                    checked = tuple(jnp.where(active, a, b) for a, b in zip(checked, fail))
                fail = checked
                ok = (overflow == 0) & (lost == 0) & (fail[0] < 0)
                if limit is not None:
                    ok = ok & active
                keep = lambda a, b: jnp.where(ok, a, b)  # noqa: E731  (stop at the first loss or instability)
                state = jax.tree_util.tree_map(keep, new, state)
                valid = keep(new_valid, valid)
                # the census of this step: the particles this device holds, and their mass
                census = jnp.sum(valid.astype(jnp.int32)), jnp.sum(jnp.where(valid, state.mass, 0))
                return (state, valid, keep(moved["ids"], ids), done + ok.astype(jnp.int32),
                        jnp.where(overflow == 0, lost, overflow),
                        migrated + jnp.where(ok, moving, 0).astype(jnp.int32), fail), census

            buffers = reset(buffers, valid)
            zero = jnp.zeros((), jnp.int32)
            stable = (jnp.full((), -1, jnp.int32), zero, jnp.full((), -1, jnp.int32))
            (buffers, valid, ids, done, overflow, migrated, fail), census = jax.lax.scan(
                body, (buffers, valid, ids, zero, zero, zero, stable), None, length=steps)
            # a device stops at its own first unstable step (the run raises): the steps all completed
            done = jax.lax.pmin(done, axis)
            return (buffers, valid, ids, done[None], overflow[None], migrated[None]) + tuple(
                f[None] for f in first_failure(fail)) + census

        def spec(a):
            return P(axis) if getattr(a, "ndim", 0) >= 1 and a.shape[0] == rows else P()

        def program(sim, buffers, valid, ids, dt, bounds=None, limit=None):
            check((bounds is not None) == moving, "ShardedSimulation.rollout: " + (
                "slabs that move need their boundaries: call rollout(steps)(sim, buffers, valid, ids, dt, "
                "sharded.bounds)" if moving else "bounds= belong to slabs that move (rebalance_every=)"))
            specs = jax.tree_util.tree_map(spec, buffers)
            # the model's arrays are replicated arguments; its other leaves -- callables such as a
            # load T(t) or a solid's motion u(t) -- are static, as eqx.filter_jit keeps them
            params, static = eqx.partition(sim, eqx.is_array)
            replicated = jax.tree_util.tree_map(lambda _: P(), params)

            def on_device(params, *args):
                return local(eqx.combine(params, static), *args)

            out_specs = (specs,) + (P(axis),) * 10
            if not moving:
                mapped = jax.shard_map(on_device, mesh=self.mesh, in_specs=(replicated, specs, P(axis), P(axis), P()),
                                       out_specs=out_specs, check_vma=False)
                return mapped(params, buffers, valid, ids, dt)
            mapped = jax.shard_map(on_device, mesh=self.mesh,
                                   in_specs=(replicated, specs, P(axis), P(axis), P(), P(), P()),
                                   out_specs=out_specs, check_vma=False)
            limit = jnp.asarray(steps if limit is None else limit, jnp.int32)
            return mapped(params, buffers, valid, ids, dt, jnp.asarray(bounds, jnp.int32), limit)

        return program


def local_devices(count, option: str = "devices") -> list:
    """The first ``count`` devices of this process, for a sharded run on one host; an InputError
    naming ``option`` and the fix when there are fewer (on a CPU: forced host devices)."""
    here = jax.local_devices()
    check(isinstance(count, (int, np.integer)) and not isinstance(count, bool) and count >= 1,
          f"{option} = {count!r} must be a positive integer (the devices to shard the run over)")
    platform = here[0].platform
    fix = (f"set XLA_FLAGS=--xla_force_host_platform_device_count={count} in the environment before starting "
           "(forced CPU devices share the machine's cores: a check of the sharded path, not a speed-up), or "
           if platform == "cpu" else "")
    check(count <= len(here), f"{option} {count}: this process has {len(here)} {platform} device"
          f"{'s' * (len(here) != 1)}; {fix}ask for at most {len(here)}")
    return list(here[:count])


def _host(a):
    """A global array's values on this process (gathered from every process when several run)."""
    if isinstance(a, jax.Array) and not a.is_fully_addressable:
        return np.asarray(multihost_utils.process_allgather(a, tiled=True))
    return np.asarray(a)


def _replicated(a):
    """A leaf every device holds the same (the time, the step), as this process's own copy."""
    if isinstance(a, jax.Array) and len(a.sharding.device_set) > 1:
        return jnp.asarray(np.asarray(a.addressable_shards[0].data))
    return a


def _local(a):
    """The first entry a process can read of a count that every device holds the same."""
    if isinstance(a, jax.Array):
        return np.asarray(a.addressable_shards[0].data).reshape(-1)[0]
    return np.asarray(a).reshape(-1)[0]


def _copied(a):
    """A copy of a global array, each of this process's devices copying its own rows (one process cannot
    copy another's)."""
    shards = [jax.device_put(shard.data, shard.device, may_alias=False) for shard in a.addressable_shards]
    return jax.make_array_from_single_device_arrays(a.shape, a.sharding, shards)


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
    return [leaf for leaf in jax.tree_util.tree_leaves(state) if per_particle(leaf, capacity)]


def _with_particles(state: State, leaves: list, capacity: int) -> State:
    flat, tree = jax.tree_util.tree_flatten(state)
    it = iter(leaves)
    return jax.tree_util.tree_unflatten(tree, [next(it) if per_particle(leaf, capacity) else leaf for leaf in flat])


