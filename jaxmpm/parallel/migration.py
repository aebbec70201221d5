"""Particles that cross a slab face move to the neighbouring device, in fixed-capacity buffers.

Each device keeps its particles in a buffer of fixed capacity with a validity mask (shapes stay
static, so one compiled program serves every step).  :func:`migrate` (inside ``shard_map``) sends the
particles whose new owner is the device above or below in buffers of ``exchange`` slots each way
(one ``lax.ppermute`` per direction of every per-particle array), removes them from the sender and
writes the received ones into the receiver's free slots.  Nothing is lost silently: the returned
``overflow`` counts the particles that did not fit -- more leavers than exchange slots, or more
arrivals than free slots -- so that a run can stop with an error naming the capacity option before
any particle is dropped (the sharded driver checks it every step).

With the CFL condition a particle crosses at most one slab face per step, so neighbours suffice.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp


def _compact(keep, size: int):
    """The indices of the first ``size`` True entries of ``keep`` (in order; the rest of the
    ``size`` slots point at entry 0), and how many True entries there are in all.  A prefix sum
    and one scatter: linear in the buffer, where a sort is not."""
    rank = jnp.cumsum(keep.astype(jnp.int32)) - 1
    where = jnp.where(keep & (rank < size), rank, size)  # size: dropped
    index = jnp.zeros((size,), jnp.int32).at[where].set(jnp.arange(keep.shape[0], dtype=jnp.int32), mode="drop")
    return index, jnp.sum(keep.astype(jnp.int32))


def migrate(particles, valid, destination, exchange: int, axis_name: str, devices: int):
    """Move particles to their destination device (inside ``shard_map`` over ``axis_name``).

    Args:
        particles: a pytree of per-particle arrays, each (C, ...) for a buffer of capacity C.
        valid: (C,) bool, the slots that hold a particle.
        destination: (C,) int, the device each particle belongs to now (this device's index for
            those that stay); a particle may move to a neighbour only.
        exchange: the slots each way per step (a static int).
        axis_name: the mesh axis of the slabs.
        devices: the number of devices along it.

    Returns:
        (particles, valid, overflow, moving): the buffer after the exchange, the number of particles
        that did not fit (0 when nothing was lost; the caller stops the run otherwise) and the
        number that changed device, both over every device.
    """
    here = jax.lax.axis_index(axis_name)
    stray = valid & (jnp.abs(destination - here) > 1)  # more than one slab in a step: not supported
    leaving = valid & (destination != here) & ~stray
    moving = jax.lax.psum(jnp.sum(leaving.astype(jnp.int32)), axis_name)
    if devices > 1:  # one device: nothing to exchange, only strays to count
        # a step where no particle changes device (most steps) skips the exchange
        particles, valid, lost = jax.lax.cond(
            moving > 0, lambda: _exchange(particles, valid, destination, here, exchange, axis_name, devices),
            lambda: (particles, valid, jnp.zeros_like(destination, dtype=jnp.int32, shape=())))
    else:
        lost = jnp.zeros((), jnp.int32)
    lost = lost + jnp.sum(stray.astype(jnp.int32))
    return particles, valid, jax.lax.psum(lost.astype(jnp.int32), axis_name), moving


def _exchange(particles, valid, destination, here, exchange: int, axis_name: str, devices: int):
    """:func:`migrate`'s exchange with the two neighbours: (particles, valid, particles that did not
    fit on this device)."""
    capacity = valid.shape[0]
    up, down = valid & (destination == here + 1), valid & (destination == here - 1)
    leaving_up, n_up = _compact(up, exchange)
    leaving_down, n_down = _compact(down, exchange)

    def pack(index, count):
        return jax.tree_util.tree_map(lambda a: a[index], particles), jnp.arange(exchange) < count

    to_above, to_below = pack(leaving_up, n_up), pack(leaving_down, n_down)
    upward = [(k, k + 1) for k in range(devices - 1)]
    downward = [(k + 1, k) for k in range(devices - 1)]
    from_below = jax.lax.ppermute(to_above, axis_name, upward)
    from_above = jax.lax.ppermute(to_below, axis_name, downward)

    # the leavers that fitted leave; the rest stay put and are counted as lost for the caller to stop
    sent = jnp.zeros((capacity,), bool)
    sent = sent.at[leaving_up].max(jnp.arange(exchange) < n_up)
    sent = sent.at[leaving_down].max(jnp.arange(exchange) < n_down)
    valid = valid & ~sent

    arrivals = jax.tree_util.tree_map(lambda a, b: jnp.concatenate([a, b]), from_below[0], from_above[0])
    arrived = jnp.concatenate([from_below[1], from_above[1]])
    slots, free = _compact(~valid, 2 * exchange)  # the first free slots, in order
    rank = jnp.cumsum(arrived.astype(jnp.int32)) - 1  # the i-th arrival takes the i-th free slot
    fits = arrived & (rank < free)
    target = jnp.where(fits, slots[jnp.clip(rank, 0, 2 * exchange - 1)], capacity)  # capacity: dropped
    particles = jax.tree_util.tree_map(lambda a, b: a.at[target].set(b, mode="drop"), particles, arrivals)
    valid = valid.at[target].set(True, mode="drop")
    lost = (jnp.maximum(n_up - exchange, 0) + jnp.maximum(n_down - exchange, 0)
            + jnp.sum((arrived & ~fits).astype(jnp.int32)))
    return particles, valid, lost.astype(jnp.int32)
