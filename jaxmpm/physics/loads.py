"""Loads on chosen particles: tractions on a body's face and point forces (001 eqs. 12-13, 20-21).

* :class:`Traction`  a traction T (force per unit area; constant or T(t)) on the face of the
  particles ``where`` picks at t = 0, through each particle domain's edge on side ``face``:
      f_i,T = int_{S_T} N_i T dS  (001 eqs. 12, 21)
  with one-point quadrature on each loaded particle's edge: f_i += T A_p w_ip, w_ip = N_i(x_p +
  l_p n) the grid basis at the edge point, l_p the particle's half-width along the face normal n
  (l_p0 F_nn, l_p0 = V0_p^(1/D) / 2) and A_p = J V0_p / (2 l_p) the edge's area (1D: 1).  Exact in
  1D; in 2D/3D the edge integral of N_i is taken at the edge's centre.  The nodes are those of the
  edge point, so the load acts at the body's surface, not at the particle centres.  For uGIMP N_i
  is the tent (``basis="grid"``, the default): in 1D A_p N_i(x_p + l_p) is then the face term of
  the particle's own gradient, V_p G_ip = A_p [N_i(x_p + l_p) - N_i(x_p - l_p)] (001 eq. 17), so
  the traction meets the stress that carries it at every node, however little of the node the
  particle reaches (at F = 1: uGIMP's domain keeps its initial size, the edge stretches with F_nn).
  ``basis="shape"`` weighs the edge point with the model's shape function instead (uGIMP: the
  tent averaged over a domain centred on the edge, half of it outside the body).  Each node's
  share is bounded by its reach, sum_p A_p w_ip <= sum_p V_p |G_ip . n| (001 eqs. 15, 17: the
  force per unit traction that the stress carrying T into the body exerts on the node;
  :func:`bounded_shares`), and each particle's weights are renormalised to 1, so the
  whole load stays on the body (a node without mass has no reach).  On an axisymmetric grid
  (001 §7) the force is per radian: A_p is the edge's length times its radius (001 eq. 108,
  traction per radian T r), the reference area A0_p = V0_p F_thth / r_p.
* :class:`ParticleForce`  a force F (constant or F(t)) on each particle ``where`` picks at t = 0,
  distributed by the particle's own shape functions: f_i += S_ip F_p  (001 eqs. 13, 20).

The particles are chosen once, from their initial positions, and carried as a particle field
(0 or 1; not saved), so the load follows them as the body moves.
"""

from __future__ import annotations

from typing import Callable

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ..core.errors import check
from ..core.fields import ParticleField
from ..core.grid import parse_face
from ..core.linalg import det
from ..core.registry import register_term
from ..core.validate import FINITE
from ..transfer.backend import materialise
from ..transfer.contractions import PerSlot, Weighted
from ..transfer.operators import p2g, slot_values
from .term import Term


def _load(owner: str, name: str, value):
    """A constant vector load (a float leaf) or a callable of time, checked."""
    if callable(value):
        return value
    return FINITE.leaf(owner, name, value, fix="a finite vector (one component per dimension) or a function of t")


def _at(load, t, dim: int, dtype):
    value = jnp.asarray(load(t) if callable(load) else load, dtype)
    check(value.shape in ((), (dim,)), f"load of shape {value.shape}: give {dim} components")
    return jnp.broadcast_to(value, (dim,))


def _chosen(owner: str, where: Callable):
    check(callable(where), f"{owner}: where = {where!r} must be a function of the initial positions x (N, D) -> bool")

    def initial(x):
        picked = np.asarray(where(np.asarray(x)), dtype=bool)
        check(picked.shape == (x.shape[0],), f"{owner}: where(x) must return one bool per particle")
        check(picked.any(), f"{owner}: where(x) picks no particle; check the region against the body")
        return picked.astype(float)

    return initial


class Traction(Term):
    """A traction (force per unit area) on one face of the particle domains of the particles
    ``where(x0)`` picks (module docstring; 001 eqs. 12, 21).  The ``basis`` options: "grid" the
    grid basis N_i itself, 001 eq. 21 as written (uGIMP: the tent), "shape" the model's shape
    function there (uGIMP: its domain-averaged S; the same as "grid" for point particles: linear,
    B-splines).  Measured on the axisymmetric ``cylinder``
    (uGIMP, static solve, ``experiments/axisymmetric.py``): "shape" moves 6.7 % of the load one
    node inward, and the hoop stress stays 3.2 %, 2.4 %, 2.0 % off Lamé at 16, 32, 64 cells;
    "grid": 1.8 %, 0.9 %, 0.5 %.  A uGIMP bar (32 cells) settled under an end traction: "grid" puts
    every particle within 0.15 % of sigma / E, "shape" the last particles up to 15 % off.  Both
    are bounded at any face position by the nodes' reach (:func:`bounded_shares`).

    Args:
        where: ``where(x0) -> bool`` (N,) of the initial positions x0 (N, D): the loaded
            particles, chosen once; it must pick at least one.
        traction: T, a finite (D,) vector (a differentiable leaf) or a function T(t) -> (D,);
            per radian times the radius on an axisymmetric grid (001 eq. 108).
        face: the side of the particle domains it acts on: "x+", "y-", ...
        name: the particle field that marks the loaded particles (default "traction_face");
            change it to put two tractions in one model.
        basis: the nodal weights of each edge point: "grid" (default) or "shape".
    """

    traction: jnp.ndarray | Callable
    face: str = eqx.field(static=True)
    where: Callable = eqx.field(static=True)
    name: str = eqx.field(static=True)
    basis: str = eqx.field(static=True, default="grid")

    def __init__(self, where: Callable, traction, face: str, name: str = "traction_face", basis: str = "grid"):
        check(basis in ("grid", "shape"), f"Traction: basis = {basis!r}; choose 'grid' (the grid basis N_i at the "
                                          "edge point, 001 eq. 21; the default) or 'shape' (the model's shape "
                                          "function there)")
        self.basis = basis
        self.where = where
        _chosen("Traction", where)
        self.traction = _load("Traction", "traction", traction)
        check(isinstance(face, str) and len(face) == 2 and face[1] in "+-",
              f"Traction: face = {face!r}; give the side of the loaded particles' domains, e.g. 'x+'")
        self.face = face
        self.name = name

    def particle_fields(self) -> tuple:
        return (ParticleField(self.name, initial=_chosen("Traction", self.where), save=False,
                              doc="1 on the particles whose domain face carries the traction"),)

    @property
    def reach_column(self) -> str:
        return f"{self.name}_reach"

    def p2g_quantities(self, sim, state, stencil) -> dict:
        """The nodes' reach R_i = sum_p V_p |G_ip . n| over every particle (:func:`bounded_shares`),
        in the step's one P2G pass."""
        axis, _ = parse_face(self.face, sim.grid.dim)
        volume = det(state.F) * state.volume0  # V_p (per radian on an r-z grid, 001 §7)
        return {self.reach_column: PerSlot(volume[None, :] * jnp.abs(stencil.gradient[axis]))}

    def nodal_force(self, sim, state, nodal):
        """f_i,T = sum_p T A_p w_ip over the loaded particles (001 eq. 21), w_ip = N_i(x_p + l_p n)
        (``basis``), each node's share bounded by its reach and each particle's weights
        renormalised to 1 (:func:`bounded_shares`)."""
        dim = sim.grid.dim
        axis, side = parse_face(self.face, dim)
        reference = state.volume0
        if sim.grid.axisymmetric:  # 001 §7: V0_p = A0_p R_p per radian, R_p = r_p / F_thth
            reference = state.volume0 * state.F[:, 2, 2] / state.x[:, 0]
        half0 = 0.5 * reference ** (1.0 / dim)  # l_p0: the particle domain's half-width
        stretch = state.F[:, axis, axis]
        edge = state.x.at[:, axis].add(side * half0 * stretch)  # x_p + l_p n
        area = det(state.F) * state.volume0 / (2.0 * half0 * stretch)  # A_p = V_p / (2 l_p)
        if sim.grid.axisymmetric:  # per radian, at the edge's radius: int T . du r dL (001 eq. 108)
            area = area * edge[:, 0] / state.x[:, 0]
        # 0 off the loaded face, and on particles without volume (a sharded run's free slots: A_p = 0/0)
        loaded = (state.fields[self.name] != 0) & (state.volume0 > 0)
        area = jnp.where(loaded, state.fields[self.name] * area, 0.0)
        load = _at(self.traction, state.time, dim, state.x.dtype)
        basis = sim.shape.grid_basis() if self.basis == "grid" else None  # 001 eq. (21): N_i at the edge
        stencil = sim.stencil(state, edge, basis)  # on the particle's own velocity field
        weight = bounded_shares(sim, stencil, area, nodal[self.reach_column])
        forces = area[:, None] * load[None, :]
        return p2g(stencil, {"force": PerSlot(weight[None] * forces.T[:, None, :])}, sim.field_nodes)["force"]


def bounded_shares(sim, stencil, area, reach):
    """The weights w_ip (K, N) of the loaded particles' edge points (``stencil``, ``area`` A_p: 0 off
    the face), each node's share Q_i = sum_p A_p w_ip bounded by its ``reach`` R_i = sum_p V_p
    |G_ip,n| over every particle (n the face normal; 001 eqs. 15, 17; scattered with the step's
    P2G), then renormalised to 1 per particle: w_ip min(1, R_i / Q_i) / sum_j w_jp min(1, R_j / Q_j).

    |T| R_i is the largest force that the stress T (x) n -- the stress that carries the traction
    into the body across planes normal to n -- exerts on node i through the particles, f_i =
    -sum_p V_p sigma_p G_ip (001 eqs. 15, 20); for a node reached from one side only, as the nodes
    at and beyond the face are, it is that force.  A share above it cannot be balanced by the
    body's stress: the node is not a node of the body, the excess only accelerates it.  Such
    shares arise where the edge point's support reaches a node that the particles barely reach
    (its mass and G_ip -> 0, the share finite): a B-spline node entering a particle's support, the
    domain-averaged uGIMP S at the edge (``basis="shape"``), uGIMP's stretched edge past its
    undeformed domain.  Unbounded, the node's force over its mass grows without limit and the
    particle's F with it (sigma / E = 1e-3: a uGIMP bar filled to a node line, F 1 -> 1.35 in two
    steps with basis="shape"; a cubic B-spline bar whose last particle sits on a node line, strain
    1.8e10 sigma / E within 40 steps; ``tests/test_loads.py``).  Linear shapes never reach the
    bound at rest, so it binds only on barely reached nodes: the settled bar and plate of
    ``tests/test_loads.py`` are bit for bit the same.  It also trims what the edge point gives
    beyond the particles' reach in ordinary positions, which brings the loaded particles closer
    to the exact stress: uGIMP's stretched edge (a settled uGIMP bar in tension, 32 cells: the
    last particles' strain 0.8 % -> 0.12 % off sigma / E) and the B-spline node one cell beyond
    the face (cubic at rest: Q = 1/6 against R = 0.156 per unit area; cylinder, cubic: sigma_thth
    3.2 % -> 2.0 % off Lamé at 16 cells, 3.2 % -> 1.7 % at 32).  A node without mass has R_i = 0."""
    share = p2g(stencil, {"share": PerSlot((area[None, :] * stencil.weight)[None])}, sim.field_nodes)["share"][:, 0]
    over = share > reach
    scale = jnp.where(over, reach / jnp.where(over, share, 1.0), 1.0)  # min(1, R_i / Q_i)
    carried = stencil.weight * slot_values(stencil, scale)
    total = jnp.sum(carried, axis=0, keepdims=True)
    return carried / jnp.where(total > 0, total, 1.0)


class ParticleForce(Term):
    """A force on each particle ``where(x0)`` picks, distributed by its own shape functions:
    f_i += S_ip F_p (001 eqs. 13, 20).

    Args:
        where: ``where(x0) -> bool`` (N,) of the initial positions x0 (N, D), chosen once; it
            must pick at least one particle.
        force: F_p, the force on each picked particle: a finite (D,) vector (a differentiable
            leaf) or a function F(t) -> (D,).
        name: the particle field that marks them (default "point_force"); change it to put two
            point forces in one model.
    """

    force: jnp.ndarray | Callable
    where: Callable = eqx.field(static=True)
    name: str = eqx.field(static=True)

    def __init__(self, where: Callable, force, name: str = "point_force"):
        self.where = where
        _chosen("ParticleForce", where)
        self.force = _load("ParticleForce", "force", force)
        self.name = name

    def particle_fields(self) -> tuple:
        return (ParticleField(self.name, initial=_chosen("ParticleForce", self.where), save=False,
                              doc="1 on the particles the point force acts on"),)

    def p2g_quantities(self, sim, state, stencil) -> dict:
        load = _at(self.force, state.time, sim.grid.dim, state.x.dtype)
        return {"force": Weighted(materialise(state.fields[self.name][:, None] * load[None, :]))}


register_term("traction", Traction, doc="traction on a body's face, int N_i T dS (001 eq. 21)")
register_term("particle_force", ParticleForce, doc="point forces on chosen particles, S_ip F_p (001 eq. 13)")
