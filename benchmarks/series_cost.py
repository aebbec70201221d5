"""Cost of the mass-matrix series: one S+S application, and XPIC(m) / FMPM(k) steps, relative to FLIP.

XPIC(m) and FMPM(k) add m - 1 (k - 1) applications of S+S = one gather and one mass-weighted scatter
(000 eqs. 3.23-3.25, 003 eq. 1.23) to a step, on a transfer the step has already built.  The issue's
aim: each extra order costs at most half a FLIP step.  Measured here, float64:

* ``splus_s``: one S+S application (a jitted loop of repeated applications on the first step's
  transfer, divided by the count), relative to one FLIP step;
  (in the table as "what = S+S", "us per step" meaning per application);
* ``step``: a jitted ``lax.fori_loop`` of ``sim.step`` for FLIP and XPIC(m), FMPM(k),
  m, k = 1, 2, 4, 8 (``--quick``: 1, 2, 4), relative to FLIP, and the marginal cost of one order,
  (t(m) - t(1)) / (m - 1) / t_FLIP, to compare with the 0.5 aim.

Cases: ``bar`` (1D) with 1024 cells x 2 particles per cell (2048 particles, v0 = 0.002 so the free end
stays in its cell), and ``disks`` (2D) at h = 0.008 (about 15.7k particles).  Every timed run is
checked for instability (NaN, J <= 0, particles off the grid) at its end.  Each timing is the best
of ``--repeats`` calls after a warm-up call, with ``jax.block_until_ready``; the jobs of a case are
timed in interleaved rounds, so a burst of load from other processes hits them alike.  Compile time
(first call minus best) is reported separately.
Besides wall time it records the process CPU time of each call (``time.process_time``, all threads),
which a busy machine disturbs less than wall time.

    python benchmarks/series_cost.py              # full run
    python benchmarks/series_cost.py --quick      # fewer steps/orders/repeats: a smoke test
    python benchmarks/series_cost.py --csv out.csv
    python benchmarks/series_cost.py --backend gpu  # the GPU policy's program (boundaries as identities), on the CPU

Writes ``benchmarks/results/series_cost.csv`` (the folder is created at run time).
"""

from __future__ import annotations

import argparse
import csv
import os
import platform
import statistics
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402

import jaxmpm as jm  # noqa: E402
from jaxmpm.run.driver import CAUSES  # noqa: E402
from jaxmpm.transfer.backend import POLICIES  # noqa: E402
from jaxmpm.transfer.operators import Transfer  # noqa: E402

DEFAULT_CSV = Path(__file__).resolve().parent / "results" / "series_cost.csv"
AIM = 0.5  # the budget: one extra order <= half a FLIP step

#: case -> (scene, scene options, steps per timed call, S+S applications per timed call)
CASES = {
    # v0 = 0.002: the free end moves by v0/omega = 0.0032 < h/4 = 0.0061, so no particle crosses into the
    # empty cell past the end (at the scene's v0 = 0.1 it moves 0.16 > one cell: particles leave the grid)
    "bar-1024": ("bar", dict(cells=1024, ppc=2, v0=0.002), 2000, 2000),
    "disks-h0.008": ("disks", dict(spacing=0.008), 40, 100),
}

FIELDS = ["case", "dim", "particles", "grid_nodes", "what", "order", "calls", "first_call_s", "compile_s",
          "best_s", "median_s", "per_call_us", "ratio_to_flip_step", "extra_order_ratio", "meets_aim",
          "cpu_per_call_us", "cpu_ratio_to_flip_step", "cpu_extra_order_ratio",
          "repeats", "policy", "backend", "device", "jax", "cpus", "load_avg"]


@eqx.filter_jit
def advance(sim, state, dt, steps):
    """``steps`` plain time steps (no diagnostics, no instability checks) as one fori_loop."""
    return jax.lax.fori_loop(0, steps, lambda _, s: sim.step(s, dt), state)


@eqx.filter_jit
def apply_splus_s(transfer, u, count):
    """``count`` applications of S+S (000 eq. 3.19) to the nodal field ``u``."""
    return jax.lax.fori_loop(0, count, lambda _, w: transfer.s_plus_s(w), u)


def step_schemes(orders):
    out = [("FLIP", 1, jm.FLIP())]
    out += [(f"XPIC({m})", m, jm.XPIC(order=m)) for m in orders]
    out += [(f"FMPM({k})", k, jm.FMPM(order=k)) for k in orders]
    return out


def environment() -> dict:
    device = jax.devices()[0]
    return dict(backend=jax.default_backend(), device=getattr(device, "device_kind", str(device)),
                jax=jax.__version__, cpus=os.cpu_count(),
                load_avg=f"{os.getloadavg()[0]:.2f}" if hasattr(os, "getloadavg") else "")


def measure_case(case: str, orders, quick: bool, repeats: int, policy: str = "auto") -> list[dict]:
    """Compile and warm up every job, then time them in ``repeats`` interleaved rounds (so a burst of
    load from other processes hits all jobs alike) and keep each job's best round.  ``policy``: the
    fusion policy the steps are traced under (``Simulation.with_backend``: "auto", "cpu", "gpu")."""
    scene, options, steps, applications = CASES[case]
    if quick:
        steps, applications = max(10, steps // 4), max(10, applications // 4)
    setup = jm.scene(scene, scheme=jm.FLIP(), dtype="f64", t_end=1e-6, frames=1, **options)
    setup.sim = setup.sim.with_backend(policy)
    state = setup.state
    dt = jnp.asarray(setup.dt, state.x.dtype)
    n_particles, grid = int(state.x.shape[0]), setup.sim.grid
    base = dict(case=case, dim=grid.dim, particles=n_particles, grid_nodes=grid.num_nodes, repeats=repeats,
                policy=policy)

    jobs = []  # (label, order, calls, function, arguments)
    for label, order, scheme in step_schemes(orders):
        sim = eqx.tree_at(lambda s: s.scheme, setup.sim, scheme)
        jobs.append((label, order, steps, advance, (sim, state, dt, steps)))
    transfer = Transfer.build(setup.sim.shape.stencil(grid, state.x), state.mass, grid.num_nodes)
    jobs.append(("S+S", 0, applications, apply_splus_s, (transfer, transfer.s_plus(state.v), applications)))

    first = {}
    for label, _, calls, fn, args in jobs:  # compile + one run
        start = time.perf_counter()
        out = jax.block_until_ready(fn(*args))
        first[label] = time.perf_counter() - start
        if fn is advance:
            code, particle = args[0].instability(out)
            if int(code) != 0:
                raise RuntimeError(f"{case} {label}: unstable after {calls} steps: {CAUSES[int(code)]} "
                                   f"(particle {int(particle)})")
    runs = {label: [] for label, *_ in jobs}
    cpu = {label: [] for label, *_ in jobs}
    for _ in range(repeats):
        for label, _, _, fn, args in jobs:
            start, start_cpu = time.perf_counter(), time.process_time()
            jax.block_until_ready(fn(*args))
            runs[label].append(time.perf_counter() - start)
            cpu[label].append(time.process_time() - start_cpu)

    flip_step = min(runs["FLIP"]) / steps
    flip_cpu = min(cpu["FLIP"]) / steps
    rows = []
    for label, order, calls, _, _ in jobs:
        best, median = min(runs[label]), statistics.median(runs[label])
        per_call = best / calls
        per_cpu = min(cpu[label]) / calls
        rows.append(dict(base, what=label, order=order, calls=calls, first_call_s=first[label],
                         compile_s=max(0.0, first[label] - best), best_s=best, median_s=median,
                         per_call_us=1e6 * per_call, ratio_to_flip_step=per_call / flip_step,
                         cpu_per_call_us=1e6 * per_cpu, cpu_ratio_to_flip_step=per_cpu / flip_cpu))
        unit = "us/app " if label == "S+S" else "us/step"
        print(f"  {case:13s} {label:9s} {1e6 * per_call:10.1f} {unit}  x{per_call / flip_step:5.2f} FLIP  "
              f"(median x{median / calls / flip_step:5.2f}; cpu time x{per_cpu / flip_cpu:5.2f}; "
              f"jit {rows[-1]['compile_s']:.2f} s)", flush=True)

    # marginal cost of one order, against the scheme's own order 1
    for family in ("XPIC", "FMPM"):
        one = next(r for r in rows if r["what"] == f"{family}(1)")
        for r in rows:
            if r["what"].startswith(family) and r["order"] > 1:
                extra = (r["per_call_us"] - one["per_call_us"]) / (r["order"] - 1) / (1e6 * flip_step)
                r["extra_order_ratio"] = extra
                r["meets_aim"] = extra <= AIM
                r["cpu_extra_order_ratio"] = (r["cpu_per_call_us"] - one["cpu_per_call_us"]) / (r["order"] - 1) / (
                    1e6 * flip_cpu)
    return rows


def table(rows) -> str:
    lines = ["| case | particles | what | us per step (wall, best) | x FLIP step | extra order / FLIP step "
             "| aim <= 0.5 | CPU time x FLIP | CPU extra order / FLIP | jit (s) |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        extra, cpu_extra = r.get("extra_order_ratio"), r.get("cpu_extra_order_ratio")
        lines.append(
            f"| {r['case']} | {r['particles']} | {r['what']} | {r['per_call_us']:.1f} "
            f"| {r['ratio_to_flip_step']:.2f} | {'—' if extra is None else f'{extra:.2f}'} "
            f"| {'—' if extra is None else ('yes' if extra <= AIM else 'no')} "
            f"| {r['cpu_ratio_to_flip_step']:.2f} | {'—' if cpu_extra is None else f'{cpu_extra:.2f}'} "
            f"| {r['compile_s']:.2f} |"
        )
    return "\n".join(lines)


def verdict(rows, case) -> list[str]:
    """Per family: the first extra order (m = 1 -> 2) and the least-squares slope per order over m >= 2,
    both in FLIP steps (wall and CPU time), against the aim of <= 0.5 FLIP step per order."""
    out = []
    splus = next(r for r in rows if r["case"] == case and r["what"] == "S+S")
    out.append(f"{case}: one S+S application = {splus['ratio_to_flip_step']:.2f} FLIP steps "
               f"(CPU time {splus['cpu_ratio_to_flip_step']:.2f})")
    for family in ("XPIC", "FMPM"):
        fam = sorted((r for r in rows if r["case"] == case and r["what"].startswith(family)), key=lambda r: r["order"])
        for key, name in (("ratio_to_flip_step", "wall"), ("cpu_ratio_to_flip_step", "CPU")):
            t = {r["order"]: r[key] for r in fam}
            first = t[2] - t[1]
            ms = [m for m in t if m >= 2]
            mean_m = sum(ms) / len(ms)
            mean_t = sum(t[m] for m in ms) / len(ms)
            slope = sum((m - mean_m) * (t[m] - mean_t) for m in ms) / sum((m - mean_m) ** 2 for m in ms)
            if max(first, slope) <= AIM:
                ok = "holds"
            else:
                ok = "holds per further order, not for the first" if slope <= AIM else "does NOT hold"
            out.append(f"  {family} ({name}): first extra order {first:.2f}, each further order {slope:.2f} "
                       f"FLIP steps (m = {', '.join(map(str, ms))}) -> aim <= {AIM}: {ok}")
    return out


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="orders 1, 2, 4; a quarter of the steps; 2 repeats")
    parser.add_argument("--repeats", type=int, default=None, help="timed rounds after the warm-up (default 7)")
    parser.add_argument("--cases", nargs="+", choices=list(CASES), default=list(CASES))
    parser.add_argument("--backend", choices=POLICIES, default="auto",
                        help="the fusion policy the steps are traced under (Simulation(backend=...)): 'gpu' on a CPU "
                             "traces the program a GPU runs (stage boundaries as identities); default auto")
    parser.add_argument("--csv", type=Path, default=DEFAULT_CSV)
    args = parser.parse_args(argv)
    orders = (1, 2, 4) if args.quick else (1, 2, 4, 8)
    repeats = args.repeats or (2 if args.quick else 7)
    env = environment()
    print(f"backend {env['backend']} ({env['device']}), fusion policy {args.backend}, jax {env['jax']}, "
          f"{env['cpus']} cpus, {platform.machine()}, load average {env['load_avg']}")
    rows = []
    for case in args.cases:
        rows += measure_case(case, orders, args.quick, repeats, args.backend)
    env["load_avg"] = f"{env['load_avg']}->{os.getloadavg()[0]:.2f}" if hasattr(os, "getloadavg") else ""
    args.csv.parent.mkdir(parents=True, exist_ok=True)
    with args.csv.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=FIELDS)
        w.writeheader()
        for r in rows:
            w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in dict(r, **env).items()
                        if k in FIELDS})
    print()
    print(table(rows))
    print()
    for case in args.cases:
        for line in verdict(rows, case):
            print(line)
    print(f"\nwrote {args.csv}")


if __name__ == "__main__":
    main()
