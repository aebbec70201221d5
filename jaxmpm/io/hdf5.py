"""HDF5 output in the layout of docs/design.md, written chunk by chunk, with an XDMF sidecar.

```
/time (T,)   /particles/x (T,N,D)  /particles/v (T,N,D)  /particles/mass (N,)  /particles/volume0 (N,)
/energy/kinetic (T,)  /energy/strain (T,)  /energy/dissipated (T,)
/momentum/linear (T,D)  /momentum/angular (T,1 or 3)
/particles/<name> (T,N,...)   every saved per-particle field a physics term declares
/particles/material (N,)      multimaterial mode: the material id of each particle (int32)
/materials/<name> (T,M[,D])   multimaterial mode: kinetic, strain, momentum, contact_force per material
/totals/<name> (T,)           the terms' totals: thermal_energy (jm.Heat), solute (jm.Diffusion)
/state/<leaf>                 the state a chunked run reached (H5Writer.write_state; jaxmpm.resume)
attributes on /: scene, scheme, order, beta, alpha_g, alpha_p, damping approach, damping varies (0/1:
                 a schedule or region scales alpha_g, alpha_p), shape, update, conventions
                 (jaxmpm/nairnmpm), constrained force (zero/reaction), position and series boundary
                 (the XPIC family's and FMPM's options; "" for other schemes), dt, cells, ppc,
                 dtype, jaxmpm version, scene parameters (JSON), and every other float
                 parameter the model's registered parts declare (E, nu, density, ...)
```
A new field or parameter needs no edit here: the writer follows ``History.fields`` and the
registry.  The sidecar is two files next to ``FILE.h5``: ``FILE.xdmf`` and ``FILE.xdmf.h5`` (per-frame
HDF5 virtual datasets into ``FILE.h5``, no data of their own; see :func:`write_xdmf`).
"""

from __future__ import annotations

import json
import os

import h5py
import numpy as np

from .xdmf import write_xdmf, xdmf_paths  # noqa: F401  (xdmf_paths re-exported)

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
    from ..core.registry import sim_parameters
    from ..core.version import __version__

    scheme = sim.scheme
    attrs = {
        "scene": scene or "",
        "scheme": type(scheme).__name__,
        "order": int(getattr(scheme, "order", 1)),
        "beta": float(np.asarray(getattr(scheme, "beta", np.nan))),
        # the layout's damping attributes for a model without damping; a damping term's own below
        "alpha_g": 0.0, "alpha_p": 0.0, "damping approach": "velocity", "damping varies": 0,
        "shape": type(sim.shape).__name__,
        "update": sim.update,
        "conventions": sim.conventions,
        "constrained force": sim.constrained_force,
        "position": str(getattr(scheme, "position", "")),
        "series boundary": str(getattr(scheme, "boundary", "")),
        "dt": float(np.asarray(dt)) if dt is not None else np.nan,
        "cells": np.asarray(sim.grid.cells, dtype=np.int64),
        "grid_lower": np.asarray(sim.grid.lower),
        "grid_upper": np.asarray(sim.grid.upper),
        "ppc": int(ppc) if ppc is not None else int(getattr(sim.shape, "ppc", 0)),
        "dtype": "",
        "jaxmpm version": __version__,
        "scene parameters": json.dumps(params or {}, default=float),
    }
    for term in sim.terms:  # the terms' descriptive attributes (Term.attributes)
        attrs.update(term.attributes())
    for name, (where, _) in sim_parameters(sim).items():  # the registered float parameters present
        value = np.asarray(where(sim))
        if np.issubdtype(value.dtype, np.floating):
            attrs[name] = float(value) if value.ndim == 0 else value.astype(np.float64)
    return attrs


class H5Writer:
    """Append-as-you-go HDF5 writer: ``append(history_chunk)`` grows every dataset along time and
    flushes, so an interrupted run keeps all frames written so far.  Use as a context manager.

    ``mode="w"`` creates (or truncates) ``path``; ``mode="a"`` reopens a file this writer made to
    append to it (:func:`jaxmpm.resume`).  ``write_state`` stores the full state reached under
    ``/state`` (every leaf of the :class:`State` pytree, with the run's schedule as attributes)."""

    def __init__(self, path, sim, state, dt=None, scene: str | None = None, params: dict | None = None,
                 ppc=None, xdmf: bool = True, mode: str = "w"):
        from ..core.errors import check

        check(mode in ("w", "a"), f"H5Writer: mode = {mode!r}; use 'w' (create) or 'a' (append)")
        self.path = os.fspath(path)
        self.xdmf = xdmf
        if mode == "a":
            check(os.path.exists(self.path), f"H5Writer: {self.path} does not exist; mode='a' appends to a run's file")
            self.file = h5py.File(self.path, "a")
            self.frames = int(self.file["time"].shape[0]) if "time" in self.file else 0
            self.n, self.dim = np.asarray(state.x).shape
            return
        self.file = h5py.File(self.path, "w")
        attrs = run_attributes(sim, dt, scene, params, ppc)
        attrs["dtype"] = str(np.asarray(state.x).dtype)
        for k, v in attrs.items():
            self.file.attrs[k] = v
        self.file.create_dataset("particles/mass", data=np.asarray(state.mass))
        self.file.create_dataset("particles/volume0", data=np.asarray(state.volume0))
        if "material" in state.fields:  # multimaterial mode: each particle's material id, once
            self.file.create_dataset("particles/material", data=np.asarray(state.fields["material"]).astype(np.int32))
        self.frames = 0
        self.n, self.dim = np.asarray(state.x).shape

    def write_state(self, state, start_step: int, steps: int, save_every: int) -> None:
        """Store ``state`` under ``/state`` (replacing an earlier one), with the schedule of the
        run it belongs to: its first frame's step, its length in steps and ``save_every``."""
        if "state" in self.file:
            del self.file["state"]
        group = self.file.create_group("state")
        for name, leaf in state_leaves(state):
            group.create_dataset(name, data=np.asarray(leaf))
        group.attrs["start step"] = int(start_step)
        group.attrs["steps"] = int(steps)
        group.attrs["save every"] = int(save_every)
        group.attrs["complete"] = int(state.step) >= int(start_step) + int(steps)
        self.file.flush()

    def append(self, history) -> None:
        """Append the frames of a :class:`jaxmpm.History` (leading axis = time)."""
        t = np.asarray(history.time)
        if t.size == 0:
            return
        series = [(getattr(history, field), name) for field, name in _SERIES.items()]
        series += [(value, f"particles/{field}") for field, value in history.fields.items()]
        series += [(value, f"materials/{name}") for name, value in history.by_material.items()]
        series += [(value, f"totals/{name}") for name, value in history.totals.items()]
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


def _key_name(key) -> str:
    for attr in ("name", "key", "idx"):
        if hasattr(key, attr):
            return str(getattr(key, attr))
    return str(key)  # pragma: no cover


def state_leaves(state):
    """(HDF5 name, array) for every leaf of a :class:`State`: ``x``, ``F``, ``scheme_state``,
    ``fields/temperature``, ``material_state/0`` ..."""
    import jax

    leaves, _ = jax.tree_util.tree_flatten_with_path(state)
    return [("/".join(_key_name(k) for k in path), leaf) for path, leaf in leaves]


def read_state(path, template):
    """The state stored under ``/state`` of ``path`` (see :meth:`H5Writer.write_state`), as a
    :class:`State` shaped like ``template`` (the run's initial state), plus the schedule:
    ``(state, {"start step", "steps", "save every", "complete"})``."""
    import jax
    import jax.numpy as jnp

    from ..core.errors import check

    with h5py.File(path, "r") as f:
        check("state" in f, f"{os.fspath(path)} holds no saved state (/state): it was written by an older "
                            "jaxmpm or a run that failed before its first chunk; rerun it")
        group = f["state"]
        leaves = []
        for name, leaf in state_leaves(template):
            check(name in group, f"{os.fspath(path)}: /state/{name} is missing; the file's run used another "
                                 "model (scheme, material, terms) than the one given")
            value = group[name][()]
            check(value.shape == np.shape(leaf) and value.dtype == jnp.result_type(leaf),
                  f"{os.fspath(path)}: /state/{name} is {value.dtype}{list(value.shape)} but the model's state "
                  f"has {jnp.result_type(leaf)}{list(np.shape(leaf))}; resume with the run's own scene and options")
            leaves.append(jnp.asarray(value))
        schedule = {k: (bool(v) if k == "complete" else int(v)) for k, v in group.attrs.items()}
    return jax.tree_util.tree_unflatten(jax.tree_util.tree_structure(template), leaves), schedule


class Results(dict):
    """What :func:`load_h5` returns: arrays by their HDF5 path, plus ``attrs`` and ``params``."""

    attrs: dict
    params: dict


def load_h5(path) -> Results:
    """Read a jaxmpm HDF5 file: ``res["particles/x"]``, ``res.attrs["scheme"]``, ``res.params`` ..."""
    out = Results()
    with h5py.File(path, "r") as f:
        def visit(name, obj):  # /state is restart data (read_state, jaxmpm.resume), not results
            if isinstance(obj, h5py.Dataset) and not name.startswith("state/"):
                out[name] = obj[()]

        f.visititems(visit)
        attrs = {k: (v.decode() if isinstance(v, bytes) else v) for k, v in f.attrs.items()}
    out.attrs = attrs
    out.params = json.loads(attrs.get("scene parameters", "{}") or "{}")
    return out


