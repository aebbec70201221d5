"""benchmarks/compile_time.py runs (one scene, one program, a few steps) and writes the columns it
documents; its numbers are the benchmark's business, not the test's."""

import csv
import subprocess
import sys
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "compile_time.py"


@pytest.mark.slow
def test_compile_time_quick_writes_its_columns(tmp_path, benchmark_script):
    path = tmp_path / "compile_time.csv"
    out = subprocess.run([sys.executable, str(SCRIPT), "--quick", "--scenes", "heat1d", "--programs", "rollout",
                          "--steps", "10", "--no-recompiles", "--csv", str(path)],
                         capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]
    with open(path) as f:
        reader = csv.DictReader(f)
        rows = list(reader)
    assert reader.fieldnames == benchmark_script("compile_time.py").FIELDS  # it imports no JAX at module level
    assert [(r["scene"], r["program"], r["steps"]) for r in rows] == [("heat1d", "rollout", "10")]
    row = rows[0]
    for name in ("trace_s", "lower_s", "compile_s", "run_s", "warm_s", "flops"):
        assert float(row[name]) > 0, (name, row[name])
    assert int(row["hlo_instructions"]) > 0 and int(row["jaxpr_eqns"]) > 0
    assert row["warm_hits"] == "1"  # the second process read the program from the persistent cache
