"""The XDMF sidecar of a run's HDF5 file, for ParaView and VTK readers.

Two files beside ``FILE.h5``: ``FILE.xdmf`` (the XML: a temporal collection of one grid per frame)
and ``FILE.xdmf.h5`` (per-frame HDF5 virtual datasets into ``FILE.h5``, no data of their own), so
that every frame is a plain (N, ...) array for readers that cannot slice.  :func:`write_xdmf` is
called by :class:`jaxmpm.H5Writer` after each chunk.
"""

from __future__ import annotations

import json
import os
import shutil

import h5py
import numpy as np


def same_file(a: str, b: str) -> bool:
    """Whether two paths name one file (False where either is missing)."""
    try:
        return os.path.samefile(a, b)
    except OSError:
        return False


def remove(*paths) -> None:
    """Remove the files that exist among ``paths``."""
    for p in paths:
        try:
            os.unlink(p)
        except FileNotFoundError:
            pass


def copy_into_place(source: str, target: str) -> None:
    """``target`` replaced in one step by a copy of ``source`` (a new file: a reader of the old one
    keeps it)."""
    shutil.copyfile(source, target + ".tmp")
    os.replace(target + ".tmp", target)


def link_into_place(source: str, target: str, links: bool = True) -> bool:
    """Make ``target`` name the file ``source`` names, in one step: a hard link renamed over it
    (POSIX ``rename`` is atomic), or, where hard links fail (or ``links`` is False), a copy renamed
    over it.  Returns whether a hard link did it."""
    if links:
        link = target + ".tmp"
        remove(link)
        try:
            os.link(source, link)
        except OSError:
            pass
        else:
            os.replace(link, target)
            remove(link)  # left when the two names were already one file (rename does nothing then)
            return True
    copy_into_place(source, target)
    return False


def views_copies(views_path: str) -> tuple[str, str]:
    """The two copies of the views file ``FILE.xdmf.h5`` that :func:`write_xdmf` keeps while a writer
    runs (one of them is the views file itself)."""
    return views_path + ".0.tmp", views_path + ".1.tmp"


def _xdmf_type(dtype) -> str:
    """XDMF NumberType and Precision of a NumPy dtype."""
    dtype = np.dtype(dtype)
    kind = {"f": "Float", "i": "Int", "u": "UInt"}.get(dtype.kind, "Float")
    return f'NumberType="{kind}" Precision="{dtype.itemsize}"'


def _xdmf_item(file_name: str, path: str, shape, dtype) -> str:
    """An XDMF DataItem that is one whole HDF5 dataset (what every XDMF reader, meshio included, reads)."""
    dims = " ".join(str(int(v)) for v in shape)
    return f'<DataItem Dimensions="{dims}" {_xdmf_type(dtype)} Format="HDF">{file_name}:/{path.lstrip("/")}</DataItem>'


def xdmf_paths(h5_path) -> tuple[str, str]:
    """The two sidecar files of ``h5_path``: ``FILE.xdmf`` and ``FILE.xdmf.h5`` (its per-frame views)."""
    stem = os.path.splitext(os.fspath(h5_path))[0]
    return stem + ".xdmf", stem + ".xdmf.h5"


def _frame_series(f: h5py.File, T: int, N: int) -> list[str]:
    """The per-frame per-particle datasets of ``f`` shown as point data: particles/x, particles/v and
    every saved field (T, N, ...)."""
    names = ["x", "v"] + sorted(n for n in f["particles"] if n not in ("x", "v", "mass", "volume0"))
    out = []
    for name in names:
        ds = f["particles"].get(name)
        if isinstance(ds, h5py.Dataset) and ds.ndim >= 2 and ds.shape[:2] == (T, N):
            out.append(name)
    return out


def stored_fields(attrs) -> tuple:
    """The per-frame fields a run chose (``jm.H5Writer(..., fields=...)``): the root attribute
    ``fields`` of its file, comma-separated, as a tuple."""
    value = attrs.get("fields", "")
    value = value.decode() if isinstance(value, bytes) else str(value)
    return tuple(name for name in value.split(",") if name)


def _tensors(f: h5py.File, series: list[str]) -> set:
    """The chosen fields (``stored_fields``) that are a d x d matrix per particle, d <= 3 (stress,
    F): shown as 3 x 3 XDMF Tensors, zero-padded in 1D and 2D."""
    chosen = set(stored_fields(f.attrs))
    return {name for name in series if name in chosen and len(f["particles"][name].shape) == 4
            and f["particles"][name].shape[2] == f["particles"][name].shape[3] <= 3}


def _view_shape(N: int, per: tuple, tensor: bool = False) -> tuple:
    """A frame's view of a (T, N, *per) dataset: (N,), (N, C), (N, prod(per)) for a matrix, or
    (N, 9) for a ``tensor`` (3 x 3, row-major)."""
    if tensor:
        return (N, 9)
    return (N,) + per if len(per) <= 1 else (N, int(np.prod(per)))


def _replace_view(g: h5py.File, path: str, layout) -> None:
    if path in g:  # left by an update that was interrupted before it recorded its frames
        del g[path]
    g.create_virtual_dataset(path, layout, fillvalue=0)


def _views_held(path: str, signature: str):
    """The frames the views file ``path`` holds, or None (missing, unreadable, or of another file)."""
    try:
        with h5py.File(path, "r") as g:
            return int(g.attrs["frames"]) if g.attrs.get("signature") == signature else None
    except (OSError, KeyError):
        return None


def _write_frame_views(views_path: str, h5_name: str, f: h5py.File, series: list[str], T: int, N: int, D: int):
    """Create (or extend) the views file: ``/index`` (N, 1) int64, the Polyvertex connectivity
    0..N-1, and for each frame t ``/particles/<name>/<t>`` (t as six digits), an HDF5 virtual
    dataset that is frame t of ``h5_name:/particles/<name>`` (no data is copied; a matrix per
    particle is flattened to a row; a chosen d x d field such as the stress, :func:`_tensors`, is
    the row of its 3 x 3 padding, the components beyond d zero); in 1D also ``/points/<t>``
    (N, 2), the position with a zero second coordinate.  A views file whose particle count,
    dtypes or fields differ from ``f`` is rebuilt; otherwise only the frames it lacks are added.

    Like ``FILE.h5`` (:class:`jaxmpm.H5Writer`), the views file is never written in place: of its
    two copies (:func:`views_copies`), one is the views file itself (a second hard link) and the
    other, which lags one update behind, receives the frames it lacks and is then renamed over it,
    so that a kill leaves the old views or the new, never half of them."""
    tensors = _tensors(f, series)
    signature = json.dumps({"views layout": 2, "source": h5_name, "N": N, "D": D,
                            "series": [[n, list(f["particles"][n].shape[2:]), f["particles"][n].dtype.str]
                                       for n in series], "tensors": sorted(tensors)})
    live = _views_held(views_path, signature)
    if live is not None and live >= T:
        return
    first, second = views_copies(views_path)
    target = second if same_file(first, views_path) else first
    held = _views_held(target, signature)
    # the copy lags the views file (by the last update): copying the views file over it costs
    # about as much as making 1/200 of its views again, so it is copied unless it lags by less
    if live is not None and (held is None or 200 * (live - held) > live):
        copy_into_place(views_path, target)
        held = live
    try:
        g = h5py.File(target, "a" if held is not None else "w")
    except OSError:  # held open by a reader since it was the views file: a new copy
        remove(target)
        if live is not None:
            copy_into_place(views_path, target)
        g = h5py.File(target, "a" if live is not None else "w")
    with g:
        if g.attrs.get("signature") != signature:
            for key in list(g.keys()):
                del g[key]
            for key in list(g.attrs.keys()):
                del g.attrs[key]
            g.create_dataset("index", data=np.arange(N, dtype=np.int64).reshape(N, 1))
            g.attrs["signature"] = signature
            g.attrs["frames"] = 0
            g.attrs["about"] = (f"per-frame views (HDF5 virtual datasets) of {h5_name} for its XDMF sidecar; "
                                "written by jaxmpm, no data of its own")
        done = int(g.attrs["frames"])
        meta = [(name, f["particles"][name].shape[2:], f["particles"][name].dtype) for name in series]
        for t in range(done, T):
            for name, per, dtype in meta:
                source = h5py.VirtualSource(h5_name, f"particles/{name}", shape=(t + 1, N) + per, dtype=dtype)
                layout = h5py.VirtualLayout(shape=_view_shape(N, per, name in tensors), dtype=dtype)
                if name in tensors and per[0] < 3:  # component (i, j) of the 3 x 3 row; the rest is the fill, 0
                    for i in range(per[0]):
                        for j in range(per[1]):
                            layout[:, 3 * i + j] = source[t, :, i, j]
                else:
                    layout[...] = source[t]  # row-major: a matrix per particle becomes one row
                _replace_view(g, f"particles/{name}/{t:06d}", layout)
                if name == "x" and D == 1:  # meshio reads only XY / XYZ geometry
                    layout = h5py.VirtualLayout(shape=(N, 2), dtype=dtype)
                    layout[:, 0] = source[t, :, 0]
                    _replace_view(g, f"points/{t:06d}", layout)
        g.attrs["frames"] = max(done, T)
    link_into_place(target, views_path)


def write_xdmf(h5_path: str, f: h5py.File) -> None:
    """The XDMF 3 sidecar ``FILE.xdmf`` of ``FILE.h5``: a temporal collection, one Polyvertex grid
    per frame, read by ParaView/VTK (checked with VTK's ``vtkXdmfReader``) and by meshio
    (``meshio.xdmf.TimeSeriesReader``).

    Every DataItem is a whole HDF5 dataset (meshio reads no hyperslabs): the per-frame slices of
    ``/particles/x``, ``/particles/v`` and the saved fields are HDF5 virtual datasets in
    ``FILE.xdmf.h5`` (see :func:`_write_frame_views`), which map into ``FILE.h5`` and copy nothing.
    Point data per frame: ``position`` (meshio takes the points of the first frame only),
    ``velocity``, ``mass``, ``volume0`` and every saved per-particle field: a scalar per particle
    is a Scalar, a 2- or 3-vector a Vector, the chosen d x d fields (stress, F) a 3 x 3 Tensor (9
    components, row-major; in 1D and 2D the components beyond d are 0, not the out-of-plane
    stress), any other matrix a Matrix (its row-major row).  1D positions are written as XY points
    with y = 0."""
    if "particles/x" not in f:
        return
    T, N, D = f["particles/x"].shape
    xdmf_path, views_path = xdmf_paths(h5_path)
    h5_name = os.path.basename(os.fspath(h5_path))
    views_name = os.path.basename(views_path)
    series = _frame_series(f, T, N)
    try:
        _write_frame_views(views_path, h5_name, f, series, T, N, D)
    except OSError as error:  # e.g. the views file held open by a viewer: keep the last consistent pair
        from ..core.warn import warn

        warn(f"XDMF sidecar not updated ({views_path}: {error}); {os.fspath(h5_path)} itself is complete", UserWarning)
        return
    times = f["time"][()]
    dtype = f["particles/x"].dtype

    def attribute(name, kind, item):
        return f'<Attribute Name="{name}" AttributeType="{kind}" Center="Node">{item}</Attribute>'

    def kind_of(per):
        return ("Scalar" if per in ((), (1,)) else "Vector" if per in ((2,), (3,)) else
                "Tensor" if per == (3, 3) else "Matrix")

    labels = {"x": "position", "v": "velocity"}
    tensors = _tensors(f, series)
    frame_items = []  # per series: (label, kind, DataItem with @T@ for the frame's group)
    for name in series:
        ds = f["particles"][name]
        item = _xdmf_item(views_name, f"particles/{name}/@T@", _view_shape(N, ds.shape[2:], name in tensors), ds.dtype)
        frame_items.append((labels.get(name, name), "Tensor" if name in tensors else kind_of(ds.shape[2:]), item))

    constants = [(name, _xdmf_item(h5_name, f"particles/{name}", (N,), f["particles"][name].dtype))
                 for name in ("mass", "volume0", "material")
                 if isinstance(f["particles"].get(name), h5py.Dataset) and f["particles"][name].shape == (N,)]
    topology = (f'<Topology TopologyType="Polyvertex" NumberOfElements="{N}" NodesPerElement="1">'
                + _xdmf_item(views_name, "index", (N, 1), np.int64) + "</Topology>")
    lines = ['<?xml version="1.0" ?>', '<Xdmf Version="3.0">', "<Domain>",
             '<Grid Name="particles" GridType="Collection" CollectionType="Temporal">']
    for t in range(T):
        lines.append(f'<Grid Name="frame{t}" GridType="Uniform"><Time Value="{float(times[t])!r}"/>')
        lines.append(topology)
        frame = f"{t:06d}"
        points = _xdmf_item(views_name, f"points/{frame}", (N, 2), dtype) if D == 1 else frame_items[0][2]
        lines.append(f'<Geometry GeometryType="{"XYZ" if D == 3 else "XY"}">{points.replace("@T@", frame)}</Geometry>')
        for label, kind, item in frame_items:  # position, velocity, then the terms' saved fields (temperature, ...)
            lines.append(attribute(label, kind, item.replace("@T@", frame)))
        for name, item in constants:
            lines.append(attribute(name, "Scalar", item))
        lines.append("</Grid>")
    lines += ["</Grid>", "</Domain>", "</Xdmf>"]
    partial = xdmf_path + ".partial"  # replaced in one step: a reader never sees half a file
    with open(partial, "w") as out:
        out.write("\n".join(lines))
    os.replace(partial, xdmf_path)
