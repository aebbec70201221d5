"""Bad input to the plastic, viscous and collider models, and a plastic run going unstable (issue 31
item 8).

The constructors' own ranges are tested in each material's file (tests/test_drucker_prager.py,
tests/test_plasticity.py, tests/test_cam_clay.py, tests/test_newtonian.py, tests/test_collider.py);
here the cases those leave out: the hardening that makes the von Mises return singular, the
dilatancy angle at 90 degrees, a plain function given as a collider's level set, the new scenes'
options and the command line; and the instability report of a plastic run (step, particle,
cause) with the frames before it kept in the HDF5 file (tests/test_inputs.py does the same for
elastic bodies).
"""

import re
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxmpm as jm
from jaxmpm import cli


def one_line_error(build) -> str:
    with pytest.raises(jm.InputError) as info:
        build()
    message = str(info.value)
    assert "\n" not in message
    return message


def test_hardening_that_makes_the_return_singular():
    """The radial return divides by 3 mu + H (jaxmpm/materials/von_mises.py): H = -3 mu makes it
    singular, and any H < 0 is refused, naming the hardening and why."""
    E, nu = 1e5, 0.25
    mu = E / (2 * (1 + nu))
    message = one_line_error(lambda: jm.VonMises(E=E, nu=nu, yield_stress=100.0, hardening=-3 * mu))
    assert message.startswith(f"VonMises: hardening = {-3 * mu} must be >= 0; ") and "softening" in message


def test_dilatancy_angle_of_90_degrees():
    message = one_line_error(lambda: jm.DruckerPrager(E=1e5, friction_angle=89.0, dilatancy_angle=90.0))
    assert message.startswith("DruckerPrager: dilatancy_angle = 90.0 must lie in [0, 90); ")


@pytest.mark.parametrize("law, kwargs, expected", [
    ("VonMises", dict(E=1e5, yield_stress=-200.0),
     "yield_stress = -200.0 must be positive; the uniaxial yield stress sigma_y, positive (stress units)"),
    ("VonMises", dict(E=-1.0), "E = -1.0 must be positive; Young's modulus, positive (stress units)"),
    ("VonMises", dict(E=1e5, density=0.0),
     "density = 0.0 must be positive; the reference density rho_0, positive (mass per volume)"),
    ("DruckerPrager", dict(E=0.0), "E = 0.0 must be positive; Young's modulus, positive (stress units)"),
    ("DruckerPrager", dict(E=1e5, density=-1.0),
     "density = -1.0 must be positive; the reference density rho_0, positive (mass per volume)"),
], ids=["von_mises-yield_stress", "von_mises-E", "von_mises-density", "drucker_prager-E", "drucker_prager-density"])
def test_plastic_law_moduli_out_of_range_name_the_fix(law, kwargs, expected):
    """The plastic laws' stiffness, yield stress and density: the one-line message names the
    argument, its value and what it must be."""
    message = one_line_error(lambda: getattr(jm, law)(**kwargs))
    assert message == f"{law}: {expected}"


def test_a_plain_function_is_not_a_collider_level_set():
    """A level set is a jm.LevelSet (its ``distance`` of one point is one number, checked when the
    step is traced: tests/test_collider.py); a bare function is refused at once, with the fix."""
    message = one_line_error(lambda: jm.Collider(lambda x: x[1]))
    assert message.startswith("Collider: shape = ") and "is not a solid; give a level set (jm.HalfSpace" in message


@pytest.mark.parametrize("scene, options, words", [
    ("column_collapse", dict(cohesion=-1.0), "cohesion = -1.0 must be >= 0; the cohesion c"),
    ("column_collapse", dict(friction_angle=-5.0), "friction_angle = -5.0 must lie in [0, 90); "),
    ("taylor_bar", dict(yield_stress=0.0), "yield_stress = 0.0 must be positive; the initial yield stress"),
    ("taylor_bar", dict(hardening=-1.0), "hardening = -1.0 must be >= 0; the linear hardening modulus"),
    ("incline", dict(angle=90.0), "angle = 90.0 must lie in [0, 90); "),
    ("incline", dict(friction=-0.1), "friction = -0.1 must be >= 0; the Coulomb friction coefficient"),
])
def test_scene_options_out_of_range(scene, options, words):
    message = one_line_error(lambda: jm.scene(scene, **options))
    assert message.startswith(f"{scene}: {words}"), message


def test_command_line_cohesion_below_zero_exits_2_in_one_line(capsys, tmp_path):
    out = tmp_path / "never.h5"
    with pytest.raises(SystemExit) as info:
        cli.main(["run", "column_collapse", "--cohesion", "-5", "--out", str(out)])
    assert info.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["jaxmpm: error: column_collapse: cohesion = -5.0 must be >= 0; the cohesion c >= 0 (stress units)"]
    assert not out.exists()


# ------------------------------------------------------------------------------ instability
@pytest.mark.slow
def test_plastic_collapse_at_ten_times_the_stable_step_stops_naming_step_particle_and_cause(tmp_path):
    """The column_collapse sand (Drucker-Prager, a = 1, 2 cells across, 16 particles) stepped at
    ten times its stable dt: a particle inverts within a few steps (measured: step 4, particle 2).
    The error names the first step where det F <= 0 and the first such particle -- both checked
    against stepping the model by hand -- and the HDF5 file keeps every frame before that step, the
    plastic strain included, equal to the hand-stepped states."""
    setup = jm.scene("column_collapse", aspect=1.0, cells=2)
    dt = 10.0 * setup.dt
    sim, state = setup.sim, setup.state

    step = jax.jit(lambda s, dt: sim.step(s, dt))  # unchecked: the model alone
    states = [state]
    while bool(jnp.all(jnp.linalg.det(states[-1].F) > 0)) and len(states) < 40:
        states.append(step(states[-1], dt))
    first = len(states) - 1  # the first step after which a particle has det F <= 0
    inverted = int(np.argmax(np.asarray(jnp.linalg.det(states[-1].F)) <= 0))
    assert 1 < first < 40
    assert all(bool(jnp.all(jnp.isfinite(s.x))) for s in states[:-1])

    path = tmp_path / "unstable.h5"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", jm.StableTimeStepWarning)  # dt is ten times the limit, on purpose
        with jm.H5Writer(path, sim, state, dt=dt, fields=("plastic_strain",)) as writer:
            with pytest.raises(jm.InstabilityError) as info:
                sim.run(state, jnp.asarray(dt), 40, 1, writer=writer, frames_per_chunk=4)
    err = info.value
    assert err.step == first and err.time == pytest.approx(first * dt, rel=1e-12)
    assert err.cause == f"J = det F <= 0 (a particle inverted) (particle {inverted})"
    assert re.search(rf"unstable at step {first} \(t = .*\): J = det F <= 0 .*\(particle {inverted}\)", str(err))

    saved = jm.load_h5(path)
    np.testing.assert_allclose(saved["time"], dt * np.arange(first), rtol=1e-12)
    x = np.stack([np.asarray(s.x) for s in states[:-1]])
    np.testing.assert_allclose(saved["particles/x"], x, rtol=1e-12, atol=1e-15)
    plastic = np.stack([np.asarray(s.material_state["plastic_strain"]) for s in states[:-1]])
    np.testing.assert_allclose(saved["particles/plastic_strain"], plastic, rtol=1e-12, atol=1e-15)
    assert plastic[-1].max() > 0.0  # the sand had yielded before it failed
