"""The memory a step counts on when it decides whether its temporaries fit (issue 32 item 7;
jaxmpm.run.memory.step_memory, jaxmpm.transfer.backend.chunks_to_fit): the members of an ensemble
stepped at once (vmapped) share the device's free memory evenly, so that B members' temporaries --
B times one member's -- fit where one member's would.  Small mpm88 scenes (16^2 grid, 512 particles,
float64), a device of 8 MiB (JAXMPM_MEMORY_BYTES) and chunks of at least 128 particles: one member's
step fits (684 KiB of temporaries against a quarter of 8 MiB), eight members' do not.  The
particles-over-CPU-devices share is checked in tests/parallel/devices_check.py."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxmpm as jm
from jaxmpm.model import simulation
from jaxmpm.run.memory import members_at_once, step_memory
from jaxmpm.transfer import backend

FREE = 8 * 2**20
MEMBERS = 8
STEPS = 10


@pytest.fixture
def small_device(monkeypatch):
    """A device of ``FREE`` bytes, chunks of at least 128 particles, and the memory each step counted on."""
    monkeypatch.setattr(backend, "SMALLEST_CHUNK", 128)
    monkeypatch.setenv("JAXMPM_MEMORY_BYTES", str(FREE))
    seen = []

    def spy(devices=1):
        seen.append(step_memory(devices))
        return seen[-1]

    monkeypatch.setattr(simulation, "step_memory", spy)
    return seen


def _scene():
    setup = jm.scene("mpm88", n_particles=512, n_grid=16)
    return setup.sim, setup.state, setup.dt


def test_members_stepped_at_once_share_the_memory(small_device):
    """One member's step fits the device; as one of eight stepped at once it counts on an eighth of the
    memory and goes in chunks, and backend_info says why.  Nested counts multiply; leaving restores."""
    sim, state, _ = _scene()
    assert jm.backend_info(sim, state)["chunk_particles"] == 0
    assert small_device[-1] == (FREE, "")
    with members_at_once(MEMBERS):
        info = jm.backend_info(sim, state)
        with members_at_once(2):
            assert step_memory() == (FREE // 16, "; that is an even share of the free memory among 16 members "
                                                 "stepped at once")
    assert info["chunk_particles"] == 128, info
    assert info["chunk_reason"] == (
        "the whole step's temporaries (about 684.0 KiB) would take more than 25% of the device's free memory "
        "(1.0 MiB): chunks of at most 128 particles; that is an even share of the free memory among 8 members "
        "stepped at once: 4 chunks of 128 particles")
    assert info["derivative_chunk_particles"] == 128 and info["derivative_chunk_reason"] == info["chunk_reason"]
    assert step_memory() == (FREE, "")
    with members_at_once(1):
        assert step_memory() == (FREE, "")


def test_backend_info_reports_members_stepped_at_once(small_device):
    """``jm.backend_info(sim, state, members=B)`` reports the choice of each of B members stepped at once (an
    ensemble's vmapped members), for a single state and an ensemble's batched one alike; ``members`` must be a
    count."""
    sim, state, _ = _scene()
    with members_at_once(MEMBERS):
        inside = jm.backend_info(sim, state)
    batched = jax.tree_util.tree_map(lambda a: jnp.stack([a] * 2), state)
    assert jm.backend_info(sim, state, members=MEMBERS) == inside
    assert jm.backend_info(sim, batched, members=MEMBERS) == inside
    assert jm.backend_info(sim, batched)["chunk_particles"] == 0  # one member alone: it fits
    for bad in (0, 2.0, True):
        with pytest.raises(jm.InputError, match="backend_info: members"):
            jm.backend_info(sim, state, members=bad)


def test_the_tables_chunks_shrink_to_fit_the_memory():
    """On the CPU the backend tables step 65536 particles of mpm88 in float64 in chunks of 16384 (CHUNK_TABLE) and
    take its derivatives in chunks of 8192 (DERIVATIVE_CHUNK_TABLE).  Where the whole step would not fit the
    device (160 MiB: about 85.5 MiB of temporaries against a quarter) chunks of 16384 fit, and both stay; on a
    device smaller still (40 MiB) both take chunks of 4096; where it fits (400 MiB) nothing is said of memory."""
    setup = jm.scene("mpm88", n_particles=65536, dtype="f64")
    rows = {}
    for free in (400, 160, 40):
        with pytest.MonkeyPatch.context() as patch:
            patch.setenv("JAXMPM_MEMORY_BYTES", str(free * 2**20))
            info = jm.backend_info(setup.sim, setup.state)
        rows[free] = [info[key] for key in ("chunk_particles", "chunk_reason", "derivative_chunk_particles",
                                            "derivative_chunk_reason")]
    assert [(rows[free][0], rows[free][2]) for free in (400, 160, 40)] == [(16384, 8192), (16384, 8192),
                                                                           (4096, 4096)], rows
    assert "memory" not in rows[400][1] + rows[400][3], rows
    assert rows[400][3].startswith("CPU, 2D float64, from 24k particles: derivatives in chunks of 8k")
    assert rows[160][1].endswith("(160.0 MiB): chunks of at most 16384 particles: 4 chunks of 16384 particles")
    assert rows[160][3].endswith("(160.0 MiB): chunks of at most 16384 particles: 8 chunks of 8192 particles")
    for reason in (rows[40][1], rows[40][3]):
        assert reason.startswith("the whole step's temporaries (about 85.5 MiB) would take more than 25% of the "
                                 "device's free memory (40.0 MiB)") and reason.endswith("16 chunks of 4096 particles")


def test_a_vmapped_ensemble_steps_each_member_in_chunks_that_fit(small_device):
    """jm.ensemble's members vmapped together: each member's step counts on its share of the memory (all
    members at once: an eighth; ``chunk=2``: a half) and steps in the chunks that fit, bit for bit the
    ensemble of those chunks forced; members one after another ("sequential") count on all of it.  The
    results equal the whole steps' to round-off (003 §2.1: P2G sums over the particles)."""
    sim, state, dt = _scene()
    E = sim.material.E * jnp.linspace(0.9, 1.1, MEMBERS)

    def ensemble(model, **how):
        return jm.ensemble(model, state, dt, STEPS, STEPS, params={"E": E}, progress=False, **how)

    fitted = ensemble(sim, strategy="vmap")
    assert set(small_device) == {(FREE // MEMBERS, "; that is an even share of the free memory among 8 members "
                                                   "stepped at once")}
    forced = ensemble(sim.with_chunks(128), strategy="vmap")
    whole = ensemble(sim.with_chunks(0), strategy="vmap")
    for got, chunked, at_once in zip(jax.tree_util.tree_leaves(fitted), jax.tree_util.tree_leaves(forced),
                                     jax.tree_util.tree_leaves(whole)):
        np.testing.assert_array_equal(got, chunked)
        if jnp.issubdtype(got.dtype, jnp.floating):
            np.testing.assert_allclose(got, at_once, rtol=0, atol=1e-12 * max(1e-300, float(jnp.max(jnp.abs(
                jnp.where(jnp.isfinite(at_once), at_once, 0))))))
    for how, free in (({"strategy": "vmap", "chunk": 2}, FREE // 2), ({"strategy": "sequential"}, FREE)):
        small_device.clear()
        jax.eval_shape(lambda: ensemble(sim, **how))  # traced, not compiled: the memory each step counted on
        assert {seen[0] for seen in small_device} == {free}, how


@pytest.mark.slow
def test_a_gradient_through_steps_too_large_for_the_memory_goes_in_chunks(small_device, monkeypatch):
    """Where the whole step would not fit, its derivatives go in the same chunks, each chunk's P2G and G2P
    recomputed in the reverse pass (chunks.step_in_chunks).  A step's gradient then holds a fraction of
    the temporaries the whole step's derivatives take (mpm88, 4096 particles, a device of 4 MiB: 8 chunks of
    512; on the development machine 1.07 against 6.1 states), and a rollout's gradient equals the whole steps'
    to round-off and a central difference (the disks colliding at speed 1, 416 particles in 4 chunks of 104 on
    a device of 1 MiB, d/dE of the kinetic energy after 300 steps, float64)."""
    monkeypatch.setenv("JAXMPM_MEMORY_BYTES", str(4 * 2**20))
    setup = jm.scene("mpm88", n_particles=4096, n_grid=32)
    sim, state, dt = setup.sim, setup.state, setup.dt
    info = jm.backend_info(sim, state)
    assert (info["chunk_particles"], info["derivative_chunk_particles"]) == (512, 512), info

    def temporaries(model):  # XLA's temporary bytes of one step's gradient with respect to the velocities
        def kinetic(v):
            new = model.step(eqx.tree_at(lambda s: s.v, state, v), dt)
            return jnp.sum(new.mass[:, None] * new.v ** 2)

        return jax.jit(jax.grad(kinetic)).lower(state.v).compile().memory_analysis().temp_size_in_bytes

    in_chunks, whole_derivatives = temporaries(sim), temporaries(sim.with_derivative_chunks(0))
    assert in_chunks < 0.3 * whole_derivatives, (in_chunks, whole_derivatives)

    monkeypatch.setenv("JAXMPM_MEMORY_BYTES", str(2**20))
    setup = jm.scene("disks", speed=1.0)
    sim, state, dt = setup.sim, setup.state, setup.dt
    assert jm.backend_info(sim, state)["derivative_chunk_reason"].endswith("4 chunks of 104 particles")
    E0 = float(sim.material.E)

    def kinetic(model, e):
        final = jm.set_params(model, E=E0 * (1 + e)).run(state, dt, 300, progress=False)[0]
        return jnp.sum(final.mass[:, None] * final.v ** 2)

    gradient = jax.jit(jax.grad(lambda e: kinetic(sim, e)))(0.0)
    whole = sim.with_chunks(0)
    expected = jax.jit(jax.grad(lambda e: kinetic(whole, e)))(0.0)
    forward = jax.jit(lambda e: kinetic(whole, e))
    central = (forward(1e-5) - forward(-1e-5)) / 2e-5
    assert abs(float(expected)) > 1.0
    np.testing.assert_allclose(gradient, expected, rtol=1e-12)
    np.testing.assert_allclose(gradient, central, rtol=1e-6)
