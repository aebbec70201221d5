"""Gradient time / forward time of a whole rollout, per scene and scheme family, under the structured
adjoint (``Simulation(adjoint="structured")``, the default) and JAX's plain autodiff
(``adjoint="autodiff"``), measured in one process (issue 15).

The loss is sum(v^2) + sum(x^2) of the final state of ``sim.run`` (frames of a tenth of the run,
no particle frames), differentiated with respect to the initial velocities.  For each
(scene, scheme, adjoint, checkpoint) it reports the forward run time, the gradient run time
(best of ``--repeat`` calls after a warm-up) and their ratio, and the compile times of both
apart (with the persistent compilation cache off, so that they are XLA's, not programs read back
from disk).  Times are CPU seconds of this process (``time.process_time``): run it pinned to one
core with one XLA thread so that other load on the machine stays out of the ratios,

    XLA_FLAGS=--xla_cpu_multi_thread_eigen=false taskset -c 0 python benchmarks/gradient_cost.py
    ... python benchmarks/gradient_cost.py --scenes mpm88 --schemes apic --checkpoint True False
    ... python benchmarks/gradient_cost.py --scenes mpm88 --particles 131072 --steps 20 --checkpoint auto

``--reuse-host-memory`` has glibc keep the memory a call frees (``jm.reuse_host_memory``): a gradient whose
temporaries exceed 32 MiB no longer pages them in at every call.

Adding ``--xla_cpu_experimental_ynn_fusion_type=`` to XLA_FLAGS (jax 0.10) turns off the library
kernels XLA:CPU uses for reductions, to see what they cost (see the benchmarks README).

Next to each ratio it prints the floor of any schedule that runs every step forward twice and
transposes it once (one level, ``checkpoint="states"``, is that schedule): 2 + the step's transpose
alone / the step, in CPU time and in XLA's operation count (``step_adjoint.floor_numbers``; the step
is the scene's, under the same adjoint).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
from _results import CHECKPOINTS, cpu_best, write_csv  # noqa: E402
from step_adjoint import floor_numbers  # noqa: E402

import jaxmpm as jm  # noqa: E402

SCENES = {"bar": ({"cells": 128}, 1000), "disks": ({}, 300), "mpm88": ({}, 100)}
SCHEMES = {"flip": "flip", "xpic2": "xpic:2", "fmpm2": "fmpm:2", "apic": "apic"}
# sim.run's checkpoint options
FIELDS = ["scene", "scheme", "particles", "steps", "derivative_chunks", "adjoint", "checkpoint", "forward_s", "grad_s",
          "ratio",
          "forward_compile_s", "grad_compile_s", "floor_time", "floor_ops"]


def compiled(fn, *args, donate=()):
    """(``fn`` compiled for ``args``, CPU seconds): as jm.calibrate compiles; ``donate``: the positions of the
    arguments whose buffers the program may reuse (``donate_argnums``)."""
    start = time.process_time()
    out = jax.jit(fn, compiler_options=jm.compiler_options(), donate_argnums=donate).lower(*args).compile()
    return out, time.process_time() - start


FLOORS = {}  # (scene, scheme, adjoint) -> step_adjoint.floor_numbers


def final_state_loss(sim, state, dt, steps: int, checkpoint="auto"):
    """This script's loss as a function of the initial velocities: sum(v^2) + sum(x^2) of the final state of
    ``sim.run`` from ``state`` (``steps`` steps, a frame every tenth of them, no particle frames)."""

    def loss(v0):
        start = eqx.tree_at(lambda s: s.v, state, v0)
        final, _ = sim.run(start, dt, steps, max(1, steps // 10), save_particles=False, checkpoint=checkpoint)
        return jnp.sum(final.v ** 2) + jnp.sum(final.x ** 2)

    return loss


def measure(scene, scheme, adjoint, checkpoint, repeat, particles=None, steps=None, derivative_chunks="auto"):
    """One row; ``particles`` (mpm88's ``n_particles``) and ``steps`` replace the scene's defaults where given;
    ``derivative_chunks``: the model's ``with_derivative_chunks``."""
    options, default_steps = SCENES[scene]
    steps = steps or default_steps
    if particles is not None:
        options = dict(options, n_particles=particles)
    setup = jm.scene(scene, scheme=SCHEMES[scheme], **options)
    sim, state, dt = setup.sim.with_adjoint(adjoint).with_derivative_chunks(derivative_chunks), setup.state, setup.dt

    loss = final_state_loss(sim, state, dt, steps, checkpoint)
    if (scene, scheme, adjoint) not in FLOORS:  # 2 + this step's transpose alone / its forward
        FLOORS[scene, scheme, adjoint] = floor_numbers(sim, state, dt, max(repeat, 5))
    floor = FLOORS[scene, scheme, adjoint]
    forward, forward_compile = compiled(loss, state.v)
    grad, grad_compile = compiled(jax.grad(loss), state.v)
    forward_s = cpu_best(forward, state.v, repeat=repeat)
    grad_s = cpu_best(grad, state.v, repeat=repeat)
    return dict(scene=scene, scheme=scheme, particles=int(state.x.shape[0]), steps=steps,
                derivative_chunks=jm.backend_info(sim, state)["derivative_chunk_particles"], adjoint=adjoint,
                checkpoint=checkpoint, forward_s=forward_s, grad_s=grad_s, ratio=grad_s / forward_s,
                forward_compile_s=forward_compile, grad_compile_s=grad_compile, floor_time=floor["floor_time"],
                floor_ops=floor["floor_ops"])


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", nargs="+", default=list(SCENES), choices=list(SCENES))
    parser.add_argument("--schemes", nargs="+", default=list(SCHEMES), choices=list(SCHEMES))
    parser.add_argument("--adjoints", nargs="+", default=["structured", "autodiff"], choices=["structured", "autodiff"])
    parser.add_argument("--checkpoint", nargs="+", default=["True"], choices=list(CHECKPOINTS))
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--particles", type=int, default=None,
                        help="mpm88's particles (default: the scene's 8192); e.g. 131072, whose steps' derivatives go "
                             "in chunks (DERIVATIVE_CHUNK_TABLE)")
    parser.add_argument("--steps", type=int, default=None, help="steps of every scene (default: 1000, 300, 100)")
    parser.add_argument("--derivative-chunk-particles", default="auto", type=lambda v: v if v == "auto" else int(v),
                        help="the steps' derivatives in chunks of this many particles (0: the whole step's; default "
                             "auto: the library's table)")
    parser.add_argument("--reuse-host-memory", action="store_true",
                        help="jm.reuse_host_memory() first: glibc keeps the memory the programs free, so a call "
                             "does not page its temporaries in again (the same as JAXMPM_REUSE_HOST_MEMORY=1)")
    parser.add_argument("--csv", default=str(Path(__file__).resolve().parent / "results" / "gradient_cost.csv"))
    args = parser.parse_args()
    if args.reuse_host_memory:  # before JAX starts its threads (nothing has run yet)
        print(f"jm.reuse_host_memory(): {jm.reuse_host_memory()}")
    jm.compilation_cache(False)  # the compile columns are XLA's compile seconds, not programs read back from disk
    print("| scene | scheme | particles | steps | adjoint | checkpoint | forward (s) | gradient (s) | gradient / "
          "forward | floor: time / ops | compile forward / gradient (s) |")
    print("|---" * 11 + "|")
    rows = []
    for scene in args.scenes:
        for scheme in args.schemes:
            for checkpoint in (CHECKPOINTS[c] for c in args.checkpoint):
                for adjoint in args.adjoints:
                    r = measure(scene, scheme, adjoint, checkpoint, args.repeat,
                                args.particles if scene == "mpm88" else None, args.steps,
                                args.derivative_chunk_particles)
                    rows.append(r)
                    print(f"| {scene} | {scheme} | {r['particles']} | {r['steps']} | {adjoint} | {checkpoint} | "
                          f"{r['forward_s']:.3f} | {r['grad_s']:.3f} | {r['ratio']:.2f} | "
                          f"{r['floor_time']:.2f} / {r['floor_ops']:.2f} | "
                          f"{r['forward_compile_s']:.1f} / {r['grad_compile_s']:.1f} |", flush=True)
    print(f"wrote {write_csv(args.csv, FIELDS, rows)}")


if __name__ == "__main__":
    main()
