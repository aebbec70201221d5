"""Tests run in float64 (docs/design.md "Verification standards") with strict dtype promotion: an
implicit promotion (int32 with int64, an integer array with a float array, float32 with float64)
is an error, so a silent cast or a loss of precision cannot hide in the library or the tests.  An
implicit rank promotion ((N, D) with (D,)) is an error too: broadcasting is written out.

The suite's time is almost all XLA compilation, so the tests compile for compile speed: JAX's own
``jax_disable_most_optimizations`` (LLVM at optimisation level 0, its expensive passes off) and, on
jaxlib 0.10, XLA:CPU's loop emitters in place of its fusion emitters
(``--xla_cpu_use_fusion_emitters=false``). Together they took the suite of their time from about 19
to about 9 minutes on the 2-core machine (today's suite and its profile: docs/testing.md), for
programs that run somewhat slower, which the tests' short runs do not feel. The numbers do not
depend on them beyond round-off: the stored reference values (tests/test_reference_values.py) were
produced at XLA's defaults and agree to 1e-13 (one step) and 1e-10 (whole runs). Benchmarks,
experiments and users compile at XLA's defaults. Both are set through the environment before JAX is
imported, so the subprocesses the tests start (CLI, notebooks, resume) inherit them;
``JAX_DISABLE_MOST_OPTIMIZATIONS=0`` and
``XLA_FLAGS="--xla_cpu_use_fusion_emitters=true --xla_cpu_parallel_codegen_split_count=32"`` in the
environment run the suite at the defaults.

On jaxlib 0.10 XLA:CPU also compiles each program as one LLVM module
(``--xla_cpu_parallel_codegen_split_count=1``) rather than splitting it into up to 32 for
parallel code generation: on two busy workers the parallelism buys nothing and the split costs
about a tenth of the compilation (measured 7-14 % less CPU time on test_nairnmpm, test_adjoint,
test_contact_scenes and test_core_v2).  At the optimisation level above it moves some results by
round-off (1e-16 relative: disks, spin, mpm88), as the level itself does; at XLA's defaults it
changes no bit.

The suite keeps every program it compiles in one folder, shared by both workers and every process
the tests start, and kept from one run to the next: ``jaxmpm/tests`` in the user's cache folder
(jaxmpm's own cache, ``$JAXMPM_CACHE_DIR`` for the processes; never the library's ``jaxmpm/xla``).
A program compiled again is read back instead of compiled: a test that builds the same simulation
anew, a module run after ``jax.clear_caches()`` below, eager code whose loops (XPIC's series) are
traced as new functions at every call, and every program of an earlier run.  A cached program is
the one XLA compiled, so no number changes (docs/testing.md, "Keeping compiled programs across
runs").  ``JAXMPM_TEST_CACHE_DIR=folder`` picks another folder; ``JAXMPM_TEST_CACHE_DIR=`` (empty)
gives each process a throw-away folder of its own instead, removed when it ends;
``JAXMPM_TEST_XLA_CACHE=0`` runs without a cache (and with ``JAXMPM_CACHE=0``)."""

import atexit
import gc
import os
import shutil
import tempfile
from importlib.metadata import version as _version

os.environ.setdefault("JAX_DISABLE_MOST_OPTIMIZATIONS", "1")
# only on the jaxlib it was measured on: XLA aborts on a flag it does not know, and the flag is
# XLA's to rename
if _version("jaxlib").startswith("0.10."):
    for _flag in ("--xla_cpu_use_fusion_emitters=false", "--xla_cpu_parallel_codegen_split_count=1"):
        if _flag.split("=")[0] not in os.environ.get("XLA_FLAGS", ""):
            os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " " + _flag).strip()

import jax

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_dtype_promotion", "strict")
jax.config.update("jax_numpy_rank_promotion", "raise")


def _kept_folder():
    """The folder the suite keeps its compiled programs in from one run to the next:
    ``$JAXMPM_TEST_CACHE_DIR`` (empty: none), else ``jaxmpm/tests`` in the user's cache folder
    (``$XDG_CACHE_HOME`` or ``~/.cache``; ``%LOCALAPPDATA%`` on Windows), never the library's own
    ``jaxmpm/xla``; None when it cannot be made."""
    folder = os.environ.get("JAXMPM_TEST_CACHE_DIR")
    if folder is None:
        base = os.environ.get("LOCALAPPDATA" if os.name == "nt" else "XDG_CACHE_HOME") or os.path.join("~", ".cache")
        folder = os.path.join(base, "jaxmpm", "tests")
    if not folder:
        return None
    folder = os.path.expanduser(folder)
    try:
        os.makedirs(folder, exist_ok=True)
    except OSError:
        return None
    return folder if os.access(folder, os.W_OK) else None


_cached = os.environ.get("JAXMPM_TEST_XLA_CACHE", "1") != "0"
_kept = _kept_folder() if _cached else None
if _kept:
    # shared by both workers and every subprocess: jaxmpm's own cache (FolderCache: entries written
    # atomically, a corrupt one compiled again, the folder bounded), which ``import jaxmpm`` switches
    # on for $JAXMPM_CACHE_DIR; a run again reads its programs back
    os.environ["JAXMPM_CACHE_DIR"] = _kept
    os.environ.setdefault("JAXMPM_CACHE_MAX_BYTES", str(2 << 30))
    os.environ.pop("JAXMPM_CACHE", None)
elif _cached:
    _compiled = tempfile.mkdtemp(prefix="jaxmpm-tests-xla-")
    atexit.register(shutil.rmtree, _compiled, ignore_errors=True)
    jax.config.update("jax_compilation_cache_dir", _compiled)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)  # every program, however quick
    os.environ["JAXMPM_CACHE_DIR"] = os.path.join(_compiled, "subprocesses")
else:
    os.environ["JAXMPM_CACHE"] = "0"


# the suite traces programs all the time: Python's collector runs its youngest generation every
# TRACING_THRESHOLD allocations rather than 700 for the whole run, as jaxmpm does inside its own
# tracing calls (gradients traced 23-26% faster, benchmarks/tracing_gc.py); imported only now, once
# the cache settings above are in the environment that ``import jaxmpm`` reads
from jaxmpm.run.collector import TRACING_THRESHOLD  # noqa: E402

gc.set_threshold(TRACING_THRESHOLD, *gc.get_threshold()[1:])

import pytest  # noqa: E402


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_programs():
    """Drop JAX's compiled programs after each test module.  A single pytest process compiles
    thousands of programs; XLA's CPU JIT maps memory for each, and past ~65k mappings (Linux's
    vm.max_map_count) compilation aborts (seen as a segfault in the compiler late in the suite).
    Modules share few programs, so the recompilation this costs is small."""
    yield
    jax.clear_caches()


BENCHMARKS = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "benchmarks")


@pytest.fixture(scope="module")
def benchmark_script():
    """A loader of the scripts in benchmarks/: ``benchmark_script("gpu.py")`` is that script as a module.
    The scripts import their helpers (``_results``, ``gpu``...) by name, so benchmarks/ is on the path while
    the test module runs."""
    import importlib.util
    import sys

    sys.path.insert(0, BENCHMARKS)

    def load(name: str):
        spec = importlib.util.spec_from_file_location(f"benchmark_{name.removesuffix('.py')}",
                                                      os.path.join(BENCHMARKS, name))
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        return module

    try:
        yield load
    finally:
        sys.path.remove(BENCHMARKS)
