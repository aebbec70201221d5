"""A roofline for the CPU step (issue 30 item 5): bytes a particle-step moves against the memory
bandwidth of this machine.

* **Bandwidth**: the best of several passes of a compiled ``x <- a * x`` over 32 Mi float32 (128 MiB
  read, 128 MiB written, larger than any cache; in place), counted as bytes read + written per second: what
  XLA's own loops reach on this machine, all cores.
* **The step**: mpm88 (``jaxmpm.scene("mpm88")``, float32, APIC + quadratic B-splines, 128^2 grid)
  at 8k, 32k and 131k particles; one step's ``bytes accessed`` and ``flops`` as XLA counts them in the
  compiled program (``cost_analysis``), per particle; the measured time per step (a jitted scan of
  ``--steps`` steps, best of ``--repeats``), and from both the bandwidth the step reaches.
* **The floor**: the bytes a particle-step must move at least -- read and write the particle state
  (x, v, F, C: 2 + 2 + 4 + 4 floats, and read the mass and volume), plus the grid's mass and momentum
  written by P2G and read by G2P (3 floats per node, twice) -- divided by the bandwidth: the time
  no implementation can beat on this machine, next to the time measured.

    python benchmarks/roofline.py
    python benchmarks/roofline.py --particles 8192 --steps 200
"""

from __future__ import annotations

import argparse
import os
import time

BYTES_F32 = 4


def bandwidth(jax, jnp, n=32 * 2**20, repeats=10) -> float:
    """Bytes read + written per second by a compiled elementwise pass over n float32, in place
    (the input donated, so no pass pays for fresh pages)."""
    x = jnp.ones((n,), jnp.float32)
    scale = jax.jit(lambda a: a * 1.0001, donate_argnums=0)
    x = jax.block_until_ready(scale(x))
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        x = jax.block_until_ready(scale(x))
        best = min(best, time.perf_counter() - start)
    return 2 * n * BYTES_F32 / best


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--particles", type=int, nargs="+", default=[8192, 32768, 131072])
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args(argv)

    import equinox as eqx
    import jax
    import jax.numpy as jnp

    import jaxmpm as jm

    bw = bandwidth(jax, jnp)
    print(f"{os.cpu_count()} CPUs, load {os.getloadavg()[0]:.1f}; jax {jax.__version__}")
    print(f"memory bandwidth (compiled a * x in place, 256 MiB moved): {bw / 1e9:.1f} GB/s")
    print(f"{'particles':>9} {'XLA B/p-step':>12} {'flops/p-step':>12} {'floor B/p-step':>14} "
          f"{'us/step':>8} {'floor us':>8} {'GB/s reached':>12} {'of bandwidth':>12}")

    @eqx.filter_jit
    def advance(sim, state, dt, n):
        return jax.lax.scan(lambda s, _: (sim.step(s, dt), None), state, None, length=n)[0]

    for n in args.particles:
        setup = jm.scene("mpm88", n_particles=n)
        sim, state = setup.sim, setup.state
        dt = jnp.asarray(setup.dt, state.x.dtype)
        cost = jax.jit(lambda s, dt: sim.step(s, dt)).lower(state, dt).compile().cost_analysis()
        cost = cost[0] if isinstance(cost, (list, tuple)) else cost
        xla_bytes, flops = float(cost.get("bytes accessed", float("nan"))), float(cost.get("flops", float("nan")))
        jax.block_until_ready(advance(sim, state, dt, args.steps))
        best = float("inf")
        for _ in range(args.repeats):
            start = time.perf_counter()
            jax.block_until_ready(advance(sim, state, dt, args.steps))
            best = min(best, time.perf_counter() - start)
        per_step = best / args.steps
        nodes = sim.grid.num_nodes
        floor_bytes = n * (2 * (2 + 2 + 4 + 4) + 2) * BYTES_F32 + nodes * 3 * 2 * BYTES_F32
        print(f"{n:9d} {xla_bytes / n:12.0f} {flops / n:12.0f} {floor_bytes / n:14.0f} {per_step * 1e6:8.0f} "
              f"{floor_bytes / bw * 1e6:8.1f} {xla_bytes / per_step / 1e9:12.1f} {xla_bytes / per_step / bw:12.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
