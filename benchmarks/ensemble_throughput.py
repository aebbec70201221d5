"""Batch throughput of ``jm.ensemble`` (one vmapped call) against single runs.

B = 1, 4, 16, 64 members of the ``bar`` (and ``disks``) scene with different beta; particle-steps per
second of the batch (all members) against a single run's, steady state (best of 3 after a
compiling call), compile time apart.

    python benchmarks/ensemble_throughput.py [--quick] [--csv PATH]
"""

import argparse
import csv
import os
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402

import jaxmpm as jm  # noqa: E402


def timed(fn, repeats=3):
    start = time.perf_counter()
    jax.block_until_ready(fn())
    first = time.perf_counter() - start
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn())
        best = min(best, time.perf_counter() - start)
    return first - best, best


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--csv", default=os.path.join(os.path.dirname(__file__), "results", "ensemble_throughput.csv"))
    args = parser.parse_args()
    scenes = {"bar": 1000, "disks": 200} if not args.quick else {"bar": 400}
    rows = []
    for name, steps in scenes.items():
        setup = jm.scene(name, scheme=jm.XPIC(order=2))
        n = int(setup.state.x.shape[0])
        single = jax.jit(lambda s=setup: s.sim.rollout(s.state, s.dt, 1, steps, save_particles=False, checkpoint=False)[0].x)
        compile_s, run_s = timed(single)
        base = n * steps / run_s
        rows.append(dict(scene=name, batch=0, particles=n, steps=steps, run_s=run_s, compile_s=compile_s,
                         particle_steps_per_s=base, vs_single=1.0))
        print(f"{name}: single run {base:.3e} particle-steps/s (compile {compile_s:.1f} s)", flush=True)
        for batch in (1, 4, 16, 64):
            betas = jnp.linspace(0.0, 0.9, batch)
            fn = lambda b=betas, s=setup: jm.ensemble(s.sim, s.state, s.dt, steps, steps, params={"beta": b})[0].x  # noqa: E731
            compile_s, run_s = timed(fn)
            rate = batch * n * steps / run_s
            rows.append(dict(scene=name, batch=batch, particles=n, steps=steps, run_s=run_s, compile_s=compile_s,
                             particle_steps_per_s=rate, vs_single=rate / base))
            print(f"{name}: batch {batch:3d}  {rate:.3e} particle-steps/s  = {rate / base:.2f} x single  "
                  f"(compile {compile_s:.1f} s)", flush=True)
    os.makedirs(os.path.dirname(args.csv), exist_ok=True)
    with open(args.csv, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    print(f"uptime: {os.popen('uptime').read().strip()}")


if __name__ == "__main__":
    main()
