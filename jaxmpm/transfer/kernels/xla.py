"""The XLA kernel: per-slot values formed from the stencil, one ``lax.scatter_add`` for all of P2G,
gathers one component at a time.  Registered for both backend policies.

Arrays are **planar**, particles last: a per-slot quantity has shape (K, N) or (C, K, N), so the
arithmetic of P2G and G2P runs on contiguous particle vectors (on the CPU XLA vectorises along
them; the per-axis factors of a tensor-product stencil are multiplied out where they are used).

P2G (:meth:`XLAKernel.p2g`) turns each contraction into per-slot values, sums a column's
contractions slot by slot, stacks the columns into one (C, K, N) buffer -- a stage boundary
(``evaluate_once``): on the CPU it is evaluated once, into its own buffer -- and scatters
(node, all columns) rows in ONE ``lax.scatter_add`` (:func:`scatter_planar`; under the CPU policy
its rows are widened to a power of two, :func:`jaxmpm.transfer.backend.scatter_row_width`).

Derivative rules (the structured adjoint, :mod:`jaxmpm.transfer.backend`): the building blocks
below carry JVP rules whose transposes are the cheap adjoint operations -- the scatter's
transpose is a gather of the nodal cotangent evaluated once (:func:`hold_tangent`), a sum over
the stencil transposes to a broadcast, slot products to row products.
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
from jax.custom_derivatives import SymbolicZero

from ...core.errors import check
from ..backend import (
    derivative_rule,
    evaluate_once,
    hold_tangent,
    in_call_context,
    materialise,
    scatter_row_width,
    stencil_sum_form,
    structured,
    xla_layout,
)
from ..contractions import Affine, Divergence, Gradient, Hoop, PerSlot, Weighted, as_terms
from ..shapes import rows
from . import Kernel, register_kernel, shared_read


def _sum_over_stencil(a):
    """sum_k a[..., k, :] for planar a of shape (..., K, N), unrolled over the (4-64) stencil
    slots: K-1 elementwise adds of contiguous particle rows, which XLA fuses with their producers;
    or one reduction over the slot axis, as the backend policy says (:func:`stencil_sum_form`)."""
    if stencil_sum_form() == "reduce":
        return jnp.sum(a, axis=-2)
    first, *others = jnp.unstack(a, axis=-2)
    total = first
    for row in others:
        total = total + row
    return total


_sum_over_stencil_ruled = jax.custom_jvp(_sum_over_stencil)


@_sum_over_stencil_ruled.defjvp
def _sum_over_stencil_jvp(primals, tangents):
    # the same sum as one reduction: its transpose broadcasts the cotangent to the K slots, where
    # that of the unrolled sum pads each row into its own (K, N) array of zeros and adds them up
    (a,), (a_dot,) = primals, tangents
    return _sum_over_stencil_ruled(a), jnp.sum(a_dot, axis=-2)


sum_over_stencil = derivative_rule(_sum_over_stencil, _sum_over_stencil_ruled)


def _per_slot(w, q):
    """w[k, p] q[c, p] (or w[k, p] q[c, k, p]) for slot values w (K, N) and per-particle values q
    (C, N) (or per-slot values q (C, K, N)): planar (C, K, N)."""
    return w[None] * (q if q.ndim == 3 else q[:, None, :])


_per_slot_ruled = jax.custom_jvp(_per_slot)


@partial(_per_slot_ruled.defjvp, symbolic_zeros=True)
def _per_slot_jvp(primals, tangents):
    # Transposes without reductions over the short slot and component axes, which XLA's CPU backend
    # runs slowly.  q's tangent row by row (w_k q_dot_c): the cotangent of q_c is K - 1 adds of row
    # products.  w's tangent whole, times each component (w_dot q_c): the cotangent of w is C - 1 adds
    # of (K, N) products, one fusion.  (Until the eighth session of 2026-11-28 it went row by row too: its
    # cotangent was K C products of (N,) rows, each its own kernel, stacked: 36 kernels a step in mpm88
    # APIC's gradient, and the 2D scenes' gradients compiled 1.1-1.25x as long, benchmarks/README.md.)
    (w, q), (w_dot, q_dot) = primals, tangents

    def slots(a):  # (K, N) -> K rows; a per-slot (K, N) array stays whole (no broadcast needed)
        return [a] if q.ndim == 3 else rows(a)

    def spread(row_terms):  # K row products -> (K, N)
        return row_terms[0] if q.ndim == 3 else jnp.stack(row_terms)

    def per_particle(qc):  # a component (N,) spread over the slots, or a per-slot one (K, N) as it is
        return qc if q.ndim == 3 else qc[None]

    terms = []
    if not isinstance(w_dot, SymbolicZero):
        terms.append([w_dot * per_particle(qc) for qc in rows(q)])
    if not isinstance(q_dot, SymbolicZero):
        terms.append([spread([wk * qd for wk in slots(w)]) for qd in rows(q_dot)])
    out = _per_slot_ruled(w, q)
    if not terms:
        return out, jnp.zeros_like(out)
    return out, jnp.stack([sum(t[c] for t in terms) for c in range(q.shape[0])])


per_slot = derivative_rule(_per_slot, _per_slot_ruled)


def _scatter_rows(index, rows_, num_nodes: int):
    """sum over the (slot, particle) rows ``rows_`` (K N,) or (K N, C) into their nodes
    ``index`` (K, N): (n,) or (n, C).  The one scatter-add of the library; its rows are (node,
    components), widened under the CPU policy (:func:`jaxmpm.transfer.backend.scatter_row_width`)."""
    width = rows_.shape[1] if rows_.ndim == 2 else 1
    padded = scatter_row_width(width)  # backend tuning: zero columns that XLA:CPU adds faster
    if padded > width:
        rows_ = jnp.concatenate([rows_, jnp.zeros((rows_.shape[0], padded - width), rows_.dtype)], axis=1)
    dims = jax.lax.ScatterDimensionNumbers(update_window_dims=tuple(range(1, rows_.ndim)), inserted_window_dims=(0,),
                                           scatter_dims_to_operand_dims=(0,))
    # in-bounds by construction: shape functions clip node numbers onto the grid (jm.Stencil)
    nodal = jax.lax.scatter_add(jnp.zeros((num_nodes,) + rows_.shape[1:], rows_.dtype), index.reshape(-1, 1), rows_,
                                dims, mode=jax.lax.GatherScatterMode.PROMISE_IN_BOUNDS)
    return nodal[:, :width] if padded > width else nodal


_scatter_rows_ruled = jax.custom_jvp(_scatter_rows, nondiff_argnums=(2,))


@_scatter_rows_ruled.defjvp
def _scatter_rows_jvp(num_nodes, primals, tangents):
    # the same scatter of the tangents, behind a stage boundary: in reverse mode the nodal
    # cotangent is evaluated once, then gathered (the scatter's transpose); without it XLA fuses
    # the cotangent's computation into the gather and repeats it for every stencil slot
    # the boundary's predicate reads one node number, not the primal sums: where only the tangent is
    # used (the planar JVP of the rows layout, XLAKernel.p2g), the primal scatter is then left out
    (index, r), (_, r_dot) = primals, tangents
    out = _scatter_rows_ruled(index, r, num_nodes)
    return out, hold_tangent(_scatter_rows(index, r_dot, num_nodes), _node_witness(index, out))


def _node_witness(index, out):
    """The predicate operand of a scatter tangent's boundary: one node number (as the sums' dtype), or the
    sums themselves when there are no stencil slots."""
    return index.reshape(-1)[:1].astype(out.dtype) if index.size else out


scatter_rows = derivative_rule(_scatter_rows, _scatter_rows_ruled)


def scatter_planar(index, contributions, num_nodes: int):
    """sum_p sum_k c[..., k, p] into node ``index[k, p]``: planar ``contributions`` (K, N) -> (n,)
    or (C, K, N) -> (n, C), as (node, components) rows (:func:`scatter_rows`)."""
    if contributions.ndim == 2:
        return scatter_rows(index, contributions.reshape(-1), num_nodes)
    return scatter_columns(index, contributions, num_nodes)


def _scatter_columns(index, contributions, num_nodes: int):
    """Planar ``contributions`` (C, K, N) summed into (n, C), as (node, components) rows."""
    return scatter_rows(index, contributions.reshape(contributions.shape[0], -1).T, num_nodes)


_scatter_columns_ruled = jax.custom_jvp(_scatter_columns, nondiff_argnums=(2,))


@_scatter_columns_ruled.defjvp
def _scatter_columns_jvp(num_nodes, primals, tangents):
    # the tangent as one scalar scatter per component, behind a stage boundary: in reverse mode the
    # nodal cotangent (n, C) is evaluated once and each component gathered on its own, planar (K, N), as
    # the contributions' cotangent.  The rows' scatter transposes to a gather of (K N, C) rows, which every
    # consumer of the planar contributions then reads transposed, element by element
    (index, c), (_, c_dot) = primals, tangents
    out = _scatter_columns_ruled(index, c, num_nodes)
    tangent = jnp.stack([_scatter_rows(index, row.reshape(-1), num_nodes) for row in rows(c_dot)], axis=1)
    return out, hold_tangent(tangent, _node_witness(index, out))


scatter_columns = derivative_rule(_scatter_columns, _scatter_columns_ruled)


def nodal_values(stencil, u, hold: bool = True):
    """u_i at every stencil slot: (n,) -> (K, N), (n, C) -> a list of C arrays (K, N).  One gather
    of scalars per component (from the transposed (C, n) nodal array): on CPU this is faster than
    gathering (K N, C) rows and transposing them, and consumers read each component directly.
    ``hold``: a vector field's gathered components are evaluated once, into their own buffers, before
    their consumers (a stage boundary); otherwise XLA may fuse each gather into every consumer
    (backend tuning: :class:`XLAKernel`'s ``hold_gathers``).  Inside a G2P's
    :func:`jaxmpm.transfer.kernels.shared_reads` a vector field is read once, the grid's v, a and v~
    together."""
    index = stencil.index  # on the grid (shape functions clip it), so no bounds handling
    if u.ndim == 1:
        return materialise(u).at[index].get(mode="promise_in_bounds")

    def held(values):
        return materialise(values) if hold else values

    def read_together(fields):  # one gather of all the fields' components, split per field
        values = iter(gather_rows(index, [f.T for f in fields]))
        return [held([next(values) for _ in range(f.shape[1])]) for f in fields]

    return shared_read(hold, index, u, lambda: held(gather_components(index, u)), read_together)


def _gather_rows(index, planar):
    """[p[c] at every slot, for each planar nodal array p (C_f, n) of the list ``planar``]: one gather
    of scalars per row.  Each array is evaluated once first: XLA would otherwise fuse its whole
    computation (v = p/m, boundary conditions) into the gather and repeat it for every slot."""
    return [uc.at[index].get(mode="promise_in_bounds") for p in planar for uc in rows(materialise(p))]


_gather_rows_ruled = jax.custom_jvp(_gather_rows)


@_gather_rows_ruled.defjvp
def _gather_rows_jvp(primals, tangents):
    # the tangent as one gather of (n, C) rows, all the arrays' components side by side: its transpose
    # is one scatter-add of rows, where the components' own gathers transpose to C scalar scatters
    index, planar = primals
    _, planar_dot = tangents
    nodal_dot = jnp.concatenate([p.T for p in planar_dot], axis=1)  # (n, C)
    gathered = nodal_dot.at[index].get(mode="promise_in_bounds")  # (K, N, C)
    # the components as one split, whose transpose is one concatenation (indexing each would transpose to
    # C zero-padded (K, N, C) arrays added up)
    return _gather_rows_ruled(index, planar), list(jnp.unstack(gathered, axis=-1))


gather_rows = derivative_rule(_gather_rows, _gather_rows_ruled)


def gather_components(index, u):
    """[u[:, c] at every slot]: one gather of scalars per component, from the transposed (C, n) nodal
    array (:func:`gather_rows`)."""
    return gather_rows(index, [u.T])


def gather_planar(stencil, u, hold: bool = True):
    """(S u)_p for nodal ``u`` (n,) or (n, C), planar result (N,) or (C, N)."""
    values = nodal_values(stencil, u, hold)
    if u.ndim == 1:
        return sum_over_stencil(stencil.weight * values)
    w = stencil.weight
    return jnp.stack([sum_over_stencil(w * vc) for vc in values])


def _to_particle_major(planar):
    """(C..., N) -> (N, C...), evaluated first: otherwise XLA moves the whole planar computation
    into the transpose, where it runs element by element instead of on particle vectors."""
    return jnp.moveaxis(materialise(planar), -1, 0)


_to_particle_major_ruled = jax.custom_jvp(_to_particle_major)


@_to_particle_major_ruled.defjvp
def _to_particle_major_jvp(primals, tangents):
    # the tangent behind a stage boundary, planar: in reverse mode the cotangent of a G2P result is
    # evaluated once, laid out (C..., N), before the per-slot products that read it; without it XLA
    # fuses the particle update's whole cotangent into those products and repeats it for every slot
    (planar,), (planar_dot,) = primals, tangents
    return _to_particle_major_ruled(planar), jnp.moveaxis(hold_tangent(planar_dot, planar.reshape(-1)[:1]), -1, 0)


to_particle_major = derivative_rule(_to_particle_major, _to_particle_major_ruled)


# ------------------------------------------------------------------ per-slot values of a contraction
def _slot_values(stencil, contraction):
    """The per-slot values c_pi of one contraction, planar (K, N) or (C, K, N)."""
    q = contraction.value
    if isinstance(contraction, Weighted):
        return stencil.weight * q[None, :] if q.ndim == 1 else per_slot(stencil.weight, q.T)
    if isinstance(contraction, Gradient):  # q_p G_pi, (D, K, N)
        return q[None, None, :] * stencil.gradient
    if isinstance(contraction, Divergence):  # sum_b q_p[a, b] G_pi[b], (C, K, N)
        g = rows(stencil.gradient)
        planar = [rows(t) for t in rows(materialise(jnp.moveaxis(q, 0, -1))[:, :, None, :])]  # (C, D, 1, N)
        return jnp.stack([sum(planar[a][b] * g[b] for b in range(len(g))) for a in range(len(planar))])
    if isinstance(contraction, Affine):  # S_pi sum_b q_p[a, b] (x_i - X_p)[b], (C, K, N)
        return per_slot(stencil.weight, _planar_matvec(materialise(jnp.moveaxis(q, 0, -1)), stencil.offset))
    if isinstance(contraction, Hoop):  # T_pi q_p (001 eq. 116)
        hoop = stencil.hoop_view().weight
        return hoop * q if q.ndim == 1 else per_slot(hoop, materialise(q.T))
    if isinstance(contraction, PerSlot):
        return q
    raise TypeError(f"P2G: {type(contraction).__name__} is not a contraction the XLA kernel knows")


def _planar_matvec(A, x):
    """A_p x_pk for planar A (C, D, N) and slot vectors x (D, K, N): (C, K, N)."""
    A, x = [rows(r) for r in rows(A)], rows(x)
    return jnp.stack([sum(Ai[j][None] * x[j] for j in range(len(x))) for Ai in A])


def _column(stencil, column):
    """A column's per-slot values: its contractions' values summed slot by slot."""
    terms = [_slot_values(stencil, c) for c in as_terms(column)]
    return sum(terms[1:], terms[0])


# ------------------------------------------------------------------ P2G as rows of per-particle coefficients


def _weight_basis(stencil, kinds):
    """The per-slot weights (K, N) of the contraction kinds used: S, G_d, S (x_i - X_p)_d, T."""
    out = {}
    if "S" in kinds or "A" in kinds:
        out["S"] = stencil.weight
    if "G" in kinds:
        out.update({("G", d): g for d, g in enumerate(rows(stencil.gradient))})
    if "A" in kinds:
        out.update({("A", d): out["S"] * o for d, o in enumerate(rows(stencil.offset))})
    if "T" in kinds:
        out["T"] = stencil.hoop_view().weight
    return out


def _coefficients(contraction, dim: int) -> dict:
    """{weight key: per-particle coefficients (N, c)} of one contraction: its per-slot values are
    sum over the keys of weight * coefficients (the rows formulation of :class:`XLAKernel`)."""
    q = contraction.value
    if isinstance(contraction, Weighted):
        return {"S": q[:, None] if q.ndim == 1 else q}
    if isinstance(contraction, Hoop):
        return {"T": q[:, None] if q.ndim == 1 else q}
    if isinstance(contraction, Gradient):  # column d: q G_d
        eye = jnp.eye(dim, dtype=q.dtype)
        return {("G", d): q[:, None] * eye[d][None, :] for d in range(dim)}
    key = "G" if isinstance(contraction, Divergence) else "A"  # column c: sum_d q[c, d] W_d
    return {(key, d): q[:, :, d] for d in range(q.shape[-1])}


class XLAKernel(Kernel):
    """Per-slot values from the stencil, one ``lax.scatter_add`` for P2G, component-wise gathers
    for G2P (module docstring).  ``layout`` picks how P2G forms its (slot, particle) rows:

    * ``"planar"``: each column's per-slot values, (C, K, N) stacked -- a concatenation of
      per-slot arrays -- and transposed to rows;
    * ``"rows"``: rows[k, p, :] = sum_j W_j[k, p] Q_j[p, :] over the weight basis W (S, G_d,
      S (x_i - X_p)_d, T) with per-particle coefficients Q_j (N, C) -- the concatenation is of
      per-particle arrays, K times smaller, and the rows are one elementwise expression that
      XLA can fuse into the scatter (more multiplies: a coefficient is zero where its kind does not
      reach a column).  :class:`PerSlot` columns are added as given.  The rows are a stage
      boundary (``evaluate_once``): on the CPU evaluated once, into the buffer the scatter reads,
      each row's C columns side by side (no transpose of planar columns); on a GPU inline, so XLA
      may fuse them into the scatter.

    ``tangent_layout`` ("planar" or "rows"): how P2G's derivatives are formed when ``layout`` is
    "rows": with "planar" the values come from the rows and their JVP from the planar layout, whose
    transpose (the reverse pass) is the cheap one; the rows' broadcasts transpose to reductions over
    short axes (gradients at 0.39-0.52x on the CPU).  Under ``adjoint="autodiff"`` (the reference
    path, no custom rules) "planar" runs the planar layout, differentiated as written.

    ``hold_gathers``: G2P's gathered nodal values (one (K, N) array per component) are evaluated
    once before the products that read them (True), or left for XLA to fuse into each product
    (False: no per-slot buffer is written).

    All three default to ``"auto"``: the backend's table for the policy and the precision traced
    (:data:`jaxmpm.transfer.backend.XLA_LAYOUT`; on the CPU: float32 planar with held gathers,
    float64 rows with planar derivatives and free gathers, its per-slot buffers leaving the cache;
    on a GPU: rows)."""

    layout: str = "auto"
    tangent_layout: str = "auto"
    hold_gathers: bool | str = "auto"

    def __check_init__(self):
        check(self.layout in ("auto", "planar", "rows"),
              f"XLAKernel: layout = {self.layout!r}; choose 'auto', 'planar' or 'rows'")
        check(self.tangent_layout in ("auto", "planar", "rows"),
              f"XLAKernel: tangent_layout = {self.tangent_layout!r}; choose 'auto', 'planar' or 'rows'")
        check(self.hold_gathers in ("auto", True, False),
              f"XLAKernel: hold_gathers = {self.hold_gathers!r}; choose 'auto', True or False")

    def _resolved(self, stencil) -> tuple:
        """(layout, tangent_layout, hold_gathers) for ``stencil``'s precision, "auto" read from the table."""
        given = (self.layout, self.tangent_layout, self.hold_gathers)
        return tuple(t if g == "auto" else g for g, t in zip(given, xla_layout(stencil.dtype)))

    def _hold(self, stencil) -> bool:
        return self._resolved(stencil)[2]

    def p2g(self, stencil, columns: dict, num_nodes: int) -> dict:
        layout, tangent_layout, _ = self._resolved(stencil)
        if layout == "planar":
            return self._p2g_planar(stencil, columns, num_nodes)
        if tangent_layout == "rows":
            return self._p2g_rows(stencil, columns, num_nodes)
        if not structured():  # the reference adjoint differentiates the planar code as written
            return self._p2g_planar(stencil, columns, num_nodes)

        # the values by rows, their derivatives by the planar layout, whose transpose is the cheap one
        # (the rows' broadcasts transpose to reductions over short axes: gradients at 0.39-0.52x)
        @jax.custom_jvp
        def rows_with_planar_tangents(stencil, columns):
            return self._p2g_rows(stencil, columns, num_nodes)

        @rows_with_planar_tangents.defjvp
        def _(primals, tangents):
            _, out_dot = jax.jvp(lambda s, c: self._p2g_planar(s, c, num_nodes), primals, tangents)
            return rows_with_planar_tangents(*primals), out_dot

        return in_call_context(rows_with_planar_tangents)(stencil, columns)

    def _p2g_planar(self, stencil, columns: dict, num_nodes: int) -> dict:
        layout = {}  # name -> (width, scalar), in the order the columns are stacked

        def stacked(stencil, columns):
            per_slot_columns = {name: _column(stencil, column) for name, column in columns.items()}
            layout.clear()
            layout.update({name: (1 if c.ndim == 2 else c.shape[0], c.ndim == 2)
                           for name, c in per_slot_columns.items()})
            return jnp.concatenate([c[None] if c.ndim == 2 else c for c in per_slot_columns.values()])

        nodal = scatter_planar(stencil.index, evaluate_once(stacked, stencil, columns), num_nodes)
        out, start = {}, 0
        for name, (width, scalar) in layout.items():
            out[name] = nodal[:, start] if scalar else nodal[:, start:start + width]
            start += width
        return out

    def _p2g_rows(self, stencil, columns: dict, num_nodes: int) -> dict:
        dim = stencil.dim
        widths, names = {}, list(columns)
        for name, column in columns.items():
            shapes = {c.width(dim) for c in as_terms(column)}
            assert len(shapes) == 1, f"P2G column {name!r} sums contractions of different widths {shapes}"
            widths[name] = shapes.pop()
        total = sum(max(1, w[0] if w else 1) for w in widths.values())
        padded = scatter_row_width(total)  # backend tuning: zero coefficients are free here

        def rows_of(stencil, columns):
            blocks, per_slot = {}, []  # weight key -> {column: coefficients (N, c)}
            for name, column in columns.items():
                for c in as_terms(column):
                    if isinstance(c, PerSlot):
                        per_slot.append((name, c.value))
                        continue
                    for key, coef in _coefficients(c, dim).items():
                        block = blocks.setdefault(key, {})
                        block[name] = block[name] + coef if name in block else coef
            kinds = {k if isinstance(k, str) else k[0] for k in blocks}
            basis = _weight_basis(stencil, kinds)
            n = stencil.num_particles
            dtype = next(iter(basis.values())).dtype if basis else per_slot[0][1].dtype
            out = None
            for key, block in blocks.items():
                pieces = [block.get(name, None) for name in names]
                pieces = [p if p is not None else jnp.zeros((n, max(1, widths[nm][0] if widths[nm] else 1)), dtype)
                          for p, nm in zip(pieces, names)]
                if padded > total:
                    pieces.append(jnp.zeros((n, padded - total), dtype))
                Q = jnp.concatenate(pieces, axis=1)  # (N, C): per particle
                term = basis[key][:, :, None] * Q[None, :, :]
                out = term if out is None else out + term
            for name, values in per_slot:  # (K, N) or (c, K, N): placed in the name's columns
                start = sum(max(1, widths[nm][0] if widths[nm] else 1) for nm in names[:names.index(name)])
                v = values[..., None] if values.ndim == 2 else jnp.moveaxis(values, 0, -1)
                v = jnp.pad(v, ((0, 0), (0, 0), (start, padded - start - v.shape[-1])))
                out = v if out is None else out + v
            return out.reshape(-1, padded)

        nodal = scatter_rows(stencil.index, evaluate_once(rows_of, stencil, columns), num_nodes)
        out, start = {}, 0
        for name in names:
            w = widths[name]
            out[name] = nodal[:, start] if not w else nodal[:, start:start + w[0]]
            start += w[0] if w else 1
        return out

    def gather(self, stencil, u):
        Su = gather_planar(stencil, u, self._hold(stencil))
        return Su if u.ndim == 1 else to_particle_major(Su)

    def velocity_gradient(self, stencil, v):
        values = nodal_values(stencil, v, self._hold(stencil))  # D arrays (K, N)
        g = rows(stencil.gradient)
        d = len(g)
        planar = jnp.stack([jnp.stack([sum_over_stencil(values[a] * g[b]) for b in range(d)]) for a in range(d)])
        return to_particle_major(planar)

    def scalar_gradient(self, stencil, u):
        values = nodal_values(stencil, u)  # (K, N)
        g = rows(stencil.gradient)
        return to_particle_major(jnp.stack([sum_over_stencil(values * g[b]) for b in range(len(g))]))

    def affine_moment(self, stencil, v):
        w, a, b = stencil.weight, nodal_values(stencil, v, self._hold(stencil)), rows(stencil.offset)
        planar = jnp.stack([jnp.stack([sum_over_stencil(w * a[i] * b[j]) for j in range(len(b))])
                            for i in range(len(a))])
        return to_particle_major(planar)


# One kernel for both policies, its options "auto": the backend's table (XLA_LAYOUT in
# jaxmpm/transfer/backend.py, from benchmarks/p2g_layout.py) picks the layouts by policy and precision.
register_kernel("cpu", XLAKernel())
register_kernel("gpu", XLAKernel())
