"""Size limits checked before anything is allocated: the step counter's range, the memory a grid,
a particle set or a run's saved frames will need against the memory this machine has.  Each limit
fails at once with one line stating the size and what to change (the CLI maps keywords to its
options)."""

from __future__ import annotations

import math
import os

from .errors import InputError

#: the step counter (``State.step``) is int32
MAX_STEPS = 2**31 - 1


def available_bytes() -> int:
    """Memory a run may use: MemAvailable of /proc/meminfo (Linux), else the physical memory;
    ``JAXMPM_MEMORY_BYTES`` overrides both (tests, shared machines)."""
    override = os.environ.get("JAXMPM_MEMORY_BYTES", "").strip()
    if override:
        try:
            value = float(override)
        except ValueError:
            value = math.nan
        if not (math.isfinite(value) and value > 0):
            raise InputError(f"JAXMPM_MEMORY_BYTES = {override!r} must be a positive number of bytes, e.g. 8e9; "
                             "unset it to use the memory available")
        return int(value)
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):  # pragma: no cover (not POSIX)
        return 2**62


def gib(nbytes: float) -> str:
    return f"{nbytes / 2**30:.3g} GiB"


def size_text(nbytes: float) -> str:
    """Bytes for a reader, in the largest unit that is at least 1: '312.5 KiB', '1.4 GiB'."""
    for unit, scale in (("GiB", 2**30), ("MiB", 2**20), ("KiB", 2**10)):
        if nbytes >= scale:
            return f"{nbytes / scale:.1f} {unit}"
    return f"{int(nbytes)} B"


def require_memory(what: str, nbytes: float, fix: str) -> None:
    """Raise :class:`InputError` when ``nbytes`` exceed the memory available."""
    have = available_bytes()
    if nbytes > have:
        raise InputError(f"{what} needs about {gib(nbytes)}, more than the {gib(have)} of memory available; {fix}")


def require_steps(steps: int, fix: str = "shorten t_end or use a larger dt") -> None:
    """The step counter is int32: a run may not go past step 2^31 - 1."""
    if steps > MAX_STEPS:
        raise InputError(f"the run needs {steps:.4g} steps, beyond the step counter's limit "
                         f"{MAX_STEPS} (int32); {fix}")
