"""How a run that fails says so (README "Errors", docs/running.md): the cause named right, the frames
before the failure kept, a state that is bad before the first step refused as input, and jm.calibrate,
whose runs inside the compiled update cannot raise, checking the parameters it reached.  Each case was wrong before:

* a particle thrown off the grid by a blow-up (thermal_bar at 40x its stable step) read "particles left
  the grid ... the grid is too small for the motion (not a numerical instability): shorten the run";
* an in-memory run's InstabilityError carried no frames: the finished ones were lost;
* a NaN or out-of-grid particle given to sim.run was reported as failing at step 1;
* jm.calibrate returned parameters where its runs go unstable (Adam took E from 100 to 1.2e13) without a word;
* ``boundary=False`` raised TypeError."""

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import optax
import pytest

import jaxmpm as jm

pytestmark = pytest.mark.filterwarnings("ignore::jaxmpm.StableTimeStepWarning")


def test_a_particle_thrown_off_the_grid_by_a_blow_up_is_an_instability_not_a_small_grid():
    setup = jm.scene("thermal_bar", cfl=20, dtype="f64")
    with pytest.raises(jm.InstabilityError) as caught:
        setup.run()
    error = caught.value
    assert not isinstance(error, jm.ParticlesLeftGrid) and error.step == 1
    assert "a particle left the grid moving more than a cell a step (|V| dt > h" in str(error)
    assert "not a grid too small (particle 0)" in str(error) and "enlarge the grid" not in str(error)
    # the model's own check says so given the step's dt; without it, the particle is off the grid (code 3)
    reached, _ = setup.sim.run(setup.state, setup.dt, 1, 1, check_stability=False)
    assert [int(a) for a in setup.sim.instability(reached, setup.dt)] == [4, 0]
    assert [int(a) for a in setup.sim.instability(reached)] == [3, 0]
    # a particle that walks off the grid slowly is still ParticlesLeftGrid (tests/test_cli.py's drifting block)


@pytest.mark.parametrize("progress", [False, True])
def test_the_frames_before_a_failure_come_with_the_error(progress):
    setup = jm.scene("bar", cfl=20, dtype="f64")  # J <= 0 at step 3, a frame every step
    with pytest.raises(jm.InstabilityError) as caught:
        setup.run(progress=progress)
    error = caught.value
    assert error.step == 3 and "J = det F <= 0" in error.cause
    history = error.history  # the frames of steps 0, 1 and 2, finite
    assert history is not None and len(history.time) == 3
    np.testing.assert_allclose(np.asarray(history.time), np.arange(3) * setup.dt)
    assert np.all(np.isfinite(np.asarray(history.x)))
    whole, _ = setup.sim.run(setup.state, setup.dt, 2, 1)  # the same as a run that stops before the failure
    np.testing.assert_array_equal(np.asarray(history.x[-1]), np.asarray(whole.x))


@pytest.mark.parametrize("what, words", [
    ("nan", r"run: the state is not finite before the first step: particle 3 has x = \[nan, "),
    ("outside", r"run: particle 3 at x = \[-5.0, .*\] lies where its shape function reaches past the grid's nodes "
                r"before the first step \(the grid spans"),
    ("inverted", r"run: particle 3 has det F <= 0 before the first step"),
])
def test_a_state_bad_before_the_first_step_is_refused_as_input(what, words):
    setup = jm.scene("disks", spacing=0.1, t_end=0.01, frames=1, dtype="f64")
    state = setup.state
    if what == "nan":
        state = eqx.tree_at(lambda s: s.x, state, state.x.at[3, 0].set(jnp.nan))
    elif what == "outside":
        state = eqx.tree_at(lambda s: s.x, state, state.x.at[3, 0].set(-5.0))
    else:
        state = eqx.tree_at(lambda s: s.F, state, state.F.at[3].set(jnp.diag(jnp.array([-1.0, 1.0]))))
    with pytest.raises(jm.InputError, match=words):
        setup.sim.run(state, setup.dt, 2, 1)


def test_calibrate_refuses_parameters_where_its_runs_go_unstable():
    """Inside the compiled update the runs cannot raise: Adam at a learning rate of 8 had driven E from
    100 to 1.2e13, where the run inverts a particle at step 2, and calibrate returned it as if fitted
    (where such a run goes depends on its garbage gradients; here the optimizer stands still at an E the
    run's dt cannot hold).  calibrate now runs the loss once more outside the trace at the parameters
    reached."""
    setup = jm.scene("bar", t_end=20, frames=10, dtype="f64")
    mass = setup.state.mass

    def loss(p):
        _, history = jm.set_params(setup.sim, **p).run(setup.state, setup.dt, 200, 20)
        return jnp.mean((history.v[..., 0] @ mass) ** 2)

    still = optax.sgd(0.0)
    with pytest.raises(jm.InputError, match=r"calibrate: at the parameters reached \(E = (10000000|9999999)\.\d+\) a "
                                            r"run of the loss goes unstable: simulation went unstable at step \d+ .*"
                                            r"J = det F <= 0.*lower the learning rate, bound the parameters"):
        jm.calibrate(loss, {"E": 1e7}, optimizer=still, steps=2, progress=False)
    fit = jm.calibrate(loss, {"E": 1e7}, optimizer=still, steps=2, progress=False, check_stability=False)
    assert float(fit.params["E"]) == pytest.approx(1e7, rel=1e-12) and np.all(np.isfinite(fit.losses))  # unchecked
    stable = jm.calibrate(loss, {"E": 100.0}, optimizer=still, steps=1, progress=False)
    assert float(stable.params["E"]) == pytest.approx(100.0, rel=1e-12)
    with pytest.raises(jm.InputError, match="check_stability = 1; pass True or False"):
        jm.calibrate(loss, {"E": 100.0}, steps=1, progress=False, check_stability=1)


def test_boundary_of_the_wrong_kind_is_an_input_error():
    bar = jm.scene("bar", cells=4)
    for boundary in (False, "walls", 3):
        with pytest.raises(jm.InputError, match=f"boundary = {boundary!r}: give a condition"):
            jm.Simulation(bar.sim.grid, bar.sim.shape, bar.sim.material, "flip", boundary=boundary)


def test_check_stability_false_checks_neither_the_start_nor_the_steps():
    """A run asked not to check its stability takes a state that is already bad (so that a file a blown-up
    run wrote with check_stability=False can be continued the same way) and returns every frame."""
    setup = jm.scene("disks", spacing=0.1, t_end=0.01, frames=1, dtype="f64")
    state = eqx.tree_at(lambda s: s.x, setup.state, setup.state.x.at[3, 0].set(jnp.nan))
    final, history = setup.sim.run(state, setup.dt, 2, 1, check_stability=False)
    assert len(history.time) == 3 and not np.all(np.isfinite(np.asarray(final.x)))
