"""Rigid colliders: level-set bodies that act on the grid velocity (issue 31 item 4).

A collider is a rigid solid given by a level set phi(x) -- negative inside the solid, positive in
the space the material may take -- with the outward normal n(x) = grad phi / |grad phi|:

* :class:`HalfSpace` (a plane with any normal), :class:`SolidBox` (axis-aligned, rotated by
  ``angle`` in 2D), :class:`SolidSphere` (a disk in 2D, a ball in 3D), :class:`SolidCylinder`
  (3D, an infinite cylinder about a given axis) and :class:`SolidUnion` of them (``a | b``;
  phi = min of the parts).  jm.Box, jm.Ball and jm.Disk (the particle regions) are taken as
  SolidBox and SolidSphere.
* It is static, or moves rigidly: a translation with the velocity u(t) and a rotation with the
  angular velocity omega(t) about ``center``, each a constant (an array leaf: ``jax.grad`` reaches
  it) or a callable of time.  The collider's position is the integral of its motion, so at time t
  a point x of space is the body point X = R(t)^T (x - c - d(t)) + c (d = int u dt, R the rotation
  by int omega dt; a callable is integrated by 8-point Gauss-Legendre quadrature, exact for a
  polynomial motion up to degree 15), and the solid moves with the velocity u + omega x (x - c - d).

On the grid nodes x_i inside or touching the collider at the step's start, phi(x_i) <= 0, with
mass, the collider sets the updated velocity v_tilde by its ``condition``, with the relative
velocity v_rel = v - v_c and its normal part v_n = v_rel . n (the standard MPM collider rule,
Stomakhin et al. 2013, "A material point method for snow simulation", §8, as in Taichi's MPM and
HydraxMPM):

* ``"sticky"``: v = v_c;
* ``"slip"``: where v_n < 0 (the node moves into the solid) v_rel <- v_rel - v_n n; a separating
  node (v_n >= 0) is free;
* ``"friction"``: Coulomb friction mu: where v_n < 0, the tangential v_t = v_rel - v_n n is
  reduced by mu |v_n|, v_rel <- max(0, |v_t| + mu v_n) v_t / |v_t| (zero: the node sticks).

It acts in the grid phase "colliders" (:mod:`jaxmpm.physics.term`), after the velocity
conditions, on v_tilde; the lumped v stays free and a takes the change, a <- a + (v_tilde' -
v_tilde)/dt, so that v + a dt = v_tilde' and every particle update (FLIP's V + S a dt too) feels
the collider -- the convention of the one-sided jm.Wall (:meth:`jaxmpm.Constraint.contact`).  USF's
start-of-step velocity and MUSL's re-extrapolated one see it as they see the walls.  In
multimaterial mode (jm.Contact) every velocity field meets it alone.

The force on the collider, F = -sum_i m_i (v_tilde'_i - v_tilde_i)/dt (the material's push on the
solid: a body at rest on a collider floor gives its weight M g), is recorded as each particle's
share in the field ``<name>_force`` and as its components per frame in ``History.totals``
(``<name>_force_x``, ``_y``, ``_z``; saved to HDF5 ``/totals``).
"""

from __future__ import annotations

import math
from typing import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..core.errors import check
from ..core.fields import ParticleField
from ..core.particles import Ball, Box
from ..core.registry import Parameter, register_term
from ..core.safe import safe_norm
from ..core.validate import FINITE, NON_NEGATIVE, POSITIVE, finite_vector, show
from .term import Term

CONDITIONS = ("sticky", "slip", "friction")
AXES = "xyz"
# 8-point Gauss-Legendre rule on [-1, 1]: the integral of a callable motion over [0, t]
_GAUSS_NODES, _GAUSS_WEIGHTS = np.polynomial.legendre.leggauss(8)


# ------------------------------------------------------------------------------------- level sets
class LevelSet(eqx.Module):
    """A solid as a level set: ``distance(x)`` for one point x (D,) is phi(x), negative inside the
    solid (a signed distance for the shapes here; any function whose gradient points out of the
    solid serves).  ``a | b`` is their union.  Subclass it and define ``distance`` (and ``dim``:
    the dimension it is made for, or None for any) for a solid of your own."""

    def distance(self, x):  # pragma: no cover - interface
        raise NotImplementedError

    @property
    def dim(self) -> int | None:
        """The dimension the solid is given in (None: any)."""
        return None

    def __or__(self, other):
        return SolidUnion(self, other)


class HalfSpace(LevelSet):
    """The solid on one side of a plane (a line in 2D, a point in 1D): phi(x) = (x - point) . n,
    n the unit ``normal`` pointing out of the solid (into the material).

    Args:
        point: a point of the plane, one finite coordinate per axis.
        normal: the outward normal, as many finite components, not zero (normalised here).
    """

    point: tuple = eqx.field(static=True)
    normal: tuple = eqx.field(static=True)

    def __init__(self, point, normal):
        self.point = finite_vector("HalfSpace", "point", point)
        n = np.asarray(finite_vector("HalfSpace", "normal", normal), dtype=float)
        check(len(n) == len(self.point), f"HalfSpace: normal has {len(n)} components but point has "
                                         f"{len(self.point)}; give both in the grid's dimension")
        check(np.linalg.norm(n) > 0, f"HalfSpace: normal = {show(normal)} is zero; give the plane's outward normal "
                                     "(out of the solid, into the material), e.g. (0, 1) for a floor")
        self.normal = tuple(float(c) for c in n / np.linalg.norm(n))

    @property
    def dim(self):
        return len(self.point)

    def distance(self, x):
        return jnp.dot(x - jnp.asarray(self.point, x.dtype), jnp.asarray(self.normal, x.dtype))


class SolidBox(LevelSet):
    """A box lower <= x <= upper, in 2D rotated by ``angle`` degrees (counter-clockwise) about its
    centre: phi is the signed distance |max(q, 0)| + min(max_k q_k, 0), q = |X - c| - (upper - lower)/2.

    Args:
        lower: the lower corner, one finite coordinate per axis.
        upper: the upper corner, each coordinate greater than ``lower``'s.
        angle: the rotation about the centre in degrees, 2D only; default 0.
    """

    lower: tuple = eqx.field(static=True)
    upper: tuple = eqx.field(static=True)
    angle: float = eqx.field(static=True, default=0.0)

    def __init__(self, lower, upper, angle: float = 0.0):
        self.lower = finite_vector("SolidBox", "lower", lower)
        self.upper = finite_vector("SolidBox", "upper", upper)
        check(len(self.lower) == len(self.upper), f"SolidBox: lower has {len(self.lower)} axes but upper has "
                                                  f"{len(self.upper)}; give both the same number")
        for a, (lo, hi) in enumerate(zip(self.lower, self.upper)):
            check(hi > lo, f"SolidBox: upper[{a}] = {hi:g} must be greater than lower[{a}] = {lo:g}; "
                           "swap or widen the corners")
        self.angle = float(finite_vector("SolidBox", "angle", angle)[0]) if np.ndim(angle) == 0 else math.nan
        check(math.isfinite(self.angle), f"SolidBox: angle = {show(angle)} must be one number (degrees)")
        check(self.angle == 0 or len(self.lower) == 2,
              f"SolidBox: angle = {self.angle:g} rotates a 2D box only; in {len(self.lower)}D give angle=0 "
              "(rotate a collider with angular_velocity)")

    @property
    def dim(self):
        return len(self.lower)

    def distance(self, x):
        lower, upper = jnp.asarray(self.lower, x.dtype), jnp.asarray(self.upper, x.dtype)
        centre = 0.5 * (lower + upper)
        r = x - centre
        if self.angle != 0:
            c, s = math.cos(math.radians(self.angle)), math.sin(math.radians(self.angle))
            r = jnp.stack([c * r[0] + s * r[1], -s * r[0] + c * r[1]])  # R^T r
        q = jnp.abs(r) - 0.5 * (upper - lower)
        return safe_norm(jnp.maximum(q, 0.0)) + jnp.minimum(jnp.max(q), 0.0)


class SolidSphere(LevelSet):
    """A ball |x - center| <= radius (a disk in 2D, a segment in 1D): phi = |x - center| - radius.

    Args:
        center: the centre, one finite coordinate per axis.
        radius: the radius, positive.
    """

    center: tuple = eqx.field(static=True)
    radius: float = eqx.field(static=True)

    def __init__(self, center, radius):
        self.center = finite_vector("SolidSphere", "center", center)
        self.radius = POSITIVE.real("SolidSphere", "radius", radius, fix="the sphere's radius, > 0")

    @property
    def dim(self):
        return len(self.center)

    def distance(self, x):
        return safe_norm(x - jnp.asarray(self.center, x.dtype)) - self.radius


class SolidCylinder(LevelSet):
    """An infinite circular cylinder in 3D about the line through ``point`` along ``axis``:
    phi = |r - (r . a) a| - radius, r = x - point, a the unit axis.

    Args:
        point: a point of the cylinder's axis, three finite coordinates.
        axis: the axis direction, three finite components, not zero (normalised here).
        radius: the radius, positive.
    """

    point: tuple = eqx.field(static=True)
    axis: tuple = eqx.field(static=True)
    radius: float = eqx.field(static=True)

    def __init__(self, point, axis, radius):
        self.point = finite_vector("SolidCylinder", "point", point)
        a = np.asarray(finite_vector("SolidCylinder", "axis", axis), dtype=float)
        check(len(self.point) == 3 and len(a) == 3,
              f"SolidCylinder: point and axis must have 3 components (a cylinder is 3D; in 2D use SolidSphere), "
              f"got {len(self.point)} and {len(a)}")
        check(np.linalg.norm(a) > 0, f"SolidCylinder: axis = {show(axis)} is zero; give the axis direction, "
                                     "e.g. (0, 0, 1)")
        self.axis = tuple(float(c) for c in a / np.linalg.norm(a))
        self.radius = POSITIVE.real("SolidCylinder", "radius", radius, fix="the cylinder's radius, > 0")

    @property
    def dim(self):
        return 3

    def distance(self, x):
        r = x - jnp.asarray(self.point, x.dtype)
        a = jnp.asarray(self.axis, x.dtype)
        return safe_norm(r - jnp.dot(r, a) * a) - self.radius


class SolidUnion(LevelSet):
    """The union of solids: phi = min over the parts (its normal that of the nearest part).

    Args:
        *parts: two or more level sets (:class:`LevelSet`, or jm.Box / jm.Ball regions), of one
            dimension.
    """

    parts: tuple

    def __init__(self, *parts):
        check(len(parts) >= 1, "SolidUnion: give the solids to unite, e.g. SolidUnion(floor, wall)")
        flat = []
        for p in map(level_set, parts):
            flat.extend(p.parts if isinstance(p, SolidUnion) else (p,))
        dims = {p.dim for p in flat} - {None}
        check(len(dims) <= 1, f"SolidUnion: the parts have dimensions {sorted(dims)}; unite solids of one dimension")
        self.parts = tuple(flat)

    @property
    def dim(self):
        return next((p.dim for p in self.parts if p.dim is not None), None)

    def distance(self, x):
        return jnp.min(jnp.stack([p.distance(x) for p in self.parts]))


def level_set(shape) -> LevelSet:
    """``shape`` as a :class:`LevelSet`: a level set itself, or a particle region jm.Box (a
    SolidBox) or jm.Ball / jm.Disk (a SolidSphere)."""
    if isinstance(shape, LevelSet):
        return shape
    if isinstance(shape, Box):
        return SolidBox(shape.lower, shape.upper)
    if isinstance(shape, Ball):
        return SolidSphere(shape.center, shape.radius)
    check(False, f"Collider: shape = {show(shape)} is not a solid; give a level set (jm.HalfSpace, jm.SolidBox, "
                 "jm.SolidSphere, jm.SolidCylinder, their union a | b) or a jm.Box / jm.Ball region")


# --------------------------------------------------------------------------------------- motion
def _motion(owner: str, name: str, value):
    """A constant rate as an array leaf (jax.grad reaches it), a callable of time, or None."""
    if value is None or callable(value):
        return value
    return jnp.atleast_1d(FINITE.leaf(owner, name, value, fix="a constant rate, or a callable of time t"))


def _integral(rate, t):
    """int_0^t rate(s) ds: constant rates exactly, callables by 8-point Gauss-Legendre quadrature."""
    if not callable(rate):
        return rate * t
    nodes = 0.5 * t * (jnp.asarray(_GAUSS_NODES, t.dtype) + 1.0)
    values = jnp.stack([jnp.asarray(rate(s), t.dtype) for s in nodes])
    return 0.5 * t * jnp.tensordot(jnp.asarray(_GAUSS_WEIGHTS, t.dtype), values, axes=1)


def _size_of_rate(rate) -> int | None:
    """How many numbers a callable rate ``rate(t)`` returns, from its shape at a traced t (no computation); None
    where it cannot be traced (the run then meets the callable's own error)."""
    try:
        out = jax.eval_shape(rate, jax.ShapeDtypeStruct((), jnp.result_type(float)))
    except Exception:  # noqa: BLE001 - a callable of host code: its error is the run's to report
        return None
    return int(np.prod(out.shape)) if hasattr(out, "shape") else None


def _at(rate, t):
    """The rate at time t (a constant: itself)."""
    return jnp.asarray(rate(t) if callable(rate) else rate, t.dtype)


def _rotation(turn, dim: int):
    """The rotation matrix of a rotation by ``turn``: an angle (2D) or a rotation vector (3D,
    Rodrigues' formula; the first-order I + [turn]x near zero keeps the derivative finite)."""
    if dim == 2:
        c, s = jnp.cos(turn[0]), jnp.sin(turn[0])
        return jnp.array([[c, -s], [s, c]])
    angle = safe_norm(turn)
    small = angle < 1e-12
    safe = jnp.where(small, 1.0, angle)
    k = turn / safe
    K = jnp.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]], dtype=turn.dtype)
    eye = jnp.eye(3, dtype=turn.dtype)
    rodrigues = eye + jnp.sin(safe) * K + (1.0 - jnp.cos(safe)) * (K @ K)
    first_order = eye + jnp.array([[0.0, -turn[2], turn[1]], [turn[2], 0.0, -turn[0]], [-turn[1], turn[0], 0.0]])
    return jnp.where(small, first_order, rodrigues)


def _spin(omega, r):
    """omega x r for points r (n, D): 2D omega (1,), 3D omega (3,)."""
    if r.shape[-1] == 2:
        return omega[0] * jnp.stack([-r[:, 1], r[:, 0]], axis=-1)
    return jnp.cross(jnp.broadcast_to(omega, r.shape), r)


# -------------------------------------------------------------------------------------- collider
class Collider(Term):
    """A rigid collider (module docstring): a level-set solid, static or moving, that sets the grid
    velocity on the nodes inside it by a sticky, slip or Coulomb-friction condition, and records
    the force on it.

    Args:
        shape: the solid: a :class:`LevelSet` (jm.HalfSpace, jm.SolidBox, jm.SolidSphere,
            jm.SolidCylinder, a union ``a | b``) or a jm.Box / jm.Ball / jm.Disk region.
        condition: ``"sticky"`` (v = the solid's velocity), ``"slip"`` (the normal velocity into
            the solid removed) or ``"friction"`` (slip with Coulomb friction ``friction``); the
            default "friction" with ``friction=0`` is "slip".
        friction: the Coulomb friction coefficient mu >= 0 of ``condition="friction"`` (default
            0); an array leaf (``jax.grad`` reaches it; the registered parameter ``friction``).
        velocity: the translation velocity u: D numbers (an array leaf), a callable ``u(t) -> (D,)``
            or None (the default): no translation.
        angular_velocity: the angular velocity omega about ``center``: one number in 2D, three in
            3D (an array leaf), a callable of t, or None (the default): no rotation.
        center: the centre of rotation at t = 0, D numbers; needed with ``angular_velocity``.
        name: the collider's name, an identifier (default "collider"): its particle field
            ``<name>_force`` and totals ``<name>_force_x``, ...; give two colliders of a model
            different names.
    """

    local = True  # a condition on nodes, each particle's share gathered at its own nodes (jaxmpm.model.chunks)
    shape: LevelSet
    friction: jnp.ndarray
    velocity: jnp.ndarray | Callable | None
    angular_velocity: jnp.ndarray | Callable | None
    center: tuple | None = eqx.field(static=True)
    condition: str = eqx.field(static=True)
    name: str = eqx.field(static=True)

    def __init__(self, shape, condition: str = "friction", friction=0.0, velocity=None, angular_velocity=None,
                 center=None, name: str = "collider"):
        self.shape = level_set(shape)
        check(isinstance(condition, str) and condition in CONDITIONS,
              f"Collider: condition = {show(condition)}; choose 'sticky' (v = the solid's velocity), 'slip' or "
              "'friction' (Coulomb, with friction=mu)")
        self.condition = condition
        self.friction = NON_NEGATIVE.leaf("Collider", "friction", friction, fix="the Coulomb coefficient mu >= 0")
        check(self.friction.ndim == 0, f"Collider: friction = {show(friction)} must be one number mu >= 0")
        check(condition == "friction" or not _nonzero(friction),
              f"Collider: friction = {show(friction)} applies only to condition='friction', not {condition!r}; "
              "pass condition='friction' or leave friction out")
        self.velocity = _motion("Collider", "velocity", velocity)
        self.angular_velocity = _motion("Collider", "angular_velocity", angular_velocity)
        check(angular_velocity is None or center is not None,
              "Collider: angular_velocity needs center=, the point the solid turns about at t = 0")
        self.center = None if center is None else finite_vector("Collider", "center", center)
        check(isinstance(name, str) and name.isidentifier(),
              f"Collider: name = {show(name)} must be an identifier, e.g. 'floor' (it names the force's field)")
        self.name = name
        dim = self.shape.dim
        if dim is not None:
            self.check_dimension(dim)

    # ------------------------------------------------------------------ checks
    def check_dimension(self, dim: int) -> None:
        """Raise InputError unless the solid and the motion are given in ``dim`` dimensions."""
        check(self.shape.dim in (None, dim), f"Collider: the shape is {self.shape.dim}D but the grid is {dim}D; "
                                             f"give the solid's coordinates in {dim}D")
        if self.velocity is not None and not callable(self.velocity):
            check(self.velocity.shape == (dim,), f"Collider: velocity has {self.velocity.size} components; give "
                                                 f"{dim}, the solid's translation velocity")
        elif self.velocity is not None:
            size = _size_of_rate(self.velocity)
            check(size in (None, dim), f"Collider: velocity(t) returns {size} components; return {dim}, the solid's "
                                       "translation velocity at time t")
        if self.angular_velocity is not None:
            check(dim in (2, 3), f"Collider: angular_velocity in {dim}D; a solid turns in 2D or 3D only")
            want = 1 if dim == 2 else 3
            if not callable(self.angular_velocity):
                check(self.angular_velocity.shape == (want,),
                      f"Collider: angular_velocity has {self.angular_velocity.size} components; give {want} in {dim}D")
            else:
                size = _size_of_rate(self.angular_velocity)
                check(size in (None, want), f"Collider: angular_velocity(t) returns {size} components; return {want} "
                                            f"in {dim}D")
        if self.center is not None:
            check(len(self.center) == dim, f"Collider: center has {len(self.center)} coordinates; give {dim}")

    def check_fields(self, fields: dict) -> None:
        self.check_dimension(fields[f"{self.name}_force"].shape[-1])

    # ------------------------------------------------------------------ the solid at time t
    def _placement(self, t, dim: int):
        """(d, c, R): the translation d = int u, the centre c and the rotation R at time t."""
        d = jnp.zeros(dim, t.dtype) if self.velocity is None else jnp.reshape(_integral(self.velocity, t), (dim,))
        c = jnp.zeros(dim, t.dtype) if self.center is None else jnp.asarray(self.center, t.dtype)
        R = None
        if self.angular_velocity is not None:
            R = _rotation(jnp.reshape(_integral(self.angular_velocity, t), (1 if dim == 2 else 3,)), dim)
        return d, c, R

    def level_set(self, x, t):
        """phi(x) (n,) and the unit outward normal n(x) (n, D) of the solid at time t, at points x (n, D)."""
        x = jnp.asarray(x)
        t = jnp.asarray(t, x.dtype)
        d, c, R = self._placement(t, x.shape[-1])

        def phi(point):
            body = point - c - d
            if R is not None:
                body = R.T.astype(point.dtype) @ body
            return self.shape.distance(body + c)

        one = jax.eval_shape(phi, x[0])
        check(one.shape == (), f"Collider: the level set {type(self.shape).__name__} returned shape {one.shape} for "
                               "one point; its distance(x) of a point (D,) must return one number, phi(x)")
        values, grads = jax.vmap(jax.value_and_grad(phi))(x)
        return values, grads / jnp.where(safe_norm(grads) > 0, safe_norm(grads), 1.0)[:, None]

    def solid_velocity(self, x, t):
        """The solid's velocity u(t) + omega(t) x (x - c - d(t)) at points x (n, D)."""
        t = jnp.asarray(t, x.dtype)
        dim = x.shape[-1]
        v = jnp.zeros_like(x)
        if self.velocity is not None:
            v = v + jnp.reshape(_at(self.velocity, t), (1, dim))
        if self.angular_velocity is not None:
            d, c, _ = self._placement(t, dim)
            v = v + _spin(jnp.reshape(_at(self.angular_velocity, t), (1 if dim == 2 else 3,)), x - (c + d)[None, :])
        return v

    def condition_velocity(self, v, v_solid, normal):
        """The velocity after the condition (module docstring; Stomakhin et al. 2013 §8) for nodes in
        contact with the solid: v (n, D) the nodal velocity, v_solid the solid's, normal the outward n."""
        if self.condition == "sticky":
            return v_solid
        rel = v - v_solid
        vn = jnp.sum(rel * normal, axis=-1, keepdims=True)
        approaching = vn < 0  # separating nodes are free
        tangential = rel - vn * normal
        if self.condition == "slip":
            after = tangential
        else:  # Coulomb: |v_t| reduced by mu |v_n|, clamped at zero (the node sticks)
            vt = safe_norm(tangential)[:, None]
            mu = self.friction.astype(v.dtype)
            scale = jnp.maximum(vt + mu * vn, 0.0) / jnp.where(vt > 0, vt, 1.0)
            after = scale * tangential
        return jnp.where(approaching, after + v_solid, v)

    # ------------------------------------------------------------------ Term hooks
    def particle_fields(self) -> tuple:
        return (ParticleField(f"{self.name}_force", shape=("D",), initial=0.0,
                              doc=f"the particle's share of the force on the collider {self.name!r}"),)

    def collide(self, sim, fields, v, dt, time):
        """Phase "colliders": the condition on the nodes with mass inside the solid at ``time``
        (phi <= 0); returns (v after, {"<name>_acceleration": (v after - v)/dt})."""
        self.check_dimension(sim.grid.dim)
        x = sim.node_positions(v.dtype)  # every velocity field's nodes
        phi, normal = self.level_set(x, time)
        touching = (phi <= 1e-9 * sim.grid.h) & (fields.mass > 0)  # on the surface despite round-off
        after = jnp.where(touching[:, None], self.condition_velocity(v, self.solid_velocity(x, time), normal), v)
        safe_dt = jnp.where(dt > 0, dt, 1.0)
        return after, {f"{self.name}_acceleration": (after - v) / safe_dt}

    def particle_action(self, sim, old, new, transfer, solution, dt):
        """Each particle's share M_p (S a)_p of the force on the solid, -m_i a_i (a the collider's change rate)."""
        share = -transfer.particle_share(solution[f"{self.name}_acceleration"])
        return eqx.tree_at(lambda s: s.fields, new, {**new.fields, f"{self.name}_force": share})

    def totals(self, sim, state) -> dict:
        force = jnp.sum(state.fields[f"{self.name}_force"], axis=0)
        return {f"{self.name}_force_{AXES[k]}": force[k] for k in range(force.shape[0])}

    def attributes(self) -> dict:
        """The collider's set-up as HDF5 root attributes: its condition and its solid (the friction is a
        registered parameter)."""
        return {f"{self.name} condition": self.condition, f"{self.name} shape": " ".join(repr(self.shape).split())}


def _nonzero(value) -> bool:
    try:
        return bool(np.any(np.asarray(value) != 0))
    except Exception:  # traced: cannot tell
        return False


register_term("collider", Collider, doc="a rigid level-set collider: sticky, slip or Coulomb friction on the grid "
                                        "velocity (Stomakhin et al. 2013 §8)",
              parameters=[Parameter("friction", lambda t: t.friction, "the collider's Coulomb friction coefficient mu",
                                    "positive", valid="non-negative", acts=lambda t: None if t.condition == "friction"
                                    else f"acts only on a collider of condition 'friction', and this one's is "
                                         f"{t.condition!r}: build it with jm.Collider(..., condition='friction')")])
