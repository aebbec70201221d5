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


class Slabs(eqx.Module):
    """The slab decomposition of ``grid`` over ``devices`` devices along grid axis x.

    Args:
        grid: the global :class:`jaxmpm.Grid`.
        devices: the number of devices (slabs), at least 1; ``grid.cells[0]`` must be a multiple.
        halo: the halo width H in node planes, at least the shape function's nodes per axis minus
            one (:func:`halo_for`: 1 for linear, 2 for uGIMP and quadratic, 3 for cubic B-splines);
            the slabs must be wider than 2 H cells.
        axis_name: the mesh axis the slabs are laid along (the name ``shard_map`` binds).
    """

    cells: tuple = eqx.field(static=True)
    devices: int = eqx.field(static=True)
    halo: int = eqx.field(static=True)
    axis_name: str = eqx.field(static=True)

    def __init__(self, grid, devices: int, halo: int, axis_name: str = "slabs"):
        check(isinstance(devices, int) and devices >= 1, f"Slabs: devices = {devices!r} must be a positive integer")
        check(isinstance(halo, int) and halo >= 1, f"Slabs: halo = {halo!r} must be a positive integer "
              "(node planes; at least the shape function's nodes per axis minus one)")
        cells_x = grid.cells[0]
        check(cells_x % devices == 0, f"Slabs: the grid's {cells_x} cells along x do not split into {devices} equal "
              f"slabs; choose a cell count along x that is a multiple of {devices}")
        check(cells_x // devices > 2 * halo, f"Slabs: slabs of {cells_x // devices} cells are not wider than twice the "
              f"halo ({halo} planes); use fewer devices or a finer grid")
        self.cells = tuple(grid.cells)
        self.devices = devices
        self.halo = halo
        self.axis_name = axis_name

    # ------------------------------------------------------------------ sizes
    @property
    def cells_per_slab(self) -> int:
        """S, the cells along x of each slab."""
        return self.cells[0] // self.devices

    @property
    def plane_nodes(self) -> int:
        """Nodes per plane normal to x (the stride of axis x in the flat numbering)."""
        return int(np.prod([c + 1 for c in self.cells[1:]], dtype=np.int64))

    @property
    def window_planes(self) -> int:
        """W = S + 2 H + 1, the node planes of each device's window."""
        return self.cells_per_slab + 2 * self.halo + 1

    @property
    def window_nodes(self) -> int:
        """The nodes of each device's window (W planes)."""
        return self.window_planes * self.plane_nodes

    @property
    def overlap_planes(self) -> int:
        """2 H + 1: the planes two neighbouring windows share."""
        return 2 * self.halo + 1

    def window_start(self, k):
        """The first node plane of device ``k``'s window, k S - H (negative on the first device:
        planes below the grid are padding that no particle reaches)."""
        return k * self.cells_per_slab - self.halo

    # ------------------------------------------------------------------ particles and stencils
    def owner(self, x, lower_x: float, spacing_x: float):
        """The device whose slab holds each particle's cell, (N,) int32, from positions (N, D)."""
        cell = jnp.floor((x[:, 0] - lower_x) / spacing_x).astype(jnp.int32)
        return jnp.clip(cell // self.cells_per_slab, 0, self.devices - 1)

    # ------------------------------------------------------------------ nodal data
    def window(self, nodal, k, fields: int = 1):
        """Device ``k``'s window of a global per-node array ``nodal`` (fields x num_nodes, ...), field
        by field: the planes [k S - H, (k + 1) S + H], zero-padded below and above the grid."""
        planes = nodal.reshape((fields, self.cells[0] + 1, self.plane_nodes) + nodal.shape[1:])
        pad = [(0, 0), (self.halo, self.halo)] + [(0, 0)] * (planes.ndim - 2)
        padded = jnp.pad(planes, pad)
        zero = jnp.zeros((), jnp.int32)
        start = (zero, jnp.asarray(k * self.cells_per_slab, jnp.int32)) + (zero,) * (planes.ndim - 2)
        sizes = (fields, self.window_planes) + planes.shape[2:]
        return jax.lax.dynamic_slice(padded, start, sizes).reshape((fields * self.window_nodes,) + nodal.shape[1:])

    def halo_sum(self, nodal, fields: int = 1):
        """Complete a window's P2G sums: each device adds its neighbours' shares on the planes it
        shares with them (inside ``shard_map`` over ``axis_name``).  ``nodal`` (fields x
        window_nodes, ...), each velocity field's window in turn."""
        planes = nodal.reshape((fields, self.window_planes, self.plane_nodes) + nodal.shape[1:])
        n, D = self.overlap_planes, self.devices
        if D == 1:
            return nodal
        upward = [(k, k + 1) for k in range(D - 1)]
        downward = [(k + 1, k) for k in range(D - 1)]
        # my top overlap goes to the device above, which adds it to its bottom overlap, and back
        from_below = jax.lax.ppermute(planes[:, -n:], self.axis_name, upward)
        from_above = jax.lax.ppermute(planes[:, :n], self.axis_name, downward)
        planes = planes.at[:, :n].add(from_below).at[:, -n:].add(from_above)
        return planes.reshape(nodal.shape)

    def device_window(self, k, fields: int = 1):
        """The transfer layer's :class:`~jaxmpm.transfer.kernels.windowed.Window` of device ``k``
        (traced inside ``shard_map``), for :func:`~jaxmpm.transfer.kernels.windowed.use_window`;
        ``fields`` the model's velocity fields."""
        num_nodes = (self.cells[0] + 1) * self.plane_nodes
        return Window(num_nodes, self.window_nodes, self.window_start(k) * self.plane_nodes,
                      complete=lambda nodal, fields: self.halo_sum(nodal, fields),
                      restrict=lambda nodal, fields: self.window(nodal, k, fields), fields=fields)


def halo_for(shape) -> int:
    """The smallest halo (node planes) for a shape function: its nodes per axis minus one, the
    reach of a stencil beyond its particle's cell."""
    return max(1, int(math.ceil(shape.nodes_per_axis)) - 1)
