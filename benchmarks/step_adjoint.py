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
cost).  Columns well above that name the path to work on.  ``--adjoint autodiff`` measures JAX's
plain rules (``Simulation(adjoint="autodiff")``) in place of the structured default.
"""

from __future__ import annotations

import argparse

import jax

jax.config.update("jax_enable_x64", True)

import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402

import jaxmpm as jm  # noqa: E402
from _results import cpu_best  # noqa: E402

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


if __name__ == "__main__":
    main()
