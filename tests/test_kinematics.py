"""Kinematics and objective stress, float64.

The deformation-gradient increment (jaxmpm/_step.py update_deformation):
dF = I + grad v dt ("linear", the default) or dF = exp(grad v dt) ("exponential", 001 eq. 26).

* a pure spin W (skew): exp(W dt) is a rotation (Q^T Q = I, det Q = 1 to round-off); the linear
  increment stretches, det(I + W dt) = 1 + w^2 dt^2 per step (2D);
* a general constant gradient L: n exponential steps of dt equal one of n dt (exp(L a) exp(L b) =
  exp(L (a + b))), which the linear increment only approaches as dt -> 0;
* on the spinning elastic disk the choice barely matters (measured below): its spurious strain
  comes from the MPM velocity field not being exactly rigid, not from the increment.

jm.HypoElastic (jaxmpm/_materials.py), the objective rate law: no stress under rotation (exact
for rotation increments), preloaded stresses rotate with their invariants, LinearElastic's
stress for small strains; the spinning disk and the bar with each law.
"""

import copy

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxmpm as jm
from jaxmpm.model.step import update_deformation


def test_a_spin_gives_an_exact_rotation():
    rng = np.random.default_rng(1)
    w = rng.normal(size=(50,))
    W = np.zeros((50, 2, 2))
    W[:, 0, 1], W[:, 1, 0] = w, -w
    F = jnp.broadcast_to(jnp.eye(2), (50, 2, 2))
    dt = 0.1
    Q = np.asarray(update_deformation(F, jnp.asarray(W), dt, "exponential"))
    np.testing.assert_allclose(np.einsum("pji,pjk->pik", Q, Q), np.broadcast_to(np.eye(2), (50, 2, 2)), atol=1e-14)
    np.testing.assert_allclose(np.linalg.det(Q), 1.0, atol=1e-14)
    np.testing.assert_allclose(Q[:, 0, 1], np.sin(w * dt), rtol=1e-13)
    linear = np.asarray(update_deformation(F, jnp.asarray(W), dt, "linear"))
    np.testing.assert_allclose(np.linalg.det(linear), 1.0 + (w * dt) ** 2, rtol=1e-13)


def test_exponential_increments_compose():
    """exp(L dt)^n = exp(L n dt) for a constant 3D gradient L: 10 steps of 0.01 against one of 0.1."""
    L = jnp.asarray(np.random.default_rng(2).normal(size=(1, 3, 3)))
    F = jnp.eye(3)[None]
    stepped = F
    for _ in range(10):
        stepped = update_deformation(stepped, L, 0.01, "exponential")
    np.testing.assert_allclose(np.asarray(stepped), np.asarray(update_deformation(F, L, 0.1, "exponential")),
                               rtol=1e-12, atol=1e-14)
    linear = F
    for _ in range(10):
        linear = update_deformation(linear, L, 0.01, "linear")
    assert np.abs(np.asarray(linear - stepped)).max() > 1e-3  # first order in dt


@pytest.mark.slow
def test_spinning_disk_with_either_increment():
    """The elastic disk spinning (spin scene, stress=True, APIC, h = 1/16): the strain energy it
    builds, over the initial kinetic energy, is 1.60e-5 (linear) and 1.71e-5 (exponential) at t = 1,
    1.775e-4 and 1.482e-4 after a full turn (t = 2 pi) -- measured; the increments differ, the run is
    stable with both, and a bad name is an error."""
    setup = jm.scene("spin", scheme="apic", stress=True, spacing=1 / 16, frames=2, t_end=1.0)
    ratios = {}
    for kinematics in ("linear", "exponential"):
        sim = copy.copy(setup.sim)
        object.__setattr__(sim, "kinematics", kinematics)
        final, hist = sim.run(setup.state, setup.dt, setup.steps, setup.save_every)
        ratios[kinematics] = float(hist.strain[-1] / hist.kinetic[0])
    assert ratios["linear"] != ratios["exponential"] and max(ratios.values()) < 1e-4, ratios
    with pytest.raises(jm.InputError, match="kinematics"):
        jm.Simulation(grid=setup.sim.grid, shape=setup.sim.shape, material=setup.sim.material, scheme=jm.FLIP(),
                      kinematics="exact")


@pytest.mark.slow
def test_gradient_through_the_exponential_increment():
    """d/dt of sum exp(L t) F by reverse mode equals the analytic L exp(L t) F."""
    L = jnp.asarray(np.random.default_rng(3).normal(size=(1, 2, 2)))
    F = jnp.asarray(np.random.default_rng(4).normal(size=(1, 2, 2)))
    grad = jax.grad(lambda t: jnp.sum(update_deformation(F, L, t, "exponential")))(0.3)
    expected = jnp.sum(L @ update_deformation(F, L, 0.3, "exponential"))
    assert float(grad) == pytest.approx(float(expected), rel=1e-12)


# ------------------------------------------------------------------ objective stress: jm.HypoElastic
def rotation(theta):
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, -s], [s, c]])


def test_hypoelastic_builds_no_stress_under_rotation_and_total_strain_does():
    """F driven through 60 rotation increments of 3 degrees (a rigid turn by 180): HypoElastic's
    stress stays 0 to round-off (its strain increment (dF^T dF - I)/2 vanishes for a rotation);
    LinearElastic's total strain sym F - I = (cos theta - 1) I = -2 I at theta = 180 gives the
    compressive stress tau_xx = -4 (lambda + mu) = -384.6 for E = 100, nu = 0.3."""
    hypo = jm.HypoElastic(E=100.0, nu=0.3)
    state = {"stress": jnp.zeros((1, 2, 2))}
    F = np.eye(2)
    for _ in range(60):
        dF = rotation(np.radians(3.0))
        F = dF @ F
        state = hypo.update_state(increment(dF, F), state)
    np.testing.assert_allclose(np.asarray(state["stress"]), 0.0, atol=1e-12)
    tau = np.asarray(jm.LinearElastic(E=100.0, nu=0.3).kirchhoff_stress(jnp.asarray(F[None])))
    lam, mu = 100.0 * 0.3 / (1.3 * 0.4), 100.0 / 2.6
    assert tau[0, 0, 0] == pytest.approx(-4.0 * (lam + mu), rel=1e-9)


def test_hypoelastic_rotates_a_preloaded_stress_and_agrees_with_small_strain():
    """A stress diag(1, 0) carried through rotation increments keeps its eigenvalues (1, 0) to
    round-off (the Hughes-Winget rotation is orthogonal); a small uniaxial stretch of 1e-4 in ten
    increments gives LinearElastic's stress to O(eps^2) (measured relative 1e-4)."""
    hypo = jm.HypoElastic(E=100.0, nu=0.3)
    state = {"stress": jnp.asarray([[[1.0, 0.0], [0.0, 0.0]]])}
    F = np.eye(2)
    for _ in range(30):
        dF = rotation(np.radians(5.0))
        F = dF @ F
        state = hypo.update_state(increment(dF, F), state)
    np.testing.assert_allclose(np.linalg.eigvalsh(np.asarray(state["stress"])[0]), [0.0, 1.0], atol=1e-13)
    state = {"stress": jnp.zeros((1, 2, 2))}
    F = np.eye(2)
    for k in range(1, 11):
        F_new = np.diag([1.0 + 1e-5 * k, 1.0])
        state = hypo.update_state(increment(F_new @ np.linalg.inv(F), F_new), state)
        F = F_new
    total = np.asarray(jm.LinearElastic(E=100.0, nu=0.3).kirchhoff_stress(jnp.asarray(np.diag([1.0001, 1.0])[None])))
    np.testing.assert_allclose(np.asarray(state["stress"]), total, rtol=2e-4, atol=1e-12)


def increment(dF, F, dt=0.01):
    """The strain update's increment a material receives (jm.Increment): dF, the F after it, dt."""
    return jm.Increment(jnp.asarray(dF[None]), jnp.asarray(F[None]), jnp.asarray(dt))


def spin_with(material):
    setup = jm.scene("spin", scheme="apic", stress=True, spacing=1 / 16, frames=2)
    sim = jm.Simulation(grid=setup.sim.grid, shape=setup.sim.shape, material=material, scheme=setup.sim.scheme)
    state = eqx.tree_at(lambda s: s.scheme_state, sim.init(setup.particles), setup.state.scheme_state,
                        is_leaf=lambda x: x is None)
    return sim.run(state, setup.dt, setup.steps, setup.save_every)


@pytest.mark.slow
def test_spinning_elastic_disk_with_the_three_laws():
    """The spin scene (APIC, h = 1/16, one full turn, E = 100, nu = 0.3): HypoElastic ends with the
    neo-Hookean disk's strain energy to 1 % (1.789e-4 vs 1.775e-4 of the initial kinetic energy);
    LinearElastic's total-strain law, not objective, compresses the turning disk until a particle
    inverts (J <= 0) at t = 0.84, about 48 degrees into the turn (measured)."""
    _, hypo = spin_with(jm.HypoElastic(E=100.0, nu=0.3))
    _, neo = spin_with(jm.NeoHookean(E=100.0, nu=0.3))
    assert float(hypo.strain[-1]) == pytest.approx(float(neo.strain[-1]), rel=0.01)
    with pytest.raises(jm.InstabilityError, match="J = det F"):
        spin_with(jm.LinearElastic(E=100.0, nu=0.3))


@pytest.mark.slow
def test_bar_velocity_error_with_either_stress_law():
    """The bar (FLIP, 16 cells, t = 40): max |v_cm - exact| / v0 is 0.0239 with LinearElastic (the
    scene's law, the README's accuracy tables) and 0.0223 with HypoElastic -- measured; issue 16
    quotes an independent dense reference moving from 0.0249 to 0.0225 with the same change."""
    setup = jm.scene("bar")
    errors = {}
    for material in (jm.LinearElastic(E=100.0, nu=0.0, density=1.0), jm.HypoElastic(E=100.0, nu=0.0, density=1.0)):
        sim = jm.Simulation(grid=setup.sim.grid, shape=setup.sim.shape, material=material, scheme=setup.sim.scheme,
                            boundary=setup.sim.boundary)
        state = sim.init(setup.particles)
        _, hist = sim.run(state, setup.dt, setup.steps, setup.save_every)
        m = np.asarray(state.mass)
        vcm = np.asarray(hist.v)[..., 0] @ m / m.sum()
        errors[type(material).__name__] = (np.abs(vcm - setup.reference(np.asarray(hist.time))).max()
                                           / setup.params["v0"])
    assert errors["LinearElastic"] == pytest.approx(0.0239, abs=5e-4)
    assert errors["HypoElastic"] == pytest.approx(0.0223, abs=5e-4)
