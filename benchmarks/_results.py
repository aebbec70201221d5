"""Shared by the benchmark scripts: writing a result table as CSV and CPU timing."""

from __future__ import annotations

import csv
import time
from pathlib import Path

#: ``sim.run``'s ``checkpoint=`` values by their command-line names (the scripts' ``--checkpoint``)
CHECKPOINTS = {"True": True, "False": False, "low_memory": "low_memory", "states": "states", "auto": "auto"}


def write_csv(path, fields, rows) -> Path:
    """``rows`` (dicts) as a CSV file at ``path`` with columns ``fields``; the folders are created."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=fields)
        writer.writeheader()
        writer.writerows(rows)
    return path


def cpu_best(fn, *args, repeat: int) -> float:
    """Best CPU time (``time.process_time``) of ``repeat`` calls of ``fn(*args)`` after a warm-up."""
    import jax  # here: scripts that time nothing keep their parent process free of jax
    jax.block_until_ready(fn(*args))
    times = []
    for _ in range(repeat):
        start = time.process_time()
        jax.block_until_ready(fn(*args))
        times.append(time.process_time() - start)
    return min(times)
