"""benchmarks/compile_profile.py: each kernel XLA:CPU emits for a program, with its emission time, its role (a
stage boundary's predicate, a branch that never runs, the step) and the jaxmpm line that made it."""

import json
import os
import subprocess
import sys

import jax
import jax.numpy as jnp
import pytest

from jaxmpm.transfer import backend

SCRIPT = os.path.join(os.path.dirname(__file__), os.pardir, "benchmarks", "compile_profile.py")


@pytest.fixture(scope="module")
def profile(benchmark_script):
    return benchmark_script("compile_profile.py")


def test_roles_of_a_stage_boundary(profile):
    """A boundary (jaxmpm.transfer.backend.materialise under the CPU policy) is an XLA conditional: its index is
    the predicate's kernel, its branch 0 the zeros that never run, its branch 1 the values."""
    def f(x):
        with backend.use_policy("cpu"):
            return backend.materialise(jnp.sin(x)) * 2.0

    text = jax.jit(f).lower(jnp.ones(64)).compile().as_text()
    roles = profile.roles(text)
    assert "boundary predicate" in roles.values() and "untaken branch" in roles.values(), roles
    predicate = next(name for name, role in roles.items() if role == "boundary predicate")
    assert f"conditional(%{predicate}" in text
    assert profile.instruction("add_fusion.3_kernel_module") == "add_fusion.3"
    assert profile.instruction("__compute_module_wrapped_copy") == "wrapped_copy"
    assert profile.kind("add_fusion.3") == "add_fusion"


@pytest.mark.slow
def test_a_rollout_profiled(tmp_path):
    """The bar's rollout at XLA's defaults (the suite's flags turn the fusion emitters off, and with them the
    emission events): every kernel emitted has a time, a size and a role; the boundaries' predicates among them."""
    env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "JAX_DISABLE_MOST_OPTIMIZATIONS")}
    env["JAX_PLATFORMS"] = "cpu"  # XLA:CPU's events, on a machine with an accelerator too
    out = tmp_path / "profile.json"
    run = subprocess.run([sys.executable, SCRIPT, "--scene", "bar", "--program", "rollout", "--steps", "20",
                          "--top", "5", "--json", str(out)], capture_output=True, text=True, env=env, timeout=300)
    assert run.returncode == 0, run.stderr[-3000:]
    r = json.loads(out.read_text())
    kernels = r["kernels"]
    assert kernels and r["launches"] >= len(kernels)  # XLA emits identical kernels once
    assert all(k["emit_ms"] > 0 and k["ops"] > 0 for k in kernels)
    assert {k["role"] for k in kernels} <= {"step", "boundary predicate", "untaken branch", "in a branch"}
    assert any(k["role"] == "boundary predicate" for k in kernels)
    assert abs(r["emit_ms"] - sum(k["emit_ms"] for k in kernels)) < 1e-6
    assert r["codegen_ms"] > 0 and r["backend_ms"] > 0
    assert any("transfer/" in k["source"] for k in kernels)  # the transfer layer's kernels, by their lines
    assert "| kernel | emit ms | ops | role | source |" in run.stdout
