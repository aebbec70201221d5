"""Particles sorted by cell every K steps (jaxmpm/run/sorting.py, issue 32 item 1): the permutation lives in
the run, so a sorted run gives the unsorted run's frames, final state, failures, HDF5 file and gradients --
equal to round-off, since only the order of P2G's floating-point sums changes -- in the user's particle
order.  Small mpm88 scenes (16^2 grid, 512 particles in random order) in float64."""

import os
import signal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxmpm as jm
from jaxmpm.run.sorting import Sorting
from jaxmpm.transfer.backend import SORT_TABLE, choose_sorting

SETUP = jm.scene("mpm88", n_particles=512, n_grid=16)
SIM, STATE, DT = SETUP.sim, SETUP.state, SETUP.dt
SORTED = SIM.with_sorting(5)


def _assert_same(a, b, tol=1e-12):
    """Every float leaf of ``b`` equals ``a``'s to ``tol`` of the leaf's scale."""
    for (path, x), y in zip(jax.tree_util.tree_leaves_with_path(a), jax.tree_util.tree_leaves(b)):
        x, y = np.asarray(x), np.asarray(y)
        if np.issubdtype(x.dtype, np.floating):
            np.testing.assert_allclose(y, x, rtol=0, atol=tol * max(1e-300, np.abs(x).max()),
                                       err_msg=jax.tree_util.keystr(path))
        else:
            np.testing.assert_array_equal(y, x, err_msg=jax.tree_util.keystr(path))


def test_the_sort_orders_particles_by_cell_and_is_undone_exactly():
    """renew() sorts the rows by C-order cell number (stable), and in_user_order() restores every
    per-particle array exactly; scalars (time, step) are left alone."""
    sorting = SORTED.sorting(STATE)
    assert isinstance(sorting, Sorting) and sorting.every == 5
    state, order = sorting.renew(STATE, sorting.start(STATE))
    cells = np.asarray(sorting.cell(state.x))
    assert np.all(np.diff(cells) >= 0)  # sorted by cell
    assert not np.array_equal(np.asarray(order.rows), np.arange(512))  # mpm88's particles start in random order
    np.testing.assert_array_equal(np.asarray(state.x), np.asarray(STATE.x)[np.asarray(order.rows)])
    _assert_same(STATE, sorting.in_user_order(state, order), tol=0.0)
    # the cell number is C order over the cells: (i, j) -> i * cells_y + j
    x = jnp.asarray([[0.01, 0.01], [0.01, 0.99], [0.99, 0.01], [0.5 + 1e-9, 0.25 + 1e-9]])
    assert np.asarray(sorting.cell(x)).tolist() == [0, 15, 240, 8 * 16 + 4]


def test_a_sorted_run_equals_an_unsorted_one_over_100_steps():
    """100 steps of mpm88 (APIC), sorted every 5 steps: every frame and the final state equal the
    unsorted run's to 1e-12 of their scale, in the user's particle order."""
    final, history = SIM.with_sorting(0).run(STATE, DT, 100, 10)
    final_s, history_s = SORTED.run(STATE, DT, 100, 10)
    cell = SORTED.sorting(STATE).cell
    moved = np.mean(np.asarray(cell(final.x)) != np.asarray(cell(STATE.x)))
    assert moved > 0.2  # a fifth of the particles changed cells: the later sorts reorder them
    _assert_same(final, final_s)
    _assert_same(history, history_s)


def test_a_sorted_chunked_run_writes_the_same_file_and_resumes(tmp_path):
    """The chunked runner (a writer, chunks of 3 frames) sorts too: the HDF5 file holds the unsorted
    run's frames and state; a sorted run stopped by SIGINT after its first chunk is continued by
    jm.resume to the uninterrupted run's answer."""
    paths = {}
    for name, sim in (("plain", SIM.with_sorting(0)), ("sorted", SORTED)):
        paths[name] = tmp_path / f"{name}.h5"
        with jm.H5Writer(paths[name], sim, STATE, dt=DT) as writer:
            final, _ = sim.run(STATE, DT, 40, 4, writer=writer, frames_per_chunk=3)
    plain, got = jm.load_h5(paths["plain"]), jm.load_h5(paths["sorted"])
    assert got["particles/x"].shape == (11, 512, 2)
    for key in ("particles/x", "particles/v", "time", "energy/kinetic", "energy/strain", "momentum/linear"):
        np.testing.assert_allclose(got[key], plain[key], rtol=0, atol=1e-12 * np.abs(plain[key]).max(), err_msg=key)
    cut = tmp_path / "cut.h5"
    with pytest.raises(jm.RunInterrupted) as stop:
        with _SigintAfterFirstChunk(cut, SORTED, STATE, dt=DT) as writer:
            SORTED.run(STATE, DT, 40, 4, writer=writer, frames_per_chunk=3)
    assert 0 < int(stop.value.state.step) < 40
    resumed = jm.resume(cut, SORTED, state=STATE)
    _assert_same(final, resumed)


class _SigintAfterFirstChunk(jm.H5Writer):
    """A writer that sends SIGINT to this process when the first chunk's frames arrive."""

    def append(self, history):
        super().append(history)
        if self.frames > 1:
            os.kill(os.getpid(), signal.SIGINT)


def test_a_failure_names_the_users_particle(monkeypatch):
    """A particle put outside the grid: the sorted run's error names the same particle (the user's
    index) and step as the unsorted run's.  (A run refuses such a state before its first step; that
    check is set aside here, so that the failure record of the step names the particle.)"""
    from jaxmpm.run import driver

    monkeypatch.setattr(driver, "_check_start", lambda sim, state: None)
    x = STATE.x.at[137].set(jnp.asarray([1.02, 0.5]))  # mpm88's grid is the unit square
    state = eqx.tree_at(lambda s: s.x, STATE, x)
    errors = []
    for sim in (SIM.with_sorting(0), SORTED):
        with pytest.raises(jm.ParticlesLeftGrid) as info:
            sim.run(state, DT, 20, 10)
        errors.append(info.value)
    assert errors[0].particle == errors[1].particle == 137
    assert errors[0].step == errors[1].step == 1


@pytest.mark.slow
def test_gradients_through_a_sorted_run_equal_the_unsorted_ones():
    """d(mean height after 30 steps)/dE through the sorted rollout equals the unsorted one (1e-10):
    the permutations are gathers, whose transposes JAX knows."""

    def loss(sim, E):
        final, _ = jm.set_params(sim, E=E).run(STATE, DT, 30, 10, save_particles=False)
        return jnp.mean(final.x[:, 1])

    E = jnp.asarray(400.0)
    g = jax.grad(lambda e: loss(SIM.with_sorting(0), e))(E)
    g_sorted = jax.grad(lambda e: loss(SORTED, e))(E)
    assert abs(float(g)) > 0
    np.testing.assert_allclose(float(g_sorted), float(g), rtol=1e-10)


def test_ensembles_sort_each_member():
    """jm.ensemble over E with a sorted model equals the unsorted ensemble (the renewal's counter is
    the loop's own, so under vmap it stays one conditional)."""
    values = jnp.asarray([300.0, 500.0])
    plain = jm.ensemble(SIM.with_sorting(0), STATE, DT, 20, 10, params={"E": values}, save_particles=True,
                        progress=False)
    got = jm.ensemble(SORTED, STATE, DT, 20, 10, params={"E": values}, save_particles=True, progress=False)
    _assert_same(plain, got)


def test_the_table_and_bad_input():
    """"auto" takes K from the backend's sort table (not sorted on the CPU or in 2D; every 16 steps in 3D on a
    GPU from 131k particles, from 1M on the Pallas kernel); backend_info says which and why; a bad
    sort_every is refused by name."""
    assert SIM.sort_every == "auto" and SIM.sorting(STATE) is None
    info = jm.backend_info(SIM, STATE)
    assert info["sort_every"] == 0 and info["sort_reason"].startswith("CPU")
    assert jm.backend_info(SORTED, STATE)["sort_every"] == 5
    assert choose_sorting("gpu", 3, 1_048_576, "xla")[0] == 16
    assert choose_sorting("gpu", 3, 1_048_576, "pallas")[0] == SORT_TABLE[0][1][0] == 16
    assert choose_sorting("gpu", 3, 131_072, "pallas")[0] == 0  # 0.96x at 131k on an H100
    assert choose_sorting("gpu", 3, 4096, "xla")[0] == 0  # a short step: the renewal would weigh more
    assert choose_sorting("gpu", 2, 524_288, "xla")[0] == 0
    for bad in (-1, 2.5, "often", True):
        with pytest.raises(jm.InputError, match="sort_every"):
            SIM.with_sorting(bad)
