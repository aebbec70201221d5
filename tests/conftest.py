"""Tests run in float64 (DESIGN.md "Verification standards")."""

import jax

jax.config.update("jax_enable_x64", True)
