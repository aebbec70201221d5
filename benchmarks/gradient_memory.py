"""Memory and time of a reverse-mode gradient through a rollout, with and without checkpointing.

d(final kinetic energy)/d(alpha_g) of the ``bar`` scene (FMPM(2), 128 cells so the state is not
trivially small) for 1k, 4k and 16k steps.  Memory is XLA's own account of the compiled gradient
(``compiled.memory_analysis().temp_size_in_bytes``: the live buffers it must keep, i.e. the
residuals of the backward pass); time is the steady state (best of 3 after a compiling call), the
forward run timed the same way gives the gradient's cost ratio.  Compile time is reported apart.

    python benchmarks/gradient_memory.py [--quick] [--csv PATH]
"""

import argparse
import csv
import os
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402

import jaxmpm as jm  # noqa: E402


def best_time(fn, arg, repeats=3):
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn(arg))
        best = min(best, time.perf_counter() - start)
    return best


def measure(steps, checkpoint, cells):
    setup = jm.scene("bar", scheme=jm.FMPM(order=2), cells=cells, v0=0.01)

    def loss(alpha):
        sim = jm.set_params(setup.sim, alpha_g=alpha)
        final, _ = sim.run(setup.state, setup.dt, steps, steps, save_particles=False, checkpoint=checkpoint)
        return jm.kinetic_energy(final)

    x = jnp.asarray(0.01)
    start = time.perf_counter()
    grad = jax.jit(jax.grad(loss)).lower(x).compile()
    compile_s = time.perf_counter() - start
    temp = grad.memory_analysis().temp_size_in_bytes
    forward = jax.jit(loss).lower(x).compile()
    jax.block_until_ready(grad(x))
    jax.block_until_ready(forward(x))
    t_grad = best_time(grad, x)
    t_fwd = best_time(forward, x)
    return dict(steps=steps, checkpoint=checkpoint, particles=int(setup.state.x.shape[0]),
                temp_MiB=temp / 2**20, grad_s=t_grad, forward_s=t_fwd, ratio=t_grad / t_fwd, compile_s=compile_s)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="1k and 4k steps only")
    parser.add_argument("--cells", type=int, default=128)
    parser.add_argument("--csv", default=os.path.join(os.path.dirname(__file__), "results", "gradient_memory.csv"))
    args = parser.parse_args()
    rows = []
    for steps in ((1000, 4000) if args.quick else (1000, 4000, 16000)):
        for checkpoint in (False, True):
            r = measure(steps, checkpoint, args.cells)
            rows.append(r)
            print(f"steps {steps:6d}  checkpoint {str(checkpoint):5s}  temp {r['temp_MiB']:9.2f} MiB  "
                  f"grad {r['grad_s']:.3f} s  forward {r['forward_s']:.3f} s  grad/forward {r['ratio']:.2f}  "
                  f"compile {r['compile_s']:.1f} s", flush=True)
    os.makedirs(os.path.dirname(args.csv), exist_ok=True)
    with open(args.csv, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    print(f"uptime: {os.popen('uptime').read().strip()}")


if __name__ == "__main__":
    main()
