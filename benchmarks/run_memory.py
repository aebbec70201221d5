"""Peak memory of a whole run (issue 32 item 7): ``sim.run`` of mpm88 with and without ``donate=True``, in memory
and with a writer (chunks of one frame), each in a fresh process, by the process's peak resident set size.

    python benchmarks/run_memory.py                              # 4.2M particles, float32, 40 steps
    python benchmarks/run_memory.py --particles 1048576 --steps 20

Each mode runs in its own process: the scene is built and its state made, a first run from a copy of the state
compiles the programs (and a second settles the process's memory), the peak resident set size is set back to the
present one (Linux: ``/proc/self/clear_refs``) and read ("before"), the run goes, and the peak is read again
(``VmHWM``).  ``peak - before`` is what the run
added: on the CPU, XLA's buffers, the frames and the writer's host copies; not the compilation.  The workers run
with glibc's ``MALLOC_MMAP_THRESHOLD_=131072``: every buffer from 128 KiB is mapped on its own and given back when
freed (glibc otherwise raises that threshold up to 32 MiB as buffers are freed, and the first run's freed buffers,
kept in the heap, would be reused unseen).  ``state`` is the particle state's size.  The run saves 5 frames
without the particles (``save_particles=False``).  Writes ``benchmarks/results/run_memory.csv`` (or ``--csv``).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

DEFAULT_CSV = Path(__file__).resolve().parent / "results" / "run_memory.csv"
MODES = ("in memory", "in memory, donated", "with a writer", "with a writer, donated")


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--particles", type=int, default=4_194_304)
    p.add_argument("--steps", type=int, default=40, help="steps of the run, in 5 frames (a multiple of 5)")
    p.add_argument("--modes", nargs="+", choices=MODES, default=list(MODES), help="the runs (default: all four)")
    p.add_argument("--csv", default=str(DEFAULT_CSV))
    p.add_argument("--worker", choices=MODES, default=None, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.steps <= 0 or args.steps % 5:
        p.error(f"--steps {args.steps}: give a positive multiple of 5")
    return args


def _status(field: str) -> int:
    """A size from /proc/self/status (VmRSS, VmHWM), bytes."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(field + ":"):
                return int(line.split()[1]) * 1024
    raise RuntimeError(f"{field} is not in /proc/self/status")


def _reset_peak() -> None:
    """The peak resident set size set back to the present one (Linux: 5 into /proc/self/clear_refs)."""
    with open("/proc/self/clear_refs", "w") as f:
        f.write("5")


def worker(mode: str, particles: int, steps: int) -> dict:
    import gc

    import jax

    import jaxmpm as jm
    from jaxmpm.run.memory import tree_bytes

    setup = jm.scene("mpm88", n_particles=particles)
    state = jax.block_until_ready(setup.state)
    options = dict(save_particles=False, donate=mode.endswith("donated"))

    def run(start):
        if not mode.startswith("with a writer"):
            return jax.block_until_ready(setup.sim.run(start, setup.dt, steps, steps // 5, **options)[0])
        with tempfile.TemporaryDirectory() as folder:
            with jm.H5Writer(os.path.join(folder, "run.h5"), setup.sim, start, dt=setup.dt) as writer:
                return jax.block_until_ready(setup.sim.run(start, setup.dt, steps, steps // 5, writer=writer,
                                                           frames_per_chunk=1, **options)[0])

    # a first run on a copy compiles the programs, whose compilation would otherwise set the peak; a second one
    # leaves the process's memory as a run leaves it (a compilation's freed memory, partly reused by the first
    # run, read 1.34 states added where a steady process reads 1.49)
    for _ in range(2):
        first = run(jax.tree_util.tree_map(lambda a: jax.device_put(a, may_alias=False), state))
        del first
        gc.collect()
    _reset_peak()
    before = _status("VmRSS")
    final = run(state)
    peak = _status("VmHWM")
    state_bytes = tree_bytes(final)
    return dict(mode=mode, particles=particles, steps=steps, state_MiB=state_bytes / 2**20, before_MiB=before / 2**20,
                peak_MiB=peak / 2**20, added_MiB=(peak - before) / 2**20, added_states=(peak - before) / state_bytes)


def main(argv=None) -> int:
    args = parse_args(argv)
    if args.worker:
        print(json.dumps(worker(args.worker, args.particles, args.steps)))
        return 0
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from _results import write_csv

    print(f"mpm88, {args.particles} particles, float32, {args.steps} steps; peak resident set size, one process "
          f"per mode\n")
    print("| run | state MiB | before the run MiB | peak MiB | added by the run MiB | added, in states |")
    print("|---|---|---|---|---|---|")
    rows = []
    for mode in args.modes:
        out = subprocess.run([sys.executable, __file__, "--worker", mode, "--particles", str(args.particles),
                              "--steps", str(args.steps)], capture_output=True, text=True, check=True,
                             env=dict(os.environ, MALLOC_MMAP_THRESHOLD_="131072"))
        row = json.loads(out.stdout.strip().splitlines()[-1])
        rows.append(row)
        print(f"| {mode} | {row['state_MiB']:.0f} | {row['before_MiB']:.0f} | {row['peak_MiB']:.0f} | "
              f"{row['added_MiB']:.0f} | {row['added_states']:.2f} |", flush=True)
    print(f"\nwrote {write_csv(args.csv, list(rows[0]), rows)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
