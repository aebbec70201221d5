"""One simulation on several devices (jaxmpm.parallel, issue 33), on forced CPU devices
(``XLA_FLAGS=--xla_force_host_platform_device_count=N`` in a process of its own: the device count is
fixed when JAX starts).  The scripts in tests/parallel/ print their measurements as JSON; the
assertions are here.  Against one device, float64: the slab decomposition's P2G (one halo exchange),
G2P and their gradients; particle migration in fixed buffers; whole sharded runs of a scene
whose particles cross the slab face both ways, under APIC, XPIC(3) with contact, and FLIP's
gradient with respect to E; colliders, tractions, reactions and symmetry planes; and such a run's
frames, HDF5 file, resume and ``jaxmpm run --devices``."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from cases import forced_devices_flags

HERE = Path(__file__).parent / "parallel"


def run_check(script: str, devices: int, *args) -> dict:
    env = dict(os.environ, XLA_FLAGS=forced_devices_flags(devices), SLAB_DEVICES=str(devices), JAX_PLATFORMS="cpu")
    done = subprocess.run([sys.executable, str(HERE / script), *map(str, args)], env=env, capture_output=True,
                          text=True, timeout=900)
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


@pytest.mark.slow
@pytest.mark.parametrize("devices, dim, shape", [(4, 2, "quadratic"), (4, 3, "cubic"), (8, 2, "linear")])
def test_slab_transfers_equal_one_device(devices, dim, shape):
    out = run_check("slabs_check.py", devices, dim, shape)
    assert out["p2g_rel_err"] < 1e-14  # every plane of every window: the global sums
    assert out["g2p_abs_err"] < 1e-14
    assert out["grad_rel_err"] < 1e-13  # d/d(x, v) through the exchange
    # halo-sized communication: neighbour permutes of the 2 H + 1 shared planes, nothing else
    assert out["collectives"] and all(c.endswith("collective-permute") for c in out["collectives"])
    for c in out["collectives"]:
        dims = c[c.index("[") + 1:c.index("]")].split(",")
        assert int(dims[1]) * int(dims[2]) == out["overlap_elements"] < out["grid_nodes"]
    # migration: particles crossed, each is held once, by its owner, unchanged
    assert out["migrated"] > 0 and out["ids_kept"] and out["on_owner"] and out["positions_kept"]
    assert out["overflow"] == 0
    # one exchange slot per face cannot carry the movers: counted, and no particle is lost
    assert out["small_overflow"] > 0 and out["small_ids_unique"]


@pytest.mark.slow
def test_sharded_runs_equal_one_device():
    out = run_check("sharded_check.py", 2, 250)
    for name in ("disks_apic", "disks_xpic:3+contact"):
        row = out[name]
        assert row["migrated"] > 50 and row["ended_elsewhere"] > 50, row  # the face crossed both ways
        # docs/scaling.md: APIC 4e-15 in v, XPIC(3) with contact 1.2e-12 (1.6e-14 in x), measured 2026-11-29
        v_bound = 1e-13 if name == "disks_apic" else 5e-12
        assert row["x_rel_err"] < 1e-13 and row["F_rel_err"] < 1e-12 and row["v_rel_err"] < v_bound, row
        assert row["mass_diff"] == 0.0 and row["momentum_diff"] < 1e-14, row
    # the scheme's dissipated energy, summed over the devices (APIC reports it as not computed: NaN)
    apic, xpic = out["disks_apic"], out["disks_xpic:3+contact"]
    assert np.isnan(apic["dissipated"]) and np.isnan(apic["dissipated_rel_err"])
    assert xpic["dissipated"] != 0.0 and xpic["dissipated_rel_err"] < 1e-13, xpic  # 7e-15 measured
    error = out["overflow_error"]
    assert "did not fit: raise capacity" in error and "exchange (now 1 per step" in error
    grad = out["gradient"]
    assert abs(grad["one"]) > 1e-3 and grad["rel_err"] < 1e-12 and grad["loss_rel_err"] < 1e-13
    # the rollout's communication, by shape: the shared planes of a P2G column (fields, 2 H + 1 planes,
    # nodes per plane, columns), a migration buffer (exchange slots, per-particle values) or a
    # scalar count; nothing of the grid's or the buffers' full size
    for op, shape, size in out["collectives"]:
        dims = [int(d) for d in shape[shape.index("[") + 1:shape.index("]")].split(",") if d]
        if op == "all-reduce":
            assert dims == [], (op, shape)
        else:
            assert op == "collective-permute", (op, shape)
            halo = len(dims) >= 3 and dims[1] * dims[2] == out["overlap_nodes"]
            assert halo or dims[0] == out["exchange"], (op, shape)


@pytest.mark.slow
def test_colliders_tractions_reactions_mirrors_and_transport_equal_one_device():
    """The terms that read the nodes' positions or numbers, on 4 devices against one, float64: two
    colliders (a box sweeping across a slab face, an inclined half-space with friction) and the fixed
    floor's reaction; two tractions (one on a face spanning every slab) and a point force; a symmetry
    plane normal to y; heat with held and flux nodes, and heat and diffusion across a contact
    interface; a symmetry plane normal to x and held ends mirrored across x (ghost nodes in the edge
    slabs' windows).  Equal slabs, and slabs that move (tests/parallel/terms_check.py)."""
    out = run_check("terms_check.py", 4)
    for name in ("impact", "beam", "symmetric", "heated", "heated_contact", "symmetric_x", "held_mirrored"):
        row = out[name]
        assert row["finite"] and row["moved"] > 5e-3, row
        scale = max([abs(np.asarray(t)).max() for t in row["totals"].values()], default=0.0)
        for slabs in ("equal", "moving") if name in ("impact", "symmetric", "heated") else ("equal",):
            many = row[slabs]
            assert many["x_abs_err"] < 1e-13 and many["v_abs_err"] < 1e-12 * many["v_scale"], (name, slabs, many)
            assert many["fields_abs_err"] < 1e-11, (name, slabs, many)  # fields of up to 100 (temperatures)
            assert many["totals_abs_err"] <= 1e-14 * scale, (name, slabs, many)
            assert slabs == "equal" or many["rebalances"] > 0
        if name != "beam":
            assert row["equal"]["migrated"] > 0  # the bodies cross slab faces
    totals = out["impact"]["totals"]
    # the solids and the floor carry the disk: non-zero forces, the reaction's summed over the devices
    assert totals["box_force_x"] > 100 and abs(totals["ramp_force_y"]) > 1 and totals["reaction"][1] > 100, totals
    # the held band heats the block; heat and moisture cross the contact interface
    assert out["heated"]["transported"]["temperature"] > 10
    assert out["heated_contact"]["transported"]["temperature"] > 1
    assert out["heated_contact"]["transported"]["concentration"] > 0.01
    # the strip's held ends (mirrored) cool it; a ghost band a slab face would cut is refused, naming the width
    assert out["held_mirrored"]["transported"]["temperature"] > 0.05
    assert "the first slab must span at least 15 cells (now 8 with 4 devices)" in out["mirror_x_error"]
    assert "slabs that move may be as narrow as 5 cells" in out["mirror_x_moving_error"]
    disks = out["disks_default_buffers"]  # default buffers carry the planes of a lattice across a face
    assert disks["step"] == 100 and disks["migrated"] > 100 and disks["x_abs_err"] < 1e-13, disks
    assert disks["exchange"] == 40 and disks["capacity"] == 136, disks  # 1.25 x 32 a column; 13 had stopped it


@pytest.mark.slow
def test_sharded_frames_hdf5_resume_and_cli_equal_one_device():
    """2 devices, disks colliding across the slab face: frames, the HDF5 file, its resume on one
    device and on 2, ``jaxmpm run --devices 2`` and ``jaxmpm resume --devices 2`` against one device,
    float64 (tests/parallel/sharded_io_check.py)."""
    out = run_check("sharded_io_check.py", 2)
    frames = out["frames"]
    assert frames["count"] == frames["reference_count"] == 9 and frames["final_step"] == 240
    assert frames["migrated"] > 50 and frames["ended_elsewhere"] > 50, frames  # the face crossed both ways
    assert frames["time_err"] == 0.0
    assert max(frames["x_per_frame"]) < 1e-14 and max(frames["v_per_frame"]) < 1e-13, frames  # every frame
    assert frames["stress_err"] < 1e-13 and frames["kinetic_err"] < 1e-14 and frames["momentum_err"] < 1e-14
    assert frames["final_x_err"] < 1e-14 and frames["no_frames_x_err"] < 1e-14  # run(state, dt, steps) as before
    one, many = frames["unstable"]  # dt far above the CFL limit: the same step and cause as one device
    assert one is not None and many == one, frames["unstable"]
    # the file a sharded run writes: the one-device file's datasets, frame by frame, and its /state
    hdf5 = out["hdf5"]
    assert hdf5["same_datasets"] and hdf5["same_schedule"] and hdf5["frames"] == hdf5["reference_frames"] == 9
    assert hdf5["worst"] < 1e-13 and max(hdf5["x_per_frame"]) < 1e-14, hdf5
    assert not hdf5["returned_history"]  # the writer holds the frames, as with sim.run
    # killed after 6 frames (the state of step 150 saved with them), then jm.resume on one device:
    # the uninterrupted one-device run's file and final state
    resume = out["resume"]
    assert resume["killed"] and resume["kept"] == {"frames": 6, "state_step": 150}
    assert resume["same_datasets"] and resume["same_schedule"] and resume["frames"] == 9
    assert resume["worst"] < 1e-13 and resume["final_step"] == 240, resume
    assert resume["final_x_err"] < 1e-14 and resume["final_v_err"] < 1e-13, resume
    # jm.resume(..., devices=2): the sharded file continued on 2 devices, and a one-device run's file killed
    # between two frames (its state at step 179, frames to 150) continued on 2: the same file and state
    for again in (out["resume_devices"], out["resume_devices_of_one"]):
        assert again["same_datasets"] and again["same_schedule"] and again["frames"] == 9, again
        assert again["worst"] < 1e-13 and max(again["x_per_frame"]) < 1e-14 and again["final_step"] == 240, again
        assert again["final_x_err"] < 1e-14 and again["final_v_err"] < 1e-13, again
    assert out["resume_devices_of_one"]["kept"] == {"killed": True, "frames": 6, "state_step": 179}
    # jaxmpm run disks --devices 2: the file of the same command on one device; --devices is a run option
    cli = out["cli"]
    assert cli["codes"] == [0, 0, 0] and cli["same_datasets"] and cli["same_schedule"] and cli["frames"] == 4
    assert cli["worst"] < 1e-13 and max(cli["x_per_frame"]) < 1e-14, cli
    assert cli["summary_devices"] and cli["summary_devices"][0].split()[1] == "2"
    rebalanced = cli["rebalanced"]  # --rebalance-every 20: the same file, the slabs moving
    assert rebalanced["same_datasets"] and rebalanced["worst"] < 1e-13, rebalanced
    assert "rebalance" not in cli["summary_devices"][0]
    assert int(cli["summary_devices"][-1].split(" rebalance(s)")[0].split()[-1]) >= 1, cli["summary_devices"]
    assert "devices" not in cli["stored_command"]  # jaxmpm resume continues the file on one device (or --devices N)
    code, message = cli["three_devices"]  # more devices than the process has: the fix, and no file
    assert code == 2 and message.startswith("jaxmpm: error: --devices 3: this process has 2 cpu devices; set "
                                            "XLA_FLAGS=--xla_force_host_platform_device_count=3")
    assert not cli["three_devices_file"]
    # a one-device `jaxmpm run disks` killed after 2 frames, then `jaxmpm resume FILE --devices 2`: the file of
    # the uninterrupted one-device command
    again = out["cli_resume"]
    assert again["code"] == 0 and again["kept"]["frames"] == 2 and again["frames"] == 4, again
    assert again["same_datasets"] and again["same_schedule"] and again["worst"] < 1e-13, again
    assert again["summary_devices"] and again["summary_devices"][0].split()[1] == "2"
    # resumed again, finished: nothing to run, and the summary counts no moves (it had raised KeyError 'migrated')
    finished = out["cli_resume_finished"]
    assert finished["code"] == 0 and finished["summary_devices"] == ["devices              2 (slabs along x), 0 "
                                                                     "particle moves between them"], finished


@pytest.mark.slow
def test_two_processes_give_the_one_device_answer(tmp_path):
    """2 processes x 2 CPU devices on localhost (jax.distributed, gloo): one sharded XPIC(3) run over
    the 4 global devices, particles crossing slab faces, equal to one device on both processes; its
    frames in one HDF5 file written by process 0; and jm.ensemble's members spread over both processes'
    devices, gathered on each, bit for bit those of one device."""
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    env = dict(os.environ, JAX_PLATFORMS="cpu")  # the script adds its 2 devices to XLA_FLAGS
    path = tmp_path / "two_processes.h5"
    procs = [subprocess.Popen([sys.executable, str(HERE / "multihost_check.py"), str(pid), str(port), str(path)],
                              env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for pid in (0, 1)]
    outs = []
    for proc in procs:
        stdout, stderr = proc.communicate(timeout=600)
        assert proc.returncode == 0, stderr[-3000:]
        outs.append(json.loads(stdout.strip().splitlines()[-1]))
    for out in outs:
        assert out["global_devices"] == 4 and out["local_devices"] == 2
        assert out["migrated"] > 100 and out["mass_diff"] == 0.0
        assert out["x_rel_err"] < 1e-13 and out["v_rel_err"] < 1e-12
    assert outs[0]["x_checksum"] == outs[1]["x_checksum"]  # both processes hold the same final state
    assert not outs[0]["history"] and not outs[1]["history"]  # process 0's file holds the frames
    for out in outs:  # jm.ensemble across the two processes: every member on both, as on one device
        assert out["ensemble_members"] == 4 and out["ensemble_spread"]
        assert out["ensemble_x_err"] == 0.0 and out["ensemble_history_err"] == 0.0
    assert outs[0]["file_frames"] == 3 and outs[0]["file_x_rel_err"] < 1e-13 and outs[0]["file_state_step"] == 200
    assert path.exists() and not list(tmp_path.glob("*.tmp"))  # one file, its writer closed


@pytest.mark.slow
def test_cli_devices_refused_with_the_fix(tmp_path, capsys):
    """``jaxmpm run --devices N``: more devices than this process has, or bad options, exit 2 naming
    the fix, before the output file is made; ``jaxmpm resume --devices N`` and ``jm.resume(...,
    devices=N)`` likewise, leaving the file as it was."""
    import jax
    from cases import run_cli

    import jaxmpm as jm
    from jaxmpm.parallel import local_devices

    have = len(jax.local_devices())
    path = tmp_path / "x.h5"
    assert run_cli(["run", "disks", "--devices", str(have + 1), "--out", str(path)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"jaxmpm: error: --devices {have + 1}: this process has {have} cpu device")
    assert f"set XLA_FLAGS=--xla_force_host_platform_device_count={have + 1}" in err and "\n" not in err
    assert run_cli(["run", "disks", "--devices", "0", "--out", str(path)]) == 2
    assert "--devices = 0 must be a positive integer" in capsys.readouterr().err
    assert run_cli(["run", "disks", "--rebalance-every", "10", "--out", str(path)]) == 2
    assert "--rebalance-every 10 moves the slabs of a run on several devices; add --devices N" in (
        capsys.readouterr().err)
    assert run_cli(["run", "disks", "--devices", "1", "--rebalance-every", "0", "--out", str(path)]) == 2
    assert "--rebalance-every 0 must be a positive integer" in capsys.readouterr().err  # the option, not the keyword
    for option, what in (("--capacity", "sizes the particle buffers"), ("--exchange", "sizes the exchange buffers")):
        assert run_cli(["run", "disks", option, "50", "--out", str(path)]) == 2
        assert f"{option} 50 {what} of a run on several devices; add --devices N" in capsys.readouterr().err
        assert run_cli(["run", "disks", "--devices", "1", option, "0", "--out", str(path)]) == 2
        assert f"{option} 0 must be a positive integer" in capsys.readouterr().err
    assert not path.exists()
    assert local_devices(1) == jax.local_devices()[:1]
    # `jaxmpm resume FILE --devices N` and jm.resume(..., devices=N): the same checks, before the file is touched
    import h5py

    done = tmp_path / "bar.h5"  # what resume reads first: the command that made the run
    with h5py.File(done, "w") as f:
        f.attrs["command"] = '{"scene": "bar"}'
    before = done.read_bytes()
    assert run_cli(["resume", str(done), "--devices", str(have + 1)]) == 2
    assert capsys.readouterr().err.strip().startswith(f"jaxmpm: error: --devices {have + 1}: this process has {have}")
    assert run_cli(["resume", str(done), "--rebalance-every", "10"]) == 2
    assert "--rebalance-every 10 moves the slabs of a run on several devices; add --devices N" in (
        capsys.readouterr().err)
    setup = jm.scene("bar")
    with pytest.raises(jm.InputError, match=f"devices {have + 1}: this process has {have}"):
        jm.resume(done, setup, devices=have + 1)
    with pytest.raises(jm.InputError, match="rebalance_every = 5 moves the slabs of a run on several devices; pass "
                                            "devices=N"):
        jm.resume(done, setup, rebalance_every=5)
    with pytest.raises(jm.InputError, match="on several devices the run always stops at its first unstable step"):
        jm.resume(done, setup, devices=1, check_stability=False)
    assert done.read_bytes() == before


def test_bad_input_names_the_option():
    import jax

    import jaxmpm as jm
    from jaxmpm.parallel import ShardedSimulation, Slabs

    class Glue(jm.Term):  # a term of one's own: it may index the global grid
        pass

    with pytest.raises(jm.InputError, match="Glue not supported on several devices yet"):
        ShardedSimulation(jm.scene("disks").sim.with_term(Glue()))
    grid = jm.Grid(lower=(0.0, 0.0), upper=(1.0, 1.0), cells=(10, 4))
    with pytest.raises(jm.InputError, match=r"do not split into 3 equal slabs; .* or let the slabs differ: "
                                            r"ShardedSimulation\(..., rebalance_every=K\)"):
        Slabs(grid, 3, 1)
    Slabs(grid, 3, 1, max_cells=4)  # as they may, moving
    with pytest.raises(jm.InputError, match=r"the grid's 10 cells along x hold at most 1 slab\(s\) of 2 H \+ 1 = 7 "
                                            r"cells \(the narrowest, halo H = 3 planes\), not 2; run on one device, or "
                                            r"use a grid of at least 14 cells along x"):
        Slabs(grid, 2, 3)
    # the advice leads somewhere: 10 cells in 4 slabs of at least 5 cells cannot be, moving or not (the
    # equal slabs' error had said to let them move, and the moving slabs' to raise max_cells)
    for moving in (None, 10):
        with pytest.raises(jm.InputError, match=r"hold at most 2 slab\(s\) of 2 H \+ 1 = 5 cells .* not 4; use at "
                                                r"most 2 devices, or a grid of at least 20 cells along x"):
            Slabs(grid, 4, 2, max_cells=moving)
    # equal slabs must also split the cells evenly: 11 cells hold two slabs of 5, but only moving ones
    odd = jm.Grid(lower=(0.0, 0.0), upper=(1.0, 1.0), cells=(11, 4))
    with pytest.raises(jm.InputError, match=r"not 3; use 1 device\(s\) \(equal slabs split the 11 cells evenly\), "
                                            r"or up to 2 with slabs that move \(--rebalance-every K\)"):
        Slabs(odd, 3, 2)
    Slabs(odd, 2, 2, max_cells=6)
    setup = jm.scene("disks")
    with pytest.raises(jm.InputError, match="raise capacity"):
        ShardedSimulation(setup.sim, capacity=10).distribute(setup.state)
    sharded = ShardedSimulation(setup.sim, devices=jax.devices()[:1])
    with pytest.raises(jm.InputError, match="belong to a run that saves frames; pass save_every="):
        sharded.run(setup.state, setup.dt, 10, progress=True)
    with pytest.raises(jm.InputError, match="save_every = 3 must be a positive integer dividing steps = 10"):
        sharded.run(setup.state, setup.dt, 10, 3)


@pytest.mark.slow
def test_slabs_move_with_a_collapsing_column():
    """3 devices, float64 (tests/parallel/balance_check.py): P2G and G2P on deliberately unequal
    slabs; a column collapse whose slabs move with its particles every K = 200 steps, and once early
    when the spreading flow fills a buffer, against one device; its particles and mass every step;
    the same run with frames; the error when no boundaries fit; and disks on 28 cells along x, which
    equal slabs cannot split over 3 devices, run on slabs that differ."""
    out = run_check("balance_check.py", 3, 900, 200, 40)
    unequal = out["unequal"]  # slabs of 5, 7 and 28 cells, every one holding particles
    assert len(set(np.diff(unequal["bounds"]))) == 3 and min(unequal["particles_per_slab"]) > 50, unequal
    assert unequal["p2g_rel_err"] < 1e-14 and unequal["g2p_rel_err"] < 1e-14, unequal
    n, run = out["particles"], out["run"]
    # every step, the devices held exactly the N particles, and their mass; no particle was lost
    assert run["census_particles"] == [n, n] and run["mass_exact"], run
    assert all(abs(m - run["total_mass"]) <= 1e-14 * run["total_mass"] for m in run["census_mass"]), run
    assert run["steps_done"] == run["final_step"] == out["steps"]
    # the slabs moved: scheduled every K steps, and once before a step where a buffer would have overflowed
    steps = [step for step, _ in run["bounds"]]
    assert run["rebalances"] == len(steps) - 1 >= 4
    assert any(step % out["every"] for step in steps), steps
    faces = [tuple(bounds) for _, bounds in run["bounds"]]
    assert faces[-1] != faces[0] and faces[-1][1] > faces[0][1], faces  # the face follows the spreading column
    # fixed equal slabs hold the whole column in the first slab: they need a buffer for every particle
    assert out["fixed_capacity_needed"] == n and run["capacity"] < 0.6 * n, (out["fixed_capacity_needed"], run)
    # the one-device run, to round-off
    assert run["x_rel_err"] < 1e-13 and run["v_rel_err"] < 1e-12 and run["F_rel_err"] < 1e-12, run
    assert run["momentum_diff"] < 1e-13, run
    frames = out["frames"]  # with frames: the slabs move between frames, every frame as on one device
    assert frames["count"] == frames["reference_count"] == 3 and frames["final_step"] == 400
    assert frames["rebalances"] == 2 and frames["census_particles"] == [n, n], frames
    assert max(frames["x_per_frame"]) < 1e-13, frames
    uneven = out["uneven"]  # 28 cells on 3 devices: only slabs that differ split them
    assert uneven["cells"] % 3 and "rebalance_every=K" in out["uneven_fixed_error"]
    assert all(len(set(np.diff(b))) > 1 for _, b in uneven["bounds"]), uneven["bounds"]
    assert uneven["migrated"] > 0 and uneven["x_rel_err"] < 1e-14 and uneven["v_rel_err"] < 1e-13, uneven
    error = out["no_fit_error"]  # one particle too few slots for the most even slabs: stops before a step
    assert error.startswith("ShardedSimulation: at step 0 the most even slabs") and "raise capacity" in error, error


def test_balanced_bounds_equalise_the_counts():
    """The boundary choice: the fewest particles in the fullest slab (against every allowed cut),
    widths between 2 H + 1 and max_cells, each face nearest its share of the particles."""
    import itertools

    import jaxmpm as jm
    from jaxmpm.parallel import Slabs

    rng = np.random.default_rng(3)
    grid = jm.Grid(lower=(0.0, 0.0), upper=(2.4, 1.0), cells=(24, 4))
    slabs = Slabs(grid, 3, 1, max_cells=12)  # slabs of 3 to 12 cells
    allowed = [(0, a, b, 24) for a, b in itertools.combinations(range(1, 24), 2)
               if all(3 <= w <= 12 for w in np.diff((0, a, b, 24)))]
    for trial in range(30):
        counts = rng.integers(0, 40, 24) * (rng.random(24) < 0.6)
        if trial == 0:
            counts = np.zeros(24, int)
            counts[2:6] = 100  # a column in two cells of slab widths: the narrowest slabs share it
        bounds = slabs.balanced_bounds(counts)
        slabs.check_bounds(bounds)
        widths = np.diff(bounds)
        assert bounds[0] == 0 and bounds[-1] == 24 and widths.min() >= 3 and widths.max() <= 12
        fullest = max(counts[a:b].sum() for a, b in zip(bounds[:-1], bounds[1:]))
        best = min(max(counts[a:b].sum() for a, b in zip(cut[:-1], cut[1:])) for cut in allowed)
        assert fullest == best, (counts, bounds)
    assert slabs.balanced_bounds(np.zeros(24, int)).tolist() == [0, 8, 16, 24]  # no particles: equal slabs
    assert slabs.balanced_bounds(np.ones(24, int)).tolist() == [0, 8, 16, 24]  # evenly spread: equal slabs
    assert slabs.equal_bounds().tolist() == [0, 8, 16, 24]
    assert Slabs(grid, 3, 1).window_planes == 8 + 3 and slabs.window_planes == 12 + 3
    with pytest.raises(jm.InputError, match=r"max_cells = 2 must be an integer from 2 H \+ 1 = 3"):
        Slabs(grid, 3, 1, max_cells=2)
    with pytest.raises(jm.InputError, match="3 slabs of at most max_cells = 7 cells cannot cover the grid's 24 "
                                            "cells along x; raise max_cells to at least 8"):
        Slabs(grid, 3, 1, max_cells=7)
    with pytest.raises(jm.InputError, match=r"bounds \[0, 2, 12, 24\] must run from 0 to 24 with 3 slabs of 3 to"):
        slabs.check_bounds([0, 2, 12, 24])


def test_rebalancing_options_checked():
    import jax

    import jaxmpm as jm
    from jaxmpm.parallel import ShardedSimulation

    setup = jm.scene("disks")
    one = jax.devices()[:1]
    with pytest.raises(jm.InputError, match="rebalance_every = 0 must be a positive integer"):
        ShardedSimulation(setup.sim, devices=one, rebalance_every=0)
    with pytest.raises(jm.InputError, match="max_cells bounds the slabs that move; pass rebalance_every="):
        ShardedSimulation(setup.sim, devices=one, max_cells=10)
    sharded = ShardedSimulation(setup.sim, devices=one, rebalance_every=5)
    buffers, valid, ids = sharded.distribute(setup.state)
    assert sharded.bounds.tolist() == [0, setup.sim.grid.cells[0]]
    with pytest.raises(jm.InputError, match="slabs that move need their boundaries"):
        sharded.rollout(5)(setup.sim, buffers, valid, ids, setup.dt)
