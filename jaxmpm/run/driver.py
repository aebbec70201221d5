"""The driver: running a model.  ``rollout`` is the pure ``lax.scan`` of steps and saved frames
(with rematerialisation for reverse-mode gradients); ``run`` adds the eager conveniences --
a CFL warning, instability detection that names the first bad step, chunked HDF5 writing and a
progress bar.  ``Simulation.run`` and ``Simulation.rollout`` call these."""

from __future__ import annotations

import math
import os

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..core.errors import InstabilityError, check
from ..core.limits import require_memory, require_steps
from ..core.state import State
from ..core.warn import warn

CAUSES = {
    1: "NaN or Inf in the particle state",
    2: "J = det F <= 0 (a particle inverted)",
    3: "particles left the grid",
}


class StableTimeStepWarning(UserWarning):
    """dt exceeds the CFL limit h / max(c + |V|) or a term's limit (conduction, diffusion)."""


class History(eqx.Module):
    """Saved frames (leading axis T): time, particle x/v (None if not saved), energies, momenta,
    the per-particle fields the terms declare (``fields``, empty if particles are not saved) and,
    in multimaterial mode, per-material sums (``by_material``: kinetic, strain, momentum,
    contact_force), and the terms' totals (``totals``: thermal energy, solute)."""

    time: jnp.ndarray
    x: jnp.ndarray | None
    v: jnp.ndarray | None
    kinetic: jnp.ndarray
    strain: jnp.ndarray
    dissipated: jnp.ndarray
    momentum: jnp.ndarray
    angular: jnp.ndarray
    fields: dict = eqx.field(default_factory=dict)  # saved per-particle fields of the terms, (T, N, ...)
    # multimaterial mode: per-material kinetic, strain (T, M), momentum and contact force (T, M, D)
    by_material: dict = eqx.field(default_factory=dict)
    # the terms' totals (T,): thermal_energy (jm.Heat), solute (jm.Diffusion)
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
    return any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree_util.tree_leaves(tree))


def check_state(state) -> None:
    """A state whose float arrays mix precisions is rejected with the dtypes and the fix (a model
    of another precision than its state is cast on entry: ``Simulation.step``)."""
    dtypes = {}
    for path, leaf in jax.tree_util.tree_flatten_with_path(state)[0]:  # the core, scheme, material, fields
        if jnp.issubdtype(jnp.result_type(leaf), jnp.floating):
            name = jax.tree_util.keystr(path).lstrip(".")
            dtypes.setdefault(str(jnp.result_type(leaf)), []).append(name)
    check(len(dtypes) == 1,
          "State mixes float precisions (" + "; ".join(f"{k}: {', '.join(v)}" for k, v in dtypes.items())
          + "); cast it to one dtype first, e.g. jm.scenes.cast_state(state, jnp.float32)")


def rollout(sim, state: State, dt, frames: int, save_every: int = 1, save_particles: bool = True,
            checkpoint=True, history_gradients: bool = True):
    """Pure ``lax.scan`` rollout of ``frames * save_every`` steps.  Returns
    ``(final_state, history, failure)``; ``history`` holds the initial frame and one frame
    every ``save_every`` steps (``frames + 1`` in all).

    ``checkpoint`` (reverse mode only; the forward pass is unchanged):

    * ``True`` (default): two levels.  The forward pass keeps the state at the start of every
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
    sim = sim.in_precision(state.x.dtype)  # the model computes in its state's precision
    dt = jnp.asarray(dt, state.x.dtype)
    none = Failure(jnp.array(-1, jnp.int32), jnp.array(0, jnp.int32), jnp.array(-1, jnp.int32))
    segment = _segment_length(save_every, checkpoint, frames)
    remat = (lambda f: f) if segment is None else jax.checkpoint  # noqa: E731
    remat_frames = jax.checkpoint if isinstance(checkpoint, str) else (lambda f: f)  # noqa: E731  ("low_memory")

    @remat
    def one_step(carry, _):
        s, fail = carry
        s = sim.step(s, dt)
        code, particle = sim.instability(jax.lax.stop_gradient(s))
        new = (fail.step < 0) & (code > 0)
        fail = Failure(
            jnp.where(new, s.step, fail.step),
            jnp.where(new, code, fail.cause),
            jnp.where(new, particle, fail.particle),
        )
        return (s, fail), None

    seg_len = save_every if segment is None else segment

    @remat
    def one_segment(carry, _):
        carry, _ = jax.lax.scan(one_step, carry, None, length=seg_len)
        return carry, None

    def frame(s):
        return sim.diagnostics_frame(s if history_gradients else jax.lax.stop_gradient(s), save_particles)

    @remat_frames
    def one_frame(carry, _):
        carry, _ = jax.lax.scan(one_segment, carry, None, length=save_every // seg_len)
        return carry, frame(carry[0])

    (final, failure), frames_hist = jax.lax.scan(one_frame, (state, none), None, length=frames)
    first = frame(state)
    history = jax.tree_util.tree_map(lambda a, b: jnp.concatenate([a[None], b]), first, frames_hist)
    return final, history, failure

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
    checkpoint=True,
    history_gradients: bool = True,
    start_step: int | None = None,
):
    """Run ``steps`` steps, saving a frame every ``save_every`` steps (plus the initial frame).

    Returns ``(final_state, history)``.  Traceable: under ``jax.grad``/``vmap``/``jit`` it is a
    single ``lax.scan``.  Called eagerly it also warns when ``dt`` exceeds the CFL limit and
    raises :class:`InstabilityError` naming the first bad step.  With ``writer`` (a
    :class:`jaxmpm.H5Writer`) or ``progress=True`` it runs in chunks of ``frames_per_chunk``
    frames, writing/reporting each before the next, and returns ``(final_state, None)`` when
    a writer holds the frames.  ``checkpoint`` controls rematerialisation for reverse-mode
    gradients and ``history_gradients=False`` makes the saved frames constants to autodiff (see
    :func:`rollout`); neither changes the forward results.

    Chunks are sized by wall time (about :data:`CHUNK_SECONDS`); ``frames_per_chunk`` caps them.
    A writer's file receives every chunk's frames with the state reached, so that whatever stops
    the run, even a kill, :func:`jaxmpm.resume` continues it from its last chunk.  SIGINT (Ctrl-C)
    or SIGTERM stops a chunked run at the next chunk boundary and raises :class:`RunInterrupted`.
    ``start_step`` (resume) is the step of the run's first frame when ``state`` is part-way
    through it.  Before anything runs, the step count and the memory the saved frames need are
    checked (:mod:`jaxmpm.core.limits`).
    """
    check(isinstance(steps, (int, np.integer)) and steps >= 0, f"run: steps = {steps!r} must be a non-negative integer")
    check(isinstance(save_every, (int, np.integer)) and save_every >= 1,
          f"run: save_every = {save_every!r} must be a positive integer")
    check(steps % save_every == 0,
          f"run: steps = {steps} is not a multiple of save_every = {save_every}; "
          f"use steps = {math.ceil(steps / save_every) * save_every}")
    check(isinstance(history_gradients, bool),
          f"run: history_gradients = {history_gradients!r} must be True (frames carry gradients) or False")
    frames = steps // save_every
    check_state(state)
    check(start_step is None or writer is not None or progress,
          "run: start_step continues a chunked run; pass writer=... (see jaxmpm.resume)")
    sim = sim.in_precision(state.x.dtype)  # the model computes in its state's precision
    traced = _is_traced((sim, state, dt))
    dt = jnp.asarray(dt, state.x.dtype)  # an array, so a new dt value does not recompile
    if not traced:
        dtc = float(np.asarray(dt))
        check(math.isfinite(dtc) and dtc > 0, f"run: dt = {dtc} must be a positive number")
        limits = {name: float(value) for name, value in sim.time_step_limits(state).items()}
        name = min(limits, key=limits.get)
        limit = limits[name]
        if dtc > limit:
            what = "h / max(c + |V|)" if name == "CFL" else f"the {name} term's limit h^2 / (2 D k / (rho C_p))"
            warn(f"dt = {dtc:.6g} exceeds the stable limit {limit:.6g} (= {what}); "
                 f"use dt <= {0.5 * limit:.6g} (CFL 0.5) to stay stable", StableTimeStepWarning)
        first = int(state.step) if start_step is None else int(start_step)
        require_steps(first + steps, "shorten t_end, use a larger dt, or split the run")
        _require_frame_memory(sim, state, frames, save_particles, writer is None)
    if traced or (writer is None and not progress):
        final, history, failure = _jit_rollout(sim, state, dt, frames, save_every, save_particles,
                                               checkpoint, history_gradients)
        if not traced and check_stability:
            _raise_if_failed(failure, dt, state)
        return final, history
    return _run_chunked(sim, state, dt, frames, save_every, save_particles, check_stability,
                        progress, writer, frames_per_chunk, checkpoint, start_step)


def _frame_bytes(sim, state, save_particles) -> int:
    shape = jax.eval_shape(lambda s: sim.diagnostics_frame(s, save_particles), state)
    return sum(math.prod(a.shape) * a.dtype.itemsize for a in jax.tree_util.tree_leaves(shape))


def _require_frame_memory(sim, state, frames, save_particles, in_memory):
    """The saved frames (all of them when kept in memory, twice: the device result and the
    concatenated history) plus the state and its step temporaries, before the run starts."""
    state_bytes = sum(a.size * a.dtype.itemsize for a in jax.tree_util.tree_leaves(state) if hasattr(a, "size"))
    frame_bytes = _frame_bytes(sim, state, save_particles)
    # a writer holds up to two chunks of frames (the file's two copies lag one publication apart)
    held = 2 * (frames + 1) * frame_bytes if in_memory else min(frames + 1, 3) * frame_bytes + 2 * _CHUNK_BYTES
    fix = ("save fewer frames (frames=/--frames, a larger save_every), save_particles=False, or write "
           "to a file (writer=jm.H5Writer(...), the CLI's --out)") if in_memory else "use fewer particles"
    require_memory(f"this run ({frames + 1} frames of {frame_bytes:,} bytes, {int(state.x.shape[0]):,} particles)",
                   held + 4 * state_bytes, fix)


class RunInterrupted(KeyboardInterrupt):
    """A chunked run stopped on SIGINT (Ctrl-C) or SIGTERM at a chunk boundary.  ``state`` is the
    state reached (also in the writer's file, see :func:`jaxmpm.resume`), ``frames`` the number
    of frames saved, ``history`` those frames when no writer holds them (else None), ``signal``
    the signal's name."""

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


def _chunk_seconds() -> float:
    """:data:`CHUNK_SECONDS`, or ``$JAXMPM_CHUNK_SECONDS`` where it is set."""
    value = os.environ.get("JAXMPM_CHUNK_SECONDS", "").strip()
    if not value:
        return CHUNK_SECONDS
    try:
        seconds = float(value)
    except ValueError:
        seconds = math.nan
    check(math.isfinite(seconds) and seconds > 0,
          f"JAXMPM_CHUNK_SECONDS = {value!r} must be a positive number of seconds (unset: {CHUNK_SECONDS:g})")
    return seconds


def _run_chunked(sim, state, dt, frames, save_every, save_particles, check_stability, progress, writer,
                 frames_per_chunk, checkpoint=True, start_step=None):
    """Run in chunks sized by wall time (about :data:`CHUNK_SECONDS` each), each chunk one call of
    the same compiled loop (``_advance``) whose frame and step counts are runtime values: no
    chunk recompiles, and the arithmetic is that of an uninterrupted run whatever the chunking.

    ``start_step`` (resume) is the step of the run's initial frame: ``state`` may be anywhere in
    the schedule of ``frames`` frames of ``save_every`` steps from there.  With a writer, the
    initial frame goes to the file with the initial state before the first step, and every chunk's
    frames with the state reached after it, in one publication each (``writer.batch()``; the file
    survives a kill at any moment, see :class:`jaxmpm.H5Writer`), so the file can be continued
    (:func:`jaxmpm.resume`) from its last chunk whatever stops the run.  On SIGINT/SIGTERM the loop
    stops at the next chunk boundary and :class:`RunInterrupted` is raised."""
    import time

    _segment_length(save_every, checkpoint, frames)  # validated; the chunked runner is forward only
    start_step = int(state.step) if start_step is None else int(start_step)
    done_steps = int(state.step) - start_step
    total = frames * save_every
    check(0 <= done_steps <= total, f"resume: the state is at step {int(state.step)}, outside the run's "
                                    f"steps {start_step}..{start_step + total}")
    seconds = _chunk_seconds()
    frame_bytes = _frame_bytes(sim, state, save_particles)
    buffer_frames = max(1, min(frames, frames_per_chunk or frames, _CHUNK_BYTES // max(1, frame_bytes)))
    rate = None  # steps per second, measured on the chunks after the first (which compiles)
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=total, initial=done_steps, unit="step", desc="jaxmpm")
    pieces = []
    if writer is not None:
        state_bytes = sum(a.size * a.dtype.itemsize for a in jax.tree_util.tree_leaves(state) if hasattr(a, "size"))
        publisher = _Publisher(writer, dict(start_step=start_step, steps=total, save_every=save_every), state_bytes)
    none = Failure(jnp.array(-1, jnp.int32), jnp.array(0, jnp.int32), jnp.array(-1, jnp.int32))
    try:
        with _StopOnSignal() as stop:
            if done_steps == 0 and (writer is None or writer.frames == 0):
                first = jax.tree_util.tree_map(lambda a: a[None], _jit_frame(sim, state, save_particles))
                if writer is None:
                    pieces.append(first)
                else:  # before the first step: from here on the file can be continued
                    publisher.publish(first, state)
            while done_steps < total:
                n_frames, per_frame = _chunk(done_steps, total, save_every, rate, buffer_frames, frames_per_chunk,
                                             seconds)
                tic = time.perf_counter()
                new_state, failure, buffer = _advance(sim, state, none, dt, jnp.asarray(n_frames, jnp.int32),
                                                      jnp.asarray(per_frame, jnp.int32), buffer_frames,
                                                      save_particles, check_stability)
                failure, buffer = jax.device_get((failure, buffer))
                elapsed = time.perf_counter() - tic
                steps_run = n_frames * per_frame
                kept = n_frames if (done_steps + steps_run) % save_every == 0 else 0  # whole frames only
                bad_step = int(failure.step)
                failed = bad_step >= 0 and check_stability
                if failed:  # the frames strictly before the failing step
                    kept = min(kept, max(0, (bad_step - int(state.step) - 1) // per_frame))
                frames_kept = jax.tree_util.tree_map(lambda a: jnp.asarray(a[:kept]), buffer) if kept else None
                if writer is None:
                    if kept:
                        pieces.append(frames_kept)
                else:  # one publication: the chunk's frames and the state reached (not a failed chunk's)
                    publisher.publish(frames_kept, None if failed else new_state,
                                      due=stop.requested is not None or done_steps + steps_run == total)
                if bar is not None:
                    bar.update(steps_run)
                if check_stability:
                    _raise_if_failed(failure, dt, state)
                state = new_state
                done_steps += steps_run
                rate = _measured_rate(rate, steps_run, elapsed)
                if stop.requested is not None and done_steps < total:
                    if writer is not None:
                        publisher.publish(None, state, due=True)  # saved already, unless the signal came late
                        raise RunInterrupted(state, writer.frames, stop.requested)
                    history = jax.tree_util.tree_map(lambda *a: jnp.concatenate(a), *pieces)
                    raise RunInterrupted(state, len(history), stop.requested, history)
    finally:
        if bar is not None:
            bar.close()
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
    """Steps per second: None after the first chunk (it includes the compilation), then the
    latest chunk's rate."""
    if rate is None:
        return 0.0 if steps else None  # 0.0 marks "compiled": the next chunk is measured
    return steps / max(elapsed, 1e-6) if rate == 0.0 else 0.5 * (rate + steps / max(elapsed, 1e-6))


@eqx.filter_jit
def _advance(sim, state, failure, dt, n_frames, steps_per_frame, buffer_frames: int, save_particles: bool,
             stop_at_failure: bool = True):
    """``n_frames`` (<= ``buffer_frames``) frames of ``steps_per_frame`` steps, both runtime
    values, stopping at the first unstable step (``stop_at_failure``); returns the state, the failure record and a
    ``buffer_frames`` buffer whose first ``n_frames`` frames hold the frames reached."""

    def running(fail):
        return (fail.step < 0) if stop_at_failure else jnp.bool_(True)

    def one_step(carry):
        s, fail, i = carry
        s = sim.step(s, dt)
        code, particle = sim.instability(jax.lax.stop_gradient(s))
        new = (fail.step < 0) & (code > 0)
        fail = Failure(jnp.where(new, s.step, fail.step), jnp.where(new, code, fail.cause),
                       jnp.where(new, particle, fail.particle))
        return s, fail, i + 1

    def one_frame(carry):
        s, fail, buffer, j = carry
        s, fail, _ = jax.lax.while_loop(lambda c: (c[2] < steps_per_frame) & running(c[1]), one_step,
                                        (s, fail, jnp.zeros((), jnp.int32)))
        frame = sim.diagnostics_frame(s, save_particles)
        buffer = jax.tree_util.tree_map(lambda b, f: b.at[j].set(f), buffer, frame)
        return s, fail, buffer, j + 1

    shapes = jax.eval_shape(lambda s: sim.diagnostics_frame(s, save_particles), state)
    buffer = jax.tree_util.tree_map(lambda a: jnp.zeros((buffer_frames,) + a.shape, a.dtype), shapes)
    state, failure, buffer, _ = jax.lax.while_loop(lambda c: (c[3] < n_frames) & running(c[1]), one_frame,
                                                   (state, failure, buffer, jnp.zeros((), jnp.int32)))
    return state, failure, buffer


@eqx.filter_jit
def _jit_frame(sim, state, save_particles):
    return sim.diagnostics_frame(state, save_particles)


@eqx.filter_jit
def _jit_rollout(sim, state, dt, frames, save_every, save_particles, checkpoint=True, history_gradients=True):
    return sim.rollout(state, dt, frames, save_every, save_particles, checkpoint, history_gradients)


def _segment_length(save_every: int, checkpoint, frames: int = 1):
    """Steps per rematerialised segment, or None for no checkpointing (see :func:`rollout`)."""
    if checkpoint is False or checkpoint is None:
        return None
    divisors = [d for d in range(1, save_every + 1) if save_every % d == 0]
    if checkpoint is True:  # two levels: fewest states kept, frames * save_every / L segment starts + L steps
        return min(divisors, key=lambda d: (frames * save_every // d + d, d))
    if isinstance(checkpoint, str) and checkpoint == "low_memory":  # three levels: segments of ~sqrt(save_every)
        return min(divisors, key=lambda d: abs(d - math.sqrt(save_every)))
    check(isinstance(checkpoint, (int, np.integer)) and not isinstance(checkpoint, (bool, str)) and checkpoint >= 1
          and save_every % checkpoint == 0,
          f"checkpoint = {checkpoint!r} must be True, False, 'low_memory' or a positive divisor of "
          f"save_every = {save_every}")
    return int(checkpoint)


def _raise_if_failed(failure: Failure, dt, state0):
    step = int(failure.step)
    if step < 0:
        return
    cause = CAUSES.get(int(failure.cause), "unknown")
    cause = f"{cause} (particle {int(failure.particle)})"
    t = float(state0.time) + (step - int(state0.step)) * float(np.asarray(dt))
    raise InstabilityError(step, cause, t)
