"""A persistent cache of compiled programs, on by default: a notebook, script or command run again
reads its programs back from the disk instead of compiling them.

Short runs are compile-bound: notebook 03 (calibration) spends about 49 of its 55 s on this CPU
tracing and compiling (38.9 s in XLA's backend alone), and ``jm.calibrate``'s first iteration is
nearly all compilation.  JAX can keep compiled programs on disk and reuse them in a later process
when the program is the same (``jax_compilation_cache_dir``).  ``import jaxmpm`` points JAX at
:func:`default_cache_dir` unless JAX already has a folder (``JAX_COMPILATION_CACHE_DIR``,
``jax.config``) or ``$JAXMPM_CACHE`` is ``0``; it only sets JAX's options, and the folder is made
at the first compilation.  :func:`compilation_cache` picks another folder or switches it off.

jaxmpm's folder is read and written by :class:`FolderCache` in place of JAX's own file cache
(which needs the ``filelock`` package to bound its size, and writes its files in place, so that a
process killed mid-write or two processes writing one entry leave a truncated entry that every
later process fails to read, with a warning, and never replaces): each entry is written to a
temporary file and renamed into place, an entry that does not decompress is deleted and compiled
again, and the folder is kept under a size bound by deleting the entries used longest ago.
"""

from __future__ import annotations

import os
import sys
import threading
import time
import uuid
import warnings
from pathlib import Path

import jax

from ..core.errors import check

ENV_VAR = "JAXMPM_CACHE_DIR"  #: the folder (default: the platform's user cache folder, see default_cache_dir)
SWITCH_VAR = "JAXMPM_CACHE"  #: "0" (or false, no, off): import jaxmpm sets no cache folder
MAX_BYTES_VAR = "JAXMPM_CACHE_MAX_BYTES"  #: the size bound in bytes (default DEFAULT_MAX_BYTES)
DEFAULT_MAX_BYTES = 1 << 30  #: 1 GiB
#: keep programs that took at least this long to compile: every one.  JAX's own default, 1 s, keeps
#: 17 of notebook 03's 156 programs and 0.5 s 18; run again, the notebook took 50 s with all of
#: them kept, 56 s at 0.1 s and 71 s at 0.5 s, for 0.4 MB more (benchmarks/notebook_rerun.py)
DEFAULT_MIN_COMPILE_SECONDS = 0.0
_OFF = ("0", "false", "no", "off")
_ON = ("", "1", "true", "yes", "on")
_SUFFIX = "-cache"  # the end of every entry's file name, as in JAX's own file cache
_STALE_TEMP_SECONDS = 3600.0  # a temporary file this old is a killed writer's

_state = {"folder": None, "max_bytes": DEFAULT_MAX_BYTES}  # the folder jaxmpm set, None when none
_lock = threading.Lock()


def default_cache_dir() -> Path:
    """The folder jaxmpm keeps compiled programs in: ``$JAXMPM_CACHE_DIR`` if set, else
    ``jaxmpm/xla`` in the platform's user cache folder: ``$XDG_CACHE_HOME`` or ``~/.cache`` on
    Linux, ``~/Library/Caches`` on macOS, ``%LOCALAPPDATA%`` on Windows."""
    if os.environ.get(ENV_VAR):
        return Path(os.environ[ENV_VAR]).expanduser()
    if sys.platform == "win32":
        base = os.environ.get("LOCALAPPDATA") or Path.home() / "AppData" / "Local"
    elif sys.platform == "darwin":
        base = Path.home() / "Library" / "Caches"
    else:
        base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base).expanduser() / "jaxmpm" / "xla"


def compilation_cache(path=None, *, enabled: bool = True, min_compile_seconds: float | None = None,
                      max_bytes: int | None = None) -> Path | None:
    """Where compiled programs are kept on disk and reused by later processes, or switch that off.

    It is on by default: ``import jaxmpm`` keeps every compiled program in
    :func:`default_cache_dir` (``$JAXMPM_CACHE_DIR``, else the platform's user cache folder), so a
    notebook or script run again skips XLA's compilation (tracing still happens).  Call this to
    pick another folder (``jm.compilation_cache(path)``), to switch it off
    (``jm.compilation_cache(False)``; ``JAXMPM_CACHE=0`` in the environment, or ``--no-cache`` on
    the command line, does the same) or to change its bounds.  A call without a folder keeps to
    the environment (``JAXMPM_CACHE=0``: it stays off; ``JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS``
    is the default threshold), so a notebook that calls it first thing stays switchable.  Call it
    early: programs compiled before the call are kept in the folder in use then.

    A folder set through JAX itself (``JAX_COMPILATION_CACHE_DIR``, or
    ``jax.config.update("jax_compilation_cache_dir", ...)`` before the first compilation) is
    JAX's: jaxmpm neither replaces nor switches it off, and ``compilation_cache()`` returns it (its
    entries are not kept per number of CPUs, as jaxmpm's are).  jaxmpm's entries are keyed by the
    program, the JAX and XLA versions, the compiler options, the device and the number of CPUs the
    process may run on (a program compiled under ``taskset -c 0`` runs on one thread, so it is not read
    back by a process with more); they are safe to delete at any time, and several processes may use
    one folder at once.  An entry that cannot be read (a truncated or corrupt file) is deleted and compiled
    again.  Keep one folder per machine: the folder is trusted, so do not share it with users you
    do not trust.

    Args:
        path: the cache folder (created if missing); None (the default): :func:`default_cache_dir`;
            False: switch the cache off (as ``enabled=False``).
        enabled: False switches off the cache folder jaxmpm set (the default True).
        min_compile_seconds: keep only programs that took at least this long to compile, a number
            >= 0 (default 0: every program, so that the gradient and calibration programs, and the
            small eager ones, are read back; JAX's own default is 1 s).
        max_bytes: the folder's size bound in bytes, a positive integer: past it the entries used
            longest ago are deleted (default ``$JAXMPM_CACHE_MAX_BYTES``, else 1 GiB).

    Returns:
        The folder in use, or None when the cache is off.
    """
    check(path is None or isinstance(path, (bool, str, os.PathLike)),
          f"compilation_cache: path = {path!r} must be a folder (a str or Path), None (the default folder) or "
          "False (off)")
    check(isinstance(enabled, bool), f"compilation_cache: enabled = {enabled!r} must be True or False")
    check(min_compile_seconds is None or (isinstance(min_compile_seconds, (int, float))
                                          and not isinstance(min_compile_seconds, bool) and min_compile_seconds >= 0),
          f"compilation_cache: min_compile_seconds = {min_compile_seconds!r} must be a number >= 0")
    check(max_bytes is None or (isinstance(max_bytes, int) and not isinstance(max_bytes, bool) and max_bytes > 0),
          f"compilation_cache: max_bytes = {max_bytes!r} must be a positive integer (bytes)")
    if path is False or not enabled:
        _switch_off()
        return None
    current = jax.config.jax_compilation_cache_dir
    ours = _state["folder"] is not None and current == _state["folder"]
    if path is None or path is True:
        if current and not ours:  # JAX's folder, set by the user: used as it is
            return Path(current)
        if _switched_off_by_environment():
            return None
        folder = default_cache_dir()
    else:
        folder = Path(path).expanduser()
    # refused before anything is created: a refused call leaves no folder behind
    check(not current or ours or current == str(folder),
          f"compilation_cache: JAX already caches compiled programs in {current!r} (set through JAX); a process "
          f"has one cache folder, so pass path={current!r} or unset JAX's (JAX_COMPILATION_CACHE_DIR)")
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        check(False, f"compilation_cache: cannot create the folder {str(folder)!r} ({err}); pass another path "
                     f"or set ${ENV_VAR}")
    check(folder.is_dir(), f"compilation_cache: path {str(folder)!r} is not a folder; pass a folder")
    if max_bytes is None:
        max_bytes = _env_max_bytes()
    _switch_on(str(folder), _default_min_seconds() if min_compile_seconds is None else min_compile_seconds, max_bytes)
    return folder


def enable_by_default() -> Path | None:
    """What ``import jaxmpm`` does: point JAX at :func:`default_cache_dir`, unless ``$JAXMPM_CACHE``
    is 0 or JAX already has a cache folder.  Nothing touches the disk until the first compilation,
    and nothing here raises: a value it cannot read is a warning.  Returns the folder, or None."""
    if _switched_off_by_environment():
        return None
    if jax.config.jax_compilation_cache_dir or not jax.config.jax_enable_compilation_cache:
        return None  # the user's, through JAX
    folder = default_cache_dir()
    _switch_on(str(folder), _default_min_seconds(), _env_max_bytes())
    return folder


def _switched_off_by_environment() -> bool:
    switch = os.environ.get(SWITCH_VAR, "").strip().lower()
    if switch not in _OFF + _ON:
        warnings.warn(f"${SWITCH_VAR} = {os.environ[SWITCH_VAR]!r} is not 0 or 1; the compilation cache stays on "
                      f"(set {SWITCH_VAR}=0 to switch it off)", stacklevel=3)
    return switch in _OFF


def _default_min_seconds() -> float:
    """DEFAULT_MIN_COMPILE_SECONDS, or JAX's option where the user set it through the environment."""
    if os.environ.get("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"):
        return float(jax.config.jax_persistent_cache_min_compile_time_secs)
    return DEFAULT_MIN_COMPILE_SECONDS


def _env_max_bytes() -> int:
    text = os.environ.get(MAX_BYTES_VAR, "").strip()
    if not text:
        return DEFAULT_MAX_BYTES
    try:
        value = int(float(text))
    except ValueError:
        value = 0
    if value <= 0:
        warnings.warn(f"${MAX_BYTES_VAR} = {text!r} is not a positive number of bytes; the compilation cache keeps "
                      f"its default bound, {DEFAULT_MAX_BYTES} bytes", stacklevel=3)
        return DEFAULT_MAX_BYTES
    return value


def _switch_on(folder: str, min_compile_seconds: float, max_bytes: int) -> None:
    with _lock:
        changed = jax.config.jax_compilation_cache_dir != folder or _state["max_bytes"] != max_bytes
        _state["folder"], _state["max_bytes"] = folder, max_bytes
        _install_folder_cache()
        jax.config.update("jax_compilation_cache_dir", folder)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", float(min_compile_seconds))
        if changed:
            _reset_jax_cache()


def _switch_off() -> None:
    with _lock:
        if _state["folder"] is not None and jax.config.jax_compilation_cache_dir == _state["folder"]:
            jax.config.update("jax_compilation_cache_dir", None)
            _reset_jax_cache()
        _state["folder"] = None


def _reset_jax_cache() -> None:
    """Make JAX open its cache again at the next compilation (it opens it once, at the first)."""
    try:
        from jax._src import compilation_cache as jax_cache

        if getattr(jax_cache, "_cache_initialized", True) or getattr(jax_cache, "_cache", None) is not None:
            jax_cache.reset_cache()
    except (ImportError, AttributeError):  # a JAX without it: the new folder counts from a new process
        pass


def _install_folder_cache() -> None:
    """Have JAX open jaxmpm's folder with :class:`FolderCache` (JAX's other folders keep JAX's own
    cache).  A JAX without the hook keeps its own cache: correct, unbounded."""
    try:
        from jax._src import compilation_cache as jax_cache
    except ImportError:
        return
    original = getattr(jax_cache, "get_file_cache", None)
    if original is None or getattr(original, "_jaxmpm", False):
        return

    def get_file_cache(path):
        folder = _state["folder"]
        if folder is not None and str(path) == folder:
            try:
                cache = FolderCache(path, max_bytes=_state["max_bytes"])
            except OSError as err:  # JAX then compiles without a cache
                warnings.warn(f"jaxmpm: the compilation cache folder {folder!r} cannot be used ({err}); compiling "
                              f"without it (set ${ENV_VAR} to another folder, or {SWITCH_VAR}=0)", stacklevel=2)
                return None
            verify = getattr(jax_cache, "VerificationCache", None)  # jax_compilation_cache_check_contents
            if verify is not None and getattr(jax.config, "jax_compilation_cache_check_contents", False):
                cache = verify(cache)
            return cache, path
        return original(path)

    get_file_cache._jaxmpm = True
    jax_cache.get_file_cache = get_file_cache


try:
    from jax._src.compilation_cache_interface import CacheInterface as _CacheBase
except ImportError:  # pragma: no cover - a JAX without it does not call FolderCache
    _CacheBase = object


def _decompress(data: bytes) -> bytes:
    from jax._src import compilation_cache as jax_cache

    return jax_cache.decompress_executable(data)


class FolderCache(_CacheBase):
    """JAX's persistent compilation cache in one folder, safe for several processes at once.

    One file per entry, named ``<key>-cpus<N>-cache``: JAX's key, and the CPUs the process may run
    on (:func:`schedulable_cpus`), which JAX's key does not hold though XLA:CPU compiles for them.
    It is written to a temporary file and renamed into place (a reader sees a whole entry or none).
    ``get`` checks that the entry decompresses; one that does not (truncated, corrupt) is deleted,
    so that the program is compiled and written again.  Reading an entry marks it used (its
    modification time); when the folder grows past ``max_bytes`` the entries used longest ago are deleted,
    down to 3/4 of it, with the temporary files of writers killed mid-write.

    Args:
        path: the folder (created if missing).
        max_bytes: the size bound in bytes, a positive integer.
    """

    def __init__(self, path, max_bytes: int = DEFAULT_MAX_BYTES):
        self._path = Path(path)
        self._path.mkdir(parents=True, exist_ok=True)
        self.max_bytes = int(max_bytes)
        self._size = None  # this process's estimate of the folder's size: counted at the first write

    def _file(self, key: str) -> Path:
        check(bool(key), "FolderCache: key must not be empty")
        return self._path / f"{key}-cpus{schedulable_cpus()}{_SUFFIX}"

    def get(self, key: str) -> bytes | None:
        """The entry for ``key``, or None (none, or one that cannot be read: deleted).

        Args:
            key: JAX's cache key of the program.
        """
        file = self._file(key)
        try:
            data = file.read_bytes()
        except OSError:  # none (or deleted by another process meanwhile)
            return None
        try:
            _decompress(data)
        except Exception:  # truncated or corrupt: compiled again, and written again
            _unlink(file)
            return None
        try:
            os.utime(file)  # used now: kept the longest
        except OSError:
            pass
        return data

    def put(self, key: str, value: bytes) -> None:
        """Write the entry for ``key`` unless one is there; keep the folder under its bound.

        Args:
            key: JAX's cache key of the program.
            value: the compressed entry JAX made.
        """
        if len(value) > self.max_bytes:
            return
        file = self._file(key)
        if file.exists():
            return
        temporary = file.with_name(f"{file.name}.{os.getpid()}-{uuid.uuid4().hex[:8]}.tmp")
        try:
            temporary.write_bytes(value)
            os.replace(temporary, file)  # atomic: another process writing the same entry wins or loses whole
        except OSError:
            _unlink(temporary)
            if not file.exists():
                raise  # JAX turns it into a warning and carries on
            return
        if self._size is None:
            self._size = self._folder_size()
        else:
            self._size += len(value)
        if self._size > self.max_bytes:
            self._size = self._evict(int(0.75 * self.max_bytes))

    def _entries(self) -> list:
        """(last used, size, path) of each entry; stale temporary files deleted on the way."""
        entries, now = [], time.time()
        for file in self._path.iterdir():
            try:
                stat = file.stat()
            except OSError:
                continue
            if file.name.endswith(_SUFFIX):
                entries.append((stat.st_mtime, stat.st_size, file))
            elif file.name.endswith(".tmp") and now - stat.st_mtime > _STALE_TEMP_SECONDS:
                _unlink(file)
        return entries

    def _folder_size(self) -> int:
        return sum(size for _, size, _ in self._entries())

    def _evict(self, target: int) -> int:
        """Delete the entries used longest ago until the folder holds at most ``target`` bytes;
        return its size."""
        entries = sorted(self._entries())
        size = sum(s for _, s, _ in entries)
        for _, s, file in entries:
            if size <= target:
                break
            _unlink(file)
            size -= s
        return size


def schedulable_cpus() -> int:
    """The CPUs this process may run on (its affinity mask), the count XLA:CPU compiles a program for: it
    splits each large kernel into up to that many parallel tasks when it compiles it (tsl's
    ``NumSchedulableCPUs``).  JAX's cache key does not hold it, so :class:`FolderCache` adds it to each
    entry's name: a program compiled in a process pinned to one CPU (``taskset -c 0``) has no parallel
    tasks, and read back by a process with two it ran on one thread, 1.5-1.6x slower (mpm88 at 131k
    particles, float64: 14.3-15.4 against 9.6-9.8 ms a step)."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # no affinity masks (macOS, Windows): the machine's count
        return os.cpu_count() or 1


def _unlink(file: Path) -> None:
    try:
        file.unlink()
    except OSError:  # gone already (another process), or open elsewhere on Windows
        pass
