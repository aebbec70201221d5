"""Where a CPU step's time goes, on one core and on all of them: XLA's kernels of a compiled mpm88 step, each
with its source line, and how much faster it runs with more threads.

    python benchmarks/cpu_profile.py                              # mpm88 131k float64: one core against all
    python benchmarks/cpu_profile.py --particles 8192 --dtype f32 --steps 50
    python benchmarks/cpu_profile.py --top 60 --markdown profile.md
    python benchmarks/cpu_profile.py --program gradient --particles 8192   # a rollout gradient's kernels

Each setting runs in its own process (XLA sizes its thread pool, and the compiler its parallel partitions, from
the CPUs a process may use): first pinned to one CPU through its affinity mask (Linux), then on all of them.
Each compiles ``--steps`` steps of ``sim.step`` in one ``fori_loop`` (mpm88 as ``jm.scene`` builds it, the
backend table's chunks included), runs it once, then traces three calls with ``jax.profiler`` and sums the
kernels' durations by name.  A kernel is one XLA fusion (or a scatter, a copy, a dot); its row gives:

* its time per step on one core and on all, and the ratio (1.9 on two cores: it parallelises; about 1: it runs
  on one thread, or its parallel tasks cost what they save);
* how many times it runs per step and its time per call on one core;
* ``parts``: the parallel partitions XLA:CPU's compiler gave it in the all-CPU program (``-``: none, it runs
  on one thread: scatters, in-place dynamic-update-slices, batched dots);
* the Python line that produced it, read from the compiled program's stack frames (the innermost jaxmpm
  frames).

``--program gradient`` profiles ``gradient_cost.py``'s gradient instead (the final sum(v^2) + sum(x^2) with
respect to the initial velocities, through ``sim.run``'s ``--steps`` steps, ``checkpoint="auto"``), compiled as
``jm.calibrate`` compiles it: its forward pass, the steps recomputed and their transposes, per step.

The summary adds the wall time per step of each setting (from the loop's own timing, outside the profiler), the
kernels launched per step, and the totals of the partitioned and the unpartitioned kernels.  Nested executors
(loops, conditionals) are left out of the sums: their time is their kernels'.
"""

from __future__ import annotations

import argparse
import collections
import glob
import gzip
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

CONTROL = ("while", "cond", "ThunkExecutor", "$", "PjitFunction", "CommonPjRt", "call")


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--particles", type=int, default=131072)
    p.add_argument("--dtype", choices=("f32", "f64"), default="f64")
    p.add_argument("--steps", type=int, default=20, help="steps per compiled call (default 20)")
    p.add_argument("--top", type=int, default=40, help="kernels listed, the costliest on one core first")
    p.add_argument("--markdown", type=Path, default=None, help="also write the table to this file")
    p.add_argument("--program", choices=("step", "gradient"), default="step",
                   help="step: --steps steps of sim.step; gradient: the gradient of gradient_cost.py's loss (the "
                        "final sum(v^2) + sum(x^2) with respect to the initial velocities) through sim.run's "
                        "--steps steps, checkpoint 'auto' (default step)")
    p.add_argument("--worker", choices=("one", "all"), default=None, help=argparse.SUPPRESS)
    p.add_argument("--out", type=Path, default=None, help=argparse.SUPPRESS)
    return p.parse_args(argv)


# ------------------------------------------------------------------------------ the compiled program's frames
def _section(lines: list, name: str) -> list:
    """The numbered rows of one section (FileNames, FunctionNames, FileLocations, StackFrames) of an HLO text."""
    try:
        start = lines.index(name)
    except ValueError:
        return []
    rows = []
    for line in lines[start + 1:]:
        if not line.strip() or not line[0].isdigit():
            break
        rows.append(line)
    return rows


def trace_events(folder) -> list | None:
    """Every event of the trace ``jax.profiler.trace(folder)`` wrote (None: it wrote none)."""
    found = glob.glob(os.path.join(folder, "**", "*.trace.json.gz"), recursive=True)
    if not found:
        return None
    trace = json.load(gzip.open(found[0]))
    return trace["traceEvents"] if isinstance(trace, dict) else trace


def source_lines(hlo_text: str) -> dict:
    """{instruction name: "file:line (function) < caller ..."}: each instruction's stack frame in a compiled
    module's text (``compiled.as_text()``), jaxmpm's own frames only, innermost first."""
    lines = hlo_text.split("\n")

    def numbered(name):
        return {int(r.split()[0]): r.split(None, 1)[1].strip().strip('"') for r in _section(lines, name)}

    files, functions = numbered("FileNames"), numbered("FunctionNames")
    locations, frames = {}, {}
    for row in _section(lines, "FileLocations"):
        f = dict(re.findall(r"(\w+)=(\d+)", row))
        locations[int(row.split()[0])] = (int(f["file_name_id"]), int(f["function_name_id"]), int(f["line"]))
    for row in _section(lines, "StackFrames"):
        f = dict(re.findall(r"(\w+)=(\d+)", row))
        frames[int(row.split()[0])] = (int(f["file_location_id"]), int(f["parent_frame_id"]))

    def chain(frame: int, depth: int = 3) -> str:
        out, seen = [], set()
        while frame in frames and frame not in seen and len(out) < depth:
            seen.add(frame)
            location, parent = frames[frame]
            file_id, function_id, line = locations[location]
            path = files.get(file_id, "?")
            if "jaxmpm/" in path and "site-packages/jax/" not in path:
                out.append(f"{path.split('jaxmpm/', 1)[1]}:{line} ({functions.get(function_id, '?')})")
            frame = parent - 1  # parent ids count from 1
        return " < ".join(out)

    return {m.group(1): chain(int(m.group(2)))
            for m in re.finditer(r"%([\w.\-]+) = [^\n]*?stack_frame_id=(\d+)", hlo_text)}


def partitions(hlo_text: str) -> dict:
    """{kernel name: its parallel partitions (1: none)} from a compiled module's ``outer_dimension_partitions``."""
    out = {}
    for m in re.finditer(r"^\s+(?:ROOT )?%([\w.\-]+) = [^\n]*", hlo_text, flags=re.M):
        parts = re.search(r'outer_dimension_partitions":\[([^\]]*)\]', m.group(0))
        count = 1
        if parts:
            for p in re.findall(r'"?(\d+)"?', parts.group(1)):
                count *= int(p)
        out[m.group(1)] = count
    return out


# ------------------------------------------------------------------------------------------------- a worker
def worker(args) -> None:
    """Compile, time and trace the step in this process; write {kernels, wall, hlo facts} to ``args.out``."""
    if args.worker == "one":  # before JAX starts: its thread pool and its compiler count the CPUs of the mask
        os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})
    import jax

    jax.config.update("jax_enable_x64", True)
    import jaxmpm as jm

    setup = jm.scene("mpm88", n_particles=args.particles, dtype=args.dtype)
    sim, state, dt = setup.sim, setup.state, setup.dt
    steps = args.steps
    if args.program == "gradient":  # gradient_cost.py's loss: the per-step figures are the gradient's per step
        from gradient_cost import final_state_loss  # this script's folder, first on the worker's path

        grad = jax.grad(final_state_loss(sim, state, dt, steps))
        call = jax.jit(lambda s: grad(s.v), compiler_options=jm.compiler_options())
    else:
        call = jax.jit(lambda s: jax.lax.fori_loop(0, steps, lambda i, s: sim.step(s, dt), s))
    compiled = call.lower(state).compile()
    jax.block_until_ready(compiled(state))
    best = float("inf")
    for _ in range(3):
        tic = time.perf_counter()
        jax.block_until_ready(compiled(state))
        best = min(best, time.perf_counter() - tic)
    folder = tempfile.mkdtemp(prefix="jaxmpm-cpu-trace-")
    calls = 3
    with jax.profiler.trace(folder):
        for _ in range(calls):
            jax.block_until_ready(compiled(state))
    events = trace_events(folder)
    shutil.rmtree(folder, ignore_errors=True)
    if events is None:
        raise RuntimeError("jax.profiler wrote no trace")
    total, count = collections.Counter(), collections.Counter()
    for e in events:
        if e.get("ph") == "X" and "dur" in e and not any(c in e["name"] for c in CONTROL):
            total[e["name"]] += e["dur"]
            count[e["name"]] += 1
    per = calls * steps
    text = compiled.as_text()
    result = {"cpus": len(os.sched_getaffinity(0)), "wall_ms": 1e3 * best / steps,
              "kernels": {k: [total[k] / per, count[k] / per] for k in total},
              "source": source_lines(text) if args.worker == "all" else {},
              "parts": partitions(text) if args.worker == "all" else {}}
    args.out.write_text(json.dumps(result))


def run_worker(setting: str, args, folder: Path) -> dict:
    out = folder / f"{setting}.json"
    cmd = [sys.executable, __file__, "--worker", setting, "--out", str(out), "--particles", str(args.particles),
           "--dtype", args.dtype, "--steps", str(args.steps), "--program", args.program]
    env = {**os.environ, "JAX_PLATFORMS": "cpu", "JAXMPM_CACHE": "0"}  # each setting compiles its own program
    subprocess.run(cmd, check=True, env=env)
    return json.loads(out.read_text())


def table(one: dict, every: dict, top: int) -> tuple:
    """(markdown rows, summary lines) from the two workers' results."""
    cpus = every["cpus"]
    rows = [f"| kernel | 1 core µs/step | {cpus} cores µs/step | ratio | calls/step | µs/call (1 core) | parts "
            "| source |", "|---|---|---|---|---|---|---|---|"]
    names = sorted(one["kernels"], key=lambda k: -one["kernels"][k][0])
    for name in names[:top]:
        t1, calls = one["kernels"][name]
        t2 = every["kernels"].get(name, [float("nan")])[0]
        parts = every["parts"].get(name, 1)
        rows.append(f"| {name} | {t1:.0f} | {t2:.0f} | {t1 / t2 if t2 else float('nan'):.2f} | {calls:g} | "
                    f"{t1 / calls if calls else 0:.1f} | {parts if parts > 1 else '-'} | "
                    f"{every['source'].get(name, '')} |")
    split = {True: [0.0, 0.0, 0.0], False: [0.0, 0.0, 0.0]}
    for name, (t1, calls) in one["kernels"].items():
        key = every["parts"].get(name, 1) > 1
        split[key][0] += t1
        split[key][1] += every["kernels"].get(name, [0.0])[0]
        split[key][2] += calls
    summary = [
        f"wall per step: 1 core {one['wall_ms']:.2f} ms, {cpus} cores {every['wall_ms']:.2f} ms "
        f"({one['wall_ms'] / every['wall_ms']:.2f}x)",
        f"kernels per step: {sum(c for _, c in one['kernels'].values()):.0f}",
        f"partitioned kernels: {split[True][2]:.0f} calls/step, {split[True][0] / 1e3:.2f} ms on 1 core -> "
        f"{split[True][1] / 1e3:.2f} ms on {cpus} ({split[True][0] / max(split[True][1], 1e-9):.2f}x)",
        f"kernels on one thread: {split[False][2]:.0f} calls/step, {split[False][0] / 1e3:.2f} ms on 1 core -> "
        f"{split[False][1] / 1e3:.2f} ms on {cpus}",
    ]
    return rows, summary


def main(argv=None) -> int:
    args = parse_args(argv)
    if args.worker:
        worker(args)
        return 0
    if not hasattr(os, "sched_getaffinity"):
        print("cpu_profile.py pins a process to one CPU through its affinity mask: Linux only", file=sys.stderr)
        return 2
    folder = Path(tempfile.mkdtemp(prefix="jaxmpm-cpu-profile-"))
    try:
        one = run_worker("one", args, folder)
        every = run_worker("all", args, folder)
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    rows, summary = table(one, every, args.top)
    program = "" if args.program == "step" else f" {args.program}"
    head = f"mpm88{program}, {args.particles} particles, {args.dtype}, {args.steps} steps per call"
    print(head)
    print("\n".join(summary))
    print("\n".join(rows))
    if args.markdown:
        listed = "\n".join(f"- {s}" for s in summary)
        args.markdown.write_text(f"# {head}\n\n{listed}\n\n" + "\n".join(rows) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
