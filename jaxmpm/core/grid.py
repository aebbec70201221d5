"""Background grid: a box of ``cells`` uniform cells in 1, 2 or 3 dimensions.

Nodes are numbered in C order over ``cells + 1`` nodes per axis; nodal fields are flat
arrays of shape ``(num_nodes, D)``.  All grid data are static: they fix array shapes.
"""

from __future__ import annotations

import math
from typing import Sequence

import equinox as eqx
import numpy as np

from .errors import check
from .validate import NON_NEGATIVE, POSITIVE, finite_vector, positive_int, sequence, show

_AXES = "xyz"
#: the most nodes a grid may have: the stencils' node numbers are int32
MAX_NODES = 2**31 - 1


def _as_tuple(value, name: str, owner: str = "Grid") -> tuple:
    return sequence(owner, name, value)


class Grid(eqx.Module):
    """Uniform background grid: ``Grid(lower=(0.0,), upper=(25.0,), cells=(16,))``.  All its data
    are static (they fix array shapes); nodes are numbered in C order over ``cells + 1`` nodes per
    axis.  :meth:`covering` builds the smallest grid of a given cell size around a box.

    ``axisymmetric=True`` (2D only) makes the grid the r-z half-plane of a body of revolution
    (001 §7): axis x is the radius r, axis y the axial coordinate z.  Particle masses and volumes
    are then per radian (:func:`jaxmpm.fill`), the shape functions the r-weighted ones of 001 eqs.
    112 and 115 with the hoop shape function T_ip of eq. 116, the internal force carries the hoop
    term -V0_p tau_thth T_ip e_r (001 eq. 120) and F is 3x3 in (r, z, theta) order, F_thth the hoop
    stretch (updated with the hoop rate v_r/r = sum_i v_ri T_ip, 001 eq. 113).

    Args:
        lower: the lower corner, one finite coordinate per axis (1, 2 or 3 axes).
        upper: the upper corner, each coordinate greater than ``lower``'s.
        cells: the number of cells per axis, positive integers; the cell size is
            (upper - lower) / cells.
        axisymmetric: True for an r-z grid of a body of revolution (2D only; default False).
    """

    lower: tuple = eqx.field(static=True)
    upper: tuple = eqx.field(static=True)
    cells: tuple = eqx.field(static=True)
    axisymmetric: bool = eqx.field(static=True, default=False)

    def __init__(self, lower: Sequence[float], upper: Sequence[float], cells: Sequence[int],
                 axisymmetric: bool = False):
        lower = finite_vector("Grid", "lower", lower)
        upper = finite_vector("Grid", "upper", upper)
        cells_in = _as_tuple(cells, "cells")
        check(1 <= len(lower) <= 3, f"Grid: lower has {len(lower)} axes; use 1, 2 or 3 axes")
        check(
            len(lower) == len(upper) == len(cells_in),
            f"Grid: lower, upper and cells must have the same number of axes "
            f"(got {len(lower)}, {len(upper)}, {len(cells_in)})",
        )
        cells_out = tuple(positive_int("Grid", f"cells[{a}]", c, fix=f"the number of cells along axis {_AXES[a]}")
                          for a, c in enumerate(cells_in))
        for a, (lo, hi) in enumerate(zip(lower, upper)):
            check(
                hi > lo,
                f"Grid: upper[{a}] = {hi} must be greater than lower[{a}] = {lo}; swap them or widen the box",
            )
            check(math.isfinite(hi - lo) and math.isfinite((hi - lo) / cells_out[a]) and (hi - lo) / cells_out[a] > 0,
                  f"Grid: the box [{lo}, {hi}] along axis {_AXES[a]} with {cells_out[a]} cells has no finite "
                  "positive cell size; use a smaller box or fewer cells")
        nodes = math.prod(c + 1 for c in cells_out)
        check(nodes <= MAX_NODES,
              f"Grid: {' x '.join(str(c + 1) for c in cells_out)} = {nodes:.4g} nodes; node numbers are int32, so a "
              f"grid has at most {MAX_NODES} nodes: use fewer cells (a coarser spacing or a smaller box)")
        check(isinstance(axisymmetric, (bool, np.bool_)),
              f"Grid: axisymmetric = {show(axisymmetric)} must be True (an r-z grid, 001 §7) or False")
        check(not axisymmetric or len(lower) == 2,
              f"Grid: axisymmetric=True needs a 2D grid (axis x = r, axis y = z), got {len(lower)} axes; "
              "give lower, upper and cells with two entries")
        self.lower = lower
        self.upper = upper
        self.cells = cells_out
        self.axisymmetric = bool(axisymmetric)

    # ----------------------------------------------------------------- geometry
    @property
    def dim(self) -> int:
        return len(self.cells)

    @property
    def spacing(self) -> tuple:
        """Cell size h per axis."""
        return tuple((hi - lo) / c for lo, hi, c in zip(self.lower, self.upper, self.cells))

    @property
    def h(self) -> float:
        """Smallest cell size (the one that sets the CFL time step)."""
        return min(self.spacing)

    @property
    def node_shape(self) -> tuple:
        return tuple(c + 1 for c in self.cells)

    @property
    def num_nodes(self) -> int:
        return math.prod(self.node_shape)  # exact (np.prod wraps past int64)

    @property
    def strides(self) -> tuple:
        """Flat-index stride of each axis (C order)."""
        shape = self.node_shape
        return tuple(int(np.prod(shape[a + 1 :])) for a in range(self.dim))

    def node_coordinates(self) -> np.ndarray:
        """Node positions, shape ``(num_nodes, D)``, flat C order (a NumPy constant)."""
        axes = [lo + h * np.arange(n) for lo, h, n in zip(self.lower, self.spacing, self.node_shape)]
        mesh = np.meshgrid(*axes, indexing="ij")
        return np.stack([m.reshape(-1) for m in mesh], axis=-1)

    def node_index_grid(self) -> np.ndarray:
        """Integer node indices per axis, shape ``(num_nodes, D)``."""
        mesh = np.meshgrid(*[np.arange(n) for n in self.node_shape], indexing="ij")
        return np.stack([m.reshape(-1) for m in mesh], axis=-1)

    def face_mask(self, face: str, layers: int = 1) -> np.ndarray:
        """Boolean mask ``(num_nodes,)`` of the nodes on a face (``"x-"``, ``"y+"``, ...).

        ``layers`` > 1 takes that many node layers inward from the face.
        """
        axis, side = parse_face(face, self.dim)
        idx = self.node_index_grid()[:, axis]
        n = self.node_shape[axis]
        return idx < layers if side < 0 else idx >= n - layers

    # --------------------------------------------------------------- builders
    @classmethod
    def covering(
        cls,
        lower: Sequence[float],
        upper: Sequence[float],
        spacing: float | Sequence[float],
        shape=None,
        pad: float | Sequence[float] = 0.0,
        axisymmetric: bool = False,
    ) -> "Grid":
        """Smallest grid with cell size ``spacing`` that covers the box [lower, upper].

        The box is widened by ``pad`` (room for motion) and by the shape function's reach, so
        every particle inside the box has its whole stencil on the grid.  Nodes are aligned with
        ``lower`` (so a boundary plane at ``lower`` falls on a node).
        """
        owner = "Grid.covering"
        d = len(finite_vector(owner, "lower", lower))
        check(1 <= d <= 3, f"{owner}: lower has {d} axes; use 1, 2 or 3 axes")
        axes = f"lower has {d}"
        finite_vector(owner, "upper", upper, d, broadcast=False, context=axes)
        finite_vector(owner, "spacing", spacing, d, valid=POSITIVE, context=axes, fix="the cell size")
        finite_vector(owner, "pad", pad, d, valid=NON_NEGATIVE, context=axes, fix="the room added around the box")
        check(shape is None or hasattr(shape, "margin"),
              f"{owner}: shape = {show(shape)} must be a shape function such as jm.Linear() (or None)")
        lower = _as_tuple(lower, "lower", owner)
        upper = _as_tuple(upper, "upper", owner)
        for a, (lo, hi) in enumerate(zip(lower, upper)):
            check(float(hi) >= float(lo), f"{owner}: upper[{a}] = {show(hi)} must be >= lower[{a}] = {show(lo)}; "
                                          "swap them")
        hs = _as_tuple(spacing, "spacing", owner)
        hs = hs * d if len(hs) == 1 else hs
        pads = _as_tuple(pad, "pad", owner)
        pads = pads * d if len(pads) == 1 else pads
        margin = 0.0 if shape is None else float(shape.margin)
        lo_out, hi_out, cells = [], [], []
        for a, (lo, hi, h, p) in enumerate(zip(lower, upper, hs, pads)):
            check(math.isfinite(p / h) and math.isfinite((hi - lo + 2 * p) / h + 2 * margin),
                  f"{owner}: spacing[{a}] = {show(h)} is too small for the box along axis {_AXES[a]}: the cell "
                  "count is not a finite number; raise the spacing")
            lo_cells = math.ceil(margin + p / h - 1e-9)
            lo_g = lo - lo_cells * h
            span = (hi + p - lo_g) / h + margin - 1e-9
            check(math.isfinite(lo_g) and math.isfinite(span) and math.isfinite(lo_g + (span + 1) * h),
                  f"{owner}: the grid along axis {_AXES[a]} (box [{show(lo)}, {show(hi)}], spacing {show(h)}, "
                  f"pad {show(p)}) overflows floating point; use smaller numbers")
            n = math.ceil(span)
            n = max(n, 1)
            lo_out.append(lo_g)
            hi_out.append(lo_g + n * h)
            cells.append(n)
        return cls(tuple(lo_out), tuple(hi_out), tuple(cells), axisymmetric=axisymmetric)


def parse_face(face: str, dim: int) -> tuple[int, int]:
    """``"x-"`` -> (0, -1); ``"y+"`` -> (1, +1)."""
    ok = isinstance(face, str) and len(face) == 2 and face[0] in _AXES[:dim] and face[1] in "+-"
    check(
        ok,
        f"face {face!r} is not a face of a {dim}D grid; use one of "
        + ", ".join(a + s for a in _AXES[:dim] for s in "-+"),
    )
    return _AXES.index(face[0]), (-1 if face[1] == "-" else 1)
