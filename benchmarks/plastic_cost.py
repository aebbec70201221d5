"""Cost of a plastic step against an elastic neo-Hookean one (issue 31: at most 1.5x on the CPU).

mpm88's scene (Taichi's 2D example, ``--particles``, float32 by default) with its material replaced:
``NeoHookean(E, nu)`` against each plastic law of the library with the same E and nu and a yield
limit low enough that the particles yield (the return mapping's yielding branch runs; a law has
the same cost on both branches, being branch-free).  Every material runs the same steps in the same
process, alternating, and the table gives the best CPU time per step (``time.process_time``: the
machine's other load counts less; wall time on a GPU) and its ratio to the neo-Hookean step,
compile time apart.

    python benchmarks/plastic_cost.py                  # 8192 particles, 200 steps, float32
    python benchmarks/plastic_cost.py --particles 32768 --float64
    python benchmarks/plastic_cost.py --only von_mises drucker_prager
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

from _results import cpu_best, write_csv

DEFAULT_CSV = Path(__file__).resolve().parent / "results" / "plastic_cost.csv"


def wall_best(jax, fn, *args) -> float:
    """Wall time of one call after a warm-up (on a GPU)."""
    jax.block_until_ready(fn(*args))
    start = time.perf_counter()
    jax.block_until_ready(fn(*args))
    return time.perf_counter() - start


def materials(jm, E, nu):
    """{name: material}: the elastic reference and each plastic law present, yielding at mpm88's
    stresses (E = 400: pressures of order 1-10)."""
    out = {"neohookean": jm.NeoHookean(E, nu)}
    out["von_mises"] = jm.VonMises(E, nu, yield_stress=0.5)
    if hasattr(jm, "DruckerPrager"):
        out["drucker_prager"] = jm.DruckerPrager(E, nu, friction_angle=30.0)
    if hasattr(jm, "CamClay"):
        out["cam_clay"] = jm.CamClay(E, nu)
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--particles", type=int, default=8192)
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--float64", action="store_true")
    parser.add_argument("--csv", default=str(DEFAULT_CSV))
    parser.add_argument("--only", nargs="+", metavar="NAME",
                        help="time only these materials (the neo-Hookean reference always runs), "
                             "e.g. --only von_mises drucker_prager")
    args = parser.parse_args(argv)

    import jax

    jax.config.update("jax_enable_x64", args.float64)
    import equinox as eqx
    import jax.numpy as jnp

    import jaxmpm as jm

    jm.compilation_cache(False)  # compile times of this process, not read back from an earlier one
    setup = jm.scene("mpm88", n_particles=args.particles)
    dtype = setup.state.x.dtype

    class Points:
        x = setup.state.x

    laws = materials(jm, 400.0, 0.2)
    unknown = sorted(set(args.only or ()) - set(laws))
    if unknown:
        parser.error(f"--only {' '.join(unknown)}: choose from {', '.join(laws)}")
    programs, compile_s = {}, {}
    for name, material in laws.items():
        if args.only and name != "neohookean" and name not in args.only:
            continue
        sim = eqx.tree_at(lambda s: s.material, setup.sim, material)
        state = eqx.tree_at(lambda s: s.material_state, setup.state, material.initial_state(Points),
                            is_leaf=lambda x: x is None)
        state = jax.tree_util.tree_map(lambda a: a.astype(dtype) if jnp.issubdtype(a.dtype, jnp.floating) else a, state)
        run = jax.jit(lambda s, sim=sim: sim.run(s, setup.dt, args.steps, args.steps, save_particles=False)[0])
        start = time.perf_counter()
        run = run.lower(state).compile()
        compile_s[name] = time.perf_counter() - start
        programs[name] = (run, state)
    best = {name: float("inf") for name in programs}
    gpu = jax.default_backend() != "cpu"  # a device's time is wall time; the host's CPU time is not it
    for _ in range(args.repeat):  # alternating, so that a burst of load hits every material alike
        for name, (run, state) in programs.items():
            best[name] = min(best[name], wall_best(jax, run, state) if gpu else cpu_best(run, state, repeat=1))
    print(f"mpm88, {args.particles} particles, {args.steps} steps, {jnp.dtype(dtype).name}; "
          f"{jax.devices()[0].device_kind}; {os.cpu_count()} CPUs, load {os.getloadavg()[0]:.1f}")
    print(f"{'material':>15} {'ms/step':>8} {'ratio':>6} {'compile_s':>9}")
    rows = []
    for name in programs:
        per_step = 1e3 * best[name] / args.steps
        ratio = best[name] / best["neohookean"]
        print(f"{name:>15} {per_step:8.3f} {ratio:6.2f} {compile_s[name]:9.2f}")
        rows.append(dict(material=name, particles=args.particles, steps=args.steps, dtype=jnp.dtype(dtype).name,
                         ms_per_step=per_step, ratio=ratio, compile_s=compile_s[name]))
    print(f"wrote {write_csv(args.csv, list(rows[0]), rows)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
