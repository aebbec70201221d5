"""One USL step over the particles in chunks: the same step (:func:`jaxmpm.model.step.step`), with
a working set that fits the CPU's cache.

P2G is a sum over the particles and G2P a map over them, so a step may take its particles a chunk
at a time (003 §2.1):

1. P2G, chunk by chunk: each chunk's stencil and quantities, scattered and added to the nodal
   sums (003 eq. 2.1, 001 eq. 20);
2. the grid solve, once, on the whole grid (:func:`jaxmpm.model.step.grid_phases`);
3. G2P, chunk by chunk: each chunk's stencil again, and its particles' update from the grid
   solution (000 eq. 3.28, 002 eq. 4, the strain and material update).

Both passes are loops over chunks of equal size, so a chunk's stencil and per-slot arrays (about
1 kB a particle in float64 2D, 3 kB in 3D) stay in the cache where a whole step's leave it (benchmarks/README.md,
"The step in chunks").  The G2P pass writes each chunk's new rows over its old ones or stacks them
as a scan's outputs, as the backend says (:data:`jaxmpm.transfer.backend.CHUNK_OUTPUT`).  The price
is a second evaluation of the stencil.
The nodal sums are added chunk by chunk, so a step in chunks equals the whole step to round-off,
not bit for bit; the dissipated energy is the sum of the chunks' shares.
Derivatives go in chunks of their own size, each chunk recomputed in the reverse pass, or differentiate the
whole step, as the backend's table says (:func:`step_in_chunks`); both sizes shrink to fit the device's memory.

Which steps: USL, a scheme whose update is local (``Scheme.local_update``: FLIP, PIC, their
blends, APIC, TPIC, RPIC) and terms that are (``Term.local``: the stress divergence without XPIC
smoothing, the body force, damping, colliders), no mirror planes, the XLA kernel, one device, and a particle
count with a divisor near the chunk size.  :func:`chunk_obstacle` names what keeps a model whole;
the chunk size comes from the backend's table (:data:`jaxmpm.transfer.backend.CHUNK_TABLE`) or
``Simulation(chunk_particles=...)``, and :func:`jaxmpm.backend_info` reports both.
"""

from __future__ import annotations

import contextvars
from functools import partial

import equinox as eqx
import jax
import jax.numpy as jnp

from ..core.fields import GridFields
from ..transfer.backend import chunk_output
from ..transfer.kernels.windowed import active_window
from ..transfer.operators import Transfer
from ..transfer.operators import p2g as scatter_quantities
from .step import folds_force, g2p, grid_phases, p2g_quantities
from .step import step as whole_step


def _particle_part(state):
    """The per-particle part of a state: every field but time, step and dissipated."""
    return (state.x, state.v, state.F, state.mass, state.volume0, state.scheme_state, state.material_state,
            state.fields)


def _with_particle_part(state, part):
    return eqx.tree_at(lambda s: _particle_part(s), state, part, is_leaf=lambda x: x is None)


def num_chunks(num_particles: int, per_chunk: int) -> int:
    """How many chunks of equal size: the least divisor C of ``num_particles`` (N) with
    ceil(N / per_chunk) <= C <= 2 ceil(N / per_chunk), so that a chunk holds between about half of
    ``per_chunk`` and ``per_chunk`` particles; 0 where there is none (a prime N: the step stays whole)."""
    fewest = -(-num_particles // per_chunk)
    for count in range(fewest, 2 * fewest + 1):
        if num_particles % count == 0:
            return count
    return 0


def chunk_obstacle(sim, state, per_chunk: int, kernel: str) -> str | None:
    """Why ``sim`` cannot step ``state`` in chunks of ``per_chunk`` particles on ``kernel``, or None."""
    n = state.x.shape[0]
    if sim.update != "USL":
        return f"update={sim.update!r}: only USL steps in chunks (USF and MUSL scatter twice)"
    if not sim.scheme.local_update:
        return f"{type(sim.scheme).__name__}'s update sums over all particles (an S+ S series)"
    whole = [type(t).__name__ for t in sim.terms if not t.local]
    if whole:
        return f"the term(s) {', '.join(whole)} act on all particles at once (Term.local)"
    if sim.constraint(state.x.dtype).mirror is not None:
        return "mirror planes fold the nodal sums (jm.Mirror)"
    if kernel != "xla":
        return f"the {kernel} kernel runs the whole step"
    if active_window() is not None:
        return "the sharded step runs whole on each device"
    lengths = {leaf.shape[0] if leaf.ndim else None for leaf in jax.tree_util.tree_leaves(_particle_part(state))}
    if lengths != {n}:
        return "the state holds a per-particle leaf of another length"
    if not num_chunks(n, per_chunk):
        return f"{n} particles have no divisor near {n // per_chunk + 1} chunks"
    return None


def step_in_chunks(sim, state, dt, per_chunk: int, derivative_chunk: int):
    """One step whose forward run goes in chunks of about ``per_chunk`` particles (:func:`chunked_step`; 0: the
    whole step, :func:`jaxmpm.model.step.step`), and whose JVPs and gradients go in chunks of about
    ``derivative_chunk`` particles, each chunk's P2G and G2P recomputed in the reverse pass
    (``chunked_step(recompute=True)``: a gradient then holds one chunk's stencil and per-slot arrays at a time;
    0: the whole step's derivatives).  The backend's tables choose both sizes
    (:data:`~jaxmpm.transfer.backend.CHUNK_TABLE`, :data:`~jaxmpm.transfer.backend.DERIVATIVE_CHUNK_TABLE`); all
    give the same values to round-off."""
    forward = partial(chunked_step, per_chunk=per_chunk) if per_chunk else whole_step
    return with_step_derivatives(forward, sim, state, dt, derivative_chunk)


def with_step_derivatives(forward, sim, state, dt, derivative_chunk: int):
    """``forward(sim, state, dt)``, a step computed another way than :func:`jaxmpm.model.step.step` (in chunks, on
    several devices), whose JVPs and gradients are those of the step on one device in chunks of about
    ``derivative_chunk`` particles, each recomputed in the reverse pass (0: the whole step's)."""
    if not derivative_chunk:
        return with_whole_step_derivatives(forward, sim, state, dt)
    return with_derivatives(forward, partial(chunked_step, per_chunk=derivative_chunk, recompute=True), sim, state,
                            dt)


def with_whole_step_derivatives(forward, sim, state, dt):
    """``forward(sim, state, dt)``, a step computed another way than :func:`jaxmpm.model.step.step` (in
    chunks, on several devices), whose JVPs and gradients are the whole step's on one device."""
    return with_derivatives(forward, whole_step, sim, state, dt)


def with_derivatives(forward, differentiated, sim, state, dt):
    """``forward(sim, state, dt)``, whose JVPs (and so gradients) are those of ``differentiated(sim, state,
    dt)``, the same step computed another way.  JAX may trace the JVP later than the call (a jitted rollout
    differentiated from outside), so it is traced in the context of the call: the model's backend policy,
    adjoint and kernel (:mod:`jaxmpm.transfer.backend`'s context variables)."""
    dt = jnp.asarray(dt, state.x.dtype)
    arrays, static = eqx.partition(sim, eqx.is_array)
    context = contextvars.copy_context()

    @jax.custom_jvp
    def stepped(arrays, state, dt):
        return forward(eqx.combine(arrays, static), state, dt)

    @stepped.defjvp
    def _(primals, tangents):
        return context.copy().run(jax.jvp, lambda a, s, d: differentiated(eqx.combine(a, static), s, d), primals,
                                  tangents)

    return stepped(arrays, state, dt)


def sums_in_chunks(sim, state, per_chunk: int) -> dict:
    """``sim._frame_sums(state)`` (energies and momenta, sums over the particles) added up chunk by chunk over
    the step's chunks of about ``per_chunk`` particles: a frame's per-particle terms then take one chunk's
    memory, not the whole state's (XLA's temporaries of a whole mpm88 frame: 40 bytes a particle in
    float32).  Equal to the whole sums to round-off; JVPs and gradients are the whole sums'."""
    count = num_chunks(state.x.shape[0], per_chunk)
    arrays, static = eqx.partition(sim, eqx.is_array)

    @jax.custom_jvp
    def sums(arrays, state):
        sim = eqx.combine(arrays, static)
        split = jax.tree_util.tree_map(lambda a: a.reshape((count, -1) + a.shape[1:]), _particle_part(state))

        def add_chunk(total, part):
            return jax.tree_util.tree_map(jnp.add, total, sim._frame_sums(_with_particle_part(state, part))), None

        first = _with_particle_part(state, jax.tree_util.tree_map(lambda a: a[0], split))
        zeros = jax.tree_util.tree_map(lambda s: jnp.zeros(s.shape, s.dtype), jax.eval_shape(sim._frame_sums, first))
        return jax.lax.scan(add_chunk, zeros, split)[0]

    @sums.defjvp
    def _(primals, tangents):
        return jax.jvp(lambda a, s: eqx.combine(a, static)._frame_sums(s), primals, tangents)

    return sums(arrays, state)


def chunked_step(sim, state, dt, per_chunk: int, axis_name=None, recompute: bool = False):
    """One USL step of ``sim`` from ``state`` over chunks of about ``per_chunk`` particles (module
    docstring); ``chunk_obstacle`` must be None.  Equal to ``jaxmpm.model.step.step`` to round-off.
    ``axis_name``: ``state`` is one device's share of the particles inside a ``shard_map`` over that
    axis (:mod:`jaxmpm.model.devices`): the nodal sums and the dissipated energy are added across it.
    ``recompute``: for derivatives that go in chunks (:func:`step_in_chunks`), each chunk's P2G and
    G2P are recomputed in the reverse pass (``jax.checkpoint``), and the new rows are a scan's outputs (a
    loop over the rows in place would keep the whole state at every chunk for its reverse pass)."""
    dt = jnp.asarray(dt, state.x.dtype)
    constraint = sim.constraint(state.x.dtype)
    count = num_chunks(state.x.shape[0], per_chunk)
    split = jax.tree_util.tree_map(lambda a: a.reshape((count, -1) + a.shape[1:]), _particle_part(state))
    folded_dt = dt if folds_force(sim) else None

    def nodal_sums(chunk):  # 1. P2G of one chunk: the nodal mass and the columns' sums
        return scatter_quantities(*p2g_quantities(sim, chunk, dt=folded_dt), sim.field_nodes)

    def add_chunk(sums, part):
        return jax.tree_util.tree_map(jnp.add, sums, chunk_sums(_with_particle_part(state, part))), None

    chunk_sums = jax.checkpoint(nodal_sums) if recompute else nodal_sums

    first = _with_particle_part(state, jax.tree_util.tree_map(lambda a: a[0], split))
    zeros = jax.tree_util.tree_map(lambda s: _varying(jnp.zeros(s.shape, s.dtype), axis_name),
                                   jax.eval_shape(nodal_sums, first))
    nodal, _ = jax.lax.scan(add_chunk, zeros, split)
    if axis_name is not None:  # the devices' shares of P2G's sums, added: every device holds the whole grid's
        nodal = jax.lax.psum(nodal, axis_name)
    mass = nodal.pop("mass")
    # 2. the grid solve: no local term reads the stencil there
    fields = GridFields(Transfer(None, None, mass, sim.field_nodes), nodal)
    solution = grid_phases(sim, fields, dt, constraint, state.time)

    def updated(part):  # 3. G2P of one chunk, its own stencil again: its new rows and dissipated energy
        chunk = _with_particle_part(state, part)
        transfer = Transfer(sim.stencil(chunk), chunk.mass, mass, sim.field_nodes)
        new = g2p(sim, chunk, transfer, constraint, solution, dt, fields)
        return _particle_part(new), new.dissipated - state.dissipated

    def total(dissipated):  # this chunk's or device's share of the dissipated energy, or every device's
        return dissipated if axis_name is None else jax.lax.psum(dissipated, axis_name)

    if recompute or chunk_output(state.x.dtype) == "stacked":  # backend tuning: how the new rows are written
        chunk_update = jax.checkpoint(updated) if recompute else updated
        _, (parts, dissipated) = jax.lax.scan(lambda _, part: (None, chunk_update(part)), None, split)
        part = jax.tree_util.tree_map(lambda a: a.reshape((-1,) + a.shape[2:]), parts)
        return _finished(state, part, dt, total(jnp.sum(dissipated)))
    size = state.x.shape[0] // count

    def in_place(i, carry):  # each chunk's new rows written over its old ones
        part, dissipated = carry
        rows, lost = updated(jax.tree_util.tree_map(lambda a: jax.lax.dynamic_slice_in_dim(a, i * size, size), part))
        part = jax.tree_util.tree_map(lambda a, b: jax.lax.dynamic_update_slice_in_dim(a, b, i * size, 0), part, rows)
        return part, dissipated + lost

    part, dissipated = jax.lax.fori_loop(0, count, in_place, (_particle_part(state),
                                                              _varying(jnp.zeros_like(state.dissipated), axis_name)))
    return _finished(state, part, dt, total(dissipated))


def _varying(zeros, axis_name):
    """A loop's initial sums, typed as differing between the devices of ``axis_name`` (inside a ``shard_map``
    that checks what varies, as the loop's body makes them); unchanged without an axis."""
    return zeros if axis_name is None else jax.lax.pcast(zeros, (axis_name,), to="varying")


def _finished(state, part, dt, dissipated):
    """The new state: the chunks' particle rows, the clock advanced, the chunks' dissipated energy added."""
    new = _with_particle_part(state, part)
    return eqx.tree_at(lambda s: (s.time, s.step, s.dissipated), new,
                       (state.time + dt, state.step + 1, state.dissipated + dissipated))
