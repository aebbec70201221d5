"""The ``jaxmpm`` command line: ``scenes``, ``run`` (HDF5 + summary), and its errors (status 2).

All runs use the bar scene with ``--t-end 2 --frames 8``: dt = 0.1 h / c = 0.1 (25/16) / 10 =
0.015625, 128 steps saved every 16 (9 frames), one compiled chunk per scheme.  The bar's initial
energy is exactly rho v0^2 L / 4 = 0.0625: the particles sit at the midpoints of equal intervals,
where the midpoint rule integrates sin^2(beta1 x) = (1 - cos(pi x / L)) / 2 over [0, L] exactly.
"""

from __future__ import annotations

import math
import re
import subprocess
import sys

import numpy as np
import pytest
from cases import run_cli

import jaxmpm as jm
from jaxmpm.cli import build_parser

E, RHO, L, V0, CELLS = 100.0, 1.0, 25.0, 0.1, 16
DT = 0.1 * (L / CELLS) / math.sqrt(E / RHO)  # bar default cfl 0.1
SHORT = ["--t-end", "2", "--frames", "8"]  # 128 steps, a frame every 16 -> 9 frames


def summary_value(text, key):
    """The value on the summary line ``key  value`` (key and value are separated by 2+ spaces)."""
    rows = dict(re.split(r"\s{2,}", line.strip(), maxsplit=1) for line in text.splitlines() if "  " in line)
    return rows[key]


def test_scenes_lists_each_scene_with_its_options_and_defaults(capsys):
    """One line per scene (name and description), then its options and their defaults."""
    assert run_cli(["scenes"]) == 0
    lines = capsys.readouterr().out.splitlines()
    heads, options = lines[0::2], lines[1::2]
    assert [line.split()[0] for line in heads] == list(jm.SCENES) and {"bar", "disks"} <= set(jm.SCENES)
    for line, (_, description) in zip(heads, jm.SCENES.values()):
        assert line.endswith(description)
    bar = dict(item.split(" ", 1) for item in options[0].strip().split(", "))
    assert bar["--cells"] == "16" and bar["--cfl"] == "0.1" and bar["--t-end"] == "40"
    assert bar["--scheme"] == "flip" and bar["--shape"] == "linear" and "--dt" not in bar
    mpm88 = dict(item.split(" ", 1) for item in options[4].strip().split(", "))
    assert mpm88["--scheme"] == "apic" and mpm88["--dt"] == "0.0002"


@pytest.mark.parametrize("scene", list(jm.SCENES))
def test_part_defaults_are_what_the_scenes_build(scene):
    """The scheme and shape `jaxmpm scenes` and --help show are those the builder uses."""
    from jaxmpm.scenes._common import PART_DEFAULTS

    small = {"bar": dict(cells=4), "disks": dict(spacing=0.25), "spin": dict(spacing=0.25),
             "rings": dict(spacing=1.0), "mpm88": dict(n_particles=64, n_grid=8), "mms": dict(cells=4),
             "vortex": dict(spacing=0.25), "bars_impact": dict(cells=4), "slide": dict(spacing=0.1),
             "heat1d": dict(cells=4), "heat_step": dict(cells=4), "diffusion2d": dict(cells=4),
             "thermal_bar": dict(cells=4), "cylinder": dict(cells=4)}[scene]
    setup = jm.scene(scene, t_end=1e-3, frames=1, **small)
    assert jm.scheme_from_name(PART_DEFAULTS[scene]["scheme"]).__class__ is type(setup.sim.scheme)
    ppc = getattr(setup.sim.shape, "ppc", None)
    shape = jm.shape_from_name(PART_DEFAULTS[scene]["shape"], **({"ppc": ppc} if ppc else {}))
    assert type(shape) is type(setup.sim.shape)


def test_help_shows_each_scenes_default():
    text = build_parser()._subparsers._group_actions[0].choices["run"].format_help()
    flat = " ".join(text.split())
    assert ("(default: bar 16, mms 16, bars_impact 32, heat1d 32, heat_step 64, diffusion2d 16, thermal_bar 32, "
            "cylinder 32; "
            "other scenes do not take it)") in flat  # --cells
    assert "(default: heat1d 1, heat_step 1; other scenes do not take it)" in flat  # --conductivity
    assert "mpm88 apic" in flat and "disks ugimp" in flat
    assert "(default: disks none, rings none, bars_impact frictionless, slide coulomb; other scenes" in flat
    assert "(default: disks 0, rings 0, slide 0.2; other scenes do not take it)" in flat  # --friction


def test_python_m_jaxmpm_scenes():
    out = subprocess.run([sys.executable, "-m", "jaxmpm", "scenes"], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    names = [line.split()[0] for line in out.stdout.splitlines() if not line.startswith(" ")]
    assert names == list(jm.SCENES) and {"bar", "disks"} <= set(names)


@pytest.mark.slow
def test_run_bar_writes_hdf5_and_summary(tmp_path, capsys):
    path = tmp_path / "bar.h5"
    assert run_cli(["run", "bar", *SHORT, "--out", str(path)]) == 0  # with the progress bar
    out = capsys.readouterr().out
    res = jm.load_h5(path)
    n = CELLS * 2  # 2 particles per cell
    assert res.attrs["scene"] == "bar" and res.attrs["scheme"] == "FLIP"
    assert res.attrs["order"] == 1 and res.attrs["beta"] == 1.0
    assert res.attrs["dtype"] == "float64" and res.attrs["dt"] == DT
    assert res["time"].shape == (9,) and res["particles/x"].shape == (9, n, 1)
    assert res["particles/v"].shape == (9, n, 1) and res["particles/mass"].shape == (n,)
    assert res["energy/kinetic"].shape == (9,) and res["momentum/linear"].shape == (9, 1)
    np.testing.assert_allclose(res["time"], 16 * DT * np.arange(9), rtol=0, atol=1e-12)
    total = res["energy/kinetic"] + res["energy/strain"]
    assert total[0] == pytest.approx(RHO * V0**2 * L / 4, rel=1e-12)  # midpoint quadrature is exact

    assert summary_value(out, "scene") == "bar"
    assert summary_value(out, "particles") == str(n)
    assert summary_value(out, "steps").startswith("128 ")
    assert float(summary_value(out, "dt")) == DT
    # every file written: the HDF5 file and the XDMF sidecar with its per-frame views
    assert summary_value(out, "output") == f"{path}, {path.with_suffix('.xdmf')}, {path.with_suffix('.xdmf.h5')}"
    energy = re.fullmatch(r"initial (\S+), final (\S+), ratio (\S+)", summary_value(out, "energy K+U"))
    e0, e1, ratio = map(float, energy.groups())
    assert e0 == pytest.approx(total[0], rel=1e-5) and e1 == pytest.approx(total[-1], rel=1e-5)
    assert ratio == pytest.approx(total[-1] / total[0], abs=1e-6)
    assert float(summary_value(out, "dissipated")) == pytest.approx(res["energy/dissipated"][-1], rel=1e-5, abs=1e-300)


@pytest.mark.slow
@pytest.mark.parametrize(
    "options, attrs, n",
    [
        (["--scheme", "xpic:3", "--dtype", "f32"], dict(scheme="XPIC", order=3, beta=0.0, dtype="float32"), 32),
        (["--scheme", "fmpm:2", "--shape", "ugimp", "--ppc", "3", "--alpha-g", "0.5", "--alpha-p", "0.25"],
         dict(scheme="FMPM", order=2, beta=0.0, shape="UGIMP", ppc=3, alpha_g=0.5, alpha_p=0.25), 48),
        (["--scheme", "blend:0.9"], dict(scheme="FLIP", order=1, beta=0.9, shape="Linear",
                                         **{"damping approach": "velocity", "damping varies": 0}), 32),
        (["--alpha-g", "0.5", "--damping-approach", "force"],
         dict(alpha_g=0.5, alpha_p=0.0, **{"damping approach": "force", "damping varies": 0}), 32),
        (["--scheme", "xpic:2", "--beta", "0.5", "--update", "MUSL"], dict(scheme="XPIC", order=2, beta=0.5,
                                                                            update="MUSL"), 32),
    ],
)
def test_run_scheme_options_reach_hdf5(tmp_path, capsys, options, attrs, n):
    path = tmp_path / "run.h5"
    assert run_cli(["run", "bar", *SHORT, *options, "--out", str(path), "--no-progress"]) == 0
    res = jm.load_h5(path)
    for key, value in attrs.items():
        if isinstance(value, float):
            assert res.attrs[key] == pytest.approx(value, rel=1e-7), key
        else:
            assert res.attrs[key] == value, key
    assert res["particles/x"].shape == (9, n, 1)
    assert summary_value(capsys.readouterr().out, "particles") == str(n)


def test_cache_option_switches_on_the_compilation_cache(tmp_path, capsys, monkeypatch):
    """`--cache` calls jm.compilation_cache() (whose own tests are in test_compilation_cache.py)
    once, before the run; it is not a scene option (not stored for `resume`); a folder it cannot
    use exits 2 in one line."""
    import h5py

    calls = []
    monkeypatch.setattr(jm, "compilation_cache", lambda: calls.append("called"))
    path = tmp_path / "cached.h5"
    assert run_cli(["run", "bar", *SHORT, "--out", str(path), "--no-progress", "--cache"]) == 0
    assert calls == ["called"]
    with h5py.File(path, "r") as f:
        assert "cache" not in f.attrs["command"]
    assert run_cli(["run", "bar", *SHORT, "--out", str(tmp_path / "plain.h5"), "--no-progress"]) == 0
    assert calls == ["called"]

    def refuse():
        raise jm.InputError("compilation_cache: path '/nowhere' is not a folder; pass a folder")

    monkeypatch.setattr(jm, "compilation_cache", refuse)
    capsys.readouterr()
    assert run_cli(["run", "bar", *SHORT, "--out", str(tmp_path / "x.h5"), "--no-progress", "--cache"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "is not a folder" in err[0], err


def test_unknown_scheme_exits_2_naming_it(tmp_path, capsys):
    path = tmp_path / "x.h5"
    assert run_cli(["run", "bar", "--scheme", "foo:3", "--out", str(path)]) == 2
    err = capsys.readouterr().err
    assert "unknown scheme 'foo:3'" in err and "xpic:M" in err
    assert not path.exists()


@pytest.mark.parametrize("scene, option, value", [("bar", "--spacing", "0.1"), ("disks", "--cells", "8"),
                                                  ("disks", "--cfl", "0.5"), ("bar", "--dt", "0.01"),
                                                  ("bar", "--contact", "stick"), ("spin", "--friction", "0.1"),
                                                  ("bars_impact", "--friction", "0.1")])
def test_option_the_scene_does_not_take_exits_2(tmp_path, capsys, scene, option, value):
    path = tmp_path / "x.h5"
    assert run_cli(["run", scene, option, value, "--out", str(path)]) == 2
    err = capsys.readouterr().err
    assert f"option {option} does not apply to scene {scene!r}" in err
    assert not path.exists()


@pytest.mark.parametrize("options, words", [
    (["--contact", "glue"], ["--contact", "invalid choice: 'glue'"]),
    (["--contact", "coulomb", "--friction", "-0.5"], ["friction = -0.5", ">= 0"]),
    (["--friction", "0.3"], ["friction = 0.3", "contact='coulomb'"]),  # disks' default contact is none
    (["--contact", "stick", "--friction", "0.3"], ["friction = 0.3", "contact='stick'"]),
])
def test_bad_contact_options_exit_2_naming_them(tmp_path, capsys, options, words):
    path = tmp_path / "x.h5"
    assert run_cli(["run", "disks", *options, "--out", str(path)]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1
    for word in words:
        assert word in err, (word, err)
    assert not path.exists()


def test_contact_options_reach_the_scene():
    """--contact/--friction become the scene's keywords: a two-material model with jm.Contact."""
    from jaxmpm.cli import build_parser, build_setup

    args = build_parser().parse_args(["run", "disks", "--spacing", "0.25", "--t-end", "0.01", "--contact", "coulomb",
                                      "--friction", "0.3", "--out", "unused.h5"])
    setup = build_setup(args)
    contact = setup.sim.term(jm.Contact)
    assert contact.law == "coulomb" and float(contact.friction) == 0.3
    assert setup.params["contact"] == "coulomb" and setup.params["friction"] == 0.3
    ids = np.asarray(setup.state.fields["material"])
    assert set(ids.tolist()) == {0.0, 1.0} and ids[:setup.params["n_first"]].max() == 0.0


def test_unstable_run_exits_2_naming_the_step(tmp_path, capsys):
    """CFL 3 (dt = 0.46875 > h/c = 0.15625): 5 steps; the error names the first bad step and
    the file keeps exactly the frames before it (one per step)."""
    path = tmp_path / "unstable.h5"
    with pytest.warns(jm.StableTimeStepWarning):
        status = run_cli(["run", "bar", "--cfl", "3", *SHORT, "--out", str(path), "--no-progress"])
    assert status == 2
    err = capsys.readouterr().err
    match = re.search(r"unstable at step (\d+)", err)
    assert match and str(path) in err and "kept" in err
    step = int(match.group(1))
    assert 1 <= step <= 5
    dt = 3 * DT / 0.1
    time = jm.load_h5(path)["time"]
    np.testing.assert_allclose(time, dt * np.arange(step), rtol=1e-12)  # frames 0 .. step-1


def test_damping_approach_needs_a_grid_rate_and_reaches_the_model(tmp_path, capsys):
    """--damping-approach sets jm.Damping's approach (001 §5.2.2); alone (no --alpha-g, the rate it
    shapes) it exits 2 in one line naming both options."""
    from jaxmpm.cli import build_parser, build_setup

    args = build_parser().parse_args(["run", "bar", *SHORT, "--alpha-g", "0.5", "--alpha-p", "0.1",
                                      "--damping-approach", "momentum", "--out", "unused.h5"])
    damping = build_setup(args).sim.damping
    assert damping.approach == "momentum" and float(damping.grid) == 0.5 and float(damping.particle) == 0.1
    path = tmp_path / "x.h5"
    assert run_cli(["run", "bar", *SHORT, "--damping-approach", "force", "--out", str(path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--damping-approach force" in err[0] and "--alpha-g" in err[0]
    assert not path.exists()
