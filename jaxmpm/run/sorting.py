"""Particles sorted by cell every K steps, their permutation carried by the run, outputs in the user's order.

P2G scatters and G2P gathers touch the nodes of each particle's cell. With the particles in the order
their cells are numbered (C order, :class:`jaxmpm.Grid`), neighbouring particles touch neighbouring nodes
and a GPU's gathers coalesce (GPU MPM codes keep particles in cell order, Gao et al. 2018): on an H100,
1M particles in 3D, the XLA step's G2P gather fell from 0.735 to 0.155 ms per step and the step from 3.93
to 3.55 ms (benchmarks/gpu_profile.py, gpu.py ``--sort-every 16``). In dense 2D the same order makes the
scatter's atomic adds contend on shared nodes (mpm88 0.51-0.84x), and on the CPU it gains nothing
(0.89-0.98x). Particles drift, so the order is renewed every ``K`` steps (``Simulation(sort_every=K)``;
the default, "auto", takes K from the backend's table, :data:`jaxmpm.transfer.backend.SORT_TABLE`: 16 for
3D on a GPU from 131k particles, else never).

The permutation is part of the run's carry, never of the user's state: ``order[i]`` is the user's index of
the particle in row ``i`` of the sorted state.  Every frame and the final state are put back in the user's
order before they leave the run (:meth:`Sorting.in_user_order`), and a failure names the user's particle;
``save_h5``, diagnostics, ``resume`` and ``sim.step`` see what they always saw.  Only the order of the
floating-point sums in P2G changes, so a sorted run equals an unsorted one to round-off
(tests/test_sorting.py).
"""

from __future__ import annotations

from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp

from ..core.state import State, per_particle


class Order(NamedTuple):
    """The run's particle order: ``rows[i]`` is the user's index of the particle in row ``i``;
    ``count`` the steps taken since the run began (a value of the loop's own, so that under ``vmap``
    the renewal stays one conditional, not a select that sorts every step)."""

    rows: jnp.ndarray
    count: jnp.ndarray


class Sorting(eqx.Module):
    """Sort the particles of a run by cell every ``every`` steps on ``grid``'s cells."""

    grid: object = eqx.field(static=True)
    every: int = eqx.field(static=True)

    def cell(self, x):
        """The C-order number of the cell holding each position (N, D) -> (N,) int32; positions
        outside the grid count in the nearest cell (they stop the run anyway)."""
        index = jnp.zeros(x.shape[:1], jnp.int32)
        for axis, (lo, h, n) in enumerate(zip(self.grid.lower, self.grid.spacing, self.grid.cells)):
            i = jnp.clip(jnp.floor((x[:, axis] - lo) / h), 0, n - 1).astype(jnp.int32)
            index = index * n + i
        return index

    @staticmethod
    def start(state: State) -> Order:
        """The order at a run's start: the user's, to be sorted before the first step (:meth:`renew`)."""
        return Order(jnp.arange(state.x.shape[0], dtype=jnp.int32), jnp.zeros((), jnp.int32))

    def renew(self, state: State, order: Order) -> tuple:
        """Before a step: the state sorted again when ``every`` steps have passed since the last sort."""

        def resort(state, rows):
            again = jnp.argsort(self.cell(jax.lax.stop_gradient(state.x)), stable=True).astype(jnp.int32)
            return permute(state, again), rows[again]

        due = (order.count % self.every) == 0
        state, rows = jax.lax.cond(due, resort, lambda s, r: (s, r), state, order.rows)
        return state, Order(rows, order.count + 1)

    @staticmethod
    def in_user_order(state: State, order: Order) -> State:
        """``state`` (rows in sorted order) with its rows back in the user's order."""
        n = order.rows.shape[0]
        inverse = jnp.zeros_like(order.rows).at[order.rows].set(jnp.arange(n, dtype=order.rows.dtype))
        return permute(state, inverse)

    @staticmethod
    def user_particle(particle, order: Order):
        """The user's index of row ``particle`` (-1 stays -1)."""
        return jnp.where(particle >= 0, order.rows[jnp.maximum(particle, 0)], particle)


def permute(state: State, rows) -> State:
    """``state`` with every per-particle array's rows taken in the order ``rows`` (a gather each)."""
    n = state.x.shape[0]
    return jax.tree_util.tree_map(lambda a: a[rows] if per_particle(a, n) else a, state)
