"""One simulation on several devices (jaxmpm.parallel, issue 33), on forced CPU devices
(``XLA_FLAGS=--xla_force_host_platform_device_count=N`` in a process of its own: the device count is
fixed when JAX starts).  The scripts in tests/parallel/ print their measurements as JSON; the
assertions are here.  Against one device, float64: the slab decomposition's P2G (one halo exchange),
G2P and their gradients; particle migration in fixed buffers; and whole sharded runs of a scene
whose particles cross the slab face both ways, under APIC, XPIC(3) with contact, and FLIP's
gradient with respect to E."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

HERE = Path(__file__).parent / "parallel"


def run_check(script: str, devices: int, *args) -> dict:
    env = dict(os.environ, XLA_FLAGS=f"--xla_force_host_platform_device_count={devices}", SLAB_DEVICES=str(devices),
               JAX_PLATFORMS="cpu")
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
        assert row["x_rel_err"] < 1e-13 and row["F_rel_err"] < 1e-11 and row["v_rel_err"] < 1e-10, row
        assert row["mass_diff"] == 0.0 and row["momentum_diff"] < 1e-14, row
    # the scheme's dissipated energy, summed over the devices (APIC reports it as not computed: NaN)
    apic, xpic = out["disks_apic"], out["disks_xpic:3+contact"]
    assert np.isnan(apic["dissipated"]) and np.isnan(apic["dissipated_rel_err"])
    assert xpic["dissipated"] != 0.0 and xpic["dissipated_rel_err"] < 1e-10, xpic
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
def test_two_processes_give_the_one_device_answer():
    """2 processes x 2 CPU devices on localhost (jax.distributed, gloo): one sharded XPIC(3) run over
    the 4 global devices, particles crossing slab faces, equal to one device on both processes."""
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    env.pop("XLA_FLAGS", None)
    procs = [subprocess.Popen([sys.executable, str(HERE / "multihost_check.py"), str(pid), str(port)], env=env,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for pid in (0, 1)]
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


def test_bad_input_names_the_option():
    import jaxmpm as jm
    from jaxmpm.parallel import ShardedSimulation, Slabs

    with pytest.raises(jm.InputError, match="Collider not supported on several devices yet"):
        ShardedSimulation(jm.scene("incline").sim)
    grid = jm.Grid(lower=(0.0, 0.0), upper=(1.0, 1.0), cells=(10, 4))
    with pytest.raises(jm.InputError, match="do not split into 4 equal slabs"):
        Slabs(grid, 4, 2)
    with pytest.raises(jm.InputError, match="not wider than twice the halo"):
        Slabs(grid, 2, 3)
    setup = jm.scene("disks")
    with pytest.raises(jm.InputError, match="raise capacity"):
        ShardedSimulation(setup.sim, capacity=10).distribute(setup.state)
