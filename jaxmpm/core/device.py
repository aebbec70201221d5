"""Host arrays onto the device, in memory of XLA's own."""

from __future__ import annotations

import jax


def to_device(x) -> jax.Array:
    """``x`` (a NumPy array or scalar) on the default device, in a buffer XLA allocated, with nothing compiled.

    ``jax.device_put`` of a NumPy array on the CPU may keep the NumPy memory itself (no copy; about two arrays in
    three, by their alignment), and XLA does not compute a donated buffer in place of such memory: a run given
    ``donate=True`` then holds two states, not one.  ``jnp.asarray`` copies, but compiles a small program per new
    shape where it converts the dtype (jaxlib 0.10, float64 data without x64).  So the array is put on the device,
    then copied there (a device copy: nothing compiled)."""
    return jax.device_put(jax.device_put(x), may_alias=False)
