"""Backend policy: where XLA may fuse, decided per backend at trace time, in this one module.

Physics code marks *stage boundaries* -- "this per-particle quantity is evaluated once, before
its consumers" -- with :func:`materialise` and :func:`evaluate_once`; what a boundary does is the
policy's business:

* ``"cpu"`` (the CPU's default): a boundary is a real materialisation point.  XLA on the CPU fuses
  cheap elementwise producers into every consumer, so without it the 1D shape-function kernels,
  the stress and APIC's C_p are recomputed for every (particle, node, component) of every
  transfer (measured 3x slower mpm88 step).  ``lax.optimization_barrier`` is removed before
  fusion on the CPU, so the boundary is a conditional whose predicate, ``not (x > +inf)``, is true
  for every float (NaN included) but cannot be folded: the taken branch is the identity and the
  values are exactly the inputs (under ``vmap`` it stays one conditional over the whole batch, its
  predicate unbatched: :func:`_taken_for_the_batch`).  Code run op by op, outside any trace, has no
  program to steer: there a boundary is skipped (:func:`_eager`).
* ``"gpu"`` (every other backend's default): boundaries are identities.  On a GPU the
  conditional costs a device-to-host round trip of its predicate per boundary (measured on an
  H100: 1.56x slower 3D step at 1M particles, 7x at 8k), and fusion is what one wants there.

The policy also sets the row width of the transfer layer's one scatter-add
(:func:`scatter_row_width`: a power of two on the CPU, the natural width elsewhere), and with the
precision how the XLA kernel lays out P2G and G2P (:data:`XLA_LAYOUT`, :func:`xla_layout`).

``Simulation(..., backend="auto" | "cpu" | "gpu")`` picks the policy; ``"auto"`` resolves from
``jax.default_backend()`` when the step is traced.  Both policies give the same numbers: a
boundary changes where values are computed, not how (tests/test_open_core.py, 1e-12).

The *adjoint* (``Simulation(..., adjoint=...)``) picks how reverse mode differentiates the
transfer layer; it too changes speed, never results (tests/test_adjoint.py, 1e-10):

* ``"structured"`` (default): the transfer layer's building blocks carry their own JVP rules
  (:func:`derivative_rule`), written so that their transposes are the cheap adjoint operations --
  a broadcast for a sum over the stencil, row products and adds for the tensor-product shape
  functions, boundaries that hold only primal values, and (:func:`hold_tangent`) a boundary on
  the scatter's tangent, so that its transpose evaluates the nodal cotangent once before the
  gather.  JAX transposes the rest as usual.
* ``"autodiff"``: JAX differentiates the forward code as written (the reference path).

The *kernel* (``Simulation(..., kernel="auto" | "xla" | "pallas")``) picks what runs P2G and G2P
(:mod:`jaxmpm.transfer.kernels`); it too changes speed, never results (tests/test_pallas_kernel.py,
1e-12).  ``"auto"`` looks the model up in :data:`KERNEL_TABLE` -- by backend, dimension, particles
per cell, dtype and whether P2G folds the force into the momentum (1 + D nodal columns instead of
1 + 2D, ``jm.folds_force``), each row with the measurement behind it -- the one place to retune when
a device is measured (``jm.backend_info(sim, state)`` names the row in force).
"""

from __future__ import annotations

import contextlib
import contextvars
import math
from functools import cache, partial, wraps

import jax
import jax.numpy as jnp
from jax.custom_batching import custom_vmap
from jax.extend.core import jaxpr_as_fun

from ..core.errors import check
from ..core.limits import size_text
from ..core.validate import one_of

try:  # whether no trace is active: code runs op by op (see _eager)
    from jax._src.core import trace_state_clean as _trace_state_clean
except ImportError:  # pragma: no cover - a JAX without it keeps every boundary
    _trace_state_clean = None

POLICIES = ("auto", "cpu", "gpu")

_active = contextvars.ContextVar("jaxmpm_backend_policy", default="auto")


def resolve(policy: str) -> str:
    """``"cpu"`` or ``"gpu"`` for a policy name (``"auto"``: from the default JAX backend)."""
    check(one_of(policy, POLICIES), f"backend = {policy!r}; choose one of {', '.join(POLICIES)}")
    if policy == "auto":
        return "cpu" if jax.default_backend() == "cpu" else "gpu"
    return policy


@contextlib.contextmanager
def use_policy(policy: str):
    """Trace the enclosed code under ``policy`` (see the module docstring)."""
    token = _active.set(resolve(policy))
    try:
        yield
    finally:
        _active.reset(token)


def active() -> str:
    """The policy in force for code being traced now: ``"cpu"`` or ``"gpu"``."""
    return resolve(_active.get())


def materialise(arrays):
    """Stage boundary: ``arrays`` (a pytree of arrays) unchanged, evaluated once before their
    consumers under the CPU policy; the identity under the GPU policy."""
    if active() != "cpu" or _eager(arrays):
        return arrays
    return _held(arrays) if structured() else _barrier(lambda a: a, arrays)


def evaluate_once(fn, *args):
    """Stage boundary around a computation: ``fn(*args)``, evaluated into its own buffers under the
    CPU policy (like :func:`materialise`, but without copying the result); ``fn(*args)`` inline
    under the GPU policy."""
    if active() != "cpu" or _eager(args):
        return fn(*args)
    if not structured():
        return _barrier(lambda a: fn(*a), args)
    closed, consts = jax.closure_convert(fn, *args)
    return _held_computation(closed, tuple(consts), args)


# Residual bytes up to which a reverse-mode rollout stores every step's residuals rather than
# recomputing the steps (``checkpoint="auto"``, jaxmpm.run.memory), per policy, from
# benchmarks/gradient_memory.py (1000 steps; gradient time with residuals stored / recomputed):
# * cpu: never -- recomputing won everywhere: bar 256 particles 51 MiB stored 2.2x slower, disks
#   14-21x against 5-6x, mpm88 8k needs ~31 GiB (2 cores, float64);
# * gpu (H200, jax 0.11.2, float32): stored won only for the bar (25-30 MiB: 0.73-0.75x the
#   recomputing gradient's time); from disks (327-469 MiB: 1.05-1.22x) to mpm88 8k (7-17 GiB:
#   1.12-1.34x) and 131k particles (11-14 GiB for 100 steps: 1.12-1.36x) recomputing won.
STORE_RESIDUALS_UP_TO = {"cpu": 0, "gpu": 64 * 2**20}

# Bytes of kept states up to which a reverse-mode rollout keeps every step's state and recomputes each
# step once (``checkpoint="states"``) rather than running two levels (``True``), per policy and
# dimension; a dimension not listed: as many as the memory budget allows.  From
# benchmarks/gradient_memory.py (one pinned core, float64, 2026-11-28; gradient / forward, two levels ->
# one level, the kept states in brackets):
# * cpu, 1D (bar, 256 particles, 10 kB a state): 1000 steps (10 MB) 4.15 -> 3.10 (FLIP), 4.29 -> 3.91
#   (APIC); 4000 steps (39 MB) 4.21 -> 4.58 and 4.21 -> 4.26; 16000 steps (156 MB) 4.15 -> 4.57.  A 1D step
#   is so cheap (14 ns a particle) that, once the states leave the cache, writing and reading them back
#   costs what recomputing them does;
# * cpu, 2D: disks 1000 steps (32 MB) 6.37 -> 5.58, 4000 steps (128 MB) 6.00 -> 5.43; mpm88 8k particles,
#   1000 steps (0.9 GB) 6.27 -> 5.36 (FLIP), 7.08 -> 6.44 (APIC);
# * cpu, 3D (benchmarks/gpu.py's mpm3d, APIC, 8k particles on 20^3, 2026-11-29): 100 steps (0.2 GB kept) 6.14-6.27
#   -> 5.35-5.40, 1000 steps (1.8 GB) 6.31 -> 5.46: as 2D;
# * gpu: not measured (benchmarks/gpu_session.sh times "auto" against two levels); kept as the CPU's 2D.
KEEP_STATES_UP_TO = {"cpu": {1: 16 * 2**20}, "gpu": {}}

# Whether ``sim.run`` outside a trace loops with runtime frame and step counts (one compiled loop for any run
# length, jaxmpm.run.driver._run_at_once), per policy.  cpu: yes, as fast as the static scans (mpm88, 2026-11-29:
# 8k float32 0.88-0.92 against 0.94 ms a step, 131k float64 10.75 against 10.67-10.94; a short run of a small model
# pays 1-2 ms, benchmarks/run_counts.py).  gpu: no, a static scan
# -- XLA:GPU reads a while loop's predicate back to the host every iteration unless its trip count is known at
# compile time (not measured here: no device).
RUNTIME_COUNTS = {"cpu": True, "gpu": False}


def scatter_row_width(width: int) -> int:
    """How many columns a scatter-add of ``width`` columns per (node) row is given: under the CPU
    policy the next power of two (the extra columns are zeros, sliced off after), ``width``
    under the GPU policy.  XLA:CPU (jax 0.10) adds rows of 3, 5, 6 or 7 columns 2-4x slower
    than rows of 4 or 8 when consecutive updates hit the same node, as they do for particles
    laid out in rows (a 2D P2G of mass, momentum and force is 5 columns: the disks step 1.4x
    faster in float64, 1.7x in float32, benchmarks/throughput.py); on a GPU the extra columns
    would be extra atomic adds.  Each column is summed on its own, so the values are the same."""
    if active() != "cpu" or width & (width - 1) == 0:
        return width
    return 1 << (width - 1).bit_length()


# How a sum over the stencil's slots (G2P: sum_k S_pk u_k) is formed, per policy (backend tuning; both give
# the same sums to round-off, tests/test_open_core.py):
# * "adds": K - 1 adds of the slots' particle rows, (K, N) -> (N,): on the CPU XLA vectorises them along the
#   particles (the reason for the planar layout);
# * "reduce": one reduction over the slot axis: on the CPU 0.27x and 0.24x the adds' speed (mpm88, float32,
#   32k and 131k particles, 100 compiled steps, 2 cores).
# The GPU's entry awaits a device: the optimised HLO of an H100 mpm88 step (524k particles, 2026-11-27,
# benchmarks/gpu_profile.py --hlo) materialises every per-slot G2P product, six (N, 9) arrays, in one fusion
# with a transpose, and sums them in the next fusions: 0.136 ms of the step's 0.534 ms in its two transpose
# fusions, where a plain-JAX step (one gather-multiply-reduce fusion) takes 0.265 ms in all.  Whoever has a
# GPU: benchmarks/gpu.py --stencil-sum reduce.
STENCIL_SUM = {"cpu": "adds", "gpu": "adds"}


def stencil_sum_form() -> str:
    """How the code being traced now sums over the stencil's slots: "adds" or "reduce" (:data:`STENCIL_SUM`)."""
    return STENCIL_SUM[active()]


# How the XLA kernel (jaxmpm.transfer.kernels.xla.XLAKernel with its "auto" options) runs, per (policy, dtype):
# (P2G's layout, the layout of P2G's derivatives, whether G2P holds its gathered nodal values).  Every choice
# gives the same numbers to round-off (tests/test_open_core.py).  Measured with benchmarks/p2g_layout.py on one
# pinned core (2026-11-27, jax 0.10.2, particle-steps per CPU second, best of 3 over two rounds; table in
# benchmarks/README.md), against planar with held gathers:
# * CPU float32: planar with held gathers stays: mpm88 8k, free gathers 0.99x, rows with planar derivatives
#   0.85x; on two threads (wall time, ms per step at 8k / 32k / 131k) the rows 0.54 / 1.74 / 9.5 against
#   0.51-0.52 / 1.65-1.68 / 9.5-9.8, free gathers 0.51-0.79 / 2.6-2.7 / 11.3-11.8;
# * CPU float64: rows, their derivatives planar, free gathers: mpm88 8k / 32k / 131k 1.10x / 1.24x / 1.26x
#   (two threads, wall: 0.79 / 3.4 / 21.2 -> 0.68 / 2.73 / 15.4-16.0 ms per step), disks at h = 0.00625 (25.7k
#   particles) 1.27x, disks (416) 1.00x, 3D mms 1.04x; gradients (mpm88 8k, disks) 1.03-1.05x.  A per-slot
#   float64 buffer of 32k particles is 2.4 MB, of 131k 9.4 MB: beyond the cache, writing and reading it costs
#   more than recomputing a gather inside each product, and P2G's rows written once in the scatter's order
#   save the transpose of stacked per-slot columns.  The rows differentiated as written ran gradients at
#   0.39-0.52x (their broadcasts transpose to reductions over short axes), hence planar derivatives;
# * GPU: the rows layout (no per-slot concatenation; fused into the scatter, the boundaries being identities).
XLA_LAYOUT = {("cpu", "float32"): ("planar", "planar", True), ("cpu", "float64"): ("rows", "planar", False),
              ("cpu", None): ("planar", "planar", True), ("gpu", None): ("rows", "rows", True)}


def xla_layout(dtype) -> tuple:
    """(P2G's layout, "planar" or "rows"; the layout of its derivatives; whether G2P holds its gathered
    nodal values) for the XLA kernel in code traced now in ``dtype`` (:data:`XLA_LAYOUT`)."""
    policy = active()
    return XLA_LAYOUT.get((policy, jnp.dtype(dtype).name), XLA_LAYOUT[(policy, None)])


def _eager(operands) -> bool:
    """Whether ``operands`` are being computed now, op by op, outside any trace (``sim.step``
    called without ``jax.jit``).  Then no program is being built, so a boundary has nothing to
    steer, and it is skipped: as a conditional it would be compiled anew at every call, its
    branches being new functions each time (1149 conditionals compiled in tests/test_conventions.py
    and tests/test_affine.py).  Under ``jax.disable_jit`` JAX already runs a conditional's branch
    directly.  False when in doubt: a JAX without ``trace_state_clean`` keeps the boundary."""
    if any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree_util.tree_leaves(operands)):
        return False
    return _trace_state_clean is not None and _trace_state_clean()


def fori_loop(lower: int, upper: int, body, init):
    """``jax.lax.fori_loop(lower, upper, body, init)`` with static bounds; in eager code (see
    :func:`_eager`) a Python loop over the same ``body``, its index an array of the loop's integer
    type.  A ``fori_loop`` called outside any trace is traced and compiled anew at every call, its
    body being a new closure each time: an eager XPIC(2) step on ``disks`` took 0.53 s against
    FLIP's 0.047 s, all of the difference compiling the series loop.  Traced code keeps the loop
    (one copy of the body in the program, differentiable)."""
    if _eager(init):
        carry = init
        for i in range(lower, upper):
            carry = body(jnp.asarray(i), carry)
        return carry
    return jax.lax.fori_loop(lower, upper, body, init)


def while_loop(cond_fun, body_fun, init):
    """``jax.lax.while_loop(cond_fun, body_fun, init)``; in eager code (see :func:`_eager`) a Python
    loop over the same functions, the carry's leaves made arrays first, as the loop makes them.  An
    eager ``while_loop`` is compiled anew at every call, as :func:`fori_loop` says (Cam-Clay's return
    mapping at 50 points: 1.0 s a call eagerly)."""
    if _eager(init):
        carry = jax.tree_util.tree_map(jnp.asarray, init)
        while bool(cond_fun(carry)):
            carry = body_fun(carry)
        return carry
    return jax.lax.while_loop(cond_fun, body_fun, init)


def _barrier(fn, operands, witness=None):
    """``fn(operands)`` inside a conditional that is always taken (see the module docstring); its
    predicate reads ``witness`` (default: the first float of ``operands``).  ``fn`` is traced once,
    into a jaxpr that gives the untaken branch its output types and that the taken branch replays
    (tracing ``fn`` for the types and again for the branch doubled the boundaries' tracing); the
    branch's program is the same.

    Under ``jax.vmap`` the predicate stays unbatched (:func:`_taken_for_the_batch`), so vmap batches
    ``fn`` inside one conditional over the whole batch.  A batched predicate would make the
    conditional a ``select`` of both branches, which XLA fuses through: the boundary lost, a vmapped
    CPU step ran at half the speed of a single one (mpm88, 8k particles: 0.44x, with all 16
    boundaries gone).  The conditional stays differentiable in every order.  (Until 2026-11-28 the
    primal boundaries were a ``custom_vmap`` whose rule called itself, through which forward over
    reverse, ``jax.jacfwd(jax.grad(loss))``, recursed without end.)"""
    if witness is None:
        witness = next(leaf for leaf in jax.tree_util.tree_leaves(operands) if jnp.issubdtype(leaf.dtype, jnp.floating))
    closed, out = jax.make_jaxpr(fn, return_shape=True)(operands)
    out_tree = jax.tree_util.tree_structure(out)

    def taken(ops):
        return jax.tree_util.tree_unflatten(out_tree, jaxpr_as_fun(closed)(*jax.tree_util.tree_leaves(ops)))

    return jax.lax.cond(_taken_for_the_batch(jax.lax.stop_gradient(witness)), taken,
                        lambda ops: _untaken(out, ops), operands)


def _varies(x) -> bool:
    """Whether ``x`` varies over a mesh axis of an enclosing ``shard_map`` (jax 0.10: the type's
    ``manual_axis_type.varying``; later versions: its ``vma``)."""
    aval = jax.typeof(x)
    manual = getattr(aval, "manual_axis_type", None)
    return bool(getattr(manual, "varying", None) or getattr(aval, "vma", None))


def _untaken(out, operands):
    """The boundary conditional's other branch: zeros of the types of ``out``.  Inside
    ``shard_map`` both branches must vary over the same mesh axes, so the zeros take the operands'
    (a zero of each varying operand is added, which only retypes them); elsewhere plain zeros."""
    varying = [leaf for leaf in jax.tree_util.tree_leaves(operands) if _varies(leaf)]

    def zeros(o):
        z = jnp.zeros(o.shape, o.dtype)
        for leaf in varying:
            z = z + jnp.zeros_like(leaf, shape=()).astype(o.dtype)
        return z

    return jax.tree_util.tree_map(zeros, out)


def _always_true(x):
    """``not (x[0] > +inf)``: true for every float, NaN included, and not foldable by XLA."""
    return jnp.logical_not(x.reshape(-1)[0] > jnp.inf)


@custom_vmap
def _taken_for_the_batch(witness):
    """A boundary's predicate, :func:`_always_true` of ``witness``, unbatched under ``jax.vmap``: one
    member's value decides for the whole batch (the predicate is true for every float).  A batched
    predicate turns the conditional into a ``select`` whose untaken operands pass through
    ``stop_gradient``; on a tangent (:func:`hold_tangent`) that ``stop_gradient`` sits in the linear
    program, which JAX cannot transpose, so ``jax.grad`` of a vmapped rollout failed.  Unbatched, the
    conditional stays one conditional over the batch, transposed as a conditional."""
    return _always_true(witness)


@_taken_for_the_batch.def_vmap
def _(axis_size, in_batched, witness):
    (batched,) = in_batched
    return _taken_for_the_batch(witness[0] if batched else witness), False


# Boundaries under the structured adjoint.  Under differentiation a boundary holds the primal
# values only; tangents (and so, transposed, cotangents) pass by ordinary fusion.  A conditional in
# the linearised program would make every residual leave it through a buffer of its own, and its
# transpose would be a second conditional that runs the branch again.


@jax.custom_jvp
def _held(arrays):
    return _barrier(lambda a: a, arrays)


@_held.defjvp
def _held_jvp(primals, tangents):
    (arrays,), (arrays_dot,) = primals, tangents
    return _held(arrays), arrays_dot


@partial(jax.custom_jvp, nondiff_argnums=(0,))
def _held_computation(closed, consts, args):
    return _barrier(lambda ca: closed(*ca[1], *ca[0]), (consts, args))


@_held_computation.defjvp
def _held_computation_jvp(closed, primals, tangents):
    out, out_dot = jax.jvp(lambda c, a: closed(*a, *c), primals, tangents)
    return _held(out), out_dot


def hold_tangent(tangent, primal):
    """A stage boundary for a tangent (a linear function of the inputs' tangents): ``tangent``
    unchanged, inside an always-taken conditional whose predicate comes from ``primal`` under the
    CPU policy.  Its transpose is the same conditional on the cotangent, so reverse mode evaluates
    that cotangent once before its consumers (e.g. the gather that transposes a scatter) instead
    of fusing its computation into them."""
    if active() != "cpu":  # only called in a JVP rule, so always traced: never eager
        return tangent
    return _barrier(lambda t: t, tangent, witness=primal)  # the predicate must not read the tangent


# ------------------------------------------------------------------ the adjoint
ADJOINTS = ("structured", "autodiff")

_adjoint = contextvars.ContextVar("jaxmpm_adjoint", default="structured")


@contextlib.contextmanager
def use_adjoint(adjoint: str):
    """Trace the enclosed code with the derivative rules of ``adjoint`` (see the module docstring)."""
    check(one_of(adjoint, ADJOINTS), f"adjoint = {adjoint!r}; choose one of {', '.join(ADJOINTS)}")
    token = _adjoint.set(adjoint)
    try:
        yield
    finally:
        _adjoint.reset(token)


def structured() -> bool:
    """Whether code being traced now uses the structured derivative rules."""
    return _adjoint.get() == "structured"


def derivative_rule(plain, ruled):
    """``ruled`` (a ``jax.custom_jvp`` of the same function as ``plain``) under the structured
    adjoint, ``plain`` under ``"autodiff"``; both give the same values.  The rule is traced in the
    context of the call (:func:`in_call_context`)."""

    @wraps(plain)
    def dispatch(*args):
        return in_call_context(ruled)(*args) if structured() else plain(*args)

    return dispatch


def in_call_context(ruled):
    """``ruled`` (a ``jax.custom_jvp``) whose JVP rule is traced in the context of this call: its backend
    policy, adjoint and kernel (this module's context variables).  JAX traces a rule when it differentiates,
    which may come after the call has returned (``jax.grad`` of a rollout differentiates the jitted rollout's
    program once traced): the rule would then read the defaults, the platform's policy for a model that forces
    another (``backend="gpu"`` traced on a CPU: half of a disks gradient's tangent boundaries were the CPU
    policy's, tests/test_derivative_rules.py::test_rules_are_traced_under_the_models_policy)."""
    context = contextvars.copy_context()
    traced = jax.custom_jvp(ruled.fun, nondiff_argnums=ruled.nondiff_argnums)
    traced.defjvp(lambda *args: context.copy().run(ruled.jvp, *args), symbolic_zeros=ruled.symbolic_zeros)
    return traced


# ------------------------------------------------------------------ the transfer kernel
# Which kernel (jaxmpm.transfer.kernels) runs P2G and G2P: ``Simulation(..., kernel="auto" |
# "xla" | "pallas")``.  "auto" looks the model up in KERNEL_TABLE; "xla" and "pallas" force one.
KERNEL_CHOICES = ("auto", "xla", "pallas")

# Particles per cell (particles / grid cells) from which a 2D model counts as dense.
DENSE_PARTICLES_PER_CELL = 4.0

# (policy, dimension or None for any, dense or None for any, dtype or None for any, P2G folds the force
# or None for any) -> (kernel, its options, why).  The first row that matches wins; whoever measures on a device
# updates it (benchmarks/gpu.py; benchmarks/gpu_session.sh takes every variant in one lease).
# Measured on an H100 80GB HBM3, jax 0.11.2, float32, particle-steps/s, best of 2 (benchmarks/README.md
# "GPU"; benchmarks/measured/gpu_h100_2026-11-27.md).  First lease: PallasKernel reading the per-slot basis W
# lost everywhere (3D 0.75-0.77x, 2D 0.55-0.73x the XLA kernel).  Second lease, the kernel forming its weights
# from the per-axis factors (PallasKernel(factors=True), checked on the device against the XLA kernel: 10
# passed, gradients and vmap among them): it wins in 3D where P2G folds the force into the momentum (APIC:
# 4 numbers per slot), loses in 3D where it does not (FLIP, XPIC, FMPM: 7 numbers per slot, atomics the
# XLA scatter does better), and loses in dense 2D.
KERNEL_TABLE = (
    # CPU: XLA.  Pallas runs on the CPU only in interpret mode, a checking tool (tests), far slower.
    (("cpu", None, None, None, None), ("xla", {}, "CPU: the XLA kernel; Pallas runs on the CPU only in interpret "
                                                  "mode (verification, far slower)")),
    # 3D float32, mpm3d (APIC, quadratic: the force folded), second lease, at 131k (64^3) / 1M (128^3):
    # unsorted, XLA (131k not measured) / 2.74e8 (first lease 2.68e8 / 2.67e8), the factor kernel
    # 2.80e8 / 3.08e8 and 3.09e8 (1.13x at 1M in the same call); sorted by cell every 16 steps, XLA
    # 2.49e8 / 2.97e8 (first lease 2.71e8 / 2.95e8), the factor kernel 2.69e8 / 3.38e8, 3.41e8 and
    # 3.39e8 (1.14x at 1M).
    # Variants that lost at 1M: nodal arrays addressed by column 2.32e8, slots unrolled 2.71e8, both
    # 2.10e8, both with blocks of 64 particles 1.83e8 or 256 on 8 warps 2.18e8.  float64 not measured: the
    # XLA kernel (the last row).
    (("gpu", 3, None, "float32", True), ("pallas", {}, "3D float32 on a GPU, force folded into the momentum: the "
                                                       "Pallas kernel forming its weights from the per-axis factors "
                                                       "(H100, APIC at 1M particles: 3.09e8 particle-steps/s against "
                                                       "the XLA kernel's 2.74e8)")),
    # 3D, force apart (FLIP, XPIC, FMPM at 1M particles, dt 5e-5, benchmarks/gpu.py --parts schemes): Pallas
    # sorted every 16 steps (second lease) against XLA unsorted (first lease): FLIP 2.12e8 / 2.29e8; XPIC(5)
    # 9.10e7 / 1.16e8; FMPM(2) 1.60e8 / 1.56e8; FMPM(4) 1.06e8 / 1.36e8; FMPM(8) 6.46e7 / 9.26e7 (0.70-1.03x).
    # 7 numbers per slot (mass, momentum, force) against APIC's 4: the atomics cost more.
    (("gpu", 3, None, None, False), ("xla", {}, "3D on a GPU, force apart from the momentum: the XLA kernel (H100 "
                                                "at 1M particles: the Pallas kernel 0.70-1.03x under FLIP, XPIC and "
                                                "FMPM)")),
    # dense 2D, mpm88 (10-200 particles per cell): XLA 2.97e8 / 6.22e8 / 8.96e8 / 9.99e8 / 1.09e9 at
    # 8k / 32k / 131k / 524k / 2.1M; Pallas from the basis 1.62e8 / 4.33e8 / 6.22e8 / 7.33e8 / 6.88e8
    # (0.55-0.73x), with its block reduction 4.0e7 / 1.2e8 / 1.2e8 at 8k / 32k / 131k (atomics contend).
    # Second lease: XLA 9.29e8 / 1.00e9 and 1.02e9 / 1.13e9 at 131k / 524k / 2.1M, the factor kernel
    # 8.49e8 / 8.87e8 and 9.07e8 / 9.33e8 (0.82-0.91x).
    (("gpu", 2, True, None, None), ("xla", {}, "dense 2D on a GPU: XLA's scatter (H100 mpm88: the Pallas kernel "
                                               "0.82-0.91x the XLA kernel)")),
    # everything else on the GPU (1D, sparse 2D, 3D float64): not measured apart; the XLA kernel
    (("gpu", None, None, None, None), ("xla", {}, "GPU: the XLA kernel (not measured apart: 1D, sparse 2D, 3D "
                                                  "float64)")),
)


def choose_kernel(policy: str, dim: int, particles_per_cell: float, dtype, folds_force: bool = False) -> tuple:
    """(kernel name, options, why): the first row of :data:`KERNEL_TABLE` that matches a model
    traced under ``policy`` ("cpu", "gpu" or "auto") in ``dim`` dimensions, with
    ``particles_per_cell`` particles per grid cell, computing in ``dtype``, whose P2G folds the force
    into the momentum or not (``folds_force``, :func:`jaxmpm.folds_force`)."""
    policy, dtype = resolve(policy), jnp.dtype(dtype).name
    dense = dim == 2 and particles_per_cell >= DENSE_PARTICLES_PER_CELL
    for (p, d, dn, dt, f), row in KERNEL_TABLE:
        if (p == policy and d in (None, dim) and dn in (None, dense) and dt in (None, dtype)
                and f in (None, folds_force)):
            return row
    return "xla", {}, "no row of KERNEL_TABLE matches: the XLA kernel"


# (policy, dimension or None for any, kernel or None for any) -> (steps between sorts of the particles
# by cell, 0 for never; why).  The first row that matches wins (jaxmpm.run.sorting; measured with
# benchmarks/gpu.py --sort-every K and benchmarks/vs_taichi.py).
SORT_TABLE = (
    # 3D on a GPU, the Pallas kernel (H100, mpm3d float32, second lease): 1M particles 3.08e8 -> 3.38e8
    # particle-steps/s sorted every 16 steps (3.09e8 -> 3.41e8 in a second call), 131k 2.80e8 -> 2.69e8
    # (0.96x).  Between the two not measured: sorted from 1M.
    (("gpu", 3, "pallas", 1_000_000), (16, "3D on a GPU, the Pallas kernel, from 1M particles: sorted by cell every "
                                           "16 steps (H100, 1M particles: 3.08e8 -> 3.38e8 particle-steps/s)")),
    (("gpu", 3, "pallas", 0), (0, "3D on a GPU, the Pallas kernel, under 1M particles: not sorted (H100, 131k "
                                  "particles sorted every 16 steps: 0.96x)")),
    # 3D on a GPU (H100, mpm3d, XLA kernel): 1M particles 2.67e8 -> 2.95e8 particle-steps/s sorted every
    # 16 steps (2.93e8 every 4, 2.95e8 every 64); 131k 2.68e8 -> 2.71e8 (1.01x: from here on).  The G2P
    # gather (a transpose fusion) falls from 0.735 to 0.155 ms per step at 1M (benchmarks/gpu_profile.py).
    # Smaller runs are not measured; a renewal's sort and gathers weigh more against a short step (2D
    # at 8k lost 42%), so they are not sorted.  The Pallas kernel at 1M: 2.06e8 -> 2.15e8.
    (("gpu", 3, None, 131072), (16, "3D on a GPU from 131k particles: sorted by cell every 16 steps (H100, 1M "
                                    "particles: 2.67e8 -> 2.95e8 particle-steps/s; the G2P gather reads "
                                    "neighbouring rows)")),
    # 2D on a GPU: the scatter's atomics contend on few nodes once neighbours share them (H100 mpm88,
    # XLA kernel, sorted every 16: 8k 2.97e8 -> 1.71e8, 131k 8.96e8 -> 7.49e8, 2.1M 1.09e9 -> 5.54e8)
    (("gpu", 2, None, 0), (0, "2D on a GPU: not sorted (H100 mpm88 sorted by cell: 0.51-0.84x, the scatter's "
                              "atomics contend on shared nodes)")),
    # CPU (2 cores, float32, one core pinned): sorted every 16 steps, mpm88 0.96x at 32k and 0.89x at 131k,
    # mpm3d 0.98x at 131k
    (("cpu", None, None, 0), (0, "CPU: not sorted (sorted by cell every 16 steps: 0.89-0.98x; XLA:CPU's scatter "
                                 "and gather gain nothing from the order)")),
    ((None, None, None, 0), (0, "not measured: not sorted")),
)


def choose_sorting(policy: str, dim: int, num_particles: int, kernel: str) -> tuple:
    """(steps between sorts of the particles by cell, 0 for never; why): the first row of
    :data:`SORT_TABLE` -- (policy, dimension, kernel, fewest particles) -> row -- that matches a
    model traced under ``policy`` in ``dim`` dimensions with ``num_particles`` particles whose
    transfers run on ``kernel``."""
    return _first_row(SORT_TABLE, (resolve(policy), dim, kernel), num_particles,
                      (0, "no row of SORT_TABLE matches: not sorted"))


def _first_row(table, keys: tuple, num_particles: int, otherwise):
    """The row of the first entry of ``table`` -- ((key fields, None for any, ..., fewest particles), row) --
    whose fields match ``keys`` and whose fewest particles are at most ``num_particles``; else ``otherwise``."""
    for (*fields, fewest), row in table:
        if num_particles >= fewest and all(f is None or f == k for f, k in zip(fields, keys)):
            return row
    return otherwise


# XLA compile options for programs built from the library's steps, per policy (``jm.compiler_options``;
# jm.calibrate compiles with them).  CPU: no XNNPACK/YNN library fusions.  XLA:CPU (jax 0.10.2) hands
# reductions to a library ("ynn_fusion"), and a gradient's transposed slot broadcasts are (K, N)
# multiply-reduce over the K stencil slots: at 131k particles each ran at about 2.7 GB/s, 7-8 ms, and
# 14 of them took 70 of a gradient step's 128 ms (mpm88 float64, jax.profiler).  Without them, XLA's
# own loops: the gradient of a 20-step rollout at 131k float64 128.8 -> 98.5 ms a step (two threads); at
# 8k, on the disks and the bar, and every forward step from 8k to 131k, within noise (gradient / forward
# one pinned core: mpm88 FLIP 6.09 -> 6.05, APIC 6.91 -> 6.81, disks 5.32 -> 5.30, bar 3.29 -> 3.26).
# An option a jaxlib does not know is left out (``compiler_options`` checks each once).
XLA_OPTIONS = {"cpu": {"xla_cpu_experimental_ynn_fusion_type": ""}, "gpu": {}}


@cache
def _known_option(name: str, value: str) -> bool:
    """Whether this jaxlib's XLA compiles a program with ``name=value`` (an unknown option is an error)."""
    try:
        jax.jit(lambda a: a + 1, compiler_options={name: value}).lower(jnp.zeros(1)).compile()
    except Exception:  # noqa: BLE001 - XLA says INVALID_ARGUMENT in an error type that moves between versions
        return False
    return True


# The options ``jm.compiler_options(fast_compile=True)`` adds, per policy: a program that compiles sooner and
# may run slower.  CPU: XLA's older LLVM emitters in place of its fusion emitters (fewer, larger fusions).
# Gradients of 100-step rollouts (float64, 2 cores, no compilation cache, two runs each; XLA compile CPU s and
# the gradient's run, default -> fast; benchmarks/README.md "Compile time", with compile_time.py's table of
# every scene: 0.55-0.65x the compile, 1.06-2.09x the rollout's against 1.79-3.55x): bar 1.27 -> 0.68 s, run equal;
# disks 2.81-2.85 -> 1.78-1.79 s, run 21.6 -> 24.0-30.2 ms; rings 3.09-3.19 -> 1.99-2.00 s, run 782-814 ->
# 912-1000 ms; cylinder 5.15-5.39 -> 3.05-3.06 s, run 9.7-14.3 -> 11.2-15.7 ms; mpm88 8k 4.05-4.10 ->
# 2.60-2.62 s, run equal; mpm88 131k (20 steps) 4.04-4.09 -> 2.93-2.98 s, run +3-5%.  A forward rollout
# runs 30% slower with it (mpm88 8k), so it is for gradients and calibrations run a few times, not a default.
XLA_FAST_COMPILE = {"cpu": {"xla_cpu_use_fusion_emitters": False}, "gpu": {}}


def compiler_options(policy: str = "auto", fast_compile: bool = False) -> dict:
    """The XLA compile options (:data:`XLA_OPTIONS`) for programs built from the library's steps under
    ``policy``, those this jaxlib knows: ``jax.jit(loss, compiler_options=jm.compiler_options())``.

    Args:
        policy: "auto" (default: the default JAX backend's), "cpu" or "gpu".
        fast_compile: also the options of :data:`XLA_FAST_COMPILE`: on the CPU the shipped scenes'
            gradients compile in 0.55-0.65x the time and run 0.9-1.4x as long (benchmarks/README.md,
            "Compile time"), worth it for a gradient called a few times; default False.

    Returns:
        {option name: value}, possibly empty.
    """
    check(isinstance(fast_compile, bool), f"fast_compile = {fast_compile!r}; pass True or False")
    policy = resolve(policy)
    options = {**XLA_OPTIONS[policy], **(XLA_FAST_COMPILE[policy] if fast_compile else {})}
    return {name: value for name, value in options.items() if _known_option(name, value)}


# (policy, dimension or None for any, bytes per float or None for any, fewest particles) -> (particles per
# chunk, 0 for the whole step at once; why).  The first row that matches wins (jaxmpm.model.chunks: one USL
# step over the particles in chunks, each chunk's stencil and per-slot arrays small enough to stay in the
# cache).  CPU, 2 cores (AMD EPYC, 2 MiB L2 per core, 32 MiB L3), ms per step, whole step -> chunks
# (2026-11-28, two runs each, the G2P pass written as CHUNK_OUTPUT says):
# * 2D, mpm88 (APIC, quadratic, 128^2 grid):
#   float64: 32k 2.52-2.57 -> 2.85-2.93 (chunks of 16k), 65k 6.51-6.89 -> 5.56-5.74 (16k; 32k 6.10-6.28),
#            131k 14.9-15.4 -> 11.5-11.6 (16k; 8k 13.0-13.6, 32k 12.4), 524k 74.6-76.6 -> 48.9-50.0 (16k,
#            stacked outputs; 8k 58.5, 32k 54.1)
#   float32: 65k 3.50-3.60 -> 4.20-4.26 (32k), 131k 9.0-9.4 -> 7.7-8.1 (32k; 16k 7.9-8.9, 64k 9.0)
# * 3D, benchmarks/gpu.py's mpm3d (27 slots a particle: about 3x the bytes, so smaller chunks), 10 steps:
#   float64: 8k (20^3) 5.25-6.26 -> 6.27-6.53 (4k), 16k (24^3) 10.5-10.8 -> 8.1-8.2 (4k), 32k (32^3)
#            22.8-23.1 -> 16.3-16.7 (4k; 8k 18.3-18.5), 131k (64^3) 106-108 -> 84-88 (4k; 8k 90, 16k 94-98)
#   float32: 8k 3.05-3.11 -> 3.63-3.68 (4k), 32k 17.4-17.9 -> 13.9-14.2 (8k; 4k 15.6-15.7), 65k (48^3)
#            38.4-38.9 -> 28.4-29.8 (8k), 131k 77.5-84 -> 59.5-63.4 (8k; 16k 64-68, 32k 69-70)
# * 1D, the bar (4 particles a cell), 50 steps, best of 5, one process (2026-11-29), whole -> chunks of 64k:
#   float32: Linear 262k 5.19 -> 4.95 (128k 4.75), 1M 24.2 -> 23.4 (128k 22.2); quadratic 262k 6.34 -> 5.46, 1M
#            29.4-29.8 -> 25.1-26.0 (128k 23.8, 256k 24.0-24.3); cubic 262k 8.14 -> 7.05, 1M 33.6 -> 27.4 (128k 25.7)
#   float64: Linear 65k 1.18 -> 1.19, 262k 5.82 -> 6.03, 1M 28.2 -> 39.1 (16k chunks 2-3x slower everywhere);
#            quadratic 262k 7.43-7.73 -> 6.95, 1M 34.8-34.9 -> 41.8-42.1 (128k 40.6, 256k 40.1-40.2): whole
# Smaller steps keep their arrays in the 32 MiB L3, and a chunk only adds the second evaluation of the
# stencil (a step of one chunk: 18% slower at 131k float64 in 2D).
CHUNK_TABLE = (
    (("cpu", 3, 8, 16_000), (4096, "CPU, 3D float64, from 16k particles: the step over chunks of 4k particles, "
                                   "whose arrays stay in the cache (mpm3d, 2 cores: 16k 1.3x, 32k 1.4x, 131k 1.2x "
                                   "the whole step; 8k 0.84-1.0x)")),
    (("cpu", 3, 4, 32_000), (8192, "CPU, 3D float32, from 32k particles: the step over chunks of 8k particles, "
                                   "whose arrays stay in the cache (mpm3d, 2 cores: 32k 1.25x, 65k 1.3x, 131k 1.3x "
                                   "the whole step; 8k 0.85x)")),
    (("cpu", 2, 8, 60_000), (16384, "CPU, 2D float64, from 60k particles: the step over chunks of 16k particles, "
                                    "whose arrays stay in the cache (mpm88, 2 cores: 65k 1.2x, 131k 1.3x, 524k 1.65x "
                                    "the whole step; 32k 0.88x)")),
    (("cpu", 2, 4, 100_000), (32768, "CPU, 2D float32, from 100k particles: the step over chunks of 32k particles, "
                                     "whose arrays stay in the cache (mpm88, 2 cores: 131k 1.1-1.2x the whole step; "
                                     "65k 0.84x)")),
    (("cpu", 1, 4, 250_000), (65536, "CPU, 1D float32, from 250k particles: the step over chunks of 64k particles "
                                     "(the bar, 2 cores: 262k 1.05-1.16x, 1M 1.04-1.23x the whole step)")),
    (("cpu", None, None, 0), (0, "CPU, smaller steps and 1D float64: the whole step at once (its arrays stay in the "
                                 "L3 cache; a chunk adds a second evaluation of the stencil)")),
    (("gpu", None, None, 0), (0, "GPU: the whole step at once (not measured in chunks)")),
)


# How a step in chunks writes its G2P pass's new particle rows (jaxmpm.model.chunks), per (policy, bytes per
# float): "in_place" (a fori_loop carrying the particle arrays, each chunk's rows written over its old
# ones) or "stacked" (a scan whose stacked outputs are the new arrays: XLA zeroes and copies them).  mpm88
# at 131k particles, 2 cores, ms per step, alternated with a git worktree (2026-11-28): float64 chunks of
# 16k, stacked 12.06 and 12.65, in place 11.52 and 11.77; float32 chunks of 32k, stacked 7.80 and 7.95,
# in place 8.57 and 8.62.  Measured again after the stencil's positions were laid out once (2026-11-28,
# alternated in one tree, ms per step): float64 131k stacked 12.66, in place 11.71; float32 131k stacked
# 7.82-8.45, in place 7.64-8.03 (four runs each); float32 524k stacked 32.4-32.8, in place 31.6-32.1; 3D
# float32 65k (48^3, chunks of 8k) stacked 28.2-28.3, in place 27.6-27.7.  So
# float32 writes in place too, and its temporaries shrink with it (524k float32, 10 compiled steps: 67.8
# -> 26.5 bytes a particle).
CHUNK_OUTPUT = {("cpu", 8): "in_place", ("cpu", 4): "in_place"}


def chunk_output(dtype) -> str:
    """"in_place" or "stacked" (:data:`CHUNK_OUTPUT`) for a step in chunks traced now in ``dtype``."""
    return CHUNK_OUTPUT.get((active(), jnp.dtype(dtype).itemsize), "stacked")


# The chunks a step's JVPs and gradients go in (jaxmpm.model.chunks.step_in_chunks: each chunk's P2G and G2P
# recomputed in the reverse pass, one chunk at a time in the cache), apart from the forward step's (CHUNK_TABLE):
# (policy, dimension, bytes per float, fewest particles) -> (particles per chunk, 0 for the whole step's
# derivatives; why).  Where the forward step itself would not fit the device's memory, the derivatives take
# chunks no larger than its (chunks_to_fit).  CPU, 2026-11-29: the gradient of a rollout (d/dv0 of the final
# kinetic energy through sim.run, "auto" checkpoints), 2 cores, ms a step, best of 3-5, each in its own
# process (benchmarks/README.md, "Gradients of a step in chunks").  The whole step's derivatives against the
# forward table's chunks (16k / 32k in 2D): mpm88 float64 65k 45.7-45.8 -> 34.9-36.1, 131k 103.9-105.6 ->
# 68.3-71.0; float32 524k 284.8-297.8 -> 222.4-223.4; mpm3d float64 32k 132.7-138.5 -> 110.1-114.6, float32
# 131k 423.7-425.0 -> 301.2-338.6.  Then the derivatives' own size: 2D float64 chunks of 8k 131k 59.1-59.2
# (4k 67.8-67.9, 16k 70.6-71.8), 65k 30.3-31.0 (16k 38.5-56.4), 32k 14.6-15.9 (4k 16.8, 16k 17.9; whole step
# 19.8-20.8), 16k 7.15 (whole 7.34, within noise); 2D float32 chunks of 16k 524k 205 (32k 232), 131k 48.1 (8k
# 51.5, 32k 58.0, whole 56.6), 32k 9.96 (8k 12.8, whole 11.3); 8k particles lose in either precision (float64
# 2.78-2.93 whole, 3.80-3.93 in 4k, 5.09-5.35 in 2k).  3D keeps the forward table's sizes: float64 32k 4k
# 127.4 (2k 139.0), 8k whole 21.5 (4k 34.3); float32 131k 8k 317.1 (4k 368.4), 32k 8k 81.3 (4k 96.9).  1D (the
# bar, 4 particles a cell, 20 steps, the forward whole, 2026-11-29) loses in chunks: quadratic float32 262k whole
# 26.9 (16k 42.7, 64k 41.4), 1M 97.2 (64k 113.7, 256k 132.3); float64 262k 27.9 (16k 39.0, 64k 32.6); Linear
# float64 1M 97.6 (64k 152.7).
DERIVATIVE_CHUNK_TABLE = (
    (("cpu", 3, 8, 16_000), (4096, "CPU, 3D float64, from 16k particles: derivatives in chunks of 4k particles, "
                                   "each recomputed in the reverse pass (mpm3d, 2 cores: 32k 1.2x the whole "
                                   "step's derivatives)")),
    (("cpu", 3, 4, 32_000), (8192, "CPU, 3D float32, from 32k particles: derivatives in chunks of 8k particles, "
                                   "each recomputed in the reverse pass (mpm3d, 2 cores: 131k 1.3x the whole "
                                   "step's derivatives)")),
    (("cpu", 2, 8, 24_000), (8192, "CPU, 2D float64, from 24k particles: derivatives in chunks of 8k particles, "
                                   "each recomputed in the reverse pass (mpm88, 2 cores: 32k 1.3x, 131k 1.8x the "
                                   "whole step's derivatives; 16k 1.03x, 8k 0.7x)")),
    (("cpu", 2, 4, 24_000), (16384, "CPU, 2D float32, from 24k particles: derivatives in chunks of 16k particles, "
                                    "each recomputed in the reverse pass (mpm88, 2 cores: 32k 1.13x, 131k 1.4x, "
                                    "524k 1.4x the whole step's derivatives; 8k 0.6x)")),
    (("cpu", None, None, 0), (0, "CPU, smaller steps and 1D: the whole step's derivatives (1D in chunks: 1.2-1.6x "
                                 "slower at 262k-1M particles)")),
    (("gpu", None, None, 0), (0, "GPU: the whole step's derivatives (not measured in chunks)")),
)


def choose_derivative_chunking(policy: str, dim: int, num_particles: int, dtype) -> tuple:
    """(particles per chunk of a step's derivatives, 0 for the whole step's; why): the first row of
    :data:`DERIVATIVE_CHUNK_TABLE` that matches a ``dim``-dimensional step of ``num_particles`` particles computing
    in ``dtype`` traced under ``policy``."""
    return _first_row(DERIVATIVE_CHUNK_TABLE, (resolve(policy), dim, jnp.dtype(dtype).itemsize), num_particles,
                      (0, "no row of DERIVATIVE_CHUNK_TABLE matches: the whole step's derivatives"))


# When a step shares its particles among the process's devices, each holding the whole grid
# (jaxmpm.model.devices), and in chunks of how many particles each device steps its share:
# (policy, dimension, bytes per float, fewest particles) -> (particles per chunk on a device, why).  A
# matching row shares them among every local device, where the process has more than one (on a CPU:
# jax.config.update("jax_num_cpu_devices", n) before JAX starts); none: one device.  mpm88, 2 forced CPU
# devices on 2 cores against one device with its two threads, each with its own best chunks, ms a step,
# best of 5, each in its own process, two alternated rounds (2026-11-28, benchmarks/cpu_devices.py): float64
# 32k 2.20-2.26 against 2.18-2.55, 65k 4.76-4.91 against 4.47-4.61, 131k 9.53-9.67 against 8.25-8.94, 524k
# 37.7-40.0 against 32.8-35.6; float32 32k 1.29-2.41 against 1.40-1.46, 65k 3.02-5.36 against 2.75-2.90, 131k
# 7.32-7.34 against 5.43-5.54, 524k 28.8-29.6 against 22.0-22.2.  A device's share in chunks of 16k: 131k
# float32 on two devices 5.2-5.4 (16k), 5.9 (32k), 6.6-7.8 (whole shares).  3D (mpm3d, forced onto 2
# devices): 0.95-1.17x, mixed; GPUs: not measured.  So one device there.
DEVICE_TABLE = (
    (("cpu", 2, 8, 60_000), (16384, "CPU, 2D float64, from 60k particles: shared among the process's CPU devices, "
                                    "each stepping its share in chunks of 16k (mpm88, 2 devices on 2 cores: 65k "
                                    "1.06x, 131k 1.16x, 524k 1.15x one device's step; 32k 1.01x)")),
    (("cpu", 2, 4, 60_000), (16384, "CPU, 2D float32, from 60k particles: shared among the process's CPU devices, "
                                    "each stepping its share in chunks of 16k (mpm88, 2 devices on 2 cores: 65k "
                                    "1.10x, 131k 1.35x, 524k 1.31x one device's step; 32k 0.92x)")),
)


def choose_devices(policy: str, dim: int, num_particles: int, dtype, available: int) -> tuple:
    """(devices, particles per chunk on each, 0 for its share at once; why): the first row of
    :data:`DEVICE_TABLE` that matches a ``dim``-dimensional step of ``num_particles`` particles computing in
    ``dtype`` traced under ``policy``, shared among the ``available`` local devices; one device where no
    row matches, only one is available, or the devices are not the policy's (the CPU policy forced on a
    GPU's devices: the rows were measured on CPU devices)."""
    platform = "cpu" if jax.default_backend() == "cpu" else "gpu"
    row = _first_row(DEVICE_TABLE, (resolve(policy), dim, jnp.dtype(dtype).itemsize), num_particles, None)
    if row is None:
        return 1, 0, "no row of DEVICE_TABLE matches: one device"
    if platform != resolve(policy):
        return 1, 0, f"one device: the {resolve(policy).upper()} policy's row, on {platform.upper()} devices"
    per_chunk, why = row
    if available < 2:
        return 1, 0, f"one device: the process has one ({why}, where it has several)"
    return available, per_chunk, f"{why}: {available} devices"


# A step too large for the device's memory also goes in chunks (issue 32 item 7).  The whole step's temporary
# buffers per particle, in floats per stencil slot: XLA's temp buffers of a compiled 5-step rollout without chunks
# (``compiled.memory_analysis()``, CPU, jax 0.10.2, 2026-11-29; Linear, quadratic and cubic B-splines x APIC and
# FLIP x float32 and float64, one material; 1D 4.9k particles on 4096 cells, 2D 23.7k on 128^2, 3D 54.9k on 32^3):
# 1D 6.7-13.2, 2D 9.1-18.9, 3D 13.5-24.03 (Linear FLIP, float32).  The table takes the largest, rounded up.  On an
# H100 the whole 2D and 3D programs took less (benchmarks/README.md, "Measured on an H100").  A step whose
# temporaries would take more than STEP_MEMORY_SHARE of the device's free memory runs over chunks whose temporaries
# take at most that share.
# Several velocity fields a node (multimaterial mode, jm.Contact(materials=M): M fields) take more: the same scenes
# cut into M slabs, M = 2, 3, 4, 8, with the contact's defaults and with its heaviest options (separation=0.5, which
# scatters the nodal mass moments: up to +20 floats a slot; Coulomb friction, "average" normals and volume gradients
# add 0.6 at most), Linear, quadratic (and uGIMP) and cubic B-splines x APIC and FLIP x float32 and float64, XLA's
# temp buffers of a compiled 3-step loop (CPU, jax 0.10.2, 2026-11-29), in floats per slot: M = 2 1D 9.6-25.7, 2D
# 11.2-35.9, 3D 17.9-44.1; M = 8 1D 22.6-65.9, 2D 13.3-56.1, 3D 18.9-52.6 (float32 steps count more floats than
# float64 ones: 2D quadratic M = 2 21.1-32.8 against 13.5-24.0).  Two parts: the contact's own temporaries, the same
# for any M (a particle scatters to its own field only), MULTIFIELD_FLOATS_PER_SLOT more a slot; and each field past
# the first, its nodal columns, up to 19 floats a particle (27 a node) at these scenes' 2 particles a cell along each
# axis on grids 0.6^D full, FIELD_FLOATS_PER_PARTICLE.  Each the largest, fitted together and rounded up: within
# 1-7% of the Linear M = 2 steps; the quadratic and cubic 3D ones take about 3/4 of it.  A body sparser on its grid
# carries more per particle, and chunks do not make the nodal columns smaller.
# The derivatives' chunks (DERIVATIVE_CHUNK_TABLE) are sized by the same bound: one step's gradient, the step and its
# pullback in one program, took 0.7-1.6x its forward step's temporaries and at most 12.6, 17.6 and 24.7 floats a slot
# in 1D-3D (the same shapes, schemes and dtypes, 2026-11-29; tests/test_chunks.py checks the bound).
STEP_FLOATS_PER_SLOT = {1: 14, 2: 19, 3: 25}
MULTIFIELD_FLOATS_PER_SLOT = {1: 4, 2: 13, 3: 18}
FIELD_FLOATS_PER_PARTICLE = 19
STEP_MEMORY_SHARE = 0.25
SMALLEST_CHUNK = 1024  # particles: fewer would not save memory worth a chunk's second stencil evaluation


def step_floats(dim: int, slots: int, fields: int = 1) -> float:
    """Floats of the whole step's temporaries per particle, for a ``dim``-dimensional step with ``slots`` stencil
    slots a particle and ``fields`` velocity fields a node: :data:`STEP_FLOATS_PER_SLOT` a slot, with several
    fields :data:`MULTIFIELD_FLOATS_PER_SLOT` more a slot and :data:`FIELD_FLOATS_PER_PARTICLE` for each field
    past the first."""
    per_slot = STEP_FLOATS_PER_SLOT[dim] + (MULTIFIELD_FLOATS_PER_SLOT[dim] if fields > 1 else 0)
    return per_slot * slots + FIELD_FLOATS_PER_PARTICLE * (fields - 1)


def chunks_to_fit(dim: int, num_particles: int, slots: int, dtype, free_bytes: int, fields: int = 1) -> tuple:
    """(particles per chunk, 0 when the whole step fits; why) for a ``dim``-dimensional step of ``num_particles``
    particles with ``slots`` stencil slots each and ``fields`` velocity fields a node (the model's
    ``velocity_fields``), computing in ``dtype``, on a device with ``free_bytes`` free: chunks (a power of two, at
    least :data:`SMALLEST_CHUNK`) whose temporaries take at most :data:`STEP_MEMORY_SHARE` of the free memory when
    the whole step's would take more (:func:`step_floats`)."""
    per_particle = step_floats(dim, slots, fields) * jnp.dtype(dtype).itemsize
    need, budget = per_particle * num_particles, STEP_MEMORY_SHARE * free_bytes
    if need <= budget:
        return 0, ""
    per = max(SMALLEST_CHUNK, 2 ** int(math.floor(math.log2(max(1.0, budget / per_particle)))))
    return per, (f"the whole step's temporaries (about {size_text(need)}) would take more than "
                 f"{STEP_MEMORY_SHARE:.0%} of the device's free memory ({size_text(free_bytes)}): chunks of at most "
                 f"{per} particles")


def choose_chunking(policy: str, dim: int, num_particles: int, dtype) -> tuple:
    """(particles per chunk, 0 for the whole step at once; why): the first row of
    :data:`CHUNK_TABLE` -- (policy, dimension, bytes per float, fewest particles) -> row -- that
    matches a ``dim``-dimensional step of ``num_particles`` particles computing in ``dtype`` traced
    under ``policy``."""
    return _first_row(CHUNK_TABLE, (resolve(policy), dim, jnp.dtype(dtype).itemsize), num_particles,
                      (0, "no row of CHUNK_TABLE matches: the whole step at once"))


_kernel = contextvars.ContextVar("jaxmpm_transfer_kernel", default=None)


@contextlib.contextmanager
def use_kernel(name, options=None):
    """Trace the enclosed transfers with kernel ``name`` ("xla" or "pallas", with ``options`` for
    it); None: the kernel registered for the policy (``jaxmpm.transfer.kernels.register_kernel``)."""
    check(name is None or one_of(name, KERNEL_CHOICES[1:]),
          f"kernel = {name!r}; choose one of {', '.join(KERNEL_CHOICES)}")
    token = _kernel.set(None if name is None else (name, tuple(sorted((options or {}).items()))))
    try:
        yield
    finally:
        _kernel.reset(token)


def kernel_in_force():
    """(name, options as sorted items) of the kernel forced for the code being traced, or None."""
    return _kernel.get()
