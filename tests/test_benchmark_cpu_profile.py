"""benchmarks/cpu_profile.py: each XLA kernel of a compiled mpm88 step on one core and on all, with its calls per
step, its parallel partitions and the jaxmpm line that made it; the frames and partitions are read from the
compiled program's text."""

import jax
import jax.numpy as jnp
import pytest


@pytest.fixture(scope="module")
def profile(benchmark_script):
    return benchmark_script("cpu_profile.py")


def test_frames_and_partitions_read_from_a_compiled_program(profile):
    from jaxmpm.core.linalg import det  # a jaxmpm line, to find in the frames

    compiled = jax.jit(lambda a: det(a) * 2.0).lower(jnp.ones((4, 2, 2))).compile()
    text = compiled.as_text()
    lines = profile.source_lines(text)
    assert any(where.startswith("core/linalg.py:") and "(det)" in where for where in lines.values()), lines
    parts = profile.partitions(text)
    assert parts and set(parts.values()) == {1}  # 16 numbers: no kernel worth splitting
    fake = '  %fusion.1 = f32[8]{0} fusion(%p), kind=kLoop, backend_config={"outer_dimension_partitions":["2","3"]}'
    assert profile.partitions(fake) == {"fusion.1": 6}


@pytest.mark.slow
def test_one_core_against_all(profile, tmp_path):
    out = tmp_path / "profile.md"
    assert profile.main(["--particles", "2048", "--steps", "2", "--top", "8", "--markdown", str(out)]) == 0
    text = out.read_text()
    assert text.startswith("# mpm88, 2048 particles, f64, 2 steps per call")
    assert "- wall per step: 1 core" in text and "- kernels per step:" in text
    rows = [line for line in text.splitlines() if line.startswith("| ") and not line.startswith("| kernel")]
    assert len(rows) == 8
    assert any("transfer/kernels/xla.py:" in row for row in rows)  # P2G's and G2P's kernels, by their lines
    assert all(float(row.split("|")[2]) > 0 for row in rows)  # each kernel's time on one core


@pytest.mark.slow
def test_a_gradients_kernels(profile, tmp_path):
    out = tmp_path / "gradient.md"
    assert profile.main(["--program", "gradient", "--particles", "1024", "--steps", "2", "--top", "200",
                         "--markdown", str(out)]) == 0
    text = out.read_text()
    assert text.startswith("# mpm88 gradient, 1024 particles, f64, 2 steps per call")
    rows = [line for line in text.splitlines() if line.startswith("| ") and not line.startswith("| kernel")]
    # the forward pass, the recomputed step and its transpose: more kernels than a step's, P2G's among them
    assert len(rows) > 60
    assert any("transfer/kernels/xla.py:" in row for row in rows)
