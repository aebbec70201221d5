"""jaxmpm's ``mpm88`` scene against Taichi's mpm88, from the same particles, float64.

The speed comparisons (benchmarks/vs_taichi.py, benchmarks/gpu.py) time jaxmpm's ``mpm88`` against
Taichi's 88-line demo.  The two are the same scene with two terms written differently
(jaxmpm/scenes/mpm88.py):

* **force:** mpm88 is MLS-MPM, f_i = -sum_p V0 tau D^-1 (x_i - X_p) S_pi with D = dx^2/4; jaxmpm
  uses the gradient form f_i = -sum_p V0 tau G_pi (001 eq. 20) for every scheme;
* **J:** mpm88 updates J <- J (1 + dt tr C_p) with APIC's C_p = B_p D^-1; jaxmpm updates
  F <- (I + dt L_p) F with L_p = sum_i v_i (x) G_pi, so J <- det(I + dt L_p) J, and the fluid resets F
  to sqrt(J) I.

Two forms of the benchmarks' Taichi kernel (``benchmarks/_taichi_mpm.py``), both float64 on one CPU thread:

1. **Taichi in jaxmpm's form** (both terms rewritten as above, everything else mpm88's): from a
   start with random velocities and J = 1 +- 0.02 (so that the first step has stress), one step
   and ten, then mpm88's own start to the pile-up.  It equals jaxmpm to round-off: the scene is
   mpm88 but for the two documented terms.
2. **Taichi's own mpm88** from the same starts: the difference the two terms make.  On mpm88's
   own start the particles fall freely (J = 1, no stress) until they reach the floor, between
   steps 500 and 700: there the two agree to round-off, and the timed windows of the benchmarks
   (300 steps on the CPU, 500 on the GPU) lie inside it.  After the impact they part.

Needs taichi (``pip install taichi``; not a dependency of jaxmpm).  Writes
experiments/results/mpm88_vs_taichi.md (``--quick``: 1024 particles, steps to 1000, no file)::

    python experiments/mpm88_vs_taichi.py [--quick] [--json]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)
import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jaxmpm as jm  # noqa: E402

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(os.path.dirname(HERE), "benchmarks"))
from _taichi_mpm import substep_kernel  # noqa: E402  (the benchmarks' mpm88 substep, in either form)

N_GRID = 128


def kinetic(v, mass: float) -> float:
    return 0.5 * mass * float(np.sum(np.asarray(v, np.float64) ** 2))


def compare(ti, particles: int, checkpoints: list, perturbed: bool) -> dict:
    """Both Taichi kernels and jaxmpm from one start, stepped to each checkpoint: per kernel and
    checkpoint, max |x - x_jaxmpm|, max |v - v_jaxmpm|, max |J - J_jaxmpm| and the kinetic energies."""
    setup = jm.scene("mpm88", n_particles=particles, dtype="f64")
    sim, state = setup.sim, setup.state
    dt = float(setup.dt)
    if perturbed:  # random velocities and J = 1 +- 0.02: stress from the first step
        rng = np.random.default_rng(1)
        v0 = np.asarray(state.v) + 0.5 * rng.standard_normal(state.v.shape)
        J0 = 1 + 0.02 * rng.standard_normal(particles)
        state = eqx.tree_at(lambda s: (s.v, s.F), state,
                            (jnp.asarray(v0), jnp.asarray(np.sqrt(J0)[:, None, None] * np.eye(2))))
    x0, v0 = np.asarray(state.x), np.asarray(state.v)
    J0 = np.linalg.det(np.asarray(state.F))
    mass = float(state.mass[0])

    @eqx.filter_jit
    def advance(state, steps):
        return jax.lax.fori_loop(0, steps, lambda _, s: sim.step(s, jnp.asarray(dt)), state)

    ours, done, reached = state, 0, {}
    for steps in checkpoints:
        ours = advance(ours, steps - done)
        done = steps
        reached[steps] = (np.asarray(ours.x), np.asarray(ours.v), np.linalg.det(np.asarray(ours.F)))
    out = {"particles": particles, "perturbed": perturbed, "rows": []}
    for form in ("gradient", "mls"):
        ti.init(arch=ti.cpu, default_fp=ti.f64, cpu_max_num_threads=1, log_level=ti.WARN)
        substep, (x, v, C, J) = substep_kernel(ti, particles, 2, N_GRID, dt, real=ti.f64, form=form)
        x.from_numpy(x0)
        v.from_numpy(v0)
        J.from_numpy(J0)
        C.fill(0)
        done = 0
        for steps in checkpoints:
            for _ in range(steps - done):
                substep()
            done = steps
            xj, vj, Jj = reached[steps]
            out["rows"].append({"form": form, "steps": steps,
                                "x": float(np.abs(x.to_numpy() - xj).max()),
                                "v": float(np.abs(v.to_numpy() - vj).max()),
                                "J": float(np.abs(J.to_numpy() - Jj).max()),
                                "kinetic_taichi": kinetic(v.to_numpy(), mass), "kinetic_jaxmpm": kinetic(vj, mass)})
    return out


def table(result: dict) -> str:
    lines = ["| Taichi kernel | steps | max abs x diff | max abs v diff | max abs J diff | KE Taichi | KE jaxmpm | "
             "KE gap |", "|---|---|---|---|---|---|---|---|"]
    for r in result["rows"]:
        gap = r["kinetic_jaxmpm"] / r["kinetic_taichi"] - 1
        lines.append(f"| {'jaxmpm form' if r['form'] == 'gradient' else 'mpm88 (MLS)'} | {r['steps']} | {r['x']:.2e} | "
                     f"{r['v']:.2e} | {r['J']:.2e} | {r['kinetic_taichi']:.6g} | {r['kinetic_jaxmpm']:.6g} | "
                     f"{gap:+.2%} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="1024 particles, steps to 1000, no results file")
    parser.add_argument("--json", action="store_true", help="print one JSON line (the tests read it)")
    args = parser.parse_args(argv)
    try:
        import taichi as ti
    except ImportError:
        print("experiments/mpm88_vs_taichi.py needs taichi: pip install taichi", file=sys.stderr)
        return 2
    particles = 1024 if args.quick else 8192
    start = time.perf_counter()
    results = {"stressed start": compare(ti, particles, [1, 10], perturbed=True),
               "mpm88's start": compare(ti, particles, [300, 500, 700, 1000] + ([] if args.quick else [2000, 5000]),
                                        perturbed=False)}
    if args.json:
        print(json.dumps(results))
        return 0
    text = ["# jaxmpm's mpm88 against Taichi's, float64 (experiments/mpm88_vs_taichi.py)", "",
            f"{particles} particles; Taichi {ti.__version__} on one CPU thread; {time.perf_counter() - start:.0f} s.",
            ""]
    for name, result in results.items():
        text += [f"## From {name}", "", table(result), ""]
    print("\n".join(text))
    if not args.quick:
        with open(os.path.join(HERE, "results", "mpm88_vs_taichi.md"), "w") as f:
            f.write("\n".join(text))
    return 0


if __name__ == "__main__":
    sys.exit(main())
