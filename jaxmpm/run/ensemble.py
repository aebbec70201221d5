"""Ensembles: many simulations in one batched (``jax.vmap``) call, sharded over devices."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from ..core.errors import check
from ..core.params import _where, _with_owner, check_value, set_params
from ..core.validate import POSITIVE, batch_members, positive_int


def _batch_size(tree) -> int:
    sizes = {np.shape(leaf)[0] for leaf in jax.tree_util.tree_leaves(tree) if np.ndim(leaf) > 0}
    check(len(sizes) == 1, f"ensemble: every batched input needs the same leading (batch) size, got {sorted(sizes)}")
    return sizes.pop()


def _check_members(sim, params: dict) -> None:
    """Every member of a concrete parameter batch in its parameter's valid range, before tracing
    (inside the vmap the values are tracers and cannot be checked)."""
    for name, batch in params.items():
        owned = _with_owner(sim, name)
        _where(owned, name)  # an unknown name is an error here, not inside the trace
        batch_members("ensemble", f"params[{name!r}]", batch,
                      lambda i, member, s=owned, n=name: check_value(
                          s, n, member, "ensemble" if i is None else f"ensemble member {i}"))


def _shard(tree, devices):
    mesh = Mesh(np.asarray(devices), ("batch",))
    sharding = NamedSharding(mesh, PartitionSpec("batch"))
    return jax.tree_util.tree_map(lambda a: jax.device_put(a, sharding), tree)


def ensemble(sim, state, dt, steps: int, save_every: int = 1, *, params: dict | None = None, states=None,
             save_particles: bool = False, devices=None):
    """Run a batch of simulations at once.

    The batch is vmapped and, when several devices are present, split over as many of them as
    divide the batch size.  Give ``params``, ``states`` or both; every batched input has the same
    leading (batch) size.

    Args:
        sim: the :class:`jaxmpm.Simulation` every member starts from.
        state: the initial :class:`jaxmpm.State` of every member (unless ``states`` is given).
        dt: the time step, > 0.
        steps: the number of steps, a multiple of ``save_every`` (>= 0).
        save_every: steps between saved frames, a positive integer (default 1).
        params: ``{name: batch}``, parameter names (see :func:`jaxmpm.set_params`: beta,
            alpha_g, alpha_p, E, nu, density, gravity, ...) to arrays whose leading axis is the
            batch; each member is checked against the parameter's valid range.
        states: a batched :class:`jaxmpm.State` (leading axis = batch) to vary the initial
            conditions instead of ``state``.
        save_particles: whether the histories keep the particle positions and velocities
            (default False).
        devices: the devices to shard the batch over; None (the default): ``jax.devices()``.

    Returns:
        ``(final_states, histories, failure_steps)``; ``failure_steps[b]`` is the first unstable
        step of member b, -1 if none.
    """
    check(params is not None or states is not None, "ensemble: give params={name: batch} and/or states=batch")
    check(params is None or isinstance(params, dict), "ensemble: params must be a dict {name: batch}")
    steps = positive_int("ensemble", "steps", steps, low=0)
    save_every = positive_int("ensemble", "save_every", save_every)
    POSITIVE.check("ensemble", "dt", dt)
    _check_members(sim, params or {})
    batch = _batch_size((params or {}, states))
    if steps % save_every:
        check(False, f"ensemble: steps = {steps} must be a multiple of save_every = {save_every}")
    frames = steps // save_every

    dt = jnp.asarray(dt, state.x.dtype)
    devices = jax.devices() if devices is None else list(devices)
    used = max(d for d in range(1, len(devices) + 1) if batch % d == 0)
    inputs = (params or None, states)
    if used > 1:
        inputs = _shard(inputs, devices[:used])
    return _batched_rollout(sim, state, dt, frames, save_every, save_particles, *inputs)


@eqx.filter_jit
def _batched_rollout(sim, state, dt, frames, save_every, save_particles, params, states):
    """vmap of one member's rollout; a module-level filter_jit, so repeated calls reuse the compilation."""

    def member(p, s):
        member_sim = set_params(sim, **p) if p else sim
        final, hist, failure = member_sim.rollout(state if s is None else s, dt, frames, save_every,
                                                  save_particles, checkpoint=False)
        return final, hist, failure.step

    in_axes = (0 if params else None, 0 if states is not None else None)
    return jax.vmap(member, in_axes=in_axes)(params, states)
