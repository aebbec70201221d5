"""The checkpoint schedule of a reverse-mode rollout, chosen from a memory budget (issue 30 item 3).

A gradient through T steps needs, for the backward pass, what each step's pullback reads (its
residuals, R bytes per step).  Four schedules trade that memory against recomputation
(:func:`jaxmpm.run.driver.rollout`, ``checkpoint=``):

* ``False`` -- every step's residuals stored: T R bytes, no recomputation;
* ``"states"`` -- one level: every step's state kept (T S bytes, S << R), each step recomputed
  once for its pullback: T S + R bytes, one forward run in the backward pass;
* ``True`` -- two levels: T / L + L states of S bytes kept (L ~ sqrt T), each segment recomputed
  once and each step once more for its pullback: about (2 sqrt T) S + R bytes, two forward runs in
  the backward pass;
* ``"low_memory"`` -- three levels: about (frames + 2 sqrt(save_every)) S + R bytes, a third
  forward pass.

``checkpoint="auto"`` (the default) picks one from the budget ``memory`` (bytes, or a string such
as ``"4 GiB"``; default: half the device's free memory) and the backend's measured preference
(:data:`jaxmpm.transfer.backend.STORE_RESIDUALS_UP_TO`): store the residuals where they fit and the
backend gains by storing them; else one level where every step's state fits the budget and the
backend's limit (:data:`jaxmpm.transfer.backend.KEEP_STATES_UP_TO`); else two levels where their kept
states fit; else three.  On the CPU storing residuals has never paid (the recomputing schedules were
faster in every case measured), and one level runs one forward pass fewer than two levels (gradient /
forward 3.9-7.4 -> 3.0-6.8, benchmarks/gradient_cost.py), so "auto" is ``"states"`` there unless the
states outgrow the budget, or 16 MiB in 1D (where a step costs no more than moving its state through
memory) -- the numbers are those of the schedule it picks (every schedule gives the same gradient to
round-off).
"""

from __future__ import annotations

import contextlib
import contextvars
import math
import re

import jax
import numpy as np

from ..core.errors import check
from ..core.limits import available_bytes, size_text
from ..core.validate import POSITIVE
from ..transfer.backend import KEEP_STATES_UP_TO, STORE_RESIDUALS_UP_TO, resolve

_UNITS = {"": 1, "b": 1, "kb": 10**3, "mb": 10**6, "gb": 10**9, "tb": 10**12,
          "kib": 2**10, "mib": 2**20, "gib": 2**30, "tib": 2**40}


def parse_memory(memory) -> int | None:
    """Bytes of a budget: an int, a float, ``"4 GiB"``, ``"500MB"``; None (the default budget)."""
    if memory is None:
        return None
    if isinstance(memory, str):
        match = re.fullmatch(r"\s*([0-9.]+(?:e[+-]?[0-9]+)?)\s*([a-zA-Z]*)\s*", memory)
        check(match is not None and match.group(2).lower() in _UNITS,
              f"memory = {memory!r}: give bytes (an int) or a size such as '4 GiB', '500 MB'")
        memory = float(match.group(1)) * _UNITS[match.group(2).lower()]
    check(isinstance(memory, (int, float, np.integer, np.floating)) and not isinstance(memory, bool)
          and math.isfinite(memory) and memory > 0,
          f"memory = {memory!r}: give a positive number of bytes or a size such as '4 GiB'")
    return int(memory)


def free_memory(device=None) -> int:
    """Free bytes of ``device`` (default: the first device): the accelerator's allocator limit less
    what is in use, or the host's available memory (:func:`jaxmpm.core.limits.available_bytes`) for
    the CPU and any backend without memory statistics."""
    device = device or jax.devices()[0]
    try:
        stats = device.memory_stats()
    except Exception:  # backends without memory statistics  # noqa: BLE001
        stats = None
    if stats and "bytes_limit" in stats:
        return int(stats["bytes_limit"] - stats.get("bytes_in_use", 0))
    return available_bytes()


_members = contextvars.ContextVar("jaxmpm_members_at_once", default=1)


@contextlib.contextmanager
def members_at_once(count: int):
    """Trace the enclosed steps as those of ``count`` members stepped at once (a vmapped ensemble,
    :func:`jaxmpm.ensemble`): each member's step counts on an even share of the device's memory
    (:func:`step_memory`)."""
    token = _members.set(max(1, int(count)) * _members.get())
    try:
        yield
    finally:
        _members.reset(token)


def step_memory(devices: int = 1) -> tuple[int, str]:
    """``(bytes, note)``: the free memory one member's step on one device may count on when it decides
    whether its temporaries fit (:func:`jaxmpm.transfer.backend.chunks_to_fit`) -- the device's free
    memory shared evenly among the members stepped at once (:func:`members_at_once`) and, on the CPU,
    among the ``devices`` its particles are shared among (CPU devices share the host's memory; each GPU
    has its own).  ``note`` says how it was shared ("" when it was not)."""
    members = _members.get()
    shared = members * (devices if jax.default_backend() == "cpu" else 1)
    if shared == 1:
        return free_memory(), ""
    among = [f"{members} members stepped at once"] * (members > 1) + [
        f"{devices} CPU devices"] * (shared > members)
    return free_memory() // shared, f"; that is an even share of the free memory among {' and '.join(among)}"


def default_budget() -> int:
    """Half the device's free memory (the rest is the forward pass's and the user's)."""
    return free_memory() // 2


def budget_bytes(memory) -> int:
    """Bytes of the budget ``memory`` (:func:`parse_memory`), :func:`default_budget` for None."""
    budget = parse_memory(memory)
    return default_budget() if budget is None else budget


def tree_bytes(tree) -> int:
    """Bytes of a pytree's array leaves (arrays, tracers or shape structs)."""
    return sum(int(np.prod(np.shape(leaf))) * np.dtype(leaf.dtype).itemsize
               for leaf in jax.tree_util.tree_leaves(tree) if hasattr(leaf, "dtype"))


def residual_bytes(step, state, dt) -> int:
    """Bytes one step's pullback keeps: the leaves of ``jax.vjp``'s pullback (a pytree of the
    residuals), by shape only (``jax.eval_shape``: traced, not compiled)."""
    pullback = jax.eval_shape(lambda s: jax.vjp(lambda s: step(s, dt), s)[1], state)
    return tree_bytes(pullback)


def is_schedule(checkpoint, name: str) -> bool:
    """Whether ``checkpoint`` (``sim.run``'s argument: a bool, an int or a name) is the schedule ``name``."""
    return isinstance(checkpoint, str) and checkpoint == name


def choose_checkpoint(sim, state, dt, frames: int, save_every: int, memory=None):
    """``(checkpoint, why)``: the schedule ``checkpoint="auto"`` runs (module docstring)."""
    return _schedule(sim, state, dt, frames, save_every, budget_bytes(memory))[:2]


def _schedule(sim, state, dt, frames: int, save_every: int, budget: int, residual=None):
    """``(checkpoint, why, kept bytes)`` of the schedule "auto" picks within ``budget``; ``residual``:
    one step's residual bytes if already known (read off the step only where the backend may store them)."""
    steps = frames * save_every
    state_bytes = tree_bytes(state)
    limit = STORE_RESIDUALS_UP_TO[resolve(sim.backend)]
    if limit > 0:
        stored = steps * (residual_bytes(sim.step, state, dt) if residual is None else residual)
        if stored <= min(limit, budget):
            return False, f"every step's residuals stored ({size_text(stored)})", stored
    one_level = steps * state_bytes
    keep = KEEP_STATES_UP_TO[resolve(sim.backend)].get(state.x.shape[-1])
    if one_level <= budget and (keep is None or one_level <= keep):
        return "states", f"one level, every step's state kept ({size_text(one_level)} of states)", one_level
    segment = _segment_length(save_every, True, frames)
    two_levels = (steps // segment + segment) * state_bytes
    if two_levels <= budget:
        return True, f"two levels, segments of {segment} steps ({size_text(two_levels)} of states)", two_levels
    segment = _segment_length(save_every, "low_memory", frames)
    three_levels = (frames + save_every // segment + segment) * state_bytes
    return "low_memory", (f"three levels ({size_text(three_levels)} of states; two levels would keep "
                          f"{size_text(two_levels)}, over the budget of {size_text(budget)})"), three_levels


#: forward passes the backward pass runs again under each schedule (on top of the one that yields the loss)
RECOMPUTATIONS = {False: 0, "states": 1, True: 2, "low_memory": 3}


def gradient_schedule(sim, state, dt, steps: int, save_every: int = 1, memory=None) -> dict:
    """What reverse mode through ``sim.run(state, dt, steps, save_every, memory=memory)`` keeps, as
    ``checkpoint="auto"`` chooses it (module docstring), without compiling anything::

        setup = jm.scene("bar", scheme=jm.FMPM(order=2))        # float64
        jm.gradient_schedule(setup.sim, setup.state, setup.dt, 400, 20)
        # {'checkpoint': 'states', 'reason': "one level, every step's state kept (507.8 KiB of states)",
        #  'recomputations': 1, 'kept_bytes': 520000, 'state_bytes': 1300, 'step_residual_bytes': 20149,
        #  'budget_bytes': ...}

    Args:
        sim: the model, as given to ``sim.run`` (:class:`jaxmpm.Simulation`).
        state: the initial state.
        dt: the time step.
        steps: steps of the run, a multiple of ``save_every``.
        save_every: steps between saved frames, as in ``sim.run``.
        memory: the budget, bytes or a string such as ``"4 GiB"``; default half the device's free memory.

    Returns a dict:

    * ``checkpoint``: the schedule (``False``, ``"states"``, ``True`` or ``"low_memory"``) and
      ``reason``, why;
    * ``recomputations``: forward passes the backward pass runs again (0, 1, 2 or 3), on top of the
      forward run that yields the loss;
    * ``kept_bytes``: what the schedule keeps between the forward and the backward pass (residuals or
      states, the saved frames apart), ``state_bytes`` one state, ``step_residual_bytes`` what one
      step's pullback reads (each recomputed step holds it while it is transposed);
    * ``budget_bytes``: the budget it was chosen from (``memory``, default half the free memory).

    The step's residuals are read off ``jax.vjp``'s pullback by shape (``jax.eval_shape``: traced,
    not compiled)."""
    check(isinstance(steps, (int, np.integer)) and isinstance(save_every, (int, np.integer)) and save_every >= 1
          and steps >= save_every and steps % save_every == 0,
          f"gradient_schedule: steps = {steps!r} must be a positive multiple of save_every = {save_every!r}")
    POSITIVE.real("gradient_schedule", "dt", dt, fix="the time step, e.g. a scene's setup.dt or sim.stable_dt(state)")
    sim.check_state(state, "gradient_schedule")  # a jm.State, made for this model
    sim = sim.in_precision(state.x.dtype)  # as sim.run: the model computes in its state's precision
    dt = jax.numpy.asarray(dt, state.x.dtype)
    frames = steps // save_every
    budget = budget_bytes(memory)
    residual = residual_bytes(sim.step, state, dt)
    checkpoint, reason, kept = _schedule(sim, state, dt, frames, save_every, budget, residual)
    return dict(checkpoint=checkpoint, reason=reason, recomputations=RECOMPUTATIONS[checkpoint], kept_bytes=int(kept),
                state_bytes=tree_bytes(state), step_residual_bytes=residual, budget_bytes=budget)


def _segment_length(save_every: int, checkpoint, frames: int = 1):
    """Steps per rematerialised segment, or None for no checkpointing (see :func:`rollout`)."""
    if checkpoint is False:
        return None
    if is_schedule(checkpoint, "states"):  # one level: a frame's steps in one segment
        return save_every
    divisors = [d for d in range(1, save_every + 1) if save_every % d == 0]
    if checkpoint is True:  # two levels: fewest states kept, frames * save_every / L segment starts + L steps
        return min(divisors, key=lambda d: (frames * save_every // d + d, d))
    if is_schedule(checkpoint, "low_memory"):  # three levels: segments of ~sqrt(save_every)
        return min(divisors, key=lambda d: abs(d - math.sqrt(save_every)))
    check(isinstance(checkpoint, (int, np.integer)) and not isinstance(checkpoint, (bool, str)) and checkpoint >= 1
          and save_every % checkpoint == 0,
          f"checkpoint = {checkpoint!r} must be 'auto', 'states', True, False, 'low_memory' or a positive divisor of "
          f"save_every = {save_every}")
    return int(checkpoint)
