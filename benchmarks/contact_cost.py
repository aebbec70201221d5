"""Cost of multimaterial mode: a two-material step with contact against the single-field step.

A two-material model keeps its two velocity fields as one nodal array of 2n rows and offsets each
particle's stencil into its material's rows (jaxmpm/_contact.py), so the particle transfers cost
what they cost in single-field mode; what grows is the nodal work (twice the rows, the contact
law, the mass gradients' D extra scatter columns, and the contact force gather).  Measured here,
float64, FLIP, USL, with a jitted ``lax.fori_loop`` of ``sim.step`` (no diagnostics), each timing
the best of ``--repeats`` interleaved rounds after a compiling call; compile time is reported apart:

* ``disks`` (Sulsky's two disks, h = 0.05, 416 particles) and ``disks-fine`` (h = 0.0125, about
  6.6k particles): single field, and two materials with stick, frictionless and Coulomb contact;
* ``mpm88-2`` (Taichi's mpm88 fluid, APIC, 8192 particles, 128^2 grid) split into two materials
  by x < 0.5 (a two-fluid variant), single field against frictionless contact.

    python benchmarks/contact_cost.py            # about a minute on 2 CPU cores
    python benchmarks/contact_cost.py --quick    # a smoke test
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from pathlib import Path

import jax
from _results import write_csv

jax.config.update("jax_enable_x64", True)

import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jaxmpm as jm  # noqa: E402

DEFAULT_CSV = Path(__file__).resolve().parent / "results" / "contact_cost.csv"

#: case -> (scene, scene options, steps per timed call)
CASES = {
    "disks": ("disks", dict(), 400),
    "disks-fine": ("disks", dict(spacing=0.0125), 100),
    "mpm88-2": ("mpm88", dict(), 100),
}
LAWS = {"disks": ("stick", "frictionless", "coulomb"), "disks-fine": ("frictionless",),
        "mpm88-2": ("frictionless",)}
FIELDS = ["case", "particles", "grid_nodes", "model", "steps", "compile_s", "best_s", "us_per_step",
          "ratio_to_single_field", "particle_steps_per_s", "device", "jax", "cpus"]


@eqx.filter_jit
def advance(sim, state, dt, steps):
    return jax.lax.fori_loop(0, steps, lambda _, s: sim.step(s, dt), state)


def material_ids(case, setup):
    x = np.asarray(setup.state.x)
    if case.startswith("disks"):
        return (np.arange(x.shape[0]) >= setup.params["n_first"]).astype(float)  # the second disk
    return (x[:, 0] >= 0.5).astype(float)  # mpm88 split at x = 0.5


def models(case, setup):
    yield "single field", setup.sim, setup.state
    ids = material_ids(case, setup)
    for law in LAWS[case]:
        contact = jm.Contact(law=law, friction=0.3 if law == "coulomb" else 0.0)
        sim = setup.sim.with_term(contact)
        x = setup.state.x  # the contact term's fields added to the scene's own state
        state = jm.with_fields(setup.state, material=jnp.asarray(ids, x.dtype), contact_force=jnp.zeros_like(x))
        yield f"two materials, {law}", sim, state


def measure(case, quick, repeats):
    scene, options, steps = CASES[case]
    steps = max(10, steps // 4) if quick else steps
    setup = jm.scene(scene, dtype="f64", t_end=1e-6, frames=1, **options)
    dt = jnp.asarray(setup.dt, jnp.float64)
    jobs = []
    for label, sim, state in models(case, setup):
        start = time.perf_counter()
        jax.block_until_ready(advance(sim, state, dt, steps))
        jobs.append((label, sim, state, time.perf_counter() - start))
    best = {label: float("inf") for label, *_ in jobs}
    for _ in range(repeats):
        for label, sim, state, _ in jobs:
            start = time.perf_counter()
            jax.block_until_ready(advance(sim, state, dt, steps))
            best[label] = min(best[label], time.perf_counter() - start)
    n = int(setup.state.x.shape[0])
    base = best["single field"]
    device = jax.devices()[0]
    rows = []
    for label, _, _, first in jobs:
        rows.append(dict(case=case, particles=n, grid_nodes=setup.sim.grid.num_nodes, model=label, steps=steps,
                         compile_s=max(0.0, first - best[label]), best_s=best[label],
                         us_per_step=1e6 * best[label] / steps, ratio_to_single_field=best[label] / base,
                         particle_steps_per_s=n * steps / best[label],
                         device=getattr(device, "device_kind", str(device)), jax=jax.__version__,
                         cpus=os.cpu_count()))
        r = rows[-1]
        print(f"  {case:10s} {label:28s} {r['us_per_step']:9.1f} us/step  x{r['ratio_to_single_field']:.2f}  "
              f"{r['particle_steps_per_s']:.3g} p-steps/s  (jit {r['compile_s']:.2f} s)", flush=True)
    return rows


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--cases", nargs="+", default=list(CASES), choices=list(CASES))
    parser.add_argument("--csv", type=Path, default=DEFAULT_CSV)
    args = parser.parse_args(argv)
    print(f"jax {jax.__version__} on {jax.default_backend()} ({platform.processor() or platform.machine()}, "
          f"{os.cpu_count()} CPUs)")
    rows = [r for case in args.cases for r in measure(case, args.quick, 2 if args.quick else args.repeats)]
    print(f"wrote {write_csv(args.csv, FIELDS, rows)}")


if __name__ == "__main__":
    main()
