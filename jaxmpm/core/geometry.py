"""Bodies from surface meshes and point clouds.

:class:`Mesh` (a closed triangle surface, 3D: an STL, OBJ or PLY file, a ``trimesh.Trimesh`` or
``(vertices, faces)``) and :class:`Polygon` (closed polygons, 2D: vertex loops or a flat mesh
file's boundary) are regions for :func:`jaxmpm.fill`, which keeps the lattice points inside them;
:func:`point_cloud` makes particles from points with volumes.

Inside test.  A point is inside when a ray from it along -x crosses the surface an odd number of
times.  The points are grouped in columns (equal transverse coordinates: a fill lattice has few
columns of many points), each triangle (edge, in 2D) is tested only against the columns its
bounding box covers, and the crossings are counted per column by one sort: a fill costs about
(points + crossings) log(points) plus one test per (triangle, column) pair of the boxes.

A column through an edge or a vertex is decided as if moved by an infinitesimal (eta, eps) in
(y, z), 0 < eta << eps, with each edge's orientation test computed one way whatever triangle
asks: of two triangles that meet at an edge, exactly one counts a crossing there (or both, where
the surface folds over, which keeps the parity), so lattice points in line with edges and vertices
are classified correctly.  On the surface itself the rule is :class:`Box`'s, lower <= x < upper
along each axis for a face normal to it: a box mesh fills exactly the particles ``jm.Box`` fills.

Reading the files is trimesh's (``pip install 'jaxmpm[mesh]'``).  The inside test is NumPy only:
trimesh's own ``mesh.contains`` casts one ray per point through an rtree (an extra compiled
dependency) and leaves points on the surface undefined.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Callable

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .errors import check
from .grid import Grid
from .particles import Particles, Region
from .validate import FINITE, POSITIVE, fail, finite_vector, ndim, positive_int, show

MESH_SUFFIXES = (".stl", ".obj", ".ply")
_CHUNK = 1 << 20  # candidate (triangle, column) pairs tested at once: a few tens of MB of temporaries
_REPAIR = ("repair it and export it again: trimesh's mesh.fill_holes() (or trimesh.repair.fill_holes(mesh)) closes "
           "small holes, MeshLab or Blender's 3D-Print Toolbox the rest; check with mesh.is_watertight")


# --------------------------------------------------------------------------- reading and transforming
def _trimesh(owner: str):
    try:
        import trimesh
    except ImportError:  # pragma: no cover - the [mesh] and [test] extras install it
        fail(owner, "reading a mesh file needs the trimesh package, which is not installed",
             "pip install 'jaxmpm[mesh]' (or pip install trimesh), or pass the (vertices, faces) arrays")
    return trimesh


def _read_mesh(owner: str, path) -> tuple[np.ndarray, np.ndarray]:
    """Vertices and triangles of an STL, OBJ or PLY file, duplicate vertices merged (trimesh)."""
    path = Path(path)
    where = f"source = {show(str(path))}"
    if not path.is_file():
        fail(owner, f"{where}: no such file" if not path.exists() else f"{where} is not a file",
             f"check the path (a relative one is taken from the working directory, {os.getcwd()})")
    suffix = path.suffix.lower()
    if suffix not in MESH_SUFFIXES:
        fail(owner, f"{where}: cannot read a {suffix or 'suffix-less'} file; a surface mesh must be STL, OBJ or "
                    "PLY (.stl, .obj, .ply)",
             "convert it with a mesh tool (e.g. meshio convert in.vtk out.stl, or export from your CAD program)")
    trimesh = _trimesh(owner)
    try:
        mesh = trimesh.load_mesh(str(path), file_type=suffix[1:])
    except Exception as e:  # every reader error: a corrupt or mislabelled file
        fail(owner, f"{where}: cannot read it as {suffix[1:].upper()} ({type(e).__name__}: {' '.join(str(e).split())})",
             f"check that it is a valid {suffix[1:].upper()} file: open it in a mesh tool and export it again")
    faces = getattr(mesh, "faces", None)
    if faces is None or len(faces) == 0:
        fail(owner, f"{where} holds no triangles (empty, unreadable as {suffix[1:].upper()}, or a point cloud)",
             "export the body's closed surface as triangles; for points with volumes use jm.point_cloud")
    return np.asarray(mesh.vertices, dtype=float), np.asarray(faces)


def _vertices_faces(owner: str, source) -> tuple[np.ndarray, np.ndarray, str]:
    """(vertices, faces, a name for messages) from a file, a trimesh-like object or a pair of arrays."""
    if isinstance(source, (str, os.PathLike)):
        v, f = _read_mesh(owner, source)
        return v, f, Path(source).name
    if hasattr(source, "vertices") and hasattr(source, "faces"):  # trimesh.Trimesh and the like
        return np.asarray(source.vertices), np.asarray(source.faces), type(source).__name__
    if isinstance(source, (tuple, list)) and len(source) == 2:
        return np.asarray(source[0]), np.asarray(source[1]), "(vertices, faces)"
    fail(owner, f"source = {show(source)} is not a mesh",
         "give a file path (.stl, .obj, .ply), a trimesh.Trimesh or (vertices (V, 3), faces (F, 3))")


def _checked_arrays(owner: str, vertices, faces, dim: int) -> tuple[np.ndarray, np.ndarray]:
    v = np.asarray(vertices)
    f = np.asarray(faces)
    check(v.ndim == 2 and v.shape[1] == dim and v.dtype.kind in "iuf",
          f"{owner}: vertices have shape {v.shape} (dtype {v.dtype}); give (V, {dim}) numbers")
    check(bool(np.all(np.isfinite(v))), f"{owner}: vertices hold non-finite coordinates (NaN or inf); fix the mesh")
    check(f.ndim == 2 and f.shape[1] == 3 and f.dtype.kind in "iu" and f.shape[0] > 0,
          f"{owner}: faces have shape {f.shape} (dtype {f.dtype}); give (F, 3) vertex indices, one row per triangle")
    check(bool(np.all((f >= 0) & (f < v.shape[0]))),
          f"{owner}: faces index vertices outside 0..{v.shape[0] - 1}; the faces must index the vertex array")
    return v.astype(float), f.astype(np.int64)


def _transform(owner: str, x: np.ndarray, scale, rotate, translate) -> np.ndarray:
    """x -> rotate @ (scale * x) + translate, row by row."""
    dim = x.shape[1]
    context = f"the {owner} is {dim}D"
    s = np.array(finite_vector(owner, "scale", scale, dim, valid=POSITIVE, context=context,
                               fix="one factor or one per axis (a mesh in mm on a grid in m: scale=1e-3)"))
    x = x * s
    if rotate is not None:
        r = np.asarray(rotate) if ndim(rotate) == 2 else None
        check(r is not None and r.shape == (dim, dim) and r.dtype.kind in "iuf",
              f"{owner}: rotate = {show(rotate)} must be a {dim}x{dim} rotation matrix")
        FINITE.check(owner, "rotate", r)
        r = r.astype(float)
        check(np.allclose(r @ r.T, np.eye(dim), rtol=0.0, atol=1e-9),
              f"{owner}: rotate = {show(r)} is not a rotation (R R^T != I); give an orthogonal matrix "
              "(stretch with scale=)")
        x = x @ r.T
    return x + np.array(finite_vector(owner, "translate", translate, dim, context=context))


def _check_on_grid(owner: str, region: Region, grid: Grid, dim: int, other: str) -> None:
    check(grid.dim == dim, f"fill: the {owner} is {dim}D but the grid is {grid.dim}D; {other}")
    lo, hi = (np.asarray(b, dtype=float) for b in region.bounds())
    glo, ghi = np.asarray(grid.lower, dtype=float), np.asarray(grid.upper, dtype=float)
    tol = 1e-9 * np.maximum(ghi - glo, 1e-300)
    check(bool(np.all(lo >= glo - tol) and np.all(hi <= ghi + tol)),
          f"fill: the {owner} spans {show(tuple(lo.tolist()))} to {show(tuple(hi.tolist()))} but the grid covers "
          f"{show(grid.lower)} to {show(grid.upper)}, so part of the body would be cut off; move or scale it "
          f"(jm.{owner}(..., translate=..., scale=...): a mesh in millimetres on a grid in metres needs scale=1e-3) "
          "or build the grid around it: jm.Grid.covering(*region.bounds(), spacing, shape=shape)")


# --------------------------------------------------------------------------- the inside test
def _unique_rows(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The distinct rows of a (N, k), sorted by column 0, then 1, ..., and each row's index among
    them (``np.unique(a, axis=0, return_inverse=True)``, which sorts rows as bytes, ten times slower)."""
    order = np.lexsort(a.T[::-1])
    b = a[order]
    new = np.ones(a.shape[0], dtype=bool)
    new[1:] = np.any(b[1:] != b[:-1], axis=1)
    inverse = np.empty(a.shape[0], dtype=np.int64)
    inverse[order] = np.cumsum(new) - 1
    return b[new], inverse


def _pairs(lo: np.ndarray, hi: np.ndarray, limit: int = _CHUNK):
    """Yield (owner, index) arrays: every index in [lo[i], hi[i]) of every owner i, in chunks of
    about ``limit`` pairs (an owner is never split)."""
    counts = np.maximum(hi - lo, 0)
    ends = np.cumsum(counts)
    start, n = 0, counts.size
    while start < n:
        base = ends[start] - counts[start]
        stop = max(start + 1, int(np.searchsorted(ends, base + limit, side="right")))
        c = counts[start:stop]
        if c.sum():
            owner = np.repeat(np.arange(start, stop), c)
            offset = np.arange(owner.size) - np.repeat(np.cumsum(c) - c, c)
            yield owner, lo[owner] + offset
        start = stop


def _parity(col_p: np.ndarray, x_p: np.ndarray, col_c: np.ndarray, x_c: np.ndarray) -> np.ndarray:
    """For each point (its column, its coordinate along the ray's axis): whether an odd number of
    the crossings in its column lie at or below it (x_c <= x_p: a point on a face x = const is
    inside at the body's low-x side and outside at its high-x side, as for :class:`Box`)."""
    n_c = x_c.size
    col = np.concatenate([col_c, col_p])
    xs = np.concatenate([x_c, x_p])
    kind = np.concatenate([np.zeros(n_c, np.int8), np.ones(col_p.size, np.int8)])  # a tie: the crossing first
    order = np.lexsort((kind, xs, col))
    crossing = kind[order] == 0
    below = np.cumsum(crossing) - crossing  # crossings before each entry in the sorted order
    sorted_col = col[order]
    first = np.searchsorted(sorted_col, sorted_col, side="left")  # the first entry of each one's column
    count = below - below[first]
    inside = np.empty(col_p.size, dtype=bool)
    point = ~crossing
    inside[order[point] - n_c] = count[point] % 2 == 1
    return inside


def _crossings_2d(seg: np.ndarray, ys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(column, x) where the lines y = ys[column] (sorted, unique) cross the segments seg (S, 2, 2).
    A segment holds its lower end and not its upper one (min(a_y, b_y) <= y < max(a_y, b_y)), so a
    line through a vertex crosses exactly one of the two segments that meet there, or neither."""
    a, b = seg[:, 0], seg[:, 1]
    lo = np.searchsorted(ys, np.minimum(a[:, 1], b[:, 1]), side="left")
    hi = np.searchsorted(ys, np.maximum(a[:, 1], b[:, 1]), side="left")
    cols, xs = [], []
    for s, c in _pairs(lo, hi):
        ax, ay, bx, by = a[s, 0], a[s, 1], b[s, 0], b[s, 1]
        xs.append(ax + (ys[c] - ay) * ((bx - ax) / (by - ay)))
        cols.append(c)
    if not cols:
        return np.zeros(0, np.int64), np.zeros(0)
    return np.concatenate(cols), np.concatenate(xs)


def _side(u: np.ndarray, w: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Twice the signed area of (u, w, p) in the y-z plane (positive: p left of u -> w)."""
    return (w[:, 0] - u[:, 0]) * (p[:, 1] - u[:, 1]) - (w[:, 1] - u[:, 1]) * (p[:, 0] - u[:, 0])


def _crossings_3d(tri: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(column, x) where the lines {(t, y, z)}, (y, z) = cols[column] (sorted by y then z, unique),
    cross the triangles tri (T, 3, 3)."""
    proj = tri[:, :, 1:]
    # edge-on triangles (parallel to x to rounding) are crossed by no line: their neighbours decide
    e1, e2 = proj[:, 1] - proj[:, 0], proj[:, 2] - proj[:, 0]
    area2 = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    keep = np.abs(area2) > 1e-12 * np.linalg.norm(tri[:, 1] - tri[:, 0], axis=1) * np.linalg.norm(
        tri[:, 2] - tri[:, 0], axis=1)
    tri, proj = tri[keep], proj[keep]
    if not tri.shape[0]:
        return np.zeros(0, np.int64), np.zeros(0)
    # a bounding-box prefilter, padded so that rounding never hides a triangle from a line it touches
    pad = 1e-9 * max(float(np.abs(proj).max()), float(np.abs(cols).max()), 1e-300)
    blo, bhi = proj.min(axis=1) - pad, proj.max(axis=1) + pad
    ys, line_start = np.unique(cols[:, 0], return_index=True)  # the lines y = const of the columns
    zmin = float(cols[:, 1].min())
    zspan = float(np.ptp(cols[:, 1])) or 1.0
    # a column's key: its line + its z scaled into [0, 0.5], so each line's columns are one sorted run
    line_of = np.repeat(np.arange(ys.size), np.diff(np.append(line_start, cols.shape[0])))
    key = line_of + 0.5 * (cols[:, 1] - zmin) / zspan
    slack = 4 * np.finfo(float).eps * ys.size
    l_lo = np.searchsorted(ys, blo[:, 0], side="left")
    l_hi = np.searchsorted(ys, bhi[:, 0], side="right")
    out_c, out_x = [], []
    for t_of, line in _pairs(l_lo, l_hi):  # (triangle, line) pairs
        q_lo = line + 0.5 * np.clip((blo[t_of, 1] - zmin) / zspan, -0.2, 1.2) - slack
        q_hi = line + 0.5 * np.clip((bhi[t_of, 1] - zmin) / zspan, -0.2, 1.2) + slack
        c_lo = np.searchsorted(key, q_lo, side="left")
        c_hi = np.searchsorted(key, q_hi, side="right")
        for k, c in _pairs(c_lo, c_hi):  # (triangle, column) pairs
            t = t_of[k]
            p = cols[c]
            sides, signs = [], []
            for i in range(3):
                a, b = proj[t, i], proj[t, (i + 1) % 3]
                # each edge is tested from its lexicographically smaller end, whichever triangle asks
                flip = (a[:, 0] > b[:, 0]) | ((a[:, 0] == b[:, 0]) & (a[:, 1] > b[:, 1]))
                u = np.where(flip[:, None], b, a)
                w = np.where(flip[:, None], a, b)
                e = _side(u, w, p)
                orient = np.where(flip, -1.0, 1.0)
                sides.append(orient * e)
                # on the edge's line: as if p moved by (eta, eps), 0 < eta << eps, which lies left of
                # u -> w when w is above u in y and right of it when level (then w is above in z)
                tie = np.where(w[:, 0] > u[:, 0], orient, -orient)
                signs.append(np.where(e != 0, np.sign(orient * e), tie))
            hit = (signs[0] == signs[1]) & (signs[1] == signs[2])
            if not hit.any():
                continue
            t, c = t[hit], c[hit]
            w0, w1, w2 = sides[1][hit], sides[2][hit], sides[0][hit]  # barycentric weights of vertices 0, 1, 2
            total = w0 + w1 + w2
            ok = total != 0
            total = np.where(ok, total, 1.0)
            x0 = tri[t, 0, 0]  # from vertex 0: a face x = const (a box's) gives x exactly
            xs = (x0 + (w1 * (tri[t, 1, 0] - x0) + w2 * (tri[t, 2, 0] - x0)) / total)[ok]
            out_c.append(c[ok])
            out_x.append(xs)
    if not out_c:
        return np.zeros(0, np.int64), np.zeros(0)
    return np.concatenate(out_c), np.concatenate(out_x)


def _inside(x: np.ndarray, crossings: Callable, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Parity of the crossings below each point x (N, D) along axis 0; points outside the box
    [lo, hi] are outside."""
    out = np.zeros(x.shape[0], dtype=bool)
    near = np.flatnonzero(np.all((x >= lo) & (x <= hi), axis=1))
    if not near.size:
        return out
    xn = x[near]
    if x.shape[1] == 2:
        cols, col_of = np.unique(xn[:, 1], return_inverse=True)
    else:
        cols, col_of = _unique_rows(xn[:, 1:])
    col_c, x_c = crossings(cols)
    out[near] = _parity(col_of.reshape(-1), xn[:, 0], col_c, x_c)
    return out


# --------------------------------------------------------------------------- regions
class Mesh(Region):
    """The inside of a closed triangle surface, for 3D grids: ``jm.fill(grid, jm.Mesh("part.stl"), ppc=2)``.

    The surface must be closed (watertight: every edge shared by an even number of triangles);
    its orientation does not matter (inside: an odd number of crossings).  The vertices are
    placed at ``rotate @ (scale * x) + translate``.  ``volume``: the enclosed volume (for a
    consistently oriented surface).

    Args:
        source: an STL, OBJ or PLY file (read by trimesh, duplicate vertices merged), a
            ``trimesh.Trimesh`` (or any object with ``vertices`` and ``faces``) or ``(vertices
            (V, 3), faces (F, 3))``.
        scale: a positive factor, or one per axis (default 1.0; a mesh in mm on a grid in m:
            ``scale=1e-3``).
        rotate: a 3x3 rotation matrix (orthogonal: stretch with ``scale``), or None (the default).
        translate: the shift after scaling and rotating, a 3-vector or one number (default 0.0).
    """

    vertices: np.ndarray
    faces: np.ndarray
    name: str = eqx.field(static=True)

    def __init__(self, source, *, scale=1.0, rotate=None, translate=0.0):
        owner = "Mesh"
        v, f, self.name = _vertices_faces(owner, source)
        if v.ndim == 2 and v.shape[1] == 2:
            fail(owner, f"{self.name} has 2D vertices; a plane region is a jm.Polygon", "use jm.Polygon(...)")
        v, f = _checked_arrays(owner, v, f, 3)
        v = _transform(owner, v, scale, rotate, translate)
        v, inverse = _unique_rows(v)  # merge equal vertices: the edges then match
        f = inverse[f]
        f = f[(f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 2] != f[:, 0])]  # a collapsed triangle: no area
        check(f.shape[0] > 0, f"{owner}: {self.name}: every triangle is degenerate (repeated vertices); no surface")
        edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
        _, count = np.unique(edges[:, 0] * v.shape[0] + edges[:, 1], return_counts=True)
        odd = int(np.sum(count % 2))
        check(odd == 0, f"{owner}: {self.name} is not closed (watertight): {odd} of its {count.size} edges belong to "
                        f"an odd number of triangles (holes, gaps or a cut surface), so it has no inside; {_REPAIR}")
        self.vertices, self.faces = v, f

    @property
    def volume(self) -> float:
        t = self.vertices[self.faces]
        return abs(float(np.sum(t[:, 0] * np.cross(t[:, 1], t[:, 2])))) / 6.0

    def bounds(self):
        return tuple(self.vertices.min(axis=0).tolist()), tuple(self.vertices.max(axis=0).tolist())

    def check_grid(self, grid):
        _check_on_grid("Mesh", self, grid, 3, "a plane problem takes a jm.Polygon (vertex loops or a flat mesh file)")

    def contains(self, x):
        x = np.asarray(x, dtype=float)
        check(x.ndim == 2 and x.shape[1] == 3, f"Mesh.contains: points have shape {x.shape}; give (N, 3)")
        tri = self.vertices[self.faces]
        lo, hi = (np.array(b) for b in self.bounds())
        return _inside(x, lambda cols: _crossings_3d(tri, cols), lo, hi)


class Polygon(Region):
    """The inside of closed polygons, for 2D grids (plane and axisymmetric r-z problems).

    Args:
        source: the vertices of one loop, (N, 2) in order (closed: the last joins the first), a
            list of loops (inside: an odd number of crossings, so a loop inside another is a
            hole), or a flat triangle mesh (an STL, OBJ or PLY file or a ``trimesh.Trimesh`` with
            every z equal), whose boundary edges bound the region.
        scale: a positive factor, or one per axis (default 1.0).
        rotate: a 2x2 rotation matrix, or None (the default).
        translate: the shift after scaling and rotating, a 2-vector or one number (default 0.0).
    """

    segments: np.ndarray
    name: str = eqx.field(static=True)

    def __init__(self, source, *, scale=1.0, rotate=None, translate=0.0):
        owner = "Polygon"
        if isinstance(source, (str, os.PathLike)) or (hasattr(source, "vertices") and hasattr(source, "faces")):
            seg = self._mesh_boundary(owner, source)
        else:
            seg = self._loops(owner, source)
        flat = _transform(owner, seg.reshape(-1, 2), scale, rotate, translate)
        self.segments = flat.reshape(-1, 2, 2)

    def _mesh_boundary(self, owner, source) -> np.ndarray:
        v, f, self.name = _vertices_faces(owner, source)
        v, f = _checked_arrays(owner, v, f, v.shape[1] if v.ndim == 2 and v.shape[1] in (2, 3) else 3)
        if v.shape[1] == 3:
            z = v[:, 2]
            check(np.ptp(z) <= 1e-9 * max(float(np.ptp(v[:, :2])), 1e-300),
                  f"{owner}: {self.name} is not flat (z spans {z.min():.6g} to {z.max():.6g}); a plane region is "
                  "a flat triangle mesh in z = const, a closed 3D surface is a jm.Mesh on a 3D grid")
            v = v[:, :2]
        v, inverse = _unique_rows(v)
        f = inverse[f]
        edges = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
        edges = edges[edges[:, 0] != edges[:, 1]]
        unique, count = np.unique(np.sort(edges, axis=1), axis=0, return_counts=True)
        boundary = unique[count % 2 == 1]  # edges of one triangle (of an odd number): the outline
        check(boundary.shape[0] >= 3, f"{owner}: {self.name} has no boundary (no triangle with area)")
        return v[boundary]

    def _loops(self, owner, source) -> np.ndarray:
        self.name = "polygon"
        arr = None
        try:
            arr = np.asarray(source)
        except ValueError:  # ragged: several loops of different lengths
            pass
        if arr is not None and arr.dtype.kind in "iuf" and arr.ndim == 2:
            loops = [arr]
        elif arr is not None and arr.dtype.kind in "iuf" and arr.ndim == 3:
            loops = list(arr)
        elif isinstance(source, (list, tuple)) and source:
            loops = [np.asarray(loop) for loop in source]
        else:
            fail(owner, f"source = {show(source)} is neither vertices nor a mesh",
                 "give the vertices of a loop (N, 2), a list of loops, or a flat mesh file (.stl, .obj, .ply)")
        segs = []
        for i, loop in enumerate(loops):
            label = "vertices" if len(loops) == 1 else f"loop {i}"
            check(loop.ndim == 2 and loop.shape[1] == 2 and loop.dtype.kind in "iuf",
                  f"{owner}: {label} have shape {loop.shape}; give (N, 2) x-y vertices in order "
                  "(a 3D body is a jm.Mesh)")
            FINITE.check(owner, label, loop)
            loop = loop.astype(float)
            if loop.shape[0] > 1 and np.array_equal(loop[0], loop[-1]):
                loop = loop[:-1]  # closed by repeating the first vertex: the closing edge is implied anyway
            check(loop.shape[0] >= 3 and np.ptp(loop[:, 0]) > 0 and np.ptp(loop[:, 1]) > 0,
                  f"{owner}: {label} has {loop.shape[0]} vertices enclosing no area; a loop needs at least 3 "
                  "vertices not on one line")
            segs.append(np.stack([loop, np.roll(loop, -1, axis=0)], axis=1))
        return np.concatenate(segs)

    def bounds(self):
        pts = self.segments.reshape(-1, 2)
        return tuple(pts.min(axis=0).tolist()), tuple(pts.max(axis=0).tolist())

    def check_grid(self, grid):
        _check_on_grid("Polygon", self, grid, 2, "a 3D body takes a jm.Mesh (a closed STL, OBJ or PLY surface)")

    def contains(self, x):
        x = np.asarray(x, dtype=float)
        check(x.ndim == 2 and x.shape[1] == 2, f"Polygon.contains: points have shape {x.shape}; give (N, 2)")
        lo, hi = (np.array(b) for b in self.bounds())
        return _inside(x, lambda ys: _crossings_2d(self.segments, ys), lo, hi)


# --------------------------------------------------------------------------- point clouds
def _read_points(path) -> dict:
    """The columns of a CSV (or whitespace-separated) file with a header: x, y[, z], volume, and
    optionally vx, vy[, vz] and mass."""
    owner = "point_cloud"
    path = Path(path)
    if not path.is_file():
        fail(owner, f"points = {show(str(path))}: no such file",
             f"check the path (a relative one is taken from the working directory, {os.getcwd()})")
    delimiter = "," if path.suffix.lower() == ".csv" else None
    try:
        table = np.genfromtxt(path, delimiter=delimiter, names=True, dtype=float, case_sensitive="lower",
                              deletechars="", ndmin=1)
    except Exception as e:
        fail(owner, f"points = {show(str(path))}: cannot read it as a table ({type(e).__name__}: {e})",
             "give a CSV with a header line, e.g. x,y,z,volume (optional: vx,vy,vz,mass)")
    names = table.dtype.names or ()
    check("x" in names, f"{owner}: {path.name} has columns {list(names)}; the header must name x, y[, z] and volume "
                        "(optional: vx, vy[, vz], mass)")
    axes = [a for a in ("x", "y", "z") if a in names]
    check(axes == ["x", "y", "z"][: len(axes)],
          f"{owner}: {path.name} has coordinate columns {axes}; give x, x y, or x y z")
    out = {"x": np.stack([table[a] for a in axes], axis=1)}
    for name in ("volume", "mass"):
        if name in names:
            out[name] = np.asarray(table[name])
    vel = [f"v{a}" for a in axes]
    if any(v in names for v in vel):
        check(all(v in names for v in vel), f"{owner}: {path.name} gives some of {vel} but not all; give every one")
        out["velocity"] = np.stack([table[v] for v in vel], axis=1)
    return out


def point_cloud(points, volume=None, *, velocity=0.0, density: float | None = None, mass=None,
                grid: Grid | None = None, ppc: int = 1) -> Particles:
    """Particles at given points with given volumes (a scanned or meshed body, another code's particles).

    The same as ``jm.Particles(x=..., v=..., volume=..., mass=..., ppc=...)``, checked.  Without
    ``density`` and ``mass`` the material's density sets the masses.

    Args:
        points: (N, D) positions (D = 1, 2 or 3), or a CSV file (whitespace-separated for other
            suffixes) whose header names the columns x, y[, z] and volume, optionally vx, vy[, vz]
            and mass.
        volume: the particle volumes, positive: one number or (N,); required unless the file has
            the column.
        velocity: one number, one per axis, (N, D) or a function f(x) -> (N, D); default 0.0.
        density: mass = density * volume (one number or (N,), positive); not with ``mass``.
        mass: the particle masses, one number or (N,), positive; not with ``density``.
        grid: a :class:`jaxmpm.Grid` the points must lie on; its axisymmetric flag is taken
            (then volume and mass are per radian, V = A r, and the points must lie at r > 0).
            None (the default): no check, plane geometry.
        ppc: particles per cell per axis (default 1); only UGIMP reads it, its particle size is
            h / (2 ppc).
    """
    owner = "point_cloud"
    if isinstance(points, (str, os.PathLike)):
        table = _read_points(points)
        points = table["x"]
        for name, given in (("volume", volume), ("mass", mass)):
            if name in table:
                check(given is None, f"{owner}: {name} is both a column of the file and an argument; give one")
        volume = table.get("volume", volume)
        mass = table.get("mass", mass)
        if "velocity" in table:
            velocity = table["velocity"]
    x = np.asarray(points) if ndim(points) == 2 else None
    check(x is not None and x.dtype.kind in "iuf" and 1 <= x.shape[1] <= 3 and x.shape[0] > 0,
          f"{owner}: points = {show(points)} must be (N, D) positions, D = 1, 2 or 3, N > 0")
    FINITE.check(owner, "points", x)
    x = x.astype(float)
    n, dim = x.shape
    check(volume is not None, f"{owner}: volume is missing; give one number or one per point ({n})")
    POSITIVE.check(owner, "volume", volume, fix="each particle's volume (per radian on an axisymmetric grid)")
    vol = np.asarray(volume, dtype=float)
    check(vol.shape in ((), (n,)), f"{owner}: volume has shape {vol.shape}; give one number or one per point ({n})")
    vol = np.broadcast_to(vol, (n,)).copy()
    ppc = positive_int(owner, "ppc", ppc, fix="particles per cell per axis (UGIMP's particle size)")
    check(density is None or mass is None, f"{owner}: give density or mass, not both")
    if density is not None:
        POSITIVE.check(owner, "density", density)
        m = np.asarray(density, dtype=float) * vol
        check(m.shape == (n,), f"{owner}: density has shape {np.shape(density)}; give one number or one per point")
    elif mass is not None:
        POSITIVE.check(owner, "mass", mass)
        m = np.broadcast_to(np.asarray(mass, dtype=float), (n,)).copy() if np.ndim(mass) == 0 else np.asarray(mass)
        check(m.shape == (n,), f"{owner}: mass has shape {m.shape}; give one number or one per point ({n})")
    else:
        m = None
    if callable(velocity):
        v = np.asarray(velocity(x), dtype=float)
    else:
        if ndim(velocity) <= 1:
            finite_vector(owner, "velocity", velocity, dim, context=f"the points are {dim}D")
        v = np.asarray(velocity, dtype=float)
    check(v.shape in ((), (dim,), (n, dim)),
          f"{owner}: velocity has shape {v.shape}; give one number, {dim} (one per axis) or ({n}, {dim})")
    FINITE.check(owner, "velocity", v)
    v = np.broadcast_to(v, (n, dim))
    axisymmetric = False
    if grid is not None:
        check(isinstance(grid, Grid), f"{owner}: grid must be a jm.Grid, got {type(grid).__name__}")
        check(grid.dim == dim, f"{owner}: the points are {dim}D but the grid is {grid.dim}D")
        out = ~np.all((x >= np.asarray(grid.lower)) & (x <= np.asarray(grid.upper)), axis=1)
        check(not out.any(), f"{owner}: {int(out.sum())} of {n} points lie off the grid (first: {x[np.argmax(out)]}"
                             f"; the grid covers {grid.lower} to {grid.upper}); move them or enlarge the grid")
        axisymmetric = grid.axisymmetric
        check(not axisymmetric or bool(np.all(x[:, 0] > 0)),
              f"{owner}: an axisymmetric grid needs the points at r > 0 (axis x is the radius)")
    return Particles(x=jnp.asarray(x), v=jnp.asarray(np.array(v)), volume=jnp.asarray(vol),
                     mass=None if m is None else jnp.asarray(m), ppc=ppc, axisymmetric=axisymmetric)
