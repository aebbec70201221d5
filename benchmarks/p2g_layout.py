"""The XLA kernel's P2G layouts and G2P gathers side by side: particle-steps per CPU second, and the gradient.

``XLAKernel(layout="planar")`` forms each P2G column's per-slot values and stacks them, (C, K, N);
``XLAKernel(layout="rows")`` multiplies per-particle coefficients (N, C) by the weight basis
(S, G_d, S (x_i - X_p)_d) into the scatter's rows, with no per-slot concatenation
(``jaxmpm/transfer/kernels/xla.py``).  ``hold_gathers`` says whether G2P's gathered nodal values are
evaluated once into per-slot buffers (``held``) or fused into the products that read them
(``free``).  This script registers each variant in turn for the CPU policy and times the same step
in the same process, so the ratio is what the variant changes; the backend's table
(``jaxmpm.transfer.backend.XLA_LAYOUT``) is set from it.

On the CPU the time is CPU time of this process (``time.process_time``, best of ``--repeats``
after a warm-up; ``benchmarks/_results.cpu_best``), which other work on the machine disturbs far
less than wall time; on a GPU it is wall time (the policy there is "gpu").  Pin one core for the
cleanest CPU numbers:

    XLA_FLAGS=--xla_cpu_multi_thread_eigen=false taskset -c 0 python benchmarks/p2g_layout.py
    python benchmarks/p2g_layout.py --quick

Cases (``--cases``): mpm88 (APIC, quadratic, 8192 particles, float32; ``mpm88-f64``, ``-32k``,
``-131k`` in float64), disks (FLIP, uGIMP, 416 particles, float64), disks-large (FLIP, uGIMP, 25.7k
particles, float32 and ``-f64``), mms 3D (FLIP, linear, float64), bar (1D, float64), and the
gradients (``/grad``) of the kinetic energy after 20 steps with respect to E (structured adjoint).
``--variants`` picks among planar-held (float32's default), planar-free, rows-held and rows-free
(float64's default).  Compile time is reported apart.  Writes ``benchmarks/results/p2g_layout.csv``.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
from _results import cpu_best, write_csv  # noqa: E402

import jaxmpm as jm  # noqa: E402
from jaxmpm.transfer.backend import use_policy  # noqa: E402
from jaxmpm.transfer.kernels import XLAKernel, kernel, register_kernel  # noqa: E402

DEFAULT_CSV = Path(__file__).resolve().parent / "results" / "p2g_layout.csv"

#: case -> (scene, options, steps per timed call); a name ending in /grad times the gradient
CASES = {
    "mpm88": ("mpm88", dict(dtype="f32"), 100),
    "mpm88-f64": ("mpm88", dict(dtype="f64"), 100),
    "mpm88-f64-32k": ("mpm88", dict(dtype="f64", n_particles=32768), 30),
    "mpm88-f64-131k": ("mpm88", dict(dtype="f64", n_particles=131072), 10),
    "disks": ("disks", dict(dtype="f64"), 400),
    "disks-large": ("disks", dict(dtype="f32", spacing=0.00625), 20),
    "disks-large-f64": ("disks", dict(dtype="f64", spacing=0.00625), 20),
    "mms-3d": ("mms", dict(dtype="f64", dim=3, cells=8), 50),
    "bar": ("bar", dict(dtype="f64"), 400),
}
GRADIENTS = ("mpm88/grad", "mpm88-f64/grad", "disks/grad")
#: variant -> XLAKernel options
VARIANTS = {"planar-held": dict(layout="planar", hold_gathers=True),
            "planar-free": dict(layout="planar", hold_gathers=False),
            "rows-held": dict(layout="rows", tangent_layout="rows", hold_gathers=True),
            "rows-free": dict(layout="rows", tangent_layout="rows", hold_gathers=False),
            "rows/planar-free": dict(layout="rows", tangent_layout="planar", hold_gathers=False)}


@eqx.filter_jit
def advance(sim, state, dt, steps):
    final, history, failure = sim.rollout(state, dt, 1, steps, save_particles=False)
    return final.x, history.kinetic


@eqx.filter_jit
def gradient(sim, state, dt, steps):
    def loss(E):
        final, _, _ = jm.set_params(sim, E=E).rollout(state, dt, 1, steps, save_particles=False)
        return jm.kinetic_energy(final)

    return jax.grad(loss)(jnp.asarray(400.0, state.x.dtype))


def wall_best(fn, *args, repeat: int) -> float:
    """Best wall time of ``repeat`` calls (an accelerator: its time is not this process's CPU time)."""
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - start)
    return min(times)


def measure(fn, setup, steps, repeats):
    sim, state = setup.sim, setup.state
    dt = jnp.asarray(setup.dt, state.x.dtype)
    start = time.perf_counter()
    jax.block_until_ready(fn(sim, state, dt, steps))
    first = time.perf_counter() - start
    best = cpu_best if jax.default_backend() == "cpu" else wall_best
    return first, best(fn, sim, state, dt, steps, repeat=repeats)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--quick", action="store_true", help="fewer steps and repeats")
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--rounds", type=int, default=2, help="alternations of the two layouts (default 2)")
    p.add_argument("--csv", default=str(DEFAULT_CSV))
    p.add_argument("--cases", nargs="+", default=list(CASES) + list(GRADIENTS), choices=list(CASES) + list(GRADIENTS))
    p.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    args = p.parse_args(argv)
    repeats = 2 if args.quick else args.repeats
    policy = "cpu" if jax.default_backend() == "cpu" else "gpu"  # the policy "auto" resolves to
    with use_policy(policy):
        default = kernel()
    rows = []
    print(f"{'case':<20}{'variant':<13}{'particle-steps/CPU s':>22}{'compile s':>11}")
    for case in args.cases:
        name, kind = (case[:-5], "gradient") if case.endswith("/grad") else (case, "forward")
        scene, options, steps = CASES[name]
        steps = max(steps // 4, 5) if args.quick else steps
        if kind == "gradient":
            steps = 5 if args.quick else 20
        setup = jm.scene(scene, t_end=0.01, frames=1, **options)
        n = int(setup.state.x.shape[0])
        best = {}
        for _ in range(args.rounds):
            for variant in args.variants:
                register_kernel(policy, XLAKernel(**VARIANTS[variant]))  # also drops the compiled programs
                first, run = measure(gradient if kind == "gradient" else advance, setup, steps, repeats)
                rate = n * steps / run
                best[variant] = max(best.get(variant, 0.0), rate)
                rows.append(dict(case=case, kind=kind, variant=variant, particles=n, steps=steps,
                                 cpu_s=run, particle_steps_per_cpu_s=rate, compile_s=first - run))
                print(f"{case:<20}{variant:<13}{rate:>22.4g}{first - run:>11.2f}", flush=True)
        base = args.variants[0]
        print(f"{'':<20}against {base}: " + ", ".join(f"{v} {best[v] / best[base]:.3f}" for v in args.variants[1:]),
              flush=True)
    register_kernel(policy, default)
    print("wrote", write_csv(args.csv, list(rows[0]), rows))


if __name__ == "__main__":
    main()
