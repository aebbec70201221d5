"""Throughput of the MPM step: particle-steps per second, float32 and float64, per scheme.

Cases: the ``bar`` scene (1D, 32 particles), the ``disks`` scene (2D, h = 0.05, 416 particles) and
``disks-large`` (the same disks at h = 0.00625: 160 x 160 cells, about 25.7k particles).  Each case
runs ``sim.rollout`` under ``eqx.filter_jit`` with one saved frame (diagnostics once, no particle
frames), so the time is the time-stepping itself.

For each case: ``first_call_s`` is the first call (trace + compile + one run, timed with
``jax.block_until_ready``); ``run_s`` is the best of ``--repeats`` further calls (steady state);
``compile_s`` = first_call_s - run_s.  Throughput = particles * steps / run_s.

    python benchmarks/throughput.py                # full run (about 40 s on 2 CPU cores)
    python benchmarks/throughput.py --quick        # under a minute (about 10 s on 2 CPU cores)
    python benchmarks/throughput.py --schemes flip xpic:2 fmpm:2 --dtypes f32 --csv out.csv
"""

from __future__ import annotations

import argparse
import csv
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)  # f64 cases need it; f32 scenes cast themselves to float32

import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402

import jaxmpm as jm  # noqa: E402
from jaxmpm.core.registry import scheme_from_name  # noqa: E402

DEFAULT_CSV = Path(__file__).resolve().parent / "results" / "throughput.csv"

#: case name -> (scene, scene options, steps per timed call, steps in --quick mode)
CASES = {
    "bar": ("bar", {}, 4000, 1000),
    "disks": ("disks", {}, 1000, 250),
    "disks-large": ("disks", {"spacing": 0.00625}, 100, 25),
}

FIELDS = ["case", "scene", "dim", "dtype", "scheme", "particles", "grid_nodes", "steps", "first_call_s",
          "compile_s", "run_s", "median_s", "particle_steps_per_s", "steps_per_s", "repeats", "backend",
          "device", "jax", "cpus"]


@eqx.filter_jit
def advance(sim, state, dt, steps):
    """``steps`` steps as one ``lax.scan`` (one saved frame at the end, no particle frames)."""
    final, history, failure = sim.rollout(state, dt, 1, steps, save_particles=False)
    return final, history.kinetic, failure.step


def timed(fn, *args):
    start = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    return time.perf_counter() - start, out


def measure(case: str, dtype: str, scheme: str, quick: bool, repeats: int) -> dict:
    """Time one (case, dtype, scheme); checks the run stayed stable and finite."""
    scene, options, steps, quick_steps = CASES[case]
    steps = quick_steps if quick else steps
    setup = jm.scene(scene, scheme=scheme_from_name(scheme), dtype=dtype, t_end=0.01, frames=1, **options)
    sim, state = setup.sim, setup.state
    dt = jnp.asarray(setup.dt, state.x.dtype)  # an array, so dt is traced, not a static argument
    first, (final, kinetic, bad_step) = timed(advance, sim, state, dt, steps)
    if int(bad_step) >= 0 or not bool(jnp.all(jnp.isfinite(final.x))):
        raise RuntimeError(f"{case} {dtype} {scheme}: went unstable at step {int(bad_step)}")
    assert final.x.dtype == jnp.dtype({"f32": "float32", "f64": "float64"}[dtype])
    runs = [timed(advance, sim, state, dt, steps)[0] for _ in range(repeats)]
    best = min(runs)
    n = int(state.x.shape[0])
    device = jax.devices()[0]
    return dict(
        case=case, scene=scene, dim=sim.grid.dim, dtype=dtype, scheme=scheme, particles=n,
        grid_nodes=int(sim.grid.node_coordinates().shape[0]), steps=steps, first_call_s=first,
        compile_s=max(0.0, first - best), run_s=best, median_s=statistics.median(runs),
        particle_steps_per_s=n * steps / best, steps_per_s=steps / best, repeats=repeats,
        backend=jax.default_backend(), device=getattr(device, "device_kind", str(device)), jax=jax.__version__,
        cpus=os.cpu_count(),
    )


def print_row(row: dict, header: bool = False) -> None:
    cols = [("case", 12, "s"), ("dtype", 5, "s"), ("scheme", 9, "s"), ("particles", 9, "d"), ("steps", 6, "d"),
            ("compile_s", 9, ".2f"), ("run_s", 8, ".3f"), ("particle_steps_per_s", 20, ".3e"),
            ("steps_per_s", 11, ".1f")]
    if header:
        print("  ".join(f"{name:>{w}}" for name, w, _ in cols))
    print("  ".join(f"{row[name]:>{w}{fmt}}" for name, w, fmt in cols), flush=True)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="fewer steps, FLIP only, 3 repeats (under a minute)")
    parser.add_argument("--cases", nargs="+", default=list(CASES), choices=list(CASES))
    parser.add_argument("--dtypes", nargs="+", default=["f32", "f64"], choices=["f32", "f64"])
    parser.add_argument("--schemes", nargs="+", default=None,
                        help="scheme specs as in `jaxmpm run --scheme` (default: flip xpic:2 fmpm:2; --quick: flip)")
    parser.add_argument("--repeats", type=int, default=None, help="timed calls after warm-up (default 5; --quick 3)")
    parser.add_argument("--csv", default=str(DEFAULT_CSV), help=f"CSV output (default {DEFAULT_CSV})")
    args = parser.parse_args(argv)
    schemes = args.schemes or (["flip"] if args.quick else ["flip", "xpic:2", "fmpm:2"])
    repeats = args.repeats or (3 if args.quick else 5)
    if repeats < 3:
        parser.error("--repeats must be >= 3")

    print(f"jaxmpm {jm.__version__}, jax {jax.__version__}, backend {jax.default_backend()} "
          f"({jax.devices()[0]}), {os.cpu_count()} CPUs, python {platform.python_version()}")
    rows = []
    for case in args.cases:
        for dtype in args.dtypes:
            for scheme in schemes:
                row = measure(case, dtype, scheme, args.quick, repeats)
                print_row(row, header=not rows)
                rows.append(row)
    path = Path(args.csv)
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.parent == DEFAULT_CSV.parent and not (path.parent / ".gitignore").exists():
        (path.parent / ".gitignore").write_text("*\n")  # results are machine-specific: keep them out of git
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=FIELDS)
        writer.writeheader()
        writer.writerows(rows)
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
