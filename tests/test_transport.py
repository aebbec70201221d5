"""Transport: heat conduction and diffusion (001 §8-9; jaxmpm/_transport.py), float64.

1. ``heat1d`` by hand: a rod [0, 1] with T = 0 held at both ends and T0 = sin(pi x); exact
   T = exp(-k pi^2 t / (rho C_p)) sin(pi x).  Linear shapes converge at second order in h;
   quadratic and cubic B-splines with mirrored ends too, but with plainly held nodes beyond the
   ends only at about first order -- a strict xfail with the numbers;
2. the steady state between held temperatures 1 and 0 is the exact linear profile to round-off,
   on the particles and on the grid (T_{g->p}, 001 eq. 145); heat_step and diffusion2d converge
   at second order, particles and grid;
3. without sources or flux boundaries the thermal energy sum_p M_p C_p T_p is conserved to
   round-off under FLIP (sum_i G_ip = 0); with k = 0 FLIP leaves T unchanged, bit for bit, while
   PIC changes it (001 §8: "the addition of PIC character ... leads to thermal conduction");
4. a free bar heated uniformly expands by alpha_T dT L (thermal stretch, damped to rest);
5. diffusion is conduction with rho = C_p = 1 (001 §9): the same run to round-off;
6. derivatives with respect to k, C_p and alpha_T against central differences;
7. bad input, the conduction time-step warning, and the HDF5 output.
"""

import math

import equinox as eqx
import h5py
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from cases import central_difference, dense_weights

import jaxmpm as jm

L = 1.0


def rod(cells, shape=None, update="flip", conductivity=1.0, heat_capacity=1.0, density=1.0, initial=None,
        boundary="held", cls=jm.Heat):
    """A 1D rod [0, L] (NoStress material: the particles stay put), ``cells`` cells, 2 particles
    per cell; ``boundary`` "held" (T = 0 at both ends) or None; returns (sim, state, heat term)."""
    shape = jm.Linear() if shape is None else shape
    h = L / cells
    grid = jm.Grid.covering((0.0,), (L,), h, shape=shape)
    particles = jm.fill(grid, jm.Box((0.0,), (L,)), ppc=2)
    initial = (lambda x: np.sin(np.pi * x[:, 0])) if initial is None else initial
    ends = [jm.Dirichlet(lambda x: (x[:, 0] <= 1e-12) | (x[:, 0] >= L - 1e-12), 0.0)] if boundary == "held" \
        else boundary
    if cls is jm.Heat:
        term = jm.Heat(conductivity=conductivity, heat_capacity=heat_capacity, initial=initial, update=update,
                       boundary=ends)
    else:
        term = jm.Diffusion(diffusivity=conductivity, initial=initial, update=update, boundary=ends)
    sim = jm.Simulation(grid=grid, shape=shape, material=jm.NoStress(density=density), scheme=jm.FLIP(),
                        terms=(term,), damping=False)
    return sim, sim.init(particles), term


@eqx.filter_jit
def advance(sim, state, dt, steps):
    return jax.lax.fori_loop(0, steps, lambda _, s: sim.step(s, dt), state)


def sine_error(cells, shape=None, t_end=0.05, boundary="held"):
    sim, state, _ = rod(cells, shape, boundary=boundary)
    h = L / cells
    steps = int(round(t_end / (0.25 * h * h)))
    final = advance(sim, state, t_end / steps, steps)
    x = np.asarray(final.x)[:, 0]
    exact = math.exp(-math.pi**2 * t_end) * np.sin(np.pi * x)
    return np.abs(np.asarray(final.fields["temperature"]) - exact).max() / np.abs(exact).max()


# ------------------------------------------------------------------ 1. convergence
@pytest.mark.slow
def test_heat1d_converges_at_second_order_with_linear_shapes():
    """Measured max relative error at t = 0.05: 1.14e-2, 2.77e-3, 6.95e-4 (8, 16, 32 cells):
    orders 2.04, 2.00 (uGIMP gives the same numbers: its particles at h/4 lie inside one cell)."""
    errors = [sine_error(c) for c in (8, 16, 32)]
    orders = np.log2(np.asarray(errors[:-1]) / np.asarray(errors[1:]))
    assert np.all(orders >= 1.9), (errors, orders)
    assert errors[-1] < 2e-3


@pytest.mark.slow
@pytest.mark.xfail(strict=True, raises=AssertionError,
                   reason="quadratic B-splines with plainly held nodes: measured errors 0.137, 0.087, 0.045 (8, "
                          "16, 32 cells, t = 0.05), orders 0.66, 0.95 -- the nodes beyond the ends are held at "
                          "T = 0 instead of the odd extension; Dirichlet(mirror=...) gives order 2 (next test)")
def test_heat1d_converges_at_second_order_with_quadratic_bsplines():
    errors = [sine_error(c, jm.QuadraticBSpline()) for c in (8, 16, 32)]
    orders = np.log2(np.asarray(errors[:-1]) / np.asarray(errors[1:]))
    assert np.all(orders >= 1.9), (errors, orders)


@pytest.mark.slow
@pytest.mark.parametrize("shape", [jm.QuadraticBSpline(), jm.CubicBSpline()], ids=["quadratic", "cubic"])
def test_heat1d_converges_at_second_order_with_bsplines_and_mirrored_ends(shape):
    """jm.Dirichlet(..., mirror=(axis, position)): the nodes beyond the end carry the odd extension
    and the particles' odd images are folded onto the grid.  Measured at t = 0.05 (8, 16, 32
    cells): quadratic 3.04e-2, 7.53e-3, 1.88e-3; cubic 4.13e-2, 1.03e-2, 2.58e-3 (orders 2.0)."""
    ends = [jm.Dirichlet(lambda x: x[:, 0] <= 1e-12, 0.0, mirror=(0, 0.0)),
            jm.Dirichlet(lambda x: x[:, 0] >= L - 1e-12, 0.0, mirror=(0, L))]
    errors = [sine_error(c, shape, boundary=ends) for c in (8, 16, 32)]
    orders = np.log2(np.asarray(errors[:-1]) / np.asarray(errors[1:]))
    assert np.all(orders >= 1.9), (errors, orders)


# ------------------------------------------------------------------ 2. steady state
@pytest.mark.slow
def test_steady_state_between_held_temperatures_is_linear():
    """T = 1 held at x = 0 and T = 0 at x = L, from T = 0: at t = 3 (the slowest mode has decayed
    by e^-30) the particle temperatures and the grid temperature T_{g->p} = S T_i are 1 - x to
    1e-10 (measured 1.0e-13 both).  The particles next to the hot end take its switch-on jump
    (1 - 0) once, at the first step (Transport.switch_on); without it they kept the initial 0
    and the FLIP values were off by up to 0.67 there."""
    ends = [jm.Dirichlet(lambda x: x[:, 0] <= 1e-12, 1.0), jm.Dirichlet(lambda x: x[:, 0] >= L - 1e-12, 0.0)]
    sim, state, heat = rod(16, initial=0.0, boundary=ends)
    h = L / 16
    final = advance(sim, state, 0.25 * h * h, int(round(3.0 / (0.25 * h * h))))
    x = np.asarray(final.x)[:, 0]
    np.testing.assert_allclose(np.asarray(heat.grid_value(sim, final)), 1.0 - x, rtol=0, atol=1e-10)
    np.testing.assert_allclose(np.asarray(final.fields["temperature"]), 1.0 - x, rtol=0, atol=1e-10)


# ------------------------------------------------------------------ 3. conservation, k = 0
def noisy(x):
    return np.sin(3.0 * x[:, 0]) + 0.3 * np.cos(40.0 * x[:, 0])


@pytest.mark.slow
def test_thermal_energy_is_conserved_without_boundaries():
    """sum_p M_p C_p T_p after 200 FLIP steps equals its initial value to 1e-14 relative
    (sum_p m_Tp dT_p = sum_i Q_i dt = sum_p V_p q_p . sum_i G_ip dt = 0)."""
    sim, state, heat = rod(16, boundary=None, initial=noisy, heat_capacity=2.5, density=3.0)
    final, hist = sim.run(state, 1e-4, 200, 20)
    energy = np.asarray(hist.totals["thermal_energy"])
    expected = float(jnp.sum(state.mass * 2.5 * state.fields["temperature"]))
    assert energy[0] == pytest.approx(expected, rel=1e-15)
    np.testing.assert_allclose(energy, expected, rtol=1e-14)
    assert np.abs(np.asarray(final.fields["temperature"] - state.fields["temperature"])).max() > 1e-3  # it conducts


def test_zero_conductivity_leaves_flip_temperatures_and_pic_smooths_them():
    """k = 0: FLIP keeps T bit for bit; PIC replaces T_p by its grid projection every step and
    changes it by up to 0.27 (measured, 100 steps) -- conduction without conductivity (001 §8)."""
    flip, state, _ = rod(16, boundary=None, initial=noisy, conductivity=0.0)
    final = advance(flip, state, 1e-3, 100)
    np.testing.assert_array_equal(np.asarray(final.fields["temperature"]), np.asarray(state.fields["temperature"]))
    pic, state, _ = rod(16, boundary=None, initial=noisy, conductivity=0.0, update="pic")
    final = advance(pic, state, 1e-3, 100)
    assert np.abs(np.asarray(final.fields["temperature"] - state.fields["temperature"])).max() > 0.1


# ------------------------------------------------------------------ XPIC for transport (000 §3.6)
def one_step(update, beta=None, conductivity=0.7, shape=None):
    sim, state, _ = rod(8, shape=shape, initial=noisy, conductivity=conductivity, heat_capacity=1.7, density=2.0,
                        boundary=None)
    sim = sim.with_term(jm.Heat(conductivity=conductivity, heat_capacity=1.7, update=update, beta=beta, initial=noisy))
    return sim, state, np.asarray(advance(sim, state, 1e-3, 1).fields["temperature"])


def test_xpic_transport_of_order_one_is_the_blend_of_000_eq_3_60():
    """m = 1: T^{n+1} = beta (T + S a dt) + (1 - beta) S t~ (000 eq. 3.60): beta = 1 is FLIP bit for
    bit, beta = 0 is PIC, and beta = 0.3 is 0.3 FLIP + 0.7 PIC (to round-off)."""
    _, _, flip = one_step("flip")
    _, _, pic = one_step("pic")
    np.testing.assert_array_equal(one_step("xpic:1", beta=1.0)[2], flip)
    np.testing.assert_allclose(one_step("xpic:1")[2], pic, rtol=0, atol=1e-14)
    np.testing.assert_allclose(one_step("xpic:1", beta=0.3)[2], 0.3 * flip + 0.7 * pic, rtol=0, atol=1e-14)
    assert np.abs(flip - pic).max() > 1e-2


@pytest.mark.parametrize("order", [2, 3])
@pytest.mark.parametrize("beta", [0.0, 0.4])
def test_xpic_transport_matches_its_matrix_form(order, beta):
    """k = 0 (no flow: a_T = 0): one step is T^{n+1} = T - (1 - beta) (I - S S+)^m T (000 eq. 3.51)
    with S+_ip = m_Tp S_pi / m_Ti the capacity-weighted extrapolation (000 eq. 3.53), dense
    matrices from the stencil (quadratic B-splines)."""
    sim, state, new = one_step(f"xpic:{order}", beta=beta, conductivity=0.0, shape=jm.QuadraticBSpline())
    S, _ = dense_weights(sim.shape.stencil(sim.grid, state.x), sim.grid.num_nodes)
    capacity = np.asarray(state.mass) * 1.7
    m_T = S.T @ capacity
    keep = m_T > 0
    S, m_T = S[:, keep], m_T[keep]
    S_plus = (S * capacity[:, None]).T / m_T[:, None]
    T = np.asarray(state.fields["temperature"])
    null = np.linalg.matrix_power(np.eye(len(T)) - S @ S_plus, order) @ T
    np.testing.assert_allclose(new, T - (1.0 - beta) * null, rtol=0, atol=1e-13)


# ------------------------------------------------------------------ 4. thermal expansion
def thermal_bar(alpha=1e-3, delta=50.0, E=1e4, steps=4000):
    """A free 1D bar [0, 1] at T = delta above T_ref = 0, k = 0 (it stays uniform), uGIMP (linear
    shapes break up at the free ends as they cross cells), damped; returns (sim, state)."""
    shape = jm.UGIMP(ppc=2)
    grid = jm.Grid.covering((-0.2,), (1.2,), 1.0 / 32, shape=shape)
    particles = jm.fill(grid, jm.Box((0.0,), (1.0,)), ppc=2)
    heat = jm.Heat(conductivity=0.0, expansion=alpha, initial=delta)
    sim = jm.Simulation(grid=grid, shape=shape, material=jm.LinearElastic(E=E, nu=0.0, density=1.0),
                        scheme=jm.FLIP(), terms=(heat,), damping=jm.Damping(particle=20.0))
    return sim, sim.init(particles)


def bar_length(state):
    x = np.asarray(state.x)[:, 0]
    return x.max() - x.min() + (x[1] - x[0])  # the particles' domains: half a spacing beyond each end


@pytest.mark.slow
def test_free_bar_expands_by_alpha_dT_L():
    """alpha_T = 1e-3, dT = 50: the bar's stress-free state is F = 1 + alpha dT = 1.05.  After the
    damped oscillation (t = 0.625) the mean stretch sum_p V0_p F_p / L - 1 is 0.0499837 (error
    3.3e-4 relative, within the issue's 1 %; docs/transport.md had said 0.049998 until 2026-11-29).  The
    particle positions lag it: the bar's span grows
    by 0.0489 (2.3 % short), the usual gap between MPM's position update (S v) and its F update
    (grad v) at free ends (uGIMP; measured, not asserted)."""
    sim, state = thermal_bar()
    final = advance(sim, state, 1.0 / 32 / 100 * 0.5, 4000)
    stretch = float(jnp.sum(final.volume0 * final.F[:, 0, 0]) / jnp.sum(final.volume0)) - 1.0
    assert stretch == pytest.approx(1e-3 * 50.0, rel=1e-2), stretch  # the goal
    assert stretch == pytest.approx(0.0499837, rel=2e-5), stretch  # the number the docs state
    assert 0.9 * 0.05 < bar_length(final) - bar_length(state) < 1.1 * 0.05  # the span grew, and by about that


# ------------------------------------------------------------------ 5. diffusion = conduction
@pytest.mark.slow
def test_diffusion_is_conduction_with_unit_density_and_capacity():
    """001 §9: mu with D for k, rho = C_p = 1 and the volume as mass: the same temperatures and
    concentrations to round-off (measured 0 difference)."""
    heat, s1, _ = rod(16, initial=noisy)
    diff, s2, _ = rod(16, initial=noisy, cls=jm.Diffusion)
    a = advance(heat, s1, 1e-3, 50).fields["temperature"]
    b = advance(diff, s2, 1e-3, 50).fields["concentration"]
    np.testing.assert_allclose(np.asarray(b), np.asarray(a), rtol=0, atol=1e-14)


# ------------------------------------------------------------------ 6. gradients
@pytest.mark.slow
@pytest.mark.parametrize("name", ["conductivity", "heat_capacity"])
def test_gradient_of_temperatures(name):
    sim, state, _ = rod(8, initial=noisy, conductivity=0.7, heat_capacity=1.3)

    def loss(value):
        model = jm.set_params(sim, **{name: value})
        return jnp.sum(advance(model, state, 2e-3, 20).fields["temperature"] ** 2)

    value = 0.7 if name == "conductivity" else 1.3
    grad = float(jax.grad(loss)(jnp.asarray(value)))
    fd = central_difference(lambda v: float(loss(jnp.asarray(v))), value, 1e-5)
    assert abs(grad - fd) <= 1e-6 * abs(fd), (grad, fd)


@pytest.mark.slow
def test_gradient_of_expansion():
    """d/d alpha_T of the particle positions after 50 steps of the thermal bar."""
    sim, state = thermal_bar()

    def loss(alpha):
        model = jm.set_params(sim, thermal_expansion=alpha)
        return jnp.sum(advance(model, state, 1.0 / 32 / 100 * 0.5, 50).x[:, 0] ** 2)

    grad = float(jax.grad(loss)(jnp.asarray(1e-3)))
    fd = central_difference(lambda a: float(loss(jnp.asarray(a))), 1e-3, 1e-7, order=4)
    assert abs(grad - fd) <= 1e-6 * abs(fd), (grad, fd)


# ------------------------------------------------------------------ 7. bad input, warnings, output
@pytest.mark.parametrize("make, name", [
    (lambda: jm.Heat(conductivity=-1.0), "conductivity"),
    (lambda: jm.Heat(conductivity=1.0, heat_capacity=0.0), "heat_capacity"),
    (lambda: jm.Diffusion(diffusivity=-0.1), "diffusivity"),
    (lambda: jm.Heat(conductivity=1.0, update="xpic"), "update"),
    (lambda: jm.Heat(conductivity=1.0, update="xpic:0"), "update"),
    (lambda: jm.Heat(conductivity=1.0, beta=1.5), "beta"),
    (lambda: jm.Heat(conductivity=[[1.0, 2.0], [0.0, 1.0]]), "conductivity"),
    (lambda: jm.Heat(conductivity=1.0, boundary=[jm.Fixed("x-")]), "boundary"),
    (lambda: jm.Dirichlet("x-", float("nan")), "value"),
])
def test_bad_transport_input(make, name):
    with pytest.raises(jm.InputError, match=name):
        make()


def test_transport_options_on_a_scene_without_the_field():
    with pytest.raises(jm.InputError, match="conductivity"):
        jm.scene("bar", conductivity=1.0)
    with pytest.raises(jm.InputError, match="transport"):
        jm.scene("disks", transport="xpic:2")
    with pytest.raises(jm.InputError, match="heat_capacity"):
        jm.scene("heat1d", heat_capacity=0.0)
    with pytest.raises(jm.InputError, match="diffusivity"):
        jm.scene("diffusion2d", diffusivity=-1.0)


def test_time_step_above_the_conduction_limit_warns_with_the_limit():
    sim, state, _ = rod(16)
    limits = sim.time_step_limits(state)
    assert float(limits["heat"]) == pytest.approx((1 / 16) ** 2 / 2, rel=1e-12)
    assert float(sim.stable_dt(state)) == pytest.approx(float(limits["heat"]), rel=1e-15)
    with pytest.warns(jm.StableTimeStepWarning, match="heat"):
        sim.run(state, 1.5 * float(limits["heat"]), 2, 1)


@pytest.mark.slow
def test_temperature_and_thermal_energy_are_written(tmp_path):
    sim, state, _ = rod(8)
    _, hist = sim.run(state, 1e-3, 4, 2)
    path = tmp_path / "heat.h5"
    jm.save_h5(path, sim, hist, state=state, dt=1e-3)
    with h5py.File(path) as f:
        np.testing.assert_array_equal(f["particles/temperature"][...], np.asarray(hist.fields["temperature"]))
        np.testing.assert_array_equal(f["totals/thermal_energy"][...], np.asarray(hist.totals["thermal_energy"]))
        assert float(f.attrs["conductivity"]) == 1.0


# ------------------------------------------------------------------ XPIC for stress (000 §3.7)
@pytest.mark.slow
@pytest.mark.parametrize("order", [1, 2, 4])
def test_xpic_stress_matches_its_matrix_form(order):
    """tau~ = tau - (I - S S+)^m tau per stress component (000 eqs. 3.64-3.67), S+ mass-weighted;
    2D, quadratic B-splines, random stresses and masses."""
    from jaxmpm.physics.stress import xpic_stress

    rng = np.random.default_rng(5)
    grid = jm.Grid((0.0, 0.0), (1.0, 1.0), (6, 6))
    x = jnp.asarray(rng.uniform(0.25, 0.75, (40, 2)))
    mass = jnp.asarray(rng.uniform(0.5, 2.0, 40))
    tau = jnp.asarray(rng.normal(size=(40, 2, 2)))
    stencil = jm.QuadraticBSpline().stencil(grid, x)
    smoothed = np.asarray(xpic_stress(stencil, mass, tau, order, grid.num_nodes))
    S, _ = dense_weights(stencil, grid.num_nodes)
    m_i = S.T @ np.asarray(mass)
    S, m_i = S[:, m_i > 0], m_i[m_i > 0]
    S_plus = (S * np.asarray(mass)[:, None]).T / m_i[:, None]
    null = np.linalg.matrix_power(np.eye(40) - S @ S_plus, order)
    expected = np.asarray(tau) - np.einsum("pq,qab->pab", null, np.asarray(tau))
    np.testing.assert_allclose(smoothed, expected, rtol=0, atol=1e-12)


@pytest.mark.slow
def test_xpic_stress_keeps_momentum_on_disks():
    """Sulsky's disks with the force from XPIC(3)-smoothed stress: momentum conserved to
    round-off (sum_i G_ip = 0 whatever the stress), and the run differs from the plain one."""
    setup = jm.scene("disks", spacing=0.1, t_end=1.5, frames=3)  # in contact from t ~ 1
    sim = setup.sim.with_term(jm.StressDivergence(xpic=3))
    final, hist = sim.run(setup.state, setup.dt, setup.steps, setup.save_every)
    plain, _ = setup.run()
    scale = float(jnp.sum(setup.state.mass * jnp.linalg.norm(setup.state.v, axis=1)))
    assert np.abs(np.asarray(hist.momentum) - np.asarray(hist.momentum[0])).max() <= 1e-13 * scale
    assert np.abs(np.asarray(final.x - plain.x)).max() > 1e-12
    with pytest.raises(jm.InputError, match="xpic"):
        jm.StressDivergence(xpic=-1)


# ------------------------------------------------------------------ the scenes, calibration, the CLI
def grid_error(setup):
    final = advance(setup.sim, setup.state, setup.dt, setup.steps)
    term = next(t for t in setup.sim.terms if isinstance(t, jm.Transport))
    exact = setup.reference(final.time, np.asarray(final.x))
    return np.abs(np.asarray(term.grid_value(setup.sim, final)) - exact).max(), final


@pytest.mark.slow
@pytest.mark.parametrize("name, cells, shape", [("heat_step", (16, 32, 64), "linear"),
                                                ("heat_step", (32, 64, 128), "quadratic"),
                                                ("diffusion2d", (8, 16, 32), "linear")])
def test_held_boundary_scenes_converge_at_second_order(name, cells, shape):
    """heat_step (erfc, t = 0.01) and diffusion2d (double sine series, t = 0.05), linear shapes:
    the FLIP particle values and the grid temperature T_{g->p} converge at second order (measured
    particles: heat_step 1.07e-2, 2.70e-3, 6.70e-4; diffusion2d 1.62e-2, 3.42e-3, 8.38e-4; grid:
    2.22e-2, 5.84e-3, 1.45e-3 and 3.08e-2, 6.93e-3, 1.82e-3; heat_step with quadratic B-splines
    and its mirrored end at 32, 64, 128 cells: particles 8.07e-3, 1.54e-3, 3.89e-4, grid 6.91e-3,
    1.73e-3, 4.42e-4).  The held boundary switches on at
    t = 0 against an initial field of 0: its jump reaches the particles at the first step
    (Transport.switch_on) -- without that the particles beside it kept the initial value (errors
    0.67 and 0.89 at every h)."""
    particle, grid = [], []
    for c in cells:
        setup = jm.scene(name, cells=c, shape=shape)
        error, final = grid_error(setup)
        grid.append(error)
        term = next(t for t in setup.sim.terms if isinstance(t, jm.Transport))
        exact = setup.reference(final.time, np.asarray(final.x))
        particle.append(np.abs(np.asarray(final.fields[term.FIELD]) - exact).max())
    for errors in (particle, grid):
        orders = np.log2(np.asarray(errors[:-1]) / np.asarray(errors[1:]))
        assert np.all(orders >= 1.9), (particle, grid)


@pytest.mark.slow
def test_thermal_bar_scene_settles_at_alpha_dT():
    setup = jm.scene("thermal_bar", frames=2)
    final, _ = setup.run()
    stretch = float(jnp.sum(final.volume0 * final.F[:, 0, 0]) / jnp.sum(final.volume0)) - 1.0
    assert stretch == pytest.approx(setup.reference(setup.t_end), rel=1e-2)
    assert setup.params["thermal_expansion"] == 1e-3 and setup.params["expansion_length"] == pytest.approx(0.05)


@pytest.mark.slow
def test_calibrate_recovers_the_conductivity():
    """A synthetic temperature history of heat1d (8 cells, k = 1.3), fitted from k = 1: recovered
    within 1 % (measured to 1e-9)."""
    setup = jm.scene("heat1d", cells=8, t_end=0.05)

    def history(k):
        model = jm.set_params(setup.sim, conductivity=k)
        _, temps = jax.lax.scan(lambda s, _: (model.step(s, setup.dt),) * 2, setup.state, None, length=setup.steps)
        return temps.fields["temperature"][::5]

    target = history(jnp.asarray(1.3))
    fit = jm.calibrate(lambda p: jnp.sum((history(p["conductivity"]) - target) ** 2), {"conductivity": 1.0},
                       optimizer=__import__("optax").lbfgs(), steps=30, tol=1e-24)
    assert fit.params["conductivity"] == pytest.approx(1.3, rel=1e-2), fit.params


@pytest.mark.slow
def test_command_line_runs_a_transport_scene(tmp_path, capsys):
    from jaxmpm import cli

    out = tmp_path / "heat.h5"
    assert cli.main(["run", "heat1d", "--cells", "8", "--conductivity", "0.5", "--transport-xpic", "2",
                     "--out", str(out)]) == 0
    assert "thermal energy" in capsys.readouterr().out
    with h5py.File(out) as f:
        assert f.attrs["conductivity"] == 0.5 and "particles/temperature" in f and "totals/thermal_energy" in f
    with pytest.raises(SystemExit):
        cli.main(["run", "heat1d", "--transport-xpic", "0", "--out", str(tmp_path / "bad.h5")])
    assert "transport" in capsys.readouterr().err


# ------------------------------------------------------------------ flux boundaries, tensor conductivity
@pytest.mark.slow
def test_heat_flux_boundary_adds_exactly_its_heat():
    """An insulated rod with q = 2.5 flowing in at x = 0 (jm.Neumann, 001 eq. 136): the thermal
    energy grows by q dt every step, to round-off (sum_p m_Tp dT_p = sum_i Q_i dt)."""
    sim, state, _ = rod(16, initial=noisy, boundary=[jm.Neumann(lambda x: x[:, 0] <= 1e-12, 2.5)])
    _, hist = sim.run(state, 1e-4, 100, 10)
    energy = np.asarray(hist.totals["thermal_energy"])
    np.testing.assert_allclose(np.diff(energy), 2.5 * 1e-4 * 10, rtol=1e-10)


@pytest.mark.slow
def test_tensor_conductivity_conducts_along_its_axes_only():
    """2D, k = diag(1, 0): a field varying along y only does not change (measured to 1e-16); one
    varying along x conducts.  A 1D model given a 2 x 2 tensor is an error naming the shape."""
    grid = jm.Grid((0.0, 0.0), (1.0, 1.0), (8, 8))
    particles = jm.fill(grid, jm.Box((0.125, 0.125), (0.875, 0.875)), ppc=2)
    k = [[1.0, 0.0], [0.0, 0.0]]
    for axis, changes in ((1, False), (0, True)):
        heat = jm.Heat(conductivity=k, initial=lambda x, a=axis: np.sin(4.0 * x[:, a]))
        sim = jm.Simulation(grid=grid, shape=jm.Linear(), material=jm.NoStress(), scheme=jm.FLIP(), terms=(heat,),
                            damping=False)
        state = sim.init(particles)
        change = np.abs(np.asarray(advance(sim, state, 1e-3, 20).fields["temperature"] - state.fields["temperature"]))
        assert (change.max() > 1e-3) if changes else (change.max() < 1e-13), change.max()
    sim, state, _ = rod(8)
    with pytest.raises(jm.InputError, match="2 x 2|shape"):
        sim.with_term(jm.Heat(conductivity=k)).step(state, 1e-4)
