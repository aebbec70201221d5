"""The ``taylor_bar`` scene (jaxmpm/scenes/taylor_bar.py): a copper rod (von Mises) hits a rigid
wall.  Fast: the first microseconds (mass, no NaN, plastic flow starts at the impact end only).
Slow: the whole impact at the default coarse resolution against the literature's final length."""

import jax.numpy as jnp
import numpy as np
import pytest

import jaxmpm as jm

RHO, L0, R0 = 8930.0, 25.4e-3, 3.8e-3


@pytest.fixture(scope="module")
def bar():
    return jm.scene("taylor_bar")


def test_the_impact_end_yields_first(bar):
    """After 15 steps (1.6 us: the elastic wave has run ~7 mm up the 25.4 mm rod) the particles
    that yielded are all within a third of the rod from the wall, the upper half is still elastic
    and, but for the discrete wave's precursor (3e-5 of v0, decaying ahead of the front: 2e-11
    over the top quarter), flying at v0, and the mass (per radian) is rho R0^2 L0 / 2."""
    mass = float(jnp.sum(bar.state.mass))
    np.testing.assert_allclose(mass, RHO * R0 ** 2 * L0 / 2.0, rtol=1e-12)
    state, _ = bar.sim.run(bar.state, bar.dt, 15, 15)
    np.testing.assert_allclose(float(jnp.sum(state.mass)), mass, rtol=1e-14)
    assert bool(jnp.all(jnp.isfinite(state.x))) and bool(jnp.all(jnp.isfinite(state.F)))
    alpha = np.asarray(state.material_state["plastic_strain"])
    z0 = np.asarray(bar.state.x[:, 1])
    assert alpha.max() > 0.01  # the wall end flows
    assert z0[alpha > 0].max() < L0 / 3.0
    upper = z0 > L0 / 2.0
    assert alpha[upper].max() == 0.0
    np.testing.assert_allclose(np.asarray(state.v[upper, 1]), -190.0, rtol=5e-5)
    np.testing.assert_allclose(np.asarray(state.v[z0 > 0.75 * L0, 1]), -190.0, rtol=1e-10)  # measured 2e-11


def test_three_dimensional_quarter_rod_builds():
    setup = jm.scene("taylor_bar", geometry="3d")
    x = np.asarray(setup.state.x)
    assert x.shape[1] == 3 and x[:, :2].min() >= 0.0
    # the quarter rod's volume pi R0^2 L0 / 4, to the staircase of the particle cells
    np.testing.assert_allclose(float(jnp.sum(setup.state.mass)), RHO * np.pi * R0 ** 2 * L0 / 4.0, rtol=0.05)


def test_bad_geometry_is_an_input_error():
    with pytest.raises(jm.InputError, match="geometry"):
        jm.scene("taylor_bar", geometry="2d")


@pytest.mark.slow
def test_final_shape_at_the_coarse_default(bar):
    """The whole impact (80 us) at the default 4 cells across the radius.  Measured (experiments/
    taylor_bar.py): final length 18.93 mm, +15.8 % on the 16.35 mm mid-value of the literature range
    the issue quotes (+15.7 % at 8 cells, +15.2 % at 16: converged, not a resolution error), foot
    radius 6.79 mm, -6.4 % on 7.25 mm (7.13 and 7.16 mm at 8 and 16 cells)."""
    state, _ = bar.sim.run(bar.state, bar.dt, bar.steps, bar.steps)
    x = np.asarray(state.x)
    shape = bar.reference(x)
    assert np.all(np.isfinite(x))
    mid_length, mid_foot = (0.5 * sum(shape["literature"][k]) for k in ("length", "foot_radius"))
    assert 0.0 < shape["length"] / mid_length - 1.0 < 0.165
    assert abs(shape["foot_radius"] / mid_foot - 1.0) < 0.07
