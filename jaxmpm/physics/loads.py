"""Loads on chosen particles: tractions on a body's face and point forces (001 eqs. 12-13, 20-21).

* :class:`Traction`  a traction T (force per unit area; constant or T(t)) on the face of the
  particles ``where`` picks at t = 0, through each particle domain's edge on side ``face``:
      f_i,T = int_{S_T} N_i T dS  (001 eqs. 12, 21)
  with one-point quadrature on each loaded particle's edge: f_i += T A_p N_i(x_p + l_p n), l_p the
  particle's half-width along the face normal n (l_p0 F_nn, l_p0 = V0_p^(1/D) / 2) and A_p = J V0_p
  / (2 l_p) the edge's area (1D: 1), the N_i renormalised over the nodes that carry mass (the
  whole load stays on the body).  Exact in 1D; in 2D/3D the edge integral of N_i is taken at
  the edge's centre.  The nodes are those of the edge point, so the load acts at the body's
  surface, not at the particle centres.  GIMP shapes weigh the edge point with their
  domain-averaged S (the same total force; the split between nodes is smoothed).  On an
  axisymmetric grid (001 §7) the force is per radian: A_p is the edge's length times its radius
  (001 eq. 108, traction per radian T r), the reference area A0_p = V0_p F_thth / r_p.
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
from ..core.registry import register_term
from ..core.validate import FINITE
from ..transfer.backend import materialise
from ..transfer.contractions import PerSlot, Weighted
from ..transfer.operators import p2g
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
    """A traction ``traction`` (force per unit area, a (D,) vector or a function of t) on the
    ``face`` ("x+", "y-", ...: the side of the particle domains it acts on) of the particles
    ``where(x0)`` picks (module docstring; 001 eqs. 12, 21).  ``name``: the particle field that
    marks them (change it to put two tractions in one model).  ``basis``: the nodal weights of
    each edge point -- "shape" (default) the model's shape function there (uGIMP: its
    domain-averaged S), "grid" the grid basis N_i itself, 001 eq. 21 as written (uGIMP: the tent;
    the same as "shape" for point particles).  Measured on the axisymmetric ``cylinder`` (uGIMP,
    static solve): "shape" moves 6.7 % of the load one node inward, and the hoop stress of the
    loaded particles stays 3.2 %, 2.5 %, 2.1 % off Lamé at 16, 32, 64 cells; "grid": 1.8 %, 0.9 %,
    0.5 %."""

    traction: jnp.ndarray | Callable
    face: str = eqx.field(static=True)
    where: Callable = eqx.field(static=True)
    name: str = eqx.field(static=True)
    basis: str = eqx.field(static=True, default="shape")

    def __init__(self, where: Callable, traction, face: str, name: str = "traction_face", basis: str = "shape"):
        check(basis in ("shape", "grid"), f"Traction: basis = {basis!r}; choose 'shape' (the model's shape function "
                                          "at the edge point) or 'grid' (the grid basis N_i, 001 eq. 21)")
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

    def nodal_force(self, sim, state, nodal_mass):
        """f_i,T = sum_p T A_p N_i(x_p + l_p n) over the loaded particles (001 eq. 21), the weights
        of each edge point renormalised over the nodes that carry mass: once the surface has moved
        past a node line, N_i of the node beyond (which no particle reaches) would take part of the
        load, and a massless node's force is lost (measured: 3 % of a bar's end load at a strain
        of 1e-3 with 32 cells)."""
        dim = sim.grid.dim
        axis, side = parse_face(self.face, dim)
        reference = state.volume0
        if sim.grid.axisymmetric:  # 001 §7: V0_p = A0_p R_p per radian, R_p = r_p / F_thth
            reference = state.volume0 * state.F[:, 2, 2] / state.x[:, 0]
        half0 = 0.5 * reference ** (1.0 / dim)  # l_p0: the particle domain's half-width
        stretch = state.F[:, axis, axis]
        edge = state.x.at[:, axis].add(side * half0 * stretch)  # x_p + l_p n
        area = jnp.linalg.det(state.F) * state.volume0 / (2.0 * half0 * stretch)  # A_p = V_p / (2 l_p)
        if sim.grid.axisymmetric:  # per radian, at the edge's radius: int T . du r dL (001 eq. 108)
            area = area * edge[:, 0] / state.x[:, 0]
        load = _at(self.traction, state.time, dim, state.x.dtype)
        forces = (state.fields[self.name] * area)[:, None] * load[None, :]
        basis = sim.shape.grid_basis() if self.basis == "grid" else None  # 001 eq. (21): N_i at the edge
        stencil = sim.stencil(state, edge, basis)  # on the particle's own velocity field
        carried = jnp.where(nodal_mass[stencil.index] > 0, stencil.weight, 0.0)  # (K, N)
        total = jnp.sum(carried, axis=0)
        weight = carried / jnp.where(total > 0, total, 1.0)
        return p2g(stencil, {"force": PerSlot(weight[None] * forces.T[:, None, :])}, sim.field_nodes)["force"]


class ParticleForce(Term):
    """A force ``force`` (a (D,) vector or a function of t) on each particle ``where(x0)`` picks,
    f_i += S_ip F_p (001 eqs. 13, 20).  ``name``: the particle field that marks them."""

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
