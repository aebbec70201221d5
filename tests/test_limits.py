"""Size limits (issue 11, item 2): the frame schedule is arithmetic, the int32 step counter and the
memory of a fill, a grid and the saved frames are checked before anything is allocated, and each
limit fails at once with one line naming the size and the fix; the CLI adds --max-steps and
refuses to overwrite --out without --force."""

from __future__ import annotations

import re

import jax
import numpy as np
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


def _moving_body():
    from cases import small_simulation

    sim = small_simulation()
    return sim, sim.init(jm.fill(sim.grid, jm.Box((4.0,), (8.0,)), ppc=2, velocity=0.1))


@pytest.mark.slow
def test_compiling_first_keeps_the_results_bit_for_bit():
    """The chunked run (compiled by a call that runs no frame, then chunks of 1 and 8 steps) ends
    where the unchunked rollout does, to the bit, frames included."""
    sim, state = _moving_body()
    final, history = sim.run(state, 0.1, 64, 1, progress=True, frames_per_chunk=8)
    unchunked, frames = sim.run(state, 0.1, 64, 1)
    for a, b in zip(jax.tree_util.tree_leaves((final, history)), jax.tree_util.tree_leaves((unchunked, frames))):
        np.testing.assert_array_equal(a, b)


def _estimate_lines(err: str) -> list:
    return [line for line in err.replace("\r", "\n").splitlines() if line.startswith("jaxmpm: this run needs")]


def test_a_long_run_says_how_long_and_compiles_before_its_clock_starts(monkeypatch, capsys):
    """A chunked run compiles its loop before the first step: meanwhile the bar reads "compiling" and
    shows no rate or ETA, and ``timings`` gets the compilation and the run apart.  Once two chunks
    have measured the rate, a run whose rest needs more than $JAXMPM_LONG_RUN_SECONDS (1 h unset)
    says so in one line on stderr."""
    sim, state = _moving_body()
    monkeypatch.setenv("JAXMPM_LONG_RUN_SECONDS", "1e-9")
    timings = {}
    final, history = sim.run(state, 0.1, 64, 1, progress=True, frames_per_chunk=8, timings=timings)
    err = capsys.readouterr().err
    renders = [line for line in err.split("\r") if line.strip()]
    assert renders[0].startswith("jaxmpm (compiling):") and "0/64 [00:00<?, ?step/s]" in renders[0]
    assert all("<?" in line for line in renders if "compiling" in line)  # no ETA while compiling
    assert "jaxmpm: 100%" in renders[-1] and "64/64" in renders[-1]
    assert timings["steps"] == 64 and timings["compile"] > 0 and timings["run"] > 0
    (line,) = _estimate_lines(err)  # after two chunks of 8 steps: 48 left
    rate = re.fullmatch(r"jaxmpm: this run needs about \S+ (?:s|min|h|days) more \(48 steps at (\S+) steps/s\); "
                        r"Ctrl-C stops it and keeps the frames", line)
    assert rate and float(rate[1]) > 0

    monkeypatch.delenv("JAXMPM_LONG_RUN_SECONDS")  # 1 h: this run says nothing
    sim.run(state, 0.1, 64, 1, progress=True, frames_per_chunk=8)
    assert _estimate_lines(capsys.readouterr().err) == []
    monkeypatch.setenv("JAXMPM_LONG_RUN_SECONDS", "soon")
    with pytest.raises(jm.InputError, match=r"JAXMPM_LONG_RUN_SECONDS = 'soon' must be a number of seconds >= 0"):
        sim.run(state, 0.1, 64, 1, progress=True)


def test_durations_and_counts_read_as_people_say_them():
    from jaxmpm.run.driver import _count, duration

    assert [duration(s) for s in (0.004, 45, 12 * 60, 37 * 3600, 3.5 * 86400)] == [
        "0.004 s", "45 s", "12 min", "37 h", "3.5 days"]
    assert [_count(n) for n in (1.2e9, 9100, 48, 640)] == ["1.2e9", "9.1e3", "48", "6.4e2"]
