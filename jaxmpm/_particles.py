"""Filling regions with material points: ``fill(grid, region, ppc=..., density=..., velocity=...)``."""

from __future__ import annotations

import itertools
from typing import Callable, Sequence

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ._errors import check
from ._grid import Grid


class Region(eqx.Module):
    """A region of space: ``contains(x) -> bool`` for points (N, D) and a bounding box."""

    def contains(self, x):  # pragma: no cover - interface
        raise NotImplementedError

    def bounds(self):  # pragma: no cover - interface
        raise NotImplementedError


class Box(Region):
    lower: tuple = eqx.field(static=True)
    upper: tuple = eqx.field(static=True)

    def __init__(self, lower: Sequence[float], upper: Sequence[float]):
        self.lower = tuple(float(v) for v in np.atleast_1d(lower))
        self.upper = tuple(float(v) for v in np.atleast_1d(upper))
        check(len(self.lower) == len(self.upper), "Box: lower and upper must have the same length")
        check(all(u > l for l, u in zip(self.lower, self.upper)), "Box: every upper must exceed lower")

    def contains(self, x):
        return np.all((x >= np.array(self.lower)) & (x < np.array(self.upper)), axis=-1)

    def bounds(self):
        return self.lower, self.upper


class Ball(Region):
    """Points within ``radius`` of ``center`` (a disk in 2D, a ball in 3D)."""

    center: tuple = eqx.field(static=True)
    radius: float = eqx.field(static=True)

    def __init__(self, center: Sequence[float], radius: float):
        self.center = tuple(float(v) for v in np.atleast_1d(center))
        check(radius > 0, f"{type(self).__name__}: radius = {radius} must be positive")
        self.radius = float(radius)

    def contains(self, x):
        return np.sum((x - np.array(self.center)) ** 2, axis=-1) < self.radius**2

    def bounds(self):
        c = np.array(self.center)
        return tuple(c - self.radius), tuple(c + self.radius)


class Disk(Ball):
    """A 2D disk (same as :class:`Ball`)."""


class Ring(Region):
    """Annulus inner <= |x - center| < outer."""

    center: tuple = eqx.field(static=True)
    inner: float = eqx.field(static=True)
    outer: float = eqx.field(static=True)

    def __init__(self, center: Sequence[float], inner: float, outer: float):
        self.center = tuple(float(v) for v in np.atleast_1d(center))
        check(0 <= inner < outer, f"Ring: need 0 <= inner ({inner}) < outer ({outer})")
        self.inner = float(inner)
        self.outer = float(outer)

    def contains(self, x):
        r2 = np.sum((x - np.array(self.center)) ** 2, axis=-1)
        return (r2 >= self.inner**2) & (r2 < self.outer**2)

    def bounds(self):
        c = np.array(self.center)
        return tuple(c - self.outer), tuple(c + self.outer)


class Particles(eqx.Module):
    """Material points: positions ``x`` (N, D), velocities ``v`` (N, D), reference volumes
    ``volume`` (N,), masses ``mass`` (N,) or None (then the material's density sets them) and the
    number of particles per cell per axis ``ppc``."""

    x: jnp.ndarray
    v: jnp.ndarray
    volume: jnp.ndarray
    mass: jnp.ndarray | None = None
    ppc: int = eqx.field(static=True, default=1)

    @property
    def num(self) -> int:
        return self.x.shape[0]


def fill(
    grid: Grid,
    region: Region | Callable,
    ppc: int = 2,
    density: float | None = None,
    velocity=0.0,
) -> Particles:
    """Place ``ppc`` particles per cell per axis, on a regular lattice aligned with the grid cells,
    at the lattice points inside ``region`` (a :class:`Region` or a callable mask ``f(x) -> bool``).

    Each particle gets volume h^D / ppc^D and, if ``density`` is given, mass density * volume;
    ``velocity`` is a constant (scalar or D-vector) or a function of position ``f(x) -> (N, D)``.
    """
    check(isinstance(ppc, (int, np.integer)) and ppc >= 1,
          f"fill: ppc = {ppc!r} must be a positive integer (particles per cell per axis)")
    if density is not None:
        check(np.all(np.asarray(density) > 0), f"fill: density = {density!r} must be positive")
    dim = grid.dim
    h = np.array(grid.spacing)
    lower = np.array(grid.lower)
    # lattice over all cells, restricted to the region's bounding box when known
    ranges = []
    if isinstance(region, Region):
        blo, bhi = (np.array(b, dtype=float) for b in region.bounds())
        check(blo.shape == (dim,), f"fill: region has {blo.shape[0]} axes but the grid has {dim}")
        first = np.clip(np.floor((blo - lower) / h).astype(int), 0, None)
        last = np.minimum(np.ceil((bhi - lower) / h).astype(int), np.array(grid.cells))
        contains = region.contains
    else:
        check(callable(region), "fill: region must be a jm.Box/Disk/Ball/Ring or a callable mask f(x) -> bool")
        first = np.zeros(dim, int)
        last = np.array(grid.cells)
        contains = region
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
    if callable(velocity):
        v = np.asarray(velocity(x), dtype=float)
    else:
        v = np.broadcast_to(np.asarray(velocity, dtype=float), (x.shape[0], dim))
    check(v.shape == (x.shape[0], dim), f"fill: velocity must give {dim} components per particle, got {v.shape}")
    mass = None if density is None else jnp.asarray(np.asarray(density) * volume)
    return Particles(x=jnp.asarray(x), v=jnp.asarray(np.array(v)), volume=jnp.asarray(volume), mass=mass, ppc=int(ppc))
