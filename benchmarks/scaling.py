"""Weak and strong scaling of one simulation over several devices (jaxmpm.parallel, issue 33).

mpm88's scene (128 x 128 cells, APIC, float32 unless ``--float64``) run by
``jaxmpm.parallel.ShardedSimulation`` on 1, 2, 4 (and 8) devices, against the same model on one
device without the sharded layer, in particle-steps per second, compile time apart:

* **strong**: a fixed particle count (``--particles``) over more devices; efficiency
  t(1) / (d t(d)) against the one-device run;
* **weak**: ``--particles`` per device; efficiency t(1) / t(d).

Each device count runs in a process of its own (the count is fixed when JAX starts). With no
accelerators the devices are forced CPU devices (``XLA_FLAGS=--xla_force_host_platform_device_count``):
they share the machine's cores, so the times measure the sharded layer's overhead and check it runs,
not a speed-up.  On a machine with several GPUs, ``--platform gpu`` uses them (real scaling).

Communication per step and device is read from the compiled program: the bytes of every
collective-permute in the step (halo planes of each P2G and the migration buffers) and their
count; and the particles that changed device over the run.

    python benchmarks/scaling.py                     # 1, 2, 4 devices, 32k strong / 8k per device weak
    python benchmarks/scaling.py --quick             # 1 and 2 devices, 2k particles, 10 steps (CI)
    python benchmarks/scaling.py --devices 1 2 4 8 --steps 100
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

DEFAULT_CSV = Path(__file__).resolve().parent / "results" / "scaling.csv"
FIELDS = ["kind", "devices", "particles", "steps", "dtype", "path", "particle_steps_per_s", "efficiency", "compile_s",
          "run_s", "halo_bytes_per_step", "permutes_per_step", "migrated", "platform"]


def measure(devices: int, particles: int, steps: int, float64: bool, repeat: int) -> list:
    """In this process (``devices`` devices already forced): the one-device run and the sharded run."""
    import jax

    jax.config.update("jax_enable_x64", float64)
    import jax.numpy as jnp
    import numpy as np

    import jaxmpm as jm
    from jaxmpm.parallel import ShardedSimulation

    jm.compilation_cache(False)
    setup = jm.scene("mpm88", n_particles=particles)
    dtype = jnp.float64 if float64 else jnp.float32
    state = jax.tree_util.tree_map(lambda a: a.astype(dtype) if jnp.issubdtype(a.dtype, jnp.floating) else a,
                                   setup.state)
    sim, dt = setup.sim, setup.dt
    rows = []

    def timed(fn, *args):
        start = time.perf_counter()
        jax.block_until_ready(fn(*args))
        first = time.perf_counter() - start
        best = 1e30
        for _ in range(repeat):
            start = time.perf_counter()
            jax.block_until_ready(fn(*args))
            best = min(best, time.perf_counter() - start)
        return first - best, best

    if devices == 1:
        single = jax.jit(lambda s: jax.lax.fori_loop(0, steps, lambda i, s: sim.step(s, jnp.asarray(dt, dtype)), s))
        compile_s, run_s = timed(single, state)
        rows.append({"path": "one device", "compile_s": compile_s, "run_s": run_s, "halo_bytes_per_step": 0,
                     "permutes_per_step": 0, "migrated": 0})
    sharded = ShardedSimulation(sim, devices=jax.devices()[:devices])
    buffers, valid, ids = sharded.distribute(state)
    program = sharded.rollout(steps)
    args = (sim, buffers, valid, ids, jnp.asarray(dt, dtype))
    compile_s, run_s = timed(program, *args)
    hlo = program.lower(*args).compile().as_text()
    halo, count = 0, 0
    for line in hlo.splitlines():
        if "collective-permute(" in line or "collective-permute-start(" in line:
            shape = line.split("=", 1)[1].strip().split(" ")[0]
            dtype_name, dims = shape.strip("(").split("[")[0], shape[shape.index("[") + 1:shape.index("]")]
            size = int(np.prod([int(d) for d in dims.split(",") if d])) if dims else 1
            halo += size * {"f64": 8, "f32": 4, "s64": 8, "s32": 4, "pred": 1}.get(dtype_name, 4)
            count += 1
    sharded.run(state, dt, steps)  # the migration count of a run
    rows.append({"path": f"sharded ({devices})", "compile_s": compile_s, "run_s": run_s, "halo_bytes_per_step": halo,
                 "permutes_per_step": count, "migrated": sharded.stats["migrated"]})
    for row in rows:
        row.update(devices=devices, particles=particles, steps=steps, dtype=jnp.dtype(dtype).name,
                   particle_steps_per_s=particles * steps / row["run_s"], platform=jax.default_backend())
    return rows


def spawn(devices: int, particles: int, args) -> list:
    env = dict(os.environ)
    if args.platform == "cpu":
        env["XLA_FLAGS"] = (env.get("XLA_FLAGS", "") + f" --xla_force_host_platform_device_count={devices}").strip()
        env["JAX_PLATFORMS"] = "cpu"
    command = [sys.executable, __file__, "--child", str(devices), str(particles), "--steps", str(args.steps),
               "--repeat", str(args.repeat)] + (["--float64"] if args.float64 else [])
    done = subprocess.run(command, env=env, capture_output=True, text=True, timeout=3600)
    if done.returncode != 0:
        raise SystemExit(f"scaling.py: the {devices}-device run failed:\n{done.stderr[-3000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--devices", type=int, nargs="+", default=[1, 2, 4])
    parser.add_argument("--particles", type=int, default=32768, help="strong scaling's total")
    parser.add_argument("--per-device", type=int, default=8192, help="weak scaling's particles per device")
    parser.add_argument("--steps", type=int, default=50)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--float64", action="store_true")
    parser.add_argument("--platform", choices=("cpu", "gpu"), default="cpu")
    parser.add_argument("--quick", action="store_true", help="1 and 2 devices, 2048 particles, 10 steps")
    parser.add_argument("--csv", default=str(DEFAULT_CSV))
    parser.add_argument("--child", nargs=2, type=int, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        print(json.dumps(measure(args.child[0], args.child[1], args.steps, args.float64, args.repeat)))
        return 0
    if args.quick:
        args.devices, args.particles, args.per_device, args.steps, args.repeat = [1, 2], 2048, 1024, 10, 1

    rows = []
    base = {}
    for kind, count in (("strong", lambda d: args.particles), ("weak", lambda d: args.per_device * d)):
        for d in args.devices:
            for row in spawn(d, count(d), args):
                if row["path"] == "one device":
                    base[kind] = row["run_s"]
                    row["efficiency"] = 1.0
                else:
                    t1 = base.get(kind)
                    ideal = d * row["run_s"] if kind == "strong" else row["run_s"]  # strong: t1 / (d t_d)
                    row["efficiency"] = t1 / ideal if t1 else ""
                row["kind"] = kind
                rows.append(row)
    header = f"{'kind':6} {'devices':>7} {'particles':>9} {'path':>13} {'p-steps/s':>10} {'eff':>5} {'compile s':>9} " \
             f"{'halo B/step':>11} {'permutes':>8} {'migrated':>8}"
    print(header)
    for r in rows:
        eff = f"{r['efficiency']:.2f}" if r["efficiency"] != "" else ""
        print(f"{r['kind']:6} {r['devices']:>7} {r['particles']:>9} {r['path']:>13} {r['particle_steps_per_s']:>10.3g} "
              f"{eff:>5} {r['compile_s']:>9.2f} {r['halo_bytes_per_step']:>11} {r['permutes_per_step']:>8} "
              f"{r['migrated']:>8}")
    path = write_csv(Path(args.csv), FIELDS, rows)
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
