"""The driver: running a model.  ``rollout`` is the pure ``lax.scan`` of steps and saved frames
(with rematerialisation for reverse-mode gradients); ``run`` adds the eager conveniences --
a CFL warning, instability detection that names the first bad step, chunked HDF5 writing and a
progress bar.  ``Simulation.run`` and ``Simulation.rollout`` call these."""

from __future__ import annotations

import contextlib
import functools
import math
import os
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..core.errors import InstabilityError, ParticlesLeftGrid, check
from ..core.limits import require_memory, require_steps
from ..core.state import State
from ..core.validate import POSITIVE, positive_int
from ..core.warn import warn
from ..transfer.backend import RUNTIME_COUNTS, resolve
from .collector import with_fewer_collections
from .memory import _segment_length, choose_checkpoint, is_schedule, parse_memory, tree_bytes  # noqa: F401  (_segment_length: tests)

CAUSES = {
    1: "NaN or Inf in the particle state",
    2: "J = det F <= 0 (a particle inverted)",
    3: "particles left the grid",
    4: "a particle left the grid moving more than a cell a step (|V| dt > h, which no stable step allows): the "
       "step blew up, or dt exceeds the CFL limit; not a grid too small",
}


class StableTimeStepWarning(UserWarning):
    """dt exceeds the CFL limit h / max(c + |V|) or a term's limit (conduction, diffusion)."""


class History(eqx.Module):
    """Saved frames (leading axis T): time, particle x/v (None if not saved), energies, momenta,
    the per-particle fields the terms declare and those the run chose (``fields``: stress,
    pressure, J, F, ..., see :mod:`jaxmpm.model.frame_fields`; empty if particles are not saved) and,
    in multimaterial mode, per-material sums (``by_material``: kinetic, strain, momentum,
    contact_force), and the model's totals (``totals``: thermal energy, solute, a material's
    dissipated energy).  Runs build it
    (``Simulation.diagnostics_frame``); :func:`jaxmpm.save_h5` writes one, and :func:`jaxmpm.load_h5`
    reads the file back as a :class:`jaxmpm.io.hdf5.Results` mapping (``res["particles/x"]``), not a History.

    Args:
        time: the frames' times, (T,).
        x: particle positions (T, N, D), or None when particles are not saved.
        v: particle velocities (T, N, D), or None.
        kinetic: kinetic energy (T,).
        strain: strain energy (T,).
        dissipated: the cumulative energy dissipated by the scheme and damping (T,).
        momentum: linear momentum (T, D).
        angular: angular momentum (T, 1) in 1D and 2D, (T, 3) in 3D (the scheme's, APIC's
            affine term included).
        fields: saved per-particle fields ``{name: (T, N, ...)}``, the terms' and those chosen;
            default ``{}``.
        by_material: multimaterial mode: per-material kinetic and strain energy (T, M), momentum
            and contact force (T, M, D); default ``{}``.
        totals: the model's totals ``{name: (T,)}`` (thermal_energy of jm.Heat, solute of
            jm.Diffusion, viscous_dissipation of jm.NewtonianFluid: ``Simulation.totals``); default ``{}``.
    """

    time: jnp.ndarray
    x: jnp.ndarray | None
    v: jnp.ndarray | None
    kinetic: jnp.ndarray
    strain: jnp.ndarray
    dissipated: jnp.ndarray
    momentum: jnp.ndarray
    angular: jnp.ndarray
    fields: dict = eqx.field(default_factory=dict)  # saved per-particle fields, the terms' and chosen, (T, N, ...)
    # multimaterial mode: per-material kinetic, strain (T, M), momentum and contact force (T, M, D)
    by_material: dict = eqx.field(default_factory=dict)
    # the model's totals (T,): thermal_energy (jm.Heat), solute (jm.Diffusion), the material's (Material.totals)
    totals: dict = eqx.field(default_factory=dict)

    @property
    def total_energy(self):
        return self.kinetic + self.strain

    def __len__(self):
        return int(self.time.shape[0])


class Failure(eqx.Module):
    """First failing step (-1 if none), cause code (see CAUSES) and the offending particle."""

    step: jnp.ndarray
    cause: jnp.ndarray
    particle: jnp.ndarray


def _is_traced(tree) -> bool:
    """Whether ``tree`` holds a traced array, or JAX is tracing at all: a function of closed-over arrays under
    ``jax.jit`` or ``jax.eval_shape`` gets no traced argument, but what it puts on the device is traced (a run
    outside a trace reads values back to the host, which a trace cannot)."""
    return (any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree_util.tree_leaves(tree))
            or isinstance(jax.device_put(np.int32(0)), jax.core.Tracer))


def check_state(state) -> None:
    """A state whose float arrays mix precisions is rejected with the dtypes and the fix (a model
    of another precision than its state is cast on entry: ``Simulation.step``)."""
    floats = {jnp.result_type(leaf) for leaf in jax.tree_util.tree_leaves(state)}
    if len({t for t in floats if jnp.issubdtype(t, jnp.floating)}) == 1:  # one precision: nothing to name
        return
    dtypes = {}
    for path, leaf in jax.tree_util.tree_flatten_with_path(state)[0]:  # the core, scheme, material, fields
        if jnp.issubdtype(jnp.result_type(leaf), jnp.floating):
            name = jax.tree_util.keystr(path).lstrip(".")
            dtypes.setdefault(str(jnp.result_type(leaf)), []).append(name)
    check(len(dtypes) == 1,
          "State mixes float precisions (" + "; ".join(f"{k}: {', '.join(v)}" for k, v in dtypes.items())
          + "); cast it to one dtype first, e.g. jm.scenes.cast_state(state, jnp.float32)")


@with_fewer_collections
def rollout(sim, state: State, dt, frames: int, save_every: int = 1, save_particles: bool = True,
            checkpoint="auto", history_gradients: bool = True, fields: tuple = (), memory=None):
    """Pure ``lax.scan`` rollout of ``frames * save_every`` steps.  Returns
    ``(final_state, history, failure)``; ``history`` holds the initial frame and one frame
    every ``save_every`` steps (``frames + 1`` in all), each with the per-particle ``fields``
    chosen by name (``("stress", "pressure", "J", "F")``, :mod:`jaxmpm.model.frame_fields`) in
    ``history.fields``.

    ``checkpoint`` (reverse mode only; the forward pass is unchanged):

    * ``"auto"`` (default): one of the four below, chosen at trace time from the budget
      ``memory`` (bytes or a string such as ``"4 GiB"``; default half the device's free memory)
      and the backend's measured preference (:mod:`jaxmpm.run.memory`): on the CPU ``"states"``
      unless every step's state outgrows the budget, or 16 MiB in 1D (then ``True``, then
      ``"low_memory"``); on a GPU ``False`` where every step's residuals fit in 64 MiB and the
      budget, else as on the CPU.
    * ``"states"``: one level.  The forward pass keeps every step's state (T states); the backward
      pass recomputes each step once for its pullback: one forward run fewer than ``True`` (on
      the CPU gradient / forward 3.0-6.8 against 3.9-7.4, benchmarks/gradient_cost.py).
    * ``True``: two levels.  The forward pass keeps the state at the start of every
      segment of L steps (L a divisor of ``save_every``, chosen to minimise the states kept,
      frames * save_every / L + L: about 2 sqrt(T) for T steps); the backward pass recomputes
      each segment once, keeping its L step states, and each step once more for its pullback.
    * ``"low_memory"``: three levels (frames, segments of about sqrt(save_every) steps, steps):
      about frames + 2 sqrt(save_every) states, at the price of a third recomputation (on the
      CPU 2-40% slower than ``True``, benchmarks/gradient_cost.py).
    * an int: two levels with that segment length (a divisor of ``save_every``).
    * ``False``: no rematerialisation; every intermediate of every step is stored (on the CPU
      slower than ``True`` in every case measured, benchmarks/gradient_memory.py: the stacked
      residual buffers cost more than recomputing).

    ``history_gradients=False`` makes the saved frames constants to autodiff (``stop_gradient``):
    a loss of the final state alone then carries no pullback of the diagnostics, and no frame
    holds residuals.  The instability record is never differentiated (its outputs are integers).
    """
    frames = positive_int("rollout", "frames", frames, low=0)  # a Python int: it fixes the scans' lengths
    save_every = positive_int("rollout", "save_every", save_every)
    final, later, failure, frame = _later_frames(sim, state, dt, frames, save_every, save_particles, checkpoint,
                                                 history_gradients, fields, memory)
    history = jax.tree_util.tree_map(lambda a, b: jnp.concatenate([a[None], b]), frame(state), later)
    return final, history, failure


def _later_frames(sim, state: State, dt, frames: int, save_every: int, save_particles: bool, checkpoint,
                  history_gradients: bool, fields: tuple, memory):
    """:func:`rollout` without its initial frame: (final state, the ``frames`` frames after the initial one,
    failure record, the frame of a state)."""
    sim = sim.in_precision(state.x.dtype)  # the model computes in its state's precision
    fields = _chosen_fields(sim, state, fields, save_particles)
    dt = jnp.asarray(dt, state.x.dtype)
    none = Failure(jnp.array(-1, jnp.int32), jnp.array(0, jnp.int32), jnp.array(-1, jnp.int32))
    if is_schedule(checkpoint, "auto"):
        checkpoint, _ = choose_checkpoint(sim, state, dt, frames, save_every, memory)
    segment = _segment_length(save_every, checkpoint, frames)
    kept = lambda f: f  # noqa: E731  (a level whose states are kept by the scan, not recomputed)
    remat = kept if segment is None else jax.checkpoint
    remat_segments = kept if is_schedule(checkpoint, "states") else remat  # one level: every step's state kept
    remat_frames = jax.checkpoint if is_schedule(checkpoint, "low_memory") else kept

    sorting = sim.sorting(state)  # particles sorted by cell every K steps, or None (jaxmpm.run.sorting)
    advance = _stepper(sim, sorting, dt)

    @remat
    def one_step(carry, _):
        return advance(carry), None

    seg_len = save_every if segment is None else segment

    @remat_segments
    def one_segment(carry, _):
        carry, _ = jax.lax.scan(one_step, carry, None, length=seg_len)
        return carry, None

    def frame(s):
        return sim.diagnostics_frame(s if history_gradients else jax.lax.stop_gradient(s), save_particles, fields)

    @remat_frames
    def one_frame(carry, _):
        carry, _ = jax.lax.scan(one_segment, carry, None, length=save_every // seg_len)
        return carry, frame(_in_user_order(sorting, carry))

    start = (state, none, None if sorting is None else sorting.start(state))
    carry, frames_hist = jax.lax.scan(one_frame, start, None, length=frames)
    return _in_user_order(sorting, carry), frames_hist, carry[1], frame


@with_fewer_collections
def run(
    sim,
    state: State,
    dt,
    steps: int,
    save_every: int = 1,
    *,
    save_particles: bool = True,
    check_stability: bool = True,
    progress: bool = False,
    writer=None,
    frames_per_chunk: int | None = None,
    checkpoint="auto",
    memory=None,
    history_gradients: bool = True,
    start_step: int | None = None,
    fields: tuple | None = None,
    timings: dict | None = None,
    donate: bool = False,
):
    """Run ``steps`` steps, saving a frame every ``save_every`` steps (plus the initial frame).

    Returns ``(final_state, history)``.  Traceable: under ``jax.grad``/``vmap``/``jit`` it is a
    single ``lax.scan`` (:func:`rollout`, static lengths).  Called eagerly it runs one compiled loop whose
    frame and step counts are runtime values (:func:`_run_at_once`: a new ``steps`` or ``save_every``
    compiles nothing), refuses a state that is unstable before its first step (NaN, det F <= 0, a particle
    off the grid: an InputError), warns when ``dt`` exceeds the CFL limit and raises
    :class:`InstabilityError` naming the first bad step, its particle and cause, with the frames saved
    before it as ``error.history`` where no writer holds them (``check_stability=False``: neither check,
    every frame returned).  With ``writer`` (a
    :class:`jaxmpm.H5Writer`) or ``progress=True`` it runs in chunks of ``frames_per_chunk``
    frames, writing/reporting each before the next, and returns ``(final_state, None)`` when
    a writer holds the frames.  ``checkpoint`` controls rematerialisation for reverse-mode
    gradients (by default chosen from the memory budget ``memory``) and ``history_gradients=False``
    makes the saved frames constants to autodiff (see :func:`rollout`); neither changes the forward
    results.

    Chunks are sized by wall time (about :data:`CHUNK_SECONDS`); ``frames_per_chunk`` caps them.
    A writer's file receives every chunk's frames with the state reached, so that whatever stops
    the run, even a kill, :func:`jaxmpm.resume` continues it from its last chunk.  SIGINT (Ctrl-C)
    or SIGTERM stops a chunked run at the next chunk boundary and raises :class:`RunInterrupted`.
    ``start_step`` (resume) is the step of the run's first frame when ``state`` is part-way
    through it.  Before anything runs, the step count and the memory the saved frames need are
    checked (:mod:`jaxmpm.core.limits`).  A chunked run compiles its loop before the first step
    (the progress bar says "compiling" meanwhile, so that its rate and ETA are the steps' alone)
    and, when the rest of the run will take more than :data:`LONG_RUN_SECONDS`, prints one line to
    stderr saying how long.  Every run outside a trace fills ``timings`` (a dict, if given) with the
    seconds spent compiling (``compile``; in a run of one call, what JAX reports compiling during it:
    0 when its program was compiled before) and running (``run``), and the ``steps`` run.

    ``fields``: the per-particle fields each frame holds besides x, v and the terms' fields,
    by name (``("stress", "pressure", "J", "F")``, :mod:`jaxmpm.model.frame_fields`; only
    these are computed); with a writer, the writer's (``jm.H5Writer(..., fields=...)``).

    ``donate=True`` hands ``state``'s device memory to the run (JAX's buffer donation): the final state
    is computed in place of the initial one, so a run holds one state fewer (the measure of
    ``benchmarks/gpu.py``'s program bytes), and ``state``'s arrays are deleted (using them again raises
    JAX's "Array has been deleted").  Under ``jit``/``grad``/``vmap`` it does nothing: the enclosing
    program owns the buffers.  A chunked run (a writer or progress) computes each chunk in place of the
    state before it in any case, after copying ``state`` once unless it is donated.
    """
    check(isinstance(steps, (int, np.integer)) and steps >= 0, f"run: steps = {steps!r} must be a non-negative integer")
    check(isinstance(save_every, (int, np.integer)) and save_every >= 1,
          f"run: save_every = {save_every!r} must be a positive integer")
    check(steps % save_every == 0,
          f"run: steps = {steps} is not a multiple of save_every = {save_every}; "
          f"use steps = {math.ceil(steps / save_every) * save_every}")
    check(isinstance(history_gradients, bool),
          f"run: history_gradients = {history_gradients!r} must be True (frames carry gradients) or False")
    check(isinstance(donate, bool),
          f"run: donate = {donate!r} must be True (the run may reuse the state's memory; the state is deleted) "
          "or False")
    if frames_per_chunk is not None:  # a negative cap ran a chunk of negative frames until memory ran out
        frames_per_chunk = positive_int("run", "frames_per_chunk", frames_per_chunk,
                                        fix="give a positive number of frames, or None (chunks of about 2 s)")
    frames = steps // save_every
    parse_memory(memory)  # checked before anything runs
    POSITIVE.real("run", "dt", dt, fix="the time step, e.g. a scene's setup.dt or sim.stable_dt(state)")
    sim.check_state(state, "run")  # a jm.State, made for this model
    check_state(state)
    check(start_step is None or writer is not None or progress,
          "run: start_step continues a chunked run; pass writer=... (see jaxmpm.resume)")
    sim = sim.in_precision(state.x.dtype)  # the model computes in its state's precision
    if writer is not None:
        held = tuple(getattr(writer, "fields", ()))
        check(fields is None or _chosen_fields(sim, state, fields, save_particles) == held,
              f"run: fields = {fields!r} but the writer saves {held!r}; choose them once, on the writer "
              "(jm.H5Writer(..., fields=...))")
        fields = held
    fields = _chosen_fields(sim, state, () if fields is None else fields, save_particles)
    traced = _is_traced((sim, state, dt))
    # an array, so a new dt value does not recompile; a number put on the device as it is (jnp.asarray
    # compiles a conversion program for it, the first time in a process)
    dtype = state.x.dtype
    dt = jax.device_put(np.asarray(dt, dtype)) if isinstance(dt, (int, float)) else jnp.asarray(dt, dtype)
    if not traced:
        dtc = float(np.asarray(dt))
        check(math.isfinite(dtc) and dtc > 0, f"run: dt = {dtc} must be a positive number")
        limits = {name: float(value) for name, value in sim.time_step_limits(state).items()}
        name = min(limits, key=limits.get)
        limit = limits[name]
        if dtc > limit:
            material, scheme = type(sim.material).__name__, type(sim.scheme).__name__
            what = ("h / max(c + |V|)" if name == "CFL" else f"{material}'s own limit, Material.time_step_limit"
                    if name == material.lower() else f"{scheme}'s limit, h / max(c + |V|) times "
                    f"{sim.scheme.time_step_factor():.4g} (Scheme.time_step_factor)" if name == scheme.lower()
                    else f"the {name} term's limit h^2 / (2 D k / (rho C_p))")
            warn(f"dt = {dtc:.6g} exceeds the stable limit {limit:.6g} (= {what}); "
                 f"use dt <= {0.5 * limit:.6g} (CFL 0.5) to stay stable", StableTimeStepWarning)
        if check_stability:  # check_stability=False: neither the start nor the steps
            _check_start(sim, state)
        first = int(state.step) if start_step is None else int(start_step)
        require_steps(first + steps, "shorten t_end, use a larger dt, or split the run")
        frame_bytes = _require_frame_memory(sim, state, frames, save_particles, writer is None, fields)
    if donate and not traced:
        state = _unshared(state)  # a buffer two leaves hold can be donated once only
    if traced:  # differentiated or staged: scans of static lengths (reverse mode needs them)
        # it cannot raise here (nor call back to the host: a program with a host callback is never kept in
        # the persistent compilation cache); jm.calibrate runs its loss once more outside the trace instead
        final, history, _ = _jit_rollout(sim, state, dt, frames, save_every, save_particles, checkpoint,
                                         history_gradients, fields, memory)
        return final, history
    if writer is None and not progress:
        with _plain_timings(timings, steps) as timed:
            final, history = _run_plain(sim, state, dt, frames, save_every, save_particles, checkpoint,
                                        history_gradients, fields, memory, donate, frame_bytes, check_stability)
            timed((final, history))
        return final, history
    return _run_chunked(sim, state, dt, frames, save_every, save_particles, check_stability,
                        progress, writer, frames_per_chunk, checkpoint, start_step, fields, timings, donate)


def _run_plain(sim, state, dt, frames, save_every, save_particles, checkpoint, history_gradients, fields, memory,
               donate, frame_bytes, check_stability):
    """A run in one call (no writer, no progress bar): :func:`run`'s path outside a trace."""
    start = _start_of(state)  # read before the run deletes the state (donation)
    if RUNTIME_COUNTS[resolve(sim.backend)]:  # one compiled loop for any length (backend tuning)
        if not is_schedule(checkpoint, "auto"):
            _segment_length(save_every, checkpoint, frames)  # validated; a run outside a trace is forward only
        final, history, failure = _run_at_once(sim, state, dt, frames, save_every, save_particles, fields,
                                               donate, frame_bytes)
    elif not donate:
        final, history, failure = _jit_rollout(sim, state, dt, frames, save_every, save_particles, checkpoint,
                                               history_gradients, fields, memory)
    else:  # the initial frame first, in a program of its own (_later_frames)
        first = _jit_first_frame(sim, state, save_particles, fields)
        final, later, failure = _jit_rollout_in_place(
            (sim, dt, frames, save_every, save_particles, checkpoint, history_gradients, fields, memory), state)
        history = _jit_joined(first, later)
    if check_stability and int(failure.step) >= 0:
        kept = _frames_before(history, int(start.step), save_every, int(failure.step))
        _raise_if_failed(failure, dt, start, None, sim.grid, kept)
    return final, history


#: the events in which JAX reports the seconds a compilation took: tracing, lowering, XLA (jax.monitoring)
_COMPILE_EVENTS = ("/jax/core/compile/jaxpr_trace_duration", "/jax/core/compile/jaxpr_to_mlir_module_duration",
                   "/jax/core/compile/backend_compile_duration")


@contextlib.contextmanager
def _plain_timings(timings: dict | None, steps: int):
    """For a run in one call, fill ``timings`` (if a dict) as a chunked run does: ``compile``, the seconds
    JAX reported compiling in the call (``jax.monitoring``'s compile events; 0 when the program was
    compiled before), ``run`` the rest of the call's wall time, and ``steps``.  Yields a function to call
    with the results, which waits for them."""
    import time

    if timings is None:
        yield lambda results: None
        return
    compiled = []

    def listen(event: str, seconds: float, **_) -> None:
        if event in _COMPILE_EVENTS:
            compiled.append(seconds)

    def timed(results) -> None:
        jax.block_until_ready(results)
        wall = time.perf_counter() - tic
        compile_s = min(float(sum(compiled)), wall)
        timings.update(compile=compile_s, run=wall - compile_s, steps=steps)

    jax.monitoring.register_event_duration_secs_listener(listen)
    tic = time.perf_counter()
    try:
        yield timed
    finally:
        jax.monitoring.unregister_event_duration_listener(listen)


#: Frames a run's compiled loop (:func:`_advance`) fills per call, at most (fewer where they would take more than
#: ``_CHUNK_BYTES``): a number that does not depend on the run's length, so that a run of another length or
#: ``save_every`` calls the same compiled loop
_BUFFER_FRAMES = 256


def _buffer_frames(frame_bytes: int, frames_per_chunk=None) -> int:
    """The frames of the buffer a run's loop fills per call (:data:`_BUFFER_FRAMES`, ``_CHUNK_BYTES``)."""
    return max(1, min(frames_per_chunk or _BUFFER_FRAMES, _CHUNK_BYTES // max(1, frame_bytes)))


def _run_at_once(sim, state, dt, frames, save_every, save_particles, fields, donate, frame_bytes: int,
                 on_host: bool = False):
    """A run outside any trace, without a writer or progress: (final state, history, failure record).

    The chunked runner's compiled loop (:func:`_advance`, its frame and step counts runtime values) is called until
    the run's frames are done, each call filling a buffer of :func:`_buffer_frames` frames, the first call's first
    frame the initial one (a frame of no steps); the buffers are joined on the host where the history is small,
    else by one small program.  A run of another length or ``save_every`` compiles at most that join (until
    2026-11-29 each new step count compiled the whole rollout again: 0.45-1.2 s for bar, disks and mpm88).

    Each call computes in place of the state before it: the caller's, donated, or a copy (which a kept state needs
    in any case: the final state is another state).  The arithmetic is :func:`rollout`'s, bit for bit; the run goes
    on past an unstable step, as :func:`rollout` does, and the failure record names the first.  ``frame_bytes``:
    the bytes of a frame (:func:`_frame_bytes`); ``on_host``: a history joined on the host is handed back there,
    as NumPy arrays (an ensemble stacks its members' histories there)."""
    capacity = _buffer_frames(frame_bytes)
    no_steps, per_frame, *counts = _device_ints(0, save_every, *_frames_per_call(frames, capacity))
    failure = Failure(*_device_ints(-1, 0, -1))
    working = state if donate else _copied(state)
    buffers = []
    for call, count in enumerate(counts):
        working, failure, buffer = _advance_in_place(
            (sim, failure, dt, count, per_frame, capacity, save_particles, False, fields,
             no_steps if call == 0 else per_frame), working)
        buffers.append(buffer)
    if (frames + 1) * frame_bytes <= _CHUNK_BYTES:  # joined on the host: nothing compiled (device_put)
        history = jax.tree_util.tree_map(lambda *b: _joined(np, b, frames), *jax.device_get(buffers))
        if not on_host:
            history = jax.device_put(history)
    else:  # a large history stays on the device: one small program per length
        history = _jit_history(tuple(buffers), frames)
    return working, history, failure


def _frames_per_call(frames: int, capacity: int) -> list[int]:
    """The frames each call of a run's loop fills, ``capacity`` at most: a run's ``frames + 1``, the first call's
    first frame the initial one (a frame of no steps)."""
    return [min(capacity, frames + 1 - done) for done in range(0, frames + 1, capacity)]


@functools.lru_cache(maxsize=1024)
def _device_int(value: int, default_device) -> jax.Array:
    """``value`` as an int32 scalar on the default device (``default_device``, the setting it was put under: the
    cache's key)."""
    return jax.device_put(np.int32(value))


def _device_ints(*values: int) -> list:
    """``values`` as int32 scalars on the default device, each kept for later runs (putting five of them on the
    device took 0.2 ms a run); a run's loop reads them and never donates them."""
    return [_device_int(int(v), jax.config.jax_default_device) for v in values]


def _joined(xnp, buffers, frames: int, axis: int = 0):
    """The run's ``frames + 1`` frames, from the buffers of :func:`_run_at_once` (their frame axis ``axis``; 1 for a
    vmapped ensemble's members): every buffer's frames, the last one's only as many as are left."""
    capacity = buffers[0].shape[axis]
    last = buffers[-1][(slice(None),) * axis + (slice(0, frames + 1 - capacity * (len(buffers) - 1)),)]
    return xnp.concatenate([*buffers[:-1], last], axis=axis) if len(buffers) > 1 else last


def _chosen_fields(sim, state, fields, save_particles) -> tuple:
    """The chosen per-frame fields, checked; they are per particle, so they need the particles saved."""
    fields = sim.check_frame_fields(state, fields, "run: fields")
    check(save_particles or not fields, f"run: fields = {fields!r} are per-particle fields, saved with the "
                                        "particles; pass save_particles=True, or no fields")
    return fields


_FRAME_BYTES: dict = {}  # (the model's and state's structure, save_particles, fields) -> bytes of a frame


def _frame_bytes(sim, state, save_particles, fields=()) -> int:
    """The bytes of a frame of ``state`` (``sim.diagnostics_frame``'s shapes), kept per structure of the model and
    the state (tracing the frame took 3-7 ms a call; an ensemble or a run of a small scene takes about 10)."""
    leaves, treedef = jax.tree_util.tree_flatten((sim, state, save_particles, tuple(fields)))
    try:
        key = (treedef, tuple(jax.typeof(leaf) if isinstance(leaf, (jax.Array, np.ndarray)) else (type(leaf), leaf)
                              for leaf in leaves))
        hash(key)
    except TypeError:  # a static leaf without a hash (a function defined anew): not kept
        key = None
    if key is not None and key in _FRAME_BYTES:
        return _FRAME_BYTES[key]
    shape = jax.eval_shape(lambda s: sim.diagnostics_frame(s, save_particles, fields), state)
    if key is not None:
        if len(_FRAME_BYTES) >= 64:
            _FRAME_BYTES.clear()
        _FRAME_BYTES[key] = tree_bytes(shape)
    return tree_bytes(shape)


def _require_frame_memory(sim, state, frames, save_particles, in_memory, fields=()):
    """The saved frames (all of them when kept in memory, twice: the device result and the
    concatenated history) plus the state and its step temporaries, before the run starts; returns the
    bytes of a frame."""
    state_bytes = tree_bytes(state)
    frame_bytes = _frame_bytes(sim, state, save_particles, fields)
    # a writer holds up to two chunks of frames (the file's two copies lag one publication apart)
    held = 2 * (frames + 1) * frame_bytes if in_memory else min(frames + 1, 3) * frame_bytes + 2 * _CHUNK_BYTES
    fix = ("save fewer frames (frames=/--frames, a larger save_every), save_particles=False, fewer fields, or "
           "write to a file (writer=jm.H5Writer(...), the CLI's --out)") if in_memory else "use fewer particles"
    require_memory(f"this run ({frames + 1} frames of {frame_bytes:,} bytes, {int(state.x.shape[0]):,} particles)",
                   held + 4 * state_bytes, fix)
    return frame_bytes


class RunInterrupted(KeyboardInterrupt):
    """A chunked run stopped on SIGINT (Ctrl-C) or SIGTERM at a chunk boundary.  ``state`` is the
    state reached (also in the writer's file, see :func:`jaxmpm.resume`), ``frames`` the number
    of frames saved, ``history`` those frames when no writer holds them (else None), ``signal``
    the signal's name.

    Args:
        state: the :class:`jaxmpm.State` reached.
        frames: the number of frames saved.
        signal_name: the signal's name, "SIGINT" or "SIGTERM" (kept as ``.signal``).
        history: the saved :class:`History` when no writer holds it; None (the default).
    """

    def __init__(self, state, frames: int, signal_name: str, history=None):
        self.state = state
        self.frames = int(frames)
        self.signal = signal_name
        self.history = history
        super().__init__(f"run interrupted by {signal_name} at step {int(state.step)}")


class _StopOnSignal:
    """Turns SIGINT/SIGTERM into a request that the chunk loop honours at the next chunk boundary
    (a few seconds at most); a second Ctrl-C stops at once.  Only in the main thread."""

    def __init__(self):
        self.requested = None
        self._previous = {}

    def __enter__(self):
        import signal
        import threading

        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                self._previous[sig] = signal.signal(sig, self._handle)
        return self

    def _handle(self, signum, frame):
        import signal

        if self.requested is not None and signum == signal.SIGINT:  # the second Ctrl-C: now
            raise KeyboardInterrupt
        self.requested = signal.Signals(signum).name

    def __exit__(self, *exc):
        import signal

        for sig, handler in self._previous.items():
            signal.signal(sig, handler)


#: wall time a chunk of the chunked runner aims at: the longest wait for Ctrl-C, the progress
#: bar's refresh, and (with a writer) how often the file is brought up to date; the environment
#: variable ``JAXMPM_CHUNK_SECONDS`` overrides it.  ``_CHUNK_BYTES`` caps the frames one chunk
#: buffers on the device
CHUNK_SECONDS = 2.0
_CHUNK_BYTES = 16 * 2**20
#: the state goes with every chunk's frames, unless saving it takes more than ``_STATE_SECONDS``
#: and more than ``_STATE_SHARE`` of the run's time (a very large state): then with fewer of them
_STATE_SHARE = 0.05
_STATE_SECONDS = 0.05


def _seconds_from_env(name: str, default: float, valid, requirement: str) -> float:
    """``$name`` as seconds where it is set (checked: ``valid(seconds)``, else an InputError saying
    ``requirement``), else ``default``."""
    value = os.environ.get(name, "").strip()
    if not value:
        return default
    try:
        seconds = float(value)
    except ValueError:
        seconds = math.nan
    check(valid(seconds), f"{name} = {value!r} must be {requirement} (unset: {default:g})")
    return seconds


def _chunk_seconds() -> float:
    """:data:`CHUNK_SECONDS`, or ``$JAXMPM_CHUNK_SECONDS`` where it is set."""
    return _seconds_from_env("JAXMPM_CHUNK_SECONDS", CHUNK_SECONDS, lambda s: math.isfinite(s) and s > 0,
                             "a positive number of seconds")


#: a chunked run whose remaining steps will take longer than this (seconds, at the measured rate) says
#: so on stderr, once, before it goes on; ``$JAXMPM_LONG_RUN_SECONDS`` overrides it (``inf``: never)
LONG_RUN_SECONDS = 3600.0


def _long_run_seconds() -> float:
    """:data:`LONG_RUN_SECONDS`, or ``$JAXMPM_LONG_RUN_SECONDS`` where it is set."""
    return _seconds_from_env("JAXMPM_LONG_RUN_SECONDS", LONG_RUN_SECONDS, lambda s: s >= 0,
                             "a number of seconds >= 0, or inf")


def duration(seconds: float) -> str:
    """A time span as people say it: "45 s", "12 min", "37 h", "3.5 days"."""
    if seconds < 90:
        return f"{seconds:.2g} s"
    if seconds < 90 * 60:
        return f"{seconds / 60:.0f} min"
    if seconds < 48 * 3600:
        return f"{seconds / 3600:.2g} h"
    return f"{seconds / 86400:.2g} days"


def _count(n: float) -> str:
    """1.2e9, 9.1e3, 640: two significant digits without the exponent's plus sign and zeros."""
    text = f"{n:.2g}"
    return text.replace("e+0", "e").replace("e+", "e")


class _Clock:
    """The times of a chunked run and what it shows of them.  The loop is compiled before the first
    step (:meth:`compiling`): meanwhile the progress bar reads "compiling" and shows no rate; from
    then (:meth:`start`) the bar's clock, rate and ETA are those of the steps.  ``timings`` (a dict,
    or None) receives ``compile`` and ``run`` (seconds; run: from the first step to the end of the
    loop, writing included) and ``steps`` (run).  :meth:`tell_if_long` prints, once, how long
    the rest of a long run will take."""

    def __init__(self, total: int, done: int, progress: bool, timings: dict | None):
        import time

        self.clock = time.perf_counter
        self.total, self.done = total, done
        self.timings = {} if timings is None else timings
        self.timings.update(compile=0.0, run=0.0, steps=0)
        self.started = None
        self.chunks = 0
        self.limit = _long_run_seconds()
        self.told = False
        self.bar = None
        if progress:
            from tqdm.auto import tqdm

            self.bar = tqdm(total=total, initial=done, unit="step", desc="jaxmpm (compiling)")

    @contextlib.contextmanager
    def compiling(self):
        tic = self.clock()
        yield
        self.timings["compile"] += self.clock() - tic

    def start(self) -> None:
        """The steps begin: the run's clock starts, and the bar's (its elapsed time, rate and ETA)."""
        self.started = self.clock()
        if self.bar is not None:
            self.bar.set_description("jaxmpm", refresh=False)
            self.bar.unpause()

    def chunk(self, steps: int) -> None:
        """A chunk of ``steps`` steps ran."""
        self.done += steps
        self.chunks += 1
        self.timings["steps"] += steps
        if self.bar is not None:
            self.bar.update(steps)

    def tell_if_long(self, rate: float, writer) -> None:
        """After the second chunk (the first is one step: its time is mostly the call's, and it sizes
        the second to about :data:`CHUNK_SECONDS`), print to stderr how long the rest of the run
        needs at that chunk's ``rate`` when that exceeds the limit (:data:`LONG_RUN_SECONDS`)."""
        import sys

        if self.told or self.chunks < 2 or rate <= 0:
            return
        self.told = True
        left = self.total - self.done
        if left <= 0 or left / rate <= self.limit:
            return
        kept = f" in {writer.path}" if getattr(writer, "path", None) else ""
        message = (f"jaxmpm: this run needs about {duration(left / rate)} more ({_count(left)} steps at "
                   f"{_count(rate)} steps/s); Ctrl-C stops it and keeps the frames{kept}")
        if self.bar is not None:
            self.bar.write(message, file=sys.stderr)
        else:
            print(message, file=sys.stderr, flush=True)

    def close(self) -> None:
        if self.started is not None:
            self.timings["run"] = self.clock() - self.started
        if self.bar is not None:
            self.bar.close()


def _run_chunked(sim, state, dt, frames, save_every, save_particles, check_stability, progress, writer,
                 frames_per_chunk, checkpoint=True, start_step=None, fields=(), timings=None, donate=False):
    """Run in chunks sized by wall time (about :data:`CHUNK_SECONDS` each), each chunk one call of
    the same compiled loop (``_advance``) whose frame and step counts are runtime values: no
    chunk recompiles, and the arithmetic is that of an uninterrupted run whatever the chunking.

    ``start_step`` (resume) is the step of the run's initial frame: ``state`` may be anywhere in
    the schedule of ``frames`` frames of ``save_every`` steps from there.  With a writer, the
    initial frame goes to the file with the initial state before the first step, and every chunk's
    frames with the state reached after it, in one publication each (``writer.batch()``; the file
    survives a kill at any moment, see :class:`jaxmpm.H5Writer`), so the file can be continued
    (:func:`jaxmpm.resume`) from its last chunk whatever stops the run.  On SIGINT/SIGTERM the loop
    stops at the next chunk boundary and :class:`RunInterrupted` is raised.  The loop is compiled
    (by a call that runs no frame) before the first step; ``timings`` and the progress bar are
    :class:`_Clock`'s.  Each chunk is computed in place of the state before it (buffer donation,
    ``_advance_in_place``): the run holds one working state, a copy of ``state`` unless ``donate``."""
    import time

    if not is_schedule(checkpoint, "auto"):
        _segment_length(save_every, checkpoint, frames)  # validated; the chunked runner is forward only
    start_step = int(state.step) if start_step is None else int(start_step)
    done_steps = int(state.step) - start_step
    total = frames * save_every
    check(0 <= done_steps <= total, f"resume: the state is at step {int(state.step)}, outside the run's "
                                    f"steps {start_step}..{start_step + total}")
    seconds = _chunk_seconds()
    frame_bytes = _frame_bytes(sim, state, save_particles, fields)
    buffer_frames = _buffer_frames(frame_bytes, frames_per_chunk)  # not the run's frames: one loop for any length
    rate = 0.0  # steps per second, measured on each chunk (compiled before the first: 0.0, unknown)
    clock = _Clock(total, done_steps, progress, timings)
    pieces = []
    if writer is not None:
        state_bytes = tree_bytes(state)
        publisher = _Publisher(writer, dict(start_step=start_step, steps=total, save_every=save_every), state_bytes)
    none = Failure(*_device_ints(-1, 0, -1))  # device_put: nothing compiled

    def advance(s, n_frames, per_frame):
        """``n_frames`` frames of ``per_frame`` steps from ``s``: one call of the compiled loop, which
        computes the new state in place of ``s`` (``s`` is deleted)."""
        counts = _device_ints(n_frames, per_frame)
        return _advance_in_place((sim, none, dt, *counts, buffer_frames, save_particles, check_stability, fields,
                                  counts[1]), s)

    if not donate:
        state = _copied(state)  # the run's working state; the caller's stays as it is

    try:
        with _StopOnSignal() as stop:
            first = None
            with clock.compiling():  # compiles the loop and runs no step: the state handed back as it came
                if done_steps == 0 and (writer is None or writer.frames == 0):  # with the initial frame: a frame of
                    state, _, buffer = advance(state, 1, 0)  # no steps (no program of its own to compile)
                    first = jax.device_put(jax.tree_util.tree_map(lambda a: a[:1].copy(), jax.device_get(buffer)))
                elif done_steps < total:
                    state = jax.block_until_ready(advance(state, 0, 1))[0]
            if first is not None:
                if writer is None:
                    pieces.append(first)
                else:  # before the first step: from here on the file can be continued
                    publisher.publish(first, state)
            clock.start()
            while done_steps < total:
                n_frames, per_frame = _chunk(done_steps, total, save_every, rate, buffer_frames, frames_per_chunk,
                                             seconds)
                tic = time.perf_counter()
                before = _start_of(state)  # read before the chunk deletes the state
                new_state, failure, buffer = advance(state, n_frames, per_frame)
                failure, buffer = jax.device_get((failure, buffer))
                elapsed = time.perf_counter() - tic
                steps_run = n_frames * per_frame
                kept = n_frames if (done_steps + steps_run) % save_every == 0 else 0  # whole frames only
                bad_step = int(failure.step)
                failed = bad_step >= 0 and check_stability
                if failed:  # the frames strictly before the failing step
                    kept = min(kept, max(0, (bad_step - before.step - 1) // per_frame))
                # device_put: jnp.asarray of a NumPy array compiles a small program per new shape (jaxlib 0.10)
                frames_kept = jax.tree_util.tree_map(lambda a: jax.device_put(a[:kept]), buffer) if kept else None
                if writer is None:
                    if kept:
                        pieces.append(frames_kept)
                else:  # one publication: the chunk's frames and the state reached (not a failed chunk's)
                    publisher.publish(frames_kept, None if failed else new_state,
                                      due=stop.requested is not None or done_steps + steps_run == total)
                clock.chunk(steps_run)
                if check_stability:  # the error carries the frames kept in memory (a writer's are in its file)
                    _raise_if_failed(failure, dt, before, new_state, sim.grid,
                                     jax.tree_util.tree_map(lambda *a: jnp.concatenate(a), *pieces)
                                     if writer is None and pieces else None)
                state = new_state
                done_steps += steps_run
                rate = _measured_rate(rate, steps_run, elapsed)
                clock.tell_if_long(steps_run / max(elapsed, 1e-6), writer)  # this chunk's rate
                if stop.requested is not None and done_steps < total:
                    if writer is not None:
                        publisher.publish(None, state, due=True)  # saved already, unless the signal came late
                        raise RunInterrupted(state, writer.frames, stop.requested)
                    history = jax.tree_util.tree_map(lambda *a: jnp.concatenate(a), *pieces)
                    raise RunInterrupted(state, len(history), stop.requested, history)
    finally:
        clock.close()
        if writer is not None:
            writer.flush()
    if writer is not None:
        return state, None
    history = jax.tree_util.tree_map(lambda *a: jnp.concatenate(a), *pieces)
    return state, history


class _Publisher:
    """Publishes a chunked run's frames and state with its writer (one ``writer.batch()`` each).
    The state goes with every chunk's frames unless saving it has taken more than
    :data:`_STATE_SECONDS` and more than :data:`_STATE_SHARE` of the run's time (then as often as
    that allows), and always when ``due`` (the run's end, a signal); a chunk without it leaves
    frames that :func:`jaxmpm.resume` computes again from the state before them."""

    def __init__(self, writer, schedule, state_bytes: int):
        import time

        self.writer, self.schedule, self.state_bytes, self.clock = writer, schedule, state_bytes, time.perf_counter
        self.step = None  # the step of the state last saved
        self.cost = 0.0  # seconds its saving took (its share of the publication, by bytes)
        self.when = self.clock()

    def publish(self, frames, state, due: bool = False) -> None:
        """``frames`` (a History, or None) and ``state`` (None: no state to save) in one publication."""
        now = self.clock()
        with_state = state is not None and int(state.step) != self.step and (
            due or self.step is None or self.cost <= _STATE_SECONDS or (now - self.when) * _STATE_SHARE >= self.cost)
        if frames is None and not with_state:
            return
        with self.writer.batch():
            if frames is not None:
                self.writer.append(frames)
            if with_state:
                self.writer.write_state(state, **self.schedule)
        if with_state:
            frame_bytes = 0 if frames is None else sum(a.nbytes for a in jax.tree_util.tree_leaves(frames))
            self.step, self.when = int(state.step), self.clock()
            self.cost = (self.when - now) * self.state_bytes / max(1, self.state_bytes + frame_bytes)


def _chunk(done_steps, total, save_every, rate, buffer_frames, frames_per_chunk, seconds=CHUNK_SECONDS):
    """(frames, steps per frame) of the next chunk: about ``seconds`` of work at ``rate``
    steps/s (one step while the rate is unknown), ending on a frame boundary where it can."""
    budget = 1 if rate is None else max(1, int(rate * seconds))
    into_frame = done_steps % save_every
    if frames_per_chunk is not None and into_frame == 0:
        return min(frames_per_chunk, buffer_frames, (total - done_steps) // save_every), save_every
    if into_frame or budget < save_every:  # a part of one frame
        return 1, min(save_every - into_frame, budget)
    return min(buffer_frames, budget // save_every, (total - done_steps) // save_every), save_every


def _measured_rate(rate, steps, elapsed):
    """Steps per second: the first chunk's (``rate`` 0.0: none measured yet; the loop is compiled
    before it, so no chunk's time includes the compilation), then the mean of the estimate so far
    and the latest chunk's."""
    latest = steps / max(elapsed, 1e-6)
    return latest if rate == 0.0 else 0.5 * (rate + latest)


def _advance(sim, state, failure, dt, n_frames, steps_per_frame, buffer_frames: int, save_particles: bool,
             stop_at_failure: bool, fields: tuple, first_steps):
    """``n_frames`` (<= ``buffer_frames``) frames of ``steps_per_frame`` steps, the first of ``first_steps`` (0: the
    state as it came, a run's initial frame), all three runtime values, stopping at the first unstable step
    (``stop_at_failure``); returns the state, the failure record and a ``buffer_frames`` buffer whose first
    ``n_frames`` frames hold the frames reached."""

    def running(fail):
        return (fail.step < 0) if stop_at_failure else jnp.bool_(True)

    sorting = sim.sorting(state)  # particles sorted by cell every K steps, or None (jaxmpm.run.sorting)
    advance = _stepper(sim, sorting, dt)

    def one_step(carry):
        moving, i = carry
        return advance(moving), i + 1

    def one_frame(carry):
        moving, buffer, j = carry
        steps = jnp.where(j == 0, first_steps, steps_per_frame)
        moving, _ = jax.lax.while_loop(lambda c: (c[1] < steps) & running(c[0][1]), one_step,
                                       (moving, jnp.zeros((), jnp.int32)))
        frame = sim.diagnostics_frame(_in_user_order(sorting, moving), save_particles, fields)
        buffer = jax.tree_util.tree_map(lambda b, f: b.at[j].set(f), buffer, frame)
        return moving, buffer, j + 1

    shapes = jax.eval_shape(lambda s: sim.diagnostics_frame(s, save_particles, fields), state)
    buffer = jax.tree_util.tree_map(lambda a: jnp.zeros((buffer_frames,) + a.shape, a.dtype), shapes)
    moving = (state, failure, None if sorting is None else sorting.start(state))
    moving, buffer, _ = jax.lax.while_loop(lambda c: (c[2] < n_frames) & running(c[0][1]), one_frame,
                                           (moving, buffer, jnp.zeros((), jnp.int32)))
    return _in_user_order(sorting, moving), moving[1], buffer


def _stepper(sim, sorting, dt):
    """One step of a run: (state, failure record, order) -> the same after the step.  ``order`` is
    the particles' :class:`~jaxmpm.run.sorting.Order` when the run sorts them by cell (``sorting``),
    else None; the failure record names the user's particle either way."""

    def advance(carry):
        s, fail, order = carry
        if sorting is not None:
            s, order = sorting.renew(s, order)
        s = sim.step(s, dt)
        code, particle = sim.instability(jax.lax.stop_gradient(s), jax.lax.stop_gradient(dt))
        if sorting is not None:
            particle = sorting.user_particle(particle, order)
        new = (fail.step < 0) & (code > 0)
        fail = Failure(jnp.where(new, s.step, fail.step), jnp.where(new, code, fail.cause),
                       jnp.where(new, particle, fail.particle))
        return s, fail, order

    return advance


def _in_user_order(sorting, carry):
    """The state of a run's carry (state, failure record, order) in the user's particle order."""
    state, _, order = carry
    return state if sorting is None else sorting.in_user_order(state, order)


@eqx.filter_jit
def _jit_frame(sim, state, save_particles, fields=()):
    return sim.diagnostics_frame(state, save_particles, fields)


@eqx.filter_jit
def _jit_first_frame(sim, state, save_particles, fields=()):
    """Frame 0 of a run with its leading frame axis, in one program (indexing it op by op compiled one
    small program per field)."""
    return jax.tree_util.tree_map(lambda a: a[None], sim.diagnostics_frame(state, save_particles, fields))


@eqx.filter_jit
def _jit_rollout(sim, state, dt, frames, save_every, save_particles, checkpoint="auto", history_gradients=True,
                 fields=(), memory=None):
    return sim.rollout(state, dt, frames, save_every, save_particles, checkpoint, history_gradients, fields, memory)


@functools.partial(eqx.filter_jit, donate="all-except-first")
def _jit_rollout_in_place(options, state):
    """:func:`_jit_rollout` of ``state`` with ``options`` (sim, dt, frames, ...) without the initial frame
    (:func:`_later_frames`), its final state computed in place of ``state`` (donated: every array but the
    first argument's): (final state, the later frames, failure record).  Read in the same program, the initial
    state would have to outlive the loop, and XLA would copy it: the initial frame is a program of its own."""
    sim, dt, *rest = options
    final, later, failure, _ = _later_frames(sim, state, dt, *rest)
    return final, later, failure


@eqx.filter_jit
def _jit_joined(first, later):
    """The initial frame (with its leading axis) and the later ones, as one history."""
    return jax.tree_util.tree_map(lambda a, b: jnp.concatenate([a, b]), first, later)


@eqx.filter_jit
def _jit_history(buffers: tuple, frames: int):
    """:func:`_joined` on the device, as one program."""
    return jax.tree_util.tree_map(lambda *b: _joined(jnp, b, frames), *buffers)


@functools.partial(eqx.filter_jit, donate="all-except-first")
def _advance_in_place(options, state):
    """:func:`_advance` of ``state`` with ``options`` (sim, failure, dt, ...), the new state computed in place of
    ``state`` (donated)."""
    sim, *rest = options
    return _advance(sim, state, *rest)


class _Start(NamedTuple):
    """The step and time of a run's state, read to the host before the run deletes it (donation):
    what :func:`_raise_if_failed` reads of the state it starts from."""

    step: int
    time: float


def _start_of(state) -> _Start:
    return _Start(int(state.step), float(state.time))


def _unshared(state, copy=lambda a: jax.device_put(a, may_alias=False)):
    """``state`` with every array that an earlier leaf already holds replaced by ``copy(array)`` (default: a copy
    on its device; ``eqx.tree_at(lambda s: s.v, state, state.x)`` makes one): XLA refuses to donate one buffer
    twice."""
    seen = set()

    def once(a):
        if not isinstance(a, jax.Array) or id(a) not in seen:
            seen.add(id(a))
            return a
        return copy(a)

    return jax.tree_util.tree_map(once, state)


def _copied(state):
    """``state`` with every array copied on its device (nothing compiled): a working state that a run
    may donate while the caller keeps ``state``."""
    leaves, treedef = jax.tree_util.tree_flatten(state)
    arrays = [i for i, leaf in enumerate(leaves) if isinstance(leaf, jax.Array)]
    for i, copy in zip(arrays, jax.device_put([leaves[i] for i in arrays], may_alias=False)):  # one transfer call
        leaves[i] = copy
    return jax.tree_util.tree_unflatten(treedef, leaves)


def _raise_if_failed(failure: Failure, dt, state0, reached=None, grid=None, history=None):
    """:class:`InstabilityError` for the first failing step of a run from ``state0``, if any:
    :class:`ParticlesLeftGrid` when particles left the grid (cause 3: the grid is too small, not
    a numerical instability), with the particle's position in ``reached`` when that is the state
    of the failing step (the chunked runner stops there) and the box of ``grid``.  ``history``: the
    frames saved before the failing step (a History, or None), which the error carries
    (:attr:`InstabilityError.history`)."""
    step = int(failure.step)
    if step < 0:
        return
    t = float(state0.time) + (step - int(state0.step)) * float(np.asarray(dt))
    particle = int(failure.particle)
    if int(failure.cause) == 3:
        at = reached is not None and int(reached.step) == step
        error = ParticlesLeftGrid(step, particle, np.asarray(reached.x[particle]) if at else None,
                                  None if grid is None else grid.lower, None if grid is None else grid.upper, t)
    else:
        error = InstabilityError(step, f"{CAUSES.get(int(failure.cause), 'unknown')} (particle {particle})", t)
    error.history = history
    raise error


def _check_start(sim, state, rows: int = 65536) -> None:
    """An InputError for a state that is unstable before its first step -- a position, velocity or F not
    finite, an inverted F, a particle whose shape function reaches past the grid -- naming the particle
    (the run had reported it as failing at its first step).  On the host, in NumPy, ``rows`` particles at a
    time (on a CPU the arrays are read in place, and the temporaries stay small): nothing compiled."""
    x, v, F = (np.asarray(a) for a in (state.x, state.v, state.F))
    for start in range(0, x.shape[0], rows):
        part = slice(start, start + rows)
        bad = np.flatnonzero(~(np.isfinite(x[part]).all(-1) & np.isfinite(v[part]).all(-1)
                               & np.isfinite(F[part]).all((-1, -2))))
        if bad.size:
            p = start + int(bad[0])
            check(False, f"run: the state is not finite before the first step: particle {p} has x = {x[p].tolist()},"
                         f" v = {v[p].tolist()}; build the state with sim.init, or mend it")
        bad = np.flatnonzero(np.linalg.det(F[part]) <= 0)
        if bad.size:
            check(False, f"run: particle {start + int(bad[0])} has det F <= 0 before the first step; F must start "
                         "invertible, e.g. the identity")
        bad = np.flatnonzero(~np.asarray(sim.shape.inside(sim.grid, x[part])))
        if bad.size:
            p = start + int(bad[0])
            check(False, f"run: particle {p} at x = {x[p].tolist()} lies where its shape function reaches past the "
                         f"grid's nodes before the first step (the grid spans {tuple(sim.grid.lower)} .. "
                         f"{tuple(sim.grid.upper)}, and a {type(sim.shape).__name__} particle needs "
                         f"{sim.shape.margin} cells of room); move it or enlarge the grid")


def _frames_before(history, start_step: int, save_every: int, step: int):
    """The frames of ``history`` (frame 0 at ``start_step``, one every ``save_every`` steps) strictly before
    the failing ``step``, or None if there are none."""
    count = (step - start_step - 1) // save_every + 1  # frames at start_step + i save_every < step
    if history is None or count <= 0:
        return None
    return jax.tree_util.tree_map(lambda a: a[:count], history)
