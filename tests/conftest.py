"""Tests run in float64 (docs/design.md "Verification standards") with strict dtype promotion: an
implicit promotion (int32 with int64, an integer array with a float array, float32 with float64)
is an error, so a silent cast or a loss of precision cannot hide in the library or the tests."""

import jax

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_dtype_promotion", "strict")


import pytest  # noqa: E402


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_programs():
    """Drop JAX's compiled programs after each test module.  A single pytest process compiles
    thousands of programs; XLA's CPU JIT maps memory for each, and past ~65k mappings (Linux's
    vm.max_map_count) compilation aborts (seen as a segfault in the compiler late in the suite).
    Modules share few programs, so the recompilation this costs is small."""
    yield
    jax.clear_caches()
