"""benchmarks/memory_per_particle.py (issue 32 item 7): gpu.py's rollout compiled, never run, and XLA's account of
its buffers per particle against the particle state's."""

import csv

import pytest


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


@pytest.mark.slow
def test_gradient_bytes_with_derivatives_in_chunks(benchmark_script, tmp_path, monkeypatch):
    """--gradient on a device of 4 MiB (--device-memory): mpm88's 8192 particles then go in chunks that fit, their
    derivatives in the same chunks, and the gradient program holds fewer bytes than with the whole step's
    derivatives over the same forward chunks (the row "library's forward")."""
    monkeypatch.setenv("JAXMPM_MEMORY_BYTES", str(2**40))  # restored after the test: the script sets it
    script = benchmark_script("memory_per_particle.py")
    out = tmp_path / "memory.csv"
    assert script.main(["--cases", "2d:8192:f32", "--steps", "2", "--gradient", "--device-memory", "4 MiB",
                        "--csv", str(out)]) == 0
    fitted, whole, forced = list(csv.DictReader(out.open()))
    assert (fitted["step"], whole["step"], forced["step"]) == (
        "library's (chunks of 1024), derivatives in chunks of 1024", "whole (whole), whole derivatives",
        "library's forward (chunks of 1024), whole derivatives")
    assert fitted["temporaries"] == forced["temporaries"]  # the same forward program
    assert float(fitted["gradient_program"]) < 0.7 * float(forced["gradient_program"]), (fitted, forced)
