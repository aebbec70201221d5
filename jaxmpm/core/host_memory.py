"""The host's memory allocator (glibc's ``malloc`` on Linux), and what XLA:CPU's programs pay it at every call.

XLA:CPU allocates a program's temporary buffer when the program is called and frees it when the call ends.
glibc hands out an allocation of more than 32 MiB (the largest threshold it adapts to) as fresh pages mapped from
the kernel, and unmaps them when it is freed, so every call of such a program touches new memory: one page fault
per 4 KiB page.  A gradient of the mpm88 scene (8192 particles, float64, 100 steps, every step's state kept)
allocates 79 MiB a call: 20 332 page faults, about 45 ms of a 317 ms call on one core.  Forward runs hold smaller
temporaries (under 32 MiB they come from glibc's heap, and the next call reuses them) or spread one allocation over
many steps, and gain nothing.

:func:`reuse_host_memory` has glibc serve every allocation from its heap and keep what is freed there, so that the
next call finds the same pages in memory, once the heap has settled after a call or two (benchmarks/README.md,
"Reusing the host's memory"):

* ``M_MMAP_MAX = 0``: no allocation is mapped on its own;
* ``M_TRIM_THRESHOLD = 1 GiB``: up to 1 GiB freed at the top of the heap stays with the process;
* ``M_ARENA_MAX = 1``: every thread allocates from the main heap (an allocation too large for a thread's own heap,
  64 MiB, would be mapped on its own anyway).  It applies to threads that have not allocated yet, so it is set
  before JAX starts its threads: at ``import jaxmpm`` with ``JAXMPM_REUSE_HOST_MEMORY=1`` in the environment, or
  by calling :func:`reuse_host_memory` before the first computation.

It is not the default, for two reasons.  The setting is the whole process's, every library's allocations included.
And memory kept in one heap fragments: a run's peak resident size grows, since a freed block serves only requests
that fit in it (``benchmarks/run_memory.py``, mpm88 with 4.2M particles in float32: 720 MiB at the peak against 1370
with it; donated, 496 against 807).  So it suits a loop of gradients of a model of moderate size, not a run at the
edge of the machine's memory.  Elsewhere than glibc (macOS, Windows, musl) nothing changes.
"""

from __future__ import annotations

import ctypes
import os
import platform

from .errors import check

# mallopt(3) parameters (glibc's malloc.h)
M_TRIM_THRESHOLD = -1
M_MMAP_MAX = -4
M_ARENA_MAX = -8

#: the settings of :func:`reuse_host_memory`
REUSE = {M_MMAP_MAX: 0, M_TRIM_THRESHOLD: 1 << 30, M_ARENA_MAX: 1}
#: glibc's defaults, which ``reuse_host_memory(False)`` sets again (as fixed values: glibc's adaptive thresholds
#: stay off once a parameter has been set)
DEFAULTS = {M_MMAP_MAX: 65536, M_TRIM_THRESHOLD: 128 * 1024, M_ARENA_MAX: 0}

ENVIRONMENT = "JAXMPM_REUSE_HOST_MEMORY"


def _glibc():
    """glibc's handle, or None where the C library is another (or cannot be loaded)."""
    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return None
    try:
        return ctypes.CDLL("libc.so.6")
    except OSError:
        return None


def reuse_host_memory(enabled: bool = True) -> bool:
    """Have the host's allocator (glibc) keep the memory XLA:CPU's programs free, so that the next call reuses it
    instead of taking fresh pages from the kernel (a page fault each 4 KiB).  A gradient whose temporaries exceed
    32 MiB gains: mpm88 at 8192 particles (float64, 100 steps, every step's state kept, one core) 8-9% faster
    under FLIP (79 MiB paged in a call) and 12-15% under APIC (105 MiB); forward runs, and gradients of small
    models, gain nothing (module docstring).

    Call it before JAX runs anything (its worker threads count too), or set ``JAXMPM_REUSE_HOST_MEMORY=1`` in the
    environment before ``import jaxmpm``.  It changes the whole process's allocator, and a large run's peak
    memory grows with it (720 MiB against 1370 for mpm88 at 4.2M particles): an opt-in for loops of gradients.

    Args:
        enabled: True (default) to reuse freed memory; False to set glibc's defaults again (and hand free memory
            back, ``malloc_trim``).

    Returns:
        Whether the allocator took the settings: False where it is not glibc's (macOS, Windows, musl).
    """
    check(isinstance(enabled, bool), f"reuse_host_memory: enabled = {enabled!r} must be True or False")
    libc = _glibc()
    if libc is None:
        return False
    done = all(libc.mallopt(parameter, value) == 1 for parameter, value in (REUSE if enabled else DEFAULTS).items())
    if not enabled:
        libc.malloc_trim(0)
    return done


def apply_from_environment() -> bool:
    """:func:`reuse_host_memory` when ``JAXMPM_REUSE_HOST_MEMORY`` is 1, true or yes (at ``import jaxmpm``)."""
    value = os.environ.get(ENVIRONMENT, "").strip().lower()
    return reuse_host_memory() if value in ("1", "true", "yes", "on") else False


apply_from_environment()  # at import, before JAX starts its threads (jaxmpm/__init__.py imports this module first)
