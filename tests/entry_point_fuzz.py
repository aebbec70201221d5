"""Every public entry point given each of a list of bad values: an InputError (or a file error for a path that
does not exist), or a result; never another exception, and never a runaway (the process's address space is capped
at 12 GiB: a negative frames_per_chunk once ran chunks of negative frames until memory ran out).  Run by
tests/test_entry_point_fuzz.py in a process of its own; prints one line per entry point and exception kind that
escaped, and nothing else on stdout."""

import os
import resource
import sys
import tempfile

resource.setrlimit(resource.RLIMIT_AS, (12 * 2**30, 12 * 2**30))

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import matplotlib  # noqa: E402
import numpy as np  # noqa: E402

jax.config.update("jax_enable_x64", True)
matplotlib.use("Agg")

import jaxmpm as jm  # noqa: E402

BAD = [None, -1, 0, 1.5, float("nan"), float("inf"), "x", [], [1, 2], np.zeros((0,)), np.zeros((2, 2)), (1,), {},
       True]


def entry_points(sim, state, dt, folder, h5):
    """(name, function of one value) for each argument fuzzed."""

    def loss(p):
        return jnp.sum(jm.set_params(sim, **p).run(state, dt, 4, 2)[1].kinetic)

    out = os.path.join(folder, "out")
    return [
        ("run dt", lambda v: sim.run(state, v, 4, 2)),
        ("run steps", lambda v: sim.run(state, dt, v, 2)),
        ("run save_every", lambda v: sim.run(state, dt, 4, v)),
        ("run fields", lambda v: sim.run(state, dt, 4, 2, fields=v)),
        ("run frames_per_chunk", lambda v: sim.run(state, dt, 4, 2, frames_per_chunk=v, progress=True)),
        ("run memory", lambda v: sim.run(state, dt, 4, 2, memory=v)),
        ("run checkpoint", lambda v: sim.run(state, dt, 4, 2, checkpoint=v)),
        ("rollout frames", lambda v: sim.rollout(state, dt, v)),
        ("ensemble steps", lambda v: jm.ensemble(sim, state, dt, v, 2, params={"E": [1.0, 2.0]}, progress=False)),
        ("ensemble params", lambda v: jm.ensemble(sim, state, dt, 4, 2, params={"E": v}, progress=False)),
        ("ensemble params dict", lambda v: jm.ensemble(sim, state, dt, 4, 2, params=v, progress=False)),
        ("ensemble states", lambda v: jm.ensemble(sim, state, dt, 4, 2, states=v, progress=False)),
        ("ensemble devices", lambda v: jm.ensemble(sim, state, dt, 4, 2, params={"E": [1.0, 2.0]}, devices=v,
                                                   progress=False)),
        ("ensemble dt", lambda v: jm.ensemble(sim, state, v, 4, 2, params={"E": [1.0, 2.0]}, progress=False)),
        ("set_params", lambda v: jm.set_params(sim, E=v)),
        ("get_params", lambda v: jm.get_params(sim, v)),
        ("reuse_host_memory", lambda v: jm.reuse_host_memory(v) if not isinstance(v, bool) else None),
        ("backend_info members", lambda v: jm.backend_info(sim, state, members=v)),
        ("gradient_schedule steps", lambda v: jm.gradient_schedule(sim, state, dt, v, 2)),
        ("gradient_schedule memory", lambda v: jm.gradient_schedule(sim, state, dt, 4, 2, memory=v)),
        ("stable_dt", lambda v: jm.stable_dt(sim, state, v)),
        ("with_chunks", lambda v: sim.with_chunks(v)),
        ("calibrate init", lambda v: jm.calibrate(loss, v, steps=1, progress=False)),
        ("calibrate steps", lambda v: jm.calibrate(loss, {"E": 100.0}, steps=v, progress=False)),
        ("calibrate tol", lambda v: jm.calibrate(loss, {"E": 100.0}, steps=1, tol=v, progress=False)),
        ("calibrate bounds", lambda v: jm.calibrate(loss, {"E": 100.0}, steps=1, bounds=v, progress=False)),
        ("calibrate free", lambda v: jm.calibrate(loss, {"E": 100.0}, steps=1, free=v, progress=False)),
        ("calibrate loss", lambda v: jm.calibrate(v, {"E": 100.0}, steps=1, progress=False)),
        ("H5Writer path", lambda v: jm.H5Writer(v, sim, state, dt)),
        ("H5Writer dt", lambda v: jm.H5Writer(out + ".h5", sim, state, v, overwrite=True)),
        ("H5Writer mode", lambda v: jm.H5Writer(out + ".h5", sim, state, dt, mode=v, overwrite=True)),
        ("H5Writer fields", lambda v: jm.H5Writer(out + ".h5", sim, state, dt, fields=v, overwrite=True)),
        ("resume path", lambda v: jm.resume(v)),
        ("load_h5", lambda v: jm.load_h5(v)),
        ("fill ppc", lambda v: jm.fill(sim.grid, jm.Box((2.0,), (6.0,)), ppc=v)),
        ("fill density", lambda v: jm.fill(sim.grid, jm.Box((2.0,), (6.0,)), density=v)),
        ("fill velocity", lambda v: jm.fill(sim.grid, jm.Box((2.0,), (6.0,)), velocity=v)),
        ("fill region", lambda v: jm.fill(sim.grid, v)),
        ("Grid lower", lambda v: jm.Grid(v, (1.0,), (4,))),
        ("Grid cells", lambda v: jm.Grid((0.0,), (1.0,), v)),
        ("plot frames", lambda v: jm.plot_frames(h5, frames=v, out=out + ".png", overwrite=True)),
        ("plot field", lambda v: jm.plot_frames(h5, field=v, out=out + ".png", overwrite=True)),
        ("plot clim", lambda v: jm.plot_frames(h5, clim=v, out=out + ".png", overwrite=True)),
        ("plot figsize", lambda v: jm.plot_frames(h5, figsize=v, out=out + ".png", overwrite=True)),
        ("animate every", lambda v: jm.animate(h5, out + ".gif", every=v, overwrite=True)),
        ("compilation_cache max_bytes", lambda v: jm.compilation_cache(os.path.join(folder, "c"), max_bytes=v)),
        ("compiler_options policy", lambda v: jm.compiler_options(v)),
        ("sim.init", lambda v: sim.init(v)),
        ("sim.diagnostics", lambda v: sim.diagnostics(v)),
        ("with_backend", lambda v: sim.with_backend(v)),
        ("with_sorting", lambda v: sim.with_sorting(v)),
        ("sim.stable_dt cfl", lambda v: sim.stable_dt(state, v)),
        ("with_adjoint", lambda v: sim.with_adjoint(v)),
        ("with_particle_devices", lambda v: sim.with_particle_devices(v)),
        ("in_precision", lambda v: sim.in_precision(v)),
        ("scene", lambda v: jm.scene(v)),
    ]


def main() -> None:
    setup = jm.scene("bar", cells=8)
    sim, state, dt = setup.sim, setup.state, setup.dt
    folder = tempfile.mkdtemp()
    h5 = os.path.join(folder, "run.h5")
    jm.save_h5(h5, sim, sim.run(state, dt, 4, 2)[1], state, dt)
    escaped = {}
    for name, call in entry_points(sim, state, dt, folder, h5):
        for value in BAD:
            try:
                call(value)
            except (jm.InputError, jm.InstabilityError, FileNotFoundError, FileExistsError):
                pass
            except Exception as err:  # noqa: BLE001  (what the fuzz looks for)
                escaped.setdefault((name, type(err).__name__), (value, str(err).split("\n")[0][:150]))
    jm.compilation_cache(False)  # the fuzz pointed it at its own folder
    for (name, kind), (value, message) in sorted(escaped.items()):
        print(f"{name} [{value!r}]: {kind}: {message}")
    sys.stdout.flush()


if __name__ == "__main__":
    main()
