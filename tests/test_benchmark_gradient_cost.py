"""benchmarks/gradient_cost.py (issue 30 item 3): gradient / forward of a rollout, with the particles, steps and the
derivatives' chunks as options."""

import pytest


@pytest.mark.slow
def test_a_row_with_the_derivatives_in_chunks(benchmark_script):
    """mpm88 at 512 particles, 10 steps, the steps' derivatives in chunks of 128 and whole: a row each, with the
    sizes asked for, a gradient that costs more than its forward run and a floor above 2 forward runs."""
    script = benchmark_script("gradient_cost.py")
    rows = [script.measure("mpm88", "flip", "structured", "auto", 1, particles=512, steps=10, derivative_chunks=chunks)
            for chunks in (128, 0)]
    assert [row["derivative_chunks"] for row in rows] == [128, 0]
    for row in rows:
        assert (row["particles"], row["steps"]) == (512, 10)
        assert row["grad_s"] > row["forward_s"] > 0 and row["ratio"] > 1
        assert row["floor_ops"] > 2 and row["floor_time"] > 2
