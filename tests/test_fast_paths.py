"""The step's fast paths give the same numbers as the plain definitions (float64).

* TensorStencil: S_pi, G_pi, x_i - X_p formed from per-axis factors equal the explicit
  tensor products of the 1D kernels, and its flat node numbers stay on the grid for a particle
  that has left it (the gathers/scatters promise in-bounds indices).
* Folded P2G (jm.folds_force): with APIC/TPIC and no damping in the model (``damping=False``)
  P2G scatters p + f dt in place of p and f; the run equals the run with zero jm.Damping()
  (unfolded) to round-off, with one-sided walls (mpm88) and with two-sided conditions and
  stress (rings), USL and MUSL.
* ``damping=False`` keeps alpha_g/alpha_p reachable: set_params puts jm.Damping back.
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from cases import FOUR_SHAPES, GRIDS, at_cells, interior_cells

import jaxmpm as jm


@pytest.mark.slow
@pytest.mark.parametrize("name", list(FOUR_SHAPES))
@pytest.mark.parametrize("dim", [1, 2, 3])
def test_tensor_stencil_is_the_product_of_1d_kernels(name, dim):
    """weight = prod_a N(r_a), gradient[a] = N'(r_a)/h_a prod_{b!=a} N(r_b), offset = x_i - X_p,
    slot k = (k_0, ..., k_{D-1}) in C order, node i = sum_a (first_a + k_a) stride_a."""
    shape, grid = FOUR_SHAPES[name], GRIDS[dim]
    xi = interior_cells(shape, grid, np.random.default_rng(dim), 7)
    x = at_cells(grid, xi)
    st = shape.stencil(grid, jnp.asarray(x))
    k1 = shape.nodes_per_axis
    first = np.array([np.asarray(shape._base(jnp.asarray(xi[:, a]))) for a in range(dim)])  # (D, N)
    h = np.array(grid.spacing)
    for slot, ks in enumerate(np.ndindex(*(k1,) * dim)):
        nodes = first + np.array(ks)[:, None]  # (D, N) node numbers per axis
        w1, dw1 = (np.asarray(v) for v in shape._kernel(jnp.asarray(xi.T - nodes)))
        np.testing.assert_array_equal(np.asarray(st.index)[slot], np.sum(nodes * np.array(grid.strides)[:, None], 0))
        np.testing.assert_allclose(np.asarray(st.weight)[slot], np.prod(w1, 0), rtol=0, atol=1e-15)
        for a in range(dim):
            g = dw1[a] / h[a] * np.prod(np.delete(w1, a, 0), 0)
            np.testing.assert_allclose(np.asarray(st.gradient)[a, slot], g, rtol=0, atol=1e-14 / h[a])
            off = np.array(grid.lower)[a] + nodes[a] * h[a] - x[:, a]
            np.testing.assert_allclose(np.asarray(st.offset)[a, slot], off, rtol=0, atol=1e-14)


@pytest.mark.parametrize("name", list(FOUR_SHAPES))
def test_stencil_indices_stay_on_the_grid_off_it(name):
    """A particle outside the grid (or NaN) still gets node numbers in [0, n): the transfers use
    promise-in-bounds gathers and scatters, and a run reports such a particle as a failure."""
    shape, grid = FOUR_SHAPES[name], GRIDS[2]
    x = jnp.asarray([[-5.0, 1.0], [10.0, 40.0], [np.nan, 1.0], [0.5, np.inf]])
    index = np.asarray(shape.stencil(grid, x).index)
    assert index.min() >= 0 and index.max() < grid.num_nodes


def _run(setup, steps):
    sim, state = setup.sim, setup.state
    dt = jnp.asarray(setup.dt, state.x.dtype)
    return jax.jit(lambda s: jax.lax.fori_loop(0, steps, lambda _, q: sim.step(q, dt), s))(state)


FOLD_CASES = [
    pytest.param("mpm88", dict(n_particles=512, n_grid=32, dt=1e-3), "USL", id="mpm88-walls-USL"),
    pytest.param("mpm88", dict(n_particles=512, n_grid=32, dt=1e-3), "MUSL", id="mpm88-walls-MUSL"),
    pytest.param("rings", dict(spacing=0.5, cfl=0.4), "USL", id="rings-neohookean-USL"),
]


@pytest.mark.slow
@pytest.mark.parametrize("scheme", [jm.APIC(), jm.TPIC()], ids=["apic", "tpic"])
@pytest.mark.parametrize("scene, kwargs, update", FOLD_CASES)
def test_folded_p2g_equals_separate_momentum_and_force(scene, kwargs, update, scheme):
    """v_tilde = (p + f dt)/m with the conditions imposed either way: the folded run (no damping
    in the model) and the unfolded run (zero jm.Damping) agree to round-off over 150 steps (the
    mpm88 block has hit the floor wall by then, so the affine field is not round-off itself)."""
    folded = jm.scene(scene, scheme=scheme, update=update, damping=False, **kwargs)
    plain = jm.scene(scene, scheme=scheme, update=update, damping=jm.Damping(), **kwargs)
    assert jm.folds_force(folded.sim) and not jm.folds_force(plain.sim)
    a, b = _run(folded, 150), _run(plain, 150)
    for name in ("x", "v", "F", "affine"):
        fa, fb = np.asarray(getattr(a, name)), np.asarray(getattr(b, name))
        scale = max(np.max(np.abs(fb)), 1e-300)
        assert np.max(np.abs(fa - fb)) <= 1e-12 * scale, name
    assert np.max(np.abs(np.asarray(a.x) - np.asarray(folded.state.x))) > 1e-3  # it moved


def test_no_fold_where_v_and_a_are_needed():
    """FLIP reads S a, grid damping reads S v, USF needs v before the force: no folding."""
    base = dict(n_particles=64, n_grid=16)
    assert not jm.folds_force(jm.scene("mpm88", scheme=jm.FLIP(), damping=False, **base).sim)
    assert not jm.folds_force(jm.scene("mpm88", scheme=jm.APIC(), damping=jm.Damping(0.1), **base).sim)
    assert not jm.folds_force(jm.scene("mpm88", scheme=jm.APIC(), damping=False, update="USF", **base).sim)


@pytest.mark.slow
def test_damping_false_can_be_calibrated():
    """set_params on a model without damping puts jm.Damping back (alpha_g, alpha_p reachable)."""
    setup = jm.scene("mpm88", n_particles=64, n_grid=16)
    assert setup.sim.damping is None
    assert float(jm.get_params(setup.sim, "alpha_g")["alpha_g"]) == 0.0
    sim = jm.set_params(setup.sim, alpha_g=0.5)
    assert isinstance(sim.damping, jm.Damping) and float(sim.damping.grid) == 0.5
    assert float(sim.damping.particle) == 0.0
    with_damping = jm.scene("mpm88", n_particles=64, n_grid=16, damping=jm.Damping(grid=0.5))
    a = _run(dataclasses.replace(setup, sim=sim), 20)
    b = _run(with_damping, 20)
    np.testing.assert_allclose(np.asarray(a.v), np.asarray(b.v), rtol=0, atol=1e-13)
