"""A run computes its states in place of the state it starts from (JAX's buffer donation; issue 32 item 7):
``sim.run(state, ..., donate=True)`` deletes ``state`` and holds one state fewer, a chunked run (a writer or
progress) works on one state, a copy of the caller's unless it is donated; the numbers are those of a run
without donation, bit for bit; inside ``jit`` or ``grad`` ``donate`` does nothing."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from cases import small_simulation
from test_inputs import SPEED, body_state, first_step_off_grid

import jaxmpm as jm
from jaxmpm.run import driver
from jaxmpm.run.memory import tree_bytes

DT = 0.3  # below the stable limit of small_simulation's grid at SPEED (test_inputs.py)


def fresh(sim, lower=6.0, upper=10.0, velocity=SPEED):
    return body_state(sim, lower, upper, velocity=velocity)


def deleted(state) -> bool:
    return any(leaf.is_deleted() for leaf in jax.tree_util.tree_leaves(state) if isinstance(leaf, jax.Array))


def assert_same(a, b):
    for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


@pytest.fixture(scope="module")
def sim():
    return small_simulation()


@pytest.fixture(scope="module")
def reference(sim):
    """The run without donation: 4 frames of 1 step (test_inputs.py's schedule, compiled once)."""
    return sim.run(fresh(sim), jnp.asarray(DT), 4, 1)


def test_a_donated_state_is_deleted_and_the_run_is_the_same(sim, reference):
    state = fresh(sim)
    final, history = sim.run(state, jnp.asarray(DT), 4, 1, donate=True)
    assert deleted(state)
    assert_same((final, history), reference)
    with pytest.raises(RuntimeError, match="deleted"):
        np.asarray(state.x)


def test_a_state_whose_leaves_share_an_array_is_donated(sim):
    """XLA donates a buffer once: a state that holds one array in two leaves (v set to x itself) runs donated
    as it runs kept, the array copied for its second leaf."""
    state = fresh(sim)
    shared = eqx.tree_at(lambda s: s.v, state, state.x)
    dt = jnp.asarray(0.01)
    kept = sim.run(shared, dt, 4, 1)
    assert_same(sim.run(shared, dt, 4, 1, donate=True), kept)
    assert deleted(shared)


def test_without_donation_the_callers_state_stays(sim, reference, tmp_path):
    """The default: the caller's state is untouched, by the whole run and by a chunked one (whose working
    state is a copy); the chunked run's final state and file equal the whole run's."""
    state = fresh(sim)
    final, _ = sim.run(state, jnp.asarray(DT), 4, 1)
    assert not deleted(state)
    with jm.H5Writer(tmp_path / "kept.h5", sim, state, dt=DT) as writer:
        chunked, _ = sim.run(state, jnp.asarray(DT), 4, 1, writer=writer, frames_per_chunk=2)
    assert not deleted(state)
    assert_same(chunked, reference[0])
    assert_same(final, reference[0])
    np.testing.assert_array_equal(jm.load_h5(tmp_path / "kept.h5")["particles/x"], np.asarray(reference[1].x))


def test_a_donated_chunked_run_writes_what_a_kept_one_does(sim, reference, tmp_path):
    """With a writer and donate=True the caller's state goes into the run; every chunk is computed in place
    of the one before; the file and the final state are the run's without donation."""
    state = fresh(sim)
    with jm.H5Writer(tmp_path / "donated.h5", sim, state, dt=DT) as writer:
        final, _ = sim.run(state, jnp.asarray(DT), 4, 1, writer=writer, frames_per_chunk=2, donate=True)
    assert deleted(state)
    assert_same(final, reference[0])
    np.testing.assert_array_equal(jm.load_h5(tmp_path / "donated.h5")["particles/x"], np.asarray(reference[1].x))


def test_a_state_from_init_is_computed_in_place(sim):
    """sim.init's arrays (jm.fill's, made on the host) lie in memory of XLA's own: a donated run's final state is
    computed in the memory of its initial one.  (``jax.device_put`` of a NumPy array keeps the NumPy memory about
    two times in three on the CPU, which XLA does not compute in place of: jaxmpm.core.device.to_device.)"""
    for _ in range(8):  # whether device_put kept the host memory depended on its alignment
        state = fresh(sim)
        before = [leaf.unsafe_buffer_pointer() for leaf in jax.tree_util.tree_leaves(state)]
        final, _ = sim.run(state, jnp.asarray(DT), 4, 1, donate=True)
        assert [leaf.unsafe_buffer_pointer() for leaf in jax.tree_util.tree_leaves(final)] == before


def test_every_chunk_of_a_donated_run_with_a_writer_is_computed_in_place(sim, reference, tmp_path, monkeypatch):
    """Each chunk's state lies in the memory of the state before it.  (Until 2026-11-29 the file's log kept the
    last state written as views of its device buffers on the CPU, so JAX computed every chunk after the first
    into new memory: two states held.)"""
    places = []
    advance = driver._advance_in_place

    def spy(args, state):
        before = [leaf.unsafe_buffer_pointer() for leaf in jax.tree_util.tree_leaves(state)]
        out = advance(args, state)
        places.append(before == [leaf.unsafe_buffer_pointer() for leaf in jax.tree_util.tree_leaves(out[0])])
        return out

    monkeypatch.setattr(driver, "_advance_in_place", spy)
    state = fresh(sim)
    with jm.H5Writer(tmp_path / "in_place.h5", sim, state, dt=DT) as writer:
        final, _ = sim.run(state, jnp.asarray(DT), 4, 1, writer=writer, frames_per_chunk=1, donate=True)
    assert places == [True] * 5  # the compiling call without steps, then four chunks of one frame
    assert_same(final, reference[0])


@pytest.mark.parametrize("chunked", [False, True])
def test_an_unstable_donated_run_names_its_step(sim, tmp_path, chunked):
    """The failure report reads the start's step and time, which a donated state no longer holds: they are
    read before the run (test_inputs.py: the body leaves the grid at step 13 from [8.5, 12.5))."""
    state = fresh(sim, 8.5, 12.5)
    expected = first_step_off_grid(state.x, SPEED, DT, 16)
    assert expected == 13
    if chunked:
        with jm.H5Writer(tmp_path / "unstable.h5", sim, state, dt=DT) as writer:
            with pytest.raises(jm.ParticlesLeftGrid) as info:
                sim.run(state, jnp.asarray(DT), 16, 1, writer=writer, frames_per_chunk=4, donate=True)
        assert jm.load_h5(tmp_path / "unstable.h5")["particles/x"].shape[0] == expected  # frames of steps 0 .. 12
    else:
        with pytest.raises(jm.ParticlesLeftGrid) as info:
            sim.run(state, jnp.asarray(DT), 16, 1, donate=True)
    assert info.value.step == expected and info.value.time == pytest.approx(expected * DT, rel=1e-12)
    assert deleted(state)


def in_place_memory(sim, state, dt, steps_per_frame: int):
    """XLA's memory account of the program that computes a run's state in place of ``state`` (lowered and
    compiled, never called): the loop of a whole run in memory (frames and steps runtime counts, a buffer of 2
    frames) and of a chunked one alike (driver._advance_in_place)."""
    none = driver.Failure(*(jnp.int32(i) for i in (-1, 0, -1)))
    counts = jnp.int32(1), jnp.int32(steps_per_frame)
    loop = driver._advance_in_place.lower((sim, none, dt, *counts, 2, True, True, (), counts[1]), state).compile()
    return loop.compiled.memory_analysis()  # equinox's Compiled wraps jax's


def test_the_program_computes_the_state_in_place(sim):
    """XLA aliases the final state with the initial one: the program's aliased bytes are the state's."""
    state = fresh(sim)
    memory = in_place_memory(sim, state, jnp.asarray(DT), 1)
    assert memory.alias_size_in_bytes >= tree_bytes(state)
    assert not deleted(state)  # lowered and compiled, never called


def test_no_copy_of_the_state_in_a_run_in_chunks():
    """Where the state dominates (mpm88, 4096 particles on 16^2 cells, chunks of 256, float64), the programs'
    temporaries stay below one state: nothing copies it.  (A read of the initial state in the rolled-out
    program, such as its frame, would make XLA copy it: the in-place run takes that frame apart.)"""
    setup = jm.scene("mpm88", n_particles=4096, n_grid=16)
    sim, state = setup.sim.with_chunks(256), setup.state
    assert jm.backend_info(sim, state)["chunk_particles"] == 256
    assert in_place_memory(sim, state, jnp.asarray(setup.dt), 2).temp_size_in_bytes < tree_bytes(state)


def test_donate_does_nothing_under_jit_and_grad(sim):
    """Inside a traced program the enclosing jit owns the buffers: the same numbers and gradient, and the
    caller's state stays."""
    state = fresh(sim)

    def loss(v, donate):
        start = eqx.tree_at(lambda s: s.v, state, v)
        final, _ = sim.run(start, jnp.asarray(DT), 4, 1, save_particles=False, donate=donate)
        return jnp.sum(final.v ** 2) + jnp.sum(final.x ** 2)

    donated = jax.jit(jax.value_and_grad(lambda v: loss(v, True)))(state.v)
    kept = jax.jit(jax.value_and_grad(lambda v: loss(v, False)))(state.v)
    assert_same(donated, kept)
    assert not deleted(state)


@pytest.mark.parametrize("donate", [1, "yes", None])
def test_donate_must_be_a_bool(sim, donate):
    with pytest.raises(jm.InputError, match="donate"):
        sim.run(fresh(sim), jnp.asarray(DT), 4, 1, donate=donate)
