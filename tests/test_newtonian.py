"""jm.NewtonianFluid, the weakly compressible Newtonian fluid, float64.

sigma = -p(J) I + 2 eta dev D, tau = J sigma; p = -K (J - 1) ("linear") or K/gamma (J^-gamma - 1)
("tait"); D = sym L of the step's increment, kept in the state for the next stress; the dissipation
2 eta J dev D : dev D dt per reference volume accumulated (jaxmpm/materials/newtonian.py).

* the stress of a prescribed velocity gradient against closed forms (simple shear, dilation in
  2D plane strain and 3D, 1D uniaxial strain, axisymmetric), the pressure laws, their energies;
* the velocity gradient of an exponential increment (the Gregory series of log dF);
* the viscous time-step limit 3 rho h^2 / (16 d eta), through Simulation.time_step_limits, and a run
  either side of it;
* the Taylor-Green vortex in a box with mirror walls: the kinetic energy decays as
  exp(-4 pi^2 nu t) (measured errors below), and the energy balance closes with the dissipation
  in History.totals;
* the gradient of a loss with respect to eta against central differences; bad input.
"""

import contextlib

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg
from cases import central_difference

import jaxmpm as jm
from jaxmpm.materials.newtonian import deviator_norm2

ETA, K = 0.3, 50.0


def state_of(D):
    """A material state holding the rate of deformation ``D`` (d, d) for one particle."""
    D = jnp.asarray(D, dtype=float)[None]
    return {"strain_rate": D, "viscous_dissipation": jnp.zeros((1,))}


def after(material, L, dt=0.01, kinematics="linear", F=None):
    """The state after one increment whose velocity gradient is ``L`` (d, d)."""
    L = np.asarray(L, dtype=float)
    d = L.shape[0]
    dF = scipy.linalg.expm(L * dt) if kinematics == "exponential" else np.eye(d) + L * dt
    F = dF if F is None else F
    increment = jm.Increment(jnp.asarray(dF)[None], jnp.asarray(F)[None], jnp.asarray(dt), kinematics)
    return material.update_state(increment, state_of(np.zeros((d, d))))


# ------------------------------------------------------------------------------ the stress at a point
@pytest.mark.parametrize("d", [2, 3])
def test_simple_shear_gives_sigma_xy_eta_gamma_dot(d):
    """v_x = gamma_dot y: L_xy = gamma_dot, D_xy = gamma_dot / 2, so sigma_xy = eta gamma_dot, no
    normal viscous stress and no pressure at J = 1 (2D plane strain and 3D)."""
    gamma_dot = 4.0
    L = np.zeros((d, d))
    L[0, 1] = gamma_dot
    material = jm.NewtonianFluid(K=K, eta=ETA)
    state = after(material, L)
    tau = np.asarray(material.stress(jnp.eye(d)[None], state))[0]
    expected = np.zeros((d, d))
    expected[0, 1] = expected[1, 0] = ETA * gamma_dot
    np.testing.assert_allclose(tau, expected, atol=1e-13)


def test_dilation_has_no_deviator_in_3d_and_the_plane_strain_one_in_2d():
    """D = a I: in 3D dev D = 0, the stress is the pressure alone.  In 2D plane strain D_zz = 0, so
    dev D = a/3 diag(1, 1, -2): sigma_xx = sigma_yy = -p + 2 eta a/3, tau_zz = J (-p - 4 eta a/3),
    and the mean of the three normal stresses is -p exactly."""
    a, J = 2.0, 0.98
    material = jm.NewtonianFluid(K=K, eta=ETA)
    p = -K * (J - 1.0)
    F3 = jnp.asarray(J ** (1 / 3) * np.eye(3))[None]
    tau3 = np.asarray(material.stress(F3, after(material, a * np.eye(3))))[0]
    np.testing.assert_allclose(tau3, -J * p * np.eye(3), rtol=1e-13)
    F2 = jnp.asarray(J ** 0.5 * np.eye(2))[None]
    state2 = after(material, a * np.eye(2))
    tau2 = np.asarray(material.stress(F2, state2))[0]
    np.testing.assert_allclose(tau2, J * (-p + 2 * ETA * a / 3) * np.eye(2), rtol=1e-13)
    tau_zz = float(material.out_of_plane_stress(F2, state2)[0])
    assert tau_zz == pytest.approx(J * (-p - 4 * ETA * a / 3), rel=1e-13)
    assert (np.trace(tau2) + tau_zz) / (3 * J) == pytest.approx(-p, rel=1e-13)


def test_uniaxial_strain_in_1d_and_the_axisymmetric_hoop_rate():
    """1D (uniaxial strain, D_yy = D_zz = 0): sigma_xx = -p + (4/3) eta D_xx, tau_yy = tau_zz =
    J (-p - 2 eta D_xx / 3).  Axisymmetric (r, z, theta): a hoop rate v_r / r enters dev D as a
    third normal component (D = diag(0, 0, c): sigma_thth = 4 eta c / 3, sigma_rr = -2 eta c / 3)."""
    material = jm.NewtonianFluid(K=K, eta=ETA)
    state = after(material, [[3.0]])
    assert float(material.stress(jnp.ones((1, 1, 1)), state)[0, 0, 0]) == pytest.approx(4 * ETA * 3.0 / 3, rel=1e-13)
    assert float(material.out_of_plane_stress(jnp.ones((1, 1, 1)), state)[0]) == pytest.approx(-2 * ETA, rel=1e-13)
    tau = np.asarray(material.stress(jnp.eye(3)[None], after(material, np.diag([0.0, 0.0, 1.5]))))[0]
    np.testing.assert_allclose(np.diag(tau), [-ETA, -ETA, 2 * ETA], rtol=1e-13)


def test_dissipation_per_update_is_2_eta_J_devD_devD_dt():
    """One increment of L over dt adds 2 eta J dev D : dev D dt, dev D of the 3D tensor (plane
    strain: the zz deviator -tr(D)/3 counts), J of the increment's total F."""
    rng = np.random.default_rng(0)
    L = rng.normal(size=(2, 2))
    D = 0.5 * (L + L.T)
    dev = D - np.trace(D) / 3 * np.eye(2)
    norm2 = np.sum(dev**2) + (np.trace(D) / 3) ** 2
    assert float(deviator_norm2(jnp.asarray(D)[None])[0]) == pytest.approx(norm2, rel=1e-14)
    F = np.diag([1.01, 0.98])
    state = after(jm.NewtonianFluid(K=K, eta=ETA), L, dt=0.02, F=F)
    assert float(state["viscous_dissipation"][0]) == pytest.approx(2 * ETA * np.linalg.det(F) * norm2 * 0.02, rel=1e-13)


def test_exponential_increment_recovers_the_velocity_gradient():
    """Under kinematics="exponential" dF = exp(L dt); the increment's velocity gradient log(dF)/dt
    (the Gregory series) gives L back to 1e-12 for |L dt| up to 0.3, where (dF - I)/dt is off by
    O(|L| |L dt|)."""
    rng = np.random.default_rng(1)
    for d in (1, 2, 3):
        L = rng.normal(size=(4, d, d))
        dt = 0.3 / np.abs(L).max()
        dF = jnp.asarray(np.stack([scipy.linalg.expm(gradient * dt) for gradient in L]))
        back = jm.Increment(dF, dF, jnp.asarray(dt), "exponential").velocity_gradient()
        np.testing.assert_allclose(np.asarray(back), L, atol=1e-12 * np.abs(L).max())
        linear = jm.Increment(dF, dF, jnp.asarray(dt)).velocity_gradient()
        assert np.abs(np.asarray(linear) - L).max() > 1e-3


# --------------------------------------------------------------------------------- the pressure laws
def test_pressure_laws_and_their_energies():
    """linear: p = -K (J - 1); tait: p = K/gamma (J^-gamma - 1); each W(J) has W(1) = 0 and
    W'(J) = -p (so tau = J W' I); dp/dJ = -K at J = 1 for both (c_0 = sqrt(K / rho)); the inverse
    volume_ratio(p) gives J back; Tait with gamma = 1 is VolumetricFluid's law exactly."""
    J = jnp.linspace(0.9, 1.1, 7)
    for eos, gamma in (("linear", 7.0), ("tait", 7.0), ("tait", 1.0), ("tait", 2.5)):
        m = jm.NewtonianFluid(K=K, eos=eos, gamma=gamma)
        p = np.asarray(m.pressure(J))
        expected = -K * (J - 1.0) if eos == "linear" else K / gamma * (J ** (-gamma) - 1.0)
        np.testing.assert_allclose(p, np.asarray(expected), rtol=1e-14, atol=1e-12)
        dW = jax.vmap(jax.grad(lambda j: m.volumetric_energy(j)))(J)
        np.testing.assert_allclose(np.asarray(dW), -p, rtol=1e-12, atol=1e-12)
        assert float(m.volumetric_energy(jnp.asarray(1.0))) == 0.0
        assert float(jax.grad(m.pressure)(1.0)) == pytest.approx(-K, rel=1e-14)
        np.testing.assert_allclose(np.asarray(m.volume_ratio(m.pressure(J))), np.asarray(J), rtol=1e-13)
    F = jnp.asarray(np.diag([1.03, 0.95]))[None]
    tait1, volumetric = jm.NewtonianFluid(K=K, eos="tait", gamma=1.0), jm.VolumetricFluid(E=K)
    state = state_of(np.zeros((2, 2)))
    np.testing.assert_allclose(np.asarray(tait1.stress(F, state)), np.asarray(volumetric.stress(F, None)), rtol=1e-13)
    np.testing.assert_allclose(np.asarray(tait1.stored_energy_density(F, state)),
                               np.asarray(volumetric.stored_energy_density(F, None)), rtol=1e-12)


# ------------------------------------------------------------------------------------- the time step
def bar_1d(eta, cells=16, K=1e-6):
    """A 1D column of fluid between fixed ends, linear shapes, FLIP, random velocities (every mode)."""
    grid = jm.Grid((0.0,), (1.0,), (cells,))
    particles = jm.fill(grid, jm.Box((0.0,), (1.0,)), ppc=2,
                        velocity=lambda x: jnp.asarray(np.random.default_rng(2).normal(size=x.shape)) * 1e-3)
    sim = jm.Simulation(grid, "linear", jm.NewtonianFluid(K=K, eta=eta), jm.FLIP(), damping=False,
                        boundary=[jm.Fixed("x-"), jm.Fixed("x+")])
    return sim, sim.init(particles)


def test_viscous_time_step_limit():
    """dt <= 3 rho h^2 / (16 d eta) (half LeVeque 2007 §9.1's explicit diffusion limit h^2 / (2 d nu)
    for the longitudinal viscosity nu = 4 eta / (3 rho), for FLIP); Simulation.time_step_limits
    names it after the material and stable_dt takes the smaller one; eta = 0 sets no limit."""
    m = jm.NewtonianFluid(K=1.0, eta=0.5, density=2.0)
    assert float(m.time_step_limit(0.1, 2)) == pytest.approx(3 * 2.0 * 0.01 / (16 * 2 * 0.5), rel=1e-14)
    assert jm.NewtonianFluid(K=1.0).time_step_limit(0.1, 2) is None
    assert jm.LinearElastic(E=1.0).time_step_limit(0.1, 2) is None
    sim, state = bar_1d(eta=0.01)
    limits = sim.time_step_limits(state, cfl=0.5)
    h = 1.0 / 16
    assert float(limits["newtonianfluid"]) == pytest.approx(0.5 * 3 * h**2 / (16 * 0.01), rel=1e-13)
    assert float(sim.stable_dt(state, 0.5)) == pytest.approx(min(float(v) for v in limits.values()), rel=1e-14)
    assert float(limits["newtonianfluid"]) < float(limits["CFL"])  # the viscous limit binds here
    inviscid, state = bar_1d(eta=0.0)
    assert set(inviscid.time_step_limits(state, cfl=0.5)) == {"CFL"}  # no limit of its own: no entry


def test_a_run_is_stable_below_the_viscous_limit_and_blows_up_above():
    """The 1D column under FLIP (linear shapes: the MPM operator is the finite-difference one, largest
    eigenvalue 4/h^2 of the longitudinal (4/3) eta / rho; the checkerboard's mass ratio mu = 1/3
    puts FLIP's threshold at 1.2 times the limit): at 0.95 of the limit the kinetic energy decays
    (measured to 0.558 of its start in 300 steps: FLIP's particle modes the grid does not see keep
    theirs), at 1.5 the grid-scale mode grows (measured x975; x219 at 1.3, 0.558 at 1.1).  The
    stiffness K is tiny so that the CFL limit does not bind."""
    sim, state = bar_1d(eta=0.01)
    limit = float(sim.material.time_step_limit(sim.grid.h, 1))
    ratios = {}
    for factor in (0.95, 1.5):
        with pytest.warns(jm.StableTimeStepWarning) if factor > 1 else contextlib.nullcontext():
            _, history = sim.run(state, factor * limit, 300, save_every=300, check_stability=False)
        ratios[factor] = float(history.kinetic[-1] / history.kinetic[0])
    assert ratios[0.95] < 0.6 and ratios[1.5] > 100.0, ratios


# ------------------------------------------------------------------------------ Taylor-Green vortex
NU = 0.01


def taylor_green(cells, eta=NU, A=0.01, scheme=None):
    """The Taylor-Green vortex v = A (sin pi x cos pi y, -cos pi x sin pi y) in the unit box, whose
    walls are mirror planes (the vortex is symmetric about them, so they hold it exactly: zero
    normal velocity and shear stress), quadratic B-splines, FLIP, rho = 1, c_0 = 1 (Mach 0.01).
    Exact for Stokes flow (and for Navier-Stokes, with its pressure): v ~ exp(-2 pi^2 nu t)."""
    h = 1.0 / cells
    grid = jm.Grid((-2 * h, -2 * h), (1 + 2 * h, 1 + 2 * h), (cells + 4, cells + 4))
    vortex = lambda x: A * jnp.stack([jnp.sin(jnp.pi * x[:, 0]) * jnp.cos(jnp.pi * x[:, 1]),  # noqa: E731
                                      -jnp.cos(jnp.pi * x[:, 0]) * jnp.sin(jnp.pi * x[:, 1])], axis=1)
    particles = jm.fill(grid, jm.Box((0.0, 0.0), (1.0, 1.0)), ppc=2, velocity=vortex)
    walls = [jm.Mirror("x-", 0.0), jm.Mirror("x+", 1.0), jm.Mirror("y-", 0.0), jm.Mirror("y+", 1.0)]
    sim = jm.Simulation(grid, "quadratic", jm.NewtonianFluid(K=1.0, eta=eta), scheme or jm.FLIP(), damping=False,
                        boundary=walls)
    return sim, sim.init(particles)


def decay(cells, t_end=2.0):
    sim, state = taylor_green(cells)
    steps = int(np.ceil(t_end / (0.5 * float(sim.stable_dt(state)))))
    _, history = sim.run(state, t_end / steps, steps, save_every=steps)
    return history


@pytest.mark.slow
def test_taylor_green_vortex_decays_at_the_viscous_rate():
    """16 cells per side: K(2)/K(0) within 4.5% of exp(-4 pi^2 nu t) = 0.454 (measured +4.07%: the
    quadratic B-spline's lumped Laplacian is smaller than -k^2 for a mode of 16 cells per half
    wave; 8 cells: +14.2%, second order).  The energy balance K + U + dissipated by the viscous stress
    closes to 1% of K(0) (measured 0.7%: the explicit viscous stress lags a step), and FLIP
    dissipates nothing."""
    history = decay(16)
    K0 = float(history.kinetic[0])
    exact = np.exp(-4 * np.pi**2 * NU * 2.0)
    ratio = float(history.kinetic[-1]) / K0
    assert 0.0 < ratio / exact - 1.0 < 0.045, ratio / exact - 1.0
    viscous = float(history.totals["viscous_dissipation"][-1])
    balance = (float(history.kinetic[-1]) + float(history.strain[-1]) + viscous) / K0 - 1.0
    assert abs(balance) < 0.01, balance
    assert abs(float(history.dissipated[-1])) < 1e-12 * K0


@pytest.mark.slow
def test_taylor_green_decay_converges_at_second_order():
    """The error of K(2)/K(0): 8 cells +14.2%, 16 cells +4.07% (measured): a ratio above 3 per halving."""
    exact = np.exp(-4 * np.pi**2 * NU * 2.0)
    errors = []
    for cells in (8, 16):
        history = decay(cells)
        errors.append(float(history.kinetic[-1] / history.kinetic[0]) / exact - 1.0)
    assert errors[0] / errors[1] > 3.0, errors


@pytest.mark.slow
def test_gradient_of_the_decay_with_respect_to_eta():
    """d K(t) / d eta of the Taylor-Green vortex (4 cells, 5 steps) by reverse mode equals the
    central difference (step 1e-5) to 1e-6."""
    sim, state = taylor_green(4)
    dt = 0.5 * float(sim.stable_dt(state))

    def loss(eta):
        model = eqx.tree_at(lambda s: s.material.eta, sim, jnp.asarray(eta))
        final, _ = model.run(state, dt, 5, save_every=5, save_particles=False)
        return jm.kinetic_energy(final)

    grad = float(jax.grad(loss)(NU))
    fd = float(central_difference(lambda e: loss(e), NU, 1e-5))
    assert grad < 0.0
    assert grad == pytest.approx(fd, rel=1e-6)


@pytest.mark.parametrize("eos", ["linear", "tait"])
def test_stress_gradient_with_respect_to_K_gamma_and_eta(eos):
    """d(tau : W)/d(K, gamma, eta) of a compressed, sheared particle by reverse mode equals the
    central difference (these parameters reach a run through the stress alone)."""
    F = jnp.asarray([[0.97, 0.02], [0.0, 0.98]])[None]
    L = np.array([[-0.3, 1.0], [0.2, 0.1]])
    weights = jnp.asarray([[1.0, 0.4], [-0.3, 0.7]])

    @jax.jit
    def loss(params):
        material = jm.NewtonianFluid(params[0], eta=params[2], eos=eos, gamma=params[1])
        state = material.update_state(jm.Increment(jnp.eye(2)[None] + jnp.asarray(L)[None] * 0.01, F,
                                                   jnp.asarray(0.01)), state_of(np.zeros((2, 2))))
        return jnp.sum(material.stress(F, state)[0] * weights)

    params = jnp.asarray([K, 7.0, ETA])
    grad = jax.grad(loss)(params)
    for k in range(3):
        e = jnp.zeros(3).at[k].set(1e-4 * float(params[k]))
        fd = (loss(params + e) - loss(params - e)) / (2e-4 * float(params[k]))
        if eos == "linear" and k == 1:
            assert float(grad[k]) == 0.0  # gamma is Tait's only
            continue
        assert float(grad[k]) == pytest.approx(float(fd), rel=1e-7), k


# ---------------------------------------------------------------------------------------- bad input
@pytest.mark.parametrize("kwargs, match", [
    (dict(K=1.0, eta=-0.1), "eta = -0.1 must be >= 0"),
    (dict(K=0.0), "K = 0.0 must be positive"),
    (dict(K=1.0, gamma=0.0), "gamma = 0.0 must be positive"),
    (dict(K=1.0, gamma=-7.0), "gamma"),
    (dict(K=1.0, eos="ideal"), "eos = 'ideal'"),
    (dict(K=1.0, density=-1.0), "density"),
    (dict(K=float("nan")), "K"),
])
def test_bad_input(kwargs, match):
    with pytest.raises(jm.InputError, match=match):
        jm.NewtonianFluid(**kwargs)
