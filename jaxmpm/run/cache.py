"""A persistent cache of compiled programs, for notebooks and scripts that are run again.

Short runs are compile-bound: notebook 03 (calibration) spends about 49 of its 55 s on this CPU
tracing and compiling (38.9 s in XLA's backend alone), and ``jm.calibrate``'s first iteration is
nearly all compilation.  JAX can keep compiled programs on disk and reuse them in a later process
when the program is the same; :func:`compilation_cache` switches that on.  It is opt-in: the
library never writes to the disk on import.
"""

from __future__ import annotations

import os
from pathlib import Path

import jax

from ..core.errors import check

ENV_VAR = "JAXMPM_CACHE_DIR"


def default_cache_dir() -> Path:
    """``$JAXMPM_CACHE_DIR`` if set, else ``$XDG_CACHE_HOME/jaxmpm/xla`` (``~/.cache/jaxmpm/xla``)."""
    if os.environ.get(ENV_VAR):
        return Path(os.environ[ENV_VAR]).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base).expanduser() / "jaxmpm" / "xla"


def compilation_cache(path=None, *, min_compile_seconds: float = 0.5) -> Path:
    """Keep every compiled program that took at least ``min_compile_seconds`` to compile in
    ``path`` (default :func:`default_cache_dir`) and reuse it in later processes: a notebook or
    script run again then skips XLA's compilation (tracing still happens).  Returns the folder.

    Call it once, early (the first cell of a notebook): programs compiled before the call are not
    kept.  The cache is JAX's own (``jax_compilation_cache_dir``); its entries are keyed by the
    program, the JAX version and the device, and are safe to delete at any time.  Keep one folder
    per machine.

    Args:
        path: the cache folder (created if missing); None (the default): ``$JAXMPM_CACHE_DIR``,
            else ``$XDG_CACHE_HOME/jaxmpm/xla`` (``~/.cache/jaxmpm/xla``).
        min_compile_seconds: keep only programs that took at least this long to compile, a
            number >= 0 (default 0.5).
    """
    check(isinstance(min_compile_seconds, (int, float)) and min_compile_seconds >= 0,
          f"compilation_cache: min_compile_seconds = {min_compile_seconds!r} must be a number >= 0")
    folder = default_cache_dir() if path is None else Path(path).expanduser()
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        check(False, f"compilation_cache: cannot create the folder {str(folder)!r} ({err}); pass another path "
                     f"or set ${ENV_VAR}")
    check(folder.is_dir(), f"compilation_cache: path {str(folder)!r} is not a folder; pass a folder")
    current = jax.config.jax_compilation_cache_dir
    check(current in (None, "", str(folder)),
          f"compilation_cache: JAX already caches compiled programs in {current!r}; a process has one cache "
          f"folder, so call compilation_cache() before anything else sets it (or pass path={current!r})")
    jax.config.update("jax_compilation_cache_dir", str(folder))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", float(min_compile_seconds))
    return folder
