"""Memory and time of a reverse-mode gradient through a rollout, with and without checkpointing.

The gradient is d(final kinetic energy)/d(alpha_g) of the ``bar`` scene (FMPM(2) by default, 128 cells =
256 particles so that the per-step state is not trivially small, v0 = 0.01) for 1k, 4k and 16k steps,
or (``--scene disks`` / ``--scene mpm88``, ``--particles`` for mpm88) the derivative of the final kinetic
energy with respect to a factor on the initial velocities,
with ``sim.run(..., checkpoint=False)`` (every intermediate of every step is kept for the backward pass)
and ``checkpoint=True`` (segments of about sqrt(steps) steps are recomputed: O(sqrt T) memory), or
``--checkpoint states`` (every step's state kept, each step recomputed once: O(T) states).

Each configuration runs in a fresh subprocess, which reports

* ``temp_MiB``: XLA's own account of the compiled gradient, ``compiled.memory_analysis().temp_size_in_bytes``
  (the buffers it keeps alive: the backward pass's residuals); ``forward_temp_MiB`` the same for the forward;
* ``rss_compile_MiB`` / ``rss_peak_MiB``: the process's peak resident memory (``ru_maxrss``) after compiling
  and after running, minus that of a baseline process that imports jax and jaxmpm and builds the scene
  but compiles nothing (so they include XLA's compile-time memory and the arrays of the run);
* ``compile_s``: lowering + compiling the gradient (``jax.jit(grad, compiler_options=jm.compiler_options())``,
  as ``jm.calibrate`` compiles; ``.lower(x).compile()``);
* ``grad_s`` / ``forward_s``: best of ``--repeat`` calls (3) after a warm-up call (none with
  ``--repeat 1``, for runs of minutes); ``ratio`` = grad_s / forward_s.

    python benchmarks/gradient_memory.py            # 1k, 4k, 16k steps (about 2 minutes on 2 CPU cores)
    python benchmarks/gradient_memory.py --quick    # 1k and 4k steps
    python benchmarks/gradient_memory.py --scheme flip xpic2 fmpm2 apic --cells 256 --csv /tmp/g.csv
    python benchmarks/gradient_memory.py --scene mpm88 --scheme apic --particles 8192 --steps 1000 --checkpoint True
    python benchmarks/gradient_memory.py --scene mpm88 --particles 131072 --steps 1000 --checkpoint True --repeat 1

``--checkpoint True`` leaves out the uncheckpointed gradient, whose residuals outgrow the memory of
most machines on the larger scenes (mpm88, 8k particles, 1000 steps: about 31 GiB).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import time
from pathlib import Path

from _results import CHECKPOINTS, write_csv

DEFAULT_CSV = Path(__file__).resolve().parent / "results" / "gradient_memory.csv"
SCHEMES = ("fmpm2", "flip", "xpic2", "apic")
SCENES = ("bar", "disks", "mpm88")
FIELDS = ["scene", "scheme", "cells", "particles", "steps", "checkpoint", "temp_MiB", "forward_temp_MiB",
          "rss_compile_MiB", "rss_peak_MiB", "baseline_rss_MiB", "compile_s", "grad_s", "forward_s", "ratio",
          "gradient", "load_1min"]


def peak_rss_mib() -> float:
    """Peak resident set size of this process (Linux reports ru_maxrss in KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def build(scene: str, scheme: str, size: int):
    """The scene (``size``: the bar's cells, mpm88's particles; unused for disks) and the name and
    value of the parameter differentiated ("amplitude": a factor on the initial velocities); imports
    jax here so the parent process stays light."""
    import jax

    jax.config.update("jax_enable_x64", os.environ.get("GRADIENT_MEMORY_PRECISION", "float64") == "float64")
    import jaxmpm as jm

    chosen = {"fmpm2": jm.FMPM(order=2), "flip": jm.FLIP(), "xpic2": jm.XPIC(order=2), "apic": jm.APIC()}[scheme]
    if scene == "bar":
        return jax, jm, jm.scene("bar", scheme=chosen, cells=size, v0=0.01), ("alpha_g", 0.01)
    options = {"n_particles": size} if scene == "mpm88" else {}
    return jax, jm, jm.scene(scene, scheme=chosen, **options), ("amplitude", 1.0)


def child(scene: str, scheme: str, size: int, steps: int, checkpoint, repeat: int = 3) -> dict:
    """One configuration, measured in this (fresh) process."""
    jax, jm, setup, (name, value) = build(scene, scheme, size)
    import equinox as eqx
    import jax.numpy as jnp

    def loss(p):
        state = setup.state
        if name == "amplitude":
            sim, state = setup.sim, eqx.tree_at(lambda s: s.v, state, p * state.v)
        else:
            sim = jm.set_params(setup.sim, **{name: p})
        final, _ = sim.run(state, setup.dt, steps, steps, save_particles=False, checkpoint=checkpoint)
        return jm.kinetic_energy(final)

    x = jnp.asarray(value)
    start = time.perf_counter()
    options = jm.compiler_options()  # what jm.calibrate compiles with (neutral at small sizes)
    grad = jax.jit(jax.grad(loss), compiler_options=options).lower(x).compile()
    compile_s = time.perf_counter() - start
    forward = jax.jit(loss, compiler_options=options).lower(x).compile()
    rss_compile = peak_rss_mib()

    def best(fn):
        """(best time, value of the last call)"""
        if repeat > 1:
            jax.block_until_ready(fn(x))  # warm-up
        times = []
        for _ in range(repeat):
            start = time.perf_counter()
            out = jax.block_until_ready(fn(x))
            times.append(time.perf_counter() - start)
        return min(times), out

    (grad_s, gradient), (forward_s, _) = best(grad), best(forward)
    return dict(
        scene=scene, scheme=scheme, cells=size if scene == "bar" else None, particles=int(setup.state.x.shape[0]),
        steps=steps, checkpoint=checkpoint,
        temp_MiB=grad.memory_analysis().temp_size_in_bytes / 2**20,
        forward_temp_MiB=forward.memory_analysis().temp_size_in_bytes / 2**20,
        rss_compile_MiB=rss_compile, rss_peak_MiB=peak_rss_mib(), compile_s=compile_s, grad_s=grad_s,
        forward_s=forward_s, ratio=grad_s / forward_s, gradient=float(gradient),
    )


def baseline(scene: str, scheme: str, size: int) -> dict:
    """Imports and the scene, nothing compiled: the memory every child starts from."""
    build(scene, scheme, size)
    return dict(rss_peak_MiB=peak_rss_mib())


def in_subprocess(*args) -> dict:
    out = subprocess.run([sys.executable, __file__, "--child", *map(str, args)], check=True, capture_output=True,
                         text=True, env={k: v for k, v in os.environ.items() if k != "XLA_FLAGS"})
    return json.loads(out.stdout.strip().splitlines()[-1])


def print_row(row: dict, header: bool) -> None:
    cols = [("scheme", 6, ""), ("steps", 6, "d"), ("checkpoint", 10, ""), ("temp_MiB", 9, ".2f"),
            ("rss_peak_MiB", 12, ".1f"), ("rss_compile_MiB", 15, ".1f"), ("compile_s", 9, ".2f"),
            ("forward_s", 9, ".3f"), ("grad_s", 8, ".3f"), ("ratio", 6, ".2f")]
    if header:
        print("  ".join(f"{name:>{w}}" for name, w, _ in cols))
    print("  ".join(f"{str(row[name]) if fmt == '' else format(row[name], fmt):>{w}}" for name, w, fmt in cols),
          flush=True)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="1k and 4k steps only")
    parser.add_argument("--steps", type=int, nargs="+", default=None, help="step counts (default 1000 4000 16000)")
    parser.add_argument("--scene", choices=SCENES, default="bar")
    parser.add_argument("--cells", type=int, default=128, help="cells along the bar (2 particles each)")
    parser.add_argument("--particles", type=int, default=8192, help="mpm88's particles")
    parser.add_argument("--scheme", choices=SCHEMES, nargs="+", default=["fmpm2"], help="one or more scheme families")
    parser.add_argument("--checkpoint", choices=("False", "True", "states"), nargs="+", default=["False", "True"],
                        help="the schedules measured (default both)")
    parser.add_argument("--repeat", type=int, default=3, help="timed calls of each program (best of; 1: no warm-up)")
    parser.add_argument("--precision", choices=("float64", "float32"), default="float64",
                        help="the precision of the scene and its gradient (default float64)")
    parser.add_argument("--csv", default=str(DEFAULT_CSV))
    parser.add_argument("--child", nargs="+", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)

    if args.child:  # internal: one measurement, printed as JSON
        if args.child[0] == "baseline":
            result = baseline(args.child[1], args.child[2], int(args.child[3]))
        else:
            scene, scheme, size, steps, checkpoint, repeat = args.child
            result = child(scene, scheme, int(size), int(steps), CHECKPOINTS[checkpoint], int(repeat))
        print(json.dumps(result))
        return 0

    os.environ["GRADIENT_MEMORY_PRECISION"] = args.precision  # the children inherit it
    steps_list = args.steps or ([1000, 4000] if args.quick else [1000, 4000, 16000])
    size = args.cells if args.scene == "bar" else args.particles
    what = (f"{args.cells} cells" if args.scene == "bar"
            else f"{args.particles} particles" if args.scene == "mpm88" else "")
    if args.repeat < 1:
        parser.error(f"--repeat {args.repeat} must be at least 1")
    print(f"{args.scene}, {' '.join(args.scheme)}, {what}, {args.precision}; python {platform.python_version()}, "
          f"{os.cpu_count()} CPUs; load {os.getloadavg()}")
    rows = []
    for scheme in args.scheme:
        base = in_subprocess("baseline", args.scene, scheme, size)["rss_peak_MiB"]
        print(f"{scheme}: baseline process (imports + scene, nothing compiled): peak RSS {base:.1f} MiB")
        for steps in steps_list:
            for checkpoint in args.checkpoint:
                row = in_subprocess(args.scene, scheme, size, steps, checkpoint, args.repeat)
                row["rss_compile_MiB"] -= base
                row["rss_peak_MiB"] -= base
                row["baseline_rss_MiB"] = base
                row["load_1min"] = os.getloadavg()[0]
                print_row(row, header=not rows)
                rows.append(row)
    for scheme in args.scheme:
        for steps in steps_list:
            pair = [next((r for r in rows if r["scheme"] == scheme and r["steps"] == steps and r["checkpoint"] is c),
                         None) for c in (False, True)]
            if None in pair:
                continue
            plain, remat = pair
            same = abs(remat["gradient"] - plain["gradient"]) <= (1e-10 if args.precision == "float64" else 1e-4) * abs(
                plain["gradient"])
            print(f"{scheme} {steps:6d} steps: checkpointing keeps {remat['temp_MiB'] / plain['temp_MiB']:.4f} of the "
                  f"temporaries, costs {remat['grad_s'] / plain['grad_s']:.2f}x the time; same gradient: {same}")
    print(f"wrote {write_csv(args.csv, FIELDS, rows)}; load after: {os.getloadavg()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
