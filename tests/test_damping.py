"""Damping variants of 001 §5 (issue 16, item 7), each against its closed form or its dense
matrix form on a 1D problem, and differentiable.

``jm.Damping(grid=alpha_g, particle=alpha_p, approach=..., schedule=..., region=...)``:

* ``approach="velocity"`` (default): A_damp = alpha_g S v + alpha_p V^n (001 eqs. 31-33, 40;
  000 eq. 2.77), in the particle update.
* ``approach="momentum"``: grid damping proportional to grid momentum, extrapolated as momentum,
  alpha_g p_{g->p}/m_{g->p} with p_{g->p} = sum_i S_ip p_i, m_{g->p} = sum_i S_ip m_i (001 §5.2.2,
  eqs. 67, 72-73, 76).
* ``approach="force"``: alpha_g in the nodal force, f** = f - alpha_g p_i (001 eqs. 58-60, 97-98),
  alpha_p in the particle update (001 eqs. 61-65).
* ``schedule``: alpha(t) = alpha s(t) (001 eq. 30, "may evolve in time"), at the step's start.
* ``region``: alpha(t, x_p) = alpha s(t) w(x_p) (001 §5.3, eq. 107); under ``approach="force"``
  the nodal rate is the mass-weighted extrapolation sum_p S_ip M_p alpha(t, x_p) / m_i.

Closed forms: a rigidly translating force-free body decays as prod_k (1 - alpha(t_k) dt) with
alpha = alpha_g + alpha_p (001 §5.1.2, the total damping constant; eqs. 40, 79) under every
approach; the force approach's final FLIP updates are those of the particle-update approach
(001 eqs. 64-65 vs 56-57).  Tests run in float64 (conftest).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from cases import central_difference, dense_weights

import jaxmpm as jm

ALPHA_G, ALPHA_P = 0.3, 0.2  # 1/time
DT = 0.05
STEPS = 12
GRID = jm.Grid(lower=(0.0,), upper=(16.0,), cells=(16,))  # h = 1
SHAPE = jm.QuadraticBSpline()
MATERIAL = jm.LinearElastic(E=4.0, nu=0.0, density=1.0)  # no stress in a rigid motion or a first step


def bars(x):
    """Two bars, x in (2, 6) and (10, 14), 8 particles each, that share no grid node."""
    return ((x[:, 0] > 2.0) & (x[:, 0] < 6.0)) | ((x[:, 0] > 10.0) & (x[:, 0] < 14.0))


LEFT = np.asarray(jm.fill(GRID, bars, ppc=2).x)[:, 0] < 8.0  # the left bar's particles


class Step(eqx.Module):
    """w(x) = left for x < 8, right for x > 8 (001 §5.3): array leaves, so that every region of these
    tests runs through one compiled program."""

    left: jnp.ndarray
    right: jnp.ndarray

    def __call__(self, x):
        return jnp.where(x[:, 0] > 8.0, self.right, self.left)


EVERYWHERE = (1.0, 1.0)
RIGHT_HALF = (0.0, 1.0)  # damping only in the right bar
UNEVEN = (0.5, 1.5)
# schedules s(t), piecewise linear through three points (one shape: one compiled program)
CONSTANT = ((0.0, 0.5, 1.0), (1.0, 1.0, 1.0))  # s(t) = 1
RAMP = ((0.0, 0.5, 1.0), (1.0, 3.0, 5.0))  # s(t) = 1 + 4 t on [0, 1]
TABLE = ((0.0, 0.1, 0.3), (1.0, 3.0, 0.5))  # rises, falls, then constant past its end


def rigid(x):
    """V = 0.3 on the left bar, -0.2 on the right: each bar translates rigidly."""
    return np.where(x[:, 0] < 8.0, 0.3, -0.2)[:, None]


def wavy(x):
    return (0.3 + 0.1 * np.sin(1.3 * x[:, 0]))[:, None]


@eqx.filter_jit
def rollout(sim, state, dt):
    """STEPS compiled steps; the velocities, positions and dissipated energy after each."""

    def body(s, _):
        s = sim.step(s, dt)
        return s, (s.v, s.x, s.dissipated)

    return jax.lax.scan(body, state, None, length=STEPS)[1]


def model(approach, scheme=None, schedule=CONSTANT, region=EVERYWHERE, velocity=rigid, alpha=(ALPHA_G, ALPHA_P)):
    """A model with the damping variant ``approach`` and its initial state.  Every model of one
    approach and scheme has the same structure (a Schedule and a Step region, both array leaves):
    one compiled ``rollout`` serves all its tests."""
    damping = jm.Damping(*alpha, approach=approach, schedule=schedule, region=Step(*map(jnp.asarray, region)))
    sim = jm.Simulation(grid=GRID, shape=SHAPE, material=MATERIAL, scheme=scheme or jm.FLIP(), damping=damping,
                        update="MUSL")  # the strain from the updated particle velocities (003 §2.1.6)
    return sim, sim.init(jm.fill(GRID, bars, ppc=2, velocity=velocity))


def damped_factor(schedule, steps=STEPS, alpha=ALPHA_G + ALPHA_P):
    """prod_{k<n} (1 - alpha s(t_k) dt), n = 1..steps: the rigid body's velocity factor (001
    eq. 40 with a* = -alpha_g(t) v, and the total constant alpha = alpha_g + alpha_p)."""
    s = np.interp(DT * np.arange(steps), *schedule)  # piecewise linear, constant past the ends
    return np.cumprod(1.0 - alpha * s * DT)


# ------------------------------------------------------------------- closed forms, rigid body

RIGID = [
    pytest.param("velocity", jm.FLIP(), CONSTANT, id="velocity-flip"),
    pytest.param("momentum", jm.FLIP(), CONSTANT, id="momentum-flip"),
    pytest.param("force", jm.FLIP(), CONSTANT, id="force-flip"),
    pytest.param("force", jm.FMPM(order=2), CONSTANT, id="force-fmpm2"),
    pytest.param("momentum", jm.FLIP(beta=0.0), RAMP, id="momentum-pic-ramp"),
    pytest.param("velocity", jm.FLIP(), TABLE, id="velocity-flip-table"),
    pytest.param("force", jm.FLIP(), RAMP, id="force-flip-ramp"),
    pytest.param("force", jm.FMPM(order=2), TABLE, id="force-fmpm2-table"),
]


@pytest.mark.slow
@pytest.mark.parametrize("approach, scheme, schedule", RIGID)
def test_rigid_body_decays_as_closed_form(approach, scheme, schedule):
    """Two bars translating rigidly (V = 0.3 and -0.2), no force: every approach gives
    V^n = V^0 prod_{k<n} (1 - (alpha_g + alpha_p) s(t_k) dt) particle by particle -- grid and
    particle damping act through their sum (001 §5.1.2, eqs. 40, 79; under the force approach
    a** = -alpha_g v, 001 eq. 60), with alpha(t) evaluated at the step's start (001 eq. 30).
    Identity: measured <= 6.5e-16 relative; tolerance 1e-13."""
    sim, state = model(approach, scheme, schedule)
    V = np.asarray(rollout(sim, state, DT)[0])[..., 0]
    expected = damped_factor(schedule)[:, None] * np.asarray(state.v)[:, 0]
    assert np.abs(V - expected).max() <= 1e-13 * 0.3, (V - expected)


@pytest.mark.parametrize("approach", ["velocity", "momentum", "force"])
def test_region_damps_only_where_nonzero(approach):
    """alpha(x) (001 §5.3) with w = 0 left of x = 8 and 1 right of it, on the two bars (no node in
    common): the left bar keeps V = 0.3 exactly, the right one decays as (1 - (alpha_g + alpha_p)
    dt)^n (001 eq. 107; under the force approach the nodal rate sum_p S_ip M_p w_p / m_i is 1 on
    the right bar's nodes and 0 on the left's).  Identities; tolerance 1e-13."""
    sim, state = model(approach, region=RIGHT_HALF)
    V = np.asarray(rollout(sim, state, DT)[0])[..., 0]
    assert np.abs(V[:, LEFT] - 0.3).max() <= 1e-13 * 0.3
    expected = -0.2 * damped_factor(CONSTANT)
    assert np.abs(V[:, ~LEFT] - expected[:, None]).max() <= 1e-13 * 0.2


# ---------------------------------------------------------------------- dense forms, one step


def dense_step(sim, state, approach, scheme):
    """One step of an unstressed body written with the dense S (N x n), M, m = S^T M 1, S+ =
    m^-1 S^T M (000 eq. 1.10) and the rates alpha(t, x_p) = alpha s(t) w(x_p) (001 eq. 107)."""
    d = sim.damping
    x = np.asarray(state.x)
    V = np.asarray(state.v)
    M = np.asarray(state.mass)
    S, _ = dense_weights(SHAPE.stencil(GRID, state.x), GRID.num_nodes)
    m = S.T @ M
    on = m > 0
    S, m = S[:, on], m[on]
    v = (S.T @ (M[:, None] * V)) / m[:, None]  # v = S+ V
    w = np.interp(float(state.time), *map(np.asarray, (d.schedule.times, d.schedule.factors))) * \
        np.where(x[:, :1] > 8.0, float(d.region.right), float(d.region.left))  # s(t^n) w(x_p), (N, 1)
    ag, ap = float(d.grid) * w, float(d.particle) * w
    if approach == "velocity":  # 001 eqs. (31), (33), (107)
        a = -(ag * (S @ v) + ap * V)
    elif approach == "momentum":  # 001 eqs. (72)-(73), (76), (79)
        a = -(ag * (S @ (m[:, None] * v)) / (S @ m)[:, None] + ap * V)
    if approach in ("velocity", "momentum"):
        V1 = V + a * DT
        return V1, x + (S @ v + 0.5 * (V1 - V)) * DT  # FLIP, 000 eq. (3.29)
    alpha_i = float(d.grid) * (S.T @ (M[:, None] * w)) / m[:, None]  # nodal rate (001 §5.3)
    a_i = -alpha_i * v  # 001 eq. (60): a** = a - alpha_g v_i (a = 0: no stress yet)
    v_tilde = v + a_i * DT  # 001 eq. (59)
    if isinstance(scheme, jm.FMPM):  # order 2: v+ = 2 v~ - S+S v~ (003 eq. 1.23), V = S v+ - alpha_p V dt
        S_plus = (S.T * M) / m[:, None]
        V1 = S @ (2.0 * v_tilde - S_plus @ (S @ v_tilde)) - ap * V * DT
        return V1, x + 0.5 * (V1 + V) * DT  # 003 eq. (2.17)
    V1 = V + S @ a_i * DT - ap * V * DT  # 001 eqs. (61), (52)
    return V1, x + (S @ v + 0.5 * (V1 - V)) * DT


DENSE = [
    pytest.param("velocity", jm.FLIP(), id="velocity"),
    pytest.param("momentum", jm.FLIP(), id="momentum"),
    pytest.param("force", jm.FLIP(), id="force"),
    pytest.param("force", jm.FMPM(order=2), id="force-fmpm2"),
]


@pytest.mark.parametrize("approach, scheme", DENSE)
def test_one_step_matches_dense_form(approach, scheme):
    """One step from t = 0.2 of the bars with a non-uniform velocity (S v != V, p_{g->p}/m_{g->p}
    != S v at the bars' ends), alpha(t) = alpha (1 + 4t) and w = 0.5 / 1.5 on the left / right bar,
    against the dense-matrix form of each variant (``dense_step``; F = I at the start, so no
    stress acts).  Measured <= 1.7e-16 absolute; tolerance 1e-13 relative."""
    sim, state = model(approach, scheme, RAMP, UNEVEN, velocity=wavy)
    state = eqx.tree_at(lambda s: s.time, state, state.time + 0.2)
    V, X, _ = (np.asarray(a)[0] for a in rollout(sim, state, DT))
    V1, X1 = dense_step(sim, state, approach, scheme)
    scale = np.abs(np.asarray(state.v)).max()
    assert np.abs(V - V1).max() <= 1e-13 * scale
    assert np.abs(X - X1).max() <= 1e-13 * scale * DT


def test_momentum_approach_differs_from_velocity_at_bar_ends():
    """p_{g->p}/m_{g->p} (001 eq. 76) and S v (001 eq. 34) coincide where the nodal masses of a
    particle's stencil are equal and differ where they are not (the bars' ends, where the end
    nodes carry less mass): the two approaches are distinct methods.  Measured max |V_mom -
    V_vel| after one step = 1.6e-4 with V ~ 0.3 (0 would mean the option does nothing)."""
    out = {}
    for approach in ("velocity", "momentum"):
        sim, state = model(approach, velocity=wavy, alpha=(ALPHA_G, 0.0))
        out[approach] = np.asarray(rollout(sim, state, DT)[0][0])
    assert np.abs(out["momentum"] - out["velocity"]).max() > 1e-6


def test_force_approach_equals_particle_update_for_flip():
    """001 eqs. (64)-(65): applying alpha_g to the nodal force (001 eq. 58) leaves FLIP's final
    updates those of the particle-update approach (001 eqs. 56-57) -- V, X and the dissipated
    energy (000 eq. 2.43, to which the force approach adds the grid damping's work back) agree
    over 12 steps of the elastic bars with alpha(t, x).  MUSL: its strain comes from the updated
    particle velocities, the same in both; under USL the strain uses the grid's v~, which the
    force approach damps (measured max |dV| = 6.1e-4 of 0.39 after 12 steps).  Measured
    <= 2.3e-16 relative; tolerance 1e-12."""
    runs = {}
    for approach in ("velocity", "force"):
        sim, state = model(approach, schedule=RAMP, region=UNEVEN, velocity=wavy)
        runs[approach] = [np.asarray(a) for a in rollout(sim, state, DT)]
    for a, b in zip(runs["velocity"], runs["force"]):
        assert np.abs(a - b).max() <= 1e-12 * np.abs(a).max(), (np.abs(a - b).max(), np.abs(a).max())
    assert runs["force"][2][-1] > 0.0  # damping dissipated energy


# ------------------------------------------------------------------------------------ gradients


def kinetic(sim, state, params):
    """KE after STEPS steps as a function of the damping's float leaves ``params`` (alpha_g,
    alpha_p, the schedule's points, the region's values)."""
    static = eqx.partition(sim.damping, eqx.is_inexact_array)[1]
    model = eqx.tree_at(lambda m: m.damping, sim, eqx.combine(params, static))
    final = jax.lax.scan(lambda s, _: (model.step(s, DT), None), state, None, length=STEPS)[0]
    return jm.kinetic_energy(final)


@eqx.filter_jit
def kinetic_and_derivative(sim, state, params, tangent):
    """KE and its derivative along ``tangent`` (forward mode: one compiled program also gives
    the values for the finite differences)."""
    return jax.jvp(lambda p: kinetic(sim, state, p), (params,), (tangent,))


kinetic_and_gradient = eqx.filter_jit(jax.value_and_grad(kinetic, argnums=2))  # reverse mode

DIRECTIONS = {  # the leaves whose derivative is checked: (path in the damping, index or None)
    "alpha_g": (lambda d: d.grid, None), "alpha_p": (lambda d: d.particle, None),
    "s(0)": (lambda d: d.schedule.factors, 0), "s(0.1)": (lambda d: d.schedule.factors, 1),
    "w_left": (lambda d: d.region.left, None), "w_right": (lambda d: d.region.right, None),
}


def unit(params, name):
    """A tangent of ``params`` that is 1 at the leaf (entry) ``name`` and 0 elsewhere."""
    zero = jax.tree_util.tree_map(jnp.zeros_like, params)
    where, j = DIRECTIONS[name]
    leaf = where(zero)
    return eqx.tree_at(where, zero, jnp.ones_like(leaf) if j is None else leaf.at[j].set(1.0))


def shifted(params, e, h):
    return jax.tree_util.tree_map(lambda p, u: p + h * u, params, e)


@pytest.mark.slow
@pytest.mark.parametrize("approach", ["velocity", "momentum", "force"])
def test_derivatives_match_finite_differences(approach):
    """d(KE)/d theta after 12 steps of the elastic bars with alpha(t, x) = alpha s(t) w(x_p)
    (001 eq. 107), for theta = alpha_g, alpha_p, two of the schedule's factors (the ones the
    12 steps reach) and the region's two values, against the five-point central difference
    (step 1e-4) in float64.  Forward mode (jax.jvp) for the velocity and momentum approaches,
    reverse mode (jax.value_and_grad, what jm.calibrate uses) for the force approach -- the
    variant with its own grid action, P2G column and dissipation correction; reverse mode through
    the default damping: tests/test_gradients.py.  Measured agreement <= 6e-11 relative;
    tolerance 1e-7."""
    sim, state = model(approach, schedule=TABLE, region=UNEVEN, velocity=wavy)
    params = eqx.partition(sim.damping, eqx.is_inexact_array)[0]
    zero = jax.tree_util.tree_map(jnp.zeros_like, params)
    if approach == "force":
        value = lambda p: kinetic_and_gradient(sim, state, p)[0]  # noqa: E731
        grad = kinetic_and_gradient(sim, state, params)[1]
    else:
        value = lambda p: kinetic_and_derivative(sim, state, p, zero)[0]  # noqa: E731
    for name, (where, j) in DIRECTIONS.items():
        e = unit(params, name)
        if approach == "force":
            derivative = where(grad) if j is None else where(grad)[j]
        else:
            derivative = kinetic_and_derivative(sim, state, params, e)[1]
        fd = central_difference(lambda h: value(shifted(params, e, h)), 0.0, 1e-4, order=4)
        assert abs(derivative) > 0 and abs(derivative - fd) <= 1e-7 * abs(fd), (name, derivative, fd)


def test_callable_schedule_and_region_give_the_same_rates():
    """A plain callable s(t) and w(x) give the rates alpha s(t^n) w(x_p) (001 eqs. 30, 107) that
    the Schedule / Step modules of the tests above give (``Damping.at``, evaluated eagerly).
    Identity; tolerance 1e-15 relative."""
    _, state = model("velocity", velocity=wavy)
    state = eqx.tree_at(lambda s: s.time, state, state.time + 0.2)
    plain = jm.Damping(ALPHA_G, ALPHA_P, schedule=lambda t: 1.0 + 4.0 * t,
                       region=lambda x: jnp.where(x[:, 0] > 8.0, 1.5, 0.5)).at(state, None, None)
    module = model("velocity", schedule=RAMP, region=UNEVEN)[0].damping.at(state, None, None)
    w = np.where(LEFT, 0.5, 1.5)[:, None] * 1.8  # s(0.2) = 1.8
    for a, b, alpha in ((plain.grid, module.grid, ALPHA_G), (plain.particle, module.particle, ALPHA_P)):
        assert np.abs(np.asarray(a) - alpha * w).max() <= 1e-15 and np.abs(np.asarray(b) - alpha * w).max() <= 1e-15


# ------------------------------------------------------------------------------------ inputs


@pytest.mark.parametrize(
    "kwargs, words",
    [
        (dict(approach="grid"), "approach"),
        (dict(schedule=((0.0, 0.0), (1.0, 1.0))), "increasing"),
        (dict(schedule=((0.0, 1.0), (1.0,))), "one factor per time"),
        (dict(schedule=((0.0, 1.0), (1.0, -1.0))), ">= 0"),
        (dict(schedule=3.0), "callable"),
        (dict(region="x>8"), "region"),
    ],
)
def test_bad_damping_options_raise(kwargs, words):
    with pytest.raises(jm.InputError, match=words):
        jm.Damping(0.1, 0.1, **kwargs)
