"""``Simulation``: the static system (grid, shape, material, scheme, ...) with ``init``, ``step``
and ``run`` (a ``lax.scan`` rollout that records diagnostics and detects instability)."""

from __future__ import annotations

import math
import warnings
from typing import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from . import _diagnostics as diag
from ._boundary import as_conditions, build_constraint
from ._errors import InstabilityError, check
from ._grid import Grid
from ._materials import Material, _leaf, concrete
from ._particles import Particles
from ._schemes import Damping, Scheme, scheme_from_name
from ._shapes import UGIMP, ShapeFunction, shape_from_name
from ._step import step as _step

UPDATES = {"USF": "USF", "USL": "USL", "USL-": "USL", "MUSL": "MUSL", "USL+": "MUSL"}

CAUSES = {
    1: "NaN or Inf in the particle state",
    2: "J = det F <= 0 (a particle inverted)",
    3: "particles left the grid",
}


class StableTimeStepWarning(UserWarning):
    """dt exceeds the CFL limit h / max(c + |V|)."""


class State(eqx.Module):
    """Particle state: positions ``x`` (N, D), velocities ``v`` (N, D), deformation gradients ``F``
    (N, D, D), masses, reference volumes, time, step count, cumulative dissipated energy, and the
    scheme's extra field ``affine`` (None unless the scheme needs one)."""

    x: jnp.ndarray
    v: jnp.ndarray
    F: jnp.ndarray
    mass: jnp.ndarray
    volume0: jnp.ndarray
    time: jnp.ndarray
    step: jnp.ndarray
    dissipated: jnp.ndarray
    affine: jnp.ndarray | None = None

    @property
    def volume(self):
        """Current volume V0 det F."""
        return self.volume0 * jnp.linalg.det(self.F)


class History(eqx.Module):
    """Saved frames (leading axis T): time, particle x/v (None if not saved), energies, momenta."""

    time: jnp.ndarray
    x: jnp.ndarray | None
    v: jnp.ndarray | None
    kinetic: jnp.ndarray
    strain: jnp.ndarray
    dissipated: jnp.ndarray
    momentum: jnp.ndarray
    angular: jnp.ndarray

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


class Simulation(eqx.Module):
    """An MPM model.  Float parameters (material constants, beta, damping, gravity) are array
    leaves, so ``jax.grad``/``jax.vmap`` reach them; everything that fixes shapes or loop lengths
    is static."""

    grid: Grid
    shape: ShapeFunction
    material: Material
    scheme: Scheme
    damping: Damping | None  # None: no damping in the model (damping=False)
    gravity: jnp.ndarray
    boundary: tuple = eqx.field(static=True)
    update: str = eqx.field(static=True)
    body_force: Callable | None = eqx.field(static=True)

    def __init__(
        self,
        grid: Grid,
        shape: ShapeFunction | str,
        material: Material,
        scheme: Scheme | str,
        damping: Damping | None = None,
        update: str = "USL",
        boundary=None,
        gravity=None,
        body_force: Callable | None = None,
    ):
        check(isinstance(grid, Grid), f"Simulation: grid must be a jm.Grid, got {type(grid).__name__}")
        if isinstance(shape, str):
            shape = shape_from_name(shape)
        check(isinstance(shape, ShapeFunction),
              f"Simulation: unknown shape {shape!r}; use jm.Linear(), jm.UGIMP(), jm.QuadraticBSpline() or jm.CubicBSpline()")
        if isinstance(scheme, str):
            scheme = scheme_from_name(scheme)
        check(isinstance(scheme, Scheme),
              f"Simulation: unknown scheme {scheme!r}; use jm.FLIP, jm.PIC, jm.XPIC, jm.FMPM, jm.APIC or jm.TPIC")
        check(isinstance(material, Material),
              f"Simulation: material must be jm.LinearElastic or jm.NeoHookean, got {type(material).__name__}")
        check(update in UPDATES, f"Simulation: update = {update!r}; choose USF, USL (USL-) or MUSL (USL+)")
        # None: zero damping, still a differentiable parameter; False: no damping in the model at
        # all (nothing compiled for it -- "model no more than a scene needs")
        if damping is False:
            damping = None
        elif damping is None:
            damping = Damping()
        else:
            check(isinstance(damping, Damping),
                  "Simulation: damping must be jm.Damping(grid=..., particle=...), None (zero) or False (none)")
        self.grid = grid
        self.shape = shape
        self.material = material
        self.scheme = scheme
        self.damping = damping
        self.update = UPDATES[update]
        self.boundary = as_conditions(boundary)
        g = jnp.zeros(grid.dim) if gravity is None else _leaf(gravity, "gravity", "Simulation")
        g = jnp.broadcast_to(g, (grid.dim,)) if g.ndim == 0 else g
        check(g.shape[-1:] == (grid.dim,), f"Simulation: gravity must have {grid.dim} components, got shape {g.shape}")
        self.gravity = g
        check(body_force is None or callable(body_force), "Simulation: body_force must be a callable b(x, t) -> (N, D)")
        self.body_force = body_force

    # ------------------------------------------------------------------ state
    def constraint(self, dtype):
        return build_constraint(self.grid, self.boundary, dtype)

    def init(self, particles: Particles) -> State:
        """Initial state from :func:`jaxmpm.fill` output (or any :class:`Particles`)."""
        check(isinstance(particles, Particles), "Simulation.init: pass the jm.Particles returned by jm.fill")
        x = jnp.asarray(particles.x)
        d = self.grid.dim
        check(x.ndim == 2 and x.shape[1] == d, f"Simulation.init: particles have shape {x.shape}; the grid is {d}D")
        xc = concrete(x)
        if xc is not None:
            with jax.ensure_compile_time_eval():  # concrete positions: check even inside jit
                inside = np.asarray(self.shape.inside(self.grid, jnp.asarray(xc)))
            if not inside.all():
                bad = int(np.argmin(inside))
                raise_msg = (
                    f"Simulation.init: particles outside the grid: {int((~inside).sum())} of {inside.size} "
                    f"(first: particle {bad} at {xc[bad].tolist()}); the {type(self.shape).__name__} stencil needs "
                    f"{self.shape.margin} cells of room. Enlarge the grid, e.g. jm.Grid.covering(..., shape=shape)."
                )
                check(False, raise_msg)
        if isinstance(self.shape, UGIMP):
            check(self.shape.ppc == particles.ppc,
                  f"Simulation.init: UGIMP(ppc={self.shape.ppc}) but particles were filled with ppc={particles.ppc}; "
                  "make them equal (the particle half-width is h / (2 ppc))")
        volume = jnp.asarray(particles.volume)
        if particles.mass is None:
            mass = self.material.density * volume
        else:
            mass = jnp.asarray(particles.mass)
            mc, vc, rc = concrete(mass), concrete(volume), concrete(self.material.density)
            if mc is not None and vc is not None and rc is not None:
                check(np.allclose(mc / vc, rc, rtol=1e-6),
                      f"Simulation.init: particles were filled with density {float(np.mean(mc / vc)):.6g} but the "
                      f"material density is {float(rc):.6g}; drop density from jm.fill or make them agree")
        dtype = x.dtype
        n = x.shape[0]
        return State(
            x=x,
            v=jnp.asarray(particles.v, dtype),
            F=jnp.broadcast_to(jnp.eye(d, dtype=dtype), (n, d, d)),
            mass=mass.astype(dtype),
            volume0=volume.astype(dtype),
            time=jnp.zeros((), dtype),
            step=jnp.zeros((), jnp.int32),
            dissipated=jnp.zeros((), dtype),
            affine=self.scheme.initial_affine(particles),
        )

    # ------------------------------------------------------------------- step
    def step(self, state: State, dt) -> State:
        """Advance one time step (pure)."""
        return _step(self, state, dt)

    def stable_dt(self, state: State, cfl: float = 1.0):
        """CFL time step h / max_p(c + |V_p|) times ``cfl``."""
        return diag.stable_dt(self.grid, self.material, state.v, cfl)

    def instability(self, state: State):
        """(cause code, particle index) for the first problem found in ``state``; code 0 = fine."""
        finite = jnp.all(jnp.isfinite(state.x), -1) & jnp.all(jnp.isfinite(state.v), -1)
        finite = finite & jnp.all(jnp.isfinite(state.F), (-1, -2))
        positive = jnp.linalg.det(state.F) > 0
        inside = self.shape.inside(self.grid, state.x)
        code = jnp.where(~jnp.all(finite), 1, jnp.where(~jnp.all(positive), 2, jnp.where(~jnp.all(inside), 3, 0)))
        bad = jnp.where(code == 1, ~finite, jnp.where(code == 2, ~positive, ~inside))
        return code.astype(jnp.int32), jnp.argmax(bad).astype(jnp.int32)

    def diagnostics(self, state: State) -> dict:
        return dict(
            kinetic=diag.kinetic_energy(state),
            strain=diag.strain_energy(state, self.material),
            dissipated=state.dissipated,
            momentum=diag.linear_momentum(state),
            angular=self.scheme.angular_momentum(state),
        )

    def _frame(self, state: State, save_particles: bool) -> History:
        d = self.diagnostics(state)
        return History(
            time=state.time,
            x=state.x if save_particles else None,
            v=state.v if save_particles else None,
            **d,
        )

    # -------------------------------------------------------------------- run
    def rollout(self, state: State, dt, frames: int, save_every: int = 1, save_particles: bool = True,
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
        dt = jnp.asarray(dt, state.x.dtype)
        none = Failure(jnp.array(-1, jnp.int32), jnp.array(0, jnp.int32), jnp.array(-1, jnp.int32))
        segment = _segment_length(save_every, checkpoint)
        remat = (lambda f: f) if segment is None else jax.checkpoint  # noqa: E731

        @remat
        def one_step(carry, _):
            s, fail = carry
            s = self.step(s, dt)
            code, particle = self.instability(s)
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
            return carry, self._frame(carry[0], save_particles)

        (final, failure), frames_hist = jax.lax.scan(one_frame, (state, none), None, length=frames)
        first = self._frame(state, save_particles)
        history = jax.tree_util.tree_map(lambda a, b: jnp.concatenate([a[None], b]), first, frames_hist)
        return final, history, failure

    def run(
        self,
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
        traced = _is_traced((self, state, dt))
        dt = jnp.asarray(dt, state.x.dtype)  # an array, so a new dt value does not recompile
        if not traced:
            dtc = float(np.asarray(dt))
            check(math.isfinite(dtc) and dtc > 0, f"run: dt = {dtc} must be a positive number")
            limit = float(self.stable_dt(state))
            if dtc > limit:
                warnings.warn(
                    f"dt = {dtc:.6g} exceeds the stable limit {limit:.6g} (= h / max(c + |V|)); "
                    f"use dt <= {0.5 * limit:.6g} (CFL 0.5) to stay stable",
                    StableTimeStepWarning,
                    stacklevel=2,
                )
        if traced or (writer is None and not progress):
            final, history, failure = _jit_rollout(self, state, dt, frames, save_every, save_particles,
                                                   checkpoint)
            if not traced and check_stability:
                _raise_if_failed(failure, dt, state)
            return final, history
        return self._run_chunked(state, dt, frames, save_every, save_particles, check_stability,
                                 progress, writer, frames_per_chunk)

    def _run_chunked(self, state, dt, frames, save_every, save_particles, check_stability, progress, writer,
                     frames_per_chunk):
        chunk = frames_per_chunk or max(1, min(frames, 50))
        bar = None
        if progress:
            from tqdm.auto import tqdm

            bar = tqdm(total=frames * save_every, unit="step", desc="jaxmpm")
        pieces = []
        first = jax.tree_util.tree_map(lambda a: a[None], _jit_frame(self, state, save_particles))
        if writer is not None:
            writer.append(first)
        else:
            pieces.append(first)
        done = 0
        try:
            while done < frames:
                n = min(chunk, frames - done)
                start_step = int(state.step)
                new_state, hist, failure = _jit_rollout(self, state, dt, n, save_every, save_particles)
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

    # ------------------------------------------------------------- helpers
    @property
    def dim(self) -> int:
        return self.grid.dim


@eqx.filter_jit
def _jit_frame(sim, state, save_particles):
    return sim._frame(state, save_particles)


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
