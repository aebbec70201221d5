"""Velocity boundary conditions on grid nodes.

A condition selects nodes -- a grid face such as ``"x-"`` or a callable ``where(x) -> bool`` on
node coordinates (n, D) -- and constrains some velocity components there:

* ``Fixed(face)``: every component is zero (no-slip wall).
* ``Slip(face)``: the normal component is zero, the tangential ones are free.
* ``Prescribed(where, velocity)``: the given components take the given velocity.
* ``Wall(face, layers)``: one-sided (unilateral) wall: the normal component is zeroed only where
  it points into the wall (Taichi's mpm88 "sticky" walls); it acts on velocities, not on
  accelerations, and on the updated velocity v_tilde = p/m + a dt (see :meth:`Constraint.contact`).

All conditions are compiled into one :class:`Constraint` (mask and values, shape (n, D)),
applied to nodal velocities (000 ch. 1; 003 §2.4).
"""

from __future__ import annotations

import dataclasses
from typing import Callable, Union

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ._errors import check
from ._grid import Grid, parse_face
from ._validate import FINITE, positive_int

Selector = Union[str, Callable]


class NodeSet:
    """A fixed set of grid nodes (a boolean mask over the nodes), compared and hashed by its
    contents.  A model stores the nodes a callable selector picked, not the callable: two
    models built alike are equal (and share compiled code) without any hand-written hashing."""

    def __init__(self, mask):
        self.mask = np.asarray(mask, dtype=bool)
        self.mask.setflags(write=False)
        self._hash = hash((self.mask.shape, self.mask.tobytes()))

    def __eq__(self, other):
        return isinstance(other, NodeSet) and self._hash == other._hash and np.array_equal(self.mask, other.mask)

    def __hash__(self):
        return self._hash

    def __repr__(self):
        return f"NodeSet({int(self.mask.sum())} of {self.mask.size} nodes)"


def _select(grid: Grid, where: Selector, layers: int) -> np.ndarray:
    if isinstance(where, str):
        return grid.face_mask(where, positive_int("boundary", "layers", layers, fix="node layers from the face"))
    if isinstance(where, NodeSet):
        check(where.mask.shape == (grid.num_nodes,), "boundary: this node set belongs to another grid")
        return where.mask
    check(callable(where), f"boundary: where={where!r} must be a face like 'x-' or a callable of node coordinates")
    mask = np.asarray(where(grid.node_coordinates()), dtype=bool)
    check(mask.shape == (grid.num_nodes,), "boundary: where(x) must return one bool per node, shape (num_nodes,)")
    return mask


def resolve(grid: Grid, condition):
    """``condition`` with a callable ``where`` replaced by the :class:`NodeSet` it selects."""
    if isinstance(condition.where, (str, NodeSet)):
        return condition
    nodes = NodeSet(_select(grid, condition.where, condition.layers))
    return dataclasses.replace(condition, where=nodes)


class Constraint(eqx.Module):
    """Constrained components ``mask`` (n, D) and their prescribed ``value`` (n, D); ``wall``
    (n, D) holds the outward normal sign (-1, 0, +1) of one-sided walls, or None without walls."""

    mask: jnp.ndarray
    value: jnp.ndarray
    wall: jnp.ndarray | None = None
    # True when some constrained component may be non-zero (a Prescribed condition)
    inhomogeneous: bool = eqx.field(static=True, default=False)

    def apply(self, u):
        """Impose the prescribed velocities: u <- value on constrained components; then, with
        walls, zero the wall-normal components that point into a wall."""
        u = jnp.where(self.mask, self.value, u)
        if self.wall is None:
            return u
        return jnp.where(self.into_wall(u), 0.0, u)

    def apply_two_sided(self, u):
        """Impose only the two-sided conditions (Fixed, Slip, Prescribed), not the walls."""
        return jnp.where(self.mask, self.value, u)

    def into_wall(self, u):
        """True on wall components (not otherwise constrained) where ``u`` points into the wall."""
        return (self.wall * u > 0) & ~self.mask

    def contact(self, v, a, dt):
        """Grid solve with one-sided walls, as in mpm88: the wall acts on the updated velocity,
        v_tilde = clamp(v + a dt); the lumped ``v`` stays free there and ``a`` becomes the effective
        acceleration (v_tilde - v)/dt, so that every scheme (FLIP's V + S a dt included) feels the
        wall.  ``v`` and ``a`` come with the two-sided conditions already imposed.
        Returns (v, a, v_tilde)."""
        free = v + a * dt
        v_tilde = self.apply(free)
        hit = self.into_wall(free)
        safe_dt = jnp.where(dt > 0, dt, 1.0)
        a = jnp.where(hit & (dt > 0), -v / safe_dt, a)  # v_tilde = 0 there: a = (0 - v)/dt
        return v, a, v_tilde

    def tile(self, copies: int) -> "Constraint":
        """The conditions on ``copies`` stacked copies of the grid (multimaterial mode: every
        material's velocity field obeys the node's conditions)."""
        if copies == 1:
            return self
        rep = lambda a: None if a is None else jnp.tile(a, (copies, 1))  # noqa: E731
        return Constraint(rep(self.mask), rep(self.value), rep(self.wall), self.inhomogeneous)

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
        # an array leaf: jax.grad reaches a wall velocity, and jit does not recompile for a new one
        FINITE.check("Prescribed", "velocity", velocity)
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


class Wall(eqx.Module):
    """One-sided wall on a grid face (``"x-"``, ``"y+"``, ...) ``layers`` nodes thick: the
    wall-normal velocity component is zeroed only where it points into the wall, i.e. v_n < 0 on
    a lower face and v_n > 0 on an upper face (Taichi mpm88: ``if i < bound and v.x < 0: v.x = 0``).
    Tangential components are free.  On a grid of ``n`` cells, ``Wall(face, layers=3)`` is exactly
    mpm88's ``bound = 3`` (nodes i < 3 and i > n - 3)."""

    where: str = eqx.field(static=True)
    layers: int = eqx.field(static=True, default=1)

    def __init__(self, where: str, layers: int = 1):
        check(isinstance(where, str), f"Wall: where = {where!r} must be a grid face like 'x-' or 'y+'")
        self.where = where
        self.layers = positive_int("Wall", "layers", layers, fix="node layers from the face")

    def normal(self, grid: Grid) -> np.ndarray:
        """(n, D) outward normal sign on the wall's nodes, 0 elsewhere."""
        axis, side = parse_face(self.where, grid.dim)
        sel = grid.face_mask(self.where, self.layers)
        out = np.zeros((grid.num_nodes, grid.dim))
        out[:, axis] = np.where(sel, float(side), 0.0)
        return out


def build_constraint(grid: Grid, conditions, dtype) -> Constraint:
    """Fold all conditions into one mask/value pair (later conditions win on overlaps); one-sided
    walls go to ``Constraint.wall`` (two-sided conditions win over walls)."""
    mask = np.zeros((grid.num_nodes, grid.dim), dtype=bool)
    value = jnp.zeros((grid.num_nodes, grid.dim), dtype)
    walls = [c for c in conditions if isinstance(c, Wall)]
    conditions = [c for c in conditions if not isinstance(c, Wall)]
    if walls:
        wall = np.zeros((grid.num_nodes, grid.dim))
        for w in walls:
            n = w.normal(grid)
            wall = np.where(n != 0, n, wall)
    for cond in conditions:
        m, v = cond.components(grid)
        mask = mask | m
        value = jnp.where(m, 0.0 if v is None else v.astype(dtype), value)
    inhomogeneous = any(isinstance(c, Prescribed) for c in conditions)
    return Constraint(mask=jnp.asarray(mask), value=value,
                      wall=jnp.asarray(wall, dtype) if walls else None, inhomogeneous=inhomogeneous)


def as_conditions(boundary, grid: Grid | None = None) -> tuple:
    """The conditions as a tuple; with ``grid``, callable selectors resolved to node sets."""
    conditions = _as_tuple(boundary)
    return conditions if grid is None else tuple(resolve(grid, c) for c in conditions)


def _as_tuple(boundary) -> tuple:
    if boundary is None:
        return ()
    if isinstance(boundary, (Fixed, Slip, Prescribed, Wall)):
        return (boundary,)
    conditions = tuple(boundary)
    for c in conditions:
        check(isinstance(c, (Fixed, Slip, Prescribed, Wall)),
              f"boundary: {c!r} is not a boundary condition; use jm.Fixed, jm.Slip, jm.Prescribed or jm.Wall")
    return conditions
