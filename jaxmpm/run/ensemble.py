"""Ensembles: many simulations in one compiled call, sharded over devices.

How the members on a device run is the ``strategy`` (:data:`STRATEGIES`), which ``"auto"`` picks by
backend (:func:`plan`; benchmarks/ensemble_throughput.py):

* a GPU vmaps them: one batched step for all (H200, mpm88 8k particles float32: 4.8x a single
  run's particle-steps/s at 256 members);
* the CPU runs them one after another, each member the single-run step (mpm88: 0.94-1.06x a single
  run's speed for 1-16 members, where vmap gave 0.49-0.94x).  Outside a trace each member is a single
  run (:func:`_one_by_one`): ``sim.run``'s compiled loop, whose frame and step counts are runtime
  values, so an ensemble of another length, or of a model ``sim.run`` has run, compiles nothing
  (1.0-1.6 s for the disks and mpm88 before); under ``jit``/``grad`` one program maps the members'
  rollouts (``lax.map``).  Vmapped members on the CPU first lost the transfer layer's stage boundaries
  (a batched ``lax.cond`` becomes a ``select``; kept since by :mod:`jaxmpm.transfer.backend`), and
  still lose with the batch size: several members' per-slot buffers (about 1 MiB per mpm88
  member in float32) outgrow the per-core cache.  Small scenes are still vmapped on the CPU, in
  chunks of about :data:`CPU_CHUNK_PARTICLES` particles, where batching amortises the cost per
  operation (the 32-particle bar: 1.6-2.7x a single run).  Outside a trace they too run in a loop of
  runtime counts (:func:`_vmapped_at_once`: ``sim.run``'s loop, vmapped), so another length compiles nothing
  there either (0.7 s of XLA compilation for the bar's before), at 0.87-0.95x the static scans' speed on the
  bar, whose vmapped step takes 5-55 us (a while loop tests its condition every step), and the same speed on
  the disks and mpm88; ``jax.jit`` of the call keeps the static scans.

Every strategy gives the same numbers to round-off (rtol 1e-13, tests/test_ensemble_strategies.py): a frame's
sums over the particles may add in another order.
With several devices, each runs its share of the members (``shard_map``) by the same strategy -- the
devices of every process too, after ``jax.distributed.initialize``: the members spread over all of them
and every process gets every member's results back (tests/test_parallel_slabs.py, 2 processes x 2 CPU
devices: bit for bit one device's)."""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import multihost_utils
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from ..core.device import to_device
from ..core.errors import check
from ..core.params import _where, _with_owner, check_material, check_value, set_params
from ..core.registry import resolve_parameter
from ..core.state import State
from ..core.validate import POSITIVE, batch_members, concrete, device_list, positive_int
from ..materials.base import Material
from ..transfer.backend import RUNTIME_COUNTS, resolve
from .driver import (
    Failure,
    _advance,
    _buffer_frames,
    _device_ints,
    _frame_bytes,
    _frames_per_call,
    _is_traced,
    _joined,
    _run_at_once,
)
from .memory import budget_bytes, members_at_once, parse_memory
from .progress import Stage, shown, shown_call


def _batch_size(tree) -> int:
    sizes = {np.shape(leaf)[0] for leaf in jax.tree_util.tree_leaves(tree) if np.ndim(leaf) > 0}
    check(sizes, "ensemble: params and states need a leading (batch) axis, one entry per member; give each "
                 "parameter an array of its members' values, e.g. params={'E': [1e5, 2e5]}")
    check(len(sizes) == 1, f"ensemble: every batched input needs the same leading (batch) size, got {sorted(sizes)}")
    size = sizes.pop()
    check(size > 0, "ensemble: the batch has no members (a leading size of 0); give at least one")
    return size


def _members_model(sim, params: dict):
    """The model the members run: ``sim`` with a term added, at its neutral default, for each parameter of
    ``params`` that belongs to a term it lacks (as :func:`jaxmpm.set_params` adds it)."""
    for name in params:
        sim = _with_owner(sim, name)
    return sim


def _check_members(members, params: dict, own_states: bool = False) -> None:
    """Every member of a concrete parameter batch in its parameter's valid range, before tracing
    (inside the vmap the values are tracers and cannot be checked); ``members``: :func:`_members_model`."""
    for name, batch in params.items():
        found = resolve_parameter(members, name)
        if found is None:
            _where(members, name)  # an unknown name: the error naming the choices, here, not inside the trace
        parameter = found[1]
        check(own_states or not parameter.through_init,
              f"ensemble: params[{name!r}] acts through sim.init only (the particles' masses), not in the step: "
              "members sharing one initial state would run alike; give each member its state, built by sim.init "
              "of a model with its value, with states= (a batch of states)")
        batch_members("ensemble", f"params[{name!r}]", batch,
                      lambda i, member, n=name: check_value(
                          members, n, member, "ensemble" if i is None else f"ensemble member {i}"))
    # the conditions the material's parameters meet together (Material.check_parameters), member by member
    if getattr(type(members.material), "check_parameters", None) in (None, Material.check_parameters):
        return  # a law without such conditions (every built-in one but Drucker-Prager)
    hosted = {name: concrete(batch) for name, batch in params.items()}
    if any(value is None for value in hosted.values()):
        return  # traced members: unchecked, as set_params leaves a traced value
    sizes = [np.shape(batch)[0] for batch in hosted.values() if np.ndim(batch) > 0]
    for i in range(max(sizes, default=1)):
        member = members
        for name, batch in hosted.items():
            value = np.asarray(batch)[i] if np.ndim(batch) > 0 else batch
            member = eqx.tree_at(_where(member, name), member, jnp.asarray(value))
        check_material(member, f"ensemble member {i}")


def _shard(tree, mesh):
    """The batched inputs laid over the mesh's "batch" axis: global arrays, each process filling the rows
    of its own devices (the mesh may span several processes, ``jax.distributed``; every process holds
    the same batch)."""
    sharding = NamedSharding(mesh, PartitionSpec("batch"))

    def put(a):
        if not mesh.is_multi_process or isinstance(a, jax.core.Tracer):
            return jax.device_put(a, sharding)
        host = np.asarray(a)
        return jax.make_array_from_callback(host.shape, sharding, lambda index: host[index])

    return jax.tree_util.tree_map(put, tree)


def _gathered(tree):
    """Every member's results on every process: arrays sharded over several processes' devices are
    gathered (``process_allgather``) into arrays on this process's default device; the rest as they are."""

    def get(a):
        if isinstance(a, jax.Array) and not a.is_fully_addressable:
            return jnp.asarray(multihost_utils.process_allgather(a, tiled=True))
        return a

    return jax.tree_util.tree_map(get, tree)


#: how the members on one device run: "auto" (by backend), "vmap" (batched) or "sequential" (one after another)
STRATEGIES = ("auto", "vmap", "sequential")

#: ``strategy="auto"`` on the CPU vmaps members together in chunks of about this many particles in all
#: (one member per chunk, i.e. "sequential", from this size on); benchmarks/ensemble_throughput.py
CPU_CHUNK_PARTICLES = 512


def plan(strategy: str, chunk: int | None, members: int, particles: int, platform: str) -> tuple[str, int | None]:
    """The ``(strategy, chunk)`` an ensemble of ``members`` members per device, each of ``particles``
    particles, runs with on a ``platform`` ("cpu", "gpu", ...) device: ``"auto"`` resolved (a GPU
    or any other accelerator: "vmap" of all members; the CPU: "vmap" in chunks of about
    :data:`CPU_CHUNK_PARTICLES` particles, "sequential" where a chunk would hold one member), and
    a chunk that holds every member dropped (None: all at once).

    Args:
        strategy: one of :data:`STRATEGIES`.
        chunk: members per vmapped chunk (only with "vmap"), or None.
        members: the number of members on each device (> 0).
        particles: particles per member.
        platform: the devices' platform, ``jax.Device.platform``.

    Returns:
        ``("vmap", chunk or None)`` or ``("sequential", None)``.
    """
    if strategy == "auto":
        if platform != "cpu":
            return "vmap", None
        chunk = max(1, CPU_CHUNK_PARTICLES // max(1, particles))
        strategy = "sequential" if chunk == 1 else "vmap"
    if strategy == "sequential":
        return strategy, None
    return strategy, None if chunk is None or chunk >= members else chunk


def ensemble(sim, state, dt, steps: int, save_every: int = 1, *, params: dict | None = None, states=None,
             save_particles: bool = False, devices=None, progress: bool | None = None, strategy: str = "auto",
             chunk: int | None = None, memory=None):
    """Run a batch of simulations at once, in one compiled program.

    When several devices are present the batch is split over as many of them as divide the batch
    size; on each device the members run as ``strategy`` says.  Every strategy gives the same
    numbers as separate :meth:`Simulation.run` calls.  Give ``params``, ``states`` or both; every
    batched input has the same leading (batch) size.

    Args:
        sim: the :class:`jaxmpm.Simulation` every member starts from.
        state: the initial :class:`jaxmpm.State` of every member (unless ``states`` is given).
        dt: the time step, > 0.
        steps: the number of steps, a multiple of ``save_every`` (>= 0).
        save_every: steps between saved frames, a positive integer (default 1).
        params: ``{name: batch}``, parameter names (see :func:`jaxmpm.set_params`: beta,
            alpha_g, alpha_p, E, nu, gravity, friction, ...) to arrays whose leading axis is the
            batch; each member is checked against the parameter's valid range, and a parameter
            that does not act in the model (a friction under a stick contact) is an error.  The
            density sets the masses at ``sim.init``, so it changes nothing from a given state: vary
            it through ``states`` (each member's state from ``sim.init`` of its density).
        states: a batched :class:`jaxmpm.State` (leading axis = batch) to vary the initial
            conditions instead of ``state``.
        save_particles: whether the histories keep the particle positions and velocities
            (default False).
        devices: the devices to shard the batch over; None (the default): ``jax.devices()``, which
            after ``jax.distributed.initialize`` holds every process's devices (each process then
            calls ``ensemble`` alike, and each gets every member's results).
        progress: True prints to stderr the compile time (``jaxmpm ensemble: 9 members x 400
            steps: compiling ... 3.1 s``; the program is compiled ahead of the run, the same
            program, so the same numbers) and then the run time; False prints nothing; None (the
            default): True when the call is interactive (stderr is a terminal, or a Jupyter
            kernel runs it).  Nothing is printed under ``jax.jit``/``grad``.
        strategy: how the members on a device run: ``"vmap"``: batched, one vmapped step for all
            (``chunk`` at a time if given; on the CPU outside a trace in ``sim.run``'s loop, vmapped, so
            that a new length compiles nothing); ``"sequential"``: one after another, each with the
            single-run step (on the CPU as fast per member as a single run; there, outside a trace,
            each member is a ``sim.run`` and a new length compiles nothing; else ``lax.map``); or
            ``"auto"`` (default): "vmap" on a GPU, on the CPU "sequential" but for small scenes,
            vmapped in chunks of about ``CPU_CHUNK_PARTICLES`` (512) particles (:func:`plan`).
        chunk: with ``strategy="vmap"``: members vmapped together, chunks one after another (fewer
            members' arrays in memory at once); None (default): all members of a device at once.
        memory: for gradients through the ensemble (``jax.grad`` of a loss of its results): the
            reverse-mode budget of a device's members together, bytes or a string such as
            ``"4 GiB"``; each member's rollout picks its schedule (``checkpoint="auto"`` of
            :meth:`Simulation.run`, :func:`jaxmpm.gradient_schedule`) from an even share of it.
            None (default): half the device's free memory.  The forward run is the same either way.

    Returns:
        ``(final_states, histories, failure_steps)``; ``failure_steps[b]`` is the first unstable
        step of member b, -1 if none.
    """
    check(params is not None or states is not None, "ensemble: give params={name: batch} and/or states=batch")
    check(params is None or isinstance(params, dict), "ensemble: params must be a dict {name: batch}")
    steps = positive_int("ensemble", "steps", steps, low=0)
    save_every = positive_int("ensemble", "save_every", save_every)
    POSITIVE.real("ensemble", "dt", dt, fix="the time step, e.g. a scene's setup.dt")  # one number (traced: passes)
    show = shown(progress, "ensemble")
    check(strategy in STRATEGIES, f"ensemble: strategy = {strategy!r}; choose one of {', '.join(STRATEGIES)}")
    if chunk is not None:
        check(strategy == "vmap", f"ensemble: chunk = {chunk!r} applies to strategy='vmap' only; drop chunk or set "
                                  "strategy='vmap'")
        chunk = positive_int("ensemble", "chunk", chunk)
    members = _members_model(sim, params or {})
    _check_members(members, params or {}, own_states=states is not None)
    # a list of numbers is a batch too (its own leaves would be taken for members' scalars)
    params = None if params is None else {name: np.asarray(values) if isinstance(values, (list, tuple)) else values
                                          for name, values in params.items()}
    for name, values in (params or {}).items():
        check(np.ndim(values) > 0, f"ensemble: params[{name!r}] = {values!r} is one value; params hold one value per "
                                   f"member (an array whose leading axis is the batch); to set {name} for every "
                                   f"member, pass jm.set_params(sim, {name}=...) as the model")
    check(isinstance(state, State), f"ensemble: state = {type(state).__name__}; give the members' initial jm.State "
                                    "(the template of states=, when given)")
    members.check_state(state, "ensemble")
    check(states is None or isinstance(states, State),
          f"ensemble: states = {type(states).__name__}; give a jm.State whose arrays have a leading batch axis, "
          "e.g. jax.tree_util.tree_map(lambda a: jnp.stack([a, a]), state)")
    batch = _batch_size((params or {}, states))
    if states is not None:  # the template's arrays, each with a leading batch axis (an unbatched state had been
        # taken as a batch along its particles, then raised IndexError)
        for (path, one), many in zip(jax.tree_util.tree_flatten_with_path(state)[0],
                                     jax.tree_util.tree_leaves(states)):
            if np.shape(many) != (batch,) + np.shape(one):
                found = ("the template state's shape, with no batch axis" if np.shape(many) == np.shape(one)
                         else f"shape {np.shape(many)}, where the template state's is {np.shape(one)}")
                check(False, f"ensemble: states{jax.tree_util.keystr(path)} has {found}: states= holds the members' "
                             "states along a leading batch axis, shape (members, *the template's shape), e.g. "
                             "jax.tree_util.tree_map(lambda a: jnp.stack([a, a]), state)")
    if steps % save_every:
        check(False, f"ensemble: steps = {steps} must be a multiple of save_every = {save_every}")
    frames = steps // save_every
    parse_memory(memory)  # a bad budget is an error here, not inside the trace

    dt = jnp.asarray(dt, state.x.dtype)
    devices = jax.devices() if devices is None else device_list("ensemble", devices)
    used = max(d for d in range(1, len(devices) + 1) if batch % d == 0)
    inputs = (params or None, states)
    mesh = Mesh(np.asarray(devices[:used]), ("batch",)) if used > 1 else None
    if mesh is not None:
        inputs = _shard(inputs, mesh)
    how = plan(strategy, chunk, batch // used, int(state.x.shape[0]), devices[0].platform)
    what = f"jaxmpm ensemble: {batch} members x {steps} steps"
    if mesh is None and _runtime_counts(sim, (state, *inputs)):  # one compiled loop for any length
        if how[0] == "sequential":
            return _one_by_one(sim, state, dt, frames, save_every, save_particles, params or {}, states, batch, what,
                               show)
        return _vmapped_at_once(sim, state, dt, frames, save_every, save_particles, how[1], *inputs, batch, what,
                                show)
    out = shown_call(_batched_rollout, (sim, state, dt, frames, save_every, save_particles, *how, mesh, memory,
                                        *inputs), what, show)
    return _gathered(out) if mesh is not None and mesh.is_multi_process else out


def _runtime_counts(sim, inputs) -> bool:
    """Whether the members run in a compiled loop whose frame and step counts are runtime values (sequential
    members: one call of ``sim.run``'s loop each, :func:`_one_by_one`; vmapped ones: :func:`_vmapped_at_once`):
    outside any trace, where the backend runs with runtime counts (``RUNTIME_COUNTS``, the CPU)."""
    return not _is_traced((sim, inputs)) and RUNTIME_COUNTS[resolve(sim.backend)]


def _one_by_one(sim, state, dt, frames: int, save_every: int, save_particles: bool, params: dict, states, batch: int,
                what: str, show: bool):
    """The members one after another, each a single run outside any trace (:func:`jaxmpm.run.driver._run_at_once`):
    the compiled loop of ``sim.run``, whose frame and step counts are runtime values, so an ensemble of another
    length compiles nothing, nor one of a model ``sim.run`` has run already; each member at a single run's speed,
    the same numbers as :func:`_batched_rollout`'s ``lax.map`` bit for bit (tests/test_ensemble_strategies.py).
    Returns what :func:`_batched_rollout` returns."""
    host_states = None if states is None else jax.device_get(states)
    first = state if host_states is None else jax.tree_util.tree_map(lambda a: a[0], host_states)  # on the host
    dtype = first.x.dtype  # the members' precision (a model computes in its state's, as Simulation.rollout does)
    sim = sim.in_precision(dtype)
    dt = jax.device_put(np.asarray(jax.device_get(dt), dtype))
    sim = _members_model(sim, params)  # a term the model lacks added once, not per member
    names = list(params)
    wheres = [_where(sim, name) for name in names]
    # every member's values on the device in one transfer, cast as set_params casts them (checked: _check_members)
    host = [np.asarray(jax.device_get(params[name]), jnp.result_type(where(sim))) for name, where in
            zip(names, wheres)]
    values = jax.device_put([[a[i] for a in host] for i in range(batch)]) if names else None
    frame_bytes = _frame_bytes(sim, first, save_particles)

    def member(i):
        """(the member's model, its initial state, whether the run may compute in place of that state)"""
        member_sim = eqx.tree_at(lambda m: [where(m) for where in wheres], sim, values[i]) if names else sim
        if host_states is None:
            return member_sim, state, False
        return member_sim, jax.tree_util.tree_map(lambda a: to_device(np.asarray(a[i])), host_states), True

    if show:  # the loop compiled (or found compiled) by a run of no steps: the compilation timed apart
        member_sim, member_state, _ = member(0)
        with Stage(f"{what}: compiling", True):
            jax.block_until_ready(_run_at_once(member_sim, member_state, dt, 0, save_every, save_particles, (), False,
                                               frame_bytes))
    finals, histories, failures = [], [], []
    with Stage(f"{what}: running", show):
        for i in range(batch):
            member_sim, member_state, own = member(i)
            final, history, failure = _run_at_once(member_sim, member_state, dt, frames, save_every, save_particles,
                                                   (), own, frame_bytes, on_host=True)
            finals.append(final)
            histories.append(history)
            failures.append(failure.step)
        finals, histories, failures = jax.device_get((finals, histories, failures))
    stacked = jax.tree_util.tree_map(lambda *a: np.stack(a), *finals), \
        jax.tree_util.tree_map(lambda *a: np.stack(a), *histories), np.asarray(failures, np.int32)
    return jax.tree_util.tree_map(to_device, stacked)


def _vmapped_at_once(sim, state, dt, frames: int, save_every: int, save_particles: bool, chunk, params, states,
                     batch: int, what: str, show: bool):
    """Vmapped members outside any trace, in :func:`_advance_members`' compiled loop: the run loop of ``sim.run``
    (:func:`jaxmpm.run.driver._run_at_once`) over all members at once (``chunk`` at a time, if given), its frame
    and step counts runtime values, so that an ensemble of another length or ``save_every`` compiles nothing
    (the static scans of :func:`_batched_rollout` compiled 0.7 s again for the bar's).  The arithmetic is
    :func:`_batched_rollout`'s, and so is what it returns; the frames' sums over the particles may add in another
    order (the bar's momentum: 2e-16 apart; tests/test_recompiles.py)."""
    dtype = state.x.dtype if states is None else states.x.dtype
    sim = sim.in_precision(dtype)  # the model computes in its members' precision, as Simulation.rollout does
    dt = jnp.asarray(dt, dtype)
    first = state if states is None else jax.tree_util.tree_map(lambda a: a[0], states)
    with members_at_once(chunk or batch):  # a frame's shapes, traced as its members' steps will be
        capacity = _buffer_frames(batch * _frame_bytes(sim, first, save_particles))
    no_steps, per_frame, *calls = _device_ints(0, save_every, *_frames_per_call(frames, capacity))
    moving = _members_start(state, states, batch)
    options = lambda call, count: (sim, params, dt, count, per_frame, capacity, save_particles,  # noqa: E731
                                   no_steps if call == 0 else per_frame, chunk)
    if show:  # compiled ahead of the run (a run of no steps), the compilation timed apart
        with Stage(f"{what}: compiling", True):
            _advance_members.lower(options(0, calls[0]), moving).compile()
    buffers = []
    with Stage(f"{what}: running", show):
        for call, count in enumerate(calls):
            moving, buffer = _advance_members(options(call, count), moving)
            buffers.append(buffer)
        # joined on the host along each member's frame axis (on the device each new length would compile its slices)
        histories = jax.tree_util.tree_map(lambda *b: _joined(np, b, frames, axis=1), *jax.device_get(buffers))
        finals, failed = jax.block_until_ready(moving)
    return finals, jax.device_put(histories), failed


@eqx.filter_jit
def _members_start(state, states, batch: int):
    """The members' initial states and first unstable steps (none yet: -1), stacked: ``states``, or ``batch``
    copies of ``state``."""
    if states is None:
        states = jax.tree_util.tree_map(lambda a: jnp.broadcast_to(a, (batch,) + a.shape), state)
    else:  # a copy, never the caller's arrays passed through: the run loop computes in place of these (donated)
        states = jax.tree_util.tree_map(jnp.copy, states)
    return states, jnp.full((batch,), -1, jnp.int32)


@functools.partial(eqx.filter_jit, donate="all-except-first")
def _advance_members(options, moving):
    """:func:`jaxmpm.run.driver._advance` of every member, vmapped (``chunk`` members at a time, else all): the
    members' states and first unstable steps ``moving`` (donated: computed in place) advanced by ``n_frames`` frames,
    and a buffer of ``capacity`` frames per member (leading axis: the members)."""
    sim, params, dt, n_frames, per_frame, capacity, save_particles, first_steps, chunk = options
    states, failed = moving

    def member(p, s, failed):
        member_sim = (set_params(sim, **p) if p else sim).in_precision(s.x.dtype)
        # the first unstable step is what the members return (as _batched_rollout's do), and all a call needs from
        # the call before: a failure's cause and particle start anew each call
        failure = Failure(failed, jnp.zeros_like(failed), jnp.full_like(failed, -1))
        s, failure, buffer = _advance(member_sim, s, failure, dt, n_frames, per_frame, capacity, save_particles,
                                      False, (), first_steps)
        return (s, failure.step), buffer

    batch = int(states.x.shape[0])
    with members_at_once(chunk or batch):  # the members stepped at once share the device's memory
        if chunk is None:
            return jax.vmap(member, in_axes=(0 if params else None, 0, 0))(params, states, failed)
        return jax.lax.map(lambda a: member(*a), (params, states, failed), batch_size=chunk)


@eqx.filter_jit
def _batched_rollout(sim, state, dt, frames, save_every, save_particles, strategy, chunk, mesh, memory, params,
                     states):
    """Every member's rollout, as :func:`plan` resolved ``strategy`` and ``chunk``, in each device's
    share of the batch (``mesh``: a ``shard_map`` over its "batch" axis; None: one device); a
    module-level filter_jit, so repeated calls reuse the compilation.  Reverse mode: each member's
    schedule is chosen (when traced) from its share of the device's budget ``memory``."""

    def members(sim, state, dt, params, states):
        share = max(1, budget_bytes(memory) // _batch_size((params, states)))

        def member(p, s):
            member_sim = set_params(sim, **p) if p else sim
            final, hist, failure = member_sim.rollout(state if s is None else s, dt, frames, save_every,
                                                      save_particles, checkpoint="auto", memory=share)
            return final, hist, failure.step

        # the members stepped at once share the device's memory when their steps decide whether they fit
        if strategy == "vmap" and chunk is None:
            in_axes = (0 if params else None, 0 if states is not None else None)
            with members_at_once(_batch_size((params, states))):
                return jax.vmap(member, in_axes=in_axes)(params, states)
        # scanned over the members: one compiled member (or chunk of members), its inputs sliced per iteration
        with members_at_once(chunk or 1):
            return jax.lax.map(lambda ps: member(*ps), (params, states), batch_size=chunk)

    if mesh is None:
        return members(sim, state, dt, params, states)
    dynamic, static = eqx.partition(sim, eqx.is_array)
    each, batched = PartitionSpec(), PartitionSpec("batch")

    def local(dynamic, state, dt, params, states):
        return members(eqx.combine(dynamic, static), state, dt, params, states)

    return jax.shard_map(local, mesh=mesh, in_specs=(each, each, each, batched, batched), out_specs=batched,
                         check_vma=False)(dynamic, state, dt, params, states)
