"""Properties of the shape functions S_pi and gradients G_pi (docs/design.md "Shape functions").

For every shape (Linear, uGIMP with ppc = 1, 2, 3, quadratic and cubic B-splines) in 1D, 2D and 3D:

* partition of unity          sum_i S_pi = 1                         (000 ch. 1)
* linear reproduction         sum_i S_pi x_i = X_p, sum_i x_i (x) G_pi = I  (interior particles)
* zero gradient sum           sum_i G_pi = 0
* G = grad S                  central finite differences, eps = 1e-6
* non-negative weights        S_pi >= 0
* ``inside``                  true for interior particles, false beyond the grid
* uGIMP is the particle-domain average of the tent function     (001 eqs. 16-17)

Each hypothesis example draws a seed and evaluates one batch of 64 random particles, so every
(shape, dimension) pair is compiled once.
"""

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest
from cases import GRIDS, SIX_SHAPES, at_cells, central_difference, dense_weights, interior_cells, particle_major
from hypothesis import given, settings
from hypothesis import strategies as st

import jaxmpm as jm

N_PARTICLES = 64
EXAMPLES = settings(max_examples=25, deadline=None)
SEEDS = st.integers(min_value=0, max_value=2**32 - 1)

CASES = [pytest.param(name, dim, id=f"{name}-{dim}d") for name in SIX_SHAPES for dim in GRIDS]


@eqx.filter_jit
def _stencil(shape, grid, x):
    return shape.stencil(grid, x)


def stencil_of(shape, grid, x):
    """The stencil's arrays per particle (N, K[, D]), as NumPy."""
    return particle_major(_stencil(shape, grid, x))


@eqx.filter_jit
def inside_of(shape, grid, x):
    return shape.inside(grid, x)


def kink_fractions(shape):
    """Fractional cell coordinates where S is not smooth or the stencil's first node changes."""
    kinks = [0.0, 0.5, 1.0]
    if isinstance(shape, jm.UGIMP):
        lp = shape.half_width  # 001 eq. (16): kinks at |r| = l_p, 1 - l_p, 1 + l_p
        kinks += [lp, 1.0 - lp]
    return np.array(kinks)


def interior_positions(shape, grid, rng, n=N_PARTICLES, keep_off_kinks=True):
    """Random particles whose whole stencil lies on the grid (``margin`` cells from each edge),
    at least 1e-3 cells away from the shape's kinks so central differences are clean."""
    xi = interior_cells(shape, grid, rng, n)
    if keep_off_kinks:
        frac = xi - np.floor(xi)
        near = np.min(np.abs(frac[..., None] - kink_fractions(shape)), axis=-1) < 1e-3
        xi = np.where(near, xi + 2e-3, xi)
    return at_cells(grid, xi)


@pytest.mark.parametrize("name, dim", CASES)
@EXAMPLES
@given(seed=SEEDS)
def test_partition_of_unity_and_nonnegative(name, dim, seed):
    """sum_i S_pi = 1 and S_pi >= 0 for interior particles."""
    shape, grid = SIX_SHAPES[name], GRIDS[dim]
    x = jnp.asarray(interior_positions(shape, grid, np.random.default_rng(seed), keep_off_kinks=False))
    st_ = stencil_of(shape, grid, x)
    w = np.asarray(st_.weight)
    assert w.shape == (N_PARTICLES, shape.nodes_per_axis**dim)
    np.testing.assert_allclose(w.sum(axis=1), 1.0, rtol=0, atol=1e-14)
    assert np.all(w >= 0.0)
    idx = np.asarray(st_.index)
    assert idx.min() >= 0 and idx.max() < grid.num_nodes


@pytest.mark.parametrize("name, dim", CASES)
@EXAMPLES
@given(seed=SEEDS)
def test_linear_reproduction(name, dim, seed):
    """sum_i S_pi x_i = X_p, sum_i x_i (x) G_pi = I, and offset = x_i - X_p, for interior particles."""
    shape, grid = SIX_SHAPES[name], GRIDS[dim]
    xp = interior_positions(shape, grid, np.random.default_rng(seed), keep_off_kinks=False)
    st_ = stencil_of(shape, grid, jnp.asarray(xp))
    nodes = grid.node_coordinates()[np.asarray(st_.index)]  # (N, K, D)
    w, g = np.asarray(st_.weight), np.asarray(st_.gradient)
    np.testing.assert_allclose(np.einsum("pk,pka->pa", w, nodes), xp, rtol=0, atol=1e-13)
    identity = np.broadcast_to(np.eye(dim), (N_PARTICLES, dim, dim))
    np.testing.assert_allclose(np.einsum("pka,pkb->pab", nodes, g), identity, rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.asarray(st_.offset), nodes - xp[:, None, :], rtol=0, atol=1e-13)


@pytest.mark.parametrize("name, dim", CASES)
@EXAMPLES
@given(seed=SEEDS)
def test_gradient_sum_is_zero(name, dim, seed):
    """sum_i G_pi = 0 (the gradient of the partition of unity)."""
    shape, grid = SIX_SHAPES[name], GRIDS[dim]
    x = jnp.asarray(interior_positions(shape, grid, np.random.default_rng(seed), keep_off_kinks=False))
    g = np.asarray(stencil_of(shape, grid, x).gradient)
    scale = 1.0 / min(grid.spacing)
    np.testing.assert_allclose(g.sum(axis=1), 0.0, rtol=0, atol=1e-13 * scale)


@pytest.mark.parametrize("name, dim", CASES)
@EXAMPLES
@given(seed=SEEDS)
def test_gradient_is_finite_difference_of_weight(name, dim, seed):
    """G_pi[a] = (S_i(X + eps e_a) - S_i(X - eps e_a)) / (2 eps), node by node (eps = 1e-6)."""
    shape, grid = SIX_SHAPES[name], GRIDS[dim]
    xp = interior_positions(shape, grid, np.random.default_rng(seed))
    _, G = dense_weights(_stencil(shape, grid, jnp.asarray(xp)), grid.num_nodes)
    for a in range(dim):
        e_a = np.eye(dim)[a]

        def S_along(s, e_a=e_a):
            return dense_weights(_stencil(shape, grid, jnp.asarray(xp + s * e_a)), grid.num_nodes)[0]

        fd = central_difference(S_along, 0.0, 1e-6)
        scale = 1.0 / grid.spacing[a]  # |G| is O(1/h)
        np.testing.assert_allclose(G[..., a], fd, rtol=0, atol=1e-6 * scale)


@pytest.mark.parametrize("name, dim", CASES)
@EXAMPLES
@given(seed=SEEDS)
def test_inside(name, dim, seed):
    """``inside`` is true for interior particles and false once one coordinate is beyond
    the shape's margin (or is not finite)."""
    shape, grid = SIX_SHAPES[name], GRIDS[dim]
    rng = np.random.default_rng(seed)
    x = interior_positions(shape, grid, rng, keep_off_kinks=False)
    assert np.all(np.asarray(inside_of(shape, grid, jnp.asarray(x))))

    cells = np.array(grid.cells, dtype=float)
    m = float(shape.margin)
    axis = rng.integers(0, dim, N_PARTICLES)
    below = rng.random(N_PARTICLES) < 0.5
    distance = 0.01 + 2.0 * rng.random(N_PARTICLES)  # cells beyond the allowed band
    xi_out = np.where(below, m - distance, cells[axis] - m + distance)
    rows = np.arange(N_PARTICLES)
    x_out = x.copy()
    x_out[rows, axis] = np.array(grid.lower)[axis] + xi_out * np.array(grid.spacing)[axis]
    assert not np.any(np.asarray(inside_of(shape, grid, jnp.asarray(x_out))))

    x_nan = x.copy()
    x_nan[rows, axis] = np.nan
    assert not np.any(np.asarray(inside_of(shape, grid, jnp.asarray(x_nan))))


def tent_average(r, lp, derivative=False):
    """(1/2l_p) int_{r-l_p}^{r+l_p} N(s) ds with the tent N(s) = max(0, 1 - |s|) (001 eq. 16),
    or the average of N'(s) (001 eq. 17), by 3-point Gauss-Legendre quadrature on the pieces
    between the tent's kinks -1, 0, 1 (exact for a piecewise-linear integrand)."""
    gauss_x, gauss_w = np.polynomial.legendre.leggauss(3)
    a, b = r - lp, r + lp
    cuts = np.sort(np.stack([a, b] + [np.clip(k, a, b) for k in (-1.0, 0.0, 1.0)], axis=-1), axis=-1)
    lo, hi = cuts[..., :-1, None], cuts[..., 1:, None]  # (M, 4 pieces, 1)
    s = 0.5 * (hi - lo) * gauss_x + 0.5 * (hi + lo)
    f = np.where(np.abs(s) < 1.0, -np.sign(s), 0.0) if derivative else np.maximum(0.0, 1.0 - np.abs(s))
    return np.sum(0.5 * (hi - lo) * gauss_w * f, axis=(-1, -2)) / (2.0 * lp)


@pytest.mark.parametrize("ppc", [1, 2, 3])
@EXAMPLES
@given(seed=SEEDS)
def test_ugimp_is_domain_average_of_tent(ppc, seed):
    """uGIMP S_pi and G_pi equal the averages of the tent function and of its derivative over the
    particle domain [X_p - l_p, X_p + l_p], l_p = h / (2 ppc) (001 eqs. 16-17), in 1D and, as
    the tensor product of the 1D averages (a box-shaped particle domain), in 2D."""
    shape = SIX_SHAPES[f"ugimp{ppc}"]
    lp = shape.half_width
    rng = np.random.default_rng(seed)
    for dim in (1, 2):
        grid = GRIDS[dim]
        h = np.array(grid.spacing)
        xp = interior_positions(shape, grid, rng)
        st_ = stencil_of(shape, grid, jnp.asarray(xp))
        nodes = grid.node_coordinates()[np.asarray(st_.index)]  # (N, K, D)
        r = (xp[:, None, :] - nodes) / h  # particle minus node, in cells
        avg = tent_average(r.reshape(-1), lp).reshape(r.shape)
        davg = tent_average(r.reshape(-1), lp, derivative=True).reshape(r.shape) / h
        expected_w = np.prod(avg, axis=-1)
        expected_g = np.stack(
            [davg[..., a] * np.prod(np.delete(avg, a, axis=-1), axis=-1) for a in range(dim)], axis=-1
        )
        np.testing.assert_allclose(np.asarray(st_.weight), expected_w, rtol=0, atol=1e-14)
        np.testing.assert_allclose(np.asarray(st_.gradient), expected_g, rtol=0, atol=1e-13 / h.min())


def test_a_stencil_forms_its_products_once_per_trace():
    """``TensorStencil.weight``, ``gradient`` and ``offset`` are formed once per trace and read again
    (mpm88 used the weight three times a step, and reverse mode summed one cotangent per use); a value
    formed inside a nested trace (here a ``jax.jit`` that closes over the stencil) is not kept, so the
    outer trace's later use forms its own and no tracer escapes; the values equal the plain products."""
    import jax

    grid = jm.Grid((0.0, 0.0), (4.0, 4.0), (4, 4))
    x = jnp.asarray(np.random.default_rng(0).uniform(1.2, 2.8, (16, 2)))

    def apart(x):  # each product from a stencil of its own: nothing shared
        return tuple(getattr(jm.QuadraticBSpline().stencil(grid, x), name) for name in ("weight", "gradient", "offset"))

    def outer(x):
        stencil = jm.QuadraticBSpline().stencil(grid, x)
        inner = jax.jit(lambda: stencil.weight * 2.0)()  # formed in the nested trace: not kept
        assert stencil.weight is stencil.weight and stencil.gradient is stencil.gradient
        return stencil.weight, stencil.gradient, stencil.offset, inner

    jaxpr = jax.make_jaxpr(outer)(x)
    splits = sum(1 for eqn in jaxpr.jaxpr.eqns if eqn.primitive.name == "unstack")
    assert splits == 3  # one per factor array (w, dw, dx), however many products use it
    weight, gradient, offset, inner = jax.jit(outer)(x)
    plain = jax.jit(apart)(x)
    np.testing.assert_array_equal(weight, plain[0])
    np.testing.assert_array_equal(gradient, plain[1])
    np.testing.assert_array_equal(offset, plain[2])
    np.testing.assert_array_equal(inner, 2.0 * plain[0])


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
@pytest.mark.parametrize("shape", [jm.QuadraticBSpline(), jm.CubicBSpline()], ids=["quadratic", "cubic"])
def test_kernel_rows_are_the_kernels_bits(shape, dtype):
    """The B-splines evaluate each stencil row on its own piece of the kernel (``_kernel_rows``, the stencil's
    form since 2026-11-28: the float64 mpm88 step 13-20% faster).  That is the kernel itself: at random
    positions, on the nodes, at the cell centres and one unit in the last place on either side of them, where
    the pieces meet, and past the grid's edges (clamped).  With XLA's optimisations on, the bits are the same
    (so were the final states of eleven scenes, benchmarks/README.md); with most of them off (this suite's
    setting) LLVM fuses a product and a difference into one FMA in one form and not the other, and up to 8%
    of the values differ by one unit in the last place.  A particle that
    has left the grid is weighted as if at the nearest position whose stencil lies on the grid:
    non-negative weights summing to one."""
    import jax

    rng = np.random.default_rng(7)
    grid = jm.Grid((0.0,), (64.0,), (64,))  # unit cells
    nodes = np.arange(0.0, 65.0)
    xi = np.concatenate([rng.uniform(-3.0, 67.0, 4096), nodes, nodes + 0.5, nodes + 0.25,
                         np.nextafter(nodes + 0.5, -9.0), np.nextafter(nodes + 0.5, 99.0),
                         np.nextafter(nodes, -9.0), np.nextafter(nodes, 99.0)]).astype(dtype)
    cells, first = jax.jit(lambda xp: shape._cells(grid, xp))(jnp.asarray(xi[None, :]))  # clamped past the edges
    r = cells - (first + jnp.arange(shape.nodes_per_axis, dtype=jnp.int32)[:, None]).astype(dtype)
    ulp = np.finfo(dtype).eps

    def both():  # the kernel and its rows, each compiled on its own
        pairs = zip(jax.jit(shape._kernel)(r), jax.jit(shape._kernel_rows)(r))
        return [(np.asarray(a), np.asarray(b)) for a, b in pairs]

    for (whole, by_rows), largest in zip(both(), (1.0, 2.0)):  # this suite's flags; |N| <= 1, |dN/dr| <= 2
        assert by_rows.dtype == dtype
        np.testing.assert_allclose(by_rows, whole, rtol=0, atol=largest * ulp)
    suite = jax.config.values["jax_disable_most_optimizations"]
    jax.config.update("jax_disable_most_optimizations", False)  # XLA's defaults (the loop emitters stay)
    try:
        for whole, by_rows in both():
            np.testing.assert_array_equal(by_rows, whole)
    finally:
        jax.config.update("jax_disable_most_optimizations", suite)

    grid = jm.Grid((0.0,), (8.0,), (8,))
    outside = jnp.asarray([[-0.7], [-0.2], [8.3], [9.6]], dtype=dtype)  # clipped stencils
    edges = jnp.asarray([[shape.margin], [shape.margin], [8.0 - shape.margin], [8.0 - shape.margin]], dtype=dtype)
    stencil, at_edges = (jax.jit(lambda x: shape.stencil(grid, x))(x) for x in (outside, edges))
    np.testing.assert_array_equal(np.asarray(stencil.weight), np.asarray(at_edges.weight))
    np.testing.assert_array_equal(np.asarray(stencil.index), np.asarray(at_edges.index))
    assert np.all(np.asarray(stencil.weight) >= 0)
    np.testing.assert_allclose(np.asarray(jnp.sum(stencil.weight, axis=0)), 1.0, rtol=0, atol=4 * ulp)
