"""The Pallas kernel: P2G and G2P as fused kernels over blocks of particles, with atomic adds.

P2G in the rows formulation of :class:`~jaxmpm.transfer.kernels.xla.XLAKernel` (``layout="rows"``):
every contraction is a sum over a small *weight basis* W_j (K, N) -- S, G_d, S (x_i - X_p)_d, T,
or the per-slot values of a :class:`PerSlot` -- times per-particle coefficients.  The kernel gets
the node index (K, N), the basis W (J, K, N) and one coefficient row q_r (N,) per nonzero (key j,
nodal column c) pair r, and computes

    nodal[i, c] = sum_p sum_k [index[k, p] = i] sum_{r = (j, c)} W[j, k, p] q_r[p]

in ONE Pallas kernel: each program instance takes a block of B particles, forms the values of
every slot and column in registers and adds them into the nodal output with atomic adds; no
(K, N, C) array is materialised.  With ``reduce=True`` the particles of a block that touch the
same nodes (the same cell, for a tensor-product stencil) are summed first and only the first of
them adds: fewer atomics on the same address, the lever for dense 2D (10-200 particles per cell,
../shared/gpu/README.md), effective when particles are sorted by cell.

The G2P side is two more kernels of the same shape: ``gather`` (out[r, p] = sum_k W[j, k, p]
u[index[k, p], c] for pairs r = (j, c): interpolation, velocity gradient, scalar gradient, affine
moment) and ``contract`` (out[j, k, p] = sum_{r = (j, c)} q_r[p] u[index[k, p], c]: a gather
contracted with coefficients).  The three are bilinear and closed under transposition, which gives
every derivative rule:

=========================  =================================  ==================================
operation                  transpose w.r.t. its first operand  w.r.t. its second
=========================  =================================  ==================================
scatter(index, W, q) (P2G)  contract(index, q, ct)  (W)         gather(index, W, ct)  (q)
gather(index, W, u)         contract(index, ct, u)  (W)         scatter(index, W, ct) (u)
contract(index, q, u)       gather(index, ct, u)    (q)         scatter(index, ct, q) (u)
=========================  =================================  ==================================

They are JAX primitives with JVP (the sum of the two bilinear terms), transpose and batching rules,
so ``jax.grad`` (any order), ``jax.jvp``, ``jax.vmap`` (ensembles: the batch is folded into the
particles, each member on its own copy of the grid) and the XPIC/FMPM series all run through these
kernels.  Positions reach P2G and G2P through the basis W (built by XLA from the stencil), whose
cotangent is the ``contract`` kernel.

With a tensor-product stencil (``factors=True``, the default) the forward kernels read the stencil's
per-axis factors instead of W and form the slot weights in registers (``scatter_factors_p``,
``gather_factors_p``; 3 D K1 values per particle instead of up to (1 + 2 D) K): on an H100 the basis
path lost to the XLA kernel (3D 0.77x, 2D 0.55-0.73x), where the fused prototype, which formed its
weights in the kernel, had run 3x faster.  Their derivatives are the basis path's (a JVP through
W = _factor_basis(index, F)), so the reverse pass forms W once and the forward pass never does.  On an
H100 (2026-11-27, second lease) they beat the XLA kernel in 3D when P2G folds the force into the
momentum (APIC at 1M particles: 1.13x), and lose with the force apart (FLIP, XPIC, FMPM: 7 numbers
per slot instead of 4) and in dense 2D (0.82-0.91x): jaxmpm.transfer.backend.KERNEL_TABLE.  Two
options, measured and left off: ``planar`` (the nodal arrays addressed column by column) and
``unroll`` (the slot loop unrolled) lost 12-41% in 3D at 1M.

Interpret mode (``interpret=None``: when the program is compiled for the CPU, chosen per platform
when the primitives are lowered) runs the same kernels through Pallas' interpreter, where the tests
compare them with the XLA kernel.  One difference: Pallas' interpreter (jax 0.10) applies an atomic
add of a vector whose indices repeat as a ``set`` -- only one of the repeated lanes counts, where a
GPU adds them all -- so in interpret mode :func:`_add_at` adds with a scatter-add into the output
(what the GPU's atomics compute).  On a GPU the kernels run on Pallas' Triton backend (the one of
the measurements in ../shared/gpu/README.md; jax 0.10's default GPU lowering, Mosaic GPU, has no
atomic adds) with ``jax.experimental.pallas.triton.atomic_add``; the tests lower them for CUDA on
the CPU, so what Triton cannot lower is caught without a device, but they have not run on one.
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
from jax.experimental import pallas as pl
from jax.experimental.pallas import triton as plgpu
from jax.extend.core import Primitive
from jax.interpreters import ad, batching, mlir

from ..contractions import Affine, Divergence, Gradient, Hoop, PerSlot, Weighted, as_terms
from ..shapes import AxisymmetricStencil, TensorStencil, rows
from . import Kernel
from .xla import _weight_basis

BLOCK = 128  # particles per program: 128 particles / 4 warps was the best 3D block on an H100 (spike)
WARPS = 4


def _triton(interpret: bool):
    """The compiler parameters that put a kernel on Pallas' Triton backend (the one measured, and
    the one with atomic adds: jax 0.10's default GPU lowering, Mosaic GPU, has none), 4 warps."""
    return None if interpret else plgpu.CompilerParams(num_warps=WARPS)


# ------------------------------------------------------------------ the three Pallas kernels
def _padded(a, multiple: int, value=0):
    """``a`` with its last (particle) axis padded to a multiple of ``multiple``: padded particles
    carry zero weights and coefficients, so they add nothing."""
    extra = -a.shape[-1] % multiple
    return a if extra == 0 else jnp.pad(a, [(0, 0)] * (a.ndim - 1) + [(0, extra)], constant_values=value)


def _add_at(ref, indices, values, mask, interpret: bool):
    """ref[indices[m]] += values[m] for each of the vectors, lanes where ``mask`` is false left out:
    atomic adds on a GPU; in interpret mode one scatter-add (see the module docstring)."""
    if interpret:
        if mask is not None:
            values = [jnp.where(mask, v, 0) for v in values]
        ref[...] = ref[...].at[jnp.concatenate(indices)].add(jnp.concatenate(values))
        return
    for index, value in zip(indices, values):
        plgpu.atomic_add(ref, (index,), value, mask=mask)


def _address(node, col, num_nodes: int, width: int, planar: bool):
    """Where nodal value (node, col) lives in a kernel's flat nodal array: node-major (``node width + col``,
    the (n, C) array's own order) or, with ``planar``, column-major (``col n + node``: the (C, n) array's, so
    the lanes of a block that address neighbouring nodes address neighbouring words of one column)."""
    return col * num_nodes + node if planar else node * width + col


def _flat_nodal(u, planar: bool):
    """The nodal array (n, C) flattened in the order :func:`_address` reads it."""
    return (u.T if planar else u).reshape(-1)


def _over_slots(K: int, slot, carry, unroll: bool):
    """``slot(k, carry)`` for k = 0 .. K-1: a loop in the kernel (its size that of one slot), or, with
    ``unroll``, K copies with k a Python int (static addresses into the blocks, the per-axis digits of
    a factor stencil's slot folded)."""
    if not unroll:
        return jax.lax.fori_loop(0, K, slot, carry)
    for k in range(K):
        carry = slot(k, carry)
    return carry


def _same_nodes(index_ref, size: int):
    """(same (B, B), leader (B,)) for a block: same[p, q] = 1 where particles p and q touch the same
    node in every slot (the same cell of a tensor-product stencil); leader[p]: no earlier particle
    of the block does.  sum_q same[p, q] v[q] is then the block's sum over p's group."""
    index = index_ref[0, :]
    same = index[:, None] == index[None, :]
    for k in range(1, size):
        index = index_ref[k, :]
        same = same & (index[:, None] == index[None, :])
    lanes = jax.lax.broadcasted_iota(jnp.int32, same.shape, 0)
    earlier = jax.lax.broadcasted_iota(jnp.int32, same.shape, 1) < lanes
    leader = jnp.sum((same & earlier).astype(jnp.int32), axis=1) == 0  # (Triton lowers no reduce_or)
    return same, leader


def _basis_source(W):
    """The weights of the slots read from the basis W (J, K, N): (array, its leading block shape,
    weights(ref, k, js) -> {j: (B,) weights of slot k})."""
    return W, W.shape[:2], lambda ref, k, js: {j: ref[j, k, :] for j in js}


def _scatter_pallas(index, source, Q, *, pairs, num_nodes, width, block, reduce, interpret, planar=False,
                    unroll=False):
    """nodal (num_nodes, width) = sum_p sum_k sum_{r = (j, c)} W[j, k, p] Q[r, p] at (index[k, p], c),
    the weights W from ``source`` (:func:`_basis_source`, :func:`_factor_source`)."""
    K = index.shape[0]
    A, lead, weights = source
    dtype = jnp.result_type(A, Q)
    index, A, Q = _padded(index, block), _padded(A.astype(dtype), block), _padded(Q.astype(dtype), block)
    by_column = [[(r, j) for r, (j, c) in enumerate(pairs) if c == col] for col in range(width)]
    used = sorted({j for j, _ in pairs})

    def kernel(index_ref, a_ref, q_ref, _, out_ref):
        q = [q_ref[r, :] for r in range(len(pairs))]
        if reduce:
            same, leader = _same_nodes(index_ref, K)
            same = same.astype(dtype)

        def slot(k, carry):  # a loop over the slots (not unrolled: the kernel's size is that of one slot)
            node = index_ref[k, :]
            w = weights(a_ref, k, used)
            indices, values = [], []
            for col, terms in enumerate(by_column):
                if not terms:
                    continue
                value = w[terms[0][1]] * q[terms[0][0]]
                for r, j in terms[1:]:
                    value = value + w[j] * q[r]
                if reduce:  # the group's sum, added once by its leader
                    value = jnp.sum(same * value[None, :], axis=1)
                indices.append(_address(node, col, num_nodes, width, planar))
                values.append(value)
            _add_at(out_ref, indices, values, leader if reduce else None, interpret)
            return carry

        _over_slots(K, slot, 0, unroll)

    blocks = index.shape[-1] // block
    nodal = pl.pallas_call(
        kernel, grid=(blocks,),
        in_specs=[pl.BlockSpec((K, block), lambda b: (0, b)), _particle_blocks(lead, block),
                  pl.BlockSpec((len(pairs), block), lambda b: (0, b)), pl.BlockSpec(memory_space=pl.ANY)],
        out_specs=pl.BlockSpec(memory_space=pl.ANY),
        out_shape=jax.ShapeDtypeStruct((num_nodes * width,), dtype),
        # the atomics add into the output: it starts as the zeros aliased to it (interpret mode
        # reads an output that is not aliased to an input as NaN)
        input_output_aliases={3: 0}, interpret=interpret, compiler_params=_triton(interpret),
    )(index, A, Q, jnp.zeros((num_nodes * width,), dtype))
    return nodal.reshape(width, num_nodes).T if planar else nodal.reshape(num_nodes, width)


def _particle_blocks(lead: tuple, block: int):
    """The BlockSpec of an array (*lead, N) taken ``block`` particles at a time, whole along ``lead``."""
    return pl.BlockSpec(tuple(lead) + (block,), lambda b: (0,) * len(lead) + (b,))


def _gather_pallas(index, source, u, *, pairs, block, interpret, planar=False, unroll=False):
    """(P, N): out[r, p] = sum_k W[j, k, p] u[index[k, p], c] for r = (j, c), W from ``source``."""
    K, N = index.shape
    A, lead, weights = source
    width = u.shape[1]
    dtype = jnp.result_type(A, u)
    index, A = _padded(index, block), _padded(A.astype(dtype), block)
    used = sorted({j for j, _ in pairs})

    num_nodes = u.shape[0]

    def kernel(index_ref, a_ref, u_ref, out_ref):
        def slot(k, total):
            node = index_ref[k, :]
            w = weights(a_ref, k, used)
            values = {c: u_ref[_address(node, c, num_nodes, width, planar)] for c in {c for _, c in pairs}}
            return tuple(t + w[j] * values[c] for t, (j, c) in zip(total, pairs))

        zero = jnp.zeros((block,), dtype)
        total = _over_slots(K, slot, (zero,) * len(pairs), unroll)
        for r in range(len(pairs)):
            out_ref[r, :] = total[r]

    out = pl.pallas_call(
        kernel, grid=(index.shape[-1] // block,),
        in_specs=[pl.BlockSpec((K, block), lambda b: (0, b)), _particle_blocks(lead, block),
                  pl.BlockSpec(memory_space=pl.ANY)],
        out_specs=pl.BlockSpec((len(pairs), block), lambda b: (0, b)),
        out_shape=jax.ShapeDtypeStruct((len(pairs), index.shape[-1]), dtype), interpret=interpret,
        compiler_params=_triton(interpret),
    )(index, A, _flat_nodal(u.astype(dtype), planar))
    return out[:, :N]


def _contract_pallas(index, Q, u, *, pairs, num_keys, block, interpret, planar=False, unroll=False):
    """(J, K, N): out[j, k, p] = sum_{r = (j, c)} Q[r, p] u[index[k, p], c]."""
    K, N = index.shape
    width = u.shape[1]
    dtype = jnp.result_type(Q, u)
    index, Q = _padded(index, block), _padded(Q.astype(dtype), block)

    num_nodes = u.shape[0]

    def kernel(index_ref, q_ref, u_ref, out_ref):
        q = [q_ref[r, :] for r in range(len(pairs))]

        def slot(k, carry):
            node = index_ref[k, :]
            values = {c: u_ref[_address(node, c, num_nodes, width, planar)] for c in {c for _, c in pairs}}
            for j in range(num_keys):
                terms = [q[r] * values[c] for r, (jj, c) in enumerate(pairs) if jj == j]
                out_ref[j, k, :] = sum(terms[1:], terms[0]) if terms else jnp.zeros((block,), dtype)
            return carry

        _over_slots(K, slot, 0, unroll)

    out = pl.pallas_call(
        kernel, grid=(index.shape[-1] // block,),
        in_specs=[pl.BlockSpec((K, block), lambda b: (0, b)), pl.BlockSpec((len(pairs), block), lambda b: (0, b)),
                  pl.BlockSpec(memory_space=pl.ANY)],
        out_specs=pl.BlockSpec((num_keys, K, block), lambda b: (0, 0, b)),
        out_shape=jax.ShapeDtypeStruct((num_keys, K, index.shape[-1]), dtype), interpret=interpret,
        compiler_params=_triton(interpret),
    )(index, Q, _flat_nodal(u.astype(dtype), planar))
    return out[..., :N]


# ------------------------------------------------------------------ the same kernels from the per-axis factors
# A tensor-product stencil (jaxmpm.transfer.shapes.TensorStencil) holds per axis a the factors
# w_a, dw_a, dx_a (K1, N); slot k = (k_0, ..., k_{D-1}) in C order (axis 0 slowest) has
#     S = prod_a w_a[k_a],   G_d = dw_d[k_d] prod_{a != d} w_a[k_a],   S (x_i - X_p)_d = S dx_d[k_d].
# The kernels below read those factors, F = (w, dw, dx) as (3, D, K1, N): 3 D K1 values per particle
# (27 in 3D quadratic) where the basis W holds up to (1 + 2 D) K (189), and form the slot weights in
# registers, as the fused prototype did (../shared/gpu/pallas_spike.py).
def _kinds(keys) -> set:
    """The weight kinds of basis keys: "S", "G" (from ("G", d)), "A", "T", "P"."""
    return {key if isinstance(key, str) else key[0] for key in keys}


def _slot_weights(f_ref, k, keys, dim: int, k1: int) -> dict:
    """{key: (B,) weights of slot ``k``} for the keys "S", ("G", d), ("A", d) from the factor ref."""
    digits = []
    if isinstance(k, int):  # an unrolled slot (_over_slots): its digits known when tracing
        for _ in range(dim):  # k = sum_a k_a K1^(D - 1 - a): the last axis varies fastest
            k, digit = divmod(k, k1)
            digits.append(digit)
    else:
        rest, base = jnp.asarray(k, jnp.int32), jnp.full((), k1, jnp.int32)
        for _ in range(dim):
            digits.append(jax.lax.rem(rest, base))  # int32 operands: Triton's lowering wants one type
            rest = jax.lax.div(rest, base)
    digits = digits[::-1]
    kinds = _kinds(keys)
    w = [f_ref[0, a, digits[a], :] for a in range(dim)]
    dw = [f_ref[1, a, digits[a], :] for a in range(dim)] if "G" in kinds else None
    dx = [f_ref[2, a, digits[a], :] for a in range(dim)] if "A" in kinds else None
    S = w[0]
    for a in range(1, dim):
        S = S * w[a]
    out = {}
    for key in keys:
        if key == "S":
            out[key] = S
        elif key[0] == "G":
            g = dw[0] if key[1] == 0 else w[0]
            for a in range(1, dim):
                g = g * (dw[a] if a == key[1] else w[a])
            out[key] = g
        else:  # ("A", d)
            out[key] = S * dx[key[1]]
    return out


def _factor_source(F, keys):
    """The weights of the slots formed from the factors F (3, D, K1, N) (:func:`_slot_weights`), for
    the basis keys ``keys`` (a source as :func:`_basis_source`'s)."""
    _, dim, k1, _ = F.shape

    def weights(ref, k, js):
        by_key = _slot_weights(ref, k, [keys[j] for j in js], dim, k1)
        return {j: by_key[keys[j]] for j in js}

    return F, F.shape[:3], weights


def _factor_basis(index, F, keys):
    """The basis W (J, K, N) of ``keys`` from the factors F (3, D, K1, N): the tensor-product
    stencil they are rebuilt into, through :func:`~jaxmpm.transfer.kernels.xla._weight_basis`, as the
    basis path forms it (the derivative rules of the factor kernels differentiate this)."""
    basis = _weight_basis(TensorStencil(index, F[0], F[1], F[2]), _kinds(keys))
    return jnp.stack([basis[k] for k in keys])


# ------------------------------------------------------------------ the primitives and their rules
scatter_p = Primitive("jaxmpm_pallas_scatter")  # (index, W, Q) -> (n, C)
gather_p = Primitive("jaxmpm_pallas_gather")  # (index, W, u) -> (P, N)
contract_p = Primitive("jaxmpm_pallas_contract")  # (index, Q, u) -> (J, K, N)


def _scatter(index, W, Q, *, pairs, num_nodes, width, **options):
    return scatter_p.bind(index, W, Q, pairs=pairs, num_nodes=num_nodes, width=width, **options)


def _gather(index, W, u, *, pairs, **options):
    return gather_p.bind(index, W, u, pairs=pairs, **options)


def _contract(index, Q, u, *, pairs, num_keys, **options):
    return contract_p.bind(index, Q, u, pairs=pairs, num_keys=num_keys, **options)


def _dtype(*avals):
    return jnp.result_type(*[a.dtype for a in avals])


scatter_p.def_abstract_eval(lambda index, W, Q, *, num_nodes, width, **_: jax.core.ShapedArray(
    (num_nodes, width), _dtype(W, Q)))
gather_p.def_abstract_eval(lambda index, W, u, *, pairs, **_: jax.core.ShapedArray(
    (len(pairs), index.shape[1]), _dtype(W, u)))
contract_p.def_abstract_eval(lambda index, Q, u, *, num_keys, **_: jax.core.ShapedArray(
    (num_keys,) + index.shape, _dtype(Q, u)))


def _scatter_impl(index, W, Q, *, reduce, interpret, on_cpu=None, **params):
    return _scatter_pallas(index, _basis_source(W), Q, reduce=reduce, interpret=_interpret(interpret, on_cpu),
                           **params)


def _gather_impl(index, W, u, *, reduce, interpret, on_cpu=None, **params):
    del reduce
    return _gather_pallas(index, _basis_source(W), u, interpret=_interpret(interpret, on_cpu), **params)


def _contract_impl(index, Q, u, *, reduce, interpret, on_cpu=None, **params):
    del reduce
    return _contract_pallas(index, Q, u, interpret=_interpret(interpret, on_cpu), **params)


def _interpret(interpret, on_cpu) -> bool:
    """Interpret mode as asked; None: when the program is compiled for the CPU (``on_cpu``, from
    the platform being lowered for), else when the default backend is the CPU."""
    if interpret is not None:
        return interpret
    return jax.default_backend() == "cpu" if on_cpu is None else on_cpu


def _register(primitive, impl) -> None:
    """``impl`` as the primitive's evaluation and lowering: interpret mode when lowered for the CPU,
    Triton when lowered for a GPU (:func:`_interpret`)."""
    primitive.def_impl(impl)
    mlir.register_lowering(primitive, mlir.lower_fun(impl, multiple_results=False))
    mlir.register_lowering(primitive, mlir.lower_fun(partial(impl, on_cpu=True), multiple_results=False),
                           platform="cpu")
    for platform in ("cuda", "rocm"):
        mlir.register_lowering(primitive, mlir.lower_fun(partial(impl, on_cpu=False), multiple_results=False),
                               platform=platform)


for _p, _impl in ((scatter_p, _scatter_impl), (gather_p, _gather_impl), (contract_p, _contract_impl)):
    _register(_p, _impl)


def _bilinear_jvp(primitive):
    """JVP of a primitive bilinear in its two float operands (the index is an integer)."""

    def jvp(primals, tangents, **params):
        index, a, b = primals
        _, a_dot, b_dot = tangents
        out = primitive.bind(index, a, b, **params)
        terms = []
        if type(a_dot) is not ad.Zero:
            terms.append(primitive.bind(index, a_dot, b, **params))
        if type(b_dot) is not ad.Zero:
            terms.append(primitive.bind(index, a, b_dot, **params))
        if not terms:
            return out, jnp.zeros_like(out)
        return out, sum(terms[1:], terms[0])

    return jvp


for _p in (scatter_p, gather_p, contract_p):
    ad.primitive_jvps[_p] = _bilinear_jvp(_p)


OPTIONS = ("block", "reduce", "interpret", "planar", "unroll")  # the kernels' options, every primitive's params


def _common(params):
    return {name: params[name] for name in OPTIONS}


def _scatter_transpose(ct, index, W, Q, *, pairs, num_nodes, width, **params):
    ct = ad.instantiate_zeros(ct)
    if ad.is_undefined_primal(W):
        return None, _contract(index, Q, ct, pairs=pairs, num_keys=W.aval.shape[0], **_common(params)), None
    return None, None, _gather(index, W, ct, pairs=pairs, **_common(params))


def _gather_transpose(ct, index, W, u, *, pairs, **params):
    ct = ad.instantiate_zeros(ct)
    if ad.is_undefined_primal(W):
        return None, _contract(index, ct, u, pairs=pairs, num_keys=W.aval.shape[0], **_common(params)), None
    num_nodes, width = u.aval.shape
    return None, None, _scatter(index, W, ct, pairs=pairs, num_nodes=num_nodes, width=width, **_common(params))


def _contract_transpose(ct, index, Q, u, *, pairs, num_keys, **params):
    ct = ad.instantiate_zeros(ct)
    if ad.is_undefined_primal(Q):
        return None, _gather(index, ct, u, pairs=pairs, **_common(params)), None
    num_nodes, width = u.aval.shape
    return None, None, _scatter(index, ct, Q, pairs=pairs, num_nodes=num_nodes, width=width, **_common(params))


ad.primitive_transposes[scatter_p] = _scatter_transpose
ad.primitive_transposes[gather_p] = _gather_transpose
ad.primitive_transposes[contract_p] = _contract_transpose


# Batching: the batch is folded into the particles.  Member b's particles address their own copy
# of the grid (node numbers + b n), so one kernel launch does the whole batch.
_NOT_MAPPED = None  # the batch axis of an operand vmap does not map (jax's batching.not_mapped)


def _batched(x, axis, size):
    """``x`` with its batch axis first (broadcast when unbatched)."""
    if axis is _NOT_MAPPED:
        return jnp.broadcast_to(x, (size,) + x.shape)
    return jnp.moveaxis(x, axis, 0)


def _fold_particles(x):
    """(batch, ..., N) -> (..., batch N)."""
    return jnp.moveaxis(x, 0, -2).reshape(x.shape[1:-1] + (-1,))


def _folded_index(index, axis, size, num_nodes):
    index = _batched(index, axis, size)
    offsets = (jnp.arange(size, dtype=index.dtype) * num_nodes).reshape((size,) + (1,) * (index.ndim - 1))
    return _fold_particles(index + offsets)


def _batch_size(args, axes):
    return next(a.shape[d] for a, d in zip(args, axes) if d is not _NOT_MAPPED)


def _scatter_batch(args, axes, *, num_nodes, **params):
    size = _batch_size(args, axes)
    index = _folded_index(args[0], axes[0], size, num_nodes)
    W, Q = (_fold_particles(_batched(x, d, size)) for x, d in zip(args[1:], axes[1:]))
    out = _scatter(index, W, Q, num_nodes=size * num_nodes, **params)
    return out.reshape((size, num_nodes) + out.shape[1:]), 0


def _gather_like_batch(primitive):
    def rule(args, axes, **params):
        size = _batch_size(args, axes)
        (index, a, u), (index_axis, a_axis, u_axis) = args, axes
        if u_axis is _NOT_MAPPED:  # one nodal field for every member: no copies of the grid
            index = _fold_particles(_batched(index, index_axis, size))
        else:
            u = _batched(u, u_axis, size)
            index = _folded_index(index, index_axis, size, u.shape[1])
            u = u.reshape((-1,) + u.shape[2:])
        a = _fold_particles(_batched(a, a_axis, size))
        out = primitive.bind(index, a, u, **params)  # (..., batch N)
        out = out.reshape(out.shape[:-1] + (size, -1))
        return out, out.ndim - 2

    return rule


batching.primitive_batchers[scatter_p] = _scatter_batch
batching.primitive_batchers[gather_p] = _gather_like_batch(gather_p)
batching.primitive_batchers[contract_p] = _gather_like_batch(contract_p)


# The factor kernels as primitives: their values from the kernels above, their derivatives (and so
# their transposes) from the basis path, jvp of the same sum with W = _factor_basis(index, F): the reverse
# pass forms W once, the forward pass never does.
scatter_factors_p = Primitive("jaxmpm_pallas_scatter_factors")  # (index, F, Q) -> (n, C)
gather_factors_p = Primitive("jaxmpm_pallas_gather_factors")  # (index, F, u) -> (P, N)

scatter_factors_p.def_abstract_eval(lambda index, F, Q, *, num_nodes, width, **_: jax.core.ShapedArray(
    (num_nodes, width), _dtype(F, Q)))
gather_factors_p.def_abstract_eval(lambda index, F, u, *, pairs, **_: jax.core.ShapedArray(
    (len(pairs), index.shape[1]), _dtype(F, u)))


def _scatter_factors_impl(index, F, Q, *, keys, reduce, interpret, on_cpu=None, **params):
    return _scatter_pallas(index, _factor_source(F, keys), Q, reduce=reduce,
                           interpret=_interpret(interpret, on_cpu), **params)


def _gather_factors_impl(index, F, u, *, keys, reduce, interpret, on_cpu=None, **params):
    del reduce
    return _gather_pallas(index, _factor_source(F, keys), u, interpret=_interpret(interpret, on_cpu), **params)


_register(scatter_factors_p, _scatter_factors_impl)
_register(gather_factors_p, _gather_factors_impl)


def _factors_jvp(primitive, basis_form):
    """JVP of a factor primitive: the value from the primitive, the tangent from its basis form
    ``basis_form(index, W, b, **params)`` (linear in W and in b) with W = _factor_basis(index, F)."""

    def jvp(primals, tangents, *, keys, **params):
        index, F, b = primals
        _, F_dot, b_dot = tangents
        out = primitive.bind(index, F, b, keys=keys, **params)
        terms = []
        if type(F_dot) is not ad.Zero:
            _, W_dot = jax.jvp(lambda F: _factor_basis(index, F, keys), (F,), (F_dot,))
            terms.append(basis_form(index, W_dot, b, **params))
        if type(b_dot) is not ad.Zero:
            terms.append(basis_form(index, _factor_basis(index, F, keys), b_dot, **params))
        if not terms:
            return out, jnp.zeros_like(out)
        return out, sum(terms[1:], terms[0])

    return jvp


ad.primitive_jvps[scatter_factors_p] = _factors_jvp(scatter_factors_p, _scatter)
ad.primitive_jvps[gather_factors_p] = _factors_jvp(gather_factors_p, _gather)


def _scatter_factors_batch(args, axes, *, num_nodes, **params):
    size = _batch_size(args, axes)
    index = _folded_index(args[0], axes[0], size, num_nodes)
    F, Q = (_fold_particles(_batched(x, d, size)) for x, d in zip(args[1:], axes[1:]))
    out = scatter_factors_p.bind(index, F, Q, num_nodes=size * num_nodes, **params)
    return out.reshape((size, num_nodes) + out.shape[1:]), 0


batching.primitive_batchers[scatter_factors_p] = _scatter_factors_batch
batching.primitive_batchers[gather_factors_p] = _gather_like_batch(gather_factors_p)


# ------------------------------------------------------------------ P2G columns as (key, column) pairs
def _coefficient_terms(contraction, dim: int):
    """[(weight key, column within the contraction's width, coefficients (N,))] of one contraction:
    its per-slot values are sum over the terms of W_key * coefficients -- the rows formulation of
    :class:`~jaxmpm.transfer.kernels.xla.XLAKernel` without its structural zeros (a Gradient's
    column d meets only G_d)."""
    q = contraction.value
    if isinstance(contraction, (Weighted, Hoop)):
        key = "S" if isinstance(contraction, Weighted) else "T"
        return [(key, 0, q)] if q.ndim == 1 else [(key, c, q[:, c]) for c in range(q.shape[1])]
    if isinstance(contraction, Gradient):  # column d: q G_d
        return [(("G", d), d, q) for d in range(dim)]
    if isinstance(contraction, (Divergence, Affine)):  # column c: sum_d q[c, d] W_d
        key = "G" if isinstance(contraction, Divergence) else "A"
        return [((key, d), c, q[:, c, d]) for c in range(q.shape[1]) for d in range(q.shape[2])]
    raise TypeError(f"P2G: {type(contraction).__name__} is not a contraction the Pallas kernel knows")


class PallasKernel(Kernel):
    """P2G and G2P as fused Pallas kernels over blocks of ``block`` particles (module docstring).

    Args:
        block: particles per program instance (a power of two; 128 measured best in 3D on an H100).
        reduce: sum the contributions of a block's particles that touch the same nodes before the
            atomic adds (module docstring); the same numbers to round-off.
        interpret: run in Pallas' interpret mode (the CPU); None (default): when the program is
            compiled for the CPU (``jax.default_backend() == "cpu"`` for eager calls).
        factors: form the slot weights in the kernels from a tensor-product stencil's per-axis
            factors (3 D K1 values per particle) instead of reading the basis W (up to (1 + 2 D) K
            values) that XLA forms from them (default True; the basis path serves the rest:
            axisymmetric stencils, per-slot columns, and every derivative).
        planar: address the nodal arrays column by column inside the kernels (``col n + node``)
            rather than node by node (``node C + col``); the same sums in the same order.
        unroll: unroll the loop over the stencil's slots (static addresses; a kernel K times as
            long to compile).
    """

    block: int = BLOCK
    reduce: bool = False
    interpret: bool | None = None
    factors: bool = True
    planar: bool = False
    unroll: bool = False

    def _options(self):
        return {name: getattr(self, name) for name in OPTIONS}

    def _from_factors(self, stencil, keys) -> bool:
        """Whether the kernels form the weights of ``keys`` from ``stencil``'s per-axis factors (a
        tensor-product stencil, keys among S, G_d, S (x_i - X_p)_d) rather than read the basis W."""
        return (self.factors and isinstance(stencil, TensorStencil) and not isinstance(stencil, AxisymmetricStencil)
                and all(k == "S" or (isinstance(k, tuple) and k[0] in ("G", "A")) for k in keys))

    def p2g(self, stencil, columns: dict, num_nodes: int) -> dict:
        dim, names = stencil.dim, list(columns)
        widths = {}
        for name, column in columns.items():
            shapes = {c.width(dim) for c in as_terms(column)}
            assert len(shapes) == 1, f"P2G column {name!r} sums contractions of different widths {shapes}"
            widths[name] = shapes.pop()
        starts, total = {}, 0
        for name in names:
            starts[name] = total
            total += widths[name][0] if widths[name] else 1
        terms, per_slot = {}, []  # (key, nodal column) -> coefficients; per-slot weights with unit coefficients
        for name, column in columns.items():
            for c in as_terms(column):
                if isinstance(c, PerSlot):
                    values = c.value if c.value.ndim == 3 else c.value[None]
                    per_slot += [(("P", len(per_slot) + i), starts[name] + i, v) for i, v in enumerate(rows(values))]
                    continue
                for key, col, coef in _coefficient_terms(c, dim):
                    at = (key, starts[name] + col)
                    terms[at] = terms[at] + coef if at in terms else coef
        index = stencil.index.astype(jnp.int32)
        keys = tuple(dict.fromkeys(k for k, _ in terms))
        if not per_slot and self._from_factors(stencil, keys):  # the weights formed in the kernel
            F = _factors_of(stencil)
            pairs = tuple((keys.index(k), col) for k, col in terms)
            Q = jnp.stack(list(terms.values())).astype(F.dtype)
            nodal = scatter_factors_p.bind(index, F, Q, keys=keys, pairs=pairs, num_nodes=num_nodes, width=total,
                                           **self._options())
        else:  # the basis W read from memory, per-slot columns with unit coefficients
            basis = _weight_basis(stencil, _kinds(keys))
            n = stencil.num_particles
            for key, col, values in per_slot:
                basis[key] = values
                terms[(key, col)] = jnp.ones((n,), values.dtype)
            keys = tuple(dict.fromkeys(k for k, _ in terms))
            W = jnp.stack([basis[k] for k in keys])
            pairs = tuple((keys.index(k), col) for k, col in terms)
            Q = jnp.stack(list(terms.values())).astype(W.dtype)
            nodal = _scatter(index, W, Q, pairs=pairs, num_nodes=num_nodes, width=total, **self._options())
        return {name: nodal[:, starts[name]] if not widths[name]
                else nodal[:, starts[name]:starts[name] + widths[name][0]] for name in names}

    def _gather(self, stencil, keys, basis, u, pairs):
        """out[r] = sum_k W_j u_c for r = (j, c): from the factors (``keys``) where they serve, else
        from the basis ``basis()`` (J, K, N)."""
        index = stencil.index.astype(jnp.int32)
        if self._from_factors(stencil, keys):
            return gather_factors_p.bind(index, _factors_of(stencil), u, keys=tuple(keys), pairs=tuple(pairs),
                                         **self._options())
        return _gather(index, basis(), u, pairs=tuple(pairs), **self._options())

    def gather(self, stencil, u):
        nodal = u[:, None] if u.ndim == 1 else u
        out = self._gather(stencil, ("S",), lambda: stencil.weight[None], nodal,
                           [(0, c) for c in range(nodal.shape[1])])
        return out[0] if u.ndim == 1 else out.T

    def velocity_gradient(self, stencil, v):
        d = stencil.dim
        out = self._gather(stencil, [("G", b) for b in range(d)], lambda: stencil.gradient, v,
                           [(b, a) for a in range(d) for b in range(d)])
        return jnp.moveaxis(out.reshape(d, d, -1), -1, 0)

    def scalar_gradient(self, stencil, u):
        d = stencil.dim
        return self._gather(stencil, [("G", b) for b in range(d)], lambda: stencil.gradient, u[:, None],
                            [(b, 0) for b in range(d)]).T

    def affine_moment(self, stencil, v):
        d, c = stencil.dim, v.shape[1]
        out = self._gather(stencil, [("A", b) for b in range(d)],
                           lambda: stencil.weight[None] * stencil.offset,  # S_pi (x_i - X_p)_b, (D, K, N)
                           v, [(b, a) for a in range(c) for b in range(d)])
        return jnp.moveaxis(out.reshape(c, d, -1), -1, 0)


def _factors_of(stencil):
    """F = (w, dw, dx) of a tensor-product stencil, (3, D, K1, N)."""
    return jnp.stack([stencil.w, stencil.dw, stencil.dx])
