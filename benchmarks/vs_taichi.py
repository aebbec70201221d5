"""mpm88 side by side: Taichi (CPU backend) against jaxmpm, float32 (and float64), in one run.

Taichi's 88-line MPM demo (``python -m taichi example mpm88``) is written out below as Taichi
kernels (its ``substep``, unchanged apart from the particle count and taking the initial positions
from NumPy); jaxmpm runs its ``mpm88`` scene (:mod:`jaxmpm.scenes.mpm88`: APIC, quadratic
B-splines, the same fluid, gravity and one-sided walls; the force uses G_pi where mpm88's MLS
uses S_pi D^-1 (x_i - X_p)).  Both start from the same particle positions and run the same
number of steps of dt = 2e-4 after a warm-up (compilation); the result is particle-steps per
second for each and the ratio jaxmpm / Taichi.

``--dtype f32 f64`` runs both precisions: Taichi with ``default_fp=ti.f64`` (every field and
constant in float64) against the scene built with ``dtype="f64"``.

Particle counts 8192 (mpm88), 32768 and 131072 on the same 128^2 grid: the grid, dt, particle
volume and mass stay mpm88's, so the larger runs are the same flow with 4x and 16x more particles
per cell (scaling the grid instead would also need a smaller dt).

Taichi is not a dependency of jaxmpm; install it to run this file::

    pip install taichi        # wheels for CPython 3.8-3.12 on x86-64 Linux/macOS/Windows

    python benchmarks/vs_taichi.py                       # 8k, 32k, 128k particles
    python benchmarks/vs_taichi.py --particles 8192 --steps 500 --repeats 5
    python benchmarks/vs_taichi.py --quick               # 8k only, fewer steps
    python benchmarks/vs_taichi.py --dtype f32 f64       # both precisions, each side by side
    python benchmarks/vs_taichi.py --quick --t-end 1     # also the full t = 1 run, f32 and f64
    python benchmarks/vs_taichi.py --cpu-devices 2       # jaxmpm with 2 CPU devices sharing the particles
    python benchmarks/vs_taichi.py --settle 2500         # the fluid piled up on the floor (t = 0.5)

``--cpu-devices D`` starts JAX with D CPU devices (``jax_num_cpu_devices``), among which jaxmpm's steps
share their particles where its table says (:mod:`jaxmpm.model.devices`); the "devices" column says how
many a run used.

The default timed window (300 steps from mpm88's start) is the free fall: the particles spread evenly
over the box, J = 1.  ``--settle S`` times from the particles of jaxmpm's scene after S untimed steps
instead (Taichi starting there with J = 1 and C = 0: the work per step depends on where the particles
are, not on J), e.g. S = 2500 for the fluid piled up on the floor.

``--t-end T`` also runs the 8192-particle scene to time T in Taichi (f32) and jaxmpm (f32 and
f64, ``sim.run`` with its instability check) and prints bulk diagnostics of the final state.

Writes ``benchmarks/results/vs_taichi.csv`` (or ``--csv``).
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np
from _results import write_csv
from _taichi_mpm import BOUND, DT, GRAVITY, E, timed

DEFAULT_CSV = Path(__file__).resolve().parent / "results" / "vs_taichi.csv"
N_GRID = 128  # mpm88's grid; its physics constants are _taichi_mpm's


def parse_args(argv=None):
    p = argparse.ArgumentParser(description="mpm88: Taichi CPU vs jaxmpm, float32, particle-steps per second")
    p.add_argument("--particles", type=int, nargs="+", default=[8192, 32768, 131072])
    p.add_argument("--steps", type=int, default=300, help="timed steps per repeat (default 300)")
    p.add_argument("--warmup", type=int, default=20, help="untimed steps first (compilation; default 20)")
    p.add_argument("--repeats", type=int, default=3, help="timed repeats; the best is reported (default 3)")
    p.add_argument("--quick", action="store_true", help="8192 particles, 100 steps, 2 repeats")
    p.add_argument("--settle", type=int, default=0, metavar="S",
                   help="start both engines from the particles of jaxmpm's scene after S untimed steps (default 0: "
                        "mpm88's start). The default timed window is mpm88's free fall; S = 2500 (t = 0.5) times "
                        "the fluid piled up on the floor, every cell full (Taichi starts there with J = 1, C = 0)")
    p.add_argument("--pause", type=float, default=2.0,
                   help="seconds of idle before each engine's measurement (default 2; see main())")
    p.add_argument("--dtype", nargs="+", choices=["f32", "f64"], default=["f32"],
                   help="precisions to run, each in both engines (default f32)")
    p.add_argument("--csv", default=str(DEFAULT_CSV))
    p.add_argument("--cpu-devices", type=int, default=0,
                   help="start JAX with this many CPU devices, which jaxmpm's steps share their particles among "
                        "where its table says (default: JAX's own count, one)")
    p.add_argument("--t-end", type=float, default=0.0,
                   help="also run 8192 particles to this time in Taichi and jaxmpm (f32, f64); 0 = skip")
    args = p.parse_args(argv)
    if args.quick:
        args.particles, args.steps, args.repeats = [8192], 100, 2
    return args


def import_taichi():
    try:
        import taichi as ti
    except ImportError:
        sys.exit("benchmarks/vs_taichi.py needs Taichi, which jaxmpm does not depend on: pip install taichi")
    return ti


# --------------------------------------------------------------------------------------- Taichi
def taichi_mpm88(ti, x0, v0, steps, warmup, repeats, dtype="f32"):
    """Taichi's mpm88 substep on the CPU backend, in float32 (or float64: ``default_fp``, so every
    field and literal).  Returns (best seconds, x, v)."""
    ti.reset()
    ti.init(arch=ti.cpu, default_fp=ti.f64 if dtype == "f64" else ti.f32, log_level=ti.WARN)
    real = np.float64 if dtype == "f64" else np.float32
    n_particles, n_grid = x0.shape[0], N_GRID
    dx = 1 / n_grid
    dt = DT
    p_rho = 1
    p_vol = (dx * 0.5) ** 2
    p_mass = p_vol * p_rho
    gravity, bound, E_ = GRAVITY, BOUND, E

    x = ti.Vector.field(2, float, n_particles)
    v = ti.Vector.field(2, float, n_particles)
    C = ti.Matrix.field(2, 2, float, n_particles)
    J = ti.field(float, n_particles)
    grid_v = ti.Vector.field(2, float, (n_grid, n_grid))
    grid_m = ti.field(float, (n_grid, n_grid))

    @ti.kernel
    def substep():
        for i, j in grid_m:
            grid_v[i, j] = [0, 0]
            grid_m[i, j] = 0
        for p in x:
            Xp = x[p] / dx
            base = int(Xp - 0.5)
            fx = Xp - base
            w = [0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1) ** 2, 0.5 * (fx - 0.5) ** 2]
            stress = -dt * 4 * E_ * p_vol * (J[p] - 1) / dx**2
            affine = ti.Matrix([[stress, 0], [0, stress]]) + p_mass * C[p]
            for i, j in ti.static(ti.ndrange(3, 3)):
                offset = ti.Vector([i, j])
                dpos = (offset - fx) * dx
                weight = w[i].x * w[j].y
                grid_v[base + offset] += weight * (p_mass * v[p] + affine @ dpos)
                grid_m[base + offset] += weight * p_mass
        for i, j in grid_m:
            if grid_m[i, j] > 0:
                grid_v[i, j] /= grid_m[i, j]
            grid_v[i, j].y -= dt * gravity
            if i < bound and grid_v[i, j].x < 0:
                grid_v[i, j].x = 0
            if i > n_grid - bound and grid_v[i, j].x > 0:
                grid_v[i, j].x = 0
            if j < bound and grid_v[i, j].y < 0:
                grid_v[i, j].y = 0
            if j > n_grid - bound and grid_v[i, j].y > 0:
                grid_v[i, j].y = 0
        for p in x:
            Xp = x[p] / dx
            base = int(Xp - 0.5)
            fx = Xp - base
            w = [0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1.0) ** 2, 0.5 * (fx - 0.5) ** 2]
            new_v = ti.Vector.zero(float, 2)
            new_C = ti.Matrix.zero(float, 2, 2)
            for i, j in ti.static(ti.ndrange(3, 3)):
                offset = ti.Vector([i, j])
                dpos = (offset - fx) * dx
                weight = w[i].x * w[j].y
                g_v = grid_v[base + offset]
                new_v += weight * g_v
                new_C += 4 * weight * g_v.outer_product(dpos) / dx**2
            v[p] = new_v
            x[p] += dt * v[p]
            J[p] *= 1 + dt * new_C.trace()
            C[p] = new_C

    def reset():
        x.from_numpy(x0.astype(real))
        v.from_numpy(v0.astype(real))
        J.fill(1)
        C.fill(0)

    result = timed(ti, substep, reset, steps, warmup, repeats), x.to_numpy(), v.to_numpy()
    ti.reset()  # shut the runtime (and its worker threads) down before anything else is timed
    return result


# --------------------------------------------------------------------------------------- jaxmpm
def jaxmpm_mpm88(setup, steps, warmup, repeats):
    """jaxmpm's mpm88 scene: ``steps`` steps of ``sim.step`` in one jitted ``lax.scan``."""
    import equinox as eqx
    import jax

    @eqx.filter_jit
    def advance(sim, state, dt, n):
        def body(s, _):
            return sim.step(s, dt), None

        return jax.lax.scan(body, state, None, length=n)[0]

    sim, state0 = setup.sim, setup.state
    dt = jax.numpy.asarray(setup.dt, state0.x.dtype)
    jax.block_until_ready(advance(sim, state0, dt, warmup))  # compile for the warm-up length
    jax.block_until_ready(advance(sim, state0, dt, steps))  # and for the timed length
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        final = jax.block_until_ready(advance(sim, state0, dt, steps))
        best = min(best, time.perf_counter() - start)
    return best, np.asarray(final.x), np.asarray(final.v)


def full_run(ti, t_end):
    """mpm88 to ``t_end``: Taichi f32, jaxmpm f32 and f64 (``sim.run``, instability checked)."""
    import jax

    import jaxmpm as jm

    steps = int(round(t_end / DT))
    print(f"\nmpm88, 8192 particles, {steps} steps to t = {steps * DT:g}")
    print(f"{'run':>14} | {'wall s':>7} | {'x_cm':>8} | {'y_cm':>8} | {'KE/m':>8} | {'min x':>7} | {'max x':>7} | "
          f"{'min y':>7} | {'max y':>7}")
    results = {}
    setup = jm.scene("mpm88", dtype="f32")
    x0, v0 = np.asarray(setup.state.x), np.asarray(setup.state.v)
    start = time.perf_counter()
    _, x, v = taichi_mpm88(ti, x0, v0, steps, 0, 1)
    results["Taichi f32"] = time.perf_counter() - start, x, v
    time.sleep(2.0)  # let Taichi's worker threads go idle (see main())
    for dtype in ("f32", "f64"):
        setup = jm.scene("mpm88", dtype=dtype, t_end=steps * DT, frames=10)
        start = time.perf_counter()
        final, _ = setup.run(save_particles=False)
        jax.block_until_ready(final.x)
        results[f"jaxmpm {dtype}"] = time.perf_counter() - start, np.asarray(final.x), np.asarray(final.v)
    for name, (wall, x, v) in results.items():
        c, k = summary(x, v)
        print(f"{name:>14} | {wall:>7.1f} | {c[0]:>8.5f} | {c[1]:>8.5f} | {k:>8.5f} | {x[:, 0].min():>7.4f} | "
              f"{x[:, 0].max():>7.4f} | {x[:, 1].min():>7.4f} | {x[:, 1].max():>7.4f}", flush=True)


def summary(x, v):
    """Centre of mass and kinetic energy per unit particle mass (equal masses)."""
    return x.mean(0), 0.5 * float(np.mean(np.sum(v.astype(np.float64) ** 2, -1)))


def main(argv=None) -> int:
    args = parse_args(argv)
    ti = import_taichi()
    import jax

    if args.cpu_devices:
        jax.config.update("jax_num_cpu_devices", args.cpu_devices)  # before JAX's first computation

    if args.t_end > 0 or "f64" in args.dtype:
        jax.config.update("jax_enable_x64", True)  # for the f64 runs; the f32 runs are cast to f32

    import jaxmpm as jm

    print(f"jax {jax.__version__} ({jax.devices()[0].platform}), taichi {'.'.join(map(str, ti.__version__))}, "
          f"{os.cpu_count()} CPUs, {platform.processor() or platform.machine()}, load {os.getloadavg()[0]:.2f}, "
          f"{len(jax.devices())} JAX device(s)")
    print(f"mpm88: {N_GRID}^2 grid, dt = {DT}; {args.steps} timed steps (best of {args.repeats}) "
          f"after {args.warmup} warm-up steps" + (f", from the particles at step {args.settle}" if args.settle else "")
          + "\n")
    rows = []
    header = f"{'dtype':>5} | {'particles':>9} | {'Taichi p-steps/s':>16} | {'jaxmpm p-steps/s':>16} | " \
             f"{'jaxmpm/Taichi':>13} | {'y_cm Taichi':>11} | {'y_cm jaxmpm':>11} | {'KE/m Taichi':>11} | " \
             f"{'KE/m jaxmpm':>11} | {'devices':>7}"
    print(header)
    print("-" * len(header))
    for dtype, n in [(dtype, n) for dtype in args.dtype for n in args.particles]:
        setup = jm.scene("mpm88", n_particles=n, dtype=dtype)
        if args.settle:  # the particles after S steps, where both engines start
            setup.state, _ = setup.sim.run(setup.state, setup.dt, args.settle, args.settle, save_particles=False)
        x0, v0 = np.asarray(setup.state.x), np.asarray(setup.state.v)
        devices = jm.backend_info(setup.sim, setup.state)["particle_devices"]
        # each engine on a quiet machine: Taichi's CPU worker threads keep both cores busy for a
        # while after its last kernel (measured: jaxmpm timed right after Taichi ran at 0.4-0.6x
        # its own speed), so jaxmpm goes first, Taichi's runtime is shut down after its run, and
        # every measurement waits --pause seconds
        time.sleep(args.pause)
        t_jm, x_jm, v_jm = jaxmpm_mpm88(setup, args.steps, args.warmup, args.repeats)
        time.sleep(args.pause)
        t_ti, x_ti, v_ti = taichi_mpm88(ti, x0, v0, args.steps, args.warmup, args.repeats, dtype)
        rate_ti, rate_jm = n * args.steps / t_ti, n * args.steps / t_jm
        (c_ti, k_ti), (c_jm, k_jm) = summary(x_ti, v_ti), summary(x_jm, v_jm)
        print(f"{dtype:>5} | {n:>9} | {rate_ti:>16.4g} | {rate_jm:>16.4g} | {rate_jm / rate_ti:>13.3f} | "
              f"{c_ti[1]:>11.5f} | {c_jm[1]:>11.5f} | {k_ti:>11.5f} | {k_jm:>11.5f} | {devices:>7}", flush=True)
        rows.append(dict(dtype=dtype, particles=n, grid=f"{N_GRID}x{N_GRID}", steps=args.steps, repeats=args.repeats,
                         taichi_s=t_ti, jaxmpm_s=t_jm, taichi_particle_steps_per_s=rate_ti,
                         jaxmpm_particle_steps_per_s=rate_jm, ratio_jaxmpm_over_taichi=rate_jm / rate_ti,
                         settle=args.settle,
                         y_cm_taichi=float(c_ti[1]), y_cm_jaxmpm=float(c_jm[1]), ke_taichi=k_ti, ke_jaxmpm=k_jm,
                         particle_devices=devices, jax=jax.__version__, taichi=".".join(map(str, ti.__version__)),
                         cpus=os.cpu_count(),
                         load=os.getloadavg()[0]))
    print(f"\nwrote {write_csv(args.csv, list(rows[0]), rows)}")
    if args.t_end > 0:
        full_run(ti, args.t_end)
    return 0


if __name__ == "__main__":
    sys.exit(main())
