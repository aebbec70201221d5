"""The ``rings`` and ``mpm88`` scenes, and the one-sided ``jm.Wall`` (``spin`` is in test_affine.py).

* rings (h = 0.5): every scheme conserves linear momentum (zero: no boundaries, no gravity) and
  creates no energy through the collision.
* mpm88 (1024 particles): linear momentum follows P0 + M g t exactly until the fluid reaches a
  wall; no particle passes the plane 1.5 cells inside a wall (a particle beyond it only sees
  clamped nodes); float32 matches float64; F stays J^(1/2) I (the fluid reset).
* materials: VolumetricFluid tau = E (J - 1) I and its reset F -> J^(1/D) I keeps J and tau;
  NoStress has tau = 0, W = 0, c = 0.
* Wall: the mpm88 rule, v_n zeroed only where it points into the wall, acting on v + a dt.
"""

import jax.numpy as jnp
import numpy as np
import pytest
from cases import UNIT_SQUARE, central_difference

import jaxmpm as jm
from jaxmpm.physics.conditions import build_constraint

# ----------------------------------------------------------------------------------------- rings
RING_SCHEMES = {"FLIP": jm.FLIP(), "PIC": jm.PIC(), "XPIC(2)": jm.XPIC(2), "FMPM(2)": jm.FMPM(2),
                "APIC": jm.APIC(), "TPIC": jm.TPIC()}


@pytest.mark.slow
@pytest.mark.parametrize("name", list(RING_SCHEMES))
def test_rings_collide_stably_with_every_scheme(name):
    """h = 0.5, through the collision (contact at t ~ 0.033) to t = 0.15, CFL 0.4 for every scheme
    (FMPM(2) at the scene's CFL 0.8 inverts a particle: a full mass matrix has a smaller critical
    time step than the lumped one).  Exact: sum_p M_p V_p = 0; total energy never above E0."""
    setup = jm.scene("rings", scheme=RING_SCHEMES[name], spacing=0.5, t_end=0.15, cfl=0.4, frames=10)
    _, hist = setup.run(save_particles=False)  # raises InstabilityError if it goes unstable
    E = np.asarray(hist.total_energy)
    scale = float(jnp.sum(setup.state.mass) * 30.0)
    assert np.max(np.abs(np.asarray(hist.momentum))) < 1e-12 * scale
    assert np.all(np.isfinite(E)) and E.max() < 1.01 * E[0]
    print(f"\nrings h=0.5 {name}: E(0.15)/E0 = {E[-1] / E[0]:.4f}, max E/E0 = {E.max() / E[0]:.5f}")


# ----------------------------------------------------------------------------------------- mpm88
MPM88_N = 1024


@pytest.fixture(scope="module")
def mpm88_runs():
    runs = {}
    for dtype in ("f32", "f64"):
        setup = jm.scene("mpm88", n_particles=MPM88_N, t_end=0.2, frames=2, dtype=dtype)
        assert setup.steps == 1000
        final, hist = setup.run(save_particles=True)
        runs[dtype] = setup, hist, final
    return runs


@pytest.mark.slow
@pytest.mark.parametrize("dtype, rtol", [("f64", 1e-12), ("f32", 1e-5)])
def test_mpm88_momentum_follows_gravity_before_the_walls(mpm88_runs, dtype, rtol):
    """t = 0.1, before any particle reaches a wall: P = P0 + M g t exactly (APIC conserves linear
    momentum, 002 props. 5.2-5.3; internal forces sum to zero)."""
    setup, hist, _ = mpm88_runs[dtype]
    t = float(hist.time[1])
    M = float(jnp.sum(setup.state.mass.astype(jnp.float64)))
    expected = np.array([0.0, -M * (1.0 + 9.8 * t)])
    np.testing.assert_allclose(np.asarray(hist.momentum[1], np.float64), expected, rtol=0, atol=rtol * M * 2.0)
    assert float(jnp.min(hist.x[1][:, 1])) > 3.0 / 128  # no wall touched yet


@pytest.mark.slow
@pytest.mark.parametrize("dtype", ["f32", "f64"])
def test_mpm88_walls_hold_the_fluid(mpm88_runs, dtype):
    """t = 0.2 after the fluid hit the floor: no particle beyond 1.5 cells inside a wall (its whole
    stencil would be clamped nodes, bound = 3), allowing one step of travel (0.1 cell)."""
    setup, hist, _ = mpm88_runs[dtype]
    dx = 1.0 / 128
    x = np.asarray(hist.x[-1], np.float64)
    assert x[:, 1].min() < 4.5 * dx  # the fluid did reach the floor region
    assert x.min() > 1.4 * dx and x.max() < 1.0 - 1.4 * dx


@pytest.mark.slow
@pytest.mark.parametrize("dtype", ["f32", "f64"])
def test_mpm88_deformation_stays_isotropic(mpm88_runs, dtype):
    """VolumetricFluid.keep_deformation: after 1000 steps F = J^(1/2) I, 0 < J (mpm88 keeps J only)."""
    F = np.asarray(mpm88_runs[dtype][2].F)
    assert np.all(F[:, 0, 1] == 0) and np.all(F[:, 1, 0] == 0) and np.all(F[:, 0, 0] == F[:, 1, 1])
    assert np.all(F[:, 0, 0] > 0) and np.any(F[:, 0, 0] != 1)


@pytest.mark.slow
def test_mpm88_float32_matches_float64(mpm88_runs):
    """Kinetic energy at t = 0.1 and 0.2 agrees to 1e-4 between float32 and float64."""
    k32 = np.asarray(mpm88_runs["f32"][1].kinetic, np.float64)
    k64 = np.asarray(mpm88_runs["f64"][1].kinetic)
    np.testing.assert_allclose(k32, k64, rtol=1e-4)


# ------------------------------------------------------------------------------------------ Wall
def test_wall_is_one_sided_and_acts_on_the_updated_velocity():
    """mpm88's rule on a 4x4-cell grid: nodes i < 2 zero v_x < 0, nodes i > 4 - 2 zero v_x > 0;
    v_tilde = clamp(v + a dt), v unchanged, a = (v_tilde - v)/dt; two-sided conditions unchanged."""
    grid = jm.Grid((0.0, 0.0), (1.0, 1.0), (4, 4))
    c = build_constraint(grid, (jm.Wall("x-", layers=2), jm.Wall("x+", layers=2)), jnp.float64)
    i = grid.node_index_grid()[:, 0]
    rng = np.random.default_rng(0)
    v = jnp.asarray(rng.normal(size=(grid.num_nodes, 2)))
    a = jnp.asarray(rng.normal(size=(grid.num_nodes, 2)))
    dt = 0.5
    v_out, a_out, v_tilde = c.contact(v, a, jnp.asarray(dt))
    free = np.asarray(v + a * dt)
    clamp = ((i < 2) & (free[:, 0] < 0)) | ((i > 2) & (free[:, 0] > 0))
    expected = free.copy()
    expected[clamp, 0] = 0.0
    np.testing.assert_array_equal(np.asarray(v_tilde), expected)
    np.testing.assert_array_equal(np.asarray(v_out), np.asarray(v))
    np.testing.assert_allclose(np.asarray(v_out + a_out * dt), expected, atol=1e-15)
    np.testing.assert_array_equal(np.asarray(c.zero(a)), np.asarray(a))  # walls leave accelerations free
    assert clamp.sum() > 0 and (~clamp & (i < 2)).sum() > 0
    # a two-sided condition wins over a wall, and without walls the constraint is the plain one
    both = build_constraint(grid, (jm.Wall("x-", layers=2), jm.Fixed("x-")), jnp.float64)
    assert np.all(np.asarray(both.apply(v))[i == 0] == 0.0)
    plain = build_constraint(grid, (jm.Fixed("x-"),), jnp.float64)
    assert plain.wall is None
    np.testing.assert_array_equal(np.asarray(plain.apply(v)), np.where(np.asarray(plain.mask), 0.0, np.asarray(v)))


# ------------------------------------------------------------------------------------- materials
@pytest.mark.parametrize("dim", [2, 3])
def test_volumetric_fluid_stress_and_reset(dim):
    """tau = E (J - 1) I, W = E (J - 1 - ln J) with tau = J dW/dJ I; the reset F -> J^(1/D) I keeps
    det F and tau; an inverted F (J <= 0) is left as it is for the instability check."""
    rng = np.random.default_rng(dim)
    inverted = np.diag([1.0] * (dim - 1) + [-0.5])[None]  # J < 0
    F = jnp.asarray(np.concatenate([np.eye(dim) + 0.3 * rng.normal(size=(50, dim, dim)), inverted]))
    J = np.linalg.det(np.asarray(F))
    fluid = jm.VolumetricFluid(E=400.0, density=1.0)
    tau = np.asarray(fluid.kirchhoff_stress(F))
    np.testing.assert_allclose(tau, (400.0 * (J - 1.0))[:, None, None] * np.eye(dim), atol=1e-12)
    # J dW/dJ = dW(J (1 + s))/ds at s = 0, with F scaled by (1 + s)^(1/D)
    dW = central_difference(lambda s: np.asarray(fluid.energy_density((1 + s) ** (1 / dim) * F)), 0.0, 1e-6)
    positive = J > 0
    np.testing.assert_allclose(dW[positive], tau[positive, 0, 0], rtol=1e-6, atol=1e-6)
    kept = np.asarray(fluid.keep_deformation(F))
    np.testing.assert_allclose(np.linalg.det(kept)[positive], J[positive], rtol=1e-12)
    np.testing.assert_allclose(kept[positive], (J[positive] ** (1 / dim))[:, None, None] * np.eye(dim), rtol=1e-13)
    np.testing.assert_allclose(np.asarray(fluid.kirchhoff_stress(jnp.asarray(kept))), tau, atol=1e-9)
    assert (~positive).sum() > 0
    np.testing.assert_array_equal(kept[~positive], np.asarray(F)[~positive])
    assert float(fluid.wave_speed(dim)) == 20.0


def test_no_stress_material():
    """NoStress: tau = 0, W = 0, F kept as it is, wave speed 0 (dt limited by the particle speed alone)."""
    F = jnp.asarray(np.eye(2) + 0.2 * np.random.default_rng(0).normal(size=(5, 2, 2)))
    mat = jm.NoStress(density=3.0)
    assert not np.any(np.asarray(mat.kirchhoff_stress(F))) and not np.any(np.asarray(mat.energy_density(F)))
    assert float(mat.wave_speed(2)) == 0.0
    np.testing.assert_array_equal(np.asarray(mat.keep_deformation(F)), np.asarray(F))  # F carried as it is
    v = jnp.asarray([[0.5, 0.0], [0.0, -2.0]])
    assert float(jm.stable_dt(UNIT_SQUARE, mat, v, 0.5)) == pytest.approx(0.5 * 0.125 / 2.0)
