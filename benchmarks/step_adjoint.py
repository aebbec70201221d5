"""Where a step's reverse-mode cost goes: the pullback of one step with respect to each particle
field, relative to the step itself (issue 15's diagnosis).

For each scene the forward step ``sim.step(state, dt)`` is timed, then the VJP of the new
velocities with respect to one field of the state at a time (positions X, velocities V,
deformation gradients F, the scheme's state such as APIC's B_p), and the VJP of v and x with
respect to the whole state.  Times are CPU seconds of this process (``time.process_time``),
best of ``--repeat`` calls after a warm-up: run it pinned to one core with one XLA thread so that
other load on the machine does not enter the ratios,

    XLA_FLAGS=--xla_cpu_multi_thread_eigen=false taskset -c 0 python benchmarks/step_adjoint.py

A structured adjoint should bring every column near 2 (one forward plus a transpose of similar
cost).  Columns well above that name the path to work on.

A second table bounds what any checkpointing schedule can reach.  It splits the gradient of the
whole step (every float of the new state, cotangent ones) in two programs: "linearise", the
forward step that also hands out every residual its pullback reads (the per-step price of a
schedule that stores residuals instead of recomputing them), and "transpose alone", the pullback
fed those residuals, with no forward work at all; times as multiples of the whole step, and the
floating-point operations XLA counts in each program (``cost_analysis``) as multiples of the
step's.  A rollout gradient that keeps O(sqrt T) states evaluates every step forward at least
twice (the pass that yields the loss, and once more from a checkpoint) and transposes it once, so
its operation count is at least 2 + (transpose / forward) times the forward run's: the last
column, whatever the schedule.  ``--adjoint autodiff`` measures JAX's
plain rules (``Simulation(adjoint="autodiff")``) in place of the structured default.
"""

from __future__ import annotations

import argparse

import jax

jax.config.update("jax_enable_x64", True)

import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
from _results import cpu_best  # noqa: E402

import jaxmpm as jm  # noqa: E402

CASES = (("bar", "flip", {"cells": 128}), ("disks", "flip", {}), ("mpm88", "apic", {}), ("mpm88", "flip", {}))
FIELDS = {"X": lambda s: s.x, "V": lambda s: s.v, "F": lambda s: s.F, "scheme state": lambda s: s.scheme_state}


def measure(scene: str, scheme: str, options: dict, repeat: int, adjoint: str = "structured") -> str:
    setup = jm.scene(scene, scheme=scheme, **options)
    sim, state, dt = setup.sim.with_adjoint(adjoint), setup.state, setup.dt
    forward = cpu_best(jax.jit(lambda s: sim.step(s, dt).v), state, repeat=repeat)
    cells = [f"{scene} {scheme} ({state.x.shape[0]} particles)", f"{forward * 1e6:.0f}"]
    for get in FIELDS.values():
        leaf = get(state)
        if leaf is None or not jnp.issubdtype(jnp.asarray(leaf).dtype, jnp.floating):
            cells.append("-")
            continue

        def pull(a, get=get):
            return jax.vjp(lambda a: sim.step(eqx.tree_at(get, state, a), dt).v, a)[1](state.v)[0]

        cells.append(f"{cpu_best(jax.jit(pull), leaf, repeat=repeat) / forward:.1f}")

    def loss(s):
        new = sim.step(s, dt)
        return jnp.sum(new.v ** 2) + jnp.sum(new.x ** 2)

    whole = cpu_best(eqx.filter_jit(eqx.filter_grad(loss)), state, repeat=repeat)
    cells.append(f"{whole / forward:.1f}")
    return "| " + " | ".join(cells) + " |"


def flops(fn, *args) -> float:
    """The floating-point operations XLA counts in the compiled ``fn(*args)``."""
    cost = jax.jit(fn).lower(*args).compile().cost_analysis()
    return (cost[0] if isinstance(cost, (list, tuple)) else cost)["flops"]


def floor_numbers(sim, state, dt, repeat: int) -> dict:
    """The whole step's gradient split in two (module docstring): CPU seconds of the step, the step's
    gradient, "linearise" and "transpose alone" as multiples of the step's time, the gradient's and the
    transpose's operations as multiples of the step's, and the floor of a rollout gradient,
    2 + transpose / forward, in operations and in time."""
    floats, rest = eqx.partition(state, eqx.is_inexact_array)

    def step(d):  # the whole step: every float of the new state
        return eqx.partition(sim.step(eqx.combine(d, rest), dt), eqx.is_inexact_array)[0]

    def linearise(d):
        return jax.vjp(step, d)[1]

    def transpose(pullback, cotangent):
        return pullback(cotangent)

    def gradient(d, cotangent):  # the two in one program
        return transpose(linearise(d), cotangent)

    ones = jax.tree_util.tree_map(jnp.ones_like, floats)
    pullback = jax.jit(linearise)(floats)
    forward = cpu_best(jax.jit(step), floats, repeat=repeat)
    times = [cpu_best(jax.jit(f), *a, repeat=repeat) / forward
             for f, a in ((gradient, (floats, ones)), (linearise, (floats,)), (transpose, (pullback, ones)))]
    step_flops = flops(step, floats)
    ops = [flops(f, *a) / step_flops for f, a in ((gradient, (floats, ones)), (transpose, (pullback, ones)))]
    return dict(step_s=forward, gradient=times[0], linearise=times[1], transpose=times[2], gradient_ops=ops[0],
                transpose_ops=ops[1], floor_ops=2 + ops[1], floor_time=2 + times[2])


def floor(scene: str, scheme: str, options: dict, repeat: int, adjoint: str = "structured") -> str:
    setup = jm.scene(scene, scheme=scheme, **options)
    f = floor_numbers(setup.sim.with_adjoint(adjoint), setup.state, setup.dt, repeat)
    cells = [f"{scene} {scheme} ({setup.state.x.shape[0]} particles)", f"{f['step_s'] * 1e6:.0f}",
             *(f"{f[k]:.1f}" for k in ("gradient", "linearise", "transpose")),
             *(f"{f[k]:.2f}" for k in ("gradient_ops", "transpose_ops", "floor_ops"))]
    return "| " + " | ".join(cells) + " |"


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=15)
    parser.add_argument("--adjoint", choices=["structured", "autodiff"], default="structured")
    args = parser.parse_args()
    print("| scene | forward step (CPU us) | " + " | ".join(f"VJP wrt {k} / forward" for k in FIELDS)
          + " | grad of (v, x) wrt the state / forward |")
    print("|---" * (3 + len(FIELDS)) + "|")
    for scene, scheme, options in CASES:
        print(measure(scene, scheme, options, args.repeat, args.adjoint), flush=True)
    print()
    print("| scene | whole step (CPU us) | step gradient / step | linearise / step | transpose alone / step "
          "| gradient flops / step flops | transpose flops / step flops "
          "| floor: rollout gradient flops / forward flops |")
    print("|---" * 8 + "|")
    for scene, scheme, options in CASES:
        print(floor(scene, scheme, options, args.repeat, args.adjoint), flush=True)


if __name__ == "__main__":
    main()
