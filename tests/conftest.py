"""Tests run in float64 (docs/design.md "Verification standards") with strict dtype promotion: an
implicit promotion (int32 with int64, an integer array with a float array, float32 with float64)
is an error, so a silent cast or a loss of precision cannot hide in the library or the tests.  An
implicit rank promotion ((N, D) with (D,)) is an error too: broadcasting is written out.

The suite's time is almost all XLA compilation, so the tests compile for compile speed: JAX's own
``jax_disable_most_optimizations`` (LLVM at optimisation level 0, its expensive passes off) and,
on jaxlib 0.10, XLA:CPU's loop emitters in place of its fusion emitters
(``--xla_cpu_use_fusion_emitters=false``).  Together they take the whole suite from about 19 to
about 9 minutes on the 2-core machine, for programs that run somewhat slower, which the tests'
short runs do not feel.  The numbers do not depend on them beyond round-off: the stored reference
values (tests/test_reference_values.py) were produced at XLA's defaults and agree to 1e-13 (one
step) and 1e-10 (whole runs).  Benchmarks, experiments and users compile at XLA's defaults.  Both
are set through the environment before JAX is imported, so the subprocesses the tests start (CLI,
notebooks, resume) inherit them; ``JAX_DISABLE_MOST_OPTIMIZATIONS=0`` and
``XLA_FLAGS=--xla_cpu_use_fusion_emitters=true`` in the environment run the suite at the defaults.

Each test process also keeps every program it compiles in a folder of its own for the session
(JAX's persistent cache, emptied and removed when the process ends), so a program compiled again
is read back instead: a test that builds the same simulation anew, a module run after
``jax.clear_caches()`` below, and above all eager code, where every ``lax.cond`` of a step (the
transfer's stage boundaries) is traced as a new function and would be compiled again each call.
About a third of the suite's compilation is such repeats.  A cached program is the one XLA
compiled, so no number changes.  The cache is this process's only (not the subprocesses', not
other workers'), is never read by a later session, and ``JAXMPM_TEST_XLA_CACHE=0`` switches it off."""

import atexit
import os
import shutil
import tempfile
from importlib.metadata import version as _version

os.environ.setdefault("JAX_DISABLE_MOST_OPTIMIZATIONS", "1")
# only on the jaxlib it was measured on: XLA aborts on a flag it does not know, and the flag is
# XLA's to rename
if _version("jaxlib").startswith("0.10.") and "xla_cpu_use_fusion_emitters" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " --xla_cpu_use_fusion_emitters=false").strip()

import jax

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_dtype_promotion", "strict")
jax.config.update("jax_numpy_rank_promotion", "raise")

if os.environ.get("JAXMPM_TEST_XLA_CACHE", "1") != "0":
    _compiled = tempfile.mkdtemp(prefix="jaxmpm-tests-xla-")
    atexit.register(shutil.rmtree, _compiled, ignore_errors=True)
    jax.config.update("jax_compilation_cache_dir", _compiled)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)  # every program, however quick


import pytest  # noqa: E402


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_programs():
    """Drop JAX's compiled programs after each test module.  A single pytest process compiles
    thousands of programs; XLA's CPU JIT maps memory for each, and past ~65k mappings (Linux's
    vm.max_map_count) compilation aborts (seen as a segfault in the compiler late in the suite).
    Modules share few programs, so the recompilation this costs is small."""
    yield
    jax.clear_caches()
