"""The sharded runner computes its particle buffers in place (JAX's buffer donation), as a one-device run
does (tests/test_donation.py): :meth:`ShardedSimulation.run` calls a rollout that deletes the buffers,
``valid`` and ``ids`` it is given -- the run's own, made by ``distribute`` or returned by the call before --
and never the model, the time step or the caller's state; the public ``rollout(steps)`` program keeps its
arguments.  The numbers are those of the run without donation (``sharded.DONATE = False``), bit for bit,
with fixed slabs and with slabs that move (``rebalance_every``), with frames and without.

The device count is fixed when JAX starts, so the runs are made in a process of their own with 2 forced CPU
devices (tests/parallel/donation_check.py prints its measurements as JSON; the assertions are here)."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from cases import forced_devices_flags

CHECK = Path(__file__).parent / "parallel" / "donation_check.py"
DEVICES = 2


@pytest.fixture(scope="module")
def out():
    env = dict(os.environ, XLA_FLAGS=forced_devices_flags(DEVICES), JAX_PLATFORMS="cpu")
    done = subprocess.run([sys.executable, str(CHECK)], env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


@pytest.mark.slow
@pytest.mark.parametrize("slabs", ["fixed", "rebalance"])
def test_a_run_in_place_is_the_run_without_donation(out, slabs):
    """Final states (one of a state whose v is its x itself) and frames, bit for bit; with rebalance_every
    the slabs moved between the rollouts, and the buffers distribute made again were computed in place."""
    row = out[slabs]
    assert row["same"] and row["leaves"] > 10, row
    assert row["rebalances"] == (1 if slabs == "rebalance" else 0), row


@pytest.mark.slow
def test_the_callers_state_and_time_step_are_kept(out):
    assert not out["state_deleted"] and not out["dt_deleted"]
    assert out["state_kept"]


@pytest.mark.slow
def test_the_run_aliases_its_buffers_and_the_public_rollout_nothing(out):
    """XLA's account is a device's: its share of the per-particle buffers, valid and ids, all aliased with
    the rollout's results; and called, the results lie in the arguments' memory (on a CPU, distribute's
    arrays are the devices' own, not views of the host's, which XLA would copy instead)."""
    assert out["devices"] == DEVICES
    assert out["donated_bytes_per_device"] * DEVICES == out["donated_bytes"]
    assert out["alias_bytes"] >= out["donated_bytes_per_device"] > 0
    assert out["public_alias_bytes"] == 0
    assert out["public_kept"] and out["in_place_deleted"] and out["in_place_same"]
    assert out["in_place_memory"]


@pytest.mark.slow
def test_buffers_that_share_an_array_are_donated_once(out):
    """XLA refuses to donate one buffer twice: an array two leaves hold is copied for the second."""
    assert out["shared_same"] and out["shared_deleted"]
