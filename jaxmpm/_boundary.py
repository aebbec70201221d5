"""Velocity boundary conditions on grid nodes.

A condition selects nodes -- a grid face such as ``"x-"`` or a callable ``where(x) -> bool`` on
node coordinates (n, D) -- and constrains some velocity components there:

* ``Fixed(face)``: every component is zero (no-slip wall).
* ``Slip(face)``: the normal component is zero, the tangential ones are free.
* ``Prescribed(where, velocity)``: the given components take the given velocity.

All conditions are compiled into one :class:`Constraint` (mask and values, shape (n, D)),
applied to nodal velocities (000 ch. 1; 003 §2.4).
"""

from __future__ import annotations

from typing import Callable, Union

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ._errors import check
from ._grid import Grid, parse_face

Selector = Union[str, Callable]


def _select(grid: Grid, where: Selector, layers: int) -> np.ndarray:
    if isinstance(where, str):
        return grid.face_mask(where, layers)
    check(callable(where), f"boundary: where={where!r} must be a face like 'x-' or a callable of node coordinates")
    mask = np.asarray(where(grid.node_coordinates()), dtype=bool)
    check(mask.shape == (grid.num_nodes,), "boundary: where(x) must return one bool per node, shape (num_nodes,)")
    return mask


class Constraint(eqx.Module):
    """Constrained components ``mask`` (n, D) and their prescribed ``value`` (n, D)."""

    mask: jnp.ndarray
    value: jnp.ndarray

    def apply(self, u):
        """Impose the prescribed velocities: u <- value on constrained components."""
        return jnp.where(self.mask, self.value, u)

    def zero(self, u):
        """Impose the homogeneous conditions: constrained components set to zero."""
        return jnp.where(self.mask, 0.0, u)

    def prescribed(self, like):
        """The prescribed field g: value on constrained components, zero elsewhere."""
        return jnp.where(self.mask, self.value, 0.0).astype(like.dtype)


class Fixed(eqx.Module):
    """No-slip: all velocity components zero on the selected nodes."""

    where: Selector = eqx.field(static=True)
    layers: int = eqx.field(static=True, default=1)

    def components(self, grid: Grid):
        sel = _select(grid, self.where, self.layers)
        return np.repeat(sel[:, None], grid.dim, axis=1), None


class Slip(eqx.Module):
    """Free slip: the normal velocity component is zero on a face (``axis`` needed for a callable)."""

    where: Selector = eqx.field(static=True)
    layers: int = eqx.field(static=True, default=1)
    axis: int | None = eqx.field(static=True, default=None)

    def components(self, grid: Grid):
        sel = _select(grid, self.where, self.layers)
        if isinstance(self.where, str):
            axis, _ = parse_face(self.where, grid.dim)
        else:
            check(self.axis is not None and 0 <= self.axis < grid.dim,
                  "Slip: give axis=0..D-1 (the normal direction) when 'where' is a callable")
            axis = self.axis
        mask = np.zeros((grid.num_nodes, grid.dim), dtype=bool)
        mask[:, axis] = sel
        return mask, None


class Prescribed(eqx.Module):
    """Prescribed velocity on the selected nodes; ``components`` picks which axes (default all)."""

    where: Selector = eqx.field(static=True)
    velocity: jnp.ndarray
    axes: tuple | None = eqx.field(static=True, default=None)
    layers: int = eqx.field(static=True, default=1)

    def __init__(self, where, velocity, axes=None, layers: int = 1):
        self.where = where
        self.velocity = jnp.atleast_1d(jnp.asarray(velocity, dtype=float))
        self.axes = None if axes is None else tuple(int(a) for a in axes)
        self.layers = layers

    def components(self, grid: Grid):
        sel = _select(grid, self.where, self.layers)
        mask = np.zeros((grid.num_nodes, grid.dim), dtype=bool)
        axes = range(grid.dim) if self.axes is None else self.axes
        for a in axes:
            check(0 <= a < grid.dim, f"Prescribed: axis {a} is not an axis of a {grid.dim}D grid")
            mask[:, a] = sel
        check(self.velocity.shape in ((1,), (grid.dim,)),
              f"Prescribed: velocity must be a scalar or have {grid.dim} components")
        value = jnp.broadcast_to(self.velocity, (grid.dim,))
        return mask, jnp.where(mask, value, 0.0)


def build_constraint(grid: Grid, conditions, dtype) -> Constraint:
    """Fold all conditions into one mask/value pair (later conditions win on overlaps)."""
    mask = np.zeros((grid.num_nodes, grid.dim), dtype=bool)
    value = jnp.zeros((grid.num_nodes, grid.dim), dtype)
    for cond in conditions:
        m, v = cond.components(grid)
        mask = mask | m
        value = jnp.where(m, 0.0 if v is None else v.astype(dtype), value)
    return Constraint(mask=jnp.asarray(mask), value=value)


def as_conditions(boundary) -> tuple:
    if boundary is None:
        return ()
    if isinstance(boundary, (Fixed, Slip, Prescribed)):
        return (boundary,)
    conditions = tuple(boundary)
    for c in conditions:
        check(isinstance(c, (Fixed, Slip, Prescribed)),
              f"boundary: {c!r} is not a boundary condition; use jm.Fixed, jm.Slip or jm.Prescribed")
    return conditions
