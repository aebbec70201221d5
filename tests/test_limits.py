"""Size limits (issue 11, item 2): the frame schedule is arithmetic, the int32 step counter and the
memory of a fill, a grid and the saved frames are checked before anything is allocated, and each
limit fails at once with one line naming the size and the fix; the CLI adds --max-steps and
refuses to overwrite --out without --force."""

from __future__ import annotations

import pytest
from cases import run_cli

import jaxmpm as jm
from jaxmpm.scenes._common import schedule


def test_schedule_is_arithmetic_at_two_billion_steps():
    """2e9 steps (the old schedule walked every divisor candidate: ~45 min here): t_end stays
    exact, a divisor of the step count gives 200 frames."""
    steps, save_every = schedule(2e9, 1.0, 200)
    assert (steps, save_every) == (2_000_000_000, 10_000_000)
    steps, save_every = schedule(1e9 + 7, 1.0, 200)  # a prime count: rounded up to a whole frame
    assert steps % save_every == 0 and steps >= 1e9 + 7 and 100 <= steps // save_every <= 400


@pytest.mark.parametrize("scene, options", [("bar", dict(t_end=1e9)), ("disks", dict(dt=1e-12)),
                                            ("mms", dict(t_end=1e9)), ("vortex", dict(dt=1e-15))])
def test_more_steps_than_the_counter_holds(scene, options):
    with pytest.raises(jm.InputError, match=r"needs .* steps, beyond the step counter's limit 2147483647"):
        jm.scene(scene, **options)


@pytest.fixture
def small_memory(monkeypatch):
    monkeypatch.setenv("JAXMPM_MEMORY_BYTES", str(64 * 2**20))  # 64 MiB


def test_fill_is_sized_before_it_allocates(small_memory):
    with pytest.raises(jm.InputError,
                       match=r"fill: 5\.062e\+06 lattice points \(250 per cell per axis over 9 x 9 cells\) "
                             r"needs about 1\.77 GiB, more than the 0\.0625 GiB .*\(ppc\)"):
        jm.scene("disks", ppc=250)


def test_a_grid_too_large_is_refused(small_memory):
    grid = jm.Grid((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), (200, 200, 200))
    with pytest.raises(jm.InputError, match=r"Simulation: a grid of 8\.121e\+06 nodes \(201 x 201 x 201\)"):
        jm.Simulation(grid=grid, shape=jm.Linear(), material=jm.LinearElastic(E=1.0, nu=0.3, density=1.0),
                      scheme=jm.FLIP())


def test_saved_frames_are_sized_before_the_run(small_memory):
    """A history kept in memory needs every frame; with a writer only a chunk's buffer."""
    setup = jm.scene("bar", cells=4, t_end=2.0, frames=1)
    with pytest.raises(jm.InputError, match=r"this run \(1000001 frames .* save fewer frames"):
        setup.sim.run(setup.state, setup.dt, 1_000_000, 1)


def test_cli_max_steps_and_oversized_runs_exit_2_in_one_line(tmp_path, capsys):
    out = tmp_path / "x.h5"
    assert run_cli(["run", "bar", "--max-steps", "1000", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["jaxmpm: error: the run needs 2560 steps, more than --max-steps 1000; shorten --t-end or use "
                   "a larger --dt/--cfl"]
    assert run_cli(["run", "bar", "--t-end", "1e9", "--out", str(out)]) == 2
    assert len(capsys.readouterr().err.strip().splitlines()) == 1
    assert not out.exists()


@pytest.mark.slow
def test_out_is_not_overwritten_without_force(tmp_path, capsys):
    out = tmp_path / "existing.txt"
    out.write_text("precious")
    assert run_cli(["run", "bar", "--t-end", "0.1", "--frames", "1", "--out", str(out), "--no-progress"]) == 2
    assert capsys.readouterr().err.strip() == (f"jaxmpm: error: --out {out} exists; pass --force to overwrite it, "
                                               "or choose another file")
    assert out.read_text() == "precious"
    assert run_cli(["run", "bar", "--t-end", "0.1", "--frames", "1", "--out", str(out), "--no-progress",
                    "--force"]) == 0
    assert jm.load_h5(out)["time"].shape == (2,)
