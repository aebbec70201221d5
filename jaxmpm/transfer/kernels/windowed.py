"""The transfer kernels seen through a window of the grid: one device's slab on the sharded path.

On the sharded path (:mod:`jaxmpm.parallel`) each device holds its nodal fields on a *window*, a
contiguous range of node numbers of every velocity field (its slab and a halo), while stencils are
computed on the global grid as on one device.  Inside :func:`use_window`, the transfer layer's
kernel is wrapped (:func:`in_window`): node numbers are shifted into the window (integer arithmetic,
so weights are bitwise those of one device), P2G scatters into the window and completes its sums
with the neighbours (the window's ``complete``: one halo exchange per P2G), and G2P gathers from
window arrays.  The physics above the transfer layer does not change.
"""

from __future__ import annotations

import contextlib
import contextvars

import equinox as eqx
import jax
import jax.numpy as jnp

from ..backend import materialise

_window = contextvars.ContextVar("jaxmpm_window", default=None)


class Window:
    """One device's window of the grid, while a sharded step is traced.

    Args:
        num_nodes: the global grid's nodes (per velocity field).
        window_nodes: the window's nodes (per velocity field).
        first_node: the global node number of the window's first node (traced: it depends on the
            device).
        complete: ``complete(nodal, fields)`` sums a window array's P2G contributions with the
            neighbours' (``nodal`` (fields x window_nodes, ...)).
        restrict: ``restrict(nodal, fields)`` cuts a global per-node array (fields x num_nodes, ...)
            to the window (the model's per-node data: the velocity conditions).
        fields: the model's velocity fields (1: node numbers are shifted, with no field to decode).
    """

    def __init__(self, num_nodes: int, window_nodes: int, first_node, complete, restrict, fields: int = 1):
        self.velocity_fields = fields
        self.num_nodes = num_nodes
        self.window_nodes = window_nodes
        self.first_node = first_node
        self.complete = complete
        self.restrict = restrict

    def fields(self, rows: int) -> int:
        """The velocity fields of a global nodal row count."""
        return max(1, rows // self.num_nodes)

    def local_nodes(self, nodes, fields: int = 1):
        """Node numbers ``nodes`` (an int array) of an array of ``fields`` copies of the grid, f n + i
        (copy f, global node i), as the rows f W + i - first_node of that many copies of the window;
        a node outside the window gets the row ``fields`` W, one past the end, which a scatter with
        ``mode="drop"`` skips and a gather with ``mode="fill"`` reads as the fill value."""
        nodes = jnp.asarray(nodes)
        copy, node = (nodes // self.num_nodes, nodes % self.num_nodes) if fields > 1 else (0, nodes)
        local = node - self.first_node
        inside = (local >= 0) & (local < self.window_nodes)
        return jnp.where(inside, copy * self.window_nodes + local, fields * self.window_nodes)

    def local_stencil(self, stencil):
        """``stencil`` with node numbers f n + i (field f, global node i) renumbered f W + i -
        first_node, clipped into the window (a particle outside its window is a failure the
        sharded run reports before its values are used)."""
        index = stencil.index
        first = self.first_node.astype(index.dtype)
        if self.velocity_fields == 1:
            local = jnp.clip(index - first, 0, self.window_nodes - 1)
        else:
            field, node = index // self.num_nodes, index % self.num_nodes
            local = field * self.window_nodes + jnp.clip(node - first, 0, self.window_nodes - 1)
        # evaluated once (a stage boundary, whose predicate reads a float of the stencil): every scatter
        # and gather of the step reads it
        witness = next(leaf for leaf in jax.tree_util.tree_leaves(stencil) if jnp.issubdtype(leaf.dtype, jnp.floating))
        local = materialise((local, witness.reshape(-1)[:1]))[0]
        return eqx.tree_at(lambda s: s.index, stencil, local)


@contextlib.contextmanager
def use_window(window: Window):
    """Trace the enclosed step on ``window`` (the sharded path; see the module docstring)."""
    token = _window.set(window)
    try:
        yield
    finally:
        _window.reset(token)


def active_window() -> Window | None:
    """The window in force for the code being traced, or None (one device: the whole grid)."""
    return _window.get()


def on_window(nodal, fields: int = 1):
    """A global per-node array ``nodal`` (fields x num_nodes, ...) of the model -- the velocity
    conditions, the nodes' positions -- as the step being traced sees it: itself on one device, the
    device's window of it (:meth:`Window.restrict`) on the sharded path."""
    window = active_window()
    return nodal if window is None else window.restrict(nodal, fields)


class WindowedKernel:
    """A kernel's P2G and G2P on a window (see the module docstring)."""

    def __init__(self, base, window: Window):
        self.base = base
        self.window = window

    def p2g(self, stencil, columns: dict, num_nodes: int) -> dict:
        w = self.window
        fields = w.fields(num_nodes)
        nodal = self.base.p2g(w.local_stencil(stencil), columns, fields * w.window_nodes)
        return {name: w.complete(a, fields) for name, a in nodal.items()}

    def gather(self, stencil, u):
        return self.base.gather(self.window.local_stencil(stencil), u)

    def velocity_gradient(self, stencil, v):
        return self.base.velocity_gradient(self.window.local_stencil(stencil), v)

    def scalar_gradient(self, stencil, u):
        return self.base.scalar_gradient(self.window.local_stencil(stencil), u)

    def affine_moment(self, stencil, v):
        return self.base.affine_moment(self.window.local_stencil(stencil), v)


def in_window(kernel):
    """``kernel`` itself, or seen through the window in force (:func:`use_window`)."""
    window = active_window()
    return kernel if window is None else WindowedKernel(kernel, window)
