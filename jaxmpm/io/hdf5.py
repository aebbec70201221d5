"""HDF5 output in the layout of docs/design.md, written chunk by chunk, with an XDMF sidecar; the
file survives a kill at any moment (see :class:`H5Writer`: it is replaced by rename, never written
in place).

```
/time (T,)   /particles/x (T,N,D)  /particles/v (T,N,D)  /particles/mass (N,)  /particles/volume0 (N,)
/energy/kinetic (T,)  /energy/strain (T,)  /energy/dissipated (T,)
/momentum/linear (T,D)  /momentum/angular (T,1 or 3)
/particles/<name> (T,N,...)   every saved per-particle field a physics term declares, and each field
                              the run chose (H5Writer's fields=: stress (T,N,d,d), pressure (T,N),
                              J (T,N), F (T,N,d,d); jaxmpm.model.frame_fields)
/particles/material (N,)      multimaterial mode: the material id of each particle (int32)
/materials/<name> (T,M[,D])   multimaterial mode: kinetic, strain, momentum, contact_force per material
/totals/<name> (T,)           the model's totals: thermal_energy (jm.Heat), solute (jm.Diffusion), the
                              material's (viscous_dissipation of jm.NewtonianFluid; Material.totals)
/state/<leaf>                 the state a chunked run reached, saved with every chunk's frames
                              (H5Writer.write_state; jaxmpm.resume); attributes start step, steps,
                              save every, complete
attributes on /: scene, scheme, order, beta, alpha_g, alpha_p, damping approach, damping varies (0/1:
                 a schedule or region scales alpha_g, alpha_p), shape, update, conventions
                 (jaxmpm/nairnmpm), constrained force (zero/reaction), position and series boundary
                 (the XPIC family's and FMPM's options; "" for other schemes), dt, cells, ppc,
                 dtype, jaxmpm version, scene parameters (JSON), and every other float
                 parameter the model's registered parts declare (E, nu, density, ...);
                 fields (the chosen fields, comma-separated: "stress,J"; "" for none)
```
A new field or parameter needs no edit here: the writer follows ``History.fields`` and the
registry.  The sidecar is two files next to ``FILE.h5``: ``FILE.xdmf`` and ``FILE.xdmf.h5`` (per-frame
HDF5 virtual datasets into ``FILE.h5``, no data of their own; see :func:`write_xdmf`).
"""

from __future__ import annotations

import contextlib
import json
import os

import h5py
import numpy as np

from ..core.validate import POSITIVE, input_file, output_file
from .xdmf import (
    copy_into_place,
    link_into_place,
    remove,
    same_file,
    stored_fields,
    views_copies,
    write_xdmf,
    xdmf_paths,
)

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
    """Append-as-you-go HDF5 writer whose file survives a kill at any moment.  Use as a context manager.

    ``append(history_chunk)`` adds frames and ``write_state(state, ...)`` stores the full state
    reached under ``/state`` (every leaf of the :class:`State` pytree, with the run's schedule as
    attributes); each is published at once, or both together at the end of a ``with
    writer.batch():`` block -- a chunked run publishes every chunk's frames with the state reached.

    ``FILE.h5`` is never written in place.  The writer keeps two copies of it, ``FILE.h5.0.tmp``
    and ``FILE.h5.1.tmp``, one of which *is* ``FILE.h5`` (a second hard link to the same file).
    Publishing opens the other copy, adds what it lacks (the operations since it was last published,
    kept in memory), closes it -- HDF5 has then written every byte of it -- and renames a link to it
    over ``FILE.h5``; POSIX ``rename(2)`` replaces the name atomically.  So ``FILE.h5`` is at every
    moment a closed, complete HDF5 file holding whole publications: first the header (attributes,
    mass, volume0), then every chunk's frames and the state reached together.  A kill (``kill -9``,
    an out-of-memory kill) leaves it as of its last publication; the ``.tmp`` copies and
    ``FILE.h5.lock`` stay beside it until the next writer of the path removes them.  The XDMF
    sidecar's views file is kept the same way (:func:`jaxmpm.io.xdmf.write_xdmf`).  Where hard
    links are not available, the copy is copied to ``FILE.h5`` instead (the same guarantee, a full
    copy per publication).  ``FILE.h5.lock`` (``flock``) keeps a second writer of the same path out.

    ``mode="w"`` creates ``path``, publishing its header at once; it refuses (InputError) to replace
    an existing ``path`` or XDMF sidecar unless ``overwrite=True``.  ``mode="a"`` continues a file
    this writer made (:func:`jaxmpm.resume`).  ``attrs`` are root attributes added to the header
    (the CLI's ``command``).

    ``fields``: the per-particle fields a run with this writer saves in every frame besides x, v
    and the terms' fields, by name -- ``("stress", "pressure", "J", "F")`` and the material's
    saved state (:mod:`jaxmpm.model.frame_fields`); each is ``/particles/<name>`` (T, N, ...),
    the names are the root attribute ``fields``.  ``sim.run(..., writer=writer)`` computes them.
    Default: none (mode "w"), the file's own (mode "a": a resumed run goes on with them).

    Args:
        path: the HDF5 file, ``FILE.h5``.
        sim: the :class:`jaxmpm.Simulation` of the run (the root attributes: scheme, shape,
            grid, parameters, ...).
        state: the run's :class:`jaxmpm.State` (the particles' mass and volume0, the sizes).
        dt: the time step, stored as the attribute ``dt``; None (the default): NaN.
        scene: the scene's name (the attribute ``scene``); None (the default): "".
        params: the scene's options, stored as JSON (``scene parameters``); None (the default).
        ppc: particles per cell per axis (the attribute ``ppc``); None (the default): the shape's
            own (UGIMP), else 0.
        xdmf: also write the XDMF sidecar ``FILE.xdmf`` for ParaView/VisIt (default True).
        mode: "w" (default) creates ``path``; "a" continues a file this writer made.
        attrs: more root attributes for the header; None (the default).
        fields: the per-frame fields by name (above); None (the default).
        overwrite: mode "w": replace an existing ``path`` or sidecar (default False: an
            InputError).
    """

    def __init__(self, path, sim, state, dt=None, scene: str | None = None, params: dict | None = None,
                 ppc=None, xdmf: bool = True, mode: str = "w", attrs: dict | None = None, fields=None,
                 overwrite: bool = False):
        from ..core.errors import check

        path = output_file("H5Writer", path, "give the run's file, e.g. 'run.h5'")
        check(isinstance(mode, str) and mode in ("w", "a"), f"H5Writer: mode = {mode!r}; use 'w' (create) or 'a' "
                                                            "(append)")
        check(fields is None or isinstance(fields, (tuple, list)),
              f"H5Writer: fields = {fields!r}; give a tuple of field names, e.g. ('stress', 'J'), or None")
        if dt is not None:
            POSITIVE.real("H5Writer", "dt", dt, fix="the run's time step, or None")
        if mode == "w":
            refuse_overwrite("H5Writer", path, xdmf, overwrite)
        self.path = os.fspath(path)
        self.xdmf = xdmf
        self.n, self.dim = np.asarray(state.x).shape
        self.fields = sim.check_frame_fields(state, fields, "H5Writer: fields") if fields else ()
        if mode == "a":
            check(os.path.exists(self.path), f"H5Writer: {self.path} does not exist; mode='a' appends to a run's file")
            self._continue_fields(fields is not None)
        self.frames = 0
        self._log = []  # operations not yet in both copies: ("frames", {path: array}), ("state", leaves or None: in
        # FILE.h5, attrs), ("truncate", T)
        self._applied = [0, 0]  # per copy, how much of the log it holds (None: unknown, copied from FILE.h5 again)
        self._current = 0  # the copy that FILE.h5 is
        self._held = 0  # depth of batch()
        self._links = True  # hard links work here (else each publication copies)
        self._closed = True
        self._lock = None
        self._lock = _take_lock(self.path)
        self._closed = False
        try:
            remove(*working_paths(self.path))
            if mode == "a":
                self._open_existing()
            else:
                self._create(run_attributes(sim, dt, scene, params, ppc) | dict(attrs or {})
                             | {"fields": ",".join(self.fields)}, state)
        except BaseException:
            self._closed = True
            _release_lock(self._lock, self.path)
            raise

    def _copy_path(self, index: int) -> str:
        return working_paths(self.path)[index]

    def _continue_fields(self, given: bool) -> None:
        """mode "a": the fields the file's run saves (its ``fields`` attribute), which ``fields=``,
        when given, must repeat."""
        from ..core.errors import check

        with h5py.File(self.path, "r") as f:
            stored = stored_fields(f.attrs)
        check(not given or self.fields == stored,
              f"H5Writer: fields = {self.fields!r} but {self.path} saves {stored!r} in every frame; a continued "
              "run keeps its file's fields (leave fields= out)")
        self.fields = stored

    def _create(self, attrs, state) -> None:
        attrs["dtype"] = str(np.asarray(state.x).dtype)
        first = self._copy_path(0)
        with h5py.File(first, "w") as f:
            for k, v in attrs.items():
                f.attrs[k] = v
            f.create_dataset("particles/mass", data=np.asarray(state.mass))
            f.create_dataset("particles/volume0", data=np.asarray(state.volume0))
            if "material" in state.fields:  # multimaterial mode: each particle's material id, once
                f.create_dataset("particles/material", data=np.asarray(state.fields["material"]).astype(np.int32))
        copy_into_place(first, self._copy_path(1))
        if self.xdmf:  # the XDMF of an earlier file of this name would list its frames (its views fit any)
            remove(xdmf_paths(self.path)[0])
        self._publish(0)  # FILE.h5 exists from here on: readable, with no frames yet

    def _open_existing(self) -> None:
        with h5py.File(self.path, "r") as f:
            self.frames = int(f["time"].shape[0]) if "time" in f else 0
        self._link_or_copy(self.path, self._copy_path(0))  # FILE.h5 itself: it is only read
        copy_into_place(self.path, self._copy_path(1))

    def _link_or_copy(self, source: str, target: str) -> None:
        """Make ``target`` name the file ``source`` names, in one step (a hard link, or a copy where
        hard links fail)."""
        self._links = link_into_place(source, target, self._links)

    def _publish(self, index: int) -> None:
        self._link_or_copy(self._copy_path(index), self.path)
        self._current = index

    def append(self, history) -> None:
        """Append the frames of a :class:`jaxmpm.History` (leading axis = time)."""
        t = np.asarray(history.time)
        if t.size == 0:
            return
        series = [(getattr(history, field), name) for field, name in _SERIES.items()]
        series += [(value, f"particles/{field}") for field, value in history.fields.items()]
        series += [(value, f"materials/{name}") for name, value in history.by_material.items()]
        series += [(value, f"totals/{name}") for name, value in history.totals.items()]
        self._log.append(("frames", {name: np.asarray(value) for value, name in series if value is not None}))
        self.frames += t.size
        self.flush()

    def write_state(self, state, start_step: int, steps: int, save_every: int) -> None:
        """Store ``state`` under ``/state`` (replacing an earlier one), with the schedule of the
        run it belongs to: its first frame's step, its length in steps and ``save_every``."""
        leaves = [(name, np.asarray(leaf)) for name, leaf in state_leaves(state)]
        attrs = {"start step": int(start_step), "steps": int(steps), "save every": int(save_every),
                 "complete": int(state.step) >= int(start_step) + int(steps)}
        self._log.append(("state", leaves, attrs))
        self.flush()

    def truncate(self, frames: int) -> None:
        """Keep only the first ``frames`` frames (:func:`jaxmpm.resume` drops the frames saved after
        the state it continues from; it computes them again, to the same bits)."""
        if frames < self.frames:
            self._log.append(("truncate", int(frames)))
            self.frames = int(frames)
            self.flush()

    @contextlib.contextmanager
    def batch(self):
        """Publish everything appended or written inside the block together, at its end (also when
        it ends with an exception)."""
        self._held += 1
        try:
            yield self
        finally:
            self._held -= 1
            if not self._held:
                self.flush()

    def flush(self) -> None:
        """Publish what was appended or written since the last publication, in one step (see the
        class notes), then update the XDMF sidecar.  Inside :meth:`batch` it waits for the end."""
        if self._held or self._closed:
            return
        if same_file(self._copy_path(1 - self._current), self.path):  # published, interrupted before recorded
            self._current = 1 - self._current
        if self._applied[self._current] == len(self._log):
            return
        index = 1 - self._current
        try:
            self._bring_up_to_date(index)
        except BaseException:
            self._applied[index] = None  # in an unknown state: copied from FILE.h5 again next time
            raise
        self._publish(index)
        done = min(self._applied)
        del self._log[:done]
        self._applied = [a - done for a in self._applied]
        # every state left in the log is now in FILE.h5, the copy the other one is brought up to date from: its
        # arrays are let go (on the CPU they are views of the run's device buffers, which JAX would otherwise not
        # compute the next chunk in place of) and read back from FILE.h5's copy when needed (_stored_state)
        self._log = [("state", None, op[2]) if op[0] == "state" else op for op in self._log]
        self.write_sidecar()

    def _bring_up_to_date(self, index: int) -> None:
        path = self._copy_path(index)
        if self._applied[index] is None or not os.path.exists(path):
            self._recopy(index)
        try:
            f = h5py.File(path, "r+")
        except OSError:  # held open (and so locked) by a reader since it was FILE.h5: write a fresh copy
            self._recopy(index)
            f = h5py.File(path, "r+")
        with f:
            _apply(f, self._log[self._applied[index]:], self._stored_state)
        self._applied[index] = len(self._log)

    @contextlib.contextmanager
    def _stored_state(self):
        """(name, dataset) of every leaf under ``/state`` of the published copy, open for the block: the state
        that :meth:`flush` let go of once FILE.h5 held it (the copy published last holds every operation left
        in the log).  It is copied from there block by block (:func:`_fill`), never whole in memory."""
        with h5py.File(self._copy_path(self._current), "r") as f:
            leaves = []
            f["state"].visititems(lambda name, obj: leaves.append((name, obj)) if isinstance(obj, h5py.Dataset)
                                  else None)
            yield leaves

    def _recopy(self, index: int) -> None:
        """The copy ``index`` made again from FILE.h5 (a new file: a reader of the old one keeps it)."""
        copy_into_place(self.path, self._copy_path(index))
        self._applied[index] = self._applied[self._current]

    def write_sidecar(self) -> None:
        """Write the XDMF sidecar of ``FILE.h5`` as it is published now (every publication does; this is for
        a file whose run ended without one, :func:`jaxmpm.resume` of a finished run)."""
        if self.xdmf:
            with h5py.File(self.path, "r") as f:
                write_xdmf(self.path, f)

    def close(self) -> None:
        """Publish what is left, remove the working copies and the lock; ``FILE.h5`` stays."""
        if self._closed:
            return
        try:
            self._held = 0
            self.flush()
        finally:
            self._closed = True
            remove(*working_paths(self.path))
            _release_lock(self._lock, self.path)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def __del__(self):  # a writer left open: published and its files removed, as h5py closes a file
        try:
            self.close()
        except Exception:  # pragma: no cover  (interpreter shutdown)
            pass


def refuse_overwrite(owner: str, path, xdmf: bool = True, overwrite: bool = False) -> None:
    """An InputError when writing ``path`` would replace an existing file -- ``path`` itself or, with
    ``xdmf``, its XDMF sidecar (``FILE.xdmf``, ``FILE.xdmf.h5``) -- unless ``overwrite``: no run's
    results are lost without consent.  (A killed writer's working copies and lock are not results:
    the next writer removes them.)"""
    from ..core.errors import check

    check(isinstance(overwrite, bool), f"{owner}: overwrite = {overwrite!r} must be True (replace an existing "
                                       "file) or False (refuse to)")
    path = os.fspath(path)
    existing = [p for p in (path,) + (xdmf_paths(path) if xdmf else ()) if os.path.exists(p)]
    check(overwrite or not existing,
          f"{owner}: {' and '.join([', '.join(existing[:-1])] * (len(existing) > 1) + existing[-1:])} "
          f"{'exists' if len(existing) == 1 else 'exist'}"
          f"{'' if path in existing else ' (the XDMF sidecar of an earlier run)'}; pass overwrite=True to "
          f"replace {'it' if len(existing) == 1 else 'them'}, or choose another path")


def working_paths(path) -> tuple[str, ...]:
    """The files an :class:`H5Writer` keeps beside ``path`` while it writes: its two copies
    (``FILE.h5.0.tmp``, ``FILE.h5.1.tmp``), those of the XDMF views file (``FILE.xdmf.h5.0.tmp``,
    ``FILE.xdmf.h5.1.tmp``) and the temporaries renamed into place (``*.tmp``, ``*.partial``).  A
    kill leaves some of them; the next writer of ``path`` removes them (so may anyone: they are not
    needed to read or resume ``FILE.h5``)."""
    path = os.fspath(path)
    xdmf_path, views_path = xdmf_paths(path)
    copies = (path + ".0.tmp", path + ".1.tmp") + views_copies(views_path)
    return copies + tuple(p + ".tmp" for p in (path, views_path) + copies) + (xdmf_path + ".partial",)


def _take_lock(path: str):
    """An exclusive ``flock`` on ``FILE.h5.lock`` for the writer's life (a kill releases it), or an
    InputError naming the process that holds it.  None where ``fcntl`` is missing (Windows)."""
    try:
        import fcntl
    except ImportError:  # pragma: no cover
        return None
    from ..core.errors import check

    for _ in range(100):
        fd = os.open(path + ".lock", os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            holder = os.pread(fd, 32, 0).decode(errors="replace").strip()
            os.close(fd)
            check(holder != str(os.getpid()), f"{path} is already open in an H5Writer of this process; close it "
                                              "first (use the writer in a `with` block)")
            check(False, f"{path} is being written by another process{' (pid ' + holder + ')' if holder else ''}; "
                         "wait for it to end, or stop it, first")
        try:  # the lock file may have been removed by the writer that held it, between our open and our flock:
            same = os.stat(path + ".lock").st_ino == os.fstat(fd).st_ino  # then we hold a lock nobody sees
        except FileNotFoundError:
            same = False
        if same:
            break
        os.close(fd)  # open the lock file anew
    else:  # pragma: no cover - a lock file removed a hundred times in a row
        check(False, f"{path}.lock keeps being removed; is another process writing {path}?")
    os.ftruncate(fd, 0)
    os.pwrite(fd, str(os.getpid()).encode(), 0)
    return fd


def _release_lock(fd, path: str) -> None:
    if fd is not None:
        remove(path + ".lock")
        os.close(fd)


def _apply(f: h5py.File, operations, stored_state) -> None:
    """Apply a writer's logged operations to an open copy: frames and truncations in order, then
    the last state (each state replaces the one before); a state whose arrays the log let go of is
    ``stored_state()``'s."""
    state = None
    for operation in operations:
        if operation[0] == "frames":
            _append_frames(f, operation[1])
        elif operation[0] == "truncate":
            _truncate(f, operation[1])
        else:
            state = operation
    if state is None:
        return
    if state[1] is not None:
        _write_state(f, state[1], state[2])
        return
    with stored_state() as leaves:
        _write_state(f, leaves, state[2])


def _append_frames(f: h5py.File, arrays: dict) -> None:
    for name, arr in arrays.items():
        if name not in f:
            f.create_dataset(name, data=arr, maxshape=(None,) + arr.shape[1:],
                             chunks=(max(1, min(64, arr.shape[0])),) + arr.shape[1:])
        else:
            ds = f[name]
            ds.resize(ds.shape[0] + arr.shape[0], axis=0)
            ds[-arr.shape[0]:] = arr


def _truncate(f: h5py.File, frames: int) -> None:
    """Every per-frame dataset (those that grow along time) cut to ``frames`` frames."""
    series = []
    f.visititems(lambda name, obj: series.append(obj) if isinstance(obj, h5py.Dataset) and obj.maxshape
                 and obj.maxshape[0] is None and not name.startswith("state/") else None)
    for ds in series:
        if ds.shape[0] > frames:
            ds.resize(frames, axis=0)


def _write_state(f: h5py.File, leaves, attrs: dict) -> None:
    """``/state``: its datasets overwritten in place when they have the leaves' names, shapes and
    dtypes (no new space in the file each chunk), else made again.  A leaf is an array or a dataset
    of another file (:func:`_fill`)."""
    group = f.get("state")
    if group is not None:
        held = {}
        group.visititems(lambda name, obj: held.__setitem__(name, (obj.shape, obj.dtype))
                         if isinstance(obj, h5py.Dataset) else None)
        if held != {name: (value.shape, value.dtype) for name, value in leaves}:
            del f["state"]
            group = None
    if group is None:
        group = f.create_group("state")
        for name, value in leaves:
            group.create_dataset(name, shape=value.shape, dtype=value.dtype)
    for name, value in leaves:
        if value.size:
            _fill(group[name], value)
    for k, v in attrs.items():
        group.attrs[k] = v


_BLOCK_BYTES = 8 * 2**20  # a dataset of another file is copied this many bytes at a time


def _fill(target: h5py.Dataset, value) -> None:
    """``target[...] = value``, an array, or a dataset of another file copied block by block along its first axis
    (a writer's state read back from its published copy: a whole state in memory at once would add one to the
    run's peak)."""
    if not isinstance(value, h5py.Dataset) or not value.ndim:
        target[()] = value[()]
        return
    rows = max(1, _BLOCK_BYTES // max(1, value.nbytes // max(1, value.shape[0])))
    for start in range(0, value.shape[0], rows):
        target[start:start + rows] = value[start:start + rows]


def save_h5(path, sim, history, state=None, dt=None, scene: str | None = None, params: dict | None = None,
            ppc=None, *, steps: int | None = None, save_every: int | None = None, start_step: int = 0,
            overwrite: bool = False) -> None:
    """Write a whole history at once.  ``state`` supplies particle mass and volume0 (the initial or
    the final State).  An existing ``path`` (or its XDMF sidecar) is an InputError unless
    ``overwrite=True``.

    With the run's schedule -- ``steps`` and ``save_every`` as given to ``sim.run``, ``start_step``
    the step of the history's first frame (0 for a scene) -- ``state`` is the state the run
    reached (its final state, or ``RunInterrupted.state``); it is stored under ``/state`` and the
    file can be continued like a ``jaxmpm run`` file: ``jm.resume(path, setup)`` runs it to
    ``steps`` in the same file (a finished run: returns ``state``).  The fields the run chose
    (``sim.run(..., fields=...)``: stress, J, ...) are the file's ``fields``, as with
    ``jm.H5Writer(..., fields=...)``; a resumed run goes on saving them.

    Args:
        path: the HDF5 file to write.
        sim: the :class:`jaxmpm.Simulation` of the run (the root attributes: scheme, shape,
            grid, parameters, ...).
        history: the :class:`jaxmpm.History` of the run.
        state: a :class:`jaxmpm.State` of the run (required): the initial or the final one, for
            the particles' mass and volume0; with the schedule, the state the run reached.
        dt: the time step (the attribute ``dt``); None (the default): NaN.
        scene: the scene's name; None (the default).
        params: the scene's options, stored as JSON; None (the default).
        ppc: particles per cell per axis; None (the default): the shape's own.
        steps: the run's steps as given to ``sim.run``, with ``save_every``: the file is
            resumable; None (the default): not.
        save_every: the run's steps between frames; None (the default).
        start_step: the step of the history's first frame (default 0).
        overwrite: replace an existing ``path`` or sidecar (default False: an InputError).
    """
    from ..core.errors import check

    if state is None:
        raise TypeError("save_h5: pass state=... (the initial or final State) for particle mass and volume0")
    resumable = steps is not None or save_every is not None
    if resumable:
        check(steps is not None and save_every is not None,
              "save_h5: pass both steps= and save_every= (the run's schedule) to make the file resumable")
        for name, value, least in (("steps", steps, 0), ("save_every", save_every, 1), ("start_step", start_step, 0)):
            check(isinstance(value, (int, np.integer)) and not isinstance(value, bool) and value >= least,
                  f"save_h5: {name} = {value!r} must be an integer >= {least}")
        reached, frames = int(state.step) - int(start_step), int(np.asarray(history.time).shape[0])
        check(0 <= reached <= steps and reached // save_every + 1 == frames,
              f"save_h5: the state is at step {int(state.step)}, where a run from step {start_step} saving every "
              f"{save_every} steps has {reached // save_every + 1 if reached >= 0 else 0} frames, but the history "
              f"holds {frames}; pass the state the run reached (its final state, or RunInterrupted.state)")
    refuse_overwrite("save_h5", path, True, overwrite)
    with H5Writer(path, sim, state, dt=dt, scene=scene, params=params, ppc=ppc, overwrite=overwrite,
                  fields=chosen_fields(history, sim, state)) as w, w.batch():
        w.append(history)
        if resumable:
            w.write_state(state, start_step, steps, save_every)


def chosen_fields(history, sim, state) -> tuple:
    """The per-frame fields a run chose (``sim.run(..., fields=...)``) among ``history.fields``:
    those of :func:`jaxmpm.model.frame_fields.available` that no term declares."""
    if not hasattr(sim, "check_frame_fields"):
        return ()
    from ..model.frame_fields import available

    offered, terms = available(sim, state), {f.name for f in sim.particle_fields() if f.save}
    return tuple(name for name in history.fields if name in offered and name not in terms)


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


def read_state(path, template, again: str = "start the run again"):
    """The state stored under ``/state`` of ``path`` (see :meth:`H5Writer.write_state`), as a
    :class:`State` shaped like ``template`` (the run's initial state), plus the schedule:
    ``(state, {"start step", "steps", "save every", "complete"})``.  ``again`` ends the message
    of a file without a state (what to do instead)."""
    import jax
    import jax.numpy as jnp

    from ..core.errors import check

    with h5py.File(path, "r") as f:
        if "state" not in f:
            frames = int(f["time"].shape[0]) if "time" in f else 0
            check(frames, f"{os.fspath(path)} holds no frames and no saved state (/state): its run was stopped "
                          f"before the first frame was saved, so there is nothing to continue; {again}")
            check(False, f"{os.fspath(path)} holds {frames} frame{'s' * (frames != 1)} but no saved state (/state) "
                         "to continue from: it was written by jm.save_h5 without steps= and save_every=, or by "
                         f"an earlier jaxmpm, which saved the state only on Ctrl-C; {again}")
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
    """What :func:`load_h5` returns: arrays by their HDF5 path, plus ``attrs``, ``params`` and
    ``fields`` (the chosen per-frame fields the file saves, each ``res["particles/<name>"]``)."""

    attrs: dict
    params: dict
    fields: tuple


def load_h5(path) -> Results:
    """Read a jaxmpm HDF5 file: ``res["particles/x"]``, ``res.attrs["scheme"]``, ``res.params`` ...
    A path that does not exist, or a file HDF5 cannot open (truncated, not HDF5), is an InputError.

    Args:
        path: the file (``jaxmpm run ... --out FILE.h5``, :func:`save_h5`, :class:`H5Writer`).

    Returns:
        A ``Results`` dict of every dataset by its HDF5 path (``/state``, restart data, left
        out), with ``attrs`` (the root attributes), ``params`` (the scene's options) and
        ``fields`` (the per-frame fields the file saves).
    """
    from ..core.errors import check

    out = Results()
    path = input_file("load_h5", path, "give the path of a jaxmpm HDF5 file")
    check(os.path.isfile(path), f"load_h5: {os.fspath(path)!r} does not exist (or is not a file); give the path of a "
                                "jaxmpm HDF5 file (`jaxmpm run ... --out FILE.h5`, jm.save_h5, jm.H5Writer)")
    try:
        f = h5py.File(path, "r")
    except OSError as err:
        check(False, f"load_h5: {os.fspath(path)!r} is not a readable HDF5 file ({str(err).splitlines()[0][:120]}); "
                     "it may be truncated or not HDF5 -- a run's file stays readable after any stop, so check the "
                     "path, or rerun the run")
    with f:
        def visit(name, obj):  # /state is restart data (read_state, jaxmpm.resume), not results
            if isinstance(obj, h5py.Dataset) and not name.startswith("state/"):
                out[name] = obj[()]

        f.visititems(visit)
        attrs = {k: (v.decode() if isinstance(v, bytes) else v) for k, v in f.attrs.items()}
    out.attrs = attrs
    out.params = json.loads(attrs.get("scene parameters", "{}") or "{}")
    out.fields = stored_fields(attrs)
    return out


