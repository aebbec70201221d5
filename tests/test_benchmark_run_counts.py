"""benchmarks/run_counts.py (RUNTIME_COUNTS in jaxmpm/transfer/backend.py): sim.run with runtime frame and step counts
against static scans, each in a fresh process."""

import pytest


@pytest.mark.slow
def test_both_settings_give_the_same_run_and_only_static_scans_compile_a_new_length(benchmark_script, capsys):
    """mpm88 at 1024 particles, 20 steps: the two settings end at the same kinetic energy (no line says they differ);
    a run of another length takes far less with runtime counts (no compilation) than with static scans."""
    script = benchmark_script("run_counts.py")
    assert script.main(["--sizes", "1024", "--steps", "20", "--repeat", "1"]) == 0
    out = capsys.readouterr().out
    assert "differ" not in out
    rows = {line.split("|")[2].strip(): [float(c) for c in line.split("|")[3:7]] for line in out.splitlines()
            if line.startswith("| 1024 |")}
    assert set(rows) == {"static", "runtime"}
    assert rows["runtime"][2] < 0.5 * rows["static"][2], rows
