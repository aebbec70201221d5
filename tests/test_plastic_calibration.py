"""Calibration and gradients through the plastic and viscous scenes (issue 31 item 7).

* ``jm.calibrate`` recovers the cohesion c together with the friction angle phi from a synthetic
  ``column_collapse`` displacement history (tests/test_column_collapse.py recovers phi alone), and
  the range of c the collapse can identify: above the cohesion that holds a vertical cut of the
  column's height the column stands and the history no longer sees c;
* ``jm.calibrate`` recovers the viscosity eta of a viscous liquid from a synthetic ``dam_break``
  surge-front history;
* the gradient of a whole ``column_collapse`` rollout with respect to phi and c, through steps
  inside the cone, on it and at its apex, equals central differences in float64.

All calibrations are synthetic: the "experiment" is a run of the same model with known values, so
that the recovered values can be held to 1 %.  The gradient with respect to a collider's friction
through a run is checked in tests/test_collider.py.
"""

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from cases import central_difference

import jaxmpm as jm


def lbfgs():
    """L-BFGS with a backtracking line search: one compiled gradient per loss (jm.calibrate)."""
    return optax.lbfgs(linesearch=optax.scale_by_backtracking_linesearch(max_backtracking_steps=20))


# ------------------------------------------------------------------- column collapse: phi and c
@pytest.mark.slow
def test_calibrate_recovers_cohesion_and_friction_angle_together():
    """A column of a = 1 on 4 cells across (64 particles), 0.15 s (165 steps, 3 frames), the
    particles' displacement history as the observation.

    c is identifiable from this history below the cohesion that holds the column up: the RMS
    displacement at 0.15 s falls steadily with c (measured 11.2, 5.8, 1.4 mm at c = 0, 200,
    400 Pa) and the column stands from about 500 Pa (0.47 mm at 600 Pa, 0.26 mm at 1000 Pa, elastic
    settling only): the critical height of a vertical cut, H_c = 4 c tan(45 + phi/2) / (rho g)
    (Terzaghi 1943), reaches H0 = 0.2 m at c = 510 Pa for phi = 30.  So the truth c = 200 Pa lies
    well inside the identifiable range, where the column slumps partly.

    phi and c act together (both raise the strength, through sqrt(J2) <= xi c - eta p): the
    history separates them because c matters most where the confinement p is small (the top
    and the free face) and phi where it is large (the base).  L-BFGS from (25 deg, 100 Pa)
    recovers both within 1 % (measured 30.000 deg and 200.000 Pa in 20 iterations)."""
    setup = jm.scene("column_collapse", aspect=1.0, cells=4, t_end=0.15, frames=3)
    start = setup.state.x

    def observe(params):
        sim = jm.set_params(setup.sim, **params)
        _, history = sim.run(setup.state, setup.dt, setup.steps, setup.save_every)
        return history.x - start[None]

    history = jax.jit(observe)
    rms = [float(jnp.sqrt(jnp.mean(history({"friction_angle": 30.0, "cohesion": c})[-1] ** 2)))
           for c in (0.0, 200.0, 400.0, 600.0, 1000.0)]
    assert np.all(np.diff(rms) < 0), rms  # more cohesion, less collapse
    assert rms[1] > 0.5 * rms[0] and rms[3] < 1e-3 and rms[4] < 1e-3, rms  # slumps at 200 Pa, stands from 600 Pa

    truth = {"friction_angle": 30.0, "cohesion": 200.0}
    target = history(truth)
    scale = jnp.mean(target**2)

    def loss(params):
        return jnp.mean((observe(params) - target) ** 2) / scale

    result = jm.calibrate(loss, {"friction_angle": 25.0, "cohesion": 100.0}, optimizer=lbfgs(), steps=40, tol=1e-12)
    assert result.params["friction_angle"] == pytest.approx(30.0, rel=1e-2), result
    assert result.params["cohesion"] == pytest.approx(200.0, rel=1e-2), result


# ------------------------------------------------------------------------ dam break: viscosity
@pytest.mark.slow
def test_calibrate_recovers_the_viscosity_from_the_surge_front():
    """The surge-front history Z(T) = x_front / a of a tiny dam break (4 cells across a, 128
    particles, 231 steps to T = 1.86, 8 frames) of a viscous liquid, eta = 2 Pa s: L-BFGS from
    1 Pa s recovers eta within 1 % (measured 2.0000000 in 9 iterations).

    Why not water: at eta = 1e-3 Pa s (Reynolds number rho U a / eta ~ 1e5) the front does not
    see the viscosity -- Z(1.86) = 1.82411 at 1e-3 Pa s and 1.81995 at 0.1 Pa s, so doubling water's
    eta moves the front by 4e-5 a, far below what the schemes themselves change (the front's
    sensitivity is about -0.04 a per Pa s).  At 2 Pa s (Re ~ 40, a glycerol-like liquid) the front
    lags the inviscid one by 4 % (Z = 1.7506).

    The start: below about 0.9 Pa s the misfit flattens towards the inviscid front and is concave
    in log eta (the variable jm.calibrate moves), so L-BFGS's first curvature pair is negative
    there and it stalls (measured: from 0.5 Pa s it stops at 0.49); from 1 Pa s (or 4 Pa s, 8
    iterations) it converges."""
    setup = jm.scene("dam_break", cells=4, t_end=0.1, frames=5, viscosity=2.0)
    p = setup.params

    def advance(params):
        """Z(T) - 1 at the saved frames: how far the front has run, in column widths a."""
        sim = jm.set_params(setup.sim, **params)
        _, history = sim.run(setup.state, setup.dt, setup.steps, setup.save_every)
        return (history.x[..., 0].max(axis=-1) + 0.5 * p["particle_spacing"]) / p["width"] - 1.0

    target = jax.jit(advance)({"eta": 2.0})
    assert target.shape == (8,) and float(target[-1]) == pytest.approx(0.7506, abs=1e-3)

    def loss(params):
        return jnp.mean((advance(params) - target) ** 2) / jnp.mean(target**2)

    result = jm.calibrate(loss, {"eta": 1.0}, optimizer=lbfgs(), steps=40, tol=1e-14)
    assert result.params["eta"] == pytest.approx(2.0, rel=1e-2), result


# ------------------------------------------------------------- gradients through the return
@pytest.mark.slow
def test_gradient_through_the_collapse_equals_central_differences():
    """d loss / d(phi, c) of a 20-step column collapse (a = 1, 2 cells across, 16 particles; loss a
    fixed random projection of the displacements) by reverse mode through every step's
    Drucker-Prager return, against fourth-order central differences (steps 1e-3 deg and 1e-2 Pa):
    equal to 1e-6 (measured 1e-8).  The rollout crosses the material's kinks: every particle has
    elastic steps (inside the cone) and plastic ones (on it), and one is returned to the apex
    (its volumetric plastic strain, zero on the cone with psi = 0, is not)."""
    setup = jm.scene("column_collapse", aspect=1.0, cells=2, t_end=1.0, frames=1)
    steps = 20
    weights = jnp.asarray(np.random.default_rng(0).standard_normal(setup.state.x.shape))

    def rollout(theta, save_every):
        sim = jm.set_params(setup.sim, friction_angle=theta[0], cohesion=theta[1])
        return sim.run(setup.state, setup.dt, steps, save_every, fields=("plastic_strain", "volumetric_plastic_strain"))

    def loss(theta):
        final, _ = rollout(theta, steps)
        return jnp.sum(weights * (final.x - setup.state.x)) / setup.params["length"]

    theta = jnp.asarray([30.0, 100.0])
    _, history = jax.jit(rollout, static_argnums=1)(theta, 1)
    grows = np.diff(np.asarray(history.fields["plastic_strain"]), axis=0) > 0  # (steps, particles): a plastic step
    assert grows.any(axis=0).all() and (~grows).any(axis=0).all()  # each particle: plastic and elastic steps
    assert np.count_nonzero(np.asarray(history.fields["volumetric_plastic_strain"][-1])) >= 1  # an apex return

    grad = jax.jit(jax.grad(loss))(theta)
    value = jax.jit(loss)
    for k, eps in enumerate((1e-3, 1e-2)):
        direction = jnp.zeros(2).at[k].set(1.0)
        fd = central_difference(lambda h: value(theta + h * direction), 0.0, eps, order=4)
        assert float(fd) != 0.0
        assert float(grad[k]) == pytest.approx(float(fd), rel=1e-6), k
