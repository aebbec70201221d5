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
  values are exactly the inputs (under ``vmap`` the cond becomes a select that picks them).
* ``"gpu"`` (every other backend's default): boundaries are identities.  On a GPU the
  conditional costs a device-to-host round trip of its predicate per boundary (measured on an
  H100: 1.56x slower 3D step at 1M particles, 7x at 8k), and fusion is what one wants there.

``Simulation(..., backend="auto" | "cpu" | "gpu")`` picks the policy; ``"auto"`` resolves from
``jax.default_backend()`` when the step is traced.  Both policies give the same numbers: a
boundary changes where values are computed, not how (tests/test_open_core.py, 1e-12).
"""

from __future__ import annotations

import contextlib
import contextvars

import jax
import jax.numpy as jnp

from ._errors import check

POLICIES = ("auto", "cpu", "gpu")

_active = contextvars.ContextVar("jaxmpm_backend_policy", default="auto")


def resolve(policy: str) -> str:
    """``"cpu"`` or ``"gpu"`` for a policy name (``"auto"``: from the default JAX backend)."""
    check(policy in POLICIES, f"backend = {policy!r}; choose one of {', '.join(POLICIES)}")
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
    if active() != "cpu":
        return arrays
    leaves = jax.tree_util.tree_leaves(arrays)
    always = _always_true(leaves[0])
    return jax.lax.cond(always, lambda a: a, lambda a: jax.tree_util.tree_map(jnp.zeros_like, a), arrays)


def evaluate_once(fn, *args):
    """Stage boundary around a computation: ``fn(*args)``, evaluated into its own buffers under the
    CPU policy (like :func:`materialise`, but without copying the result); ``fn(*args)`` inline
    under the GPU policy."""
    if active() != "cpu":
        return fn(*args)
    leaves = jax.tree_util.tree_leaves(args)
    x = next(leaf for leaf in leaves if jnp.issubdtype(leaf.dtype, jnp.floating))
    out = jax.eval_shape(fn, *args)
    return jax.lax.cond(_always_true(x), fn,
                        lambda *a: jax.tree_util.tree_map(lambda o: jnp.zeros(o.shape, o.dtype), out), *args)


def _always_true(x):
    """``not (x[0] > +inf)``: true for every float, NaN included, and not foldable by XLA."""
    return jnp.logical_not(x.reshape(-1)[0] > jnp.inf)
