"""Scenes of one's own on the command line (issue 29, item 3): ``jaxmpm run my_scene.py`` (a file
whose function ``scene`` builds the scene; resumable, the file's path and sha256 stored),
``jm.register_scene`` and the entry-point group ``jaxmpm.scenes``, per-scene ``--help``, the
defaults ``jaxmpm scenes`` prints as values, the material and gravity options, ``--version``.

Runs use a 1D bar of 8 cells (64 steps); most tests only build the scene, or replace
``run_setup`` by a record of what would run.
"""

from __future__ import annotations

import json
import math
import signal
import types

import h5py
import pytest
from cases import assert_same_files, run_cli

import jaxmpm as jm
import jaxmpm.scenes as scenes
from jaxmpm import cli

BAR_FILE = '''"""A short bar of one's own."""
import jaxmpm as jm


def scene(cells=8, t_end=2.0, frames=8, E=100.0, dtype=None):
    """The fixed-free bar, 8 cells, to t = 2."""
    return jm.scene("bar", cells=cells, t_end=t_end, frames=frames, E=E, dtype=dtype)
'''


@pytest.fixture
def bar_file(tmp_path):
    path = tmp_path / "my_bar.py"
    path.write_text(BAR_FILE)
    return path


@pytest.fixture
def registry():
    """SCENES and the entry-point state as they were, after the test."""
    saved = dict(scenes.SCENES)
    yield scenes.SCENES
    scenes.SCENES.clear()
    scenes.SCENES.update(saved)


@pytest.fixture
def recorded(monkeypatch):
    """`jaxmpm run` builds its Setup and stops there: the Setups and stored options it would run."""
    runs = []
    monkeypatch.setattr(cli, "run_setup", lambda setup, args, options, resume=False: runs.append((setup, options)))
    return runs


def one_error_line(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("jaxmpm: error: "), err
    return err[0]


def parsed(*argv):
    return cli.build_parser().parse_args(["run", *argv, "--out", "unused.h5"])


# --------------------------------------------------------------------------- scene files
def test_scene_file_builds_stores_its_path_and_digest_and_resume_checks_them(bar_file, recorded, capsys):
    """The stored command rebuilds the same scene; a changed or missing file is named on resume."""
    assert run_cli(["run", str(bar_file), "--E", "50", "--out", str(bar_file.parent / "o.h5")]) is None
    (setup, options), = recorded
    assert float(setup.sim.material.E) == 50.0 and setup.state.x.shape == (16, 1)
    assert options["scene"] == str(bar_file.resolve()) and options["E"] == 50.0
    digest = options["scene_sha256"]
    assert len(digest) == 64 and setup.params["scene_sha256"] == digest  # in the HDF5 parameters too
    again = cli.setup_from_options(json.loads(json.dumps(options)))  # as `jaxmpm resume` reads it back
    assert float(again.sim.material.E) == 50.0 and (again.dt, again.steps) == (setup.dt, setup.steps)

    bar_file.write_text(BAR_FILE + "\n# edited\n")
    with pytest.raises(jm.InputError, match=rf"scene file {bar_file} changed since the run began \(sha256 "
                                            rf"{digest[:12]}\.\.\. then"):
        cli.setup_from_options(options)
    bar_file.unlink()
    with pytest.raises(jm.InputError, match="does not exist; the run being resumed was started from it"):
        cli.setup_from_options(options)


@pytest.mark.slow
def test_a_shape_a_scene_file_registers_is_taken_by_shape(tmp_path, recorded, capsys):
    """--shape had argparse choices fixed before the scene file was imported: a shape the file
    registers was refused ("invalid choice"), while a scheme it registers was taken."""
    path = tmp_path / "my_shape.py"
    path.write_text('''"""A bar on a shape of one's own."""
import jaxmpm as jm


class FileQuadratic(jm.QuadraticBSpline):
    """The quadratic B-spline under a name of the file's own."""


jm.register_shape("file_quadratic", FileQuadratic)


def scene(shape="linear", cells=8, t_end=2.0, frames=8):
    """The fixed-free bar, 8 cells."""
    return jm.scene("bar", shape=shape, cells=cells, t_end=t_end, frames=frames)
''')
    try:
        assert run_cli(["run", str(path), "--shape", "file_quadratic", "--out", str(tmp_path / "o.h5")]) is None
        (setup, options), = recorded
        assert type(setup.sim.shape).__name__ == "FileQuadratic" and options["shape"] == "file_quadratic"
        assert run_cli(["run", "bar", "--shape", "foo", "--out", str(tmp_path / "o.h5")]) == 2
        assert one_error_line(capsys).endswith("unknown shape 'foo'; choose linear | ugimp | quadratic | cubic | "
                                               "file_quadratic")
        jm.SHAPES._entries.pop("file_quadratic")  # as in a new process: the file's help registers it again
        assert run_cli(["run", str(path), "--help"]) == 0
        assert "--shape linear|ugimp|quadratic|cubic|file_quadratic" in capsys.readouterr().out
    finally:
        jm.SHAPES._entries.pop("file_quadratic", None)


def test_set_reaches_a_scene_keyword_without_an_option_and_is_stored_for_resume(recorded, capsys, tmp_path):
    """mpm88's n_particles, mms's dim, the bar's boundary: keywords the command line could not reach."""
    from jaxmpm.scenes.command import setup_from_options

    out = str(tmp_path / "o.h5")
    assert run_cli(["run", "mpm88", "--set", "n_particles=1024", "--set", "speed=2", "--out", out]) is None
    assert run_cli(["run", "mms", "--set", "dim=2", "--cells", "4", "--out", out]) is None
    assert run_cli(["run", "bar", "--set", "boundary=mirror", "--out", out]) is None  # a bare word: text
    (mpm88, stored), (mms, _), (bar, _) = recorded
    assert mpm88.state.x.shape == (1024, 2) and float(mpm88.state.v[0, 1]) == -2.0 and mms.sim.grid.dim == 2
    assert any(isinstance(condition, jm.Mirror) for condition in bar.sim.boundary)
    assert stored["set"] == ["n_particles=1024", "speed=2"]  # in the file's command: resume rebuilds it
    assert setup_from_options(stored).state.x.shape == (1024, 2)
    for argv, words in [(["--set", "E=3"], "--set E: 'mpm88' takes it as the option --E; use that"),
                        (["--set", "foo=1"], "--set foo: scene 'mpm88' has no keyword 'foo'; its keywords without an "
                                             "option of their own: n_particles=8192, n_grid=128, bound=3, speed=1.0, "
                                             "seed=0"),
                        (["--set", "n_particles"], "--set 'n_particles': give NAME=VALUE"),
                        (["--set", "seed=1", "--set", "seed=2"], "--set seed is given twice"),
                        (["--set", "n_particles=0"], "mpm88: n_particles = 0 must be a positive integer"),
                        # no literal (literal_eval raised TypeError, a traceback): the text, which the scene refuses
                        (["--set", "n_particles={[1]: 2}"], "mpm88: n_particles = '{[1]: 2}' must be a positive")]:
        assert run_cli(["run", "mpm88", *argv, "--out", out]) == 2
        assert words in one_error_line(capsys)
    assert run_cli(["run", "heat1d", "--set", "E=3", "--out", out]) == 2  # an option it does not take at all
    assert "--set E: scene 'heat1d' has no keyword 'E'; its keywords without an option of their own: length=1.0" in \
        one_error_line(capsys)
    assert run_cli(["scenes"]) == 0
    assert "  --set n_particles=8192, n_grid=128, bound=3, speed=1.0, seed=0" in capsys.readouterr().out


def test_scene_file_run_interrupted_then_resumed_equals_the_whole_run(bar_file, monkeypatch, capsys):
    """`jaxmpm run my_bar.py`, stopped by SIGINT after its first chunk, then `jaxmpm resume`: the
    file equals the uninterrupted run's bit for bit."""
    whole, cut = bar_file.parent / "whole.h5", bar_file.parent / "cut.h5"
    assert run_cli(["run", str(bar_file), "--no-progress", "--out", str(whole)]) == 0

    class SignalAfterFirst(jm.H5Writer):
        def append(self, history):
            super().append(history)
            signal.raise_signal(signal.SIGINT)

    with monkeypatch.context() as m:
        m.setattr(jm, "H5Writer", SignalAfterFirst)
        assert run_cli(["run", str(bar_file), "--no-progress", "--out", str(cut)]) == 130
    with h5py.File(cut, "r") as f:
        assert not f["state"].attrs["complete"]
    assert run_cli(["resume", str(cut), "--no-progress"]) == 0
    assert_same_files(whole, cut)


@pytest.mark.parametrize("text, words", [
    (None, ["does not exist"]),
    ("def build(cells=8):\n    pass\n", ["defines no function `scene`", "def scene("]),
    ("import numpy\nraise ValueError('no mesh\\nhere')\n", ["cannot import scene file", "ValueError: no mesh here",
                                                            "(line 2)"]),
    ("def scene(:\n", ["cannot import scene file", "SyntaxError", "(line 1)"]),
    ("from jaxmpm import scene\n", ["defines no function `scene`"]),
    ("def scene(cells=8):\n    return 1 / 0\n", ["`scene` raised ZeroDivisionError: division by zero (line 2)"]),
    ("def scene(cells=8):\n    return cells\n", ["`scene` returned int, not a jm.scenes.Setup"]),
    ("def scene(cells=8):\n    pass\n", ["option --spacing does not apply to scene", "it takes --cells"]),
    ("def scene(cells=8):\n    pass\n", ["option --dtype does not apply"]),
    ("def scene(cells=8):\n    pass\n", ["my_scene.py: cells = 0 must be a positive integer"]),
])
def test_scene_file_errors_exit_2_in_one_line_naming_the_file(tmp_path, capsys, text, words):
    path = tmp_path / "my_scene.py"
    if text is not None:
        path.write_text(text)
    extra = {"option --spacing": ["--spacing", "0.1"], "option --dtype": ["--dtype", "f32"],
             "cells = 0": ["--cells", "0"]}
    argv = ["run", str(path), *next((v for k, v in extra.items() if k in words[0]), []), "--out",
            str(tmp_path / "o.h5")]
    assert run_cli(argv) == 2
    line = one_error_line(capsys)
    assert str(path) in line or "my_scene.py" in line
    for word in words:
        assert word in line, (word, line)


# --------------------------------------------------------------------------- the registry
def tiny_bar(cells=4, t_end=0.5, frames=2, E=100.0, dtype=None):
    """A four-cell bar.

    (more text that is not the description)"""
    return jm.scene("bar", cells=cells, t_end=t_end, frames=frames, E=E, dtype=dtype)


def test_register_scene_reaches_jm_scene_the_listing_and_run(registry, recorded, tmp_path, capsys):
    jm.register_scene("tiny_bar", tiny_bar)
    assert registry["tiny_bar"][1] == "A four-cell bar."  # the docstring's first line
    assert jm.scene("tiny_bar", cells=2).state.x.shape == (4, 1)
    with pytest.raises(jm.InputError, match=r"tiny_bar: cells = 0 must be a positive integer"):
        jm.scene("tiny_bar", cells=0)  # checked like a built-in scene
    with pytest.raises(jm.InputError, match=r"the scene name 'tiny_bar' is taken \(A four-cell bar\.\); choose "
                                            r"another name, or pass replace=True"):
        jm.register_scene("tiny_bar", lambda **kw: tiny_bar(**kw), "another")
    jm.register_scene("tiny_bar", tiny_bar, "the same builder again")  # a notebook cell run twice
    assert registry["tiny_bar"][1] == "the same builder again"
    with pytest.raises(jm.InputError, match="the scene name 'bar' is taken"):
        jm.register_scene("bar", tiny_bar)
    with pytest.raises(jm.InputError, match="name = 'my scene' must be a word"):
        jm.register_scene("my scene", tiny_bar)
    jm.register_scene("tiny_bar", tiny_bar, "a bar of four cells", replace=True)

    assert run_cli(["scenes"]) == 0
    lines = capsys.readouterr().out.splitlines()
    at = next(i for i, line in enumerate(lines) if line.startswith("tiny_bar"))
    assert lines[at].endswith("a bar of four cells")
    assert lines[at + 1].split() == ["--cells", "4,", "--t-end", "0.5,", "--frames", "2,", "--E", "100"]

    assert run_cli(["run", "tiny_bar", "--cells", "3", "--E", "7", "--out", str(tmp_path / "o.h5")]) is None
    (setup, options), = recorded
    assert setup.state.x.shape == (6, 1) and float(setup.sim.material.E) == 7.0
    assert options["scene"] == "tiny_bar" and "scene_sha256" not in options


def test_entry_point_scenes_load_when_the_command_line_starts(registry, recorded, monkeypatch, tmp_path, capsys):
    """Each entry point of the group jaxmpm.scenes: its name the scene's, the builder's docstring
    the description; one that fails to import, or takes a name in use, is left out with a warning
    and `jaxmpm run NAME` says why."""
    def broken():
        raise ModuleNotFoundError("No module named 'missing_pkg'")

    points = [types.SimpleNamespace(name="pkg_bar", value="pkg.scenes:tiny_bar", load=lambda: tiny_bar),
              types.SimpleNamespace(name="broken", value="missing_pkg:scene", load=broken),
              types.SimpleNamespace(name="bar", value="pkg.scenes:tiny_bar", load=lambda: tiny_bar)]
    listed = []
    monkeypatch.setattr(scenes, "scene_entry_points", lambda: listed.append(1) or points)
    monkeypatch.setattr(scenes, "_entry_points_loaded", False)
    monkeypatch.setattr(scenes, "ENTRY_POINT_ERRORS", {})
    assert "pkg_bar" not in jm.SCENES and not listed  # not at import

    assert run_cli(["scenes"]) == 0
    out, err = capsys.readouterr()
    assert any(line.startswith("pkg_bar") and line.endswith("A four-cell bar.") for line in out.splitlines())
    assert "jaxmpm: warning: scene entry point broken = missing_pkg:scene (group jaxmpm.scenes) failed to load: " \
           "ModuleNotFoundError: No module named 'missing_pkg'" in err
    assert "entry point bar = pkg.scenes:tiny_bar (group jaxmpm.scenes) is not registered: register_scene: the " \
           "scene name 'bar' is taken" in err
    assert registry["bar"][0] is not tiny_bar and listed == [1]

    assert run_cli(["run", "pkg_bar", "--cells", "2", "--out", str(tmp_path / "o.h5")]) is None
    assert recorded[0][0].state.x.shape == (4, 1)
    assert run_cli(["run", "broken", "--out", str(tmp_path / "o.h5")]) == 2
    assert "failed to load: ModuleNotFoundError" in one_error_line(capsys)
    assert listed == [1]  # read once


def test_jm_scene_loads_the_entry_points_for_a_name_it_does_not_know(registry, monkeypatch):
    monkeypatch.setattr(scenes, "scene_entry_points", lambda: [
        types.SimpleNamespace(name="pkg_bar", value="pkg:tiny_bar", load=lambda: tiny_bar)])
    monkeypatch.setattr(scenes, "_entry_points_loaded", False)
    assert jm.scene("pkg_bar", cells=1).state.x.shape == (2, 1)


# --------------------------------------------------------------------------- help and defaults
def help_text(capsys, *argv) -> str:
    assert run_cli(["run", *argv]) == 0
    return " ".join(capsys.readouterr().out.split())


def test_run_scene_help_lists_its_options_with_its_defaults(capsys):
    bar = help_text(capsys, "bar", "--help")
    assert "Run bar: 1D fixed-free elastic bar" in bar
    assert "options of bar:" in bar and "run options:" in bar
    for shown in ("--cells N cells along each axis (default 16)", "--cfl C time step dt = C h / c (default 0.1)",
                  "--scheme flip|", "velocity update (default flip)", "--alpha-g A grid damping alpha_g in 1/time "
                  "(default 0)", "(default 100)", "--out FILE.h5", "--max-steps N"):
        assert shown in bar, shown
    for absent in ("--spacing", "--contact", "--theta", "--nu", "--gravity", "default: bar 16"):
        assert absent not in bar, absent

    slide = help_text(capsys, "--cells", "8", "slide", "-h")  # SCENE after an option and its value
    for shown in ("--spacing H grid spacing (default 0.025)", "--dt DT time step (default from cfl)",
                  "--theta DEG", "(default 30)", "--contact {none,stick,frictionless,coulomb}", "(default coulomb)",
                  "--gravity G|GX,GY[,GZ]", "(default 9.8)", "--nu NU Poisson's ratio nu in (-1, 0.5) (default 0.3)"):
        assert shown in slide, shown
    assert "--cells" not in slide.split("options of slide:")[1]

    cylinder = help_text(capsys, "cylinder", "--help")
    assert "--alpha-g A grid damping alpha_g in 1/time (default the breathing mode's frequency)" in cylinder
    assert "or none (default stress)" in cylinder and "mpm88 pressure" not in cylinder  # its own --fields default
    assert "or none (default none)" in help_text(capsys, "heat1d", "--help")

    with pytest.raises(SystemExit) as generic:  # without SCENE: argparse's help of every option
        cli.main(["run", "--help"])
    assert generic.value.code == 0
    text = " ".join(capsys.readouterr().out.split())
    assert "--spacing H" in text and "--theta DEG" in text and "(default: bar 16, mms 16" in text
    assert "`jaxmpm run SCENE --help` lists the options SCENE takes" in text

    assert run_cli(["run", "nope", "--help"]) == 2
    assert "unknown scene 'nope'" in one_error_line(capsys)


def test_scenes_prints_every_default_as_a_value(capsys):
    assert run_cli(["scenes"]) == 0
    lines = capsys.readouterr().out.splitlines()
    options = {line.split()[0]: dict(item.split(" ", 1) for item in lines[i + 1].strip().split(", "))
               for i, line in enumerate(lines) if not line.startswith(" ")}
    for scene, shown in options.items():
        for option, value in shown.items():
            assert value not in ("derived", "None", "False", "set by the scene"), (scene, option, value)
    assert options["spin"]["--dt"] == "from cfl" and options["slide"]["--dt"] == "from cfl"
    assert options["bar"]["--alpha-g"] == "0" and options["mpm88"]["--alpha-p"] == "0"
    assert options["thermal_bar"]["--alpha-p"] == "20"
    assert options["cylinder"]["--alpha-g"] == "the breathing mode's frequency"
    assert options["mpm88"]["--gravity"] == "9.8" and options["slide"]["--theta"] == "30"
    assert options["disks"]["--nu"] == "0.3" and options["rings"]["--E"] == "1e+08"
    assert "--damping-approach" not in options["bar"]


@pytest.mark.slow
def test_derived_defaults_are_what_the_scenes_build():
    """The numbers DERIVED_DEFAULTS states: thermal_bar's particle damping 20, spin's t_end 1,
    bars_impact's 4 L/c, the cylinder's grid damping at the breathing mode's frequency."""
    assert float(jm.scene("thermal_bar", cells=4, t_end=1e-3, frames=1).sim.damping.particle) == 20.0
    spin = dict(spacing=0.25, frames=1)
    assert jm.scene("spin", **spin).steps == jm.scene("spin", t_end=1.0, **spin).steps
    bars = dict(cells=4, frames=1, E=400.0, length=2.0)  # c = 20: 4 L/c = 0.4
    assert jm.scene("bars_impact", **bars).steps == jm.scene("bars_impact", t_end=0.4, **bars).steps
    E, nu, rho, inner, outer = 1000.0, 0.3, 1.0, 1.0, 2.0
    omega0 = math.sqrt(E / (rho * (1 - nu * nu))) / (0.5 * (inner + outer))
    damping = jm.scene("cylinder", cells=4, t_end=1e-3, frames=1).sim.damping
    assert float(damping.grid) == pytest.approx(omega0, rel=1e-12)


# --------------------------------------------------------------------------- material constants and gravity
def test_material_options_reach_the_setup():
    bar = cli.build_setup(parsed("bar", "--cells", "4", "--E", "50", "--density", "2"))
    assert float(bar.sim.material.E) == 50.0 and float(bar.sim.material.density) == 2.0
    assert bar.params["E"] == 50.0 and bar.dt == pytest.approx(0.1 * (25 / 4) / 5.0, rel=1e-12)  # c = 5


@pytest.mark.slow
def test_poisson_ratio_and_gravity_options_reach_the_setup():
    build_setup = cli.build_setup
    disks = build_setup(parsed("disks", "--spacing", "0.25", "--nu", "0.25", "--t-end", "0.01"))
    assert float(disks.sim.material.nu) == 0.25
    g, theta = 5.0, 10.0
    slide = build_setup(parsed("slide", "--spacing", "0.1", "--dt", "1e-3", "--t-end", "0.01", "--gravity", str(g),
                               "--theta", str(theta)))
    tilt = math.radians(theta)
    assert slide.sim.gravity.tolist() == pytest.approx([g * math.sin(tilt), -g * math.cos(tilt)], rel=1e-12)
    mpm88 = build_setup(parsed("mpm88", "--gravity", "1.5,-2", "--t-end", "1e-3"))
    assert mpm88.sim.gravity.tolist() == [1.5, -2.0] and mpm88.params["gravity"] == [1.5, -2.0]
    assert build_setup(parsed("mpm88", "--gravity", "-3", "--t-end", "1e-3")).sim.gravity.tolist() == [0.0, 3.0]


@pytest.mark.parametrize("argv, words", [
    (["bar", "--E", "-1"], ["bar: E = -1.0 must be positive"]),
    (["bar", "--density", "0"], ["bar: density = 0.0 must be positive"]),
    (["disks", "--nu", "0.5"], ["disks: nu = 0.5 must lie in (-1, 0.5)"]),
    (["slide", "--theta", "90"], ["slide: theta = 90.0 must lie in [0, 90)"]),
    (["slide", "--gravity", "0,-9.8"], ["slide: gravity = (0.0, -9.8) must be one number"]),
    (["mpm88", "--gravity", "1,2,3"], ["mpm88: gravity = (1.0, 2.0, 3.0) has 3 components but the scene is 2D"]),
    (["mpm88", "--gravity", "1,nan"], ["mpm88: gravity[1] = nan must be a finite number"]),
    (["mpm88", "--gravity", "1,2,3,4"], ["argument --gravity: '1,2,3,4' has 4 components"]),
    (["mpm88", "--gravity", "down"], ["argument --gravity: 'down' is not G or GX,GY[,GZ]"]),
    (["bar", "--theta", "10"], ["option --theta does not apply to scene 'bar'"]),
    (["heat1d", "--nu", "0.3"], ["option --nu does not apply to scene 'heat1d'"]),
])
def test_bad_material_or_gravity_values_exit_2_naming_them(tmp_path, capsys, argv, words):
    assert run_cli(["run", *argv, "--out", str(tmp_path / "o.h5")]) == 2
    line = one_error_line(capsys)
    for word in words:
        assert word in line, (word, line)


def test_version(capsys):
    import jax

    with pytest.raises(SystemExit) as done:
        cli.main(["--version"])
    assert done.value.code == 0
    assert capsys.readouterr().out.startswith(f"jaxmpm {jm.__version__} (jax {jax.__version__}, Python ")


def test_negative_vector_values_reach_the_option():
    """`--gravity -1,0` reads as the option's value (argparse would take "-1,0" for an option)."""
    argv = cli._negative_values_joined(["run", "mpm88", "--gravity", "-1,0", "--out", "o.h5"])
    assert cli.build_parser().parse_args(argv).gravity == (-1.0, 0.0)
