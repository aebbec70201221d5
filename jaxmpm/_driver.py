"""The driver: running a model.  ``rollout`` is the pure ``lax.scan`` of steps and saved frames
(with rematerialisation for reverse-mode gradients); ``run`` adds the eager conveniences --
a CFL warning, instability detection that names the first bad step, chunked HDF5 writing and a
progress bar.  ``Simulation.run`` and ``Simulation.rollout`` call these."""

from __future__ import annotations

import math
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._errors import InstabilityError, check

CAUSES = {
    1: "NaN or Inf in the particle state",
    2: "J = det F <= 0 (a particle inverted)",
    3: "particles left the grid",
}


class StableTimeStepWarning(UserWarning):
    """dt exceeds the CFL limit h / max(c + |V|)."""


class History(eqx.Module):
    """Saved frames (leading axis T): time, particle x/v (None if not saved), energies, momenta,
    and the per-particle fields the terms declare (``fields``, empty if particles are not saved)."""

    time: jnp.ndarray
    x: jnp.ndarray | None
    v: jnp.ndarray | None
    kinetic: jnp.ndarray
    strain: jnp.ndarray
    dissipated: jnp.ndarray
    momentum: jnp.ndarray
    angular: jnp.ndarray
    fields: dict = eqx.field(default_factory=dict)  # saved per-particle fields of the terms, (T, N, ...)

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
    for name in ("x", "v", "F", "mass", "volume0", "time", "dissipated"):
        dtypes.setdefault(str(jnp.result_type(getattr(state, name))), []).append(name)
    check(len(dtypes) == 1,
          "State mixes float precisions (" + "; ".join(f"{k}: {', '.join(v)}" for k, v in dtypes.items())
          + "); cast it to one dtype first, e.g. jm.scenes.cast_state(state, jnp.float32)")


def rollout(sim, state: State, dt, frames: int, save_every: int = 1, save_particles: bool = True,
            checkpoint=True):
    """Pure ``lax.scan`` rollout of ``frames * save_every`` steps.  Returns
    ``(final_state, history, failure)``; ``history`` holds the initial frame and one frame
    every ``save_every`` steps (``frames + 1`` in all).

    ``checkpoint`` (reverse mode only; the forward pass is unchanged): ``True`` splits each
    frame into segments of about sqrt(save_every) steps and rematerialises frames, segments and
    steps, so the gradient stores O(frames + sqrt(save_every)) states instead of every
    intermediate of every step; an int sets the segment length (a divisor of save_every);
    ``False`` stores everything (fastest for short rollouts).
    """
    sim = sim.in_precision(state.x.dtype)  # the model computes in its state's precision
    dt = jnp.asarray(dt, state.x.dtype)
    none = Failure(jnp.array(-1, jnp.int32), jnp.array(0, jnp.int32), jnp.array(-1, jnp.int32))
    segment = _segment_length(save_every, checkpoint)
    remat = (lambda f: f) if segment is None else jax.checkpoint  # noqa: E731

    @remat
    def one_step(carry, _):
        s, fail = carry
        s = sim.step(s, dt)
        code, particle = sim.instability(s)
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

    @remat
    def one_frame(carry, _):
        carry, _ = jax.lax.scan(one_segment, carry, None, length=save_every // seg_len)
        return carry, sim.diagnostics_frame(carry[0], save_particles)

    (final, failure), frames_hist = jax.lax.scan(one_frame, (state, none), None, length=frames)
    first = sim.diagnostics_frame(state, save_particles)
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
):
    """Run ``steps`` steps, saving a frame every ``save_every`` steps (plus the initial frame).

    Returns ``(final_state, history)``.  Traceable: under ``jax.grad``/``vmap``/``jit`` it is a
    single ``lax.scan``.  Called eagerly it also warns when ``dt`` exceeds the CFL limit and
    raises :class:`InstabilityError` naming the first bad step.  With ``writer`` (a
    :class:`jaxmpm.H5Writer`) or ``progress=True`` it runs in chunks of ``frames_per_chunk``
    frames, writing/reporting each before the next, and returns ``(final_state, None)`` when
    a writer holds the frames.  ``checkpoint`` controls rematerialisation for reverse-mode
    gradients (see :meth:`rollout`); it does not change the forward results.
    """
    check(isinstance(steps, (int, np.integer)) and steps >= 0, f"run: steps = {steps!r} must be a non-negative integer")
    check(isinstance(save_every, (int, np.integer)) and save_every >= 1,
          f"run: save_every = {save_every!r} must be a positive integer")
    check(steps % save_every == 0,
          f"run: steps = {steps} is not a multiple of save_every = {save_every}; "
          f"use steps = {math.ceil(steps / save_every) * save_every}")
    frames = steps // save_every
    check_state(state)
    sim = sim.in_precision(state.x.dtype)  # the model computes in its state's precision
    traced = _is_traced((sim, state, dt))
    dt = jnp.asarray(dt, state.x.dtype)  # an array, so a new dt value does not recompile
    if not traced:
        dtc = float(np.asarray(dt))
        check(math.isfinite(dtc) and dtc > 0, f"run: dt = {dtc} must be a positive number")
        limit = float(sim.stable_dt(state))
        if dtc > limit:
            warnings.warn(
                f"dt = {dtc:.6g} exceeds the stable limit {limit:.6g} (= h / max(c + |V|)); "
                f"use dt <= {0.5 * limit:.6g} (CFL 0.5) to stay stable",
                StableTimeStepWarning,
                stacklevel=2,
            )
    if traced or (writer is None and not progress):
        final, history, failure = _jit_rollout(sim, state, dt, frames, save_every, save_particles,
                                               checkpoint)
        if not traced and check_stability:
            _raise_if_failed(failure, dt, state)
        return final, history
    return _run_chunked(sim, state, dt, frames, save_every, save_particles, check_stability,
                        progress, writer, frames_per_chunk, checkpoint)

def _run_chunked(sim, state, dt, frames, save_every, save_particles, check_stability, progress, writer,
                 frames_per_chunk, checkpoint=True):
    chunk = frames_per_chunk or max(1, min(frames, 50))
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=frames * save_every, unit="step", desc="jaxmpm")
    pieces = []
    first = jax.tree_util.tree_map(lambda a: a[None], _jit_frame(sim, state, save_particles))
    if writer is not None:
        writer.append(first)
    else:
        pieces.append(first)
    done = 0
    try:
        while done < frames:
            n = min(chunk, frames - done)
            start_step = int(state.step)
            new_state, hist, failure = _jit_rollout(sim, state, dt, n, save_every, save_particles, checkpoint)
            hist = jax.tree_util.tree_map(lambda a: a[1:], hist)  # drop the repeated first frame
            bad_step = int(failure.step)
            if bad_step >= 0 and check_stability:
                good = max(0, (bad_step - start_step - 1) // save_every)  # frames strictly before failure
                hist = jax.tree_util.tree_map(lambda a: a[:good], hist)
            if writer is not None:
                writer.append(hist)
            else:
                pieces.append(hist)
            if bar is not None:
                bar.update(n * save_every)
            if check_stability:
                _raise_if_failed(failure, dt, state)
            state = new_state
            done += n
    finally:
        if bar is not None:
            bar.close()
        if writer is not None:
            writer.flush()
    if writer is not None:
        return state, None
    history = jax.tree_util.tree_map(lambda *a: jnp.concatenate(a), *pieces)
    return state, history


@eqx.filter_jit
def _jit_frame(sim, state, save_particles):
    return sim.diagnostics_frame(state, save_particles)


@eqx.filter_jit
def _jit_rollout(sim, state, dt, frames, save_every, save_particles, checkpoint=True):
    return sim.rollout(state, dt, frames, save_every, save_particles, checkpoint)


def _segment_length(save_every: int, checkpoint):
    """Steps per rematerialised segment, or None for no checkpointing."""
    if checkpoint is False or checkpoint is None:
        return None
    if checkpoint is True:
        divisors = [d for d in range(1, save_every + 1) if save_every % d == 0]
        return min(divisors, key=lambda d: abs(d - math.sqrt(save_every)))
    check(isinstance(checkpoint, (int, np.integer)) and checkpoint >= 1 and save_every % checkpoint == 0,
          f"checkpoint = {checkpoint!r} must be True, False or a positive divisor of save_every = {save_every}")
    return int(checkpoint)


def _raise_if_failed(failure: Failure, dt, state0):
    step = int(failure.step)
    if step < 0:
        return
    cause = CAUSES.get(int(failure.cause), "unknown")
    cause = f"{cause} (particle {int(failure.particle)})"
    t = float(state0.time) + (step - int(state0.step)) * float(np.asarray(dt))
    raise InstabilityError(step, cause, t)
