"""benchmarks/run_memory.py (issue 32 item 7): what a whole run adds to the process's peak resident set size."""

import csv

import pytest


@pytest.mark.slow
def test_a_donated_run_holds_one_state_less(benchmark_script, tmp_path):
    """mpm88 with 524k particles (float32 state of 28 MiB, chunks of 32k), 5 steps in memory: kept, the run adds its
    final state and its chunks' buffers (1.49 states measured; 1.07 at 4.2M particles, whose chunks weigh less);
    donated, it computes the final state in place of the initial one and adds the buffers alone (0.49; 0.08 at
    4.2M): one state less."""
    script = benchmark_script("run_memory.py")
    out = tmp_path / "run_memory.csv"
    assert script.main(["--particles", "524288", "--steps", "5", "--modes", "in memory", "in memory, donated",
                        "--csv", str(out)]) == 0
    kept, donated = list(csv.DictReader(out.open()))
    assert kept["mode"] == "in memory" and donated["mode"] == "in memory, donated"
    assert abs(float(kept["state_MiB"]) - 28.0) < 0.01
    saved = float(kept["added_states"]) - float(donated["added_states"])
    assert 0.8 < saved < 1.2 and float(donated["added_states"]) < 0.7, (kept, donated)
