"""Gradient-descent calibration of simulation parameters with optax.

``calibrate(loss, {"alpha_g": 0.5}, steps=200)`` minimises ``loss(params)`` over a dict of
parameters.  Parameters that must stay positive or inside an interval are reparameterised, not
clipped: the optimiser works on an unconstrained ``raw`` value and the loss sees
``transform(raw)`` (exp for positive values, a scaled sigmoid for intervals).
"""

from __future__ import annotations

import dataclasses
import time
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np
import optax

from ..core.errors import check
from ..core.params import default_bounds


def _transform(bound):
    """(forward raw -> value, inverse value -> raw) for a bound."""
    if bound is None:
        return (lambda r: r), (lambda v: v)
    if bound == "positive":  # log-parameterisation: scale-free steps, never reaches 0
        return jnp.exp, jnp.log
    lo, hi = bound
    check(hi > lo, f"calibrate: bound {bound!r} needs lower < upper")

    def forward(r):
        return lo + (hi - lo) * jax.nn.sigmoid(r)

    def inverse(v):
        u = (v - lo) / (hi - lo)
        return jnp.log(u) - jnp.log1p(-u)

    return forward, inverse


@dataclasses.dataclass
class CalibrationResult:
    """What :func:`calibrate` returns.

    Args:
        params: the fitted values, ``{name: array}`` (after the last iteration's update).
        losses: the loss at every iteration, (iterations,).
        trajectory: ``{name: (iterations, ...)}``, the parameters at which each loss was
            evaluated.
        iterations: the number of iterations run (fewer than ``steps`` when ``tol`` was met).
        wall_time: the seconds the iterations took, compilation included.
    """

    params: dict  # fitted values
    losses: np.ndarray  # loss at every iteration
    trajectory: dict  # parameter values at every iteration
    iterations: int
    wall_time: float


def calibrate(
    loss: Callable[[dict], jnp.ndarray],
    init: dict,
    *,
    bounds: dict | None = None,
    optimizer: optax.GradientTransformation | None = None,
    steps: int = 200,
    tol: float | None = None,
    callback: Callable | None = None,
) -> CalibrationResult:
    """Minimise ``loss(params)`` from ``init`` with ``optimizer`` (default ``optax.adam(0.05)``
    on the raw parameters; ``optax.lbfgs()`` converges in far fewer iterations on smooth,
    low-dimensional problems, and with ``linesearch=optax.scale_by_backtracking_linesearch(...)``
    compiles one copy of the loss's gradient instead of two) for at most ``steps`` iterations,
    stopping early once the loss is below ``tol``.  ``bounds`` maps a name to ``"positive"``,
    ``(lower, upper)`` or ``None``; names of simulation parameters get the bounds their
    registration declares (``jaxmpm.core.registry``).

    Args:
        loss: ``loss(params) -> scalar`` of a dict of parameters, differentiable (usually a
            :func:`jaxmpm.set_params` of a model, a run and a misfit).
        init: ``{name: initial value}``, non-empty; each inside its bounds.
        bounds: ``{name: "positive" | (lower, upper) | None}``: the parameter is reparameterised
            (exp, a scaled sigmoid) to stay inside; default: the registered bounds of simulation
            parameters, None (unbounded) for other names.
        optimizer: an optax ``GradientTransformation`` on the raw parameters; None (the
            default): ``optax.adam(0.05)``.
        steps: the most iterations, a positive integer (default 200).
        tol: stop once the loss is below it; None (the default): run all ``steps``.
        callback: ``callback(iteration, loss, params)``, called every iteration; None (the
            default).

    Returns:
        A :class:`CalibrationResult`.
    """
    check(isinstance(init, dict) and init, "calibrate: init must be a non-empty dict {name: initial value}")
    check(isinstance(steps, int) and steps >= 1, f"calibrate: steps = {steps!r} must be a positive integer")
    bounds = {**{k: default_bounds(k) for k in init}, **(bounds or {})}
    transforms = {k: _transform(bounds.get(k)) for k in init}
    for k, v in init.items():
        b = bounds.get(k)
        if b == "positive":
            check(np.all(np.asarray(v) > 0), f"calibrate: initial {k} = {v} must be > 0")
        elif isinstance(b, tuple):
            check(np.all((np.asarray(v) > b[0]) & (np.asarray(v) < b[1])),
                  f"calibrate: initial {k} = {v} must lie strictly inside {b}")
    raw = {k: transforms[k][1](jnp.asarray(v, dtype=jnp.result_type(float))) for k, v in init.items()}

    def constrained(r):
        return {k: transforms[k][0](r[k]) for k in r}

    optimizer = optax.adam(0.05) if optimizer is None else optimizer
    opt_state = optimizer.init(raw)
    # strong types: optax.lbfgs starts with a weakly typed counter that its update makes strong, which
    # would make the jitted update below compile twice
    opt_state = jax.tree_util.tree_map(lambda a: jnp.asarray(a, dtype=a.dtype) if hasattr(a, "dtype") else a, opt_state)

    def raw_loss(rr):
        return loss(constrained(rr))

    @jax.jit
    def update(r, s):
        value, grads = jax.value_and_grad(raw_loss)(r)
        # optimizers with a line search (optax.lbfgs) need the value, gradient and function;
        # the others ignore these extra arguments
        # optax mixes Python floats with integer step counts (Adam's decay**count): let it
        # promote as it expects even when the caller runs JAX with strict promotion
        with jax.numpy_dtype_promotion("standard"):
            updates, s = optimizer.update(grads, s, r, value=value, grad=grads, value_fn=raw_loss)
        return optax.apply_updates(r, updates), s, value

    losses, trajectory = [], {k: [] for k in init}
    start = time.perf_counter()
    for it in range(steps):
        params = constrained(raw)
        raw, opt_state, value = update(raw, opt_state)
        value = float(value)
        check(np.isfinite(value), f"calibrate: the loss became {value} at iteration {it}; lower the learning rate")
        losses.append(value)
        for k in init:
            trajectory[k].append(np.asarray(params[k]))
        if callback is not None:
            callback(it, value, params)
        if tol is not None and value < tol:
            break
    final = {k: np.asarray(v) for k, v in constrained(raw).items()}
    return CalibrationResult(final, np.asarray(losses), {k: np.asarray(v) for k, v in trajectory.items()},
                             len(losses), time.perf_counter() - start)
