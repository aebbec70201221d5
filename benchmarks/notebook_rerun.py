"""A notebook run twice with the persistent compilation cache (on by default): the first run fills a
fresh cache folder, the second reads the programs back.  Once per ``--min-compile-seconds``
threshold, and once with the cache off (``JAXMPM_CACHE=0``), each in its own Jupyter kernel, as
``tests/test_notebooks.py`` runs them (nbclient); the rows of one call are comparable, and the load
average is printed beside them.

    python benchmarks/notebook_rerun.py                        # notebook 03, full size, thresholds 0 and 0.5
    python benchmarks/notebook_rerun.py --quick --notebook 01 --min-compile-seconds 0 0.1 1
"""

from __future__ import annotations

import argparse
import os
import pathlib
import tempfile
import time

import nbformat
from _results import write_csv
from nbclient import NotebookClient

ROOT = pathlib.Path(__file__).resolve().parent.parent


def run_notebook(path: pathlib.Path, env: dict, workdir: str) -> float:
    """Seconds to execute the notebook top to bottom in a fresh kernel (kernel start included)."""
    saved = dict(os.environ)
    os.environ.update(env)
    try:
        nb = nbformat.read(path, as_version=4)
        start = time.perf_counter()
        NotebookClient(nb, timeout=1800, kernel_name="python3", resources={"metadata": {"path": workdir}}).execute()
        return time.perf_counter() - start
    finally:
        os.environ.clear()
        os.environ.update(saved)


def folder_stats(folder: pathlib.Path) -> tuple:
    files = [f for f in folder.glob("*-cache")] if folder.exists() else []
    return len(files), sum(f.stat().st_size for f in files)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--notebook", default="03", help="the notebook's number (default 03)")
    parser.add_argument("--quick", action="store_true", help="JAXMPM_NOTEBOOK_QUICK=1 (the test suite's size)")
    parser.add_argument("--min-compile-seconds", type=float, nargs="+", default=[0.0, 0.5],
                        help="thresholds, one pair of runs each (default 0 0.5)")
    parser.add_argument("--no-baseline", action="store_true", help="leave out the run with the cache off")
    args = parser.parse_args()
    path = next((ROOT / "notebooks").glob(f"{args.notebook}_*.ipynb"))
    base = {"MPLBACKEND": "Agg", "JAXMPM_NOTEBOOK_QUICK": "1" if args.quick else "0"}
    rows = []
    with tempfile.TemporaryDirectory(prefix="jaxmpm-rerun-") as tmp:
        if not args.no_baseline:
            seconds = run_notebook(path, {**base, "JAXMPM_CACHE": "0"}, tmp)
            rows.append({"cache": "off", "min_compile_s": "", "run": 1, "wall_s": round(seconds, 2), "entries": 0,
                         "mbytes": 0.0, "load": round(os.getloadavg()[0], 2)})
            print(rows[-1], flush=True)
        for threshold in args.min_compile_seconds:
            folder = pathlib.Path(tmp) / f"xla-{threshold}"
            env = {**base, "JAXMPM_CACHE": "1", "JAXMPM_CACHE_DIR": str(folder),
                   "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": str(threshold)}
            for run in (1, 2):
                seconds = run_notebook(path, env, tmp)
                entries, size = folder_stats(folder)
                rows.append({"cache": "on", "min_compile_s": threshold, "run": run, "wall_s": round(seconds, 2),
                             "entries": entries, "mbytes": round(size / 1e6, 1), "load": round(os.getloadavg()[0], 2)})
                print(rows[-1], flush=True)
    print(f"\nnotebook {path.name} ({'quick' if args.quick else 'full size'})")
    print(f"{'cache':>5} {'min_compile_s':>13} {'run':>3} {'wall_s':>8} {'entries':>7} {'MB':>6} {'load':>5}")
    for r in rows:
        print(f"{r['cache']:>5} {r['min_compile_s']!s:>13} {r['run']:>3} {r['wall_s']:>8} {r['entries']:>7} "
              f"{r['mbytes']:>6} {r['load']:>5}")
    out = write_csv(ROOT / "benchmarks" / "results" / "notebook_rerun.csv", list(rows[0]), rows)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
