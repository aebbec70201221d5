"""Slab domain decomposition of the grid along its first axis, for one simulation on many devices.

The devices of one mesh axis each own a slab of ``cells_per_slab`` cells along grid axis x (the
first, slowest-varying axis of the flat C-order node numbering, so that a slab's nodes are one
contiguous range of node numbers) and keep a *window* of node planes around it:

    owned planes of device k:   [k S, (k + 1) S)            (the last device also the plane at the top)
    window of device k:         [k S - H, (k + 1) S + H]    W = S + 2 H + 1 planes, H = ``halo``

Particles live on the device whose slab holds their cell; with H at least the shape function's
reach, a particle's whole stencil lies in its device's window.  The stencil is computed on the
*global* grid, exactly as on one device, and only its node numbers are shifted into the window
(:meth:`jaxmpm.transfer.kernels.windowed.Window.local_stencil`: integer arithmetic, so the weights are
bitwise those of one device).

**One exchange per P2G.** After a device's particles are scattered into its window, the planes it
shares with a neighbour, [(k + 1) S - H, (k + 1) S + H] (2 H + 1 planes), hold only its own
particles' share.  Each device sends that overlap to the neighbour and adds what it receives
(:meth:`Slabs.halo_sum`, one ``lax.ppermute`` each way).  With S > 2 H no plane is shared by three
devices, so afterwards every plane of every window holds the complete sum -- the owned planes and
the halo alike.  Grid operations that act node by node then give the same values on a halo plane
as on the neighbour's owned plane, and G2P reads its window without a second exchange.  The bytes
moved per P2G are the overlap's, (2 H + 1) x (nodes per plane) x columns each way, independent of the
grid's length along x and of the particle count.

**Slabs that move** (load balance).  Built with ``max_cells``, the slabs may be unequal: slab k owns
the cells [b_k, b_{k+1}) for boundaries b (b_0 = 0, b_D = cells along x), each slab between
2 H + 1 and ``max_cells`` cells wide.  Every window then has W = ``max_cells`` + 2 H + 1 planes,
starting at b_k - H, so that one compiled program serves any boundaries: they are a runtime int
array (``bounds``) of the methods below, not a static size.  Neighbouring windows still share the
2 H + 1 planes [b_{k+1} - H, b_{k+1} + H] at their face, which lie at offset b_{k+1} - b_k in
device k's window: the exchange slices them there (a dynamic slice, still one ``ppermute`` each
way).  A narrower slab's window reaches past its neighbour's face; those planes receive none of
its particles and none of the exchange, and no stencil of its particles reads them.  The
boundaries that equalise the particle counts are chosen on the host (:meth:`Slabs.balanced_bounds`).
Without ``bounds`` the methods are the equal slabs' (static slices, as before).

This is the communication layer of the sharded path built on JAX's own runtime (``jax.shard_map``
over a ``Mesh``, ``lax.ppermute``); nothing here talks to devices by itself.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..core.errors import check
from ..transfer.kernels.windowed import Window


def _too_many(cells_x: int, devices: int, halo: int, moving: bool) -> str:
    """The error for more slabs than the grid holds: each is at least 2 H + 1 cells wide; equal slabs
    also split the cells evenly."""
    narrow = 2 * halo + 1
    most = cells_x // narrow
    where = f"Slabs: the grid's {cells_x} cells along x hold at most {most} slab(s) of 2 H + 1 = {narrow} cells (the " \
            f"narrowest, halo H = {halo} planes), not {devices}; "
    if most < 2:
        return where + f"run on one device, or use a grid of at least {devices * narrow} cells along x"
    even = max(d for d in range(1, most + 1) if cells_x % d == 0)
    fits = (f"use at most {most} devices" if moving else
            f"use {even} device(s) (equal slabs split the {cells_x} cells evenly), or up to {most} with slabs that "
            "move (--rebalance-every K)" if even < most else f"use at most {most} devices")
    return where + f"{fits}, or a grid of at least {devices * narrow} cells along x"


class Slabs(eqx.Module):
    """The slab decomposition of ``grid`` over ``devices`` devices along grid axis x.

    Args:
        grid: the global :class:`jaxmpm.Grid`.
        devices: the number of devices (slabs), at least 1; ``grid.cells[0]`` must be a multiple.
        halo: the halo width H in node planes, at least the shape function's nodes per axis minus
            one (:func:`halo_for`: 1 for linear, 2 for uGIMP and quadratic, 3 for cubic B-splines);
            the slabs must be wider than 2 H cells.
        axis_name: the mesh axis the slabs are laid along (the name ``shard_map`` binds).
        max_cells: the widest a slab may be, in cells (slabs that move with the particles: see the
            module docstring; every window is ``max_cells`` + 2 H + 1 planes); None (the default):
            equal slabs of cells_x / devices cells.
    """

    cells: tuple = eqx.field(static=True)
    devices: int = eqx.field(static=True)
    halo: int = eqx.field(static=True)
    axis_name: str = eqx.field(static=True)
    max_cells: int = eqx.field(static=True)

    def __init__(self, grid, devices: int, halo: int, axis_name: str = "slabs", max_cells: int | None = None):
        check(isinstance(devices, int) and devices >= 1, f"Slabs: devices = {devices!r} must be a positive integer")
        check(isinstance(halo, int) and halo >= 1, f"Slabs: halo = {halo!r} must be a positive integer "
              "(node planes; at least the shape function's nodes per axis minus one)")
        cells_x = grid.cells[0]
        if max_cells is not None:  # slabs that move: any boundaries with widths in [2 H + 1, max_cells]
            check(isinstance(max_cells, (int, np.integer)) and not isinstance(max_cells, bool)
                  and 2 * halo + 1 <= max_cells <= cells_x, f"Slabs: max_cells = {max_cells!r} must be an integer "
                  f"from 2 H + 1 = {2 * halo + 1} (the narrowest slab) to the grid's {cells_x} cells along x")
            check(devices * (2 * halo + 1) <= cells_x, _too_many(cells_x, devices, halo, moving=True))
            check(cells_x <= devices * max_cells, f"Slabs: {devices} slabs of at most max_cells = {max_cells} cells "
                  f"cannot cover the grid's {cells_x} cells along x; raise max_cells to at least "
                  f"{-(-cells_x // devices)}")
            self.cells, self.devices, self.halo, self.axis_name = tuple(grid.cells), devices, halo, axis_name
            self.max_cells = int(max_cells)
            return
        check(devices * (2 * halo + 1) <= cells_x, _too_many(cells_x, devices, halo, moving=False))
        check(cells_x % devices == 0, f"Slabs: the grid's {cells_x} cells along x do not split into {devices} equal "
              f"slabs; choose a cell count along x that is a multiple of {devices}, or let the slabs differ: "
              "ShardedSimulation(..., rebalance_every=K) (--rebalance-every K on the command line)")
        self.cells = tuple(grid.cells)
        self.devices = devices
        self.halo = halo
        self.axis_name = axis_name
        self.max_cells = cells_x // devices

    # ------------------------------------------------------------------ sizes
    @property
    def cells_per_slab(self) -> int:
        """S, the cells along x of each equal slab."""
        return self.cells[0] // self.devices

    @property
    def min_cells(self) -> int:
        """2 H + 1, the narrowest slab: no node plane is shared by three windows."""
        return 2 * self.halo + 1

    @property
    def plane_nodes(self) -> int:
        """Nodes per plane normal to x (the stride of axis x in the flat numbering)."""
        return int(np.prod([c + 1 for c in self.cells[1:]], dtype=np.int64))

    @property
    def window_planes(self) -> int:
        """W = S + 2 H + 1, the node planes of each device's window (S = ``max_cells``)."""
        return self.max_cells + 2 * self.halo + 1

    @property
    def window_nodes(self) -> int:
        """The nodes of each device's window (W planes)."""
        return self.window_planes * self.plane_nodes

    @property
    def overlap_planes(self) -> int:
        """2 H + 1: the planes two neighbouring windows share."""
        return 2 * self.halo + 1

    def window_start(self, k, bounds=None):
        """The first node plane of device ``k``'s window, k S - H, or b_k - H with ``bounds``
        (negative on the first device: planes below the grid are padding that no particle reaches)."""
        return (k * self.cells_per_slab if bounds is None else bounds[k]) - self.halo

    # ------------------------------------------------------------------ boundaries
    def equal_bounds(self) -> np.ndarray:
        """(devices + 1,) int32: the boundaries of slabs as equal as the cells allow."""
        return (np.arange(self.devices + 1, dtype=np.int64) * self.cells[0] // self.devices).astype(np.int32)

    def balanced_bounds(self, counts) -> np.ndarray:
        """(devices + 1,) int32: the boundaries that equalise the slabs' particle counts, on the host.

        ``counts`` (cells_x,): the particles in each column of cells along x (a histogram of the
        particles' cells).  Of the boundaries whose widths lie in [2 H + 1, ``max_cells``], those
        with the fewest particles in the fullest slab (a bisection on that count, each try a sweep
        over the cumulative counts: which faces the first k slabs can reach); among them, each face
        as near as it can be to the cumulative count's k/D point, and then to the equal slabs' face
        (an empty stretch of grid is shared evenly)."""
        counts = np.asarray(counts, dtype=np.int64)
        cells, D, narrow, wide = self.cells[0], self.devices, self.min_cells, self.max_cells
        check(counts.shape == (cells,), f"Slabs.balanced_bounds: counts of shape {counts.shape}, expected ({cells},)")
        cum = np.concatenate([[0], np.cumsum(counts)])
        total = int(cum[-1])

        def ends(b, most):
            """The furthest face after faces ``b`` (array) of a slab of at most ``most`` particles."""
            return np.minimum(np.searchsorted(cum, cum[b] + most, side="right") - 1, np.minimum(b + wide, cells))

        def reachable(most):
            """reach[k][f]: the first k slabs can end at face f, none fuller than ``most``."""
            reach = [np.zeros(cells + 1, bool)]
            reach[0][0] = True
            for _ in range(D):
                b = np.flatnonzero(reach[-1])
                first, last = b + narrow, ends(b, most)
                ok = first <= last
                step = np.zeros(cells + 2, np.int64)
                np.add.at(step, first[ok], 1)
                np.add.at(step, last[ok] + 1, -1)
                reach.append(np.cumsum(step)[:cells + 1] > 0)
            return reach

        # the chains-on-chains partition (Pinar & Aykanat 2004): bisect on the fullest slab's count,
        # here with the slabs' widths bounded; the fullest slab holds at least N / D particles
        low, high = -(-total // D), total
        while low < high:
            mid = (low + high) // 2
            if reachable(mid)[D][cells]:
                high = mid
            else:
                low = mid + 1
        reach = reachable(low)
        bounds = [cells]
        for k in range(D - 1, -1, -1):  # back from the top face: each face nearest its share, then its equal place
            b = np.flatnonzero(reach[k])
            fits = b[(b + narrow <= bounds[-1]) & (ends(b, low) >= bounds[-1])]
            nearest = np.lexsort((np.abs(fits * D - k * cells), np.abs(cum[fits] * D - k * total)))[0]
            bounds.append(int(fits[nearest]))
        return np.asarray(bounds[::-1], dtype=np.int32)

    def possible_faces(self, moving: bool) -> np.ndarray:
        """The cells at which an interior slab face can lie: the equal slabs' faces, or with
        ``moving`` every place a face of slabs between 2 H + 1 and ``max_cells`` cells wide can take
        (the j-th face lies between j narrow and j wide slabs from either end)."""
        if not moving:
            return self.equal_bounds()[1:-1].astype(np.int64)
        cells, D, narrow, wide = self.cells[0], self.devices, self.min_cells, self.max_cells
        return np.unique(np.concatenate([
            np.arange(max(j * narrow, cells - (D - j) * wide), min(j * wide, cells - (D - j) * narrow) + 1)
            for j in range(1, D)]))

    def check_bounds(self, bounds) -> None:
        """An InputError unless ``bounds`` (host values) cut the grid into slabs this layout serves."""
        b = np.asarray(bounds)
        widths = np.diff(b)
        check(b.shape == (self.devices + 1,) and b[0] == 0 and b[-1] == self.cells[0]
              and np.all(widths >= self.min_cells) and np.all(widths <= self.max_cells),
              f"Slabs: bounds {b.tolist()} must run from 0 to {self.cells[0]} with {self.devices} slabs of "
              f"{self.min_cells} to {self.max_cells} cells")

    # ------------------------------------------------------------------ particles and stencils
    def cell(self, x, lower_x: float, spacing_x: float):
        """Each particle's cell index along x, (N,) int32 (not clipped), from positions (N, D)."""
        return jnp.floor((x[:, 0] - lower_x) / spacing_x).astype(jnp.int32)

    def owner(self, x, lower_x: float, spacing_x: float, bounds=None):
        """The device whose slab holds each particle's cell, (N,) int32, from positions (N, D)
        (``bounds``: the slabs' boundaries, for slabs that move)."""
        cell = self.cell(x, lower_x, spacing_x)
        if bounds is None:
            return jnp.clip(cell // self.cells_per_slab, 0, self.devices - 1)
        # the interior faces at or below the cell (cells off the grid: the first or last slab)
        return jnp.sum(cell[:, None] >= jnp.asarray(bounds)[None, 1:-1], axis=1).astype(jnp.int32)

    # ------------------------------------------------------------------ nodal data
    def window(self, nodal, k, fields: int = 1, bounds=None):
        """Device ``k``'s window of a global per-node array ``nodal`` (fields x num_nodes, ...), field
        by field: the planes [k S - H, (k + 1) S + H] (with ``bounds``: W planes from b_k - H),
        zero-padded below and above the grid."""
        planes = nodal.reshape((fields, self.cells[0] + 1, self.plane_nodes) + nodal.shape[1:])
        # above: the last window may start as high as the narrowest slab allows
        above = self.halo if bounds is None else self.halo + self.max_cells - self.min_cells
        pad = [(0, 0), (self.halo, above)] + [(0, 0)] * (planes.ndim - 2)
        padded = jnp.pad(planes, pad)
        zero = jnp.zeros((), jnp.int32)
        first = k * self.cells_per_slab if bounds is None else bounds[k]
        start = (zero, jnp.asarray(first, jnp.int32)) + (zero,) * (planes.ndim - 2)
        sizes = (fields, self.window_planes) + planes.shape[2:]
        return jax.lax.dynamic_slice(padded, start, sizes).reshape((fields * self.window_nodes,) + nodal.shape[1:])

    def halo_sum(self, nodal, fields: int = 1, width=None):
        """Complete a window's P2G sums: each device adds its neighbours' shares on the planes it
        shares with them (inside ``shard_map`` over ``axis_name``).  ``nodal`` (fields x
        window_nodes, ...), each velocity field's window in turn; ``width``: this device's slab
        width b_{k+1} - b_k (traced), for slabs that move (the overlap with the device above starts
        there); None: the window's top planes."""
        planes = nodal.reshape((fields, self.window_planes, self.plane_nodes) + nodal.shape[1:])
        n, D = self.overlap_planes, self.devices
        if D == 1:
            return nodal
        upward = [(k, k + 1) for k in range(D - 1)]
        downward = [(k + 1, k) for k in range(D - 1)]
        # my top overlap goes to the device above, which adds it to its bottom overlap, and back
        if width is None:
            from_below = jax.lax.ppermute(planes[:, -n:], self.axis_name, upward)
            from_above = jax.lax.ppermute(planes[:, :n], self.axis_name, downward)
            planes = planes.at[:, :n].add(from_below).at[:, -n:].add(from_above)
            return planes.reshape(nodal.shape)
        top = jax.lax.dynamic_slice_in_dim(planes, width, n, axis=1)
        from_below = jax.lax.ppermute(top, self.axis_name, upward)
        from_above = jax.lax.ppermute(planes[:, :n], self.axis_name, downward)
        planes = planes.at[:, :n].add(from_below)  # width >= 2 H + 1: the two overlaps are apart
        planes = jax.lax.dynamic_update_slice_in_dim(planes, top + from_above, width, axis=1)
        return planes.reshape(nodal.shape)

    def device_window(self, k, fields: int = 1, bounds=None):
        """The transfer layer's :class:`~jaxmpm.transfer.kernels.windowed.Window` of device ``k``
        (traced inside ``shard_map``), for :func:`~jaxmpm.transfer.kernels.windowed.use_window`;
        ``fields`` the model's velocity fields; ``bounds`` (traced (devices + 1,) int) the slabs'
        boundaries, for slabs that move."""
        num_nodes = (self.cells[0] + 1) * self.plane_nodes
        width = None if bounds is None else bounds[k + 1] - bounds[k]
        return Window(num_nodes, self.window_nodes, self.window_start(k, bounds) * self.plane_nodes,
                      complete=lambda nodal, fields: self.halo_sum(nodal, fields, width),
                      restrict=lambda nodal, fields: self.window(nodal, k, fields, bounds), fields=fields)


def halo_for(shape) -> int:
    """The smallest halo (node planes) for a shape function: its nodes per axis minus one, the
    reach of a stencil beyond its particle's cell."""
    return max(1, int(math.ceil(shape.nodes_per_axis)) - 1)
