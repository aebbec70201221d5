"""Python's cyclic garbage collector while jaxmpm traces and compiles.

Tracing a program allocates hundreds of thousands of short-lived Python objects (tracers, jaxpr
variables and equations), and CPython's collector runs a collection of its youngest generation
every 700 allocations of container objects, and a full one, which walks every object of the
process (jax's and jaxlib's modules included), every 100 of those.  Almost none of what it walks is
garbage: the objects die by reference counting.  Raising the first threshold while a program is
traced takes the full collections while a 100-step rollout's gradient is traced from 2 to 0, and
its tracing from 0.87 to 0.67 s (mpm88 APIC) and from 0.72 to 0.53 s (disks FLIP)
(benchmarks/tracing_gc.py; benchmarks/README.md, "Python's garbage collector while tracing").
Other compilers written in Python tune their collector the same way (mypy's build raises the
threshold; PyTorch's dynamo defers full collections while it compiles).

:func:`fewer_collections` does it for the span of a call and then restores the thresholds, so a
process's own setting outside jaxmpm's calls is left as it was; a threshold already at least as
high, or a collector switched off, is left alone.
"""

from __future__ import annotations

import contextlib
import functools
import gc

#: the first-generation threshold while jaxmpm traces and compiles (CPython's default: 700)
TRACING_THRESHOLD = 20_000


@contextlib.contextmanager
def fewer_collections():
    """Collect the youngest generation every :data:`TRACING_THRESHOLD` allocations (not 700) inside
    the block; the thresholds as they were after it."""
    before = gc.get_threshold()
    if not gc.isenabled() or before[0] >= TRACING_THRESHOLD:
        yield
        return
    gc.set_threshold(TRACING_THRESHOLD, *before[1:])
    try:
        yield
    finally:
        gc.set_threshold(*before)


def with_fewer_collections(fn):
    """``fn`` run inside :func:`fewer_collections` (a decorator)."""

    @functools.wraps(fn)
    def wrapped(*args, **kwargs):
        with fewer_collections():
            return fn(*args, **kwargs)

    return wrapped
