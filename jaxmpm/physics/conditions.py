"""Velocity boundary conditions on grid nodes.

A condition selects nodes -- a grid face such as ``"x-"`` or a callable ``where(x) -> bool`` on
node coordinates (n, D) -- and constrains some velocity components there:

* ``Fixed(face)``: every component is zero (no-slip wall).
* ``Slip(face)``: the normal component is zero, the tangential ones are free.
* ``Prescribed(where, velocity)``: the given components take the given velocity.
* ``Wall(face, layers)``: one-sided (unilateral) wall: the normal component is zeroed only where
  it points into the wall (Taichi's mpm88 "sticky" walls); it acts on velocities, not on
  accelerations, and on the updated velocity v_tilde = p/m + a dt (see :meth:`Constraint.contact`).
* ``Slip(normal=n, point=x0)``: free slip on an inclined plane: the nodes on and beyond the plane
  (x - x0).n >= 0 lose their velocity component along n, u <- u - (u.n) n (``Constraint.normal``).
* ``Mirror(face, position)``: a symmetry plane through a node plane: the body continues as its
  mirror image beyond it.  Nodal mass, momentum and force gather the images' contributions (the
  particles' reflections, folded onto the grid: :class:`MirrorMap`), so the normal velocity is odd
  and the tangential velocity even across the plane, and a B-spline stencil that crosses it sees
  the reflected body.  Velocity fields on the ghost nodes beyond the plane are the reflections of
  their mirror nodes; on the plane the normal component is zero.

All conditions are compiled into one :class:`Constraint` (mask and values, shape (n, D)),
applied to nodal velocities (000 ch. 1; 003 §2.4).
"""

from __future__ import annotations

import dataclasses
from typing import Callable, Union

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ..core.errors import check
from ..core.grid import Grid, parse_face
from ..core.validate import FINITE, positive_int

Selector = Union[str, Callable]

# how the grid solve imposes the conditions on a node's constrained components (Simulation's
# ``constrained_force``): "zero" -- v = g and a = 0 (003 §2.4, jaxmpm's default); "reaction" -- the
# lumped v = p/m is kept and the force is replaced by the reaction m (g - v)/dt, so that
# v + a dt = g (NairnMPM 19.0: its FLIP increment S a dt carries the reaction to the particles)
CONSTRAINED_FORCES = ("zero", "reaction")


class NodeSet:
    """A fixed set of grid nodes (a boolean mask over the nodes), compared and hashed by its
    contents.  A model stores the nodes a callable selector picked, not the callable: two
    models built alike are equal (and share compiled code) without any hand-written hashing.
    A condition's ``where`` may be one.

    Args:
        mask: one bool per grid node, (num_nodes,); stored read-only.
    """

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
    if condition.where is None or isinstance(condition.where, (str, NodeSet)):
        return condition  # (an inclined Slip without where selects its nodes from its plane)
    nodes = NodeSet(_select(grid, condition.where, condition.layers))
    return dataclasses.replace(condition, where=nodes)


class _Indices:
    """A fixed integer index array (a static field), compared and hashed by its contents."""

    def __init__(self, index):
        self.array = np.asarray(index, dtype=np.int64).reshape(-1)
        self.array.setflags(write=False)
        self._hash = hash(self.array.tobytes())

    def __eq__(self, other):
        return isinstance(other, _Indices) and self._hash == other._hash and np.array_equal(self.array, other.array)

    def __hash__(self):
        return self._hash


def node_plane(grid: Grid, axis: int, position: float, owner: str) -> int:
    """The node-plane index k with x_axis = lower + k h = ``position`` (a mirror plane must be one)."""
    check(0 <= axis < grid.dim, f"{owner}: mirror axis {axis} on a {grid.dim}D grid")
    plane = (position - grid.lower[axis]) / grid.spacing[axis]
    check(abs(plane - round(plane)) < 1e-9 and 0 <= round(plane) < grid.node_shape[axis],
          f"{owner}: mirror position {position} is not a node plane of axis {axis} "
          f"(nodes every {grid.spacing[axis]:g})")
    return int(round(plane))


def mirror_nodes(grid: Grid, axis: int, plane: int, ghosts: np.ndarray, owner: str) -> tuple:
    """(ghost nodes, their mirror nodes): the flat indices of the nodes ``ghosts`` (a bool mask) and
    of their reflections through the node plane ``plane`` of ``axis``, i_axis -> 2 plane - i_axis."""
    index = grid.node_index_grid()
    reflected = index[ghosts].copy()
    reflected[:, axis] = 2 * plane - reflected[:, axis]
    check(np.all((reflected[:, axis] >= 0) & (reflected[:, axis] < grid.node_shape[axis])),
          f"{owner}: a mirrored node falls off the grid; select fewer node layers beyond the plane")
    return np.nonzero(ghosts)[0], np.ravel_multi_index(tuple(reflected.T), grid.node_shape)


class MirrorMap(eqx.Module):
    """The mirror images of the body through symmetry planes (:class:`Mirror`), on the nodes.

    A particle's image through the plane x_a = c (its reflection x' = x - 2 (x_a - c) e_a, with the
    velocity R V, R = I - 2 e_a e_a^T) adds to node j what the particle adds to the reflected node
    rho(j): S(x' - x_j) = S(x - x_rho(j)).  So the nodal sums of the body and its image are the
    body's own sums *folded* through the plane,

        q_j <- q_j + R q_rho(j)      (rho(j) a ghost node beyond the plane, or j itself on the plane)

    and the ghost nodes carry the reflection of their mirror node, q_g = R q_mirror(g) (R = 1 for a
    scalar such as the mass).  Folding mass, momentum and force (and S+ in the mass-matrix series)
    gives exactly the grid of the doubled body on the doubled domain.  Several planes fold one
    after the other (corner nodes get the double image), then extend one after the other.

    On the sharded path (:mod:`jaxmpm.parallel`) the map acts on a device's window of the grid
    (:meth:`on_window`): the same sums, node by node, on the window's complete planes.  A plane
    normal to y or z pairs nodes of one x plane, always in the same windows; a plane normal to x
    pairs planes at the grid's end, which :class:`jaxmpm.parallel.ShardedSimulation` keeps in the
    edge slab's window (it refuses slabs that would split a pair)."""

    planes: tuple = eqx.field(static=True)  # (axis, ghosts, mirrors, on-plane nodes) per plane, _Indices
    # on a window: (ghosts, mirrors, on-plane nodes) per plane as the window's rows (traced), those
    # outside it one past its end; None: the whole grid
    window_rows: tuple | None = None

    def on_window(self, local_nodes) -> "MirrorMap":
        """The map on a window of the grid: ``local_nodes(nodes)`` gives the window's rows of global
        node numbers, a node outside the window one past its end
        (:meth:`jaxmpm.transfer.kernels.windowed.Window.local_nodes`)."""
        rows = tuple(tuple(local_nodes(nodes.array) for nodes in (g, m, p)) for _, g, m, p in self.planes)
        return MirrorMap(self.planes, rows)

    def _nodes(self):
        """(axis, ghosts, mirrors, on-plane nodes, concatenate, read, write) per plane: the rows of
        the nodal arrays and how to index them (on a window, rows past its end read 0 and are
        not written)."""
        if self.window_rows is None:
            return [(axis, g.array, m.array, p.array, np.concatenate, {}, {}) for axis, g, m, p in self.planes]
        return [(axis, *rows, jnp.concatenate, {"mode": "fill", "fill_value": 0}, {"mode": "drop"})
                for (axis, *_), rows in zip(self.planes, self.window_rows)]

    def reflect(self, q, axis: int):
        """R q: a scalar is even, a vector's ``axis`` component odd."""
        if q.ndim == 1:
            return q
        return q.at[..., axis].multiply(-1.0)

    def fold(self, q):
        """The nodal sum ``q`` (n,) or (n, D) of the particles plus that of their images."""
        for axis, ghosts, mirrors, plane, concatenate, read, write in self._nodes():
            source = concatenate([ghosts, plane])
            target = concatenate([mirrors, plane])
            q = q.at[target].add(self.reflect(q.at[source].get(**read), axis), **write)
        return self.extend(q)

    def extend(self, u):
        """Ghost nodes take the reflection of their mirror node, u_g = R u_mirror(g) (idempotent)."""
        for axis, ghosts, mirrors, _, _, read, write in self._nodes():
            u = u.at[ghosts].set(self.reflect(u.at[mirrors].get(**read), axis), **write)
        return u

    def fold_columns(self, nodal: dict, names) -> dict:
        """``fold`` of the nodal columns ``names`` (the velocity field's mass, momentum and force,
        and the terms' mass-weighted sums, e.g. the force approach's damping rate, 001 eq. 107);
        the other columns (a transport's) keep their own conditions."""
        return {k: self.fold(v) if k in names else v for k, v in nodal.items()}


class Constraint(eqx.Module):
    """Constrained components ``mask`` (n, D) and their prescribed ``value`` (n, D); ``wall``
    (n, D) holds the outward normal sign (-1, 0, +1) of one-sided walls, or None without walls;
    ``normal`` (n, D) the unit normal of inclined slip planes on their nodes (0 elsewhere), or None;
    ``mirror`` the symmetry planes' images (:class:`MirrorMap`), or None; ``impulse`` (n, D) the
    components whose change the particles take as an impulse (``Prescribed(impulse=True)``), or None;
    ``reaction`` how the grid solve imposes them (:data:`CONSTRAINED_FORCES`): False, v = g and
    a = 0 on constrained components (jaxmpm's default), True, v keeps the lumped p/m and the force
    becomes the reaction that brings v + a dt to g (NairnMPM's rule).  A model builds it from its
    conditions (``sim.constraint(dtype)``); the series and schemes read it.

    Args:
        mask: (n, D) bool, the constrained components.
        value: (n, D) their prescribed velocities (0 elsewhere).
        wall: (n, D) the outward normal sign (-1, 0, +1) of one-sided walls, or None (the
            default) without walls.
        inhomogeneous: True when some constrained component may be non-zero (a Prescribed
            condition); default False.
        normal: (n, D) the unit normal of inclined slip planes on their nodes (0 elsewhere), or
            None (the default).
        mirror: the symmetry planes' images (``MirrorMap``), or None (the default).
        impulse: (n, D) bool, the components whose change the particles take as an impulse
            (``Prescribed(impulse=True)``), or None (the default).
        reaction: False (the default): v = g, a = 0 on constrained components; True: the
            reaction force (``Simulation(constrained_force="reaction")``).
    """

    mask: jnp.ndarray
    value: jnp.ndarray
    wall: jnp.ndarray | None = None
    # True when some constrained component may be non-zero (a Prescribed condition)
    inhomogeneous: bool = eqx.field(static=True, default=False)
    normal: jnp.ndarray | None = None
    mirror: MirrorMap | None = None
    impulse: jnp.ndarray | None = None
    reaction: bool = eqx.field(static=True, default=False)

    def particle_impulse(self, v, v_free, mass):
        """The nodal velocity change the particles take at the start of the step, v - v_free on the
        ``impulse`` components of nodes with mass (``Prescribed``), or None without such components."""
        if self.impulse is None:
            return None
        return jnp.where(self.impulse & (mass > 0)[:, None], v - v_free, 0.0)

    def apply(self, u):
        """Impose the prescribed velocities: u <- value on constrained components; then, with
        walls, zero the wall-normal components that point into a wall."""
        u = self._planes(jnp.where(self.mask, self.value, u))
        if self.wall is None:
            return u
        return jnp.where(self.into_wall(u), 0.0, u)

    def apply_two_sided(self, u):
        """Impose only the two-sided conditions (Fixed, Slip, Prescribed, Mirror), not the walls."""
        return self._planes(jnp.where(self.mask, self.value, u))

    def _planes(self, u):
        """Inclined slip, u <- u - (u.n) n on its nodes (homogeneous: the plane does not move), then
        the mirror planes' ghost nodes, u_g = R u_mirror(g)."""
        if self.normal is not None:
            n = self.normal.astype(u.dtype)
            u = u - jnp.sum(u * n, axis=-1, keepdims=True) * n
        return u if self.mirror is None else self.mirror.extend(u)

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
        check(self.mirror is None, "Mirror: symmetry planes act on one velocity field; they do not combine with "
                                   "jm.Contact (multimaterial mode) yet")
        rep = lambda a: None if a is None else jnp.tile(a, (copies, 1))  # noqa: E731
        return Constraint(rep(self.mask), rep(self.value), rep(self.wall), self.inhomogeneous, rep(self.normal),
                          impulse=rep(self.impulse), reaction=self.reaction)

    def zero(self, u):
        """Impose the homogeneous conditions: constrained components set to zero (inclined slip:
        the normal component; mirror planes: the ghosts reflect their mirror nodes)."""
        return self._planes(jnp.where(self.mask, 0.0, u))

    def prescribed(self, like):
        """The prescribed field g: value on constrained components, zero elsewhere (and zero normal
        component on inclined slip nodes)."""
        return self._planes(jnp.where(self.mask, self.value, 0.0).astype(like.dtype))


class Fixed(eqx.Module):
    """No-slip: all velocity components zero on the selected nodes.

    Args:
        where: the nodes: a grid face (``"x-"``, ``"y+"``, ...), a callable ``where(x) -> bool`` of
            the node coordinates (n, D), or a :class:`NodeSet`.
        layers: node layers inward from a face (a positive integer, default 1); ignored for a
            callable ``where``.
    """

    where: Selector = eqx.field(static=True)
    layers: int = eqx.field(static=True, default=1)

    def components(self, grid: Grid):
        sel = _select(grid, self.where, self.layers)
        return np.repeat(sel[:, None], grid.dim, axis=1), None


class Slip(eqx.Module):
    """Free slip: the normal velocity component is zero on a face (``axis`` needed for a callable).

    An inclined plane: ``Slip(normal=n, point=x0)`` (n and x0 of the grid's dimension, n pointing
    out of the body into the wall) acts on the nodes on and beyond the plane, (x_i - x0).n >= 0,
    or on the nodes ``where`` selects; there u <- u - (u.n) n for momentum, force and every
    iterate of the mass-matrix series (:meth:`Constraint.zero`).

    Args:
        where: the nodes: a grid face (``"x-"``, ``"y+"``, ...), a callable ``where(x) -> bool`` of
            the node coordinates (n, D), or a :class:`NodeSet`; None (the default) with an
            inclined plane's ``point``.
        layers: node layers inward from a face (a positive integer, default 1); ignored for a
            callable ``where``.
        axis: the normal axis (0 .. D-1) when ``where`` is a callable; a face names its own.
        normal: an inclined plane's normal, D numbers pointing out of the body into the wall
            (normalised here); not with ``axis``.
        point: a point of the inclined plane, D numbers; needed with ``normal`` unless ``where``
            picks the nodes.
    """

    where: Selector | None = eqx.field(static=True, default=None)
    layers: int = eqx.field(static=True, default=1)
    axis: int | None = eqx.field(static=True, default=None)
    normal: tuple | None = eqx.field(static=True, default=None)
    point: tuple | None = eqx.field(static=True, default=None)

    def __init__(self, where: Selector | None = None, layers: int = 1, axis: int | None = None, normal=None,
                 point=None):
        self.where, self.layers, self.axis = where, layers, axis
        self.normal = self.point = None
        if normal is None:
            check(where is not None and point is None,
                  "Slip: give a face ('x-', ...), a callable where(x) with axis=, or an inclined plane normal=, point=")
            return
        n = np.asarray(normal, dtype=float).reshape(-1)
        check(n.size >= 1 and np.all(np.isfinite(n)) and np.linalg.norm(n) > 0,
              f"Slip: normal = {normal!r} must be a finite non-zero vector (the plane's normal, out of the body)")
        check(axis is None, "Slip: give either axis= (an axis-aligned plane) or normal= (any plane), not both")
        self.normal = tuple(float(c) for c in n / np.linalg.norm(n))
        if where is None:
            x0 = np.asarray(point if point is not None else np.nan, dtype=float).reshape(-1)
            check(point is not None and x0.size == n.size and np.all(np.isfinite(x0)),
                  f"Slip: point = {point!r}; give a point of the inclined plane with {n.size} finite coordinates "
                  "(or where= to pick the nodes yourself)")
            self.point = tuple(float(c) for c in x0)

    def normals(self, grid: Grid) -> np.ndarray:
        """(n, D): the inclined plane's unit normal on its nodes, 0 elsewhere."""
        check(len(self.normal) == grid.dim, f"Slip: normal has {len(self.normal)} components; the grid is {grid.dim}D")
        n = np.asarray(self.normal)
        if self.where is None:
            x = grid.node_coordinates()
            sel = (x - np.asarray(self.point)) @ n >= -1e-9 * grid.h  # on and beyond the plane
        else:
            sel = _select(grid, self.where, self.layers)
        return np.where(sel[:, None], n, 0.0)

    def components(self, grid: Grid):
        if self.normal is not None:  # an inclined plane: no component of the grid axes is constrained
            return np.zeros((grid.num_nodes, grid.dim), dtype=bool), None
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
    """Prescribed velocity on the selected nodes; ``axes`` picks which components (default all).

    ``impulse`` (default True): the condition drives the particles.  The change it makes to the
    nodal velocity at the start of the step, g - p/m (003 §2.1.1, "change nodal momenta to match
    velocity boundary conditions", i.e. the momentum m (g - p/m) on the node), is given back to the
    particles in proportion to their mass share of the node, V_p^n <- V_p^n + sum_i S_pi (g_i - v_i)
    (the particles' momentum change is the nodal one exactly), before the scheme's update.  So a
    FLIP particle on prescribed nodes takes the prescribed velocity (003 eqs. 2.42, 2.51 make the
    condition a force on the updated momentum, which FLIP's increment must carry), and PIC-like
    updates are unchanged (they read only the grid).  ``impulse=False``: the grid alone holds the
    velocity, as a jm.Fixed node holds zero (FLIP particles on the nodes keep their own velocity;
    the convention before core v2).

    Args:
        where: the nodes: a grid face (``"x-"``, ``"y+"``, ...), a callable ``where(x) -> bool`` of
            the node coordinates (n, D), or a :class:`NodeSet`.
        velocity: the prescribed velocity, one number or D components, finite; an array leaf
            (``jax.grad`` reaches it, a new value does not recompile).
        axes: the constrained components, e.g. ``(0,)`` for x only; None (the default): all.
        layers: node layers inward from a face (a positive integer, default 1); ignored for a
            callable ``where``.
        impulse: True (the default): the particles take the nodal change as an impulse;
            False: only the grid holds the velocity.
    """

    where: Selector = eqx.field(static=True)
    velocity: jnp.ndarray
    axes: tuple | None = eqx.field(static=True, default=None)
    layers: int = eqx.field(static=True, default=1)
    impulse: bool = eqx.field(static=True, default=True)

    def __init__(self, where, velocity, axes=None, layers: int = 1, impulse: bool = True):
        self.where = where
        # an array leaf: jax.grad reaches a wall velocity, and jit does not recompile for a new one
        FINITE.check("Prescribed", "velocity", velocity)
        self.velocity = jnp.atleast_1d(jnp.asarray(velocity, dtype=float))
        self.axes = None if axes is None else tuple(int(a) for a in axes)
        self.layers = layers
        check(isinstance(impulse, bool), f"Prescribed: impulse = {impulse!r}; use True (the particles take the "
                                         "prescribed velocity) or False (only the grid holds it)")
        self.impulse = impulse

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
    mpm88's ``bound = 3`` (nodes i < 3 and i > n - 3).

    Args:
        where: the grid face, ``"x-"``, ``"y+"``, ...
        layers: the wall's thickness in node layers from the face, a positive integer
            (default 1).
    """

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


class Mirror(eqx.Module):
    """A symmetry plane (a mirror): the body continues as its mirror image beyond the node plane
    x_axis = ``position``.  ``where`` names the side of the body: ``"x-"`` -- the plane bounds the
    body from below (the image lies at x < position), ``"x+"`` from above.  The particles' images
    are folded onto the grid (:class:`MirrorMap`): normal velocity odd, tangential velocity even,
    zero normal velocity on the plane, and B-spline stencils that cross the plane see the reflected
    body.  Every node on the image side is a ghost node; its reflection must lie on the grid.

    Args:
        where: the body's side of the plane as a face: ``"x-"`` (the image lies below
            x = position), ``"x+"``, ``"y-"``, ...
        position: the plane's coordinate along that axis, finite; it must be a node plane.
    """

    where: str = eqx.field(static=True)
    position: float = eqx.field(static=True)
    layers: int = eqx.field(static=True, default=1)

    def __init__(self, where: str, position):
        check(isinstance(where, str) and len(where) == 2 and where[1] in "+-",
              f"Mirror: where = {where!r}; give the body's side of the plane as a face, 'x-' (the image below "
              "x = position), 'x+', 'y-', ...")
        self.where = where
        self.position = FINITE.real("Mirror", "position", position, fix="the node plane of the symmetry plane")
        self.layers = 1

    def plane(self, grid: Grid) -> tuple:
        """(axis, ghost nodes, mirror nodes, nodes on the plane) as flat node indices."""
        axis, side = parse_face(self.where, grid.dim)
        k = node_plane(grid, axis, self.position, "Mirror")
        index = grid.node_index_grid()[:, axis]
        ghosts = index < k if side < 0 else index > k
        check(np.all(2 * k - index[ghosts] < grid.node_shape[axis]) and np.all(2 * k - index[ghosts] >= 0),
              f"Mirror: the grid reaches further beyond the plane x_{axis} = {self.position:g} than on the body's "
              "side; shrink the grid on the image side (the ghost nodes need mirror nodes)")
        g, m = mirror_nodes(grid, axis, k, ghosts, "Mirror")
        return axis, g, m, np.nonzero(index == k)[0]


def build_constraint(grid: Grid, conditions, dtype, constrained_force: str = "zero") -> Constraint:
    """Fold all conditions into one mask/value pair (later conditions win on overlaps); one-sided
    walls go to ``Constraint.wall`` (two-sided conditions win over walls), inclined slip planes to
    ``Constraint.normal``, symmetry planes to ``Constraint.mirror`` (their plane nodes slip);
    ``constrained_force`` (:data:`CONSTRAINED_FORCES`) sets ``Constraint.reaction``."""
    check(constrained_force in CONSTRAINED_FORCES, f"constrained_force = {constrained_force!r}; choose 'zero' "
          "(v = g, a = 0 on constrained nodes, jaxmpm's default) or 'reaction' (v = p/m, the force the reaction "
          "m (g - v)/dt: NairnMPM's rule)")
    mask = np.zeros((grid.num_nodes, grid.dim), dtype=bool)
    value = jnp.zeros((grid.num_nodes, grid.dim), dtype)
    walls = [c for c in conditions if isinstance(c, Wall)]
    mirrors = [c.plane(grid) for c in conditions if isinstance(c, Mirror)]
    inclined = [c for c in conditions if isinstance(c, Slip) and c.normal is not None]
    conditions = [c for c in conditions if not isinstance(c, (Wall, Mirror))]
    normal = None
    if inclined:
        normal = np.zeros((grid.num_nodes, grid.dim))
        for c in inclined:
            n = c.normals(grid)
            normal = np.where(np.any(n != 0, axis=1, keepdims=True), n, normal)
    for axis, _, _, on_plane in mirrors:
        mask[on_plane, axis] = True  # the plane slips: the normal velocity is odd, so zero there
    if walls:
        wall = np.zeros((grid.num_nodes, grid.dim))
        for w in walls:
            n = w.normal(grid)
            wall = np.where(n != 0, n, wall)
    impulse = np.zeros((grid.num_nodes, grid.dim), dtype=bool)
    for cond in conditions:
        m, v = cond.components(grid)
        mask = mask | m
        value = jnp.where(m, 0.0 if v is None else v.astype(dtype), value)
        impulse = np.where(m, getattr(cond, "impulse", False), impulse)  # later conditions win
    inhomogeneous = any(isinstance(c, Prescribed) for c in conditions)
    mirror = MirrorMap(tuple((axis, _Indices(g), _Indices(m), _Indices(p)) for axis, g, m, p in mirrors)) \
        if mirrors else None
    return Constraint(mask=jnp.asarray(mask), value=value,
                      wall=jnp.asarray(wall, dtype) if walls else None, inhomogeneous=inhomogeneous,
                      normal=None if normal is None else jnp.asarray(normal, dtype), mirror=mirror,
                      impulse=jnp.asarray(impulse) if impulse.any() else None,
                      reaction=constrained_force == "reaction")


def as_conditions(boundary, grid: Grid | None = None) -> tuple:
    """The conditions as a tuple; with ``grid``, callable selectors resolved to node sets."""
    conditions = _as_tuple(boundary)
    return conditions if grid is None else tuple(resolve(grid, c) for c in conditions)


def _as_tuple(boundary) -> tuple:
    if boundary is None:
        return ()
    if isinstance(boundary, (Fixed, Slip, Prescribed, Wall, Mirror)):
        return (boundary,)
    check(isinstance(boundary, (tuple, list)),
          f"boundary = {boundary!r}: give a condition (jm.Fixed, jm.Slip, jm.Prescribed, jm.Wall, jm.Mirror), a "
          "tuple or list of them, or None (no conditions)")
    conditions = tuple(boundary)
    for c in conditions:
        check(isinstance(c, (Fixed, Slip, Prescribed, Wall, Mirror)),
              f"boundary: {c!r} is not a boundary condition; use jm.Fixed, jm.Slip, jm.Prescribed, jm.Wall or "
              "jm.Mirror")
    return conditions
