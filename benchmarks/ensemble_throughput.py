"""Batch throughput of ``jm.ensemble`` under each strategy, against a single run of the same scene.

Scenes: ``bar`` (1D, 32 particles, XPIC(2), float64, 2000 steps), ``disks`` (2D, uGIMP, 416 particles,
XPIC(2), float64, 200 steps) and ``mpm88`` (Taichi's fluid, APIC, 8192 particles, float32, 100 steps).
For each batch size B the members differ in one parameter (beta; E for mpm88) and run as one
``jm.ensemble`` call per strategy: ``vmap`` (all members batched), ``sequential`` (one member after
another inside the program, ``lax.map``) and, with ``--chunks``, ``vmap`` in chunks of k members.  The
baseline, measured in the same process, is one compiled single rollout (``eqx.filter_jit`` of
``sim.rollout`` with the outputs of one member: final state, history, failure step; no Python loop);
one ``sim.run`` call is timed against it too (its row's ratio: the run driver's own cost), and
``--loop`` adds a loop of B ``sim.run`` calls (what a script without ``jm.ensemble`` does).

Reported per row: ``compile_s`` (first call minus steady state), ``run_s`` (best of ``--repeat`` calls
after the first), ``particle_steps_per_s`` = B x particles x steps / run_s, ``vs_single`` = that
throughput over the single run's (``vs_single_cpu``: the same ratio from process CPU times, steadier when other
processes load the machine), and ``auto`` = "*" on the row ``strategy="auto"`` resolves to on this
backend (jaxmpm.run.ensemble.plan).  One saved frame per run, no particle frames.  The machine's load
average is printed before and after each scene and stored per row.

    python benchmarks/ensemble_throughput.py              # CPU: bar, disks (B = 1-64), mpm88 (B = 1, 4, 16)
    python benchmarks/ensemble_throughput.py --quick      # bar and mpm88, fewer steps and batches
    python benchmarks/ensemble_throughput.py --gpu        # B up to 256 (the default on a GPU backend)
    python benchmarks/ensemble_throughput.py --scenes bar disks --chunks 2 4 8 16   # chunked vmap too

In GPU mode the batches are 1, 16, 64, 256 and ``sequential`` runs up to B = 16 only (its throughput per
member is that of a single run; at 256 members it would take minutes).
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
from jaxmpm.run.ensemble import plan  # noqa: E402

DEFAULT_CSV = Path(__file__).resolve().parent / "results" / "ensemble_throughput.csv"
#: scene -> (scene options, varied parameter and its range, steps, steps in --quick mode, CPU batches)
SCENES = {
    "bar": (dict(scheme="xpic2"), ("beta", 0.0, 0.9), 2000, 500, (1, 4, 16, 64)),
    "disks": (dict(scheme="xpic2"), ("beta", 0.0, 0.9), 200, 50, (1, 4, 16, 64)),
    "mpm88": (dict(dtype="f32"), ("E", 300.0, 500.0), 100, 50, (1, 4, 16)),
}
GPU_BATCHES = (1, 16, 64, 256)
GPU_SEQUENTIAL_UP_TO = 16
FIELDS = ["scene", "strategy", "auto", "batch", "particles", "steps", "dtype", "compile_s", "run_s",
          "particle_steps_per_s", "vs_single", "cpu_s", "vs_single_cpu", "load_1min", "backend", "device", "jax",
          "cpus"]


def timed(fn, repeats=3):
    """(compile_s, run_s, cpu_s): first call minus the best of ``repeats`` further calls, that best
    (wall clock), and the best process CPU time of those calls (less sensitive to other processes)."""
    start = time.perf_counter()
    jax.block_until_ready(fn())
    first = time.perf_counter() - start
    best = cpu = np.inf
    for _ in range(repeats):
        start, start_cpu = time.perf_counter(), time.process_time()
        jax.block_until_ready(fn())
        best = min(best, time.perf_counter() - start)
        cpu = min(cpu, time.process_time() - start_cpu)
    return max(0.0, first - best), best, cpu


@eqx.filter_jit
def single_rollout(sim, state, dt, steps):
    """One member's work: the final state, the history and the failure record (without them XLA
    drops the per-step instability check, a third of a small scene's step)."""
    final, history, failure = sim.rollout(state, dt, 1, steps, save_particles=False, checkpoint=False)
    return final, history, failure.step


def scene_setup(scene: str):
    options = dict(SCENES[scene][0])
    if options.get("scheme") == "xpic2":
        options["scheme"] = jm.XPIC(order=2)
    return jm.scene(scene, **options)


def measure(scene: str, steps: int, batches, gpu: bool, chunks=(), loop=False, repeats=3) -> list[dict]:
    setup = scene_setup(scene)
    name, low, high = SCENES[scene][1]
    n = int(setup.state.x.shape[0])
    dtype = setup.state.x.dtype
    dt = jnp.asarray(setup.dt, dtype)
    device = jax.devices()[0]
    common = dict(scene=scene, particles=n, steps=steps, dtype=str(dtype), backend=jax.default_backend(),
                  device=device.device_kind, jax=jax.__version__, cpus=os.cpu_count())
    rows = []

    def row(strategy, batch, compile_s, run_s, cpu_s, auto=""):
        rate = batch * n * steps / run_s
        rows.append(dict(common, strategy=strategy, auto=auto, batch=batch, compile_s=compile_s, run_s=run_s,
                         particle_steps_per_s=rate, vs_single=rate / base[0], cpu_s=cpu_s,
                         vs_single_cpu=batch * base[1] / cpu_s, load_1min=os.getloadavg()[0]))
        print_rows(rows[-1:])

    compile_s, run_s, cpu_s = timed(lambda: single_rollout(setup.sim, setup.state, dt, steps), repeats)
    base = (n * steps / run_s, cpu_s)
    row("single rollout", 1, compile_s, run_s, cpu_s)
    row("sim.run", 1, *timed(lambda: setup.sim.run(setup.state, dt, steps, steps, save_particles=False, progress=False),
                             repeats))
    for batch in batches:
        values = jnp.linspace(low, high, batch).astype(dtype)
        auto = plan("auto", None, batch, n, device.platform)
        configs = [("vmap", None)] + [("vmap", k) for k in chunks if k < batch]
        if not gpu or batch <= GPU_SEQUENTIAL_UP_TO:
            configs.append(("sequential", None))
        if auto not in configs:
            configs.append(auto)
        for strategy, chunk in configs:
            def batched(values=values, strategy=strategy, chunk=chunk):
                return jm.ensemble(setup.sim, setup.state, dt, steps, steps, params={name: values}, strategy=strategy,
                                   chunk=chunk, progress=False)

            label = strategy if chunk is None else f"vmap, chunk {chunk}"
            row(label, batch, *timed(batched, repeats), auto="*" if (strategy, chunk) == auto else "")
        if loop:
            def looped(values=values):
                return [jm.set_params(setup.sim, **{name: v}).run(setup.state, dt, steps, steps, save_particles=False,
                                                                 progress=False) for v in values]

            row("loop of sim.run", batch, *timed(looped, repeats))
    return rows


def print_rows(rows) -> None:
    for r in rows:
        print(f"{r['scene']:>6} {r['strategy']:>16} {r['auto']:>4} {r['batch']:4d} {r['particles']:9d} {r['steps']:6d} "
              f"{r['compile_s']:9.2f} {r['run_s']:8.4f} {r['particle_steps_per_s']:16.3e} {r['vs_single']:9.2f} "
              f"{r['vs_single_cpu']:7.2f} {r['load_1min']:5.2f}", flush=True)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="bar and mpm88, fewer steps, batches up to 16")
    parser.add_argument("--gpu", action="store_true", help="batches up to 256 (the default on a non-CPU backend)")
    parser.add_argument("--scenes", nargs="+", choices=list(SCENES), default=None)
    parser.add_argument("--batches", nargs="+", type=int, default=None, help="override the batch sizes")
    parser.add_argument("--chunks", nargs="+", type=int, default=(), help="also vmap in chunks of k members")
    parser.add_argument("--loop", action="store_true", help="also a Python loop of sim.run calls")
    parser.add_argument("--steps", type=int, default=None, help="override the steps of every scene")
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--csv", default=str(DEFAULT_CSV))
    args = parser.parse_args(argv)
    jm.compilation_cache(False)  # compile_s: XLA compiling, not reading a program from an earlier run's disk cache
    gpu = args.gpu or jax.default_backend() != "cpu"
    scenes = args.scenes or (["bar", "mpm88"] if args.quick else list(SCENES))
    print(f"jaxmpm {jm.__version__}, jax {jax.__version__}, backend {jax.default_backend()} "
          f"({jax.devices()[0].device_kind}), {os.cpu_count()} CPUs, python {platform.python_version()}; "
          f"load {os.getloadavg()}")
    print(f"{'scene':>6} {'strategy':>16} {'auto':>4} {'B':>4} {'particles':>9} {'steps':>6} {'compile_s':>9} "
          f"{'run_s':>8} {'particle-steps/s':>16} {'vs single':>9} {'(cpu)':>7} {'load':>5}")
    rows = []
    for scene in scenes:
        steps = args.steps or SCENES[scene][3 if args.quick else 2]
        batches = args.batches or (GPU_BATCHES if gpu else SCENES[scene][4])
        if args.quick and not args.batches:
            batches = tuple(b for b in batches if b <= 16)
        rows += measure(scene, steps, batches, gpu, tuple(args.chunks), args.loop, args.repeat)
        print(f"load after {scene}: {os.getloadavg()}", flush=True)
    print(f"wrote {write_csv(args.csv, FIELDS, rows)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
