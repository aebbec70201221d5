"""Every GPU number of issue 32 in one command: mpm88 and its 3D variant against Taichi, the XPIC/FMPM series
against FLIP, the gradient's cost and the ensembles' throughput, written as a markdown table and a CSV.

    python benchmarks/gpu.py                        # on a GPU: every part at the issue's sizes
    python benchmarks/gpu.py --quick                # on a CPU: the same code at small sizes (under 2 minutes)
    python benchmarks/gpu.py --parts mpm88 schemes --repeats 5 --out /tmp/gpu

Parts (``--parts``, default all), each in particle-steps per second (particles x steps / seconds), the run timed
as the best of ``--repeats`` calls (wall clock, ``jax.block_until_ready``) with the compile time apart:

* ``mpm88``: the ``mpm88`` scene (2D, 128^2 grid, APIC, quadratic B-splines) at 8k, 32k, 131k, 524k and 2.1M
  particles, 500 steps, next to Taichi's mpm88 substep (``_taichi_mpm.py``) from the same particles;
* ``mpm3d``: the same physics in 3D (particles in [0.2, 0.6]^3) at 131k particles on a 64^3 grid and 1M on
  128^3, 100 steps, next to Taichi;
* ``schemes``: FLIP, XPIC(5) and FMPM(2/4/8) per step against FLIP on mpm88 at 131k particles and the 3D
  scene at 1M, at dt = 5e-5 (a quarter of mpm88's: FMPM(k)'s stable time step shrinks with k, and at
  mpm88's 2e-4 FMPM(k >= 4) turns to NaN within 100 steps -- a blown-up run is what made FMPM(8) look like
  23 FLIP steps on the H100, issue 32 item 5, benchmarks/README.md "The series"); every run's final state
  is checked and an unstable one is marked, not compared;
* ``gradient``: d(mean particle height after the rollout) / dE through ``sim.run`` (1000 steps, 8k and 131k
  particles) against the forward run, and a central difference of the forward run as a check;
* ``ensemble``: ``jm.ensemble`` over E (8k particles, 500 steps, 1 to 256 members, strategy "auto")
  against one compiled single rollout (benchmarks/ensemble_throughput.py's).

Beside each jaxmpm run: the particle state's bytes per particle and the compiled program's (arguments,
outputs and XLA's temporaries, ``compiled.memory_analysis()``; issue 32 item 7).  Taichi runs in the same
process when ``taichi`` is importable (CUDA on a GPU, its CPU backend on a CPU; ``--no-taichi`` skips it),
jaxmpm first and Taichi's runtime shut down after each run (its worker threads would slow what follows).
``--quick`` runs every part at small sizes and few steps; ``--smallest`` keeps only each part's first size.
``--kernel xla|pallas|auto`` picks jaxmpm's transfer kernel (``Simulation.with_kernel``; default "auto", the
library's table), ``--sort-every K`` how often the particles are sorted by cell (``Simulation.with_sorting``; 0
never, default "auto", the library's table) and ``--chunk-particles P`` the particles per chunk of a step
(``Simulation.with_chunks``; 0 the whole step, default "auto", the library's table); each row records the kernel,
sorting and chunks its run used (``jm.backend_info``).

Writes ``benchmarks/results/gpu.md`` and ``gpu.csv`` (``--out`` another folder).
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import sys
import time
from pathlib import Path

import jax
from _results import write_csv
from ensemble_throughput import single_rollout, timed
from gradient_cost import compiled

jax.config.update("jax_enable_x64", True)  # the f64 runs; the f32 ones are cast

import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jaxmpm as jm  # noqa: E402
from jaxmpm.run.driver import CAUSES  # noqa: E402
from jaxmpm.run.memory import choose_checkpoint, tree_bytes  # noqa: E402

DEFAULT_OUT = Path(__file__).resolve().parent / "results"
PARTS = ("mpm88", "mpm3d", "schemes", "gradient", "ensemble")
DT = 2e-4  # mpm88's time step (and Taichi's)
SCHEMES_DT = 5e-5  # stable for FMPM(8) on both scenes (see the module docstring)
SCHEMES = (("FLIP", 1, jm.FLIP()), ("XPIC(5)", 5, jm.XPIC(order=5)), ("FMPM(2)", 2, jm.FMPM(order=2)),
           ("FMPM(4)", 4, jm.FMPM(order=4)), ("FMPM(8)", 8, jm.FMPM(order=8)))  # (label, S+S order + 1, scheme)

#: what-if rows of the kernel table: flag -> the Pallas kernel's options, what the row tries
WHAT_IF = (("reduce", {"reduce": True}, "the Pallas kernel with its block reduction before the atomic adds"),
           ("basis", {"factors": False}, "the Pallas kernel reading XLA's per-slot basis W instead of forming the "
                                         "weights from the per-axis factors"),
           ("planar", {"planar": True}, "the Pallas kernel addressing its nodal arrays column by column"),
           ("unroll", {"unroll": True}, "the Pallas kernel with its loop over the stencil's slots unrolled"))

#: part -> sizes and steps; 2D sizes are particle counts, 3D ones (particles, grid cells per axis)
FULL = dict(mpm88=((8192, 32768, 131072, 524288, 2097152), 500), mpm3d=(((131072, 64), (1048576, 128)), 100),
            schemes=((131072, (1048576, 128)), 200), gradient=((8192, 131072), 1000),
            ensemble=((8192, (1, 16, 64, 256)), 500))
QUICK = dict(mpm88=((1024, 4096), 40), mpm3d=(((2048, 16),), 20), schemes=((1024,), 20), gradient=((512,), 40),
             ensemble=((512, (4,)), 40))

FIELDS = ["part", "case", "particles", "grid", "steps", "dtype", "engine", "kernel", "compile_s", "run_s",
          "particle_steps_per_s", "ratio", "ratio_to", "ms_per_step", "state_bytes_per_particle",
          "program_bytes_per_particle", "check", "backend", "device", "jax", "date"]


# ------------------------------------------------------------------------------------------- scenes
SORT_EVERY = "auto"  # --sort-every: steps between sorts of the particles by cell ("auto": the library's table)
CHUNK_PARTICLES = "auto"  # --chunk-particles: particles per chunk of a step (0: whole; "auto": the library's table)
DERIVATIVE_CHUNKS = "auto"  # --derivative-chunk-particles: particles per chunk of a step's derivatives (0: whole)
SETTLE = 0  # --settle: untimed steps before the side-by-side parts' timed window (0: the scene's start, a free fall)


def with_kernel(sim, kernel: str):
    """``sim`` with its transfers on ``kernel`` ("xla", "pallas"), or as the library chooses ("auto"), sorting its
    particles by cell as ``--sort-every`` says and stepping them in chunks as ``--chunk-particles`` does."""
    sim = sim if kernel == "auto" else sim.with_kernel(kernel)
    return sim.with_sorting(SORT_EVERY).with_chunks(CHUNK_PARTICLES).with_derivative_chunks(DERIVATIVE_CHUNKS)


def kernel_of(sim, state) -> str:
    """The transfer kernel ``sim`` steps ``state`` with (``jm.backend_info``), its sorting and chunks if any."""
    info = jm.backend_info(sim, state)
    return (info["kernel"] + (f", sorted/{info['sort_every']}" if info.get("sort_every") else "")
            + (f", chunks/{info['chunk_particles']}" if info.get("chunk_particles") else "")
            + (f", derivative chunks/{info['derivative_chunk_particles']}" if info.get("derivative_chunk_particles")
               else ""))


def mpm88(n: int, dtype: str, scheme=None, dt: float = DT, kernel: str = "auto"):
    """The ``mpm88`` scene at ``n`` particles: (sim, state, dt)."""
    setup = jm.scene("mpm88", n_particles=n, dtype=dtype, scheme=scheme, dt=dt)
    return with_kernel(setup.sim, kernel), setup.state, dt


def mpm3d(n: int, cells: int, dtype: str, scheme=None, dt: float = DT, kernel: str = "auto", seed: int = 0):
    """mpm88's physics in 3D (as ``../shared/gpu/gpu_bench.py`` built it): ``n`` random particles in
    [0.2, 0.6]^3 falling at 1 m/s on a ``cells``^3 grid of the unit cube, volume (dx/2)^3, density 1, the J-fluid
    of E = 400, gravity 9.8 along -y, walls 3 cells wide on every face, APIC (default) and USL.  (sim, state, dt)."""
    dx = 1.0 / cells
    x = np.random.default_rng(seed).random((n, 3)) * 0.4 + 0.2
    particles = jm.Particles(x=x, v=np.tile([0.0, -1.0, 0.0], (n, 1)), volume=np.full(n, (dx * 0.5) ** 3), ppc=2)
    walls = tuple(jm.Wall(face, layers=3) for face in ("x-", "x+", "y-", "y+", "z-", "z+"))
    sim = jm.Simulation(grid=jm.Grid((0.0,) * 3, (1.0,) * 3, (cells,) * 3), shape=jm.QuadraticBSpline(),
                        material=jm.VolumetricFluid(E=400.0, density=1.0), scheme=scheme or jm.APIC(),
                        damping=False, update="USL", boundary=walls, gravity=(0.0, -9.8, 0.0))
    state = sim.init(particles)
    precision = jnp.float32 if dtype == "f32" else jnp.float64
    state = jax.tree_util.tree_map(
        lambda a: a.astype(precision) if isinstance(a, jax.Array) and jnp.issubdtype(a.dtype, jnp.floating) else a,
        state)
    return with_kernel(sim.in_precision(precision), kernel), state, dt


# ------------------------------------------------------------------------------------------- timing
def compile_rollout(sim, state, dt, steps: int):
    """``steps`` steps of ``sim.step`` as one program, compiled ahead of time: (call, compile seconds, program
    bytes) -- ``call()`` runs it from ``state``; the bytes are its arguments, outputs and temporaries, less the
    final state computed in place of the initial one (donated, as ``sim.run`` does with ``donate=True`` and a
    chunked run with its working state).  Each call donates a fresh copy of ``state`` (a device copy, timed
    with the steps: one state's bytes)."""
    (sim_arrays, state_arrays, dt_array), static = eqx.partition((sim, state, jnp.asarray(dt, state.x.dtype)),
                                                                 eqx.is_array)
    shared = (sim_arrays, dt_array)

    def rollout(shared, state_arrays):
        sim, state, dt = eqx.combine((shared[0], state_arrays, shared[1]), static)
        sorting = sim.sorting(state)  # particles sorted by cell every K steps (jaxmpm.run.sorting), or None
        if sorting is None:
            return jax.lax.fori_loop(0, steps, lambda _, s: sim.step(s, dt), state)

        def step(_, carry):
            state, order = sorting.renew(*carry)
            return sim.step(state, dt), order

        state, order = jax.lax.fori_loop(0, steps, step, (state, sorting.start(state)))
        return sorting.in_user_order(state, order)

    program, compile_s = compiled(rollout, shared, state_arrays, donate=(1,))
    memory = program.memory_analysis()

    def call():
        return program(shared, jax.tree_util.tree_map(lambda a: jax.device_put(a, may_alias=False), state_arrays))

    call.program = program  # the compiled program (benchmarks/gpu_profile.py --hlo writes its text)
    return call, compile_s, held_bytes(memory)


def held_bytes(memory) -> float:
    """The bytes a run of a compiled program holds on its device, from XLA's account of it
    (``compiled.memory_analysis()``): its arguments, outputs and temporaries, less the outputs written over
    donated arguments; NaN where the backend gives no account."""
    if memory is None:
        return float("nan")
    return (memory.argument_size_in_bytes + memory.output_size_in_bytes + memory.temp_size_in_bytes
            - memory.alias_size_in_bytes)


def time_rollout(sim, state, dt, steps: int, repeats: int) -> dict:
    """One jaxmpm run timed: compile seconds, best run seconds, bytes per particle, the final state and its check
    ("ok" or the instability's cause)."""
    call, compile_s, program_bytes = compile_rollout(sim, state, dt, steps)
    last = []

    def run():
        last[:] = [call()]
        return last[0]

    _, run_s, _ = timed(run, repeats)
    final = last[0]
    code, particle = sim.instability(final)
    n = int(state.x.shape[0])
    return dict(kernel=kernel_of(sim, state), compile_s=compile_s, run_s=run_s,
                particle_steps_per_s=n * steps / run_s,
                ms_per_step=1e3 * run_s / steps,
                state_bytes_per_particle=tree_bytes(state) / n, program_bytes_per_particle=program_bytes / n,
                check="ok" if int(code) == 0 else f"unstable: {CAUSES[int(code)]} (particle {int(particle)})",
                final=final)


class Taichi:
    """Taichi's mpm88 substep in this process, or a printed reason why not."""

    def __init__(self, enabled: bool):
        self.ti, self.why = None, "--no-taichi"
        if not enabled:
            return
        try:
            import taichi as ti
        except ImportError:
            self.why = "taichi is not importable (pip install taichi; jaxmpm does not depend on it)"
            return
        self.ti, self.why = ti, ""
        self.gpu = jax.default_backend() == "gpu"
        self.version = ".".join(map(str, ti.__version__))

    def run(self, x0, v0, cells: int, steps: int, repeats: int):
        """(best seconds, final x, arch name) of Taichi from ``x0``, ``v0``; None when Taichi is skipped."""
        if self.ti is None:
            return None
        import _taichi_mpm

        ti = self.ti
        ti.init(arch=ti.cuda if self.gpu else ti.cpu, default_fp=ti.f32, offline_cache=False, log_level=ti.WARN)
        arch = ti.lang.impl.current_cfg().arch.name  # Taichi falls back to its CPU backend without CUDA
        try:
            best, x, _ = _taichi_mpm.run(ti, np.asarray(x0, np.float64), np.asarray(v0, np.float64), cells, steps,
                                         warmup=min(20, steps), repeats=repeats)
        finally:
            ti.reset()
        return best, x, arch


# ------------------------------------------------------------------------------------------- parts
def part_side_by_side(part: str, sizes, steps: int, dtype: str, repeats: int, taichi: Taichi, common: dict):
    """mpm88 (2D) or its 3D variant: jaxmpm and Taichi from the same particles."""
    rows = []
    for size in sizes:
        n, cells = (size, 128) if part == "mpm88" else size
        kernel = common.get("kernel", "auto")
        sim, state, dt = mpm88(n, dtype, kernel=kernel) if part == "mpm88" else mpm3d(n, cells, dtype, kernel=kernel)
        if SETTLE:  # both engines start from the particles after SETTLE steps (Taichi with J = 1, C = 0)
            state, _ = sim.run(state, dt, SETTLE, SETTLE, save_particles=False)
        grid = "x".join([str(cells)] * sim.grid.dim)
        r = time_rollout(sim, state, dt, steps, repeats)
        final = r.pop("final")
        y_jm = float(jnp.mean(final.x[:, 1]))
        case = f"{part} {n}" + (f" from step {SETTLE}" if SETTLE else "")
        row = dict(common, part=part, case=case, particles=n, grid=grid, steps=steps, dtype=dtype,
                   engine="jaxmpm", **r)
        row["check"] += f"; y_cm {y_jm:.6f} from {float(jnp.mean(state.x[:, 1])):.6f}"  # the centre of mass's height
        rows.append(row)
        ran = taichi.run(state.x, state.v, cells, steps, repeats)
        if ran is not None:
            best, x_ti, arch = ran
            rate = n * steps / best
            rows.append(dict(common, part=part, case=case, particles=n, grid=grid, steps=steps, dtype="f32",
                             engine=f"Taichi {arch}", kernel="", run_s=best, particle_steps_per_s=rate,
                             ms_per_step=1e3 * best / steps, check=f"y_cm {float(np.mean(x_ti[:, 1])):.6f}"))
            # an unstable run's speed is not compared (see the docstring), nor float64 with Taichi's float32
            if r["check"].startswith("ok") and dtype == "f32":
                row["ratio"], row["ratio_to"] = r["particle_steps_per_s"] / rate, f"Taichi {arch}"
        report(rows[-2:] if ran is not None else rows[-1:])
    return rows


def part_schemes(sizes, steps: int, dtype: str, repeats: int, common: dict):
    """FLIP, XPIC(5), FMPM(2/4/8): cost per step against FLIP, at a time step every one is stable at."""
    rows = []
    for size in sizes:
        scene = "mpm88" if isinstance(size, int) else "mpm3d"
        n, cells = (size, 128) if scene == "mpm88" else size
        per_step = {}
        for label, order, scheme in SCHEMES:
            kernel = common.get("kernel", "auto")
            sim, state, dt = (mpm88(n, dtype, scheme, SCHEMES_DT, kernel) if scene == "mpm88"
                              else mpm3d(n, cells, dtype, scheme, SCHEMES_DT, kernel))
            r = time_rollout(sim, state, dt, steps, repeats)
            r.pop("final")
            per_step[label] = r["run_s"]
            row = dict(common, part="schemes", case=f"{scene} {n}", particles=n,
                       grid="x".join([str(cells)] * sim.grid.dim), steps=steps, dtype=dtype, engine=label,
                       ratio=r["run_s"] / per_step["FLIP"], ratio_to="FLIP", **r)
            if not r["check"].startswith("ok"):  # a blown-up run's speed is not the scheme's (issue 32 item 5)
                row["ratio"] = None
            elif order > 1:  # an order's cost in FLIP steps (the XPIC/FMPM series has order - 1 S+S; aim: <= 0.5)
                row["check"] += f"; per order {(row['ratio'] - 1) / (order - 1):.2f} FLIP"
            rows.append(row)
            report(rows[-1:])
    return rows


def part_gradient(sizes, steps: int, dtype: str, repeats: int, common: dict, checkpoint="auto"):
    """d(mean height after ``steps``)/dE through ``sim.run`` (its ``checkpoint`` policy) against the forward run; a
    central difference."""
    rows = []
    for n in sizes:
        sim, state, dt = mpm88(n, dtype, kernel=common.get("kernel", "auto"))
        dt = jnp.asarray(dt, state.x.dtype)
        every = max(1, steps // 10)

        def loss(E):
            final, _ = jm.set_params(sim, E=E).run(state, dt, steps, every, save_particles=False, progress=False,
                                                   checkpoint=checkpoint)
            return jnp.mean(final.x[:, 1])

        E0 = jnp.asarray(400.0, state.x.dtype)
        forward, forward_compile = compiled(loss, E0)
        gradient, gradient_compile = compiled(jax.grad(loss), E0)
        _, forward_s, _ = timed(lambda: forward(E0), repeats)
        _, gradient_s, _ = timed(lambda: gradient(E0), repeats)
        eps = 1.0  # 0.25 % of E
        difference = (float(forward(E0 + eps)) - float(forward(E0 - eps))) / (2 * eps)
        check = f"dL/dE {float(gradient(E0)):.4g}, central difference {difference:.4g}"
        if checkpoint == "auto":  # the schedule "auto" ran (jaxmpm.run.memory.choose_checkpoint)
            check += "; auto: " + choose_checkpoint(sim, state, dt, steps // every, every)[1]
        base = dict(common, part="gradient", kernel=kernel_of(sim, state), case=f"mpm88 {n}", particles=n,
                    grid="128x128", steps=steps, dtype=dtype)
        rows.append(dict(base, engine="forward", compile_s=forward_compile, run_s=forward_s,
                         particle_steps_per_s=n * steps / forward_s, ms_per_step=1e3 * forward_s / steps))
        rows.append(dict(base, engine=f"gradient (checkpoint={checkpoint})", compile_s=gradient_compile,
                         run_s=gradient_s,
                         particle_steps_per_s=n * steps / gradient_s, ms_per_step=1e3 * gradient_s / steps,
                         ratio=gradient_s / forward_s, ratio_to="forward", check=check))
        report(rows[-2:])
    return rows


def part_ensemble(n: int, batches, steps: int, dtype: str, repeats: int, common: dict):
    """``jm.ensemble`` over E against one compiled single rollout of the same scene."""
    sim, state, dt = mpm88(n, dtype, kernel=common.get("kernel", "auto"))
    dt = jnp.asarray(dt, state.x.dtype)
    base = dict(common, part="ensemble", kernel=kernel_of(sim, state), particles=n, grid="128x128", steps=steps,
                dtype=dtype)
    compile_s, single_s, _ = timed(lambda: single_rollout(sim, state, dt, steps), repeats)
    single = n * steps / single_s
    rows = [dict(base, case="single rollout", engine="single rollout", compile_s=compile_s, run_s=single_s,
                 particle_steps_per_s=single, ratio=1.0, ratio_to="single rollout")]
    report(rows)
    for batch in batches:
        values = jnp.linspace(300.0, 500.0, batch).astype(state.x.dtype)
        def batched(values=values):
            return jm.ensemble(sim, state, dt, steps, steps, params={"E": values}, progress=False)

        compile_s, run_s, _ = timed(batched, repeats)
        rate = batch * n * steps / run_s
        rows.append(dict(base, case=f"{batch} members", engine="jm.ensemble", compile_s=compile_s, run_s=run_s,
                         particle_steps_per_s=rate, ratio=rate / single, ratio_to="single rollout"))
        report(rows[-1:])
    return rows


# ------------------------------------------------------------------------------------------- output
def report(rows) -> None:
    for r in rows:
        ratio = f"  x{r['ratio']:.3g} {r['ratio_to']}" if r.get("ratio") is not None else ""
        compile_s = f"  compile {r['compile_s']:.1f} s" if r.get("compile_s") is not None else ""
        print(f"  {r['part']:8s} {r['case']:16s} {r['engine']:16s} {r['particle_steps_per_s']:10.3e} p-steps/s"
              f"{ratio}{compile_s}  {r.get('check') or ''}", flush=True)


def markdown(rows, header: str) -> str:
    """The rows as one markdown table per part."""
    out = [header, ""]
    for part in PARTS:
        mine = [r for r in rows if r["part"] == part]
        if not mine:
            continue
        out += [f"## {part}", "",
                "| case | engine | grid | steps | particle-steps/s | ms/step | ratio | compile (s) | state B/particle "
                "| program B/particle | check |",
                "|---|---|---|---|---|---|---|---|---|---|---|"]
        for r in mine:
            def number(key, form):
                return "" if r.get(key) is None else format(r[key], form)

            ratio = f"{r['ratio']:.3g}x {r['ratio_to']}" if r.get("ratio") is not None else ""
            engine = f"{r['engine']} [{r['kernel']}]" if r.get("kernel") else r["engine"]
            out.append(f"| {r['case']} | {engine} | {r['grid']} | {r['steps']} "
                       f"| {number('particle_steps_per_s', '.3g')} | {number('ms_per_step', '.3g')} | {ratio} "
                       f"| {number('compile_s', '.1f')} "
                       f"| {number('state_bytes_per_particle', '.0f')} | {number('program_bytes_per_particle', '.0f')} "
                       f"| {r.get('check') or ''} |")
        out.append("")
    return "\n".join(out)


def _auto_or_int(value: str):
    """A command-line value: "auto" or an integer."""
    return value if value == "auto" else int(value)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--parts", nargs="+", choices=PARTS, default=list(PARTS))
    parser.add_argument("--quick", action="store_true", help="small sizes and few steps (a CPU runs it in < 2 min)")
    parser.add_argument("--smallest", action="store_true", help="only the first size of each part")
    parser.add_argument("--sizes", nargs="+", type=int, default=None, metavar="N",
                        help="only these particle counts of each part (default: all of the part's sizes)")
    parser.add_argument("--dtype", choices=("f32", "f64"), default="f32", help="jaxmpm's precision (Taichi: f32)")
    parser.add_argument("--repeats", type=int, default=None, help="timed calls, best kept (default 3; --quick 2)")
    parser.add_argument("--no-taichi", dest="taichi", action="store_false", help="skip Taichi")
    parser.add_argument("--kernel", choices=("auto", "xla", "pallas"), default="auto",
                        help="jaxmpm's transfer kernel (Simulation(kernel=...)); default auto: the library's table")
    for flag, options, text in WHAT_IF:
        parser.add_argument(f"--{flag}", action="store_true",
                            help=f"{text} (PallasKernel({', '.join(f'{k}={v}' for k, v in options.items())}): a row "
                                 "put first in the library's kernel table for this run; implies --kernel auto)")
    parser.add_argument("--block", type=int, default=None,
                        help="particles per program of the Pallas kernel (PallasKernel(block=...); default: its own, "
                             "128; a what-if row as --reduce)")
    parser.add_argument("--stencil-sum", choices=("adds", "reduce"), default=None,
                        help="how the GPU policy sums over the stencil's slots (jaxmpm.transfer.backend.STENCIL_SUM; "
                             "default: the library's entry)")
    parser.add_argument("--warps", type=int, default=None,
                        help="warps per program of the Pallas kernel on Triton (default: the kernel module's WARPS)")
    parser.add_argument("--checkpoint", default="auto", type=lambda v: {"true": True, "false": False}.get(v.lower(), v),
                        help="the gradient part's sim.run(checkpoint=...): auto (default), true, false, states, "
                             "low_memory")
    parser.add_argument("--sort-every", default="auto", type=_auto_or_int, metavar="K",
                        help="sort the particles by cell every K steps (0: never; default auto: the library's table)")
    parser.add_argument("--chunk-particles", default="auto", type=_auto_or_int, metavar="P",
                        help="step the particles in chunks of about P (Simulation.with_chunks; 0: the whole step; "
                             "default auto: the library's table)")
    parser.add_argument("--derivative-chunk-particles", default="auto", type=_auto_or_int, metavar="P",
                        help="the gradient's steps differentiated in chunks of about P, each recomputed in the reverse "
                             "pass (Simulation.with_derivative_chunks; 0: the whole step's; default auto: the "
                             "library's table)")
    parser.add_argument("--settle", type=int, default=0, metavar="S",
                        help="mpm88 and mpm3d timed from the particles after S untimed steps (default 0: the scene's "
                             "start, where the timed window is a free fall; 2500: the fluid piled up on the floor, "
                             "denser cells, more atomic adds to one node)")
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT, help="folder of gpu.md and gpu.csv")
    args = parser.parse_args(argv)
    global SORT_EVERY, CHUNK_PARTICLES, DERIVATIVE_CHUNKS, SETTLE
    SORT_EVERY, CHUNK_PARTICLES, SETTLE = args.sort_every, args.chunk_particles, args.settle
    DERIVATIVE_CHUNKS = args.derivative_chunk_particles
    from jaxmpm.transfer import backend
    from jaxmpm.transfer.kernels import pallas

    if args.warps:
        pallas.WARPS = args.warps
    if args.stencil_sum:
        backend.STENCIL_SUM = dict(backend.STENCIL_SUM, gpu=args.stencil_sum)
    variant = " ".join(f"--{flag}" for flag, _, _ in WHAT_IF if getattr(args, flag))
    variant += "".join(f" --{name.replace('_', '-')} {getattr(args, name)}"
                       for name in ("block", "warps", "stencil_sum") if getattr(args, name))
    options = {k: v for flag, pairs, _ in WHAT_IF if getattr(args, flag) for k, v in pairs.items()}
    options.update({"block": args.block} if args.block else {})
    if options:  # what-if row: how whoever measures tries a table entry before writing it
        row = ("pallas", options, f"benchmarks/gpu.py {variant.strip()}")
        backend.KERNEL_TABLE = ((("cpu", None, None, None, None), row), (("gpu", None, None, None, None), row))
        args.kernel = "auto"
    sizes = QUICK if args.quick else FULL
    repeats = args.repeats or (2 if args.quick else 3)
    jm.compilation_cache(False)  # compile times: XLA compiling, not a program read back from disk

    device = jax.devices()[0]
    common = dict(kernel=args.kernel, backend=jax.default_backend(),
                  device=getattr(device, "device_kind", str(device)),
                  jax=jax.__version__, date=datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"))
    taichi = Taichi(args.taichi)
    header = (f"# benchmarks/gpu.py{' --quick' if args.quick else ''}: {common['device']} ({common['backend']}), "
              f"jax {common['jax']}, jaxmpm {jm.__version__}, "
              f"Taichi {taichi.version if taichi.ti else 'skipped: ' + taichi.why}, {common['date']}\n\n"
              f"jaxmpm {args.dtype}, --kernel {args.kernel}{' ' + variant if variant else ''}, "
              f"--sort-every {args.sort_every} --chunk-particles {args.chunk_particles} "
              f"--derivative-chunk-particles {args.derivative_chunk_particles} "
              f"(the kernel each run used in brackets), Taichi f32; "
              f"best of {repeats}; {os.cpu_count()} CPUs, {platform.machine()}, "
              f"load {os.getloadavg()[0]:.2f} at the start.")
    print(header, flush=True)
    if taichi.ti is None:
        print(f"Taichi skipped: {taichi.why}", flush=True)

    def first(values, sized=True):
        if args.sizes and sized:  # a size is a particle count, or (particles, cells) in 3D
            values = tuple(v for v in values if (v[0] if isinstance(v, tuple) else v) in args.sizes)
        return values[:1] if args.smallest else values

    rows = []
    for part in args.parts:
        values, steps = sizes[part]
        started = time.perf_counter()
        if part in ("mpm88", "mpm3d"):
            rows += part_side_by_side(part, first(values), steps, args.dtype, repeats, taichi, common)
        elif part == "schemes":
            rows += part_schemes(first(values), steps, args.dtype, repeats, common)
        elif part == "gradient":
            rows += part_gradient(first(values), steps, args.dtype, repeats, common, args.checkpoint)
        else:
            n, batches = values
            rows += part_ensemble(n, first(batches, sized=False), steps, args.dtype, repeats, common)
        print(f"  ({part}: {time.perf_counter() - started:.0f} s in all)", flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    csv_path = write_csv(args.out / "gpu.csv", FIELDS, [{k: r.get(k) for k in FIELDS} for r in rows])
    md_path = args.out / "gpu.md"
    md_path.write_text(markdown(rows, header + f" Load {os.getloadavg()[0]:.2f} at the end."))
    print(f"wrote {md_path} and {csv_path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
