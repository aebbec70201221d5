"""mpm88 (or its 3D variant) with its particles shared among the process's CPU devices against one device
(jaxmpm.model.devices).

A process's device count is fixed when JAX starts, so every measurement runs in a process of its own:
one with JAX's single CPU device (the step as the chunk table has it, its large kernels split among
XLA's threads), and one with ``--devices`` CPU devices (``jax_num_cpu_devices``) among which each step
shares its particles, each device summing its share's P2G onto its own copy of the grid, the copies
added by one all-reduce.  The rounds alternate the two, so that a slow phase of a shared machine falls
on both alike.  Each measurement: ``--steps`` steps of ``sim.step`` in one jitted ``lax.scan``, best of
``--repeats`` calls after a compiling call, in ms a step; the compile time apart (the first call minus
a run); the final mean height of the two runs, which agree to round-off.

    python benchmarks/cpu_devices.py                             # 32k-524k particles, f32 and f64, 2 devices
    python benchmarks/cpu_devices.py --particles 131072 --dtype f64 --devices 2 4 --rounds 3
    python benchmarks/cpu_devices.py --quick                     # 4096 particles, f64, one round (CI)
    python benchmarks/cpu_devices.py --scene mpm3d --particles 32768 131072   # gpu.py's mpm3d (32^3, 64^3 cells)

``--chunk N`` sets the particles per chunk of a device's share (default: the table's, 16k).  Writes
``benchmarks/results/cpu_devices.csv`` (or ``--csv``).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

from _results import write_csv

DEFAULT_CSV = Path(__file__).resolve().parent / "results" / "cpu_devices.csv"


def parse_args(argv=None):
    p = argparse.ArgumentParser(description="mpm88: particles shared among CPU devices against one device")
    p.add_argument("--scene", choices=["mpm88", "mpm3d"], default="mpm88",
                   help="mpm88, or gpu.py's mpm3d (APIC in 3D: 32^3 cells up to 65k particles, 64^3 above)")
    p.add_argument("--particles", type=int, nargs="+", default=[32768, 65536, 131072, 524288])
    p.add_argument("--dtype", nargs="+", choices=["f32", "f64"], default=["f64", "f32"])
    p.add_argument("--devices", type=int, nargs="+", default=[2], help="CPU device counts to share among")
    p.add_argument("--steps", type=int, default=50, help="steps per timed call (10 from 500k particles)")
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--rounds", type=int, default=2, help="alternated rounds of every measurement")
    p.add_argument("--chunk", type=int, default=None, help="particles per chunk of a device's share")
    p.add_argument("--quick", action="store_true", help="4096 particles, f64, 2 devices, 10 steps, one round")
    p.add_argument("--csv", default=str(DEFAULT_CSV))
    p.add_argument("--worker", nargs=3, metavar=("DEVICES", "PARTICLES", "DTYPE"), help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.quick:
        args.particles, args.dtype, args.devices, args.steps, args.rounds, args.repeats = [4096], ["f64"], [2], 10, 1, 2
    return args


def worker(devices: int, particles: int, dtype: str, steps: int, repeats: int, chunk,
           scene: str = "mpm88") -> dict:
    """One measurement in this process: ``devices`` CPU devices (1: JAX's default), printed as JSON."""
    import jax

    if devices > 1:
        jax.config.update("jax_num_cpu_devices", devices)  # before JAX's first computation
    jax.config.update("jax_enable_x64", True)
    import equinox as eqx
    import jax.numpy as jnp

    import jaxmpm as jm

    if scene == "mpm3d":
        from gpu import mpm3d

        sim, state, dt = mpm3d(particles, 32 if particles <= 65536 else 64, dtype)
    else:
        setup = jm.scene("mpm88", n_particles=particles, dtype=dtype)
        sim, state, dt = setup.sim, setup.state, setup.dt
    sim = sim.with_particle_devices(devices)
    if chunk is not None and devices > 1:
        sim = sim.with_chunks(chunk)
    dt = jnp.asarray(dt, state.x.dtype)
    info = jm.backend_info(sim, state)

    @eqx.filter_jit
    def advance(sim, state, dt):
        return jax.lax.scan(lambda s, _: (sim.step(s, dt), None), state, None, length=steps)[0]

    start = time.perf_counter()
    final = jax.block_until_ready(advance(sim, state, dt))
    first = time.perf_counter() - start
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        final = jax.block_until_ready(advance(sim, state, dt))
        best = min(best, time.perf_counter() - start)
    return {"devices": info["particle_devices"], "particles": particles, "dtype": dtype,
            "ms_per_step": 1e3 * best / steps, "compile_s": first - best, "y_cm": float(jnp.mean(final.x[:, 1])),
            "chunk_reason": info["chunk_reason"]}


def measure(devices: int, particles: int, dtype: str, args) -> dict:
    steps = min(args.steps, 10) if particles >= 500_000 else args.steps
    command = [sys.executable, __file__, "--worker", str(devices), str(particles), dtype, "--steps", str(steps),
               "--repeats", str(args.repeats), "--scene", args.scene]
    command += [] if args.chunk is None else ["--chunk", str(args.chunk)]
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    done = subprocess.run(command, env=env, capture_output=True, text=True, timeout=1800)
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(command[2:])} failed:\n{done.stderr[-2000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    args = parse_args(argv)
    if args.worker:
        devices, particles, dtype = int(args.worker[0]), int(args.worker[1]), args.worker[2]
        print(json.dumps(worker(devices, particles, dtype, args.steps, args.repeats, args.chunk, args.scene)))
        return 0
    cases = [(dtype, n) for dtype in args.dtype for n in args.particles]
    results = {}  # (dtype, n, devices) -> [measurements]
    for _ in range(args.rounds):
        for dtype, n in cases:
            for devices in [1, *args.devices]:
                results.setdefault((dtype, n, devices), []).append(measure(devices, n, dtype, args))
    print(f"{args.scene}, {os.cpu_count()} CPUs, load {os.getloadavg()[0]:.2f}; ms a step, best of {args.repeats} "
          f"per process, {args.rounds} alternated round(s)\n")
    header = "| dtype | particles | devices | ms a step: one device | shared | one / shared | compile s: one, shared " \
             "| y_cm difference |"
    print(header)
    print("|---" * 8 + "|")
    rows = []
    for dtype, n in cases:
        one = results[(dtype, n, 1)]
        for devices in args.devices:
            shared = results[(dtype, n, devices)]
            t1, td = [r["ms_per_step"] for r in one], [r["ms_per_step"] for r in shared]
            used = {r["devices"] for r in shared}
            print(f"| {dtype} | {n} | {'/'.join(map(str, sorted(used)))} | {_span(t1)} | {_span(td)} | "
                  f"{min(t1) / min(td):.2f} | {min(r['compile_s'] for r in one):.1f}, "
                  f"{min(r['compile_s'] for r in shared):.1f} | {abs(one[0]['y_cm'] - shared[0]['y_cm']):.1e} |",
                  flush=True)
            rows.append(dict(scene=args.scene, dtype=dtype, particles=n, devices=devices, devices_used=max(used),
                             one_ms=min(t1), shared_ms=min(td), ratio=min(t1) / min(td),
                             one_compile_s=min(r["compile_s"] for r in one),
                             shared_compile_s=min(r["compile_s"] for r in shared),
                             y_cm_difference=abs(one[0]["y_cm"] - shared[0]["y_cm"]), rounds=args.rounds,
                             load=os.getloadavg()[0]))
    print(f"\nwrote {write_csv(args.csv, list(rows[0]), rows)}")
    return 0


def _span(values) -> str:
    low, high = min(values), max(values)
    return f"{low:.3f}" if high - low < 5e-4 else f"{low:.3f}-{high:.3f}"


if __name__ == "__main__":
    sys.exit(main())
