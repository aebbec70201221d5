"""Particles are checked where they enter (issue 29, item 2): jm.Particles rejects what it cannot
hold with one InputError naming the argument; Simulation.init follows one precision rule (the
positions'), warning when it narrows another array."""

import warnings

import numpy as np
import pytest

import jaxmpm as jm

GRID = jm.Grid((0.0,), (4.0,), (4,))


def particles(**overrides):
    kwargs = dict(x=np.array([[1.0], [2.0], [3.0]]), v=np.zeros((3, 1)), volume=np.ones(3))
    kwargs.update(overrides)
    return jm.Particles(**kwargs)


@pytest.mark.parametrize("overrides, message", [
    (dict(x=np.zeros((0, 1)), v=np.zeros((0, 1)), volume=np.zeros(0)), "x holds no particles"),
    (dict(v=np.zeros((2, 1))), r"v has shape \(2, 1\) but x has \(3, 1\)"),
    (dict(v=np.zeros(3)), r"v has shape \(3,\) but x has \(3, 1\)"),
    (dict(volume=np.ones(2)), r"volume has shape \(2,\); give one reference volume per particle, shape \(3,\)"),
    (dict(mass=np.ones(4)), r"mass has shape \(4,\)"),
    (dict(x=np.array([["a"], ["b"], ["c"]])), r"x \(positions.*\) has dtype <U1; give real numbers"),
    (dict(x=np.ones((3, 1)) * 1j), "x .* has dtype complex128"),
    (dict(v=np.array([["fast"]] * 3)), "v .* has dtype <U4"),
    (dict(x=np.array([1.0, 2.0, 3.0])), r"x has shape \(3,\); give positions as \(N, D\)"),
    (dict(x=np.ones((3, 4)), v=np.zeros((3, 4))), r"x has shape \(3, 4\); give positions as \(N, D\) with D = 1, 2"),
    (dict(x=np.array([[1.0], [np.nan], [3.0]])), "x = .* must be a finite number"),
    (dict(v=np.array([[0.0], [np.inf], [0.0]])), "v = .* must be a finite number"),
    (dict(volume=np.array([1.0, 0.0, 1.0])), "volume = .* must be positive"),
    (dict(mass=-np.ones(3)), "mass = .* must be positive"),
    (dict(ppc=0), "ppc"),
])
def test_bad_particles_get_one_line(overrides, message):
    with pytest.raises(jm.InputError, match=message):
        particles(**overrides)


def test_integer_positions_are_positions():
    """Integer positions inside the grid are inside it (they take the default float), not "outside"."""
    sim = jm.Simulation(grid=GRID, shape=jm.Linear(), material=jm.LinearElastic(E=1.0), scheme=jm.FLIP())
    state = sim.init(particles(x=np.array([[1], [2], [3]])))
    assert state.x.dtype == np.float64
    np.testing.assert_array_equal(np.asarray(state.x)[:, 0], [1.0, 2.0, 3.0])


def test_precision_follows_the_positions_and_warns_when_it_narrows():
    sim = jm.Simulation(grid=GRID, shape=jm.Linear(), material=jm.LinearElastic(E=1.0), scheme=jm.FLIP())
    with pytest.warns(UserWarning, match="particles.v is float64 but the positions are float32"):
        state = sim.init(particles(x=np.array([[1.0], [2.0], [3.0]], np.float32), volume=np.ones(3, np.float32)))
    assert state.x.dtype == state.v.dtype == state.mass.dtype == np.float32
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # float32 velocities with float64 positions widen: no warning
        state = sim.init(particles(v=np.zeros((3, 1), np.float32)))
    assert state.v.dtype == np.float64


def test_terms_simulation_adds_itself_replace_its_own():
    """A term of the classes Simulation adds itself (stress divergence, body force, damping) given in
    terms= replaces Simulation's own, as with_term does: a scene's sim.terms given back no longer
    doubles the stress (a silent factor-2 force met while building the NairnMPM comparison)."""
    setup = jm.scenes.bar(t_end=1.0, frames=2)
    kwargs = dict(grid=setup.sim.grid, shape=setup.sim.shape, material=setup.sim.material, scheme=jm.FLIP())
    again = jm.Simulation(terms=setup.sim.terms, **kwargs)
    assert [type(t).__name__ for t in again.terms] == [type(t).__name__ for t in setup.sim.terms]
    assert np.array_equal(np.asarray(again.step(setup.state, setup.dt).v), np.asarray(setup.sim.step(setup.state,
                                                                                                      setup.dt).v))
    smoothed = jm.Simulation(terms=(jm.StressDivergence(xpic=2),), **kwargs)
    assert [t.xpic for t in smoothed.terms if isinstance(t, jm.StressDivergence)] == [2]
    damped = jm.Simulation(terms=(jm.Damping(grid=0.1),), **kwargs)
    assert [float(t.grid) for t in damped.terms if isinstance(t, jm.Damping)] == [0.1]
    with pytest.raises(jm.InputError, match="terms holds a jm.Damping and damping= gives another"):
        jm.Simulation(terms=(jm.Damping(grid=0.1),), damping=jm.Damping(particle=0.2), **kwargs)


def test_load_h5_on_a_missing_or_truncated_file(tmp_path):
    path = tmp_path / "run.h5"
    with pytest.raises(jm.InputError, match="does not exist"):
        jm.load_h5(path)
    path.write_bytes(b"\x89HDF\r\n\x1a\n" + b"\0" * 200)  # an HDF5 signature, then nothing: truncated
    with pytest.raises(jm.InputError, match="is not a readable HDF5 file"):
        jm.load_h5(path)


def test_negative_numbers_reach_the_options_own_check(tmp_path, capsys):
    """`--cfl -0.5`: argparse alone says "expected one argument" (an exponent or a negative value
    looks like an option to it); the value now reaches the scene's check, which names it."""
    from cases import run_cli

    assert run_cli(["run", "bar", "--cfl", "-0.5", "--out", str(tmp_path / "x.h5")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "cfl = -0.5 must be positive" in err[0]
    assert run_cli(["run", "bar", "--t-end", "-1e-3", "--out", str(tmp_path / "x.h5")]) == 2
    assert "t_end" in capsys.readouterr().err and not (tmp_path / "x.h5").exists()


@pytest.mark.parametrize("gravity, message", [
    (9.81, r"gravity must be a vector of the grid's D components.*got shape \(\)"),
    ("down", "gravity must be a number, got 'down'"),
    ((0.0, float("nan")), r"gravity = \(0.0, nan\) must be a finite number"),
])
def test_body_force_checks_its_gravity(gravity, message):
    """A BodyForce given directly (terms=...) checks gravity as Simulation(gravity=...) does, instead of
    failing inside the run (a tuple had no .astype, a scalar broke the gravitational potential)."""
    with pytest.raises(jm.InputError, match=message):
        jm.BodyForce(gravity)
    assert jm.BodyForce((0, -10)).gravity.dtype.kind == "f"
