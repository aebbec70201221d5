"""Shape functions S_pi and their gradients G_pi, built from separable 1D factors.

Every shape function is a 1D kernel N(r) of the distance r = (X_p - x_i)/h in cells.  A particle
touches ``K1`` consecutive nodes per axis starting at ``base(xi)``; in D dimensions the stencil is
the tensor product, ``K = K1**D`` nodes:

    S_pi = prod_a N(r_a),      G_pi[a] = N'(r_a)/h_a * prod_{b != a} N(r_b)

uGIMP (001 eqs. 16-17) is the tent function averaged over a particle domain of half-width
l_p = h / (2 ppc), ppc = particles per cell per axis.
"""

from __future__ import annotations


import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._errors import check


class Stencil(eqx.Module):
    """Per-particle view of the grid: ``index`` (N, K) flat node numbers, ``weight`` (N, K) = S_pi,
    ``gradient`` (N, K, D) = G_pi, ``offset`` (N, K, D) = x_i - X_p."""

    index: jnp.ndarray
    weight: jnp.ndarray
    gradient: jnp.ndarray
    offset: jnp.ndarray


class ShapeFunction(eqx.Module):
    """Base class: subclasses define ``nodes_per_axis``, ``margin``, ``_base`` and ``_kernel``."""

    # nodes touched per axis, and the distance (in cells) a particle must keep from the grid edge
    # for its whole stencil to exist; subclasses set both as class constants
    nodes_per_axis = 0
    margin = 0.0

    def _base(self, xi):  # first node of the stencil along one axis, xi in cells
        raise NotImplementedError

    def _kernel(self, r):  # (N(r), dN/dr), r = particle minus node, in cells
        raise NotImplementedError

    # ----------------------------------------------------------------- public
    def weights_1d(self, xi):
        """Along one axis: first node ``base``, weights ``w`` (..., K1) and dN/dxi ``dw`` (..., K1)."""
        base = self._base(xi)
        k = jnp.arange(self.nodes_per_axis, dtype=base.dtype)
        r = xi[..., None] - (base[..., None] + k)
        w, dw = self._kernel(r)
        return base, w, dw

    def stencil(self, grid, x) -> Stencil:
        """S_pi and G_pi for particles at ``x`` (N, D) on ``grid``."""
        dim = grid.dim
        k1 = self.nodes_per_axis
        lower = jnp.asarray(grid.lower, dtype=x.dtype)
        h = jnp.asarray(grid.spacing, dtype=x.dtype)
        xi = (x - lower) / h
        bases, ws, dws = [], [], []
        for a in range(dim):
            b, w, dw = self.weights_1d(xi[:, a])
            bases.append(b)
            ws.append(w)
            dws.append(dw / h[a])
        # tensor products by broadcasting (K = K1^D in C order, the order of itertools.product);
        # no constant-index gathers, so XLA fuses each product into one elementwise kernel
        k = jnp.arange(k1, dtype=jnp.int32)
        weight = _tensor(ws, jnp.multiply)
        gradient = jnp.stack([_tensor([dws[b] if b == a else ws[b] for b in range(dim)], jnp.multiply)
                              for a in range(dim)], axis=-1)
        nodes = [bases[a].astype(jnp.int32)[:, None] + k for a in range(dim)]  # (N, K1) node numbers per axis
        index = _tensor([nodes[a] * jnp.int32(grid.strides[a]) for a in range(dim)], jnp.add)
        offs = [nodes[a].astype(x.dtype) * h[a] + lower[a] - x[:, a:a + 1] for a in range(dim)]  # x_i - X_p per axis
        offset = jnp.stack([_tensor([offs[b] if b == a else jnp.zeros_like(offs[b]) for b in range(dim)], jnp.add)
                            for a in range(dim)], axis=-1)
        # materialise the stencil once: without the barrier XLA fuses the 1D kernels into every
        # consumer and recomputes them per (particle, node, component) -- measured 2-4x slower on CPU
        index, weight, gradient, offset = _materialise((index, weight, gradient, offset), x)
        return Stencil(index=index, weight=weight, gradient=gradient, offset=offset)

    def inside(self, grid, x):
        """True where the particle's whole stencil lies on the grid."""
        lower = jnp.asarray(grid.lower, dtype=x.dtype)
        h = jnp.asarray(grid.spacing, dtype=x.dtype)
        xi = (x - lower) / h
        base = self._base(xi)
        top = base + self.nodes_per_axis - 1
        cells = jnp.asarray(grid.cells)
        return jnp.all((base >= 0) & (top <= cells) & jnp.isfinite(xi), axis=-1)


def _materialise(arrays, x):
    """``arrays`` unchanged, computed once.  XLA on CPU fuses cheap elementwise producers into every
    consumer, so without this the 1D kernels (selects, abs, floor) are recomputed for each
    (particle, node, component) of every transfer: measured 3x slower time step (mpm88, 8k
    particles).  A conditional's result is not fused into its consumers (``lax.optimization_barrier``
    is removed before fusion on CPU, and a cond with two identical branches is inlined).  The
    predicate ``not (x > +inf)`` is true for every float, NaN included, but XLA cannot fold it, so
    the taken branch is always the identity and the values are exactly the inputs (under vmap the
    cond becomes a select that picks them)."""
    always = jnp.logical_not(x.reshape(-1)[0] > jnp.inf)
    return jax.lax.cond(always, lambda a: a, lambda a: jax.tree_util.tree_map(jnp.zeros_like, a), arrays)


def _tensor(factors, combine):
    """combine(f_0[k_0], f_1[k_1], ...) over all K1^D combinations, (N, K) in C order (the order of
    itertools.product), by broadcasting the per-axis (N, K1) factors."""
    n, k1 = factors[0].shape
    out = factors[0]
    for f in factors[1:]:
        out = combine(out[..., None], f.reshape((n,) + (1,) * (out.ndim - 1) + (k1,)))
    return out.reshape(n, k1 ** len(factors))


def _floor_int(v):
    return jnp.floor(v).astype(jnp.int32)


class Linear(ShapeFunction):
    """Linear (tent) shape functions, 2 nodes per axis."""

    nodes_per_axis = 2
    margin = 0.0

    def _base(self, xi):
        return _floor_int(xi)

    def _kernel(self, r):
        a = jnp.abs(r)
        inside = a < 1.0
        return jnp.where(inside, 1.0 - a, 0.0), jnp.where(inside, -jnp.sign(r), 0.0)


class UGIMP(ShapeFunction):
    """Uniform GIMP (001 eqs. 16-17) with particle half-width l_p = h / (2 ppc).

    ``ppc`` is the number of particles per cell along each axis used when filling the body
    (it must match the ``ppc`` given to :func:`jaxmpm.fill`).
    """

    ppc: int = eqx.field(static=True)
    nodes_per_axis = 3
    margin = 0.5

    def __init__(self, ppc: int = 2):
        check(
            isinstance(ppc, (int, np.integer)) and ppc >= 1,
            f"UGIMP: ppc = {ppc!r} must be a positive integer (particles per cell per axis)",
        )
        self.ppc = int(ppc)

    @property
    def half_width(self) -> float:
        """l_p / h."""
        return 0.5 / self.ppc

    def _base(self, xi):
        return _floor_int(xi + 0.5) - 1

    def _kernel(self, r):
        lp = self.half_width
        a = jnp.abs(r)
        s = jnp.sign(r)
        # |r| < l_p: the particle domain straddles the node
        w_in = 1.0 - (r * r + lp * lp) / (2.0 * lp)
        d_in = -r / lp
        # l_p <= |r| < 1 - l_p: the domain lies inside one element, tent value
        w_mid = 1.0 - a
        d_mid = -s
        # 1 - l_p <= |r| < 1 + l_p: the domain overlaps the tent's edge
        w_out = (1.0 + lp - a) ** 2 / (4.0 * lp)
        d_out = -s * (1.0 + lp - a) / (2.0 * lp)
        w = jnp.where(a < lp, w_in, jnp.where(a < 1.0 - lp, w_mid, jnp.where(a < 1.0 + lp, w_out, 0.0)))
        d = jnp.where(a < lp, d_in, jnp.where(a < 1.0 - lp, d_mid, jnp.where(a < 1.0 + lp, d_out, 0.0)))
        return w, d


class QuadraticBSpline(ShapeFunction):
    """Quadratic B-spline, 3 nodes per axis."""

    nodes_per_axis = 3
    margin = 0.5

    def _base(self, xi):
        return _floor_int(xi - 0.5)

    def _kernel(self, r):
        a = jnp.abs(r)
        w = jnp.where(a < 0.5, 0.75 - a * a, jnp.where(a < 1.5, 0.5 * (1.5 - a) ** 2, 0.0))
        d = jnp.where(a < 0.5, -2.0 * r, jnp.where(a < 1.5, -jnp.sign(r) * (1.5 - a), 0.0))
        return w, d

    def inertia_factor(self) -> float:
        """APIC's D_p = factor * h^2 * I (002): h^2/4 for quadratic B-splines."""
        return 0.25


class CubicBSpline(ShapeFunction):
    """Cubic B-spline, 4 nodes per axis."""

    nodes_per_axis = 4
    margin = 1.0

    def _base(self, xi):
        return _floor_int(xi) - 1

    def _kernel(self, r):
        a = jnp.abs(r)
        w = jnp.where(a < 1.0, 0.5 * a**3 - a * a + 2.0 / 3.0, jnp.where(a < 2.0, (2.0 - a) ** 3 / 6.0, 0.0))
        d = jnp.where(a < 1.0, 1.5 * a * r - 2.0 * r, jnp.where(a < 2.0, -0.5 * jnp.sign(r) * (2.0 - a) ** 2, 0.0))
        return w, d

    def inertia_factor(self) -> float:
        """APIC's D_p = factor * h^2 * I (002): h^2/3 for cubic B-splines."""
        return 1.0 / 3.0


SHAPES = {
    "linear": Linear,
    "ugimp": UGIMP,
    "quadratic": QuadraticBSpline,
    "cubic": CubicBSpline,
}


def shape_from_name(name: str, **kwargs) -> ShapeFunction:
    check(name in SHAPES, f"unknown shape {name!r}; choose one of {', '.join(SHAPES)}")
    return SHAPES[name](**kwargs)
