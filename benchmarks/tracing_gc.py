"""What Python's garbage collector costs while a program is traced (``jaxmpm.run.collector``).

Each row traces and lowers one program in a fresh process (the collector's state depends on what a
process did before), three ways, alternated:

* ``python``: CPython's thresholds (700, 10, 10) throughout; jaxmpm's scoping switched off
  (``collector.TRACING_THRESHOLD = 0``);
* ``scoped``: the default: the user's ``jax.jit(jax.grad(loss))`` traced as a user writes it, with
  jaxmpm raising the threshold inside its own calls (``sim.run``: the forward rollout's trace; JAX
  linearises and transposes it after the call returns, at the process's thresholds);
* ``whole``: the whole trace and lowering inside :func:`jaxmpm.run.collector.fewer_collections`, as
  ``jm.calibrate`` and ``jm.ensemble`` compile their programs.

    python benchmarks/tracing_gc.py                     # disks FLIP and mpm88 APIC, forward and gradient
    python benchmarks/tracing_gc.py --repeat 5 --cases mpm88:apic

Times are wall seconds of ``jax.jit(f).trace(...)`` and of ``.lower()``, best of ``--repeat`` processes.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import subprocess
import sys
import time

MODES = ("python", "scoped", "whole")


def child(scene: str, scheme: str, program: str, mode: str) -> dict:
    import gc

    import jax

    jax.config.update("jax_enable_x64", True)
    import equinox as eqx
    import jax.numpy as jnp

    import jaxmpm as jm
    from jaxmpm.run import collector

    if mode == "python":
        collector.TRACING_THRESHOLD = 0  # fewer_collections leaves every threshold alone
    setup = jm.scene(scene, scheme=scheme)
    sim, state, dt = setup.sim, setup.state, setup.dt

    def loss(v0):
        start = eqx.tree_at(lambda s: s.v, state, v0)
        final, _ = sim.run(start, dt, 100, 10, save_particles=False, checkpoint=True)
        return jnp.sum(final.v ** 2) + jnp.sum(final.x ** 2)

    jitted = jax.jit(jax.grad(loss) if program == "gradient" else loss)
    full = gc.get_stats()[2]["collections"]
    with collector.fewer_collections() if mode == "whole" else contextlib.nullcontext():
        start = time.perf_counter()
        traced = jitted.trace(state.v)
        middle = time.perf_counter()
        traced.lower()
        end = time.perf_counter()
    return dict(trace=middle - start, lower=end - middle, full_collections=gc.get_stats()[2]["collections"] - full)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cases", nargs="+", default=["disks:flip", "mpm88:apic"], help="scene:scheme")
    parser.add_argument("--programs", nargs="+", default=["forward", "gradient"], choices=["forward", "gradient"])
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--child", nargs=4, metavar=("SCENE", "SCHEME", "PROGRAM", "MODE"), help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        print(json.dumps(child(*args.child)))
        return 0
    print("| program | python: trace / lower (s) | scoped: trace / lower | whole: trace / lower | "
          "trace, whole / python | full collections (python, whole) |")
    print("|---|---|---|---|---|---|")
    for case in args.cases:
        scene, scheme = case.split(":")
        for program in args.programs:
            best = {mode: None for mode in MODES}
            for _ in range(args.repeat):
                for mode in MODES:  # alternated, each in a fresh process
                    out = subprocess.run([sys.executable, __file__, "--child", scene, scheme, program, mode],
                                         capture_output=True, text=True, check=True)
                    got = json.loads(out.stdout.strip().splitlines()[-1])
                    if best[mode] is None or got["trace"] < best[mode]["trace"]:
                        best[mode] = got
            cells = [f"{best[m]['trace']:.2f} / {best[m]['lower']:.2f}" for m in MODES]
            print(f"| {scene} {scheme} {program} | " + " | ".join(cells)
                  + f" | {best['whole']['trace'] / best['python']['trace']:.2f} | "
                  f"{best['python']['full_collections']}, {best['whole']['full_collections']} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
