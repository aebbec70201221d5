"""Resuming a run from its HDF5 file (``jaxmpm resume FILE.h5`` on the command line).

A chunked run (:func:`jaxmpm.run.driver.run` with a writer) publishes every chunk's frames together
with the full state reached (:meth:`H5Writer.write_state`, under ``/state``), and its file is
replaced by rename, never written in place (:class:`jaxmpm.H5Writer`): whatever stops the run --
Ctrl-C, SIGTERM, ``kill -9``, an out-of-memory kill -- the file holds its last chunk's frames and
state.  :func:`resume` reads that state back bit for bit and runs the same compiled loop on to the
end of the run's schedule, appending to the same file.  On the CPU the result equals the
uninterrupted run bitwise (``tests/test_resume.py``, ``tests/test_crash_safety.py``).  With
``devices=N`` (``jaxmpm resume FILE --devices N``) the run continues on N devices
(:class:`jaxmpm.parallel.ShardedSimulation`), whether one device or several wrote the file: the
uninterrupted run's file to round-off (``tests/parallel/sharded_io_check.py``).
"""

from __future__ import annotations

import json
import os
import shlex

import h5py
import numpy as np

from .core.errors import InputError, check
from .core.validate import input_file


def run_info(path) -> dict:
    """The root attributes of a run's file that resuming needs (``dt``, ``command``, ``scene``)."""
    from .io.hdf5 import working_paths

    path = input_file("resume", path, "give the path of a run's file (jaxmpm run ... --out FILE.h5, jm.H5Writer)")
    if not os.path.exists(path):
        started = any(os.path.exists(p) for p in working_paths(path))
        check(False, f"resume: {os.fspath(path)} does not exist" + (
            "; its run was stopped while creating it, before anything was saved: start the run again"
            if started else ""))
    try:
        with h5py.File(path, "r") as f:
            return {k: (v.decode() if isinstance(v, bytes) else v) for k, v in f.attrs.items()}
    except OSError as err:
        reason = " ".join(str(err).split())  # h5py's messages span lines
        raise InputError(f"resume: cannot read {os.fspath(path)} as a jaxmpm HDF5 file ({reason})") from None


def restart_command(info: dict, path) -> str:
    """What to do with a file that cannot be continued: the ``jaxmpm run`` command that writes it
    again (from its stored options), or a plain sentence for a file of the Python API."""
    if "command" not in info:
        return "run it again"
    options = json.loads(info["command"])
    words = ["jaxmpm", "run", str(options.get("scene", "SCENE"))]
    for key, value in options.items():
        if key not in ("scene", "scene_sha256"):  # a scene file's digest: not an option
            text = ",".join(map(str, value)) if isinstance(value, list) else str(value)  # --gravity GX,GY
            words += [f"--{key.replace('_', '-')}", text]
    return "start it again: `" + shlex.join(words + ["--out", os.fspath(path), "--force"]) + "`"


def resume(path, model=None, state=None, *, progress: bool = False, check_stability: bool = True,
           timings: dict | None = None, devices=None, rebalance_every: int | None = None):
    """Continue the run stored in ``path`` to its end, appending its frames to ``path``; returns
    the final state.

    ``model`` is the :class:`jaxmpm.scenes.Setup` that made the run (``jm.scene(...)``), or its
    :class:`Simulation` with ``state`` the run's initial state (for the state's structure; its
    values are not used).  Left out, the run is rebuilt from the options the command line
    stored in the file (``jaxmpm run``).  The file is one that :class:`jaxmpm.H5Writer` wrote
    during a run -- stopped by a signal or killed at any moment -- or one :func:`jaxmpm.save_h5`
    wrote with the run's schedule (``steps=``, ``save_every=``).  The run continues from the
    state saved last; frames saved after it (by a chunk whose state was not saved) are computed
    again, to the same bits.  A run that already reached its end returns its final state and
    runs nothing.

    Args:
        path: the HDF5 file of the run; the new frames are appended to it.
        model: the :class:`jaxmpm.scenes.Setup` that made the run, or its
            :class:`jaxmpm.Simulation` (then give ``state``); None (the default): rebuilt from the
            options ``jaxmpm run`` stored in the file.
        state: with a Simulation, the run's initial :class:`jaxmpm.State` (its structure only).
        progress: show a progress bar (default False).
        check_stability: raise :class:`jaxmpm.InstabilityError` at the first bad step (default
            True).
        timings: a dict to fill with the seconds spent compiling (``compile``) and running
            (``run``) and the ``steps`` run, as :func:`jaxmpm.run.driver.run` does; None (the
            default).
        devices: continue on several devices: N, the first N local devices (the grid cut into N
            slabs along x, :class:`jaxmpm.parallel.ShardedSimulation`), or a ShardedSimulation of
            the run's model; None (the default): one device.  Either way the file is the one the
            uninterrupted run writes (on one device or several: the sharded path equals one device
            to round-off), whichever wrote its first part.
        rebalance_every: with ``devices=N``, move the slabs with the particles every K steps
            (:class:`~jaxmpm.parallel.ShardedSimulation`'s ``rebalance_every``); None (the default):
            equal slabs.

    Returns:
        The final :class:`jaxmpm.State`.
    """
    from .io.hdf5 import H5Writer, read_state

    info = run_info(path)
    if model is None:
        check("command" in info, f"resume: {os.fspath(path)} was not written by `jaxmpm run`; pass the Setup "
                                 "(jm.scene(...)) or the Simulation and initial state that made it")
        from .scenes.command import setup_from_options

        model = setup_from_options(json.loads(info["command"]))
    if hasattr(model, "sim") and hasattr(model, "dt"):  # a scene's Setup
        sim, template, dt = model.sim, model.state, model.dt
    else:
        check(state is not None, "resume: with a Simulation, pass state= (the run's initial state)")
        sim, template, dt = model, state, float(info["dt"])
    _check_same_model(info, sim, dt, path)
    sharded = _sharded(sim, devices, rebalance_every, check_stability)
    again = restart_command(info, path)
    try:
        loaded, schedule = read_state(path, template, again=again)
    except InputError:  # a file that cannot be continued: a killed writer's working copies go all the same
        _remove_leftovers(path)
        raise
    if schedule["complete"]:  # nothing to run; a run killed after its last publication left its XDMF sidecar
        with H5Writer(path, sim, loaded, mode="a") as writer:  # behind and its working copies: both mended
            writer.write_sidecar()
        return loaded
    start, steps, save_every = schedule["start step"], schedule["steps"], schedule["save every"]
    with H5Writer(path, sim, loaded, mode="a") as writer:
        expected = (int(loaded.step) - start) // save_every + 1
        check(writer.frames >= expected, f"resume: {os.fspath(path)} holds {writer.frames} frames but its state "
                                         f"(step {int(loaded.step)}) comes after frame {expected}; the file was "
                                         f"modified after its run stopped; {again}")
        writer.truncate(expected)  # frames saved after the state: computed again
        if sharded is None:
            final, _ = sim.run(loaded, dt, steps, save_every, writer=writer, start_step=start, progress=progress,
                               check_stability=check_stability, timings=timings, donate=True)  # resume's own state
        else:
            final, _ = sharded.run(loaded, dt, steps, save_every, writer=writer, start_step=start,
                                   progress=progress, timings=timings)
    return final


#: root attributes that describe the run rather than its model (what resume does not compare)
_NOT_THE_MODEL = {"scene", "ppc", "dtype", "jaxmpm version", "scene parameters", "command", "fields", "damping varies",
                  "scene_file", "scene_sha256"}


def _check_same_model(info: dict, sim, dt, path) -> None:
    """An InputError unless ``sim`` and ``dt`` are the model the file's run had: its scheme, shape, update, grid,
    dt and every registered parameter, as the file's root attributes hold them (:func:`run_attributes`).  A
    file continued by another model would mix two runs under the first one's header."""
    from .io.hdf5 import run_attributes

    here = run_attributes(sim, dt)
    differ = []
    for key, value in here.items():
        if key in _NOT_THE_MODEL or key not in info:
            continue
        stored = info[key]
        if isinstance(value, str) or isinstance(stored, (str, bytes)):
            same = str(value) == (stored.decode() if isinstance(stored, bytes) else str(stored))
        else:
            a, b = np.asarray(value, dtype=float), np.asarray(stored, dtype=float)
            if b.size and np.isnan(b).all():  # the file does not say (a writer given no dt)
                continue
            # to float32's rounding: a model is another only by more (a file's float32 dt or parameter is the same)
            same = a.shape == b.shape and bool(np.allclose(a, b, rtol=1e-6, atol=0.0, equal_nan=True))
        if not same:
            differ.append(f"{key} = {_shown(value)} here, {_shown(stored)} in the file")
    check(not differ, f"resume: {os.fspath(path)} was written by another model: {'; '.join(differ)}; resume it with "
                      "the Setup (jm.scene options) or Simulation that made it, or start a new run")


def _shown(value) -> str:
    value = value.decode() if isinstance(value, bytes) else value
    if isinstance(value, str):
        return repr(value)
    a = np.asarray(value)
    return f"{float(a):.6g}" if a.ndim == 0 else np.array2string(a, precision=6, separator=", ")


def _remove_leftovers(path) -> None:
    """Remove a killed writer's working copies and lock file beside ``path``, unless a writer holds it."""
    from .io.hdf5 import _release_lock, _take_lock, remove, working_paths

    try:
        lock = _take_lock(os.fspath(path))
    except InputError:  # a live writer: its files are its own
        return
    remove(*working_paths(os.fspath(path)))
    _release_lock(lock, os.fspath(path))


def _sharded(sim, devices, rebalance_every, check_stability: bool):
    """The :class:`jaxmpm.parallel.ShardedSimulation` of :func:`resume`'s ``devices=`` (None: one
    device), checked before the file is touched."""
    from .parallel import ShardedSimulation, local_devices

    check(rebalance_every is None or (devices is not None and not isinstance(devices, ShardedSimulation)),
          f"resume: rebalance_every = {rebalance_every!r} moves the slabs of a run on several devices; pass "
          "devices=N with it (or build the ShardedSimulation with rebalance_every= and pass it as devices=)")
    if devices is None:
        return None
    check(check_stability, "resume: on several devices the run always stops at its first unstable step; leave "
                           "check_stability=True, or resume on one device (devices=None)")
    if isinstance(devices, ShardedSimulation):
        check(devices.sim is sim, "resume: devices= is a ShardedSimulation of another model; build it from the "
                                  "Simulation being resumed (ShardedSimulation(setup.sim, ...))")
        return devices
    return ShardedSimulation(sim, devices=local_devices(devices, "devices"), rebalance_every=rebalance_every)
