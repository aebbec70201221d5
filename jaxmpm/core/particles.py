"""Filling regions with material points: ``fill(grid, region, ppc=..., density=..., velocity=...)``."""

from __future__ import annotations

from typing import Callable, Sequence

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .device import to_device
from .errors import check
from .grid import Grid
from .limits import require_memory
from .validate import FINITE, NON_NEGATIVE, POSITIVE, concrete, finite_vector, ndim, positive_int


class Region(eqx.Module):
    """A region of space: ``contains(x) -> bool`` for points (N, D) and a bounding box."""

    def contains(self, x):  # pragma: no cover - interface
        raise NotImplementedError

    def bounds(self):  # pragma: no cover - interface
        raise NotImplementedError

    def check_grid(self, grid) -> None:
        """Raise InputError when the region cannot be filled on ``grid`` (the default: no check)."""


class Box(Region):
    """The points with lower <= x < upper along every axis (a segment, rectangle or box).

    Args:
        lower: the lower corner, one finite coordinate per axis.
        upper: the upper corner, each coordinate greater than ``lower``'s.
    """

    lower: tuple = eqx.field(static=True)
    upper: tuple = eqx.field(static=True)

    def __init__(self, lower: Sequence[float], upper: Sequence[float]):
        self.lower = finite_vector("Box", "lower", lower)
        self.upper = finite_vector("Box", "upper", upper)
        check(len(self.lower) == len(self.upper),
              f"Box: lower has {len(self.lower)} axes but upper has {len(self.upper)}; give both the same number")
        for a, (lo, hi) in enumerate(zip(self.lower, self.upper)):
            check(hi > lo, f"Box: upper[{a}] = {hi} must be greater than lower[{a}] = {lo}")

    def contains(self, x):
        return np.all((x >= np.array(self.lower)) & (x < np.array(self.upper)), axis=-1)

    def bounds(self):
        return self.lower, self.upper


class Ball(Region):
    """Points within ``radius`` of ``center``: |x - center| < radius (a disk in 2D, a ball in 3D).

    Args:
        center: the centre, one finite coordinate per axis.
        radius: the radius, positive.
    """

    center: tuple = eqx.field(static=True)
    radius: float = eqx.field(static=True)

    def __init__(self, center: Sequence[float], radius: float):
        self.center = finite_vector(type(self).__name__, "center", center)
        self.radius = POSITIVE.real(type(self).__name__, "radius", radius)

    def contains(self, x):
        return np.sum((x - np.array(self.center)) ** 2, axis=-1) < self.radius**2

    def bounds(self):
        c = np.array(self.center)
        return tuple(c - self.radius), tuple(c + self.radius)


class Disk(Ball):
    """A 2D disk (the same as :class:`Ball`): |x - center| < radius.

    Args:
        center: the centre, (x, y).
        radius: the radius, positive.
    """


class Ring(Region):
    """Annulus inner <= |x - center| < outer (a hollow ball in 3D).

    Args:
        center: the centre, one finite coordinate per axis.
        inner: the inner radius, >= 0 (0: a full disk).
        outer: the outer radius, greater than ``inner``.
    """

    center: tuple = eqx.field(static=True)
    inner: float = eqx.field(static=True)
    outer: float = eqx.field(static=True)

    def __init__(self, center: Sequence[float], inner: float, outer: float):
        self.center = finite_vector("Ring", "center", center)
        self.inner = NON_NEGATIVE.real("Ring", "inner", inner)
        self.outer = POSITIVE.real("Ring", "outer", outer)
        check(self.inner < self.outer, f"Ring: need 0 <= inner ({inner}) < outer ({outer})")

    def contains(self, x):
        r2 = np.sum((x - np.array(self.center)) ** 2, axis=-1)
        return (r2 >= self.inner**2) & (r2 < self.outer**2)

    def bounds(self):
        c = np.array(self.center)
        return tuple(c - self.outer), tuple(c + self.outer)


class Particles(eqx.Module):
    """Material points: what :func:`jaxmpm.fill` returns and :meth:`jaxmpm.Simulation.init` turns
    into a :class:`jaxmpm.State` (or built by hand from arrays).  Every array is checked where it
    enters, each error naming the argument.

    Args:
        x: positions, shape (N, D) with D = 1, 2 or 3 and N >= 1; finite.
        v: velocities, shape (N, D); finite (zeros for a body at rest).
        volume: reference volumes V_p, shape (N,); positive.
        mass: masses m_p, shape (N,), positive; None (the default): the material's density sets
            them, m_p = rho V_p.
        ppc: particles per cell per axis (a positive integer, default 1; :func:`jaxmpm.fill`
            sets it); :class:`jaxmpm.UGIMP` checks it against its own ``ppc``.
        axisymmetric: True when x = (r, z) on an axisymmetric grid; ``volume`` and ``mass`` are then
            per radian (001 §7: V_p = A_p r_p, m_p = rho A_p r_p).  Default False.
    """

    x: jnp.ndarray
    v: jnp.ndarray
    volume: jnp.ndarray
    mass: jnp.ndarray | None = None
    ppc: int = eqx.field(static=True, default=1)
    axisymmetric: bool = eqx.field(static=True, default=False)

    def __check_init__(self):
        """Where particles enter: shapes, kinds and (for concrete arrays) values, each error naming
        the argument.  Tracers (a Particles built under jit/grad/vmap) get the shape checks only."""
        x = _real_array("x", self.x, "positions, one row per particle: shape (N, D)")
        check(x.ndim == 2 and 1 <= x.shape[1] <= 3,
              f"jm.Particles: x has shape {tuple(x.shape)}; give positions as (N, D) with D = 1, 2 or 3 "
              "(one row per particle; a 1D body is x[:, None])")
        n, d = x.shape
        check(n >= 1, "jm.Particles: x holds no particles (shape (0, D)); a body needs at least one: "
                      "check the region given to jm.fill lies on the grid")
        v = _real_array("v", self.v, f"velocities, shape ({n}, {d})")
        check(tuple(v.shape) == (n, d), f"jm.Particles: v has shape {tuple(v.shape)} but x has {(n, d)}; "
                                        "give one velocity per particle (zeros for a body at rest)")
        volume = _real_array("volume", self.volume, f"reference volumes, shape ({n},)")
        check(tuple(volume.shape) == (n,), f"jm.Particles: volume has shape {tuple(volume.shape)}; give one "
                                           f"reference volume per particle, shape ({n},)")
        if self.mass is not None:
            mass = _real_array("mass", self.mass, f"masses, shape ({n},)")
            check(tuple(mass.shape) == (n,), f"jm.Particles: mass has shape {tuple(mass.shape)}; give one mass "
                                             f"per particle, shape ({n},), or mass=None (density x volume)")
        positive_int("jm.Particles", "ppc", self.ppc, fix="particles per cell per axis (jm.fill sets it)")
        for name, value, rule in (("x", self.x, FINITE), ("v", self.v, FINITE), ("volume", self.volume, POSITIVE),
                                  ("mass", self.mass, POSITIVE)):
            values = None if value is None else concrete(value)
            if values is not None:
                rule.check("jm.Particles", name, values)

    @property
    def num(self) -> int:
        return self.x.shape[0]


def _real_array(name: str, value, what: str):
    """``value`` as an array of real numbers (int or float), or an InputError naming ``name``."""
    try:
        dtype = np.result_type(value) if not hasattr(value, "dtype") else value.dtype
    except TypeError:
        dtype = np.dtype(object)
    check(np.issubdtype(dtype, np.integer) or np.issubdtype(dtype, np.floating),
          f"jm.Particles: {name} ({what}) has dtype {dtype}; give real numbers (float32 or float64)")
    return value if hasattr(value, "shape") else np.asarray(value)


def fill(
    grid: Grid,
    region: Region | Callable,
    ppc: int = 2,
    density: float | None = None,
    velocity=0.0,
) -> Particles:
    """Place ``ppc`` particles per cell per axis, on a regular lattice aligned with the grid cells,
    at the lattice points inside ``region`` (a :class:`Region` or a callable mask ``f(x) -> bool``).

    Each particle gets volume h^D / ppc^D and, if ``density`` is given, mass density * volume.
    On an axisymmetric grid (``Grid(..., axisymmetric=True)``) volume and mass are per radian:
    V_p = A_p r_p, A_p = h_r h_z / ppc^2 the particle's area in the r-z plane (001 eq. 111), and
    the region must lie at r > 0.

    Args:
        grid: the :class:`Grid` whose cells the lattice follows.
        region: a :class:`Region` (Box, Ball, Disk, Ring, Polygon, Mesh) or a callable mask
            ``f(x) -> bool`` of the lattice points x (N, D).
        ppc: particles per cell per axis, a positive integer (default 2).
        density: the mass density, positive (one number or one per particle); None (the
            default) leaves the masses to the material's density (:meth:`Simulation.init`).
        velocity: the initial velocity: one number, a D-vector, (N, D), or a function of
            position ``f(x) -> (N, D)``; default 0.0.

    Returns:
        The :class:`Particles` at the lattice points inside ``region``.
    """
    check(isinstance(grid, Grid), f"fill: grid must be a jm.Grid, got {type(grid).__name__}")
    ppc = positive_int("fill", "ppc", ppc, fix="particles per cell per axis")
    if density is not None:
        POSITIVE.check("fill", "density", density)
    dim = grid.dim
    if not callable(velocity) and ndim(velocity) <= 1:  # a constant: one number or one per axis
        finite_vector("fill", "velocity", velocity, dim)
    elif not callable(velocity):
        FINITE.check("fill", "velocity", velocity)
    h = np.array(grid.spacing)
    lower = np.array(grid.lower)
    # lattice over all cells, restricted to the region's bounding box when known
    ranges = []
    if isinstance(region, Region):
        region.check_grid(grid)
        blo, bhi = (np.array(b, dtype=float) for b in region.bounds())
        check(blo.shape == (dim,), f"fill: region has {blo.shape[0]} axes but the grid has {dim}")
        first = np.clip(np.floor((blo - lower) / h).astype(int), 0, None)
        last = np.minimum(np.ceil((bhi - lower) / h).astype(int), np.array(grid.cells))
        contains = region.contains
    else:
        check(callable(region),
              "fill: region must be a jm.Box/Disk/Ball/Ring/Polygon/Mesh or a callable mask f(x) -> bool")
        first = np.zeros(dim, int)
        last = np.array(grid.cells)
        contains = region
    # the lattice is built whole before the region selects from it: size it first.  Per lattice
    # point: its coordinates, the mesh and the mask (about 3 D + 1 floats); per particle kept, the
    # State a Simulation makes of it (x, v, F, mass, volume: D^2 + 2 D + 2 floats) a few times over
    candidates = float(np.prod((last - first).astype(float))) * float(ppc) ** dim
    require_memory(f"fill: {candidates:.4g} lattice points ({ppc} per cell per axis over "
                   f"{' x '.join(str(int(n)) for n in last - first)} cells)",
                   candidates * 8.0 * (3 * dim + 1 + 4 * (dim * dim + 2 * dim + 2)),
                   "use a coarser grid (spacing/cells) or fewer particles per cell (ppc)")
    offsets = (np.arange(ppc) + 0.5) / ppc
    for a in range(dim):
        cells = np.arange(first[a], last[a])
        ranges.append((lower[a] + h[a] * (cells[:, None] + offsets[None, :])).reshape(-1))
    mesh = np.meshgrid(*ranges, indexing="ij")
    x = np.stack([m.reshape(-1) for m in mesh], axis=-1) if ranges[0].size else np.zeros((0, dim))
    if x.shape[0]:
        x = x[np.asarray(contains(x), dtype=bool)]
    check(x.shape[0] > 0, "fill: the region contains no lattice point; check it lies on the grid or raise ppc")
    volume = np.full(x.shape[0], np.prod(h) / ppc**dim)
    if grid.axisymmetric:  # per radian: A_p <r_p> with <r_p> = r_p for the rectangle (001 eq. 111)
        check(np.all(x[:, 0] > 0), f"fill: an axisymmetric grid needs the region at r > 0 (axis x is the radius); "
                                   f"{int(np.sum(x[:, 0] <= 0))} lattice points lie at r <= 0")
        volume = volume * x[:, 0]
    if callable(velocity):
        v = np.asarray(velocity(x), dtype=float)
        check(np.all(np.isfinite(v)), "fill: velocity(x) returned non-finite values (NaN or inf)")
    else:
        v = np.asarray(velocity, dtype=float)
        check(v.shape in ((), (dim,), (x.shape[0], dim)),
              f"fill: velocity has shape {v.shape}; give one number, {dim} (one per axis) or ({x.shape[0]}, {dim})")
        v = np.broadcast_to(v, (x.shape[0], dim))
    check(v.shape == (x.shape[0], dim), f"fill: velocity must give {dim} components per particle, got {v.shape}")
    check(density is None or np.shape(density) in ((), (x.shape[0],)),
          f"fill: density has shape {np.shape(density)}; give one number (or one per particle, {x.shape[0]})")
    # onto the device without compiling (jnp.asarray of a NumPy array compiles a small program per new shape on
    # jaxlib 0.10, jit(stage)), in memory of XLA's own that a donated run computes in place of (to_device)
    mass = None if density is None else to_device(np.asarray(density) * volume)
    return Particles(x=to_device(x), v=to_device(np.array(v)), volume=to_device(volume), mass=mass,
                     ppc=int(ppc), axisymmetric=grid.axisymmetric)


def joined(*parts: Particles, ppc: int) -> Particles:
    """The particles of ``parts`` (:func:`fill` results, e.g. two bodies) one after the other, in that
    order, their masses from the material (``mass=None``); joined on the host (``jnp.concatenate``
    compiled a small program per array on a first call)."""
    def stacked(name):
        return to_device(np.concatenate([np.asarray(getattr(p, name)) for p in parts]))

    return type(parts[0])(x=stacked("x"), v=stacked("v"), volume=stacked("volume"), mass=None, ppc=ppc)
