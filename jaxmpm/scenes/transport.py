"""The transport scenes (issue 14; 001 §8-9, jaxmpm/_transport.py), each with an exact solution.

* ``heat1d``       a rod [0, L] held at T = 0 at both ends, T0 = A sin(pi x / L):
                   T = A exp(-a pi^2 t / L^2) sin(pi x / L), a = k / (rho C_p);
* ``heat_step``    a long rod [0, L] at T = 0 whose end x = 0 is held at T_s from t = 0 (a
                   semi-infinite body while sqrt(a t) << L): T = T_s erfc(x / (2 sqrt(a t)));
* ``diffusion2d``  a unit square at mu = 0 whose boundary is held at mu = 1 (001 §9):
                   mu = 1 - sum_{m,n odd} 16 / (pi^2 m n) sin(m pi x) sin(n pi y) exp(-D pi^2 (m^2 + n^2) t);
* ``thermal_bar``  a free elastic bar heated uniformly by dT (k = 0) expands to (1 + alpha_T dT) L;
                   damped, it settles there (the reference is the stretch alpha_T dT).

``transport`` is the particle update of the field: "flip" (001 §8, default), "pic" or "xpic:M"
(000 §3.6; ``jm.Heat(update=...)``).  The rods' held ends are mirrored boundaries (the odd extension
beyond the end: second order with B-splines as with linear shapes); diffusion2d holds its edge
nodes (second order with linear shapes, its default).  The conduction scenes use
:class:`jaxmpm.NoStress` (the particles stay put: pure conduction) and dt = cfl times the
conduction limit h^2 / (2 D a) (``Simulation.time_step_limits``).  Their ``reference(t, x)`` takes
the particle positions (N, D) as well.  Every scene saves its physical parameters (conductivity,
density, heat_capacity, length, ...) in ``params`` (HDF5 attributes).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ..core.errors import check
from ..core.grid import Grid
from ..core.particles import Box, fill
from ..materials import LinearElastic, NoStress
from ..model.simulation import Simulation
from ..physics.conditions import NodeSet
from ..physics.damping import Damping
from ..physics.transport import Diffusion, Dirichlet, Heat
from ..schemes import FLIP
from ..transfer.shapes import UGIMP, Linear
from ._common import Setup, cast_state, resolve_dtype, schedule
from ._options import checked_options


@dataclasses.dataclass(frozen=True)
class SineProfile:
    """heat1d's initial temperature T0(x) = amplitude sin(pi x / length), a module-level callable
    compared and hashed by value (a lambda per build would be a new static value: every build would
    compile the rollout again).

    Args:
        amplitude: the peak temperature A.
        length: the rod's length L.
    """

    amplitude: float
    length: float

    def __call__(self, x):
        return self.amplitude * np.sin(np.pi * x[:, 0] / self.length)


def _conduction(name, grid, shape, particles, term, cfl, t_end, frames, dtype, params, reference):
    """A pure-conduction Setup: NoStress particles at rest, dt = cfl times the conduction limit."""
    option = "diffusivity" if name == "diffusion2d" else "conductivity"
    check(params["conductivity"] > 0, f"{name}: {option} = 0 carries nothing, and the time step (cfl times the limit "
                                      f"h^2 / (2 D a), a = 0) is infinite; give {option} > 0")
    sim = Simulation(grid=grid, shape=shape, material=NoStress(density=params["density"]), scheme=FLIP(),
                     terms=(term,), damping=False)
    state = cast_state(sim.init(particles), dtype)
    dt = cfl * float(sim.stable_dt(state))
    steps, save_every = schedule(t_end, dt, frames)
    params = dict(params, cfl=cfl, dt=dt, t_end=steps * dt, diffusivity=params["conductivity"]
                  / (params["density"] * params["heat_capacity"]))
    return Setup(name, sim, state, dt, steps, save_every, params, reference, particles)


def _held_end(grid, at: float, value: float, side: int) -> Dirichlet:
    """The rod's end x = ``at`` held at ``value``: the node there and, mirrored, the nodes beyond
    (``side`` -1: x < at, +1: x > at) -- second order with B-splines too (jm.Dirichlet)."""
    x = grid.node_coordinates()[:, 0]
    tol = 1e-9 * max(grid.spacing)
    return Dirichlet(NodeSet(side * (x - at) >= -tol), value, mirror=(0, at))


@checked_options
def heat1d(shape=None, cells: int = 32, ppc: int = 2, cfl: float = 0.5, t_end: float = 0.1, frames: int = 20,
           conductivity: float = 1.0, heat_capacity: float = 1.0, density: float = 1.0, length: float = 1.0,
           amplitude: float = 1.0, transport: str = "flip", dtype=None) -> Setup:
    """The rod of ``length`` with ``cells`` cells, T = 0 held at both ends, T0 = amplitude sin(pi x / L)."""
    dtype = resolve_dtype(dtype)
    shape = Linear() if shape is None else shape
    grid = Grid.covering((0.0,), (length,), length / cells, shape=shape)
    particles = fill(grid, Box((0.0,), (length,)), ppc=ppc)
    term = Heat(conductivity=conductivity, heat_capacity=heat_capacity, update=transport,
                initial=SineProfile(amplitude, length),
                boundary=[_held_end(grid, 0.0, 0.0, -1), _held_end(grid, length, 0.0, +1)])
    a = conductivity / (density * heat_capacity)

    def reference(t, x):
        """Exact T(t, x) = A exp(-a pi^2 t / L^2) sin(pi x / L), x (N, 1)."""
        return (amplitude * math.exp(-a * math.pi**2 * float(t) / length**2)
                * np.sin(np.pi * np.asarray(x)[:, 0] / length))

    params = dict(conductivity=conductivity, heat_capacity=heat_capacity, density=density, length=length,
                  amplitude=amplitude, cells=cells, ppc=ppc, transport=transport)
    return _conduction("heat1d", grid, shape, particles, term, cfl, t_end, frames, dtype, params, reference)


@checked_options
def heat_step(shape=None, cells: int = 64, ppc: int = 2, cfl: float = 0.5, t_end: float = 0.01, frames: int = 20,
              conductivity: float = 1.0, heat_capacity: float = 1.0, density: float = 1.0, length: float = 1.0,
              amplitude: float = 1.0, transport: str = "flip", dtype=None) -> Setup:
    """The rod [0, ``length``] at T = 0 with T = ``amplitude`` held at x = 0 from t = 0; the far end
    is adiabatic.  Exact while sqrt(a t) << L: T = T_s erfc(x / (2 sqrt(a t)))."""
    dtype = resolve_dtype(dtype)
    shape = Linear() if shape is None else shape
    grid = Grid.covering((0.0,), (length,), length / cells, shape=shape)
    particles = fill(grid, Box((0.0,), (length,)), ppc=ppc)
    term = Heat(conductivity=conductivity, heat_capacity=heat_capacity, update=transport, initial=0.0,
                boundary=_held_end(grid, 0.0, amplitude, -1))
    a = conductivity / (density * heat_capacity)

    def reference(t, x):
        """Exact T(t, x) = T_s erfc(x / (2 sqrt(a t))) of the semi-infinite body, x (N, 1)."""
        t = float(t)
        if t <= 0:
            return np.zeros(np.asarray(x).shape[0])
        return amplitude * np.array([math.erfc(xi / (2.0 * math.sqrt(a * t))) for xi in np.asarray(x)[:, 0]])

    params = dict(conductivity=conductivity, heat_capacity=heat_capacity, density=density, length=length,
                  amplitude=amplitude, cells=cells, ppc=ppc, update=transport,
                  penetration=2.0 * math.sqrt(a * t_end) / length)
    return _conduction("heat_step", grid, shape, particles, term, cfl, t_end, frames, dtype, params, reference)


@checked_options
def diffusion2d(shape=None, cells: int = 16, ppc: int = 2, cfl: float = 0.5, t_end: float = 0.05, frames: int = 20,
                diffusivity: float = 1.0, transport: str = "flip", dtype=None) -> Setup:
    """The unit square with ``cells`` cells a side at mu = 0, its boundary held at mu = 1 (001 §9)."""
    dtype = resolve_dtype(dtype)
    shape = Linear() if shape is None else shape
    grid = Grid.covering((0.0, 0.0), (1.0, 1.0), 1.0 / cells, shape=shape)
    particles = fill(grid, Box((0.0, 0.0), (1.0, 1.0)), ppc=ppc)
    nodes = grid.node_coordinates()
    tol = 1e-9
    edge = NodeSet(np.any((nodes <= tol) | (nodes >= 1.0 - tol), axis=1))
    term = Diffusion(diffusivity=diffusivity, update=transport, initial=0.0, boundary=Dirichlet(edge, 1.0))

    def reference(t, x, terms: int = 199):
        """Exact mu(t, x) (the double sine series over odd m, n <= ``terms``), x (N, 2)."""
        x = np.asarray(x)
        odd = np.arange(1, terms + 1, 2)
        sx = np.sin(np.pi * np.outer(x[:, 0], odd)) / odd
        sy = np.sin(np.pi * np.outer(x[:, 1], odd)) / odd
        decay = np.exp(-diffusivity * np.pi**2 * (odd[:, None] ** 2 + odd[None, :] ** 2) * float(t))
        return 1.0 - 16.0 / np.pi**2 * np.einsum("pm,pn,mn->p", sx, sy, decay)

    params = dict(conductivity=diffusivity, heat_capacity=1.0, density=1.0, length=1.0, cells=cells, ppc=ppc,
                  transport=transport)
    return _conduction("diffusion2d", grid, shape, particles, term, cfl, t_end, frames, dtype, params, reference)


@checked_options
def thermal_bar(shape=None, cells: int = 32, ppc: int = 2, cfl: float = 0.5, t_end: float = 0.625, frames: int = 20,
                E: float = 1e4, density: float = 1.0, length: float = 1.0, expansion: float = 1e-3,
                heating: float = 50.0, damping: Damping | None = None, scheme=None, dtype=None) -> Setup:
    """A free bar of ``length`` at T = ``heating`` above T_ref = 0, alpha_T = ``expansion``, k = 0
    (it stays uniform); damped (alpha_p = 20 unless ``damping`` is given) so that it settles at
    the stretch alpha_T dT.  uGIMP by default (linear shapes break up at the free ends as they
    cross cells)."""
    dtype = resolve_dtype(dtype)
    shape = UGIMP(ppc=ppc) if shape is None else shape
    scheme = FLIP() if scheme is None else scheme
    h = length / cells
    stretch = expansion * heating
    check(abs(stretch) < 1.0, f"thermal_bar: expansion * heating = {expansion:g} * {heating:g} = {stretch:.3g}, a "
                              "thermal strain of magnitude 1 or more (the bar would double or vanish); give "
                              "|expansion * heating| < 1, e.g. expansion 1e-3 and heating 50")
    room = abs(stretch) * length + 2 * h
    grid = Grid.covering((-room,), (length + room,), h, shape=shape)
    particles = fill(grid, Box((0.0,), (length,)), ppc=ppc)
    sim = Simulation(grid=grid, shape=shape, material=LinearElastic(E=E, nu=0.0, density=density), scheme=scheme,
                     terms=(Heat(conductivity=0.0, expansion=expansion, initial=heating),),
                     damping=Damping(particle=20.0) if damping is None else damping)
    state = cast_state(sim.init(particles), dtype)
    c = math.sqrt(E / density)
    dt = cfl * h / c
    steps, save_every = schedule(t_end, dt, frames)

    def reference(t):
        """The stress-free stretch alpha_T dT the bar settles at (F = 1 + alpha_T dT)."""
        return stretch

    params = dict(E=E, density=density, length=length, thermal_expansion=expansion, heating=heating,
                  conductivity=0.0, heat_capacity=1.0, cells=cells, ppc=ppc, cfl=cfl, dt=dt, t_end=steps * dt,
                  expansion_length=stretch * length)
    return Setup("thermal_bar", sim, state, dt, steps, save_every, params, reference, particles)
