"""Shape functions S_pi and their gradients G_pi, built from separable 1D factors.

Every shape function is a 1D kernel N(r) of the distance r = (X_p - x_i)/h in cells.  A particle
touches ``K1`` consecutive nodes per axis starting at ``base(xi)``; in D dimensions the stencil is
the tensor product, ``K = K1**D`` nodes:

    S_pi = prod_a N(r_a),      G_pi[a] = N'(r_a)/h_a * prod_{b != a} N(r_b)

uGIMP (001 eqs. 16-17) is the tent function averaged over a particle domain of half-width
l_p = h / (2 ppc), ppc = particles per cell per axis.

On an axisymmetric grid (``Grid(..., axisymmetric=True)``, 001 §7) the radial factors are
r-weighted (001 eqs. 112, 115) and the stencil carries the hoop shape function T_ip (eq. 116):
:class:`AxisymmetricStencil`.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..core.errors import check
from ..core.registry import SHAPES, register_shape
from .backend import derivative_rule, evaluate_once, hold_tangent


def rows(a):
    """[a[0], a[1], ...]: the slices of ``a`` along its first axis, taken as one split.  The same
    values as indexing; in reverse mode the split's transpose concatenates the slices' cotangents,
    where each index would pad its own into a zero array of ``a``'s size (for the planar (D, K, N)
    stencil arrays, D pads of K N numbers per use)."""
    return list(jnp.unstack(a, axis=0))


def _kept(owner, key, compute):
    """``compute()``, kept on ``owner`` (a frozen module) under ``key``: every use of a stencil's weight,
    gradient or offset in one trace then reads one set of values, so reverse mode sums their cotangents
    before transposing the products once (mpm88 used the weight 3 times, the gradient and the offset
    twice each, per step).  A value is kept only if it belongs to the trace of ``owner``'s arrays: one
    computed inside a nested trace (a stage boundary's branch, a derivative rule) is used there and not
    kept, so no value escapes its trace."""
    cache = owner.__dict__.get("_kept")
    if cache is None:
        cache = {}
        object.__setattr__(owner, "_kept", cache)
    if key in cache:
        return cache[key]
    value = compute()
    if of_trace(value, jax.tree_util.tree_leaves(owner)[0]):
        cache[key] = value
    return value


def of_trace(value, anchor) -> bool:
    """Whether every array of ``value`` (a pytree) belongs to the trace of the array ``anchor``: a value
    computed inside a nested trace does not, and keeping it for the outer one would leak its tracers."""
    home = _trace_of(anchor)
    return all(_trace_of(leaf) is home for leaf in jax.tree_util.tree_leaves(value))


def _trace_of(a):
    """The trace a tracer belongs to; None for a concrete array; for a tracer that does not say (another
    JAX), a new object, so that nothing is kept."""
    if not isinstance(a, jax.core.Tracer):
        return None
    return getattr(a, "_trace", None) or object()


class StencilBase(eqx.Module):
    """Per-particle view of the grid, stored node-slot-major with the particle axis last
    ("planar": every per-(node, particle) quantity is a stack of length-N rows, so the arithmetic
    of P2G/G2P runs on contiguous particle vectors):

    * ``index``    (K, N) flat node numbers i of the K stencil slots of each particle
    * ``weight``   (K, N) S_pi
    * ``gradient`` (D, K, N) G_pi, component first
    * ``offset``   (D, K, N) x_i - X_p, component first

    :class:`Stencil` holds the four arrays (any stencil, e.g. a padded one in a test); shape
    functions return a :class:`TensorStencil`, which stores per-axis factors and forms the four
    arrays where they are used.  :meth:`matrices` gives the dense S (N, n) and G (N, n, D)."""

    @property
    def num_particles(self) -> int:
        return self.index.shape[-1]

    @property
    def size(self) -> int:
        """K, the number of nodes each particle touches."""
        return self.index.shape[0]

    @property
    def dim(self) -> int:
        return self.gradient.shape[0]

    @property
    def dtype(self):
        """The floating dtype of the stencil's weights (the precision the transfers compute in)."""
        return self.weight.dtype

    @property
    def nodes_per_axis(self) -> int:
        """K1 with K = K1^D for a tensor-product stencil."""
        return int(round(self.size ** (1.0 / self.dim)))

    def matrices(self, num_nodes: int):
        """Dense NumPy S (N, n) and G (N, n, D) of this stencil (small problems, tests)."""
        index = np.asarray(self.index)
        k, n_p = index.shape
        d = self.dim
        rows = np.broadcast_to(np.arange(n_p), (k, n_p)).reshape(-1)
        S = np.zeros((n_p, num_nodes))
        np.add.at(S, (rows, index.reshape(-1)), np.asarray(self.weight).reshape(-1))
        G = np.zeros((n_p, num_nodes, d))
        grad = np.asarray(self.gradient).reshape(d, -1)
        for a in range(d):
            np.add.at(G[..., a], (rows, index.reshape(-1)), grad[a])
        return S, G

    def inertia(self):
        """D_p = sum_i S_pi (x_i - X_p)(x_i - X_p)^T, planar (D, D, N)  (002 eq. 3)."""
        w, off = self.weight, self.offset
        d = self.dim
        return jnp.stack([jnp.stack([jnp.sum(w * off[a] * off[b], axis=0) for b in range(d)]) for a in range(d)])

    def explicit(self) -> "Stencil":
        """The four planar arrays as a plain :class:`Stencil`."""
        return Stencil(index=self.index, weight=self.weight, gradient=self.gradient, offset=self.offset)


class Stencil(StencilBase):
    """A stencil given by its four planar arrays (see :class:`StencilBase`), e.g. a padded one in
    a test; shape functions return a :class:`TensorStencil`.

    Args:
        index: (K, N) flat node numbers i of the K stencil slots of each particle, in [0, n): the
            transfers gather and scatter without bounds handling (shape functions clip).
        weight: (K, N) the shape function values S_pi.
        gradient: (D, K, N) the gradients G_pi, component first.
        offset: (D, K, N) x_i - X_p, component first.
    """

    index: jnp.ndarray
    weight: jnp.ndarray
    gradient: jnp.ndarray
    offset: jnp.ndarray


class TensorStencil(StencilBase):
    """A tensor-product stencil kept as its per-axis factors (K1 nodes per axis, K = K1^D):

    * ``index``  (K, N) flat node numbers, stored (every transfer reads them)
    * ``w``      (D, K1, N) N(r) per axis,  ``dw`` (D, K1, N) dN/dx per axis (1/h included)
    * ``dx``     (D, K1, N) x_i - X_p per axis

    ``weight``, ``gradient`` and ``offset`` are products and sums of these factors,
    S_pi = prod_a w_a,  G_pi[a] = dw_a prod_{b != a} w_b, formed where they are used: on CPU one
    multiply per slot inside the consuming kernel is cheaper than reading a stored (K, N) array,
    while the kernels themselves (selects, powers) are evaluated once per axis.

    Args:
        index: (K, N) flat node numbers of the K = K1^D slots, C order over the axes.
        w: (D, K1, N) the 1D shape function N(r) per axis.
        dw: (D, K1, N) its derivative dN/dx per axis (1/h included).
        dx: (D, K1, N) x_i - X_p per axis.
        inertia_diagonal: APIC's D_p = diag(c h_a^2) (:meth:`inertia`) where it is the same at every particle
            position, as for the B-splines (002 eq. 3: c = 1/4 quadratic, 1/3 cubic; ``shape.inertia_factor()``),
            one number per axis; None (the default) where D_p depends on the position and is summed from the
            factors.
    """

    index: jnp.ndarray
    w: jnp.ndarray
    dw: jnp.ndarray
    dx: jnp.ndarray
    inertia_diagonal: tuple | None = eqx.field(static=True, default=None, kw_only=True)

    @property
    def num_particles(self) -> int:
        return self.w.shape[-1]

    @property
    def size(self) -> int:
        return self.w.shape[1] ** self.w.shape[0]

    @property
    def dim(self) -> int:
        return self.w.shape[0]

    @property
    def nodes_per_axis(self) -> int:
        return self.w.shape[1]

    @property
    def dtype(self):
        return self.w.dtype

    def inertia(self):
        """D_p from the per-axis factors: with sum_i w_a,i = 1 per axis, D_aa = sum_i w_a,i dx_a,i^2
        and D_ab = (sum_i w_a,i dx_a,i)(sum_j w_b,j dx_b,j) for a != b (zero for B-splines).

        Where D_p is the same at every position (``inertia_diagonal``: the B-splines, 002 eq. 3), it is that
        constant, diag(c h_a^2), which the sums equal to round-off: no sums are formed, and differentiation
        sees the constant it is (the sums' derivative is round-off, tests/test_affine.py)."""
        d = self.dim
        if self.inertia_diagonal is not None:
            diagonal = jnp.diag(jnp.asarray(self.inertia_diagonal, self.dtype))[:, :, None]
            return jnp.broadcast_to(diagonal, (d, d, self.num_particles))
        wdx = self.w * self.dx
        wdx_k, dx_k = rows(jnp.moveaxis(wdx, 1, 0)), rows(jnp.moveaxis(self.dx, 1, 0))
        m1 = rows(sum(wdx_k))  # (D, N) per axis; unrolled: fuses on CPU
        m2 = rows(sum(a * b for a, b in zip(wdx_k, dx_k)))
        return jnp.stack([jnp.stack([m2[a] if a == b else m1[a] * m1[b] for b in range(d)]) for a in range(d)])

    def _once(self, key, compute):
        """``compute()``, kept on this stencil for the trace its factors belong to (see :func:`_kept`)."""
        return _kept(self, key, compute)

    def factor_rows(self, name: str) -> list:
        """[f_0, f_1, ...]: the per-axis (K1, N) factors of ``w``, ``dw`` or ``dx``, split once per stencil."""
        return self._once(("rows", name), lambda: rows(getattr(self, name)))

    @property
    def weight(self):
        return self._once("weight", lambda: _tensor(self.factor_rows("w"), jnp.multiply))

    @property
    def gradient(self):
        def compute():
            d = self.dim
            w, dw = self.factor_rows("w"), self.factor_rows("dw")
            return jnp.stack([_tensor([dw[b] if b == a else w[b] for b in range(d)], jnp.multiply) for a in range(d)])
        return self._once("gradient", compute)

    @property
    def offset(self):
        def compute():
            d = self.dim
            dx = self.factor_rows("dx")
            zero = jnp.zeros_like(dx[0])
            return jnp.stack([_tensor([dx[b] if b == a else zero for b in range(d)], jnp.add) for a in range(d)])
        return self._once("offset", compute)


class AxisymmetricStencil(TensorStencil):
    """The stencil of an axisymmetric (r-z) grid (001 §7): the per-axis factors of
    :class:`TensorStencil`, with the radial ones r-weighted (001 eqs. 112, 115),

        S_ip = (1/(A_p r_p)) int chi_p N_i r dA,   G_ip = (1/(A_p r_p)) int chi_p grad N_i r dA,

    plus ``t_r`` (K1, N), the radial factor of the hoop shape function of 001 eq. 116,

        T_ip = (1/(A_p r_p)) int chi_p N_i dA = t_r * w_z,   t_r = (Cartesian radial factor) / r_p,

    (for a rectangle <r_p> = r_p).  Point particles (Linear, B-splines): S = N_i(X_p),
    G = grad N_i(X_p), T = N_i(X_p) / r_p.

    Args:
        index: (K, N) flat node numbers, as for :class:`TensorStencil`.
        w: (2, K1, N) the per-axis factors (r, z), the radial one r-weighted (001 eq. 112).
        dw: (2, K1, N) their derivatives, the radial one r-weighted (001 eq. 115).
        dx: (2, K1, N) x_i - X_p per axis.
        t_r: (K1, N) the radial factor of the hoop shape function, T_ip = t_r * w_z (001 eq. 116).
        inertia_diagonal: as for :class:`TensorStencil`; None (the default) here, since the r-weighted radial
            factors make D_p depend on the position.
    """

    t_r: jnp.ndarray

    @property
    def hoop(self):
        """T_ip (K, N), 001 eq. 116."""
        return _tensor([self.t_r, rows(self.w)[1]], jnp.multiply)

    def hoop_view(self) -> TensorStencil:
        """A stencil whose weight is T_ip: the transfer layer's gather and scatter with it give
        sum_i u_i T_ip and sum_p T_ip q_p."""
        return TensorStencil(self.index, jnp.stack([self.t_r, rows(self.w)[1]]), self.dw, self.dx)


class ShapeFunction(eqx.Module):
    """Base class: subclasses define ``nodes_per_axis``, ``margin``, ``_base`` and ``_kernel``
    (docs/extending.md, "A shape function")."""

    # nodes touched per axis, and the distance (in cells) a particle must keep from the grid edge
    # for its whole stencil to exist; subclasses set both as class constants
    nodes_per_axis = 0
    margin = 0.0

    def __check_init__(self):
        cls = type(self)
        missing = [hook for hook in ("_base", "_kernel") if getattr(cls, hook) is getattr(ShapeFunction, hook)]
        count = self.nodes_per_axis  # a class constant, or a property of the instance
        check(not missing and isinstance(count, (int, np.integer)) and not isinstance(count, bool) and count >= 1,
              f"{cls.__name__}: a shape function sets nodes_per_axis (a positive int; now {count!r}) and margin, "
              f"and defines _base(xi) and _kernel(r){'; missing: ' + ', '.join(missing) if missing else ''} "
              "(docs/extending.md, 'A shape function')")

    def _base(self, xi):  # first node of the stencil along one axis, xi in cells
        raise NotImplementedError

    def _kernel(self, r):  # (N(r), dN/dr), r = particle minus node, in cells
        raise NotImplementedError

    def _kernel_rows(self, r):
        """(N(r), dN/dr) on a particle's stencil rows: ``r`` (K1, N), row k the particle minus its k-th node,
        in cells.  Inside the grid each row of a B-spline stencil lies in one piece of the kernel, so a shape
        may evaluate that piece alone, with the same operations as :meth:`_kernel` (the same values; the same
        bits where the compiler fuses them alike).  A particle that has left the grid is evaluated at the
        nearest position whose stencil is whole (:meth:`_cells`), so its rows too lie in their pieces.  By
        default the whole kernel."""
        return self._kernel(r)

    def inertia_factor(self) -> float | None:
        """c in APIC's D_p = c h^2 I (002, per axis h_a) where D_p is the same at every position (the B-splines);
        None where it depends on the position (uGIMP) or is singular on grid lines (:class:`Linear`)."""
        return None

    def grid_basis(self) -> "ShapeFunction":
        """The grid basis N_i(x) itself, evaluated at a point (001 eq. 21's int N_i T dS): the
        shape function for point particles; the tent (:class:`Linear`) for uGIMP."""
        return self

    def _radial_moment(self, r):
        """(M1(r), dM1/dr), the first moment over the particle domain (1/(2 l_p)) int N(r + q) q dq
        (cells), that the r-weighting of 001 eqs. 112 and 115 adds; None for point particles."""
        return None

    # ----------------------------------------------------------------- public
    def stencil(self, grid, x) -> "TensorStencil":
        """S_pi and G_pi for particles at ``x`` (N, D) on ``grid`` (planar layout, see :class:`Stencil`)."""
        # a stage boundary (jaxmpm.transfer.backend): on the CPU the 1D kernels (selects, powers) are
        # evaluated once into their own buffers instead of being fused into every consumer.  The planar
        # positions are its operand, so they are laid out once, before it: inside, XLA fused the transpose
        # of x into each factor's loop, element by element
        return evaluate_once(lambda xp: self._factors(grid, xp), planar_positions(x))

    def _factors(self, grid, xp) -> "TensorStencil":
        """The factors at the planar positions ``xp`` (D, N)."""
        k1 = self.nodes_per_axis
        lower = jnp.asarray(grid.lower, dtype=xp.dtype)
        h = jnp.asarray(grid.spacing, dtype=xp.dtype)
        # one split of the positions into their axes' rows: in reverse mode the rows' cotangents are
        # concatenated once, where an index per axis would pad each into a (D, N) array and add them up
        # in one loop that evaluated every axis's kernel derivative at every element
        positions = rows(xp)
        k = jnp.arange(k1, dtype=jnp.int32)[:, None]
        # the positions in cells and each axis's first node, evaluated once (a stage boundary on the CPU):
        # fused into the factors, they were evaluated again for each of the K1 rows of each factor and for
        # each of the K node numbers (mpm88, float64, chunks of 16k particles: the stencil 17.7 -> 6.7 ns a
        # particle with the B-splines' rows on their pieces, benchmarks/README.md "The stencil in two stages")
        in_cells, firsts = evaluate_once(lambda xp: self._cells(grid, xp), xp)
        nodes_per_axis, ws, dws, dxs = [], [], [], []
        for a, (xi, first) in enumerate(zip(rows(in_cells), rows(firsts))):
            nodes = first[None, :] + k  # (K1, N)
            r = xi[None, :] - nodes.astype(xp.dtype)  # particle minus node, in cells
            w, dw = self._kernel_rows(r)
            if a == 0 and grid.axisymmetric:
                w, dw, t_r = _radial_factors(self, r, w, dw, positions[0], h[a])
            nodes_per_axis.append(nodes * jnp.int32(grid.strides[a]))
            ws.append(w)
            dws.append(dw / h[a])
            dxs.append(nodes.astype(xp.dtype) * h[a] + lower[a] - positions[a][None, :])  # x_i - X_p
        index = _tensor(nodes_per_axis, jnp.add)
        if grid.axisymmetric:
            return AxisymmetricStencil(index, jnp.stack(ws), jnp.stack(dws), jnp.stack(dxs), t_r)
        factor = self.inertia_factor()  # D_p = diag(c h_a^2) at every position (B-splines), else None
        diagonal = None if factor is None else tuple(factor * float(h) ** 2 for h in grid.spacing)
        return TensorStencil(index, jnp.stack(ws), jnp.stack(dws), jnp.stack(dxs), inertia_diagonal=diagonal)

    def _cells(self, grid, xp):
        """(xi, first): the planar positions ``xp`` (D, N) in cells from the grid's lower corner, and each
        axis's first stencil node (D, N) int32.  A particle that has left the grid (``inside`` false) is
        weighted as if at the nearest position whose stencil lies on the grid: xi clamped to
        [margin, cells - margin], and its first node kept on the grid.  Its weights are then a valid
        stencil's (non-negative, summing to one) on nodes that exist, and the run reports it as a failure;
        inside the grid neither clamp changes anything."""
        lower = jnp.asarray(grid.lower, dtype=xp.dtype)
        h = jnp.asarray(grid.spacing, dtype=xp.dtype)
        in_cells, firsts = [], []
        for a, position in enumerate(rows(xp)):
            # the spacing behind a barrier: XLA turns a division by a known scalar into a product with its
            # reciprocal wherever it sees the constant, and only there (not in a sharded run's branches),
            # so the same particle got cells one unit in the last place apart in the two programs
            xi = (position - lower[a]) / jax.lax.optimization_barrier(h[a])  # (N,)
            xi = jnp.clip(xi, self.margin, grid.cells[a] - self.margin)
            in_cells.append(xi)
            firsts.append(jnp.clip(self._base(xi), 0, grid.cells[a] + 1 - self.nodes_per_axis))
        return jnp.stack(in_cells), jnp.stack(firsts)

    def inside(self, grid, x):
        """True where the particle's whole stencil lies on the grid.  A numpy ``x`` is checked in
        numpy, on the host, with the same arithmetic: ``Simulation.init``'s check compiles nothing (as
        jnp operations run eagerly, it compiled 16 small programs in a new process, 0.34 of the first
        ``jm.scene("disks")``'s 0.63 s)."""
        xp = np if isinstance(x, np.ndarray) else jnp
        lower = xp.asarray(grid.lower, dtype=x.dtype)
        h = xp.asarray(grid.spacing, dtype=x.dtype)
        xi = (x - lower[None, :]) / h[None, :]
        base = self._base(xi)
        top = base + self.nodes_per_axis - 1
        cells = xp.asarray(grid.cells, dtype=np.int32)
        return xp.all((base >= 0) & (top <= cells[None, :]) & xp.isfinite(xi), axis=-1)


SHAPES.base = ShapeFunction  # register_shape accepts its subclasses only


def _radial_factors(shape, r, w, dw, radius, h):
    """The radial factors on an axisymmetric grid (001 §7), r = particle minus node in cells,
    ``radius`` r_p (N,): with u = x - X_p, int N (r_p + u) du / (2 l_p r_p) = w + (h / r_p) M1, and
    likewise for dN/dr (001 eqs. 112, 115); the hoop factor is w / r_p (001 eq. 116).  Point
    particles have M1 = 0."""
    t_r = w / radius[None, :]  # 001 eq. (116): (1/(2 l_p r_p)) int N dr
    moment = shape._radial_moment(r)
    if moment is not None:
        m1, dm1 = moment
        w = w + (h / radius)[None, :] * m1  # 001 eq. (112)
        dw = dw + (h / radius)[None, :] * dm1  # 001 eq. (115)
    return w, dw, t_r


def _planar_positions(x):
    """The particles' positions (N, D) as planar rows (D, N)."""
    return x.T


_planar_positions_ruled = jax.custom_jvp(_planar_positions)


@_planar_positions_ruled.defjvp
def _planar_positions_jvp(primals, tangents):
    # the tangent behind a stage boundary: in reverse mode the positions' cotangent is evaluated planar,
    # (D, N), once, and then transposed to (N, D); without it XLA fuses the stencil's whole transpose into
    # that layout change, where it runs element by element (mpm88 gradient at 131k particles: one 12.5 ms
    # fusion of a 100 ms step)
    (x,), (x_dot,) = primals, tangents
    return x.T, hold_tangent(x_dot.T, x.reshape(-1)[:1])


planar_positions = derivative_rule(_planar_positions, _planar_positions_ruled)


def _tensor_product(factors, combine):
    """combine(f_0[k_0], f_1[k_1], ...) over all K1^D combinations, (K, N) in C order (the order of
    itertools.product), by broadcasting the per-axis (K1, N) factors."""
    k1, n = factors[0].shape
    out = factors[0]
    for f in factors[1:]:
        out = combine(out[..., None, :], f.reshape((1,) * (out.ndim - 1) + (k1, n)))
    return out.reshape(k1 ** len(factors), n)


_tensor_product_ruled = jax.custom_jvp(_tensor_product, nondiff_argnums=(1,))


@_tensor_product_ruled.defjvp
def _tensor_product_jvp(combine, primals, tangents):
    # the same products, one particle row per slot: the transpose of a broadcast is a reduction over
    # a short axis, which XLA's CPU backend runs slowly; that of a row product is a multiply and an
    # add (the forward keeps the broadcast, which fuses better)
    (factors,), (dots,) = primals, tangents

    def by_rows(factors):
        slots = rows(factors[0])
        for f in factors[1:]:
            slots = [combine(s, r) for s in slots for r in rows(f)]
        return jnp.stack(slots)

    return _tensor_product_ruled(factors, combine), jax.jvp(by_rows, (factors,), (dots,))[1]


_tensor = derivative_rule(_tensor_product, _tensor_product_ruled)


def _floor_int(v):
    """floor(v) as int32, in numpy for a numpy ``v`` (:meth:`ShapeFunction.inside`'s host check)."""
    if isinstance(v, np.ndarray):
        return np.floor(v).astype(np.int32)
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

    Args:
        ppc: the number of particles per cell along each axis used when filling the body, a
            positive integer (default 2); it must match the ``ppc`` given to :func:`jaxmpm.fill`
            (:meth:`jaxmpm.Simulation.init` checks).
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

    def grid_basis(self) -> "ShapeFunction":
        """The tent N_i that uGIMP averages over the particle domain (001 eqs. 16-17)."""
        return Linear()

    def _radial_moment(self, r):
        """M1(r) = (1/(2 l_p)) int_{-l_p}^{l_p} N(r + q) q dq of the tent N (odd in r), and dM1/dr
        (even): the r-weighting of 001 eqs. 112 and 115 on the uGIMP domain of half-width l_p."""
        lp = self.half_width
        a = jnp.abs(r)
        s = jnp.sign(r)
        e = 1.0 + lp - a  # the domain's overlap with the tent's edge
        m_in, dm_in = (a**3 / 3.0 - a * lp * lp) / (2.0 * lp), (a * a - lp * lp) / (2.0 * lp)  # |r| < l_p
        m_mid, dm_mid = -lp * lp / 3.0, 0.0  # inside one element: the tent's slope times l_p^2/3
        m_out, dm_out = e * e * (e - 3.0 * lp) / (12.0 * lp), e * (2.0 * lp - e) / (4.0 * lp)  # the edge
        m = jnp.where(a < lp, m_in, jnp.where(a < 1.0 - lp, m_mid, jnp.where(a < 1.0 + lp, m_out, 0.0)))
        dm = jnp.where(a < lp, dm_in, jnp.where(a < 1.0 - lp, dm_mid, jnp.where(a < 1.0 + lp, dm_out, 0.0)))
        return s * m, dm


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

    def _kernel_rows(self, r):
        # first node floor(xi - 1/2) (exact in floating point), so r = (r0, r0 - 1, r0 - 2) with r0 in [1/2, 3/2]
        # (3/2 at the clamped edge, :meth:`ShapeFunction._cells`): row 0 on the outer piece (zero at 3/2), row 1
        # on the inner one (at |r| = 1/2 both pieces give 1/2 and slope 1), row 2 on the outer piece mirrored
        far, mid, near = rows(r)
        w = jnp.stack([0.5 * (1.5 - far) ** 2, 0.75 - mid * mid, 0.5 * (1.5 + near) ** 2])
        d = jnp.stack([-(1.5 - far), -2.0 * mid, 1.5 + near])
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

    def _kernel_rows(self, r):
        # first node floor(xi) - 1, so r = (r0, r0 - 1, r0 - 2, r0 - 3) with r0 in [1, 2] (2 at the clamped
        # edge, :meth:`ShapeFunction._cells`): rows 0 and 3 on the outer piece, rows 1 and 2 on the inner one,
        # except where |r| = 1 exactly (row 2 for a particle on a node, row 1 at the clamped edge): there the
        # kernel takes the outer piece's value, 1/6, where the inner one's rounds to 2/3 - 1/2
        def inner(r, a):
            return 0.5 * a**3 - a * a + 2.0 / 3.0, 1.5 * a * r - 2.0 * r

        def outer(a, sign):
            return (2.0 - a) ** 3 / 6.0, sign * (2.0 - a) ** 2

        def inner_unless_one(r, a, sign):
            (w_in, d_in), (w_out, d_out), at_one = inner(r, a), outer(a, sign), a == 1.0
            return jnp.where(at_one, w_out, w_in), jnp.where(at_one, d_out, d_in)

        r0, r1, r2, r3 = rows(r)
        (w0, d0), (w3, d3) = outer(r0, -0.5), outer(-r3, 0.5)
        (w1, d1), (w2, d2) = inner_unless_one(r1, r1, -0.5), inner_unless_one(r2, -r2, 0.5)
        return jnp.stack([w0, w1, w2, w3]), jnp.stack([d0, d1, d2, d3])

    def inertia_factor(self) -> float:
        """APIC's D_p = factor * h^2 * I (002): h^2/3 for cubic B-splines."""
        return 1.0 / 3.0


def _parse_ugimp(arg, ppc=None):
    return UGIMP() if ppc is None else UGIMP(ppc=ppc)


register_shape("linear", Linear)
register_shape("ugimp", UGIMP, parse=_parse_ugimp)
register_shape("quadratic", QuadraticBSpline)
register_shape("cubic", CubicBSpline)


def field_stencil(stencil, field, num_nodes: int):
    """The stencil on stacked velocity fields: each particle's node numbers moved to its field's
    copy of the grid, i -> field_p n + i (``field`` (N,) integers 0..M-1; multimaterial mode)."""
    return eqx.tree_at(lambda s: s.index, stencil,
                       stencil.index + field.astype(stencil.index.dtype)[None, :] * num_nodes)
