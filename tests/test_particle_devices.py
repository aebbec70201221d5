"""Steps whose particles are shared among the process's devices, each holding the whole grid
(jaxmpm.model.devices): P2G summed on each device and added across them (one all-reduce), the grid
solved on every device, G2P on each device's own particles.  003 §2.1: P2G is a sum over the
particles and G2P a map over them, so the shared step equals one device's to round-off, which the
checks below measure against the one-device run, float64.  The device count is fixed when JAX starts,
so those checks run in a process of their own with 2 forced CPU devices (tests/parallel/devices_check.py
prints its measurements as JSON; the assertions are here).  The options' errors run here."""

import json
import os
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import pytest
from cases import forced_devices_flags

import jaxmpm as jm

CHECK = Path(__file__).parent / "parallel" / "devices_check.py"


@pytest.mark.slow
def test_shared_particles_equal_one_device():
    env = dict(os.environ, XLA_FLAGS=forced_devices_flags(2), JAX_PLATFORMS="cpu")
    done = subprocess.run([sys.executable, str(CHECK)], env=env, capture_output=True, text=True, timeout=900)
    assert done.returncode == 0, done.stderr[-3000:]
    out = json.loads(done.stdout.strip().splitlines()[-1])
    assert out["devices"] == 2
    for name in ("mpm88_apic", "disks_flip"):  # runs with frames: APIC in chunks on each device, FLIP at once
        row = out[name]
        assert row["devices_used"] == 2 and row["sharded_output"] == 2, row
        assert row["x"] < 1e-13 and row["v"] < 1e-13 and row["F"] < 1e-13, row  # round-off: the sums' order
        assert row["frames"] == 5 and row["frames_x"] < 1e-13 and row["kinetic"] < 1e-13, row
        assert row["mass_diff"] == 0.0 and row["momentum_diff"] < 1e-15, row  # conserved as on one device
    assert "1024 particles a device, in chunks of 512" in out["mpm88_apic"]["reason"]
    assert "208 particles a device, at once" in out["disks_flip"]["reason"]
    # the scheme's dissipated energy, summed over the devices (APIC does not compute it: NaN on both)
    apic, flip = out["mpm88_apic"]["dissipated"], out["disks_flip"]["dissipated"]
    assert all(d != d for d in apic) and abs(flip[1] - flip[0]) < 1e-30
    # derivatives differentiate the whole step on one device: the same gradient, which a central difference
    # of the shared forward runs confirms (the bar, d/dE of its kinetic energy)
    grad = out["grad"]
    assert grad["loss_rel"] < 1e-14 and grad["grad_rel"] < 1e-14 and abs(grad["grad"]) > 0, grad
    assert grad["fd_rel"] < 1e-6, grad
    # jm.ensemble shards its members over the devices: each member's step stays on its device
    assert out["ensemble_rel"] < 1e-14
    # a vmapped rollout shares each member's particles
    assert out["ensemble_vmapped_rel"] < 1e-13
    # the table: below 60k particles one device, from it every device, each in chunks of 16k
    assert out["auto_small"] == 1 and out["auto_large"] == 2
    assert out["auto_large_reason"].endswith("2 devices: 32768 particles a device, in chunks of 16384")
    assert "2047 particles do not divide among 2 devices" in out["odd_reason"]
    assert out["prime_reason"].endswith("1031 particles a device, at once") and out["prime_x"] < 1e-15
    # a device's share that would not fit (a host of 4 MiB, shared by the 2 devices) steps in chunks that do
    assert out["memory_reason"].endswith(
        "chunks of at most 256 particles; that is an even share of the free memory among 2 CPU devices: 1024 "
        "particles a device, in chunks of 256"), out
    assert out["memory_x"] < 1e-13 and out["memory_grad"] < 1e-13
    assert out["memory_fits_reason"].endswith("1024 particles a device, at once"), out
    assert "jax_num_cpu_devices" in out["too_many"] and "particle_devices=1" in out["too_many"]


@pytest.mark.parametrize("bad", [0, -1, 1.5, True, "two"])
def test_particle_devices_is_checked(bad):
    setup = jm.scene("bar")
    with pytest.raises(jm.InputError, match="particle_devices"):
        setup.sim.with_particle_devices(bad)


def test_one_device_process_steps_on_one_device():
    setup = jm.scene("bar")
    info = jm.backend_info(setup.sim, setup.state)
    assert info["particle_devices"] == 1 and info["devices_reason"]
    if len(jax.devices()) > 1:
        pytest.skip("this process has several devices")
    # forcing more devices than the process has names the fix
    with pytest.raises(jm.InputError, match=r'jax_num_cpu_devices", 2\)'):
        setup.sim.with_particle_devices(2).step(setup.state, jnp.asarray(setup.dt))
    # a forced single device is the plain step, bit for bit
    one = setup.sim.with_particle_devices(1).step(setup.state, setup.dt)
    plain = setup.sim.step(setup.state, setup.dt)
    assert jnp.array_equal(one.x, plain.x) and jnp.array_equal(one.v, plain.v)


@pytest.mark.slow
def test_cli_starts_jax_with_cpu_devices(tmp_path):
    """``jaxmpm run --cpu-devices 2``: the disks at 103k particles share them among 2 CPU devices (the summary says
    so), and the file's final state equals the same command's on one device to round-off."""
    import h5py

    command = [sys.executable, "-m", "jaxmpm", "run", "disks", "--spacing", "0.0125", "--ppc", "8", "--t-end", "0.003",
               "--frames", "1", "--dt", "0.001", "--no-progress"]
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    runs = {}
    for devices in (1, 2):
        out = tmp_path / f"disks{devices}.h5"
        extra = ["--cpu-devices", "2"] if devices == 2 else []
        done = subprocess.run(command + extra + ["--out", str(out)], env=env, capture_output=True, text=True,
                              timeout=600)
        assert done.returncode == 0, done.stderr[-3000:]
        runs[devices] = done.stdout
        with h5py.File(out, "r") as f:
            runs[devices, "x"] = f["state/x"][()]
    assert "particle devices     2 CPU devices, each holding the whole grid" in runs[2]
    assert "particle devices" not in runs[1]
    x1, x2 = runs[1, "x"], runs[2, "x"]
    assert x1.shape == (102936, 2) and abs(x2 - x1).max() < 1e-13 * abs(x1).max()


def test_cli_cpu_devices_is_checked(tmp_path, capsys):
    from cases import run_cli

    jnp.ones(1).block_until_ready()  # JAX has computed in this process: its device count is fixed
    out = str(tmp_path / "bar.h5")
    assert run_cli(["run", "bar", "--cpu-devices", "0", "--out", out]) == 2
    assert "--cpu-devices = 0 must be a positive integer" in capsys.readouterr().err
    assert run_cli(["run", "bar", "--cpu-devices", "2", "--out", out]) == 2
    err = capsys.readouterr().err
    assert "--cpu-devices 2: JAX has already computed in this process" in err and "new `jaxmpm` process" in err
    assert not os.path.exists(out)


def test_device_table_rows(monkeypatch):
    """DEVICE_TABLE: 2D on the CPU from 60k particles, chunks of 16k on each device; one device below it, in 3D, with
    one device in the process, and for the CPU policy forced onto a GPU's devices (the rows were measured on CPUs)."""
    from jaxmpm.transfer.backend import choose_devices

    f64, f32 = jnp.dtype("float64"), jnp.dtype("float32")
    assert choose_devices("cpu", 2, 65536, f64, 2)[:2] == (2, 16384)
    assert choose_devices("cpu", 2, 131072, f32, 4)[:2] == (4, 16384)
    assert choose_devices("cpu", 2, 32768, f64, 2)[:2] == (1, 0)
    assert choose_devices("cpu", 3, 131072, f32, 2)[:2] == (1, 0)
    devices, _, why = choose_devices("cpu", 2, 131072, f64, 1)
    assert devices == 1 and why.startswith("one device: the process has one")
    assert choose_devices("gpu", 2, 131072, f32, 2)[:2] == (1, 0)
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    devices, _, why = choose_devices("cpu", 2, 131072, f64, 2)
    assert devices == 1 and why == "one device: the CPU policy's row, on GPU devices"
