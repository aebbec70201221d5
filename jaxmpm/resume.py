"""Resuming an interrupted run from its HDF5 file (``jaxmpm resume FILE.h5`` on the command line).

A chunked run (:func:`jaxmpm.run.driver.run` with a writer) that stops on SIGINT/SIGTERM leaves every
finished frame in its file and the full state reached under ``/state`` (:meth:`H5Writer.write_state`);
:func:`resume` reads that state back bit for bit and runs the same compiled loop on to the end
of the run's schedule, appending to the same file.  On the CPU the result equals the
uninterrupted run bitwise (``tests/test_resume.py``).
"""

from __future__ import annotations

import json
import os

import h5py

from .core.errors import InputError, check


def run_info(path) -> dict:
    """The root attributes of a run's file that resuming needs (``dt``, ``command``, ``scene``)."""
    check(os.path.exists(path), f"resume: {os.fspath(path)} does not exist")
    try:
        with h5py.File(path, "r") as f:
            return {k: (v.decode() if isinstance(v, bytes) else v) for k, v in f.attrs.items()}
    except OSError as err:
        raise InputError(f"resume: cannot read {os.fspath(path)} as a jaxmpm HDF5 file ({err})") from None


def resume(path, model=None, state=None, *, progress: bool = False, check_stability: bool = True):
    """Continue the run stored in ``path`` to its end, appending its frames to ``path``; returns
    the final state.

    ``model`` is the :class:`jaxmpm.scenes.Setup` that made the run (``jm.scene(...)``), or its
    :class:`Simulation` with ``state`` the run's initial state (for the state's structure; its
    values are not used).  Left out, the run is rebuilt from the options the command line
    stored in the file (``jaxmpm run``).  A run that already reached its end returns its final
    state and runs nothing."""
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
    loaded, schedule = read_state(path, template)
    if schedule["complete"]:
        return loaded
    start, steps, save_every = schedule["start step"], schedule["steps"], schedule["save every"]
    with H5Writer(path, sim, loaded, mode="a") as writer:
        expected = (int(loaded.step) - start) // save_every + 1
        check(writer.frames == expected, f"resume: {os.fspath(path)} holds {writer.frames} frames but its state "
                                         f"(step {int(loaded.step)}) belongs after frame {expected}; the file "
                                         "was modified after the run stopped")
        final, _ = sim.run(loaded, dt, steps, save_every, writer=writer, start_step=start, progress=progress,
                           check_stability=check_stability)
    return final
