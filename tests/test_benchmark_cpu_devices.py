"""benchmarks/cpu_devices.py: mpm88 with its particles shared among 2 CPU devices against one device, each in a
process of its own (the device count is fixed when JAX starts), in its --quick form."""

import csv

import pytest


@pytest.mark.slow
def test_shared_against_one_device(benchmark_script, tmp_path):
    script = benchmark_script("cpu_devices.py")
    out = tmp_path / "cpu_devices.csv"
    # 4096 particles are below the table's 60k, so the shared run forces its 2 devices; chunks of 1024 on each
    assert script.main(["--quick", "--chunk", "1024", "--csv", str(out)]) == 0
    (row,) = list(csv.DictReader(out.open()))
    assert row["particles"] == "4096" and row["dtype"] == "f64" and row["devices_used"] == "2"
    assert float(row["one_ms"]) > 0 and float(row["shared_ms"]) > 0 and float(row["ratio"]) > 0
    assert float(row["y_cm_difference"]) < 1e-13  # the same flow to round-off
