"""Transfer kernels: how P2G scatters the tagged per-particle quantities and how G2P gathers, per backend.

The physics never scatters or gathers by itself: terms and schemes hand the transfer layer
per-particle quantities tagged with their contraction (:mod:`jaxmpm.transfer.contractions`) and
ask for nodal fields back at the particles (``Transfer.gather``, ``velocity_gradient``, ...).  A
:class:`Kernel` does the work; one is registered per backend policy ("cpu", "gpu"; see
:mod:`jaxmpm.transfer.backend`) and the policy in force when a step is traced picks it.  Each
kernel brings its own derivative rules: P2G's transpose is a G2P gather and vice versa, so
``jax.grad``, ``jax.vmap`` and the XPIC/FMPM series run through the same kernel.

The default kernel, :class:`~jaxmpm.transfer.kernels.xla.XLAKernel`, forms the per-slot values
from the stencil's per-axis factors and scatters every column in one ``lax.scatter_add``; it is
registered for both policies.  :class:`~jaxmpm.transfer.kernels.pallas.PallasKernel` runs P2G and
G2P as fused Pallas kernels with atomic adds (interpret mode on the CPU); a model uses it where
``Simulation(kernel=...)`` forces it or the kernel table of :mod:`jaxmpm.transfer.backend` picks
it (``jm.backend_info`` says which and why).  A new kernel is one file defining a :class:`Kernel`
subclass and one :func:`register_kernel` call.
"""

from __future__ import annotations

import contextlib
import contextvars

import equinox as eqx
import jax

from ...core.errors import check
from ...core.validate import one_of
from ..backend import POLICIES, active, kernel_in_force
from ..shapes import of_trace


class Kernel(eqx.Module):
    """How P2G and G2P run on a backend.  A subclass defines every method below; all take the
    particles' stencil (:class:`jaxmpm.StencilBase`) and work on planar per-slot data inside."""

    def p2g(self, stencil, columns: dict, num_nodes: int) -> dict:
        """{name: nodal array}: each column (a contraction or a tuple of them, summed) scattered
        over the particles, all in one pass where the kernel can."""
        raise NotImplementedError

    def gather(self, stencil, u):
        """(S u)_p = sum_i S_pi u_i for nodal u (n,) or (n, C): (N,) or (N, C)."""
        raise NotImplementedError

    def velocity_gradient(self, stencil, v):
        """sum_i v_i (x) G_pi for a nodal vector field v (n, D): (N, D, D)."""
        raise NotImplementedError

    def scalar_gradient(self, stencil, u):
        """sum_i u_i G_pi for a nodal scalar u (n,): (N, D)."""
        raise NotImplementedError

    def affine_moment(self, stencil, v):
        """sum_i S_pi v_i (x_i - X_p)^T for a nodal vector field v (n, D): (N, D, D)."""
        raise NotImplementedError


_KERNELS: dict = {}

# while a G2P reads the grid (shared_reads): the stencil's node numbers, the grid's fields read together, and
# {key: (node numbers, nodal field, its slot values)}
_SHARED_READS: contextvars.ContextVar = contextvars.ContextVar("jaxmpm_shared_reads", default=None)


@contextlib.contextmanager
def shared_reads(index, fields=()):
    """Within the block, a kernel reads each nodal field at the slots of the node numbers ``index`` once,
    however many G2P operators use it (APIC's S v~, its affine moment and the strain update's grad v~ all
    read v~), and the ``fields`` (the grid's v, a and v~) together, as one field of all their components,
    on the first read of any of them.  The values are the same; in reverse mode the operators' cotangents
    are summed per slot and go back onto the nodes in one scatter instead of one per operator and field.
    What was read is forgotten when the block ends; what is read inside a nested trace (a loop body, a
    stage boundary's branch) is used there and not kept.

    Args:
        index: the node numbers of the particles' stencil (``stencil.index``).
        fields: nodal arrays (n, C) read together (default: none).
    """
    token = _SHARED_READS.set({"index": index, "fields": tuple(fields), "read": {}})
    try:
        yield
    finally:
        _SHARED_READS.reset(token)


def shared_read(key, index, field, read, read_together):
    """The slot values of nodal ``field`` at node numbers ``index``: ``read()`` outside :func:`shared_reads`;
    inside, the values read earlier for the same (identical) ``index``, ``field`` and ``key``, else
    ``read_together(fields)`` (a list of values, one per field) for the block's fields when ``field`` is
    one of them, else ``read()``."""
    memory = _SHARED_READS.get()
    if memory is None:
        return read()
    known = memory["read"]

    def keep(f, values):  # only values of the field's own trace: a read inside a nested trace (a loop body, a
        # stage boundary's branch) is used there and not kept, so none of its tracers escapes it
        if of_trace(values, f):
            known[key, id(index), id(f)] = (index, f, values)
        return values

    found = known.get((key, id(index), id(field)))
    if found is not None and found[0] is index and found[1] is field:
        return found[2]
    together = memory["fields"]
    if memory["index"] is index and any(f is field for f in together):
        values = [keep(f, v) for f, v in zip(together, read_together(together))]
        return next(v for f, v in zip(together, values) if f is field)
    return keep(field, read())


def register_kernel(policy: str, kernel: Kernel) -> Kernel:
    """Use ``kernel`` for the transfers traced under ``policy`` ("cpu" or "gpu").  The kernel is
    chosen when a step is traced, so the programs JAX compiled with the previous one are dropped
    (``jax.clear_caches``): the next call retraces with the new kernel.

    Args:
        policy: the backend policy, "cpu" or "gpu" (``Simulation(backend=...)``; "auto" picks
            one of them).
        kernel: a :class:`Kernel` instance.

    Returns:
        ``kernel``.
    """
    check(one_of(policy, POLICIES) and policy != "auto",
          f"register_kernel: policy = {policy!r}; choose 'cpu' or 'gpu' (jaxmpm.transfer.backend)")
    check(isinstance(kernel, Kernel), f"register_kernel: {kernel!r} is not a jaxmpm Kernel")
    if _KERNELS.get(policy) is not kernel:
        if policy in _KERNELS:
            jax.clear_caches()
        _KERNELS[policy] = kernel
    return kernel


def kernel() -> Kernel:
    """The kernel for the code being traced: the one forced by ``Simulation(kernel=...)``
    (:func:`jaxmpm.transfer.backend.use_kernel`), else the one registered for the policy in force."""
    forced = kernel_in_force()
    base = _KERNELS[active()] if forced is None else _stock_kernel(forced[0], forced[1], active())
    return in_window(base)  # on the sharded path, the device's window of the grid (jaxmpm.parallel)


_STOCK: dict = {}


def _stock_kernel(name: str, options: tuple, policy: str) -> Kernel:
    """The library's own kernel ``name`` with ``options`` ("xla": :class:`XLAKernel`, by default as the
    backend's table says; "pallas": :class:`~jaxmpm.transfer.kernels.pallas.PallasKernel`), one instance per key."""
    key = (name, options, policy)
    if key not in _STOCK:
        if name == "pallas":
            from .pallas import PallasKernel  # imported on first use: Pallas is not needed otherwise

            _STOCK[key] = PallasKernel(**dict(options))
        else:
            _STOCK[key] = XLAKernel(**dict(options))
    return _STOCK[key]


from .windowed import in_window  # noqa: E402
from .xla import XLAKernel  # noqa: E402  (registers itself for both policies)

__all__ = ["Kernel", "XLAKernel", "kernel", "register_kernel", "shared_reads"]
