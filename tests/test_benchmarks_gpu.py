"""benchmarks/gpu.py (issue 32 item 4) runs its --quick mode at each part's smallest size and writes its markdown
table and CSV; every jaxmpm run it times ends stable, and Taichi, where importable, ends where jaxmpm does."""

import csv

import pytest


@pytest.fixture(scope="module")
def gpu(benchmark_script):
    return benchmark_script("gpu.py")


@pytest.mark.slow
def test_quick_run_writes_every_part(gpu, tmp_path):
    assert gpu.main(["--quick", "--smallest", "--repeats", "1", "--no-taichi", "--out", str(tmp_path)]) == 0
    with open(tmp_path / "gpu.csv") as f:
        rows = list(csv.DictReader(f))
    assert {r["part"] for r in rows} == set(gpu.PARTS)
    assert all(float(r["particle_steps_per_s"]) > 0 and r["device"] and r["jax"] for r in rows)

    jaxmpm = [r for r in rows if r["part"] in ("mpm88", "mpm3d", "schemes")]
    assert all(r["check"].startswith("ok") for r in jaxmpm), [r["check"] for r in jaxmpm]  # no NaN run timed
    assert all(float(r["state_bytes_per_particle"]) > 0 and float(r["program_bytes_per_particle"]) > 0 for r in jaxmpm)
    assert all(r["kernel"] in ("xla", "pallas") for r in rows)  # the kernel each run used (--kernel auto)
    schemes = [r for r in rows if r["part"] == "schemes"]
    assert [r["engine"] for r in schemes] == [label for label, _, _ in gpu.SCHEMES]
    assert float(schemes[0]["ratio"]) == 1.0 and schemes[0]["ratio_to"] == "FLIP"
    gradient = next(r for r in rows if r["part"] == "gradient" and r["engine"].startswith("gradient"))
    assert float(gradient["ratio"]) > 0 and "central difference" in gradient["check"]
    assert [r["case"] for r in rows if r["part"] == "ensemble"] == ["single rollout", "4 members"]

    table = (tmp_path / "gpu.md").read_text()
    assert table.startswith("# benchmarks/gpu.py --quick") and "Taichi skipped: --no-taichi" in table
    assert all(f"## {part}" in table for part in gpu.PARTS)


@pytest.mark.slow
def test_taichi_side_by_side(gpu):
    """Taichi's substep (its CPU backend here) from the same particles as jaxmpm's mpm88 scene: the centres of
    mass fall alike.  (The 3D substep is the same code; Taichi compiles it in ~15 s on this machine's CPU.)"""
    pytest.importorskip("taichi")
    jaxmpm, taichi = gpu.part_side_by_side("mpm88", (1024,), 40, "f32", 1, gpu.Taichi(True), {})
    assert taichi["engine"].startswith("Taichi") and jaxmpm["ratio_to"] == taichi["engine"]
    assert jaxmpm["ratio"] == pytest.approx(jaxmpm["particle_steps_per_s"] / taichi["particle_steps_per_s"])
    height, start = (float(v) for v in jaxmpm["check"].split("y_cm ")[1].split(" from "))
    assert start - height == pytest.approx(start - float(taichi["check"].split("y_cm ")[1]), rel=2e-3)


@pytest.mark.slow
def test_sorted_rollout_ends_where_the_unsorted_one_does(gpu):
    """--sort-every K: the benchmark's rollout sorts the particles by cell every K steps (jaxmpm.run.sorting) and
    hands back the final state in the user's order -- the same particles to round-off (float32 here)."""
    import numpy as np

    sim, state, dt = gpu.mpm3d(512, 8, "f32")
    finals = {}
    for every in (0, 3):
        call, _, _ = gpu.compile_rollout(sim.with_sorting(every), state, dt, 12)
        finals[every] = np.asarray(call().x)
    assert gpu.kernel_of(sim.with_sorting(3), state) == "xla, sorted/3"
    np.testing.assert_allclose(finals[3], finals[0], atol=1e-6)
    assert np.abs(finals[0] - np.asarray(state.x)).max() > 1e-3  # the particles moved
