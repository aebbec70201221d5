"""Run by tests/test_parallel_slabs.py in a process of its own with 2 forced CPU devices: a sharded
run that saves frames (ShardedSimulation.run with save_every), writes HDF5 and is resumed, and
``jaxmpm run disks --devices 2``, each against the same run on one device, float64, with particles
crossing the slab face both ways.  Prints one JSON line.

1. frames: every frame's positions and velocities (and energies, stress) of the sharded run
   against ``sim.run``'s;
2. HDF5: the file a sharded run writes against the file a one-device run writes, dataset by
   dataset and frame by frame (``/state`` included);
3. resume: a sharded run killed after its second publication, continued by ``jm.resume`` on one
   device and on 2 (``devices=2``), and a one-device run killed the same way continued on 2, against
   the uninterrupted one-device run (the file and the final state);
4. the CLI: ``jaxmpm run disks --devices 2`` (also with ``--rebalance-every 20``) against the same command
   without ``--devices``; a one-device ``jaxmpm run disks`` killed after its second frame, continued by
   ``jaxmpm resume FILE --devices 2``."""

import contextlib
import io
import json
import os
import shutil
import tempfile

import jax

jax.config.update("jax_enable_x64", True)
import h5py  # noqa: E402
import numpy as np  # noqa: E402

import jaxmpm as jm  # noqa: E402
from jaxmpm.cli import main  # noqa: E402
from jaxmpm.parallel import ShardedSimulation  # noqa: E402
from jaxmpm.run import driver  # noqa: E402

os.environ["JAXMPM_CHUNK_SECONDS"] = "1e-9"  # every frame published at once (the chunked runs too)
# every publication saves the state, however long the writing takes on a loaded machine (the files
# killed below keep the state of their last publication: the same step every time)
driver._STATE_SECONDS = float("inf")
STEPS, SAVE_EVERY = 240, 30  # the disks meet after about 160 steps and rebound across the slab face
out = {"devices": len(jax.devices())}
folder = tempfile.mkdtemp(prefix="sharded-io-")


def rel_err(a, b, scale=None) -> float:
    """max |a - b| over ``scale`` (default max |b|); integers: 0 if equal, else inf."""
    a, b = np.asarray(a), np.asarray(b)
    if a.shape != b.shape:
        return float("inf")
    if not np.issubdtype(b.dtype, np.floating):
        return 0.0 if np.array_equal(a, b) else float("inf")
    scale = (np.max(np.abs(b)) if b.size else 0.0) if scale is None else scale
    with np.errstate(invalid="ignore"):
        both_nan = np.isnan(a) & np.isnan(b)
    diff = np.where(both_nan, 0.0, np.abs(a - b))
    return float(np.max(diff) / scale) if scale > 0 else float(np.max(diff, initial=0.0))


def scales(data) -> dict:
    """The physical scale of the quantities that are zero but for round-off in the colliding disks
    (their total momentum, FLIP's dissipated energy; and, in the CLI's run below, which ends at t = 0.06
    before they meet, the stress and strain energy of F = I + round-off, about 5e-15 and 1e-33): the
    largest energy, that energy over the bodies' volume for the stress (or its largest value if larger),
    the total mass times the largest speed (times the largest distance from the origin for the angular
    momentum)."""
    mass, speed = float(np.sum(data["particles/mass"])), float(np.max(np.abs(data["particles/v"])))
    energy = float(np.max(data["energy/kinetic"] + data["energy/strain"]))
    reach = float(np.max(np.abs(data["particles/x"])))
    volume0 = np.asarray(data["particles/volume0"])  # (N,): written once, the reference volumes
    volume = float(np.sum(volume0 if volume0.ndim == 1 else volume0[0]))
    stress = max(energy / volume, float(np.max(np.abs(data["particles/stress"]))))
    return {"energy/dissipated": energy, "energy/strain": energy, "particles/stress": stress,
            "momentum/linear": mass * speed, "momentum/angular": mass * speed * reach, "state/dissipated": energy}


def file_err(path, reference) -> dict:
    """The worst relative difference of every dataset of two files (``/state`` included) and
    whether they hold the same datasets, each frame by frame (the largest over frames)."""
    def datasets(p):
        with h5py.File(p, "r") as f:
            found = {}
            f.visititems(lambda name, obj: found.__setitem__(name, obj[()]) if isinstance(obj, h5py.Dataset) else None)
            return found, {k: (v.decode() if isinstance(v, bytes) else v) for k, v in f["state"].attrs.items()}

    (mine, my_schedule), (theirs, their_schedule) = datasets(path), datasets(reference)
    scale = scales(theirs)
    errs = {name: rel_err(mine[name], theirs[name], scale.get(name)) for name in theirs if name in mine}
    frames = int(theirs["time"].shape[0])
    return {"same_datasets": sorted(mine) == sorted(theirs), "frames": int(mine["time"].shape[0]),
            "reference_frames": frames, "worst": max(errs.values()), "worst_dataset": max(errs, key=errs.get),
            "x_per_frame": [rel_err(mine["particles/x"][t], theirs["particles/x"][t]) for t in range(frames)],
            "same_schedule": {k: int(v) for k, v in my_schedule.items()}
            == {k: int(v) for k, v in their_schedule.items()}}


# 1. frames --------------------------------------------------------------------------------------
setup = jm.scene("disks", speed=1.0)
sim, state, dt = setup.sim, setup.state, setup.dt
one_final, one = sim.run(state, dt, STEPS, SAVE_EVERY, fields=("stress",))
sharded = ShardedSimulation(sim)
many_final, many = sharded.run(state, dt, STEPS, SAVE_EVERY, fields=("stress",))
out["frames"] = {
    "count": len(many), "reference_count": len(one), "migrated": sharded.stats["migrated"],
    "ended_elsewhere": int(np.sum(np.asarray(sharded.owner(many_final.x)) != np.asarray(sharded.owner(state.x)))),
    "time_err": rel_err(many.time, one.time),
    "x_per_frame": [rel_err(many.x[t], one.x[t]) for t in range(len(one))],
    "v_per_frame": [rel_err(many.v[t], one.v[t]) for t in range(len(one))],
    "stress_err": rel_err(many.fields["stress"], one.fields["stress"]),
    "kinetic_err": rel_err(many.kinetic, one.kinetic),
    "momentum_err": rel_err(many.momentum, one.momentum, float(np.sum(state.mass) * np.max(np.abs(one.v)))),
    "final_x_err": rel_err(many_final.x, one_final.x), "final_step": int(many_final.step),
    "no_frames_x_err": rel_err(sharded.run(state, dt, STEPS).x, one_final.x),  # run(state, dt, steps) as before
}

# a time step far above the CFL limit: the same InstabilityError as one device (step, cause), the
# frames' rollout program reused with the new dt
errors = []
for model in (lambda: sim.run(state, 0.03, SAVE_EVERY, SAVE_EVERY), lambda: sharded.run(state, 0.03, SAVE_EVERY,
                                                                                          SAVE_EVERY)):
    try:
        model()
        errors.append(None)
    except jm.InstabilityError as error:
        errors.append([error.step, error.cause.split(" (particle")[0], error.time])
out["frames"]["unstable"] = errors

# 2. HDF5 ----------------------------------------------------------------------------------------
paths = {name: os.path.join(folder, f"{name}.h5") for name in ("one", "many", "killed", "killed_many", "killed_one",
                                                                "cli1", "cli2", "cli2b", "cli_killed")}
with jm.H5Writer(paths["one"], sim, state, dt=dt, scene="disks", fields=("stress",)) as writer:
    sim.run(state, dt, STEPS, SAVE_EVERY, writer=writer)
with jm.H5Writer(paths["many"], sim, state, dt=dt, scene="disks", fields=("stress",)) as writer:
    final, nothing = ShardedSimulation(sim).run(state, dt, STEPS, SAVE_EVERY, writer=writer)
out["hdf5"] = file_err(paths["many"], paths["one"]) | {"returned_history": nothing is not None}


# 3. a sharded run killed after its second publication, resumed on one device -----------------------
class Killed(Exception):
    pass


KILLED_AT = 7  # the frames of steps 0 to 150 (and the state of step 150) kept: after the disks met

class DyingWriter(jm.H5Writer):
    """A writer whose process is 'killed' when the run hands it its third chunk of frames."""

    appended = 0

    def append(self, history):
        self.appended += 1
        if self.appended == KILLED_AT:
            raise Killed
        super().append(history)


def killed_run(path, run) -> dict:
    """``run(writer)`` into ``path`` with a writer 'killed' at its KILLED_AT-th chunk: what the file kept."""
    try:
        with DyingWriter(path, sim, state, dt=dt, scene="disks", fields=("stress",)) as writer:
            run(writer)
        killed = False
    except Killed:
        killed = True
    with h5py.File(path, "r") as f:
        return {"killed": killed, "frames": int(f["time"].shape[0]), "state_step": int(f["state/step"][()])}


def resumed_err(path, resumed) -> dict:
    return file_err(path, paths["one"]) | {"final_x_err": rel_err(resumed.x, one_final.x),
                                           "final_v_err": rel_err(resumed.v, one_final.v),
                                           "final_step": int(resumed.step)}


kept = killed_run(paths["killed"], lambda w: ShardedSimulation(sim).run(state, dt, STEPS, SAVE_EVERY, writer=w))
killed = kept.pop("killed")
shutil.copy(paths["killed"], paths["killed_many"])
resumed = jm.resume(paths["killed"], setup)  # on one device: the file's state is the user's particles in order
out["resume"] = resumed_err(paths["killed"], resumed) | {"killed": killed, "kept": kept}
# the same file continued on 2 devices; and a one-device run's file continued on 2 devices
out["resume_devices"] = resumed_err(paths["killed_many"], jm.resume(paths["killed_many"], setup, devices=2))
kept_one = killed_run(paths["killed_one"], lambda w: sim.run(state, dt, STEPS, SAVE_EVERY, writer=w))
out["resume_devices_of_one"] = resumed_err(paths["killed_one"], jm.resume(paths["killed_one"], setup, devices=2)) | {
    "kept": kept_one}

# 4. the CLI -------------------------------------------------------------------------------------
command = ["run", "disks", "--t-end", "0.06", "--frames", "3", "--no-progress"]
printed = io.StringIO()
with contextlib.redirect_stdout(printed):
    codes = [main(command + ["--devices", "2", "--out", paths["cli2"]]), main(command + ["--out", paths["cli1"]]),
             main(command + ["--devices", "2", "--rebalance-every", "20", "--out", paths["cli2b"]])]
out["cli"] = file_err(paths["cli2"], paths["cli1"]) | {"codes": codes, "summary_devices": [
    line for line in printed.getvalue().splitlines() if line.startswith("devices")]}
out["cli"]["rebalanced"] = file_err(paths["cli2b"], paths["cli1"])  # slabs moving every 20 steps
with h5py.File(paths["cli2"], "r") as f:
    out["cli"]["stored_command"] = json.loads(f.attrs["command"])
errors = io.StringIO()
with contextlib.redirect_stderr(errors):
    try:
        main(command + ["--devices", "3", "--out", os.path.join(folder, "three.h5")])
        out["cli"]["three_devices"] = None
    except SystemExit as stop:
        out["cli"]["three_devices"] = [stop.code, errors.getvalue().strip()]
out["cli"]["three_devices_file"] = os.path.exists(os.path.join(folder, "three.h5"))
# a one-device `jaxmpm run` killed as its writer takes the third frame, then `jaxmpm resume --devices 2`
saved = jm.H5Writer.append


def dying_append(self, history):
    dying_append.calls += 1
    if dying_append.calls == 3:
        raise Killed
    saved(self, history)


dying_append.calls = 0
jm.H5Writer.append = dying_append
try:
    with contextlib.redirect_stdout(io.StringIO()):
        main(command + ["--out", paths["cli_killed"]])
except Killed:
    pass
finally:
    jm.H5Writer.append = saved
with h5py.File(paths["cli_killed"], "r") as f:
    kept = {"frames": int(f["time"].shape[0]), "state_step": int(f["state/step"][()])}
printed = io.StringIO()
with contextlib.redirect_stdout(printed):
    code = main(["resume", paths["cli_killed"], "--devices", "2", "--no-progress"])
out["cli_resume"] = file_err(paths["cli_killed"], paths["cli1"]) | {"code": code, "kept": kept, "summary_devices": [
    line for line in printed.getvalue().splitlines() if line.startswith("devices")]}
# `jaxmpm resume --devices 2` of the finished file: no step left to run (its summary read a count of none, KeyError)
printed = io.StringIO()
with contextlib.redirect_stdout(printed):
    code = main(["resume", paths["cli_killed"], "--devices", "2", "--no-progress"])
out["cli_resume_finished"] = {"code": code, "summary_devices": [
    line for line in printed.getvalue().splitlines() if line.startswith("devices")]}
shutil.rmtree(folder, ignore_errors=True)
print(json.dumps(out))
