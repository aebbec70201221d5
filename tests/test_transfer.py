"""Transfer operators S, S+, S^T and the force divergence (jaxmpm.transfer.operators), and conservation of
linear momentum by one full time step of every scheme.

* P2G conserves mass and momentum: sum_i m_i = sum_p M_p, sum_i p_i = sum_p M_p V_p (003 eq. 2.1)
* S+ of a constant particle field is that constant on every node with mass (000 eq. 1.10)
* gather of a linear nodal field reproduces it at interior particles
* the internal force f_i = -sum_p V0_p tau_p . G_pi (001 eq. 20) sums to zero (sum_i G_pi = 0),
  does the virtual work -sum_p V0_p tau_p : A on u_i = A x_i, and exerts no torque
* one FLIP / PIC / XPIC(3) / FMPM(3) step without external forces or boundaries conserves
  sum_p M_p V_p (000 ch. 5, 003 §2.3)
"""

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest
from cases import FOUR_SHAPES, GRIDS, UNIT_SQUARE, dense_weights, random_particles

import jaxmpm as jm

N_PARTICLES = 64

CASES = [pytest.param(name, dim, id=f"{name}-{dim}d") for name in FOUR_SHAPES for dim in GRIDS]
SEEDS = (0, 1, 2)


def make_state(x, v, mass):
    n, d = x.shape
    return jm.State(
        x=jnp.asarray(x), v=jnp.asarray(v), F=jnp.broadcast_to(jnp.eye(d), (n, d, d)), mass=jnp.asarray(mass),
        volume0=jnp.asarray(mass), time=jnp.zeros(()), step=jnp.zeros((), jnp.int32), dissipated=jnp.zeros(()),
    )


def elastic_sim(grid, shape):
    return jm.Simulation(grid=grid, shape=shape, material=jm.LinearElastic(E=100.0, nu=0.3, density=1.0),
                         scheme=jm.FLIP())


@eqx.filter_jit
def _transfer_outputs(sim, state, u, weighted_stress):
    fields = jm.p2g(sim, state)  # the P2G of the time step
    tr = fields.transfer
    return dict(
        stencil=tr.stencil,
        nodal_mass=tr.nodal_mass,
        momentum=fields.momentum,
        s_plus=tr.s_plus(state.v),
        s_plus_s=tr.s_plus_s(u),
        gather=tr.gather(u),
        velocity_gradient=tr.velocity_gradient(u),
        force=tr.divergence(weighted_stress),
    )


def transfer_outputs(shape, grid, x, mass, v=None, u=None, weighted_stress=None):
    """Every transfer of one particle configuration, from one compiled function per (shape, dim)."""
    n, d = x.shape
    v = np.zeros((n, d)) if v is None else v
    u = np.zeros((grid.num_nodes, d)) if u is None else u
    weighted_stress = np.zeros((n, d, d)) if weighted_stress is None else weighted_stress
    out = _transfer_outputs(elastic_sim(grid, shape), make_state(x, v, mass), jnp.asarray(u),
                            jnp.asarray(weighted_stress))
    return {k: (val if k == "stencil" else np.asarray(val)) for k, val in out.items()}


@pytest.mark.slow
@pytest.mark.parametrize("name, dim", CASES)
def test_p2g_conserves_mass_and_momentum(name, dim):
    """sum_i m_i = sum_p M_p and sum_i p_i = sum_p M_p V_p to round-off (partition of unity), and
    m = S^T M, p = S^T M V with the dense matrix S of the stencil (003 eq. 2.1)."""
    shape, grid = FOUR_SHAPES[name], GRIDS[dim]
    for seed in SEEDS:
        x, mass, v = random_particles(shape, grid, np.random.default_rng(seed), N_PARTICLES)
        out = transfer_outputs(shape, grid, x, mass, v=v)
        m_i, p_i = out["nodal_mass"], out["momentum"]
        assert abs(m_i.sum() - mass.sum()) <= 1e-13 * mass.sum()
        scale = np.sum(mass[:, None] * np.abs(v))
        np.testing.assert_allclose(p_i.sum(axis=0), (mass[:, None] * v).sum(axis=0), rtol=0, atol=1e-13 * scale)
        S, _ = dense_weights(out["stencil"], grid.num_nodes)
        np.testing.assert_allclose(m_i, S.T @ mass, rtol=1e-13, atol=1e-14)
        np.testing.assert_allclose(p_i, S.T @ (mass[:, None] * v), rtol=0, atol=1e-13 * scale)


@pytest.mark.parametrize("name, dim", CASES)
def test_s_plus_of_constant_is_constant_on_nodes_with_mass(name, dim):
    """(S+ U)_i = sum_p S_pi M_p c / m_i = c where m_i > 0, and 0 where m_i = 0 (000 eq. 1.10);
    S+S of a constant nodal field is the same constant (000 eq. 3.19)."""
    shape, grid = FOUR_SHAPES[name], GRIDS[dim]
    rng = np.random.default_rng(11)
    x, mass, _ = random_particles(shape, grid, rng, N_PARTICLES, extent=0.4)  # the upper nodes stay empty
    c = rng.normal(size=dim)
    const_nodal = np.broadcast_to(c, (grid.num_nodes, dim))
    out = transfer_outputs(shape, grid, x, mass, v=np.broadcast_to(c, x.shape), u=const_nodal)
    has_mass = out["nodal_mass"] > 0
    assert 0 < has_mass.sum() < grid.num_nodes
    expected = np.broadcast_to(c, (has_mass.sum(), dim))
    np.testing.assert_allclose(out["s_plus"][has_mass], expected, rtol=1e-14, atol=1e-14)
    assert np.all(out["s_plus"][~has_mass] == 0.0)
    np.testing.assert_allclose(out["s_plus_s"][has_mass], expected, rtol=1e-14, atol=1e-14)


@pytest.mark.parametrize("name, dim", CASES)
def test_gather_reproduces_linear_nodal_field(name, dim):
    """(S u)_p = A X_p + b and grad v_p = sum_i u_i (x) G_pi = A for u_i = A x_i + b, at interior
    particles (linear reproduction of the shape functions)."""
    shape, grid = FOUR_SHAPES[name], GRIDS[dim]
    rng = np.random.default_rng(3)
    x, mass, _ = random_particles(shape, grid, rng, N_PARTICLES)
    A, b = rng.normal(size=(dim, dim)), rng.normal(size=dim)
    u = grid.node_coordinates() @ A.T + b
    out = transfer_outputs(shape, grid, x, mass, u=u)
    np.testing.assert_allclose(out["gather"], x @ A.T + b, rtol=0, atol=1e-12)
    np.testing.assert_allclose(out["velocity_gradient"], np.broadcast_to(A, (N_PARTICLES, dim, dim)),
                               rtol=0, atol=1e-11)


@pytest.mark.parametrize("name, dim", CASES)
def test_divergence_sums_to_zero_and_does_virtual_work(name, dim):
    """f_i = -sum_p V0_p tau_p . G_pi (001 eq. 20): sum_i f_i = 0 because sum_i G_pi = 0, for a
    constant and for a random symmetric stress; sum_i f_i . (A x_i) = -sum_p V0_p tau_p : A (virtual
    work with the exact gradient A of a linear field); with A antisymmetric that is zero torque."""
    shape, grid = FOUR_SHAPES[name], GRIDS[dim]
    rng = np.random.default_rng(5)
    x, volume, _ = random_particles(shape, grid, rng, N_PARTICLES)
    sym = rng.normal(size=(N_PARTICLES, dim, dim))
    tau_random = sym + np.swapaxes(sym, 1, 2)
    tau_constant = np.broadcast_to(tau_random[0], tau_random.shape)
    nodes = grid.node_coordinates()
    for tau in (tau_constant, tau_random):
        weighted = volume[:, None, None] * tau
        f = transfer_outputs(shape, grid, x, volume, weighted_stress=weighted)["force"]
        scale = np.abs(f).sum()
        assert scale > 1.0  # the test is not vacuous
        np.testing.assert_allclose(f.sum(axis=0), 0.0, rtol=0, atol=1e-14 * scale)
        A = rng.normal(size=(dim, dim))
        work = np.sum(f * (nodes @ A.T))
        expected = -np.sum(weighted * A)
        assert abs(work - expected) <= 1e-12 * np.abs(weighted).sum() * np.abs(A).sum()
        W = A - A.T  # rigid rotation: internal forces of a symmetric stress exert no torque
        torque = np.sum(f * (nodes @ W.T))
        assert abs(torque) <= 1e-12 * np.abs(weighted).sum() * np.abs(W).sum()


# ----------------------------------------------------------------- one full step
SCHEMES = {
    "FLIP": jm.FLIP(),
    "PIC": jm.PIC(),
    "XPIC3": jm.XPIC(order=3),
    "FMPM3": jm.FMPM(order=3),
}


@eqx.filter_jit
def one_step(sim, state, dt):
    return sim.step(state, dt)


def perturbed_elastic_state(sim, rng, n=40):
    """Random particles in [0.3, 0.7]^2 with random velocities and F = I + 0.05 * noise."""
    x = 0.3 + 0.4 * rng.random((n, 2))
    v = rng.normal(size=(n, 2))
    particles = jm.Particles(x=jnp.asarray(x), v=jnp.asarray(v), volume=jnp.full(n, 1.0 / 256), ppc=1)
    state = sim.init(particles)
    F = np.eye(2) + 0.05 * rng.normal(size=(n, 2, 2))
    return eqx.tree_at(lambda s: s.F, state, jnp.asarray(F))


@pytest.mark.slow
@pytest.mark.parametrize("scheme_name", list(SCHEMES))
def test_step_conserves_linear_momentum(scheme_name):
    """Without gravity or boundaries sum_i f_i = 0 and S+S keeps sum_i m_i u_i, so every scheme
    keeps sum_p M_p V_p (000 ch. 5; 003 §2.3) to round-off while the stresses change V."""
    sim = jm.Simulation(grid=UNIT_SQUARE, shape=jm.QuadraticBSpline(), scheme=SCHEMES[scheme_name],
                        material=jm.LinearElastic(E=1000.0, nu=0.3, density=1.0))
    state = perturbed_elastic_state(sim, np.random.default_rng(13))
    dt = jnp.asarray(0.2 * float(sim.stable_dt(state)))
    new = one_step(sim, state, dt)
    p0 = np.asarray(jm.linear_momentum(state))
    p1 = np.asarray(jm.linear_momentum(new))
    mass, v0, v1 = (np.asarray(a) for a in (state.mass, state.v, new.v))
    scale = np.sum(mass[:, None] * np.abs(v0))
    change = np.sum(mass[:, None] * np.abs(v1 - v0))
    assert change > 1e-2 * scale  # forces and the transfer really change the velocities
    np.testing.assert_allclose(p1, p0, rtol=0, atol=1e-12 * scale)
    assert int(new.step) == 1 and np.isclose(float(new.time), float(dt))
