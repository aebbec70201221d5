"""benchmarks/memory_per_particle.py (issue 32 item 7): gpu.py's rollout compiled, never run, and XLA's account of
its buffers per particle against the particle state's."""

import csv


def test_program_bytes_against_the_state(benchmark_script, tmp_path):
    """mpm88 at 2048 particles, float32: the library steps it whole (one row) and --chunks 512 adds the chunked
    step.  The program holds the state once (donated: the final state aliases the initial one), so program /
    state is one less than without donation, and the chunks' temporaries are smaller than the whole step's."""
    script = benchmark_script("memory_per_particle.py")
    out = tmp_path / "memory.csv"
    assert script.main(["--cases", "2d:2048:f32", "--steps", "2", "--chunks", "512", "--csv", str(out)]) == 0
    whole, chunked = list(csv.DictReader(out.open()))
    assert whole["step"] == "library's (whole)" and chunked["step"] == "forced (chunks of 512)"
    for row in (whole, chunked):
        state, aliased = float(row["state"]), float(row["aliased"])
        # x, v (2 + 2), F, B (4 + 4), mass, volume: 14 float32, and the time, step and dissipated energy
        assert 56.0 < state < 56.01 and aliased == state
        program = float(row["arguments"]) + float(row["outputs"]) + float(row["temporaries"]) - aliased
        assert abs(float(row["program"]) - program) < 1e-9
        assert abs(float(row["without_donation_over_state"]) - float(row["program_over_state"]) - 1.0) < 1e-9
    assert float(chunked["temporaries"]) < 0.6 * float(whole["temporaries"])
