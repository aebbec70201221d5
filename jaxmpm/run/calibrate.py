"""Gradient-descent calibration of simulation parameters with optax.

``calibrate(loss, {"alpha_g": 0.5}, steps=200)`` minimises ``loss(params)`` over a dict of
parameters.  Parameters that must stay positive or inside an interval are reparameterised, not
clipped: the optimiser works on an unconstrained ``raw`` value and the loss sees
``transform(raw)`` (exp for positive values, a scaled sigmoid for intervals).

The update (loss, gradient, optimizer step) is compiled once per loss function, optimizer and
bounds and kept while the loss function lives: a second ``calibrate`` with the same ones compiles
nothing (issue 30).  It is compiled for every parameter of ``init``, and ``free=`` picks the ones
fitted by a mask passed as an argument, so fitting a, then b, then both runs one program.
"""

from __future__ import annotations

import collections
import dataclasses
import time
import weakref
from typing import Callable, Iterable

import jax
import jax.numpy as jnp
import numpy as np
import optax

from ..core.errors import InputError, InstabilityError, check
from ..core.params import default_bounds
from ..core.validate import FINITE
from ..transfer.backend import compiler_options
from .progress import AheadOfTime, bar, shown


def _transform(bound):
    """(forward raw -> value, inverse value -> raw) for a bound."""
    if bound is None:
        return (lambda r: r), (lambda v: v)
    if bound == "positive":  # log-parameterisation: scale-free steps, never reaches 0
        return jnp.exp, jnp.log
    try:
        ok = isinstance(bound, tuple) and len(bound) == 2 and all(np.isfinite(float(b)) for b in bound)
    except (TypeError, ValueError):  # ("a", "b"): not numbers
        ok = False
    check(ok, f"calibrate: bound {bound!r} must be (lower, upper), two finite numbers, or 'positive' (0, inf), or "
              "None (unbounded)")
    lo, hi = bound
    check(hi > lo, f"calibrate: bound {bound!r} needs lower < upper")

    def forward(r):
        return lo + (hi - lo) * jax.nn.sigmoid(r)

    def inverse(v):
        u = (v - lo) / (hi - lo)
        return jnp.log(u) - jnp.log1p(-u)

    return forward, inverse


def _bound_key(bound):
    """A bound as a hashable key: a (lower, upper) pair as two floats; None, "positive" and anything
    malformed (that :func:`_transform` then reports) unchanged."""
    if bound is None or isinstance(bound, str):
        return bound
    try:
        lower, upper = bound
        return float(lower), float(upper)
    except (TypeError, ValueError):
        return bound


_ADAM = optax.adam(0.05)  # the default optimizer: one object, so that calls without optimizer= share programs
# compiled updates: loss function (weakly: dropped with it) -> {(optimizer, bounds): _Update}, the most recent
# _KEPT_PER_LOSS pairs per loss
_UPDATES = weakref.WeakKeyDictionary()
_KEPT_PER_LOSS = 4


@dataclasses.dataclass
class _Update:
    """The jitted update of one (loss, optimizer, bounds) and the programs compiled for it ahead of
    time (:class:`jaxmpm.run.progress.AheadOfTime`'s, one per signature of the parameters)."""

    jitted: Callable
    programs: dict


def _make_update(loss_ref, optimizer, bounds, fast_compile: bool = False) -> _Update:
    """The update ``(raw, optimizer state, free) -> (raw, state, loss, |gradient|)`` of the loss
    ``loss_ref()`` (a weak reference: the cache does not keep the loss, nor what it holds, alive)
    over the raw parameters with ``bounds`` (``((name, bound), ...)``); ``free`` ``{name: bool}``
    masks the gradient and the step, so the held parameters keep their values exactly; ``fast_compile``:
    compiled with :func:`jaxmpm.compiler_options`'s faster-compiling options."""
    transforms = {k: _transform(b) for k, b in bounds}

    def raw_loss(rr):
        return loss_ref()({k: transforms[k][0](rr[k]) for k in rr})

    def masked(tree, free):
        return {k: jnp.where(free[k], v, jnp.zeros_like(v)) for k, v in tree.items()}

    def update(r, s, free):
        value, grads = jax.value_and_grad(raw_loss)(r)
        grads = masked(grads, free)
        # optimizers with a line search (optax.lbfgs) need the value, gradient and function;
        # the others ignore these extra arguments
        # optax mixes Python floats with integer step counts (Adam's decay**count): let it
        # promote as it expects even when the caller runs JAX with strict promotion
        with jax.numpy_dtype_promotion("standard"):
            updates, s = optimizer.update(grads, s, r, value=value, grad=grads, value_fn=raw_loss)
            grad_norm = _norm(jax.tree_util.tree_leaves(grads))  # shown; infinite only where a component is
        return optax.apply_updates(r, masked(updates, free)), s, value, grad_norm

    # the backend's XLA options for gradients of steps (jm.compiler_options: 1.3x at 131k particles)
    return _Update(jax.jit(update, compiler_options=compiler_options(fast_compile=fast_compile)), {})


def _norm(leaves) -> jnp.ndarray:
    """The Euclidean norm of the leaves, scaled by their largest magnitude first: the squares of a finite
    float32 gradient past 1.3e19 overflow, and its norm read infinite (a NaN or Inf component still gives
    NaN or Inf)."""
    largest = jnp.max(jnp.stack([jnp.max(jnp.abs(g)) for g in leaves]))
    scale = jnp.where(jnp.isfinite(largest) & (largest > 0), largest, 1.0)
    return scale * jnp.sqrt(sum(jnp.sum(jnp.square(g / scale)) for g in leaves))


def _check_finite(it: int, value: float, grad_norm: float, params: dict, losses: list) -> None:
    """Raise InputError naming where the loss or its gradient stopped being finite, and why it may have."""
    at = ", ".join(f"{k} = {np.asarray(v).tolist()}" for k, v in params.items())
    if not np.isfinite(value):
        check(it > 0, f"calibrate: the loss is {value} at the initial parameters ({at}): the loss function "
                      "gives it there, before any step; check that the model is stable at these values")
        check(False, f"calibrate: the loss became {value} at iteration {it} ({at}), after {losses[-1]:.6g}; the step "
                     "was too long: lower the learning rate, or bound the parameters (bounds=)")
    check(np.isfinite(grad_norm),
          f"calibrate: the loss's gradient is {grad_norm} at iteration {it} ({at}) while the loss is {value:.6g}: "
          "a derivative inside the loss function is undefined there (a square root or norm of 0, a division by "
          "0; jax.config.update('jax_debug_nans', True) finds it)")


def _update_for(loss, optimizer, bounds, fast_compile: bool = False) -> _Update:
    """The cached update of (``loss``, ``optimizer``, ``bounds``, ``fast_compile``), made on the first call; a
    loss that cannot be weakly referenced or hashed (or an unhashable optimizer) gets one of its own."""
    key = (optimizer, bounds, fast_compile)
    try:
        kept = _UPDATES.get(loss)
        if kept is None:
            kept = _UPDATES[loss] = collections.OrderedDict()
        entry = kept.get(key)
    except TypeError:
        return _make_update(lambda: loss, optimizer, bounds, fast_compile)
    if entry is None:
        entry = kept[key] = _make_update(weakref.ref(loss), optimizer, bounds, fast_compile)
        while len(kept) > _KEPT_PER_LOSS:
            kept.popitem(last=False)
    else:
        kept.move_to_end(key)
    return entry


def _names(free) -> list:
    """``free`` as a list (empty when it is not iterable: calibrate reports it)."""
    try:
        return list(free)
    except TypeError:
        return []


@dataclasses.dataclass
class CalibrationResult:
    """What :func:`calibrate` returns.

    Args:
        params: the fitted values, ``{name: array}`` (after the last iteration's update); the
            parameters ``free=`` leaves out keep their initial values.
        losses: the loss at every iteration, (iterations,).
        trajectory: ``{name: (iterations, ...)}``, the parameters at which each loss was
            evaluated.
        iterations: the number of iterations run (fewer than ``steps`` when ``tol`` was met).
        wall_time: the seconds the whole calibration took, from before compiling to the last
            iteration's end: ``compile_time`` plus the iterations.
        compile_time: the seconds spent compiling the update (the loss, its gradient and the
            optimizer's step), ahead of the first iteration; part of ``wall_time``; 0 when an
            earlier call compiled it (the same loss function, optimizer and bounds).
    """

    params: dict  # fitted values
    losses: np.ndarray  # loss at every iteration
    trajectory: dict  # parameter values at every iteration
    iterations: int
    wall_time: float  # compilation included
    compile_time: float = 0.0


def calibrate(
    loss: Callable[[dict], jnp.ndarray],
    init: dict,
    *,
    bounds: dict | None = None,
    optimizer: optax.GradientTransformation | None = None,
    steps: int = 200,
    tol: float | None = None,
    callback: Callable | None = None,
    progress: bool | None = None,
    free: str | Iterable[str] | None = None,
    fast_compile: bool = False,
    check_stability: bool = True,
) -> CalibrationResult:
    """Minimise ``loss(params)`` from ``init`` with ``optimizer`` (default ``optax.adam(0.05)``
    on the raw parameters; ``optax.lbfgs()`` converges in far fewer iterations on smooth,
    low-dimensional problems, and with ``linesearch=optax.scale_by_backtracking_linesearch(...)``
    compiles one copy of the loss's gradient instead of two) for at most ``steps`` iterations,
    stopping early once the loss is below ``tol``.  ``bounds`` maps a name to ``"positive"``,
    ``(lower, upper)`` or ``None``; names of simulation parameters get the bounds their
    registration declares (``jaxmpm.core.registry``).

    The update (the loss, its gradient and the optimizer's step) is compiled ahead of the first
    iteration, timed apart (``CalibrationResult.compile_time``).  With progress shown, stderr
    gets ``jaxmpm calibrate: compiling the loss and its gradient ... 3.1 s``, then a tqdm bar of
    the iterations with the loss, the gradient's norm (of the raw parameters, what the optimizer
    sees), the time per iteration and the time left (for ``steps`` iterations: an upper bound
    when ``tol`` stops it early).  Showing progress changes no number.

    The compiled update is kept while the loss function lives (for its 4 most recent optimizers and
    bounds) and reused by a later call with the same loss function, optimizer object (the default
    Adam is one object) and bounds, and parameters of the same names and shapes: that call compiles
    nothing (``compile_time`` 0).  As with ``jax.jit``, the loss is traced once: a value it reads
    from outside and that changed since (a global target assigned anew) keeps its first value in
    the reused program, so define the loss function again to trace it anew.  The update covers every
    parameter of ``init``; ``free`` picks the fitted ones by a mask passed to the program, so fitting
    ``free="alpha_g"``, then ``free="alpha_p"``, then both from one ``init`` compiles once.

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
        progress: show the compilation time and a progress bar on stderr (True), or not (False);
            None (the default): shown when the call is interactive (stderr is a terminal, or a
            Jupyter kernel runs it), so tests and CI stay quiet.
        free: the names of ``init`` to fit, a name or several; the others keep their initial
            values (their gradient and step are masked out); None (the default): all of them.
        fast_compile: compile the update with ``jm.compiler_options(fast_compile=True)``: on the CPU
            0.55-0.65x the compile time, each iteration 0.9-1.4x as long (benchmarks/README.md, "Compile
            time"); for a calibration of a few iterations.  Default False.
        check_stability: evaluate the loss once more at the parameters reached, outside the trace, so
            that a run that goes unstable there raises (True, the default: one forward run more, not in
            ``wall_time``).  A run inside the compiled update cannot raise: an optimizer that steps into
            an unstable range would otherwise return its parameters as if fitted.

    Returns:
        A :class:`CalibrationResult`.

    Raises:
        InputError: where the loss or its gradient stops being finite, and (``check_stability``)
            where a run of the loss goes unstable at the parameters reached.
    """
    check(callable(loss), f"calibrate: loss = {loss!r} is not a function; give loss(params) -> a scalar, params "
                          "a dict like init")
    check(isinstance(init, dict) and init, "calibrate: init must be a non-empty dict {name: initial value}")
    check(bounds is None or isinstance(bounds, dict),
          f"calibrate: bounds = {bounds!r}; give a dict {{name: (low, high) or 'positive' or None}}, or None (each "
          "parameter's registered range)")
    if tol is not None:
        FINITE.real("calibrate", "tol", tol, fix="the loss below which to stop, or None (run every step)")
    check(isinstance(steps, int) and not isinstance(steps, bool) and steps >= 1,
          f"calibrate: steps = {steps!r} must be a positive integer")
    names = [free] if isinstance(free, str) else None if free is None else _names(free)
    check(names is None or (names and all(isinstance(n, str) and n in init for n in names)),
          f"calibrate: free = {free!r} must name one or more parameters of init ({', '.join(map(str, init))}); "
          "the others keep their initial values")
    unknown = sorted(set(bounds or {}) - set(init), key=str)
    check(not unknown, f"calibrate: bounds name {unknown}, which init does not have ({', '.join(map(str, init))}); "
                       "bound the parameters init gives")
    for k, v in init.items():
        value = np.asarray(v)
        check(np.issubdtype(value.dtype, np.number) and bool(np.all(np.isfinite(value))),
              f"calibrate: initial {k} = {v!r} must be finite numbers")
    show = shown(progress, "calibrate")
    bounds = {**{k: default_bounds(k) for k in init}, **(bounds or {})}
    bounds = {k: _bound_key(bounds.get(k)) for k in init}
    transforms = {k: _transform(bounds[k]) for k in init}
    for k, v in init.items():
        b = bounds[k]
        if b == "positive":
            check(np.all(np.asarray(v) > 0), f"calibrate: initial {k} = {v} must be > 0")
        elif isinstance(b, tuple):
            check(np.all((np.asarray(v) > b[0]) & (np.asarray(v) < b[1])),
                  f"calibrate: initial {k} = {v} must lie strictly inside {b}")
    raw = {k: transforms[k][1](jnp.asarray(v, dtype=jnp.result_type(float))) for k, v in init.items()}

    def constrained(r):
        return {k: transforms[k][0](r[k]) for k in r}

    check(optimizer is None or all(callable(getattr(optimizer, method, None)) for method in ("init", "update")),
          f"calibrate: optimizer = {optimizer!r} is not an optax optimizer; give one, e.g. optimizer=optax.adam(0.05) "
          "(import optax), or None for that default")
    check(callback is None or callable(callback),
          f"calibrate: callback = {callback!r} is not a function; give callback(iteration, loss, params), or None")
    optimizer = _ADAM if optimizer is None else optimizer
    opt_state = optimizer.init(raw)
    # strong types: optax.lbfgs starts with a weakly typed counter that its update makes strong, which
    # would make the jitted update below compile twice
    opt_state = jax.tree_util.tree_map(lambda a: jnp.asarray(a, dtype=a.dtype) if hasattr(a, "dtype") else a, opt_state)

    mask = {k: jnp.asarray(names is None or k in names) for k in init}  # the parameters fitted
    check(isinstance(fast_compile, bool), f"calibrate: fast_compile = {fast_compile!r}; pass True or False")
    check(isinstance(check_stability, bool), f"calibrate: check_stability = {check_stability!r}; pass True or False")
    cached = _update_for(loss, optimizer, tuple(sorted(bounds.items())), fast_compile)

    losses, trajectory = [], {k: [] for k in init}
    start = time.perf_counter()
    # compiled before the first iteration (the same program a first call would compile, once), so
    # that its time is measured and shown apart from the iterations'; an optimizer whose state
    # changes type compiles again, as a plain jax.jit would; programs an earlier call compiled are reused
    update = AheadOfTime(cached.jitted, "jaxmpm calibrate: compiling the loss and its gradient", show)
    update.programs = cached.programs
    update.compile(raw, opt_state, mask)
    with bar(show, total=steps, unit="it", desc="jaxmpm calibrate") as progress_bar:
        for it in range(steps):
            params = constrained(raw)
            raw, opt_state, value, grad_norm = update(raw, opt_state, mask)
            value = float(value)
            _check_finite(it, value, float(grad_norm), params, losses)
            losses.append(value)
            for k in init:
                trajectory[k].append(np.asarray(params[k]))
            if progress_bar is not None:
                progress_bar.set_postfix_str(f"loss {value:.3e}, |grad| {float(grad_norm):.2e}", refresh=False)
                progress_bar.update(1)
            if callback is not None:
                callback(it, value, params)
            if tol is not None and value < tol:
                break
    final = {k: np.asarray(v) for k, v in constrained(raw).items()}
    for k in init:  # the parameters held (not free) keep their initial values exactly, not through exp(log(v))
        if names is not None and k not in names:
            final[k] = np.asarray(jnp.asarray(init[k], dtype=final[k].dtype))
            trajectory[k] = [final[k]] * len(trajectory[k])
    wall_time = time.perf_counter() - start
    if check_stability:
        _check_stable_at(loss, final)
    return CalibrationResult(final, np.asarray(losses), {k: np.asarray(v) for k, v in trajectory.items()},
                             len(losses), wall_time, update.compile_time)


def _check_stable_at(loss, params: dict) -> None:
    """The loss evaluated outside any trace at ``params``: its runs check their stability there (inside the
    compiled update they cannot raise), and one that goes unstable is an InputError naming the parameters."""
    try:
        loss({k: jnp.asarray(v) for k, v in params.items()})
    except InstabilityError as err:
        at = ", ".join(f"{k} = {np.asarray(v).tolist()}" for k, v in params.items())
        raise InputError(f"calibrate: at the parameters reached ({at}) a run of the loss goes unstable: {err} "
                         "The optimizer stepped out of the stable range: lower the learning rate, bound the "
                         "parameters (bounds=), or lower the run's dt") from err
