"""Tests run in float64 (docs/design.md "Verification standards") with strict dtype promotion: an
implicit promotion (int32 with int64, an integer array with a float array, float32 with float64)
is an error, so a silent cast or a loss of precision cannot hide in the library or the tests."""

import jax

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_dtype_promotion", "strict")
