"""NaN-safe helpers: norms and unit vectors whose derivatives stay finite at zero (the double-where
rule: the square root never sees a zero, and the result is selected afterwards), shared by the
materials' return mappings and the terms' contact normals, level sets and transport."""

from __future__ import annotations

import jax.numpy as jnp


def safe_norm(u, axis: int = -1):
    """|u| along ``axis``, 0 where u = 0, with a derivative that is 0 there, not NaN."""
    sq = jnp.sum(u * u, axis=axis)
    positive = sq > 0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, sq, 1.0)), 0.0)


def safe_unit(u, axis: int = -1):
    """u / |u| along ``axis``, 0 where u = 0 (value and derivative)."""
    sq = jnp.sum(u * u, axis=axis, keepdims=True)
    positive = sq > 0
    return jnp.where(positive, u / jnp.sqrt(jnp.where(positive, sq, 1.0)), 0.0)
