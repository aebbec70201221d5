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


def test_compile_time_pieces_are_the_step_and_its_pullback(benchmark_script):
    """The ``step`` and ``transpose`` programs (the pieces whose compile times the summary adds up) are one
    step of the scene and that step's pullback: the pullback fed ones equals jax.vjp of the step."""
    import equinox as eqx
    import jax
    import jax.numpy as jnp
    import numpy as np

    compile_time = benchmark_script("compile_time.py")
    step, step_args, steps, particles = compile_time._program("heat1d", "step", 10)
    transpose, (pullback, ones), _, _ = compile_time._program("heat1d", "transpose", 10)
    assert steps == 1 and particles > 0
    floats = step_args[0]
    assert jax.tree_util.tree_structure(step(*step_args)) == jax.tree_util.tree_structure(floats)
    expected = jax.vjp(step, *step_args)[1](jax.tree_util.tree_map(jnp.ones_like, floats))
    got = jax.jit(transpose)(pullback, ones)
    for a, b in zip(jax.tree_util.tree_leaves(eqx.filter(got, eqx.is_array)),
                    jax.tree_util.tree_leaves(eqx.filter(expected, eqx.is_array))):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-12, atol=1e-300)
