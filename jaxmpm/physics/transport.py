"""Transport: heat conduction and diffusion on the particles (001 §8-9), as physics terms.

Conduction is the scalar analogue of the momentum equation (001 §8).  With thermal mass
m_Tp = M_p C_p on the particle (C_p the heat capacity per unit mass) and temperature T_p:

* thermal mass and thermal momentum on the nodes, in the step's one P2G scatter
      m_Ti = sum_p m_Tp S_ip,   p_Ti = sum_p m_Tp T_p S_ip                    (001 eqs. 133, 138)
  (001 eq. 138 writes m_p for m_Tp; the thermal mass is meant), and T_i = p_Ti / m_Ti;
* the heat flux at the particle from the nodal temperatures
      q_p = -k grad T_p = -k sum_i T_i G_ip                                   (001 eq. 137)
  (k a scalar or a D x D tensor), and the nodal heat flow, a second scatter
      Q_i = sum_p V_p (q_p . G_ip + q_s,p S_ip)                              (001 eq. 135)
  with V_p = J_p V0_p the current volume and q_s the heat source per unit volume;
* the thermal momentum update and nodal rate a_Ti = (Q_i + Q_i,q) / m_Ti     (001 eqs. 139-140)
  where Q_i,q is the heat entering through a boundary (001 eq. 136, :class:`Neumann`);
* the particle update by FLIP, T_p += sum_i a_Ti S_ip dt                     (001 eqs. 141, 143)

001 §8 updates temperatures "always ... using FLIP": the PIC update T_p = sum_i (T_i + a_Ti dt) S_ip
(001 eq. 142) replaces the particle values by their grid projection every step, which smooths
(conducts) the field even with k = 0.  ``update="pic"`` is offered only to show that.
``update="xpic:M"`` is XPIC(m) for transport (000 §3.6): T^{n+1} = beta T^n + (1 - beta) S t(m) +
S a_T dt with t(m) = m (t - t*) the XPIC series of the nodal values under S+ weighted by the
capacity (000 eqs. 3.53-3.58); it removes particle-scale (null-space) noise that FLIP keeps,
without PIC's smoothing of what the grid resolves.  ``beta`` blends in FLIP (default 1 for
"flip", 0 otherwise); m = 1 is the blend of 000 eq. (3.60).

Diffusion (001 §9) is the same with the concentration potential mu = c / c_sat for T, the
current particle volume as the "mass" (rho = 1, C_p = 1), the diffusivity D for k
(001 eqs. 146-150): :class:`Diffusion`.

Boundary conditions (the term's ``boundary=``): :class:`Dirichlet` holds the field at a value on
nodes (a fixed temperature or concentration: T_i is the held value in the gradient and in PIC's
projection, and a_Ti = 0 there -- the nodal value does not change -- except at the first step,
where the FLIP particles take the switch-on jump, held value minus the ``initial`` field at the
node, once: :meth:`Transport.switch_on`); :class:`Neumann` adds a prescribed
inward flux per unit area, Q_i,q = flux h^(D-1) on its nodes (the lumped surface integral of 001
eq. 136 for a boundary through a node plane).  Without conditions the boundary is adiabatic /
sealed.

Coupling to mechanics: with ``expansion`` alpha the material sees the elastic part of F,
F_e = F / (1 + alpha (T - T_ref)) (a multiplicative thermal stretch; for small strains the stress
of eps - alpha dT I).  The stable time step of explicit conduction on lumped nodes is
dt <= h^2 / (2 D a) with a = k / (rho C_p) the diffusivity (D the dimension; 1D linear elements:
the largest eigenvalue of the lumped conduction matrix is 4 a / h^2); ``Simulation.stable_dt``
takes the smaller of it and the CFL limit.

Contact interfaces (multimaterial mode, jm.Contact), ``interface=``:

* ``"perfect"`` (default): perfect thermal contact -- the field lives on the grid's nodes whatever
  material is there (the fields' capacities and flows summed per node), so heat crosses an
  interface as within one body (NairnMPM's conduction works on the nodes' global temperature);
* ``"insulated"``: each material conducts within itself, nothing crosses;
* a number h_c >= 0: an interface conductance (flow h_c A (T^b - T^a), imperfect thermal contact,
  the thermal analogue of NairnMPM's imperfect interfaces): each material keeps its own nodal
  field and the fields on a node exchange heat over the interface area the volume gradients give
  (:meth:`Transport.interface_rate`).
"""

from __future__ import annotations

from typing import Callable, Union

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ..core.errors import check
from ..core.fields import ParticleField
from ..core.linalg import det
from ..core.registry import Parameter, register_term
from ..core.safe import safe_norm
from ..core.validate import FINITE, FRACTION, NON_NEGATIVE, POSITIVE, concrete, positive_int, traced
from ..transfer.contractions import Divergence, Gradient, Weighted
from ..transfer.kernels.windowed import active_window, on_window
from ..transfer.operators import Transfer, gather, p2g, safe_divide
from ..transfer.series import series
from .conditions import NodeSet, _select, mirror_nodes, node_plane
from .term import Term

Selector = Union[str, Callable, NodeSet]


class Dirichlet(eqx.Module):
    """Hold the transported field at ``value`` on the nodes ``where`` selects (a grid face such
    as ``"x-"`` or a callable of node coordinates (n, D) -> bool): a fixed temperature or
    concentration.

    ``mirror=(axis, position)``: the boundary is the node plane x_axis = position; the selected
    nodes on it hold ``value``, and the selected nodes beyond it are its odd (mirror) extension,
    T_ghost = 2 value - T_mirror, with a_ghost = -a_mirror -- what B-spline shape functions, whose
    stencils reach past the boundary, need for a second-order boundary (held ghosts are first
    order).  Linear shapes do not reach past the plane; for them it changes nothing.

    Args:
        where: the nodes: a grid face (``"x-"``, ...), a callable of the node coordinates
            (n, D) -> bool, or a :class:`jaxmpm.NodeSet`.
        value: the held value (a temperature, a concentration potential), finite; a
            differentiable leaf.
        layers: node layers inward from a face, a positive integer (default 1).
        mirror: ``(axis, position)`` of the boundary's node plane for the odd extension beyond
            it, or None (the default: the selected nodes are simply held).
    """

    where: Selector
    value: jnp.ndarray
    layers: int = eqx.field(static=True, default=1)
    mirror: tuple | None = eqx.field(static=True, default=None)

    def __init__(self, where: Selector, value, layers: int = 1, mirror: tuple | None = None):
        self.where = where
        self.value = FINITE.leaf("Dirichlet", "value", value)
        self.layers = positive_int("Dirichlet", "layers", layers, fix="node layers from the face")
        if mirror is not None:
            ok = isinstance(mirror, tuple) and len(mirror) == 2 and isinstance(mirror[0], int) and mirror[0] >= 0
            check(ok, f"Dirichlet: mirror = {mirror!r}; give (axis, position) of the boundary's node plane, "
                      "e.g. (0, 0.0)")
            mirror = (mirror[0], FINITE.real("Dirichlet", "mirror position", mirror[1]))
        self.mirror = mirror


class Neumann(eqx.Module):
    """A prescribed inward ``flux`` per unit area through the nodes ``where`` selects:
    Q_i,q = flux h^(D-1) (001 eq. 136, lumped).

    Args:
        where: the nodes: a grid face (``"x-"``, ...), a callable of the node coordinates
            (n, D) -> bool, or a :class:`jaxmpm.NodeSet`.
        flux: the inward flux per unit area (heat: W/m^2; diffusion: mu m/s), finite; a
            differentiable leaf.
        layers: node layers inward from a face, a positive integer (default 1).
    """

    where: Selector
    flux: jnp.ndarray
    layers: int = eqx.field(static=True, default=1)

    def __init__(self, where: Selector, flux, layers: int = 1):
        self.where = where
        self.flux = FINITE.leaf("Neumann", "flux", flux)
        self.layers = positive_int("Neumann", "layers", layers, fix="node layers from the face")


def _nodes(grid, condition, copies: int) -> np.ndarray:
    """The condition's node mask on every velocity field's copy of the grid, (copies n,)."""
    return np.tile(_select(grid, condition.where, condition.layers), copies)


def _read(nodal, rows):
    """``nodal[rows]``, a row one past the end (a node outside the device's window on the sharded
    path: :meth:`Transport.mirror_rows`) read as 0."""
    return nodal.at[rows].get(mode="fill", fill_value=0)


def _parse_update(owner: str, update: str, name: str = "update") -> tuple:
    """(XPIC order, default beta) of an update spec: "flip" (1, 1), "pic" (1, 0), "xpic:M" (M, 0)."""
    spec = update.strip().lower() if isinstance(update, str) else update
    if spec == "flip":
        return 1, 1.0
    if spec == "pic":
        return 1, 0.0
    if isinstance(spec, str) and spec.startswith("xpic:"):
        try:
            order = int(spec[5:])
        except ValueError:
            order = 0
        check(order >= 1, f"{owner}: {name} = {update!r}; the XPIC order M in 'xpic:M' must be a positive integer")
        return order, 0.0
    check(False, f"{owner}: {name} = {update!r}; choose 'flip' (001 §8), 'pic' (a comparison) or 'xpic:M' "
                 "(000 §3.6)")


class Transport(Term):
    """Scalar transport by conduction/diffusion (the module ``jaxmpm.physics.transport``, 001
    §8-9).  Subclasses name the field and the particle capacity: :class:`Heat` (temperature,
    m_Tp = M_p C_p) and :class:`Diffusion` (concentration potential, m_Tp = V_p); build those
    (their constructors check and convert the arguments into the fields below).

    Args:
        conductivity: k (heat) or D (diffusion), >= 0: a scalar or a symmetric positive
            semi-definite (D, D) tensor.
        capacity: C_p per unit mass (heat); 1 (diffusion).
        source: the source per unit volume and time.
        expansion: alpha, the isotropic stretch per unit field (thermal or moisture expansion).
        reference: the field at which the stretch is zero.
        boundary: the field's conditions, a tuple of :class:`jaxmpm.Dirichlet` and
            :class:`jaxmpm.Neumann`.
        beta: the FLIP fraction of the particle update, in [0, 1] (000 eq. 3.58).
        order: the XPIC(m) order of the particle update (1: the FLIP/PIC blend).
        initial: the initial field: a number or f(x) -> (N,).
        interface: across contact interfaces: "perfect", "insulated" or "conductance".
        conductance: the interface conductance h_c >= 0 (with ``interface="conductance"``).
    """

    conductivity: jnp.ndarray  # k (heat) or D (diffusion): a scalar or a (D, D) tensor
    capacity: jnp.ndarray  # C_p per unit mass (heat); 1 (diffusion)
    source: jnp.ndarray  # per unit volume and time
    expansion: jnp.ndarray  # alpha: the thermal (moisture) stretch per unit field
    reference: jnp.ndarray  # the field at which the stretch is zero
    boundary: tuple
    beta: jnp.ndarray  # the FLIP fraction of the particle update (000 eq. 3.58)
    order: int = eqx.field(static=True)  # XPIC(m) order of the update (1: FLIP/PIC)
    # a number: a leaf (another value compiles nothing new); a function of the positions: kept as it is, static
    # to eqx.filter_jit (give one that compares equal when rebuilt, not a new lambda, to reuse compiled programs)
    initial: jnp.ndarray | Callable
    interface: str = eqx.field(static=True)  # across contact interfaces: "perfect", "insulated" or "conductance"
    conductance: jnp.ndarray  # the interface conductance h_c (interface="conductance")

    FIELD = ""  # the particle field
    MASS = ""  # the nodal capacity ("thermal mass") column
    MOMENTUM = ""  # the nodal field-times-capacity ("thermal momentum") column
    TOTAL = ""  # the saved total sum_p m_Tp T_p

    def _setup(self, owner, conductivity, capacity, source, expansion, reference, boundary, update, beta, initial,
               conductivity_name, interface="perfect"):
        fix = "a scalar >= 0 or a symmetric positive semi-definite D x D tensor"
        scalar = np.ndim(conductivity) == 0
        self.conductivity = (NON_NEGATIVE if scalar else FINITE).leaf(owner, conductivity_name, conductivity, fix=fix)
        check(self.conductivity.ndim in (0, 2),
              f"{owner}: {conductivity_name} has shape {self.conductivity.shape}; give a scalar or a D x D tensor")
        if self.conductivity.ndim == 2:
            k = concrete(self.conductivity)
            check(k is None or (k.shape[0] == k.shape[1] and np.allclose(k, k.T)
                                and np.all(np.linalg.eigvalsh(k) >= 0)),
                  f"{owner}: {conductivity_name} tensor must be square, symmetric and positive semi-definite")
        self.capacity = POSITIVE.leaf(owner, "heat_capacity" if owner == "Heat" else "capacity", capacity)
        self.source = FINITE.leaf(owner, "source", source)
        self.expansion = FINITE.leaf(owner, "expansion", expansion)
        self.reference = FINITE.leaf(owner, "reference", reference)
        conditions = () if boundary is None else (boundary,) if isinstance(boundary, (Dirichlet, Neumann)) \
            else tuple(boundary)
        for c in conditions:
            check(isinstance(c, (Dirichlet, Neumann)),
                  f"{owner}: boundary holds {c!r}; use jm.Dirichlet(where, value) or jm.Neumann(where, flux)")
        self.boundary = conditions
        self.order, default_beta = _parse_update(owner, update)
        self.beta = FRACTION.leaf(owner, "beta", default_beta if beta is None else beta,
                                 fix="the FLIP fraction of the update, in [0, 1]")
        check(callable(initial) or traced(initial) or np.isfinite(np.asarray(initial, dtype=float)).all(),
              f"{owner}: initial = {initial!r}; give a finite number or a function f(x) -> (N,)")
        self.initial = initial if callable(initial) else jnp.asarray(initial, dtype=jnp.result_type(float))
        if isinstance(interface, str):
            check(interface in ("perfect", "insulated"),
                  f"{owner}: interface = {interface!r}; choose 'perfect' (one field on shared nodes), 'insulated' "
                  "(nothing crosses a contact interface) or a conductance h_c >= 0 (heat flow h_c A dT)")
            self.interface, self.conductance = interface, jnp.zeros(())
        else:
            self.interface = "conductance"
            self.conductance = NON_NEGATIVE.leaf(owner, "interface (conductance h_c)", interface,
                                                 fix="'perfect', 'insulated' or a conductance >= 0")

    # ------------------------------------------------------------------ per particle
    def particle_fields(self) -> tuple:
        initial = self.initial
        if not callable(initial):  # a leaf, but ParticleField keeps a static value: a float (or NumPy values),
            value = concrete(initial)  # or while traced a function returning the traced value
            initial = (lambda x: self.initial) if value is None else float(value) if value.ndim == 0 else value
        return (ParticleField(self.FIELD, initial=initial, doc=f"{self.FIELD} of the particle (001 §8-9)"),)

    def particle_capacity(self, state):
        """m_Tp: the particle's capacity (heat: M_p C_p; diffusion: the current volume)."""
        raise NotImplementedError

    def stretch(self, state):
        """The isotropic stretch 1 + alpha (T_p - T_ref) the field imposes on the particle, (N,)."""
        return 1.0 + self.expansion * (state.fields[self.FIELD] - self.reference)

    def diffusivity(self, state):
        """a_p = k / (rho_p C_p) per particle (diffusion: D), the largest eigenvalue for a tensor."""
        k = self.conductivity if self.conductivity.ndim == 0 else jnp.max(jnp.linalg.eigvalsh(self.conductivity))
        volume = state.volume0 * det(state.F)
        return k * volume / self.particle_capacity(state)

    def time_step_limit(self, sim, state):
        """dt <= h^2 / (2 D a_max) (module docstring)."""
        a = jnp.max(self.diffusivity(state))
        bound = sim.grid.h**2 / (2.0 * sim.grid.dim)
        return jnp.where(a > 0, bound / jnp.where(a > 0, a, 1.0), jnp.inf)

    def totals(self, sim, state) -> dict:
        """sum_p m_Tp T_p: the total thermal energy (heat) or solute (diffusion)."""
        return {self.TOTAL: jnp.sum(self.particle_capacity(state) * state.fields[self.FIELD])}

    # ------------------------------------------------------------------ the step
    def p2g_quantities(self, sim, state, stencil) -> dict:
        capacity = self.particle_capacity(state)
        return {self.MASS: Weighted(capacity),  # 001 eq. (138)
                self.MOMENTUM: Weighted(capacity * state.fields[self.FIELD])}  # 001 eq. (133)

    def held(self, sim, dtype):
        """(mask, value) of the Dirichlet nodes on every field's copy of the grid (on the sharded
        path, of the device's window of it)."""
        copies = self.copies(sim)
        mask = np.zeros(copies * sim.grid.num_nodes, dtype=bool)
        value = jnp.zeros(copies * sim.grid.num_nodes, dtype)
        for c in self.boundary:
            if isinstance(c, Dirichlet):
                nodes = _nodes(sim.grid, c, copies)
                mask |= nodes
                value = jnp.where(nodes, c.value.astype(dtype), value)
        return on_window(jnp.asarray(mask), copies), on_window(value, copies)

    def mirror_map(self, sim) -> tuple:
        """(ghost nodes, their mirror nodes) of the mirrored Dirichlet conditions, as field-node
        indices on every field's copy (NumPy int arrays; empty without a mirror)."""
        grid = sim.grid
        ghosts, mirrors = [], []
        index = grid.node_index_grid()
        for c in self.boundary:
            if not (isinstance(c, Dirichlet) and c.mirror is not None):
                continue
            axis, position = c.mirror  # the index map of jm.Mirror's images (jaxmpm.physics.conditions)
            plane = node_plane(grid, axis, position, "Dirichlet")
            beyond = _select(grid, c.where, c.layers) & (index[:, axis] != plane)
            ghost, mirror = mirror_nodes(grid, axis, plane, beyond, "Dirichlet")
            ghosts.append(ghost)
            mirrors.append(mirror)
        if not ghosts:
            return np.zeros(0, int), np.zeros(0, int)
        n = grid.num_nodes
        copies = np.arange(self.copies(sim))[:, None] * n
        return ((np.concatenate(ghosts)[None] + copies).ravel(), (np.concatenate(mirrors)[None] + copies).ravel())

    def mirror_rows(self, sim) -> tuple:
        """(ghosts, mirrors) of :meth:`mirror_map` as the rows of the nodal arrays being traced: the
        field-node indices themselves on one device; on the sharded path the device's window rows,
        a node outside the window one past the window's end (read as 0 with ``mode="fill"``, skipped
        by a scatter with ``mode="drop"``; the sharded run keeps each pair in the same windows:
        :class:`jaxmpm.parallel.ShardedSimulation`)."""
        ghosts, mirrors = self.mirror_map(sim)
        window = active_window()
        if window is None or not ghosts.size:
            return ghosts, mirrors
        return window.local_nodes(ghosts, self.copies(sim)), window.local_nodes(mirrors, self.copies(sim))

    def boundary_flow(self, sim, dtype):
        """Q_i,q: the Neumann conditions' inward flux times the nodal face area h^(D-1) (on the
        sharded path, on the device's window of the grid)."""
        flow = jnp.zeros(self.copies(sim) * sim.grid.num_nodes, dtype)
        for c in self.boundary:
            if isinstance(c, Neumann):
                flow = flow + jnp.where(_nodes(sim.grid, c, self.copies(sim)),
                                        c.flux.astype(dtype) * sim.grid.h ** (sim.grid.dim - 1), 0.0)
        return on_window(flow, self.copies(sim))

    def nodal_field(self, sim, mass, momentum):
        """(T_i, m_Ti, held mask, ghosts, mirrors): T_i = p_Ti / m_Ti (001 eq. 138), the held value on
        Dirichlet nodes.  Beyond a mirrored boundary the particles' odd images are folded in first
        (a ghost's accumulated m and 2 v m - p added to its mirror node: what the mirrored particles
        would give it), then the ghosts take the odd extension 2 v - T_mirror."""
        held, value = self.held(sim, mass.dtype)
        ghosts, mirrors = self.mirror_rows(sim)
        if ghosts.size:
            m_g, p_g, v_g = (_read(a, ghosts) for a in (mass, momentum, value))
            momentum = momentum.at[mirrors].add(2.0 * v_g * m_g - p_g, mode="drop")
            mass = mass.at[mirrors].add(m_g, mode="drop")
        t_nodes = jnp.where(held, value, safe_divide(momentum, mass))
        if ghosts.size:
            t_nodes = t_nodes.at[ghosts].set(2.0 * _read(value, ghosts) - _read(t_nodes, mirrors), mode="drop")
        return t_nodes, mass, held, ghosts, mirrors

    # ------------------------------------------------------------------ contact interfaces
    def shared(self, sim) -> bool:
        """Whether the field lives on shared nodes across velocity fields (``interface="perfect"``
        in multimaterial mode): each node has one temperature whatever material is on it."""
        return sim.velocity_fields > 1 and self.interface == "perfect"

    def copies(self, sim) -> int:
        """The copies of the grid the field lives on: 1 (one field, or shared nodes), or one per
        velocity field (each material its own nodal field)."""
        return 1 if self.shared(sim) else sim.velocity_fields

    def field_transfer(self, sim, state, transfer):
        """The transfer the field uses: the step's (per velocity field), or on shared nodes the
        particles' stencil on the single grid."""
        if not self.shared(sim):
            return transfer
        return Transfer(sim.shape.stencil(sim.grid, state.x), transfer.particle_mass, None, sim.grid.num_nodes)

    def on_shared_nodes(self, sim, nodal):
        """A nodal sum (M n,) of the velocity fields as one sum per node (n,) on shared nodes."""
        if not self.shared(sim):
            return nodal
        M = sim.velocity_fields  # the fields' nodes: the grid's, or on the sharded path the window's
        return jnp.sum(nodal.reshape((M, nodal.shape[0] // M) + nodal.shape[1:]), axis=0)

    def interface_rate(self, sim, state, transfer, t_nodes, m_T, dt):
        """``interface=h_c``: the heat each velocity field gains across the contact interface per
        thermal mass, (M n,).  On a node where material a and the rest (the other fields'
        capacity-weighted temperature) both have capacity, the flow h_c A_i (T^rest - T^a) over
        the interface area A_i = |g^a - g^rest| / 2, g the fields' volume gradients sum_p V_p G_pi
        (by the divergence theorem sum_p V_p G_pi ~ -oint N_i n dS: the surface area node i carries),
        integrated exactly over the step: the two capacities C^a, C^rest relax with rate
        k = h_c A (1/C^a + 1/C^rest), so the heat passed is C^a C^rest/(C^a + C^rest) (T^rest - T^a)
        (1 - exp(-k dt)) -- stable for any h_c, and summing to zero over the fields."""
        M = sim.velocity_fields
        n = m_T.shape[0] // M  # the fields' nodes: the grid's, or on the sharded path the window's
        volume = state.volume0 * det(state.F)
        g = transfer.p2g({"g": Gradient(volume)})["g"].reshape(M, n, -1)
        C = m_T.reshape(M, n)
        H = (C * t_nodes.reshape(M, n))
        C_rest, H_rest = jnp.sum(C, 0)[None] - C, jnp.sum(H, 0)[None] - H
        T_rest = safe_divide(H_rest, C_rest)
        area = 0.5 * safe_norm(g - (jnp.sum(g, 0)[None] - g))
        both = (C > 0) & (C_rest > 0)
        reduced = jnp.where(both, C * C_rest / jnp.where(both, C + C_rest, 1.0), 0.0)
        rate_k = jnp.where(both, self.conductance * area * (C + C_rest) / jnp.where(both, C * C_rest, 1.0), 0.0)
        heat = reduced * (T_rest - t_nodes.reshape(M, n)) * -jnp.expm1(-rate_k * dt)
        safe_dt = jnp.where(dt > 0, dt, 1.0)
        return (safe_divide(heat, C) / safe_dt).reshape(-1)

    def nodal_rate(self, sim, state, transfer, fields_mass, fields_momentum, dt):
        """(T_i, a_Ti) on every node: 001 eqs. (135)-(140), T_i the held value on Dirichlet nodes
        (where a_Ti = 0: the value stays; its switch-on jump is :meth:`switch_on`); beyond a
        mirrored boundary the heat flow is folded like the mass and a_ghost = -a_mirror."""
        t_nodes, m_T, held, ghosts, mirrors = self.nodal_field(sim, fields_mass, fields_momentum)
        own = self.field_transfer(sim, state, transfer)
        grad = own.gradient(t_nodes)  # sum_i T_i G_ip, (N, D)
        k = self.conductivity.astype(m_T.dtype)
        d = grad.shape[-1]
        check(k.ndim == 0 or k.shape == (d, d), f"{type(self).__name__}: the conductivity tensor has shape {k.shape}; "
                                                f"this model is {d}D: give a scalar or a {d} x {d} tensor")
        flux = -(k * grad if k.ndim == 0 else grad @ k.T)  # 001 eq. (137)
        volume = state.volume0 * det(state.F)
        heat_flow = (Divergence((volume[:, None] * flux)[:, None, :]),  # sum_p V_p q_p . G_ip (001 eq. 135)
                     Weighted((volume * self.source.astype(m_T.dtype))[:, None]))  # + sum_p V_p q_s,p S_ip
        flow = own.p2g({"flow": heat_flow})["flow"][:, 0] + self.boundary_flow(sim, m_T.dtype)
        if ghosts.size:  # the mirrored particles' flow: odd, as the field
            flow = flow.at[mirrors].add(-_read(flow, ghosts), mode="drop")
        rate = safe_divide(flow, m_T)  # 001 eq. (140)
        if self.interface == "conductance" and sim.velocity_fields > 1:
            rate = rate + self.interface_rate(sim, state, transfer, t_nodes, m_T, dt)
        rate = jnp.where(held, 0.0, rate)  # held nodes keep their value
        if ghosts.size:
            rate = rate.at[ghosts].set(-_read(rate, mirrors), mode="drop")
        return t_nodes, rate

    def switch_on(self, sim, state, dtype):
        """At the first step (state.step = 0), the held values' jump from the initial field on the
        held nodes, value - T0(x_i) with T0 the term's ``initial`` (0 elsewhere and later): FLIP
        particles take it once, as the change of the nodal field when the condition switches on
        (a heated end: the particles beside it see the step).  T0 comes from ``initial``: a field
        given to ``sim.init`` instead is not seen here, so give the initial field as ``initial=``
        when a held value differs from it."""
        held, value = self.held(sim, dtype)
        x = sim.grid.node_coordinates()
        copies = self.copies(sim)
        if callable(self.initial):  # evaluated on the nodes while tracing
            t0 = np.asarray(self.initial(x), dtype=float)
            t0 = jnp.asarray(np.tile(np.broadcast_to(t0, (len(x),)), copies), dtype)
        else:
            check(self.initial.ndim == 0, f"{type(self).__name__}: initial has shape {self.initial.shape}; with held "
                                          "values (jm.Dirichlet) give a number or a function f(x) -> (N,)")
            t0 = jnp.broadcast_to(self.initial.astype(dtype), (copies * len(x),))
        target = value
        ghosts, mirrors = self.mirror_rows(sim)
        t0 = on_window(t0, copies)  # on the sharded path, the device's window
        if ghosts.size:  # a ghost switches on to the odd extension of the initial field
            target = target.at[ghosts].set(2.0 * _read(value, ghosts) - _read(t0, mirrors), mode="drop")
        return jnp.where(held & (state.step == 0), target - t0, 0.0)

    def grid_value(self, sim, state):
        """T_{g->p} = sum_i T_i S_ip (001 eq. 145): the field on the particles as the grid sees it,
        T_i = p_Ti / m_Ti (the held value on Dirichlet nodes).  001 §8 recommends it wherever a
        feature needs the local temperature: FLIP particle values keep within-cell variations (a
        null-space part the grid does not see), which this projection removes."""
        stencil = sim.stencil(state)
        nodal = p2g(stencil, self.p2g_quantities(sim, state, stencil), sim.field_nodes)
        nodal = {k: self.on_shared_nodes(sim, v) for k, v in nodal.items()}
        if self.shared(sim):
            stencil = sim.shape.stencil(sim.grid, state.x)
        return gather(stencil, self.nodal_field(sim, nodal[self.MASS], nodal[self.MOMENTUM])[0])

    def read_grid(self, sim, fields, solution, dt):
        """Keep the nodal capacity and field-times-capacity for the transport stage (one sum per
        node on shared nodes)."""
        return {self.MASS: self.on_shared_nodes(sim, fields[self.MASS]),
                self.MOMENTUM: self.on_shared_nodes(sim, fields[self.MOMENTUM])}

    def particle_action(self, sim, old, new, transfer, solution, dt):
        """The transport stage: the nodal rate from the start-of-step particles (001 eqs. 135-140),
        then the particle update (:meth:`particle_update`)."""
        mass = solution[self.MASS]
        t_nodes, rate = self.nodal_rate(sim, old, transfer, mass, solution[self.MOMENTUM], dt)
        value = self.particle_update(sim, old, self.field_transfer(sim, old, transfer), mass, t_nodes, rate, dt)
        return eqx.tree_at(lambda s: s.fields, new, {**new.fields, self.FIELD: value})

    def particle_update(self, sim, state, transfer, mass, t_nodes, rate, dt):
        """T^{n+1} = beta T^n + (1 - beta) S t(m) + S a_T dt, t(m) the XPIC(m) series of the nodal
        values with S+ weighted by the capacity (000 eqs. 3.53-3.58; m(t~ - t*) = t(m) + m a_T dt
        collects the a_T terms).  m = 1 is the FLIP/PIC blend of 000 eq. (3.60); beta = 1 FLIP,
        T_p += S a_T dt (001 eq. 141); beta = 0, m = 1 PIC, T_p = S (t + a_T dt) (001 eq. 142)."""
        T = state.fields[self.FIELD]
        Sa = transfer.gather(rate)
        if any(isinstance(c, Dirichlet) for c in self.boundary):  # the held values switch on at t = 0
            T = T + transfer.gather(self.switch_on(sim, state, T.dtype))
        if self.order == 1:
            if self.is_flip():
                return T + Sa * dt  # 001 eqs. (141), (143)
            St = transfer.gather(t_nodes)
        else:
            # the transfer layer's XPIC series (000 eqs. 3.22-3.25), S+ weighted by the capacity (000 eq. 3.53)
            capacity = Transfer(transfer.stencil, self.particle_capacity(state), mass, transfer.num_nodes)
            tm = series(t_nodes[:, None], self.order, capacity, None, "binomial")[:, 0]  # m (t - t*)
            St = transfer.gather(tm)
        beta = self.beta.astype(T.dtype)
        return beta * T + (1.0 - beta) * St + Sa * dt  # 000 eq. (3.58)

    def is_flip(self) -> bool:
        """True when the update is concretely pure FLIP (beta = 1, m = 1): no projection to compute."""
        b = concrete(self.beta)
        return self.order == 1 and b is not None and float(b) == 1.0


class Heat(Transport):
    """Heat conduction (001 §8) on the particle field ``temperature``; with ``expansion`` the
    material sees F / (1 + alpha_T (T - T_ref)).  The stable time step h^2 / (2 D a) joins
    :meth:`jaxmpm.Simulation.stable_dt`.

    Args:
        conductivity: k (W/(m K)), >= 0: a scalar or a symmetric positive semi-definite D x D
            tensor (the parameter ``conductivity``).
        heat_capacity: C_p per unit mass (J/(kg K)), positive (default 1.0).
        source: q_s, the heat source per unit volume (W/m^3; default 0.0).
        expansion: alpha_T, the thermal expansion coefficient (1/K; default 0.0: no coupling).
        reference: T_ref, the temperature of zero thermal strain (default 0.0).
        boundary: a :class:`jaxmpm.Dirichlet` (fixed temperature), a :class:`jaxmpm.Neumann`
            (heat flux in), a sequence of them, or None (the default: adiabatic).
        update: the particle update: "flip" (default, 001 §8), "pic" (a comparison: it smooths
            even with k = 0) or "xpic:M" (000 §3.6).
        beta: the FLIP fraction in [0, 1]; None (the default): 1 for "flip", 0 otherwise.
        initial: the initial temperature: a finite number (default 0.0; an array leaf) or
            f(x) -> (N,) (static: pass one that compares equal when rebuilt).
        interface: across contact interfaces (jm.Contact): "perfect" (default), "insulated" or
            a conductance h_c >= 0 (W/(m^2 K)).
    """

    FIELD, MASS, MOMENTUM, TOTAL = "temperature", "thermal_mass", "thermal_momentum", "thermal_energy"

    def __init__(self, conductivity, heat_capacity=1.0, source=0.0, expansion=0.0, reference=0.0, boundary=None,
                 update: str = "flip", beta=None, initial=0.0, interface="perfect"):
        self._setup("Heat", conductivity, heat_capacity, source, expansion, reference, boundary, update, beta, initial,
                    "conductivity", interface)

    def particle_capacity(self, state):
        return state.mass * self.capacity  # m_Tp = M_p C_p (001 §8)


class Diffusion(Transport):
    """Diffusion (001 §9) of the concentration potential mu = c / c_sat, the particle field
    ``concentration``; the particle's "mass" is its current volume.

    Args:
        diffusivity: D (m^2/s), >= 0: a scalar or a symmetric positive semi-definite D x D
            tensor (the parameter ``diffusivity``).
        source: the source per unit volume (1/s; default 0.0).
        expansion: the moisture expansion per unit mu (default 0.0: no coupling).
        reference: the potential of zero moisture strain (default 0.0).
        boundary: a :class:`jaxmpm.Dirichlet` (fixed concentration), a :class:`jaxmpm.Neumann`
            (flux in), a sequence of them, or None (the default: sealed).
        update: the particle update: "flip" (default), "pic" or "xpic:M".
        beta: the FLIP fraction in [0, 1]; None (the default): 1 for "flip", 0 otherwise.
        initial: the initial potential: a finite number (default 0.0; an array leaf) or
            f(x) -> (N,) (static: pass one that compares equal when rebuilt).
        interface: across contact interfaces: "perfect" (default), "insulated" or a
            mass-transfer coefficient >= 0.
    """

    FIELD, MASS, MOMENTUM, TOTAL = "concentration", "solvent_mass", "solvent_momentum", "solute"

    def __init__(self, diffusivity, source=0.0, expansion=0.0, reference=0.0, boundary=None, update: str = "flip",
                 beta=None, initial=0.0, interface="perfect"):
        self._setup("Diffusion", diffusivity, 1.0, source, expansion, reference, boundary, update, beta, initial,
                    "diffusivity", interface)

    def particle_capacity(self, state):
        return state.volume0 * det(state.F)  # V_p (001 eq. 146)


def _conductance_acts(term, fix: str):
    """Why the interface conductance does not act in ``term`` (Parameter.acts), or None."""
    if term.interface == "conductance":
        return None
    return f"acts only across an interface given as a conductance, and this term's is {term.interface!r}: build it " \
           f"with {fix}"


register_term("heat", Heat, doc="heat conduction, FLIP temperature update (001 §8)", parameters=[
    Parameter("conductivity", lambda t: t.conductivity, "thermal conductivity k", "positive", valid="non-negative"),
    Parameter("heat_capacity", lambda t: t.capacity, "heat capacity C_p per unit mass", "positive", valid="positive"),
    Parameter("thermal_expansion", lambda t: t.expansion, "thermal expansion coefficient alpha_T"),
    Parameter("interface_conductance", lambda t: t.conductance, "interface conductance h_c (interface=h_c)",
              "positive", valid="non-negative", acts=lambda t: _conductance_acts(t, "jm.Heat(..., interface=h_c)")),
])
register_term("diffusion", Diffusion, doc="diffusion of the concentration potential (001 §9)", parameters=[
    Parameter("diffusivity", lambda t: t.conductivity, "diffusivity D", "positive", valid="non-negative"),
    Parameter("moisture_expansion", lambda t: t.expansion, "moisture expansion coefficient per unit mu"),
    Parameter("interface_conductance", lambda t: t.conductance, "interface mass-transfer coefficient (interface=h)",
              "positive", valid="non-negative", acts=lambda t: _conductance_acts(t, "jm.Diffusion(..., interface=h)")),
])
