"""``sim.run`` with runtime frame and step counts against static scans (``RUNTIME_COUNTS`` in
jaxmpm/transfer/backend.py): the run's speed, its first call, and a run of another length, each way in a fresh
process.

    python benchmarks/run_counts.py                 # mpm88 at 8k, 131k and 524k particles, 200 steps, a frame every 10
    python benchmarks/run_counts.py --quick         # 1k and 4k particles, 40 steps (a CPU, under a minute)

With runtime counts (the CPU's setting) ``sim.run`` outside a trace calls one compiled loop for any run length; with
static scans (the GPU's setting) each length compiles its rollout.  On the CPU the two run at the same speed for
runs of some length (2026-11-29: mpm88 8k float32, 200 steps, 0.88-0.92 against 0.94 ms a step; 131k float64 10.75
against 10.67-10.94), while a short run of a small model pays 1-2 ms a run (the initial frame's call of the loop,
the state's copy, the frames joined on the host; a call of the loop itself costs 0.16 ms to dispatch): ``--quick``,
40 steps, 1k particles 0.125-0.128 against 0.096-0.099 ms a step, 4k 0.331-0.350 against 0.287-0.306, and a run of
another length 0.01-0.04 s against 1.07-1.16 s.  XLA:GPU
reads a while loop's predicate back to the host every iteration unless its trip count is known, so a step there may
cost a host round trip more with runtime counts: this script measures it on a device (``gpu_session.sh``), and
whoever runs it sets the GPU row of ``RUNTIME_COUNTS`` from the ratio.  Each row: the first ``sim.run`` (compile
and run), the same run again (best of ``--repeat``), and a run of ``steps + 10 * save_every`` steps (a new length:
a compilation with static scans).  float32, the state kept (not donated).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

SIZES = (8192, 131072, 524288)
QUICK = (1024, 4096)


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--sizes", type=int, nargs="+", default=None, help="mpm88's particles (default 8k 131k 524k)")
    p.add_argument("--steps", type=int, default=None, help="steps of the run (default 200; --quick 40)")
    p.add_argument("--save-every", type=int, default=10)
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--quick", action="store_true", help="1k and 4k particles, 40 steps")
    p.add_argument("--worker", default=None, help=argparse.SUPPRESS)
    return p.parse_args(argv)


def worker(counts: bool, particles: int, steps: int, save_every: int, repeat: int) -> dict:
    """One process, one setting: (first call s, run s, another length s, final kinetic energy)."""
    import time

    import jax

    import jaxmpm as jm
    from jaxmpm.transfer import backend

    for policy in backend.RUNTIME_COUNTS:
        backend.RUNTIME_COUNTS[policy] = counts
    setup = jm.scene("mpm88", n_particles=particles, dtype="f32")
    sim, state, dt = setup.sim, setup.state, setup.dt

    def timed(n):
        tic = time.perf_counter()
        final, _ = jax.block_until_ready(sim.run(state, dt, n, save_every, save_particles=False))
        return time.perf_counter() - tic, final

    first, final = timed(steps)
    run = min(timed(steps)[0] for _ in range(repeat))
    other, _ = timed(steps + 10 * save_every)
    return dict(first_s=first, run_s=run, other_length_s=other, ke=float((final.v ** 2).sum()))


def main(argv=None) -> int:
    args = parse_args(argv)
    if args.worker:
        counts, particles = args.worker.split(":")
        out = worker(counts == "runtime", int(particles), args.steps, args.save_every, args.repeat)
        print(json.dumps(out))
        return 0
    sizes = args.sizes or (QUICK if args.quick else SIZES)
    steps = args.steps or (40 if args.quick else 200)
    import jax

    print(f"sim.run of mpm88 (float32, {steps} steps, a frame every {args.save_every}) on {jax.devices()[0]}; "
          "each setting in a fresh process\n")
    print("| particles | counts | first call s | run ms/step | another length s | runtime / static run |")
    print("|---|---|---|---|---|---|")
    for n in sizes:
        rows = {}
        for counts in ("static", "runtime"):
            cmd = [sys.executable, __file__, "--worker", f"{counts}:{n}", "--steps", str(steps), "--save-every",
                   str(args.save_every), "--repeat", str(args.repeat)]
            env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1]), JAXMPM_CACHE="0")
            done = subprocess.run(cmd, capture_output=True, text=True, env=env, check=True)
            rows[counts] = json.loads(done.stdout.strip().splitlines()[-1])
        if rows["static"]["ke"] != rows["runtime"]["ke"]:
            print(f"  (the two final states differ: kinetic energy {rows['static']['ke']!r} against "
                  f"{rows['runtime']['ke']!r})")
        for counts, row in rows.items():
            ratio = row["run_s"] / rows["static"]["run_s"]
            print(f"| {n} | {counts} | {row['first_s']:.2f} | {1e3 * row['run_s'] / steps:.3f} | "
                  f"{row['other_length_s']:.2f} | {ratio:.2f} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
