"""HDF5 output in the layout of docs/design.md, written chunk by chunk, with an XDMF sidecar.

```
/time (T,)   /particles/x (T,N,D)  /particles/v (T,N,D)  /particles/mass (N,)  /particles/volume0 (N,)
/energy/kinetic (T,)  /energy/strain (T,)  /energy/dissipated (T,)
/momentum/linear (T,D)  /momentum/angular (T,1 or 3)
/particles/<name> (T,N,...)   every saved per-particle field a physics term declares
attributes on /: scene, scheme, order, beta, alpha_g, alpha_p, shape, update, dt, cells, ppc,
                 dtype, jaxmpm version, scene parameters (JSON), and every other float
                 parameter the model's registered parts declare (E, nu, density, ...)
```
A new field or parameter needs no edit here: the writer follows ``History.fields`` and the
registry.
"""

from __future__ import annotations

import json
import os

import h5py
import numpy as np

_SERIES = {
    "time": "time",
    "x": "particles/x",
    "v": "particles/v",
    "kinetic": "energy/kinetic",
    "strain": "energy/strain",
    "dissipated": "energy/dissipated",
    "momentum": "momentum/linear",
    "angular": "momentum/angular",
}


def run_attributes(sim, dt=None, scene: str | None = None, params: dict | None = None, ppc=None) -> dict:
    """The root attributes of docs/design.md for a simulation."""
    from . import __version__

    from ._registry import sim_parameters

    scheme = sim.scheme
    attrs = {
        "scene": scene or "",
        "scheme": type(scheme).__name__,
        "order": int(getattr(scheme, "order", 1)),
        "beta": float(np.asarray(getattr(scheme, "beta", np.nan))),
        "alpha_g": 0.0 if sim.damping is None else float(np.asarray(sim.damping.grid)),
        "alpha_p": 0.0 if sim.damping is None else float(np.asarray(sim.damping.particle)),
        "shape": type(sim.shape).__name__,
        "update": sim.update,
        "dt": float(np.asarray(dt)) if dt is not None else np.nan,
        "cells": np.asarray(sim.grid.cells, dtype=np.int64),
        "grid_lower": np.asarray(sim.grid.lower),
        "grid_upper": np.asarray(sim.grid.upper),
        "ppc": int(ppc) if ppc is not None else int(getattr(sim.shape, "ppc", 0)),
        "dtype": "",
        "jaxmpm version": __version__,
        "scene parameters": json.dumps(params or {}, default=float),
    }
    for name, (where, _) in sim_parameters(sim).items():  # the registered float parameters present
        value = np.asarray(where(sim))
        if np.issubdtype(value.dtype, np.floating):
            attrs[name] = float(value) if value.ndim == 0 else value.astype(np.float64)
    return attrs


class H5Writer:
    """Append-as-you-go HDF5 writer: ``append(history_chunk)`` grows every dataset along time and
    flushes, so an interrupted run keeps all frames written so far.  Use as a context manager."""

    def __init__(self, path, sim, state, dt=None, scene: str | None = None, params: dict | None = None,
                 ppc=None, xdmf: bool = True):
        self.path = os.fspath(path)
        self.xdmf = xdmf
        self.file = h5py.File(self.path, "w")
        attrs = run_attributes(sim, dt, scene, params, ppc)
        attrs["dtype"] = str(np.asarray(state.x).dtype)
        for k, v in attrs.items():
            self.file.attrs[k] = v
        self.file.create_dataset("particles/mass", data=np.asarray(state.mass))
        self.file.create_dataset("particles/volume0", data=np.asarray(state.volume0))
        self.frames = 0
        self.n, self.dim = np.asarray(state.x).shape

    def append(self, history) -> None:
        """Append the frames of a :class:`jaxmpm.History` (leading axis = time)."""
        t = np.asarray(history.time)
        if t.size == 0:
            return
        series = [(getattr(history, field), name) for field, name in _SERIES.items()]
        series += [(value, f"particles/{field}") for field, value in history.fields.items()]
        for value, name in series:
            if value is None:
                continue
            arr = np.asarray(value)
            if name not in self.file:
                self.file.create_dataset(name, data=arr, maxshape=(None,) + arr.shape[1:],
                                         chunks=(max(1, min(64, arr.shape[0])),) + arr.shape[1:])
            else:
                ds = self.file[name]
                ds.resize(ds.shape[0] + arr.shape[0], axis=0)
                ds[-arr.shape[0]:] = arr
        self.frames += t.size
        self.flush()

    def flush(self) -> None:
        self.file.flush()
        if self.xdmf:
            write_xdmf(self.path, self.file)

    def close(self) -> None:
        if self.file.id.valid:
            self.flush()
            self.file.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def save_h5(path, sim, history, state=None, dt=None, scene: str | None = None, params: dict | None = None,
            ppc=None) -> None:
    """Write a whole history at once (``state`` supplies particle mass/volume0; it defaults to a
    state with the history's particle count and unit values if omitted)."""
    if state is None:
        raise TypeError("save_h5: pass state=... (the initial or final State) for particle mass and volume0")
    with H5Writer(path, sim, state, dt=dt, scene=scene, params=params, ppc=ppc) as w:
        w.append(history)


class Results(dict):
    """What :func:`load_h5` returns: arrays by their HDF5 path, plus ``attrs`` and ``params``."""

    attrs: dict
    params: dict


def load_h5(path) -> Results:
    """Read a jaxmpm HDF5 file: ``res["particles/x"]``, ``res.attrs["scheme"]``, ``res.params`` ..."""
    out = Results()
    with h5py.File(path, "r") as f:
        def visit(name, obj):
            if isinstance(obj, h5py.Dataset):
                out[name] = obj[()]

        f.visititems(visit)
        attrs = {k: (v.decode() if isinstance(v, bytes) else v) for k, v in f.attrs.items()}
    out.attrs = attrs
    out.params = json.loads(attrs.get("scene parameters", "{}") or "{}")
    return out


def write_xdmf(h5_path: str, f: h5py.File) -> None:
    """An XDMF 3 sidecar so ParaView opens the particle frames (Polyvertex, one grid per frame)."""
    if "particles/x" not in f:
        return
    T, N, D = f["particles/x"].shape
    h5name = os.path.basename(h5_path)
    times = f["time"][()]
    geom = {1: "X", 2: "XY", 3: "XYZ"}[D]

    def slab(name, t):
        """One time slice of a (T, N) or (T, N, C) dataset as an XDMF hyperslab."""
        ds = f[name]
        per = ds.shape[2:]  # () for a scalar per particle, (C,) otherwise
        ones = " ".join(["1"] * len(ds.shape))
        start = " ".join([str(t)] + ["0"] * (len(ds.shape) - 1))
        count = " ".join(["1", str(N)] + [str(c) for c in per])
        return (
            f'<DataItem ItemType="HyperSlab" Dimensions="{" ".join(str(v) for v in (N,) + per)}" Format="XML">'
            f'<DataItem Dimensions="3 {len(ds.shape)}" Format="XML">{start} {ones} {count}</DataItem>'
            f'<DataItem Dimensions="{" ".join(str(v) for v in ds.shape)}" NumberType="Float" '
            f'Precision="{ds.dtype.itemsize}" Format="HDF">{h5name}:/{name}</DataItem></DataItem>'
        )

    fields = [name for name, ds in f["particles"].items()
              if name not in ("x", "v", "mass", "volume0") and ds.ndim in (2, 3) and ds.shape[:2] == (T, N)]

    def field_attribute(name, t):
        ds = f[f"particles/{name}"]
        kind = "Scalar" if ds.ndim == 2 else "Vector" if ds.shape[2] == D else "Matrix"
        return f'<Attribute Name="{name}" AttributeType="{kind}" Center="Node">{slab("particles/" + name, t)}</Attribute>'

    lines = ['<?xml version="1.0" ?>', '<Xdmf Version="3.0">', "<Domain>",
             '<Grid Name="particles" GridType="Collection" CollectionType="Temporal">']
    geometry_type = geom if D > 1 else "X"
    for t in range(T):
        lines.append(f'<Grid Name="frame{t}" GridType="Uniform"><Time Value="{float(times[t])!r}"/>')
        lines.append(f'<Topology TopologyType="Polyvertex" NumberOfElements="{N}"/>')
        if D == 1:
            lines.append('<Geometry GeometryType="X_Y">' + slab("particles/x", t)
                         + f'<DataItem Dimensions="{N} 1" Format="XML">{" ".join(["0"] * N)}</DataItem></Geometry>')
        else:
            lines.append(f'<Geometry GeometryType="{geometry_type}">' + slab("particles/x", t) + "</Geometry>")
        if "particles/v" in f:
            kind = "Scalar" if D == 1 else "Vector"
            lines.append(f'<Attribute Name="velocity" AttributeType="{kind}" Center="Node">'
                         + slab("particles/v", t) + "</Attribute>")
        for name in fields:  # the terms' saved per-particle fields (temperature, ...)
            lines.append(field_attribute(name, t))
        lines.append("</Grid>")
    lines += ["</Grid>", "</Domain>", "</Xdmf>"]
    with open(os.path.splitext(h5_path)[0] + ".xdmf", "w") as out:
        out.write("\n".join(lines))
