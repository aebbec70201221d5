"""Batch throughput of ``jm.ensemble`` (one vmapped rollout) against single runs.

For the ``bar`` (1D, 32 particles) and ``disks`` (2D, uGIMP, 416 particles) scenes under XPIC(2), batches of
B = 1, 4, 16, 64 members with different beta run as one ``jm.ensemble`` call; the single-run baseline is
one compiled rollout (``eqx.filter_jit`` of ``sim.rollout``, the same work per member, no Python loop).
A loop of B ``sim.run`` calls (what a script without ``jm.ensemble`` does) is timed as well.

Reported per row: ``compile_s`` (first call minus steady state), ``run_s`` (best of 3 after the first
call), ``particle_steps_per_s`` = B x particles x steps / run_s, and ``vs_single`` = that throughput over
the single compiled run's.  One saved frame per run, no particle frames.

    python benchmarks/ensemble_throughput.py            # bar and disks (about a minute on 2 CPU cores)
    python benchmarks/ensemble_throughput.py --quick    # bar only, fewer steps
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

import jax
from _results import write_csv

jax.config.update("jax_enable_x64", True)

import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jaxmpm as jm  # noqa: E402

DEFAULT_CSV = Path(__file__).resolve().parent / "results" / "ensemble_throughput.csv"
BATCHES = (1, 4, 16, 64)
#: scene -> (steps, steps in --quick mode)
SCENES = {"bar": (2000, 500), "disks": (200, 50)}
FIELDS = ["scene", "method", "batch", "particles", "steps", "compile_s", "run_s", "particle_steps_per_s", "vs_single",
          "load_1min", "jax", "cpus"]


def timed(fn, repeats=3):
    """(compile_s, run_s): first call minus the best of ``repeats`` further calls, and that best."""
    start = time.perf_counter()
    jax.block_until_ready(fn())
    first = time.perf_counter() - start
    best = np.inf
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn())
        best = min(best, time.perf_counter() - start)
    return max(0.0, first - best), best


@eqx.filter_jit
def single_rollout(sim, state, dt, steps):
    return sim.rollout(state, dt, 1, steps, save_particles=False, checkpoint=False)[0].v


def measure(scene: str, steps: int, batches) -> list[dict]:
    setup = jm.scene(scene, scheme=jm.XPIC(order=2))
    n = int(setup.state.x.shape[0])
    dt = jnp.asarray(setup.dt)
    common = dict(scene=scene, particles=n, steps=steps, load_1min=os.getloadavg()[0], jax=jax.__version__,
                  cpus=os.cpu_count())
    rows = []
    compile_s, run_s = timed(lambda: single_rollout(setup.sim, setup.state, dt, steps))
    base = n * steps / run_s
    rows.append(dict(common, method="single compiled rollout", batch=1, compile_s=compile_s, run_s=run_s,
                     particle_steps_per_s=base, vs_single=1.0))
    for batch in batches:
        betas = jnp.linspace(0.0, 0.9, batch)

        def batched(betas=betas):
            return jm.ensemble(setup.sim, setup.state, setup.dt, steps, steps, params={"beta": betas})[0].v

        def loop(betas=betas):
            return [jm.set_params(setup.sim, beta=b).run(setup.state, setup.dt, steps, steps, save_particles=False)[0].v
                    for b in betas]

        for method, fn in (("jm.ensemble", batched), ("loop of sim.run", loop)):
            compile_s, run_s = timed(fn)
            rate = batch * n * steps / run_s
            rows.append(dict(common, method=method, batch=batch, compile_s=compile_s, run_s=run_s,
                             particle_steps_per_s=rate, vs_single=rate / base))
    return rows


def print_rows(rows) -> None:
    print(f"{'scene':>6} {'method':>24} {'B':>3} {'particles':>9} {'steps':>6} {'compile_s':>9} {'run_s':>8} "
          f"{'particle-steps/s':>16} {'vs single':>9}")
    for r in rows:
        print(f"{r['scene']:>6} {r['method']:>24} {r['batch']:3d} {r['particles']:9d} {r['steps']:6d} "
              f"{r['compile_s']:9.2f} {r['run_s']:8.4f} {r['particle_steps_per_s']:16.3e} {r['vs_single']:9.2f}",
              flush=True)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="bar only, fewer steps")
    parser.add_argument("--scenes", nargs="+", choices=list(SCENES), default=None)
    parser.add_argument("--csv", default=str(DEFAULT_CSV))
    args = parser.parse_args(argv)
    scenes = args.scenes or (["bar"] if args.quick else list(SCENES))
    print(f"jaxmpm {jm.__version__}, jax {jax.__version__}, backend {jax.default_backend()}, {os.cpu_count()} CPUs, "
          f"python {platform.python_version()}; load {os.getloadavg()}")
    rows = []
    for scene in scenes:
        steps = SCENES[scene][1 if args.quick else 0]
        scene_rows = measure(scene, steps, BATCHES)
        print_rows(scene_rows)
        rows += scene_rows
    print(f"wrote {write_csv(args.csv, FIELDS, rows)}; load after: {os.getloadavg()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
