"""Interrupt and resume (issue 11, item 4): SIGINT/SIGTERM stop a chunked run at a chunk boundary,
the file keeps every finished frame and the full state reached, and resuming equals the
uninterrupted run bitwise on the CPU -- every chunk is a call of one compiled loop whose frame and
step counts are runtime values, so the chunking does not change the arithmetic.  Files of
jm.save_h5 with the run's schedule resume too (issue 29); SIGKILL: tests/test_crash_safety.py.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time

import h5py
import jax
import numpy as np
import pytest
from cases import assert_same_files

import jaxmpm as jm

BAR = dict(cells=8, t_end=2.0, frames=8)  # dt = 0.1 (25/8)/10 = 0.03125: 64 steps, a frame every 8


class SignalAfter(jm.H5Writer):
    """A writer that sends ``signum`` to this process when its ``after``-th append arrives."""

    def __init__(self, *args, signum, after, **kwargs):
        super().__init__(*args, **kwargs)
        self.signum, self.after, self.appends = signum, after, 0

    def append(self, history):
        super().append(history)
        self.appends += 1
        if self.appends == self.after:
            os.kill(os.getpid(), self.signum)


def written(setup, path, writer_class=jm.H5Writer, **kwargs):
    with writer_class(path, setup.sim, setup.state, dt=setup.dt, scene=setup.name, params=setup.params,
                      **kwargs) as writer:
        return setup.run(writer=writer)[0]


MPM88 = dict(n_particles=64, n_grid=8, t_end=2e-3, frames=2)  # APIC: the scheme state B_p is saved too


@pytest.mark.slow
@pytest.mark.parametrize("scene, options, signum, after", [("bar", BAR, signal.SIGINT, 1),
                                                           ("bar", BAR, signal.SIGTERM, 2),
                                                           ("mpm88", MPM88, signal.SIGINT, 1)])
def test_interrupted_then_resumed_equals_the_uninterrupted_run(tmp_path, scene, options, signum, after):
    """After the initial frame (SIGINT: the run stops after its first chunk, one step, part-way
    through frame 1) or once frame 1 is written (SIGTERM); resume from Python with the Setup."""
    setup = jm.scene(scene, **options)
    whole = tmp_path / "whole.h5"
    final = written(setup, whole)
    cut = tmp_path / "cut.h5"
    with pytest.raises(jm.RunInterrupted) as stop:
        written(setup, cut, SignalAfter, signum=signum, after=after)
    assert stop.value.signal == signal.Signals(signum).name
    reached = int(stop.value.state.step)
    assert 0 < reached < setup.steps
    with h5py.File(cut, "r") as f:  # every finished frame, and the state reached
        assert f["time"].shape[0] == reached // setup.save_every + 1 == stop.value.frames
        assert int(f["state/step"][()]) == reached and not f["state"].attrs["complete"]
        np.testing.assert_array_equal(f["state/x"][()], np.asarray(stop.value.state.x))
        if scene == "mpm88":
            np.testing.assert_array_equal(f["state/scheme_state"][()], np.asarray(stop.value.state.scheme_state))
    resumed = jm.resume(cut, setup)
    np.testing.assert_array_equal(np.asarray(resumed.x), np.asarray(final.x))
    assert_same_files(whole, cut)
    assert jm.resume(cut, setup).step == setup.steps  # a finished run: nothing more to do


def test_resume_with_a_simulation_and_its_initial_state(tmp_path):
    setup = jm.scene("bar", **BAR)
    cut = tmp_path / "cut.h5"
    with pytest.raises(jm.RunInterrupted):
        written(setup, cut, SignalAfter, signum=signal.SIGINT, after=2)
    final = jm.resume(cut, setup.sim, state=setup.state)
    reference, _ = setup.run()
    np.testing.assert_array_equal(np.asarray(final.v), np.asarray(reference.v))


def test_resume_errors_name_the_problem(tmp_path):
    setup = jm.scene("bar", **BAR)
    with pytest.raises(jm.InputError, match="does not exist"):
        jm.resume(tmp_path / "nothing.h5", setup)
    path = tmp_path / "python.h5"
    jm.save_h5(path, setup.sim, setup.run()[1], state=setup.state, dt=setup.dt)
    with pytest.raises(jm.InputError, match="not written by `jaxmpm run`"):
        jm.resume(path)
    with pytest.raises(jm.InputError, match="no saved state"):
        jm.resume(path, setup)
    cut = tmp_path / "cut.h5"
    with pytest.raises(jm.RunInterrupted):
        written(setup, cut, SignalAfter, signum=signal.SIGINT, after=1)
    other = jm.scene("bar", cells=16, t_end=2.0, frames=8)  # another grid and particle count
    with pytest.raises(jm.InputError, match=r"written by another model: dt = 0.015625 here, 0.03125 in the file; "
                                            r"cells = \[18\] here, \[10\]"):
        jm.resume(cut, other)
    with pytest.raises(jm.InputError, match=r"/state/x is float64\[16, 1\] but the model's state has float64\[32, 1\]"):
        jm.resume(cut, setup.sim, state=other.state)  # the model's own, a state of another particle count


@pytest.mark.parametrize("options, words", [(dict(E=50.0), r"dt = 0.0441942 here, 0.03125 in the file; E = 50 here, "
                                                          r"100 in the file"),
                                            (dict(scheme="pic"), r"scheme = 'PIC' here, 'FLIP' in the file"),
                                            (dict(cfl=0.2), r"dt = 0.0625 here, 0.03125 in the file")])
def test_resume_refuses_another_model(tmp_path, options, words):
    """jm.resume(path, setup) had continued a run with whatever model it was given: E = 50 ran on to t = 2.72 of
    a 2.0 run, PIC's frames followed FLIP's under a header saying FLIP (the audit of 2026-11-29)."""
    setup = jm.scene("bar", **BAR)
    cut = tmp_path / "cut.h5"
    with pytest.raises(jm.RunInterrupted):
        written(setup, cut, SignalAfter, signum=signal.SIGINT, after=2)
    before = os.path.getmtime(cut)
    with pytest.raises(jm.InputError, match="resume: .* was written by another model: " + words):
        jm.resume(cut, jm.scene("bar", **BAR, **options))
    assert os.path.getmtime(cut) == before  # untouched
    assert jm.resume(cut, jm.scene("bar", **BAR, v0=0.2)).step == setup.steps  # the initial state is not the model


def test_resume_of_a_finished_run_mends_its_sidecar_and_working_copies(tmp_path, monkeypatch):
    """A run killed after its last publication but before the sidecar that follows it (the audit of 2026-11-29:
    once in 120 random kills) left an XDMF sidecar listing fewer frames, and its working copies and lock; resume
    returned at once and left them."""
    import jaxmpm.io.hdf5 as hdf5
    from jaxmpm.io.xdmf import xdmf_paths

    setup = jm.scene("bar", **BAR)
    path = tmp_path / "run.h5"
    calls = []
    real = hdf5.write_xdmf

    def stale_after_two(*args):  # the sidecar stops at the second publication: as a kill after the last one
        calls.append(1)
        if len(calls) <= 2:
            real(*args)

    monkeypatch.setattr(hdf5, "write_xdmf", stale_after_two)
    written(setup, path)
    monkeypatch.setattr(hdf5, "write_xdmf", real)
    sidecar = xdmf_paths(str(path))[0]
    assert open(sidecar).read().count("<Grid Name=\"frame") < 9
    for leftover in hdf5.working_paths(str(path)):
        open(leftover, "w").close()
    assert jm.resume(path, setup).step == setup.steps
    assert open(sidecar).read().count("<Grid Name=\"frame") == 9
    assert sorted(os.listdir(tmp_path)) == ["run.h5", "run.xdmf", "run.xdmf.h5"]


def test_a_save_h5_file_with_its_schedule_is_resumable(tmp_path):
    """jm.save_h5 with steps= and save_every= stores the state reached: jm.resume(path, setup)
    continues a part of a run kept in memory to the file of the whole run, bit for bit."""
    setup = jm.scene("bar", **BAR)
    final, history = setup.run()
    whole = tmp_path / "whole.h5"
    jm.save_h5(whole, setup.sim, history, state=final, dt=setup.dt, steps=setup.steps, save_every=setup.save_every)
    assert jm.resume(whole, setup).step == setup.steps  # finished: nothing to run
    part, part_history = setup.sim.run(setup.state, setup.dt, 3 * setup.save_every, setup.save_every)
    cut = tmp_path / "cut.h5"
    jm.save_h5(cut, setup.sim, part_history, state=part, dt=setup.dt, steps=setup.steps, save_every=setup.save_every)
    resumed = jm.resume(cut, setup)
    np.testing.assert_array_equal(np.asarray(resumed.x), np.asarray(final.x))
    assert_same_files(whole, cut)
    with pytest.raises(jm.InputError, match="the state is at step 0, where a run from step 0 saving every 8 steps "
                                            "has 1 frames, but the history holds 4"):
        jm.save_h5(cut, setup.sim, part_history, state=setup.state, steps=setup.steps, save_every=setup.save_every)
    with pytest.raises(jm.InputError, match="pass both steps= and save_every="):
        jm.save_h5(cut, setup.sim, part_history, state=part, steps=setup.steps)


def test_frames_after_the_saved_state_are_computed_again(tmp_path):
    """A file whose last frames came after its state (a chunk published without it): resume drops
    them and computes them again, to the same bits."""
    setup = jm.scene("bar", **BAR)
    final, history = setup.run()
    whole = tmp_path / "whole.h5"
    jm.save_h5(whole, setup.sim, history, state=final, dt=setup.dt, steps=setup.steps, save_every=setup.save_every)
    part, part_history = setup.sim.run(setup.state, setup.dt, 2 * setup.save_every, setup.save_every)
    cut = tmp_path / "cut.h5"
    with jm.H5Writer(cut, setup.sim, setup.state, dt=setup.dt) as writer, writer.batch():
        writer.append(jax.tree_util.tree_map(lambda a: a[:6], history))  # frames 0..5
        writer.write_state(part, 0, setup.steps, setup.save_every)  # the state of frame 2
    jm.resume(cut, setup)
    assert_same_files(whole, cut)


def cli(*args, **popen):
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    return subprocess.Popen([sys.executable, "-m", "jaxmpm", *args], env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, **popen)


def read_now(fd) -> str:
    try:
        return os.read(fd, 1 << 16).decode(errors="replace")
    except BlockingIOError:
        return ""


@pytest.mark.slow
def test_ctrl_c_then_jaxmpm_resume_equals_the_uninterrupted_run(tmp_path, request):
    """The CLI in a subprocess: SIGINT once the progress bar shows steps done, exit status 130
    with one line naming the file and `jaxmpm resume`; `jaxmpm resume` finishes it; every dataset
    (frames, energies, the final state) equals an uninterrupted run's, bit for bit."""
    # PIC damps the bar to rest (stable for ever): 1,024,000 steps of 32 particles, about 5 s here
    options = ["run", "bar", "--scheme", "pic", "--t-end", "16000", "--frames", "40"]
    cut, whole = tmp_path / "cut.h5", tmp_path / "whole.h5"
    # the uninterrupted run is independent of the other two processes: it runs alongside them (suite time)
    uninterrupted = cli(*options, "--out", str(whole), "--no-progress")
    request.addfinalizer(uninterrupted.kill)  # a no-op once it has finished
    proc = cli(*options, "--out", str(cut))
    seen, deadline = "", time.time() + 120
    os.set_blocking(proc.stderr.fileno(), False)
    while time.time() < deadline and proc.poll() is None:
        seen += read_now(proc.stderr.fileno())
        done = [int(n) for n in re.findall(r"\| *(\d+)/1024000", seen)]
        if done and max(done) > 0:
            break
        time.sleep(0.05)
    assert proc.poll() is None, f"the run ended before the signal: {seen[-400:]}"
    proc.send_signal(signal.SIGINT)
    sent = time.time()
    proc.wait(timeout=60)
    stopped_in = time.time() - sent
    os.set_blocking(proc.stderr.fileno(), True)
    err = seen + proc.stderr.read().decode()
    assert proc.returncode == 130, err[-3000:]
    last = err.strip().splitlines()[-1]
    assert re.fullmatch(rf"jaxmpm: SIGINT at step \d+ \(t = \S+\): \d+ frames? and the state reached are saved "
                        rf"in {re.escape(str(cut))}; continue with `jaxmpm resume {re.escape(str(cut))}`", last), last
    assert stopped_in < 10, stopped_in  # a chunk is about two seconds of work
    with h5py.File(cut, "r") as f:
        step = int(f["state/step"][()])
        assert 0 < step < 1024000 and f["time"].shape[0] == step // 25600 + 1
    resumed = cli("resume", str(cut), "--no-progress")
    out, err = resumed.communicate(timeout=300)
    assert resumed.returncode == 0, err
    assert b"steps resumed" in out
    out, err = uninterrupted.communicate(timeout=300)
    assert uninterrupted.returncode == 0, err
    assert_same_files(whole, cut)
