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

import equinox as eqx
import jax.numpy as jnp
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
    heads = [line for line in lines if not line.startswith(" ")]
    options = [lines[lines.index(head) + 1] for head in heads]  # then, where it has any, the --set line
    sets = {head.split()[0]: lines[lines.index(head) + 2].strip() for head in heads
            if lines.index(head) + 2 < len(lines) and lines[lines.index(head) + 2].strip().startswith("--set ")}
    assert sets["mpm88"] == "--set n_particles=8192, n_grid=128, bound=3, speed=1.0, seed=0" and "incline" not in sets
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
             "thermal_bar": dict(cells=4), "cylinder": dict(cells=4),
             "column_collapse": dict(cells=2, aspect=1.0), "dam_break": dict(cells=2),
             "incline": dict(spacing=0.05), "taylor_bar": dict(cells=1)}[scene]
    setup = jm.scene(scene, t_end=1e-3, frames=1, **small)
    assert jm.scheme_from_name(PART_DEFAULTS[scene]["scheme"]).__class__ is type(setup.sim.scheme)
    ppc = getattr(setup.sim.shape, "ppc", None)
    shape = jm.shape_from_name(PART_DEFAULTS[scene]["shape"], **({"ppc": ppc} if ppc else {}))
    assert type(shape) is type(setup.sim.shape)


def test_help_shows_each_scenes_default():
    text = build_parser()._subparsers._group_actions[0].choices["run"].format_help()
    flat = " ".join(text.split())
    assert ("(default: bar 16, mms 16, bars_impact 32, heat1d 32, heat_step 64, diffusion2d 16, thermal_bar 32, "
            "dam_break 8, cylinder 32") in flat  # --cells (then the scenes registered after cylinder)
    assert "(default: heat1d 1, heat_step 1; other scenes do not take it)" in flat  # --conductivity
    assert "mpm88 apic" in flat and "disks ugimp" in flat
    assert "(default: disks none, rings none, bars_impact frictionless, slide coulomb; other scenes" in flat
    assert "(default: disks 0, rings 0, slide 0.2, incline 0.2; other scenes do not take it)" in flat  # --friction


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
    energy = re.fullmatch(r"initial (\S+), final (\S+), ratio (\S+)", summary_value(out, "energy K+U+V_g"))
    e0, e1, ratio = map(float, energy.groups())
    assert e0 == pytest.approx(total[0], rel=1e-5) and e1 == pytest.approx(total[-1], rel=1e-5)
    assert ratio == pytest.approx(total[-1] / total[0], abs=1e-6)
    for key, series in (("kinetic K", res["energy/kinetic"]), ("strain U", res["energy/strain"])):  # the parts
        start, end = map(float, re.fullmatch(r"initial (\S+), final (\S+)", summary_value(out, key)).groups())
        assert start == pytest.approx(series[0], rel=1e-5, abs=1e-300) and end == pytest.approx(series[-1], rel=1e-5)
    assert summary_value(out, "gravitational V_g") == "0 (no gravity)"
    assert float(summary_value(out, "dissipated")) == pytest.approx(res["energy/dissipated"][-1], rel=1e-5, abs=1e-300)
    # the times: compilation and run apart, the wall time from the process's start, the rate over the run alone
    compile_s = float(summary_value(out, "compile time").split()[0])
    run_s, steps = re.fullmatch(r"(\S+) s \((\d+) steps, writing included\)", summary_value(out, "run time")).groups()
    wall = re.fullmatch(r"(\S+) s since the process started \(start-up and set-up \S+ s, compile (\S+) s, "
                        r"run (\S+) s\)", summary_value(out, "wall time"))
    assert compile_s > 0 and float(run_s) > 0 and steps == "128"
    assert float(wall[1]) >= compile_s + float(run_s) and (float(wall[2]), float(wall[3])) == (compile_s, float(run_s))
    rate = float(summary_value(out, "particle-steps/s").removesuffix(" (over the run time)"))
    slowest, fastest = (n * 128 / (float(run_s) + d) for d in (5e-4, -5e-4))  # the run time to 3 decimals
    assert slowest * (1 - 5e-4) <= rate <= fastest * (1 + 5e-4)  # and the rate to 4 digits


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


def test_no_cache_switches_the_compilation_cache_off(tmp_path, monkeypatch):
    """The cache is on by default (test_compilation_cache.py); `--no-cache` calls
    jm.compilation_cache(False) once, before the run; `--cache` (the default, kept for older
    command lines) is accepted and calls nothing; neither is a scene option (not stored for `resume`)."""
    import h5py

    from jaxmpm.run import cache

    calls = []
    monkeypatch.setattr(cache, "compilation_cache", lambda *args, **kwargs: calls.append(args))
    path = tmp_path / "uncached.h5"
    assert run_cli(["run", "bar", *SHORT, "--out", str(path), "--no-progress", "--no-cache"]) == 0
    assert calls == [(False,)]
    assert run_cli(["run", "bar", *SHORT, "--out", str(tmp_path / "cached.h5"), "--no-progress", "--cache"]) == 0
    assert calls == [(False,)]
    for name in ("uncached.h5", "cached.h5"):
        with h5py.File(tmp_path / name, "r") as f:
            assert "cache" not in f.attrs["command"]


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


@pytest.mark.slow
def test_apic_dissipation_is_not_tracked_and_an_earlier_run_is_not_overwritten(tmp_path, capsys):
    """APIC reports its dissipation as NaN (the budget does not close with the affine part; jaxmpm/
    schemes/affine.py): the summary says n/a.  --out, and the XDMF sidecar of an earlier run beside
    it, are replaced only with --force."""
    path = tmp_path / "apic.h5"
    argv = ["run", "bar", *SHORT, "--scheme", "apic", "--out", str(path), "--no-progress"]
    assert run_cli(argv) == 0
    assert summary_value(capsys.readouterr().out, "dissipated") == "n/a (not tracked by APIC)"
    dissipated = jm.load_h5(path)["energy/dissipated"]
    assert dissipated[0] == 0 and np.isnan(dissipated[1:]).all()  # from the first step on
    assert run_cli(argv) == 2
    assert capsys.readouterr().err == (f"jaxmpm: error: --out {path} exists; pass --force to overwrite it, or "
                                       "choose another file\n")
    path.unlink()  # the earlier run's sidecar stays
    assert run_cli(argv) == 2
    assert capsys.readouterr().err == (
        f"jaxmpm: error: --out {path}: {path.with_suffix('.xdmf')} and {path.with_suffix('.xdmf.h5')} exist (the "
        "XDMF sidecar of an earlier run, which this run would replace); pass --force to overwrite, or choose "
        "another file\n")
    assert not path.exists()
    assert run_cli([*argv, "--force"]) == 0 and jm.load_h5(path)["time"].shape == (9,)


@pytest.mark.slow
def test_slide_summary_counts_gravity_and_its_total_is_conserved(tmp_path, capsys):
    """The frictionless slide trades the block's gravitational potential for kinetic energy: the
    summary's V_g is -sum m g.(x - x0) of the file's first and last frames, and K + U + V_g, 0 at
    the start, stays within 0.5 % of the energy exchanged (it read 0 -> 23.8 as K + U)."""
    path = tmp_path / "slide.h5"
    assert run_cli(["run", "slide", "--contact", "frictionless", "--out", str(path), "--no-progress"]) == 0
    out = capsys.readouterr().out
    res = jm.load_h5(path)
    theta = math.radians(30.0)
    g = 9.8 * np.array([math.sin(theta), -math.cos(theta)])
    drop = -np.sum(res["particles/mass"] * ((res["particles/x"][-1] - res["particles/x"][0]) @ g))
    gravitational = re.fullmatch(r"initial 0, final (\S+) \(-sum m g\.\(x - x0\): from the start\)",
                                 summary_value(out, "gravitational V_g"))
    assert float(gravitational[1]) == pytest.approx(drop, rel=1e-5) and drop < -20
    kinetic = float(summary_value(out, "kinetic K").split("final ")[1])
    assert kinetic == pytest.approx(res["energy/kinetic"][-1], rel=1e-5)
    total = re.fullmatch(r"initial 0, final (\S+)", summary_value(out, "energy K+U+V_g"))
    assert abs(float(total[1])) < 5e-3 * abs(drop)


@pytest.mark.slow
def test_particles_leaving_the_grid_are_not_called_an_instability(tmp_path, capsys):
    """disks past t = 6.8 (h = 0.1): the rebounding disks reach the edge of the scene's grid.  One
    line says where, and what to do; the frames before it stay in the file."""
    path = tmp_path / "disks.h5"
    argv = ["run", "disks", "--spacing", "0.1", "--dt", "0.01", "--t-end", "10", "--frames", "10", "--out", str(path),
            "--no-progress"]
    assert run_cli(argv) == 2
    err = capsys.readouterr().err
    assert re.fullmatch(
        r"jaxmpm: error: particles left the grid at step (\d+) \(t = (\S+)\): particle \d+ at x = \(\S+, \S+\), "
        r"where its shape function reaches past the grid's nodes; the grid spans \(-0\.3, -0\.3\) \.\. \(1\.3, 1\.3\); "
        r"the scene's grid is too small for this long a run \(not a numerical instability\): shorten --t-end; the "
        rf"frames before it were kept in {re.escape(str(path))}\n", err), err
    assert "unstable" not in err
    step = int(re.search(r"at step (\d+)", err)[1])
    time = jm.load_h5(path)["time"]
    assert time[-1] < step * 0.01 and len(time) == step // 100 + 1  # a frame every 100 steps, up to the failure


def test_wall_time_counts_from_the_process_start():
    """The summary's wall time is the process's age (Linux: /proc), not the time since jaxmpm.cli
    was imported: at least that long, and less than a day."""
    import time

    import jaxmpm.cli as cli

    assert time.perf_counter() - cli._IMPORTED - 0.02 <= cli.seconds_since_start() < 86400


def test_energy_parts_count_gravity_from_the_start():
    """sim.diagnostics' ``gravitational`` is -sum m g.x (zero at the origin); the summary counts it
    from the start, so a body lifted by dx against g = (0, -2) reads V_g = +sum m 2 dx, and K+U+V_g
    is their sum.  No gravity: V_g is 0; a body force b(x, t) has no potential, and the line says so."""
    from jaxmpm.cli import energy_rows

    grid = jm.Grid((0.0, 0.0), (4.0, 4.0), (4, 4))
    material = jm.LinearElastic(E=1.0, nu=0.0, density=2.0)
    sim = jm.Simulation(grid, "linear", material, "flip", gravity=(0.0, -2.0))
    state = sim.init(jm.fill(grid, jm.Box((1.0, 1.0), (2.0, 2.0)), ppc=2, velocity=(0.5, 0.0)))
    mass = np.asarray(state.mass)
    assert float(sim.diagnostics(state)["gravitational"]) == pytest.approx(np.sum(mass * 2.0 * state.x[:, 1]))
    lifted = eqx.tree_at(lambda s: s.x, state, state.x + jnp.array([[0.25, 0.5]]))
    rows = dict(energy_rows(sim, sim.diagnostics(state), lifted))
    kinetic = 0.5 * np.sum(mass) * 0.25
    assert rows["  gravitational V_g"] == (f"initial 0, final {np.sum(mass) * 2.0 * 0.5:.6g} "
                                           "(-sum m g.(x - x0): from the start)")
    assert rows["  kinetic K"] == f"initial {kinetic:.6g}, final {kinetic:.6g}"
    assert rows["energy K+U+V_g"] == (f"initial {kinetic:.6g}, final {kinetic + np.sum(mass):.6g}, "
                                      f"ratio {(kinetic + np.sum(mass)) / kinetic:.6f}")
    plain = jm.Simulation(grid, "linear", material, "flip")
    assert dict(energy_rows(plain, plain.diagnostics(state), lifted))["  gravitational V_g"] == "0 (no gravity)"
    pushed = jm.Simulation(grid, "linear", material, "flip", body_force=lambda x, t: jnp.ones_like(x))
    assert dict(energy_rows(pushed, pushed.diagnostics(state), lifted))["  gravitational V_g"] == (
        "0 (no gravity); the body force b(x, t) has no potential and is not counted")
