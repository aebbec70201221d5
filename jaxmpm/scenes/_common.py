"""Shared pieces of the scene builders."""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Callable

import jax
import jax.numpy as jnp

from .._errors import check


@dataclasses.dataclass
class Setup:
    """A ready-to-run scene: ``sim``, initial ``state``, ``dt``, ``steps``, ``save_every``,
    ``params`` (the scene's parameters, written to HDF5) and ``reference`` (exact solution, if any)."""

    name: str
    sim: Any
    state: Any
    dt: float
    steps: int
    save_every: int
    params: dict
    reference: Callable | None = None
    particles: Any = None  # the filled particles: sim.init(particles) inside a loss makes d/d(density) flow

    def __post_init__(self):
        # The simulation's float parameters (E, beta, damping, gravity) follow the state's dtype, so a
        # dtype="f32" scene stays float32 in a 64-bit process instead of promoting inside lax.scan.
        self.sim = cast_state(self.sim, self.state.x.dtype)

    @property
    def t_end(self) -> float:
        return self.dt * self.steps

    def run(self, **kwargs):
        """``sim.run(state, dt, steps, save_every, **kwargs)``."""
        return self.sim.run(self.state, self.dt, self.steps, self.save_every, **kwargs)


def resolve_dtype(dtype):
    """"f32"/"f64"/None -> a JAX float dtype; f64 requires jax_enable_x64."""
    if dtype is None:
        return jnp.result_type(float)
    name = {"f32": "float32", "float32": "float32", "f64": "float64", "float64": "float64"}.get(str(dtype))
    check(name is not None, f"dtype = {dtype!r}; use 'f32' or 'f64'")
    if name == "float64":
        check(jax.config.jax_enable_x64,
              "dtype = 'f64' needs 64-bit JAX: call jax.config.update('jax_enable_x64', True) first")
    return jnp.dtype(name)


def schedule(t_end: float, dt: float, frames: int = 200) -> tuple[int, int]:
    """(steps, save_every): about ``frames`` saved frames covering at least t_end."""
    check(t_end > 0, f"t_end = {t_end} must be positive")
    steps = max(1, int(math.ceil(t_end / dt - 1e-9)))
    target = steps / frames
    divisors = [d for d in range(1, steps + 1) if steps % d == 0 and frames / 2 <= steps / d <= 2 * frames]
    if divisors:  # keep t_end exact when a divisor gives a sensible frame count
        return steps, min(divisors, key=lambda d: abs(d - target))
    save_every = max(1, int(round(target)))
    return int(math.ceil(steps / save_every)) * save_every, save_every


def cast_state(state, dtype):
    """Cast the float leaves of a state to ``dtype``."""
    return jax.tree_util.tree_map(
        lambda a: a.astype(dtype) if hasattr(a, "dtype") and jnp.issubdtype(a.dtype, jnp.floating) else a, state
    )
