"""Fail loudly (docs/design.md principle 6): bad input raises jm.InputError naming the parameter, a too
large time step warns with the stable limit, and a run that goes unstable stops with
jm.InstabilityError naming the first bad step and its cause (NaN/Inf, J <= 0, particles leaving the
grid), keeping the frames written before it."""

import math
import warnings

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest
from cases import small_simulation

import jaxmpm as jm

# ----------------------------------------------------------------- constructors


def test_input_error_is_a_value_error():
    assert issubclass(jm.InputError, ValueError)


BAD_INPUTS = {
    "cells zero": (lambda: jm.Grid((0.0,), (1.0,), (0,)), "cells"),
    "cells negative": (lambda: jm.Grid((0.0, 0.0), (1.0, 1.0), (4, -2)), "cells"),
    "cells fractional": (lambda: jm.Grid((0.0,), (1.0,), (2.5,)), "cells"),
    "upper equals lower": (lambda: jm.Grid((0.0,), (0.0,), (4,)), "upper"),
    "upper below lower": (lambda: jm.Grid((0.0, 1.0), (1.0, 0.5), (4, 4)), "upper"),
    "axis counts differ": (lambda: jm.Grid((0.0, 0.0), (1.0,), (4, 4)), "axes"),
    "four axes": (lambda: jm.Grid((0.0,) * 4, (1.0,) * 4, (2,) * 4), "axes"),
    "negative density": (lambda: jm.LinearElastic(E=1.0, nu=0.0, density=-1.0), "density"),
    "zero density neo-Hookean": (lambda: jm.NeoHookean(E=1.0, nu=0.3, density=0.0), "density"),
    "negative fill density": (lambda: jm.fill(jm.Grid((0.0,), (4.0,), (4,)), jm.Box((1.0,), (2.0,)), density=-2.0),
                              "density"),
    "zero E": (lambda: jm.LinearElastic(E=0.0), "E"),
    "negative E": (lambda: jm.NeoHookean(E=-5.0), "E"),
    "nu = -1": (lambda: jm.LinearElastic(E=1.0, nu=-1.0), "nu"),
    "nu = 0.5": (lambda: jm.LinearElastic(E=1.0, nu=0.5), "nu"),
    "nu = 0.7": (lambda: jm.NeoHookean(E=1.0, nu=0.7), "nu"),
    "negative grid damping": (lambda: jm.Damping(grid=-0.1), "grid"),
    "negative particle damping": (lambda: jm.Damping(particle=-2.0), "particle"),
    "FLIP beta > 1": (lambda: jm.FLIP(beta=1.5), "beta"),
    "XPIC beta < 0": (lambda: jm.XPIC(order=2, beta=-0.1), "beta"),
    "FMPM beta > 1": (lambda: jm.FMPM(order=2, beta=2.0), "beta"),
    "XPIC order -1": (lambda: jm.XPIC(order=-1), "order"),
    "XPIC order 2.5": (lambda: jm.XPIC(order=2.5), "order"),
    "XPIC order '3'": (lambda: jm.XPIC(order="3"), "order"),
    "FMPM order -1": (lambda: jm.FMPM(order=-1), "order"),
    "FMPM order 2.5": (lambda: jm.FMPM(order=2.5), "order"),
    "FMPM order '3'": (lambda: jm.FMPM(order="3"), "order"),
    "UGIMP ppc 0": (lambda: jm.UGIMP(ppc=0), "ppc"),
}


@pytest.mark.parametrize("make, name", list(BAD_INPUTS.values()), ids=list(BAD_INPUTS))
def test_bad_input_names_the_parameter(make, name):
    with pytest.raises(jm.InputError) as info:
        make()
    assert name in str(info.value)


BAD_SIMULATIONS = {
    "unknown scheme": (dict(scheme="warp"), "scheme"),
    "scheme order not a number": (dict(scheme="xpic:three"), "scheme"),
    "unknown shape": (dict(shape="hexic"), "shape"),
    "update name": (dict(update="USX"), "update"),
    "damping type": (dict(damping=0.1), "damping"),
    "gravity components": (dict(gravity=(0.0, -9.8)), "gravity"),
}


@pytest.mark.parametrize("options, name", list(BAD_SIMULATIONS.values()), ids=list(BAD_SIMULATIONS))
def test_bad_simulation_names_the_parameter(options, name):
    with pytest.raises(jm.InputError) as info:
        small_simulation(**options)
    assert name in str(info.value)


def test_scheme_and_shape_strings_that_exist_are_accepted():
    sim = small_simulation(scheme="xpic:3", shape="quadratic")
    assert isinstance(sim.scheme, jm.XPIC) and sim.scheme.order == 3
    assert isinstance(sim.shape, jm.QuadraticBSpline)


def _raises(error):
    raise error


# sim.init(particles, fields={"temperature": value}) for 8 particles: value -> the words of the one-line error
BAD_FIELDS = {
    "too few values": (np.ones(3), r"fields\['temperature'\] has shape \(3,\); give an array of shape \(8,\)"),
    "one column too many": (np.ones((8, 2)), r"has shape \(8, 2\); give an array of shape \(8,\)"),
    "NaN": (np.r_[np.ones(5), np.nan, 1.0, 1.0], r"holds 1 NaN or infinite value\(s\) \(first at index \(5,\)\)"),
    "infinite number": (np.inf, r"holds 1 NaN or infinite value\(s\); give finite numbers"),
    "text": ("hot", r"fields\['temperature'\] = 'hot': give real numbers"),
    "text array": (np.array(["a"] * 8), r"has dtype <U1; give real numbers"),
    "complex": (np.ones(8) + 1j, r"has dtype complex128; give real numbers"),
    "None": (None, r"fields\['temperature'\] = None: give real numbers"),
    "dict": ({"T": 1.0}, r"= \{'T': 1.0\}: give real numbers"),
    "ragged list": ([[1.0], [1.0, 2.0]], r"has dtype object; give real numbers"),
    "function that raises": (lambda x: _raises(KeyError("T0")),
                             r"fields\['temperature'\]: calling it on the positions x, shape \(8, 1\), raised "
                             r"KeyError: 'T0'; give f\(x\) -> an array of shape \(8,\)"),
    "function of the wrong shape": (lambda x: np.ones(3), r"fields\['temperature'\]\(x\) has shape \(3,\)"),
    "function returning NaN": (lambda x: np.full(len(x), np.nan), r"\(x\) holds 8 NaN or infinite value"),
}


@pytest.mark.parametrize("value, message", list(BAD_FIELDS.values()), ids=list(BAD_FIELDS))
def test_init_fields_are_checked_in_one_line_naming_the_field(value, message):
    sim = small_simulation(terms=[jm.Heat(conductivity=1.0)])
    particles = jm.fill(sim.grid, jm.Box((4.0,), (8.0,)), ppc=2)
    with pytest.raises(jm.InputError, match=message) as info:
        sim.init(particles, fields={"temperature": value})
    assert str(info.value).startswith("Simulation.init: fields['temperature']") and "\n" not in str(info.value)


def test_init_fields_take_numbers_arrays_and_functions_of_the_positions():
    """What fields= accepts: one number, one value per particle, or f(x) of the (N, D) positions;
    a fields= that is not a dict, and a field no term declares, are named too."""
    sim = small_simulation(terms=[jm.Heat(conductivity=1.0)])
    particles = jm.fill(sim.grid, jm.Box((4.0,), (8.0,)), ppc=2)
    x = np.asarray(particles.x)[:, 0]
    for value, expected in ((300, np.full(8, 300.0)), (list(x), x), (lambda x: 2 * x[:, 0], 2 * x)):
        np.testing.assert_array_equal(sim.init(particles, fields={"temperature": value}).fields["temperature"],
                                      expected)
    with pytest.raises(jm.InputError, match=r"fields = \[300\] must be a dict \{name: value\}"):
        sim.init(particles, fields=[300])
    with pytest.raises(jm.InputError, match=r"fields \['heat'\] are not declared .* \(declared: \['temperature'\]\)"):
        sim.init(particles, fields={"heat": 300})


@pytest.mark.parametrize("shape, x", [(jm.Linear(), -0.5), (jm.Linear(), 16.0), (jm.QuadraticBSpline(), 0.2),
                                      (jm.CubicBSpline(), 15.5)])
def test_init_rejects_particles_outside_the_grid(shape, x):
    """A particle whose stencil leaves the grid (beyond the shape's margin) is an input error."""
    sim = small_simulation(shape=shape)
    particles = jm.Particles(x=jnp.array([[8.0], [x]]), v=jnp.zeros((2, 1)), volume=jnp.ones(2), ppc=1)
    with pytest.raises(jm.InputError) as info:
        sim.init(particles)
    assert "outside the grid" in str(info.value) and "particle 1" in str(info.value)


def test_instability_names_the_first_bad_particle_of_the_first_cause():
    """Simulation.instability: the cause (1 NaN/Inf, 2 J <= 0, 3 outside the grid, in that order of precedence) and
    the first particle with it, as jnp.argmax over the bad mask finds it (a min-reduction of indices since
    2026-11-29), 0 when nothing is wrong; under jit too."""
    import jax

    sim = small_simulation()
    n = 12
    particles = jm.Particles(x=jnp.linspace(2.0, 14.0, n)[:, None], v=jnp.zeros((n, 1)), volume=jnp.ones(n), ppc=1)
    state = sim.init(particles)
    nan_at, flat_at, out_at = [9, 5], [3, 10], [7, 11]
    x = state.x.at[jnp.asarray(out_at), 0].set(40.0)
    F = state.F.at[jnp.asarray(flat_at)].set(0.0)
    v = state.v.at[jnp.asarray(nan_at), 0].set(jnp.nan)
    cases = [(state, (0, 0)), (eqx.tree_at(lambda s: s.x, state, x), (3, 7)),
             (eqx.tree_at(lambda s: (s.x, s.F), state, (x, F)), (2, 3)),
             (eqx.tree_at(lambda s: (s.x, s.F, s.v), state, (x, F, v)), (1, 5))]
    for bad, (code, particle) in cases:
        for instability in (sim.instability, jax.jit(lambda s: sim.instability(s))):
            got = tuple(int(a) for a in instability(bad))
            assert got == (code, particle), (got, code, particle)


# ----------------------------------------------------------------- run arguments
STEPS = 4  # every run below has 4 frames of 1 step, so the rollout compiles once


def body_state(sim, lower, upper, velocity=0.0):
    """Particles filling [lower, upper) with 2 per cell (8 particles for 4 cells)."""
    return sim.init(jm.fill(sim.grid, jm.Box((lower,), (upper,)), ppc=2, velocity=velocity))


@pytest.mark.parametrize("dt", [0.0, -0.1, math.nan])
def test_run_rejects_non_positive_dt(dt):
    sim = small_simulation()
    with pytest.raises(jm.InputError) as info:
        sim.run(body_state(sim, 6.0, 10.0), jnp.asarray(dt), STEPS, 1)
    assert "dt" in str(info.value)


@pytest.mark.parametrize("steps, save_every", [(10, 3), (4, 0), (-4, 1), (4.0, 1)])
def test_run_rejects_bad_step_counts(steps, save_every):
    sim = small_simulation()
    with pytest.raises(jm.InputError) as info:
        sim.run(body_state(sim, 6.0, 10.0), jnp.asarray(0.1), steps, save_every)
    assert "steps" in str(info.value) or "save_every" in str(info.value)
    if steps == 10:
        assert "save_every" in str(info.value) and "12" in str(info.value)  # suggests the next multiple


def test_time_step_above_stable_limit_warns_with_the_limit():
    """dt > h / max(c + |V|) (docs/design.md "Diagnostics") warns and quotes the limit."""
    sim = small_simulation()
    state = body_state(sim, 6.0, 10.0)
    limit = 1.0 / math.sqrt(2.0)  # h / c with h = 1, c = sqrt(E / rho) = sqrt(2), body at rest
    assert float(sim.stable_dt(state)) == pytest.approx(limit, rel=1e-14)
    with pytest.warns(jm.StableTimeStepWarning) as record:
        sim.run(state, jnp.asarray(1.05 * limit), STEPS, 1)
    messages = [str(w.message) for w in record if issubclass(w.category, jm.StableTimeStepWarning)]
    assert len(messages) == 1
    assert f"{limit:.6g}" in messages[0] and "stable limit" in messages[0]


# ----------------------------------------------------------------- instability
def assert_names_step_and_cause(err, step, cause_words):
    assert isinstance(err.step, int) and err.step == step
    message = str(err)
    assert f"step {step}" in message
    assert cause_words in err.cause and err.cause in message


def test_bar_with_cfl_3_is_unstable():
    """The bar scene at three times the CFL limit under FLIP stops with a positive step number."""
    setup = jm.scene("bar", cfl=3.0)
    with pytest.warns(jm.StableTimeStepWarning):
        with pytest.raises(jm.InstabilityError) as info:
            setup.run()
    err = info.value
    assert isinstance(err.step, int) and 0 < err.step <= setup.steps
    assert f"step {err.step}" in str(err) and err.cause in str(err)
    assert err.time == pytest.approx(err.step * setup.dt, rel=1e-12)


def test_nan_in_the_state_is_refused_before_the_first_step():
    """A NaN in the state a run starts from is bad input (it was reported as going unstable at step 1)."""
    sim = small_simulation()
    state = body_state(sim, 6.0, 10.0)
    state = eqx.tree_at(lambda s: s.v, state, state.v.at[3, 0].set(jnp.nan))
    with pytest.raises(jm.InputError, match=r"run: the state is not finite before the first step: particle 3 has "
                                            r"x = \[7.75\], v = \[nan\]"):
        sim.run(state, jnp.asarray(0.1), STEPS, 1)


class _NaNForce(jm.Term):
    """A nodal force that is NaN: the first step's particles turn NaN."""

    def grid_force(self, sim, fields, dt):
        return {"force": fields.force * jnp.nan}


def test_nan_made_by_a_step_is_detected_at_step_1():
    sim = small_simulation().with_term(_NaNForce())
    with pytest.raises(jm.InstabilityError) as info:
        sim.run(body_state(sim, 6.0, 10.0), jnp.asarray(0.1), STEPS, 1)
    assert_names_step_and_cause(info.value, 1, "NaN")


def test_inverted_particle_is_detected_at_step_1():
    """V = -k (x - 8) with k dt = 1.5: F = 1 + grad v dt ~ -0.5 inside the body after one step."""
    sim = small_simulation()
    k, dt = 15.0, 0.1
    state = body_state(sim, 6.0, 10.0, velocity=lambda x: -k * (x - 8.0))
    with pytest.warns(jm.StableTimeStepWarning):
        with pytest.raises(jm.InstabilityError) as info:
            sim.run(state, jnp.asarray(dt), STEPS, 1)
    assert_names_step_and_cause(info.value, 1, "J = det F <= 0")


def first_step_off_grid(x0, speed, dt, cells):
    """A rigid translation X_p + n V dt leaves a Linear-shape grid of ``cells`` unit cells at the
    first n with max_p X_p + n V dt >= cells."""
    return math.ceil((cells - float(np.max(np.asarray(x0)))) / (speed * dt))


SPEED, DT_MOVING = 1.0, 0.3  # below the stable limit h / (c + |V|) = 1 / (sqrt(2) + 1) = 0.414


def test_particles_leaving_the_grid_are_detected_at_the_exact_step():
    """A body at uniform velocity V translates rigidly (S+ of a constant is that constant, and
    sum_i G_pi = 0 keeps F = I), so it leaves the grid exactly at the predicted step."""
    sim = small_simulation()
    state = body_state(sim, 11.5, 15.5, velocity=SPEED)  # X_p = 11.75 ... 15.25
    expected = first_step_off_grid(state.x, SPEED, DT_MOVING, 16)
    assert expected == 3  # 15.25 + 2 * 0.3 < 16 <= 15.25 + 3 * 0.3
    with warnings.catch_warnings():
        warnings.simplefilter("error", jm.StableTimeStepWarning)  # dt is below the limit: no warning
        with pytest.raises(jm.InstabilityError) as info:
            sim.run(state, jnp.asarray(DT_MOVING), STEPS, 1)
    assert_names_step_and_cause(info.value, expected, "left the grid")
    assert info.value.time == pytest.approx(expected * DT_MOVING, rel=1e-12)
    # its own kind: the grid is too small, not a numerical instability; a lax.scan rollout goes on past
    # the step, so the position there is unknown
    assert isinstance(info.value, jm.ParticlesLeftGrid) and "not a numerical instability" in str(info.value)
    assert info.value.position is None and (info.value.lower, info.value.upper) == ((0.0,), (16.0,))


@pytest.mark.parametrize("lower, expected", [(8.0, 15), (8.5, 13)])
def test_chunked_writer_keeps_the_frames_before_the_failure(tmp_path, lower, expected):
    """With writer=H5Writer, every frame before the failing step is in the file and none at or
    after it.  Chunks of 4 one-step frames; the body leaves the grid at step 15 (inside the fourth
    chunk) or 13 (its first step): the file holds the frames of steps 0 .. expected - 1."""
    sim = small_simulation()
    state = body_state(sim, lower, lower + 4.0, velocity=SPEED)
    assert first_step_off_grid(state.x, SPEED, DT_MOVING, 16) == expected
    path = tmp_path / "unstable.h5"
    with jm.H5Writer(path, sim, state, dt=DT_MOVING) as writer:
        with pytest.raises(jm.InstabilityError) as info:
            sim.run(state, jnp.asarray(DT_MOVING), 4 * STEPS, 1, writer=writer, frames_per_chunk=STEPS)
    assert_names_step_and_cause(info.value, expected, "left the grid")
    # the chunked runner stops at the failing step: the particle's position there, past the last node
    err = info.value
    assert isinstance(err, jm.ParticlesLeftGrid) and err.particle == int(np.argmax(np.asarray(state.x)[:, 0]))
    assert err.position[0] == pytest.approx(float(state.x[err.particle, 0]) + SPEED * DT_MOVING * expected,
                                            rel=1e-12) and err.position[0] >= 16.0
    assert f"at x = ({err.position[0]:.6g})" in err.detail and "the grid spans (0) .. (16)" in err.detail
    res = jm.load_h5(path)
    kept = np.arange(expected)  # steps 0, 1, ..., expected - 1
    np.testing.assert_allclose(res["time"], kept * DT_MOVING, rtol=1e-13, atol=1e-15)
    assert res["particles/x"].shape == (expected, state.x.shape[0], 1)
    # the frames hold the rigid translation X_p + n V dt, all still on the grid
    np.testing.assert_allclose(res["particles/x"][:, :, 0],
                               np.asarray(state.x)[None, :, 0] + SPEED * DT_MOVING * kept[:, None], rtol=1e-12)
    assert np.all(res["particles/x"] < 16.0)
    assert res["energy/kinetic"].shape == res["momentum/linear"].shape[:1] == (expected,)
