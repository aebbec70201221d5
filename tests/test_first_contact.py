"""Inputs that escaped as raw exceptions or misleading messages (an audit of the documentation against the
code, 2026-11-29), each now a one-line jm.InputError naming the parameter and the fix, or exit status 2 on the
command line; and the documented behaviours that did not happen (``timings`` of a plain run, a scene's
default fields, spin's stiffness)."""

from __future__ import annotations

import os
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from cases import run_cli

import jaxmpm as jm

GRID = jm.Grid((0.0, 0.0), (1.0, 1.0), (8, 8))


def _particles():
    return jm.fill(GRID, jm.Box((0.3, 0.2), (0.7, 0.5)), ppc=2)


def _model(scheme="flip", material=None, terms=()):
    return jm.Simulation(GRID, "quadratic", material or jm.NeoHookean(E=1e3), scheme, boundary=jm.Fixed("y-"),
                         terms=terms)


# ----------------------------------------------------------------- a state for this model


@pytest.mark.parametrize("made, runs, words", [
    (_model("apic"), _model("flip"), ["scheme_state", "FLIP needs nothing"]),
    (_model("flip"), _model("apic"), ["scheme_state holds nothing", "APIC needs an array of shape"]),
    (_model(), _model(material=jm.VonMises(E=1e3, nu=0.3, yield_stress=10.0)),
     ["material_state holds nothing", "VonMises needs {Fe"]),
    (_model(material=jm.VonMises(E=1e3, nu=0.3, yield_stress=10.0)), _model(), ["NeoHookean needs nothing"]),
    (_model(), _model(terms=[jm.Reaction()]), ["carries no fields", "['reaction_force']"]),
    (_model(terms=[jm.Reaction()]), _model(), ["the fields ['reaction_force']", "declare none"]),
], ids=["apic->flip", "flip->apic", "elastic->plastic", "plastic->elastic", "term added", "term removed"])
def test_a_state_made_for_another_model_is_named(made, runs, words):
    """It had raised KeyError, AttributeError or TypeError from inside the step, or run on silently."""
    state = made.init(_particles())
    with pytest.raises(jm.InputError) as err:
        runs.run(state, 1e-4, 2, 1)
    text = str(err.value)
    assert text.startswith("run: the state was made for another model") and "sim.init(particles)" in text
    for word in words:
        assert word in text, (word, text)


def test_a_state_of_this_model_runs_also_under_jit_and_vmap():
    """The check compares shapes only: it passes inside jit and vmap (an ensemble's members)."""
    sim = _model("apic", terms=[jm.Reaction()])
    state = sim.init(_particles())
    final, _ = sim.run(state, 1e-4, 2, 1)
    assert int(final.step) == 2
    out = jm.ensemble(sim, state, 1e-4, 2, 1, params={"E": jnp.array([1e3, 2e3])})
    assert np.asarray(out[0].step).tolist() == [2, 2]


def test_an_ensemble_names_a_state_of_another_model():
    """jm.ensemble did not check its state as sim.run does: a state without the fields of a term added for a
    parameter (an ensemble over contact friction on a one-body model, set_params adding jm.Contact) had raised
    KeyError 'material' from inside the step (the audit of the gradients, 2026-11-29).  That friction is now
    refused as a parameter that does not act (tests/test_params_act.py); a state of another model is named."""
    state = _model("apic").init(_particles())
    with pytest.raises(jm.InputError, match=r"ensemble: the state was made for another model: its scheme_state"):
        jm.ensemble(_model("flip"), state, 1e-4, 2, 1, params={"E": jnp.asarray([1e3, 2e3])})


@pytest.mark.parametrize("state, words", [(_particles(), "state is a jm.Particles; make the state first"),
                                          (None, "state = None must be a jm.State")])
def test_run_of_something_not_a_state(state, words):
    with pytest.raises(jm.InputError, match=words):
        _model().run(state, 1e-4, 2, 1)


# ----------------------------------------------------------------- timings of a plain run


def test_a_plain_run_fills_timings():
    """docs/running.md: ``timings={}`` receives compile, run and steps; a plain run (no writer, no progress)
    had left it empty.  Its compile seconds are JAX's compile events: none when the program was compiled."""
    sim, state = _model(), _model().init(_particles())
    first, second = {}, {}
    sim.run(state, 1e-4, 4, 2, timings=first)
    sim.run(state, 1e-4, 4, 2, timings=second)  # the same program again
    for timings in (first, second):
        assert set(timings) == {"compile", "run", "steps"} and timings["steps"] == 4
        assert timings["run"] > 0 and timings["compile"] >= 0
    assert second["compile"] == 0.0


# ----------------------------------------------------------------- calibrate, colliders, memory


def test_calibrate_names_an_optimizer_or_callback_of_the_wrong_kind():
    sim, state = _model(), _model().init(_particles())

    def loss(p):
        return jnp.sum(jm.set_params(sim, **p).run(state, 1e-4, 2, 1)[1].kinetic)

    with pytest.raises(jm.InputError, match="optimizer = 'adam' is not an optax optimizer"):
        jm.calibrate(loss, {"E": 1e3}, steps=1, progress=False, optimizer="adam")
    with pytest.raises(jm.InputError, match="callback = 3 is not a function"):
        jm.calibrate(loss, {"E": 1e3}, steps=1, progress=False, callback=3)


def test_a_collider_velocity_function_of_the_wrong_length():
    """A constant velocity of the wrong length was an InputError already; a function's raised TypeError."""
    with pytest.raises(jm.InputError, match=r"velocity\(t\) returns 3 components; return 2"):
        jm.Simulation(GRID, "linear", jm.NeoHookean(E=1e3), "flip",
                      terms=[jm.Collider(jm.HalfSpace((0.0, 0.1), (0.0, 1.0)),
                                         velocity=lambda t: jnp.array([0.0, 0.0, t]))])
    with pytest.raises(jm.InputError, match=r"angular_velocity\(t\) returns 2 components; return 1"):
        jm.Simulation(GRID, "linear", jm.NeoHookean(E=1e3), "flip",
                      terms=[jm.Collider(jm.Ball((0.5, 0.5), 0.1), angular_velocity=lambda t: jnp.array([t, t]),
                                         center=(0.5, 0.5))])
    for velocity in (lambda t: jnp.array([0.0, t]), lambda t: [0.0, float(t)]):  # the right length; host code
        jm.Simulation(GRID, "linear", jm.NeoHookean(E=1e3), "flip",
                      terms=[jm.Collider(jm.HalfSpace((0.0, 0.1), (0.0, 1.0)), velocity=velocity)])


@pytest.mark.parametrize("value", ["abc", "-1", "nan"])
def test_a_bad_memory_override_is_named(monkeypatch, value):
    from jaxmpm.core.limits import available_bytes

    monkeypatch.setenv("JAXMPM_MEMORY_BYTES", value)
    with pytest.raises(jm.InputError, match="JAXMPM_MEMORY_BYTES = .* must be a positive number of bytes"):
        available_bytes()
    monkeypatch.setenv("JAXMPM_MEMORY_BYTES", "8e9")
    assert available_bytes() == 8_000_000_000


# ----------------------------------------------------------------- files


@pytest.mark.parametrize("kind", ["folder", "empty", "missing folder"])
def test_a_writer_path_that_is_not_a_file(tmp_path, kind):
    """A folder with overwrite had failed inside h5py and left FOLDER.tmp, FOLDER.0.tmp, FOLDER.1.tmp."""
    sim, state = _model(), _model().init(_particles())
    path = {"folder": str(tmp_path), "empty": "", "missing folder": str(tmp_path / "nowhere" / "run.h5")}[kind]
    words = {"folder": "is a folder; give a file in it", "empty": "is empty",
             "missing folder": "does not exist; create it first"}[kind]
    with pytest.raises(jm.InputError, match=words):
        jm.H5Writer(path, sim, state, overwrite=True)
    assert sorted(os.listdir(tmp_path)) == []


def test_the_command_line_refuses_a_folder_or_an_empty_out(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    os.mkdir("r_dir")
    for out, words in (("r_dir", "--out 'r_dir' is a folder"), ("", "--out '' is empty")):
        assert run_cli(["run", "bar", "--cells", "4", "--t-end", "0.5", "--frames", "1", "--out", out,
                        "--force"]) == 2
        err = capsys.readouterr().err
        assert words in err and len(err.strip().splitlines()) == 1
    assert sorted(os.listdir(tmp_path)) == ["r_dir"] and os.listdir("r_dir") == []  # nothing left behind


def test_resume_and_run_name_a_folder(tmp_path, capsys):
    assert run_cli(["resume", str(tmp_path)]) == 2
    assert f"resume: {tmp_path} is a folder, not a file" in capsys.readouterr().err
    bad = tmp_path / "bad.h5"
    bad.write_text("not HDF5")
    assert run_cli(["resume", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "cannot read" in err and len(err.strip().splitlines()) == 1  # h5py's message had spanned two lines
    assert run_cli(["run", str(tmp_path), "--out", str(tmp_path / "x.h5")]) == 2
    assert f"scene file {tmp_path} is a folder" in capsys.readouterr().err


# ----------------------------------------------------------------- pictures


def _small_run(tmp_path):
    setup = jm.scene("bar", cells=4, t_end=0.5, frames=2)
    final, history = setup.run()
    path = tmp_path / "bar.h5"
    jm.save_h5(path, setup.sim, history, final, dt=setup.dt)
    return path


def test_plot_dpi_beyond_an_image_is_named(tmp_path):
    """dpi 1e9 had raised matplotlib's TypeError, dpi 1e5 a MemoryError."""
    path = _small_run(tmp_path)
    for dpi in (1e9, 1e5):
        with pytest.raises(jm.InputError, match=r"dpi=.* makes an image of .* pixels; the most is 65535 a side"):
            jm.plot_frames(path, out=tmp_path / "p.png", dpi=dpi)
    assert not (tmp_path / "p.png").exists()


def test_a_projection_of_a_run_below_3d_is_named(tmp_path):
    """axes="xz" on a 1D or 2D run had been accepted and ignored."""
    path = _small_run(tmp_path)
    with pytest.raises(jm.InputError, match="axes='xz': a 1D run has one view"):
        jm.plot_frames(path, axes="xz")


def test_animate_fps_below_what_a_gif_holds_is_named(tmp_path):
    """fps 0.001 had raised Pillow's OverflowError and left a broken GIF; a GIF's frame delay is 16 bits of
    hundredths of a second."""
    path = _small_run(tmp_path)
    with pytest.raises(jm.InputError, match=r"fps=0.001: a GIF shows a frame for at most 655.35 s"):
        jm.animate(path, tmp_path / "a.gif", fps=0.001)
    out = jm.animate(path, tmp_path / "a.gif", fps=0.002, progress=False)
    assert os.path.getsize(out) > 0
    assert sorted(os.listdir(tmp_path)) == ["a.gif", "bar.h5", "bar.xdmf", "bar.xdmf.h5"]  # no partial file left


# ----------------------------------------------------------------- scenes on the command line


def test_spin_takes_its_stiffness_only_with_stress(tmp_path, capsys):
    """--E and --nu had been accepted and ignored: the disk is stress-free unless --stress."""
    out = str(tmp_path / "s.h5")
    short = ["--spacing", "0.125", "--t-end", "0.05", "--frames", "1", "--no-progress", "--out", out]
    assert run_cli(["run", "spin", "--E", "5000", *short]) == 2
    assert "spin: E and nu are the neo-Hookean disk's; give stress=True" in capsys.readouterr().err
    assert run_cli(["run", "spin", "--stress", "--E", "5000", "--nu", "0.45", *short]) == 0
    params = jm.load_h5(out).params
    assert params["E"] == 5000.0 and params["nu"] == 0.45
    assert jm.scene("spin", spacing=0.125, stress=True).sim.material.E == 100.0  # the documented default


def test_incline_saves_its_stress_by_default():
    from jaxmpm.scenes._common import FIELD_DEFAULTS

    assert FIELD_DEFAULTS["incline"] == ("stress",)


def test_per_scene_help_says_what_v0_is(capsys):
    for scene, words in (("bar", "amplitude v0 of the initial velocity"), ("bars_impact", "each bar meets"),
                         ("taylor_bar", "impact speed v0 of the rod")):
        assert run_cli(["run", scene, "--help"]) == 0
        assert words in capsys.readouterr().out


@pytest.mark.parametrize("argv, words", [
    (["heat1d", "--conductivity", "0"], "heat1d: conductivity = 0 carries nothing"),
    (["diffusion2d", "--diffusivity", "0"], "diffusion2d: diffusivity = 0 carries nothing"),
    (["disks", "--contact", "none", "--separation", "2"], "separation = 2.0 is the contact law's"),
    (["bar", "--E", "1e-300"], "bar: the free end would swing by v0 / omega = 1.59e+150"),  # had blamed the grid
    (["thermal_bar", "--expansion", "1e300"], "thermal_bar: expansion * heating = 1e+300 * 50"),  # the grid, too
])
def test_scene_options_that_mean_nothing_are_named(tmp_path, capsys, argv, words):
    """Zero conductivity had said only "dt = inf" (these scenes have no --dt); a separation without a contact
    law had been accepted silently while a friction was refused."""
    assert run_cli(["run", *argv, "--out", str(tmp_path / "x.h5")]) == 2
    assert words in capsys.readouterr().err


def test_command_line_warnings_print_one_line(tmp_path):
    """A warning had printed Python's file, line and source line (``sys.exit(main())``)."""
    import subprocess
    import sys

    result = subprocess.run([sys.executable, "-m", "jaxmpm", "run", "bar", "--cells", "4", "--cfl", "3", "--t-end",
                             "0.5", "--frames", "1", "--no-progress", "--out", str(tmp_path / "u.h5")],
                            capture_output=True, text=True, timeout=300)
    warning = [line for line in result.stderr.splitlines() if "exceeds the stable limit" in line]
    assert len(warning) == 1 and warning[0].startswith("jaxmpm: warning: dt = ")
    assert "sys.exit" not in result.stderr


# ----------------------------------------------------------------- calibrate and ensembles (audit of 2026-11-29)


def _bar_loss():
    setup = jm.scene("bar", cells=4, t_end=0.5, frames=1)

    def loss(p):
        return jnp.sum(jm.set_params(setup.sim, **p).run(setup.state, setup.dt, 2, 1)[1].kinetic)

    return setup, loss


@pytest.mark.parametrize("bounds, init, words", [
    ({"E": "negative"}, {"E": 100.0}, r"bound 'negative' must be \(lower, upper\), two finite numbers"),  # ValueError
    ({"E": (50.0, float("inf"))}, {"E": 100.0}, r"bound \(50.0, inf\) must be"),  # had read as a NaN loss
    ({"e": (120.0, 140.0)}, {"E": 100.0}, r"bounds name \['e'\], which init does not have"),  # had been ignored
    (None, {"E": float("nan")}, "initial E = nan must be finite"),  # had read as a NaN loss at iteration 0
])
def test_calibrate_names_bad_bounds_and_initial_values(bounds, init, words):
    _, loss = _bar_loss()
    with pytest.raises(jm.InputError, match=words):
        jm.calibrate(loss, init, bounds=bounds, steps=1, progress=False)


def test_calibrate_says_where_the_loss_or_its_gradient_stopped_being_finite():
    """Each read "the loss became nan at iteration N; lower the learning rate": a loss undefined at
    the initial values, or a finite loss whose derivative is not (no learning rate mends either)."""
    optimizer = optax.sgd(1.0)
    with pytest.raises(jm.InputError, match=r"the loss is nan at the initial parameters \(a = 1.0\): the loss "
                                            r"function gives it there, before any step"):
        jm.calibrate(lambda p: jnp.log(p["a"] - 2.0), {"a": 1.0}, steps=3, optimizer=optimizer, progress=False)
    with pytest.raises(jm.InputError, match=r"the loss's gradient is (nan|inf) at iteration 0 \(a = 2.0\) while "
                                            r"the loss is 0: a derivative inside the loss function is undefined"):
        jm.calibrate(lambda p: jnp.sqrt(jnp.abs(p["a"] - 2.0)), {"a": 2.0}, steps=3, optimizer=optimizer,
                     progress=False)
    # a step too long: a = 1 - 2 * 2.25 = -3.5 lands where log(a + 3) is undefined
    with pytest.raises(jm.InputError, match=r"the loss became nan at iteration 1 \(a = -3.5\), after 1; the step "
                                            r"was too long: lower the learning rate"):
        jm.calibrate(lambda p: p["a"] ** 2 + jnp.log(p["a"] + 3.0) - jnp.log(4.0), {"a": 1.0}, steps=3,
                     optimizer=optax.sgd(2.0), progress=False)


def test_calibrate_keeps_held_parameters_exactly():
    """A held (not free) positive parameter came back as exp(log(100)) = 100.00000000000004."""
    _, loss = _bar_loss()
    fit = jm.calibrate(loss, {"E": 100.0, "alpha_p": 0.1}, free="alpha_p", steps=2, progress=False)
    assert float(fit.params["E"]) == 100.0 and np.all(np.asarray(fit.trajectory["E"]) == 100.0)


def test_a_vector_parameter_takes_one_value_per_axis():
    """In 2D, set_params(gravity=-9.8) set both axes to -9.8, and an ensemble's params={"gravity": [0, -9.8]}
    ran as two members, each with a number for every axis.  In 1D a number is the one axis's value."""
    disks = jm.scene("disks", spacing=0.2, t_end=0.01, frames=1)
    with pytest.raises(jm.InputError, match=r"gravity has shape \(\); this model's gravity has shape \(2,\)"):
        jm.set_params(disks.sim, gravity=-9.8)
    with pytest.raises(jm.InputError, match=r"ensemble member 0: gravity has shape \(\).*shape \(members, 2\)"):
        jm.ensemble(disks.sim, disks.state, disks.dt, 1, 1, params={"gravity": [0.0, -9.8]})
    assert np.asarray(jm.get_params(jm.set_params(disks.sim, gravity=(0.0, -9.8)), "gravity")["gravity"]).shape == (2,)
    bar, _ = _bar_loss()
    assert float(np.asarray(jm.get_params(jm.set_params(bar.sim, gravity=-9.8), "gravity")["gravity"]).ravel()[0]) \
        == -9.8


def test_ensemble_states_need_their_batch_axis():
    """An unbatched states= had been taken as a batch along its particles, then raised IndexError."""
    setup, _ = _bar_loss()
    with pytest.raises(jm.InputError, match=r"states.x has the template state's shape, with no batch axis"):
        jm.ensemble(setup.sim, setup.state, setup.dt, 1, 1, states=setup.state)
    fewer = jax.tree_util.tree_map(lambda a: jnp.stack([a[:4] if a.ndim else a] * 2), setup.state)
    with pytest.raises(jm.InputError, match=r"states.x has shape \(2, 4, 1\), where the template state's is"):
        jm.ensemble(setup.sim, setup.state, setup.dt, 1, 1, states=fewer)


def test_a_force_holding_per_particle_arrays_is_neither_sorted_nor_chunked():
    """The mms scene's manufactured force holds each particle's reference position in the user's order: sorting
    had handed particles each other's forces (|dv| 1.41 of max |v| 13.7 after 40 steps, no error), and chunks
    had raised an InputError from inside the step (the float32/3D audit of 2026-11-29)."""
    from jaxmpm.parallel import ShardedSimulation

    setup = jm.scene("mms", dim=2, cells=8)
    with pytest.raises(jm.InputError, match=r"sort_every=1: the term\(s\) BodyForce hold per-particle arrays"):
        setup.sim.with_sorting(1)
    info = jm.backend_info(setup.sim.with_chunks(64), setup.state)
    assert info["sort_every"] == 0 and "per-particle arrays" in info["sort_reason"]
    assert info["chunk_particles"] == 0 and "Term.local" in info["chunk_reason"]
    plain, _ = setup.sim.run(setup.state, setup.dt, 4, 4)
    chunked, _ = setup.sim.with_chunks(64).run(setup.state, setup.dt, 4, 4)
    np.testing.assert_array_equal(np.asarray(chunked.v), np.asarray(plain.v))
    with pytest.raises(jm.InputError, match="ShardedSimulation: the term.s. BodyForce hold per-particle arrays"):
        ShardedSimulation(setup.sim)


def test_gradient_schedule_checks_dt_and_state_and_run_refuses_checkpoint_none():
    """gradient_schedule took dt = 0 or nan (and a state of another kind) without a word; checkpoint=None
    ran as False, a value no documentation named."""
    setup, _ = _bar_loss()
    for dt, words in [(0.0, "dt = 0.0 must be positive"), (float("nan"), "dt = nan must be finite and positive")]:
        with pytest.raises(jm.InputError, match=f"gradient_schedule: {words}; the time step"):
            jm.gradient_schedule(setup.sim, setup.state, dt, 4, 1)
    with pytest.raises(jm.InputError, match="gradient_schedule: state = None must be a jm.State"):
        jm.gradient_schedule(setup.sim, None, setup.dt, 4, 1)
    with pytest.raises(jm.InputError, match=r"checkpoint = None must be 'auto', 'states', True, False"):
        setup.sim.run(setup.state, setup.dt, 4, 1, checkpoint=None)


def test_a_shape_function_without_its_hooks_is_refused_when_made():
    """An empty jm.ShapeFunction subclass was made, and its run raised a bare NotImplementedError."""
    class Empty(jm.ShapeFunction):
        pass

    class NoKernel(jm.ShapeFunction):
        nodes_per_axis = 2

        def _base(self, xi):
            return xi

    with pytest.raises(jm.InputError, match=r"Empty: a shape function sets nodes_per_axis \(a positive int; now 0\) "
                                            r"and margin, and defines _base\(xi\) and _kernel\(r\); missing: _base, "
                                            r"_kernel \(docs/extending.md, 'A shape function'\)"):
        Empty()
    with pytest.raises(jm.InputError, match="NoKernel: .*; missing: _kernel "):
        NoKernel()


def test_a_law_or_scheme_of_ones_own_returning_the_wrong_shape_is_named():
    """A kirchhoff_stress of shape (N,) raised "P2G column 'force' sums contractions of different widths";
    a scheme's update returning a tuple raised AttributeError 'strain_velocity', and a velocity of the
    wrong shape JAX's while-loop type error."""
    class FlatStress(jm.ElasticMaterial):
        E: float = 1.0
        nu: float = 0.3

        def kirchhoff_stress(self, F):
            return jnp.zeros(F.shape[0])

        def energy_density(self, F):
            return jnp.zeros(F.shape[0])

    disks = jm.scene("disks", spacing=0.2, t_end=0.01, frames=1)
    sim = jm.Simulation(disks.sim.grid, disks.sim.shape, FlatStress(density=1000.0), "flip")
    state = sim.init(jm.fill(disks.sim.grid, jm.Disk((0.5, 0.5), 0.3), ppc=2))
    n = state.x.shape[0]
    with pytest.raises(jm.InputError, match=rf"FlatStress.stress \(kirchhoff_stress of an elastic law\) returned shape "
                                            rf"\({n},\); the Kirchhoff stress has F's shape \({n}, 2, 2\)"):
        sim.run(state, 1e-3, 1, 1)

    class Returns(jm.Scheme):
        answer: str = "tuple"

        def update(self, V, X, transfer, constraint, grid, damping, dt):
            if self.answer == "tuple":
                return V, X
            if self.answer == "flat":
                return jm.ParticleUpdate(V[:, 0], X, grid.v, jnp.zeros(()))
            return jm.ParticleUpdate(V, X, grid.v, jnp.zeros(V.shape[0]))

    for answer, words in [("tuple", r"Returns.update returned tuple; return jm.ParticleUpdate\(velocity, position, "
                                    r"strain_velocity, dissipated\)"),
                          ("flat", rf"Returns.update returned velocity of shape \({n},\); it must have shape "
                                   rf"\({n}, 2\)"),
                          ("per particle", rf"returned dissipated of shape \({n},\); it must have shape \(\) \(one "
                                           r"energy for all the particles\)")]:
        model = jm.Simulation(disks.sim.grid, disks.sim.shape, jm.LinearElastic(E=1.0, nu=0.3, density=1.0),
                              Returns(answer))
        with pytest.raises(jm.InputError, match=words):
            model.run(model.init(jm.fill(disks.sim.grid, jm.Disk((0.5, 0.5), 0.3), ppc=2)), 1e-3, 1, 1)


def test_a_grid_force_returned_under_a_misspelt_name_warns():
    """grid_force's {"forces": f} became a named result that nothing read: the term acted by exactly nothing,
    silently.  A name close to "force" warns; other names (results for other terms) do not."""
    class Drag(jm.Term):
        key: str = "forces"

        def grid_force(self, sim, fields, dt):
            return {self.key: -0.5 * fields.momentum}

    disks = jm.scene("disks", spacing=0.2, t_end=0.01, frames=1)
    for key, warns in (("forces", True), ("Force", True), ("drag_force_x", False)):
        sim = disks.sim.with_term(Drag(key))
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            sim.run(disks.state, disks.dt, 1, 1)
        said = [str(w.message) for w in caught if "grid_force returned" in str(w.message)]
        assert bool(said) == warns, (key, said)
        if warns:
            assert said[0].startswith(f"Drag.grid_force returned {key!r}, which is kept as a named result") and \
                said[0].endswith("a nodal force is returned as 'force'")


def test_a_shape_functions_node_count_may_be_a_numpy_integer_or_a_property():
    class NumpyCount(jm.QuadraticBSpline):
        nodes_per_axis = np.int64(3)

    class PropertyCount(jm.QuadraticBSpline):
        @property
        def nodes_per_axis(self):
            return 3

    NumpyCount()
    PropertyCount()
    for bad in (True, 0, 2.5):
        with pytest.raises(jm.InputError, match=f"a positive int; now {bad!r}"):
            type("Bad", (jm.QuadraticBSpline,), {"nodes_per_axis": bad})()


def test_calibrate_reads_a_finite_float32_gradient_past_1e19_as_finite():
    """Its norm, summed as squares, overflowed float32 and read as an undefined derivative."""
    from jaxmpm.run.calibrate import _norm

    big = [jnp.asarray([1e19, 1e19], jnp.float32), jnp.asarray([3e19], jnp.float32)]
    assert float(_norm(big)) == pytest.approx(np.sqrt(11.0) * 1e19, rel=1e-6)
    assert not np.isfinite(float(_norm([jnp.asarray([1.0, np.nan], jnp.float32)])))
    assert not np.isfinite(float(_norm([jnp.asarray([1.0, np.inf], jnp.float32)])))
    assert float(_norm([jnp.zeros(3)])) == 0.0
