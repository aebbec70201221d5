"""Where the compile time goes: trace, lowering and XLA compilation of each program a user runs,
per shipped scene, with the size of what is compiled, the steady-state run and the warm-cache cost
(issue 30).

Programs, per scene (float64):

* ``rollout``: the jitted rollout ``sim.run`` compiles (``sim.run`` traced inside ``jax.jit``, with the
  simulation's arrays, the state and dt as arguments, as ``sim.run``'s own jit has them);
* ``gradient``: ``jax.grad`` of loss = sum over the saved frames of m v^2 (heat1d: of T^2) with
  respect to a material parameter (``E``; heat1d: ``conductivity``), through ``jm.set_params`` and
  ``sim.run``;
* ``ensemble``: ``jm.ensemble`` of 4 members with different values of that parameter (its default
  strategy: on the CPU the members of large scenes run one after another in the program);
* ``calibrate``: one ``jm.calibrate`` update with its default optimiser (Adam; the update's code
  is repeated here so that it can be staged, with the parameter log-transformed as calibrate does);
* ``step`` and ``transpose`` (only when named in ``--programs``): one step of the scene, every float of
  the state, the simulation's arrays and dt in and out, and that step's pullback alone, fed the residuals
  a forward pass hands it (as ``step_adjoint.py``'s "transpose alone").  A rollout's gradient program
  holds the rollout (the forward pass), the step once more (recomputed in the backward pass) and its
  transpose, so with both named the summary prints 1 + (step + transpose) / rollout in XLA compile CPU
  seconds next to the gradient's ratio: what its pieces cost to compile on their own.

Each (scene, program) runs in a fresh process (no tracing or compilation shared between programs),
with JAX's persistent compilation cache in a new temporary folder, and then once more in a second
process with that cache primed.  Reported per row:

* ``trace_s``, ``lower_s``, ``compile_s``: wall seconds of ``jax.jit(f).trace(*args)``, ``.lower()``,
  ``.compile()``, ``first_call_s`` their sum; the same as CPU seconds of the process (``*_cpu_s``:
  steadier than wall time on a loaded machine; XLA's compilation may use more than one thread);
* ``jaxpr_eqns`` (equations of the traced jaxpr, sub-jaxprs included), ``stablehlo_ops`` (lowered
  module) and ``hlo_instructions`` (XLA's optimised HLO, ``compiled.as_text()``): the program's size;
  ``hlo_op_counts``: its fusions, while loops, conditionals, scatters and gathers (copies of a
  step's scatter show duplicated subgraphs);
* ``flops`` and ``bytes_accessed`` from ``compiled.cost_analysis()``.  XLA counts a while loop's
  body once, not once per iteration (bar's rollout: 7162 flops at 20 and 100 steps, 7164 at
  2000), so these are about one time step's (plus one saved frame's); ``flops_vs_rollout`` is the
  program's flops over the scene's rollout: for the gradient, its per-step flops against the
  forward's (for an ensemble, members run in a loop count once);
* ``run_s``: the steady state, best of ``--repeat`` calls after the first;
* ``warm_s``: trace + lower + compile in the second process, where the compilation is a cache
  load (``warm_compile_s``); ``warm_hits``: cache hits it counted (1 = the program came from disk).

Then it prints, per scene, gradient compile / rollout compile (the issue's target: <= 2), and
(unless ``--no-recompiles``) which changes of a run recompile: in one process, after a
first run, each change (a new E, beta or dt, another step count, the scene built again, ...) is
run and the XLA compilations it triggers are counted (``jax.monitoring``).

    python benchmarks/compile_time.py                        # every scene and program (~15 min, 2 cores)
    python benchmarks/compile_time.py --quick                # 20 steps, 1 repeat, no XPIC(8) bar
    python benchmarks/compile_time.py --scenes bar --programs rollout gradient --steps 10
    python benchmarks/compile_time.py --scenes bar --programs gradient --checkpoint False --adjoint autodiff
    python benchmarks/compile_time.py --programs rollout gradient --fast-compile --no-warm --no-recompiles
    python benchmarks/compile_time.py --programs rollout gradient step transpose --no-warm --no-recompiles

``--checkpoint`` (default ``auto``, what ``sim.run`` picks: one level, ``"states"``, on the CPU for these
scenes; the tables before 2026-11-28 used ``True``) and ``--adjoint`` set ``sim.run``'s checkpoint and the
simulation's adjoint in the gradient and calibrate programs (columns ``checkpoint``, ``adjoint``); XLA_FLAGS and
JAX_DISABLE_MOST_OPTIMIZATIONS in the environment reach the measuring processes.  ``--fast-compile`` compiles the
gradient and calibrate programs with ``jm.compiler_options(fast_compile=True)`` (column ``options``), the rollout
and ensemble as ``sim.run`` and ``jm.ensemble`` do.

On a shared machine compare the CPU-second columns and ratios from one run; each row has the load
average.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))  # _results, also when this file is loaded by path (tests)
from _results import CHECKPOINTS  # noqa: E402  (plain Python: this process stays free of jax)

DEFAULT_CSV = HERE / "results" / "compile_time.csv"

#: name -> (jm.scene name, options, steps, parameter differentiated)
SCENES = {
    "bar": ("bar", {"scheme": "xpic:2"}, 2000, "E"),
    "bar_xpic8": ("bar", {"scheme": "xpic:8"}, 2000, "E"),
    "disks": ("disks", {}, 500, "E"),
    "disks_contact": ("disks", {"contact": "frictionless"}, 500, "E"),
    "mpm88": ("mpm88", {}, 200, "E"),
    "rings": ("rings", {"spacing": 0.25}, 100, "E"),  # reduced: 2 832 particles instead of 17 608
    "cylinder": ("cylinder", {}, 500, "E"),
    "heat1d": ("heat1d", {}, 400, "conductivity"),
}
QUICK_LEFT_OUT = ("bar_xpic8",)
# sim.run's checkpoint options
PROGRAMS = ("rollout", "gradient", "ensemble", "calibrate", "step", "transpose")
DEFAULT_PROGRAMS = PROGRAMS[:4]
ENSEMBLE_MEMBERS = 4
FRAMES = 10  # saved frames per run (plus the initial one)
FIELDS = ["scene", "program", "particles", "steps", "checkpoint", "adjoint", "options", "trace_s", "lower_s",
          "compile_s", "first_call_s", "trace_cpu_s", "lower_cpu_s", "compile_cpu_s", "first_call_cpu_s", "jaxpr_eqns",
          "stablehlo_ops", "hlo_instructions", "hlo_op_counts", "flops", "bytes_accessed", "flops_vs_rollout", "run_s",
          "warm_trace_s", "warm_lower_s", "warm_compile_s", "warm_s", "warm_hits", "load_1min", "jax", "cpus"]
RECOMPILE_FIELDS = ["change", "compiles", "compile_s", "programs", "load_1min", "jax", "cpus"]


# ---------------------------------------------------------------------------------------------
# worker: one (scene, program) in this process


def _count_eqns(jaxpr) -> int:
    """Equations of a jaxpr, those of its sub-jaxprs (scan, cond, pjit, custom_vjp bodies) included."""
    from jax.extend.core import ClosedJaxpr, Jaxpr

    def subs(value):
        if isinstance(value, ClosedJaxpr):
            yield value.jaxpr
        elif isinstance(value, Jaxpr):
            yield value
        elif isinstance(value, (tuple, list)):
            for v in value:
                yield from subs(v)

    total = 0
    for eqn in jaxpr.eqns:
        total += 1
        for value in eqn.params.values():
            total += sum(_count_eqns(j) for j in subs(value))
    return total


_INSTRUCTION = re.compile(r"^\s+(ROOT\s+)?%?[\w.\-]+ = ")


def _count_instructions(text: str) -> int:
    """Instructions (``name = op(...)`` lines) of an HLO or StableHLO module's text."""
    return sum(1 for line in text.splitlines() if _INSTRUCTION.match(line))


def _program(name: str, program: str, steps: int, checkpoint="auto", adjoint=None):
    """(function, args, steps, particles) of one program of scene ``name``; the function is pure in its
    array args."""
    import equinox as eqx
    import jax
    import jax.numpy as jnp
    import optax

    import jaxmpm as jm
    from jaxmpm.run.calibrate import _transform

    scene_name, options, _, param = SCENES[name]
    setup = jm.scene(scene_name, **options)
    sim, state = setup.sim, setup.state
    dt = jnp.asarray(setup.dt, state.x.dtype)
    save_every = max(1, steps // FRAMES)
    steps = save_every * (steps // save_every)
    n = int(state.x.shape[0])
    sim_dyn, sim_static = eqx.partition(sim, eqx.is_array)
    value = jnp.asarray(jm.get_params(sim, param)[param], state.x.dtype)

    def run(sim_dyn, state, dt):
        return eqx.combine(sim_dyn, sim_static).run(state, dt, steps, save_every)

    def loss(p, sim_dyn, state, dt):
        model = jm.set_params(eqx.combine(sim_dyn, sim_static), **{param: p})
        model = model if adjoint is None else model.with_adjoint(adjoint)
        _, history = model.run(state, dt, steps, save_every, checkpoint=checkpoint)
        if param == "conductivity":
            return jnp.sum(history.fields["temperature"] ** 2)
        return jnp.sum(state.mass[None, :, None] * history.v ** 2)

    if program == "rollout":
        return run, (sim_dyn, state, dt), steps, n
    if program in ("step", "transpose"):  # the pieces a gradient program holds besides the rollout
        floats, rest = eqx.partition(state, eqx.is_inexact_array)

        def step(d, sim_dyn, dt):  # one step, every float of the state, the simulation's arrays and dt in and out
            model = eqx.combine(sim_dyn, sim_static)
            model = model if adjoint is None else model.with_adjoint(adjoint)
            return eqx.partition(model.step(eqx.combine(d, rest), dt), eqx.is_inexact_array)[0]

        if program == "step":
            return step, (floats, sim_dyn, dt), 1, n
        # the step's pullback alone: fed the residuals a forward pass hands it, no forward work in it
        pullback = jax.jit(lambda *a: jax.vjp(step, *a)[1])(floats, sim_dyn, dt)
        ones = jax.tree_util.tree_map(jnp.ones_like, floats)
        return (lambda pullback, cotangent: pullback(cotangent)), (pullback, ones), 1, n
    if program == "gradient":
        return jax.grad(loss), (value, sim_dyn, state, dt), steps, n
    if program == "ensemble":
        def ensemble(values, sim_dyn, state):
            return jm.ensemble(eqx.combine(sim_dyn, sim_static), state, setup.dt, steps, save_every,
                               params={param: values})
        return ensemble, (value * jnp.linspace(0.9, 1.1, ENSEMBLE_MEMBERS), sim_dyn, state), steps, n
    if program == "calibrate":  # jm.calibrate's update (jaxmpm/run/calibrate.py) with optax.adam(0.05)
        forward, inverse = _transform("positive")
        optimizer = optax.adam(0.05)
        raw = {param: inverse(value)}
        opt_state = jax.tree_util.tree_map(lambda a: jnp.asarray(a, dtype=a.dtype) if hasattr(a, "dtype") else a,
                                           optimizer.init(raw))

        def update(r, s, sim_dyn, state, dt):
            def raw_loss(rr):
                return loss(forward(rr[param]), sim_dyn, state, dt)

            value, grads = jax.value_and_grad(raw_loss)(r)
            with jax.numpy_dtype_promotion("standard"):
                updates, s = optimizer.update(grads, s, r, value=value, grad=grads, value_fn=raw_loss)
            return optax.apply_updates(r, updates), s, value
        return update, (raw, opt_state, sim_dyn, state, dt), steps, n
    raise ValueError(program)


def _op_counts(text: str) -> str:
    """How many of the ops that show duplicated subgraphs and loops an HLO module's text holds."""
    ops = ("fusion", "while", "conditional", "scatter", "gather")
    return " ".join(f"{op}={len(re.findall(rf' {op}[(]', text))}" for op in ops)


def measure(name: str, program: str, steps: int, repeat: int, timed_run: bool, checkpoint="auto",
            adjoint=None, fast_compile: bool = False) -> dict:
    """Stage times, sizes and costs of one program, compiled in this process (``fast_compile``: a gradient
    or calibrate program with ``jm.compiler_options(fast_compile=True)``)."""
    import jax

    import jaxmpm as jm

    hits = []
    jax.monitoring.register_event_listener(
        lambda event, **kw: hits.append(event) if event == "/jax/compilation_cache/cache_hits" else None)
    fn, args, steps, particles = _program(name, program, steps, checkpoint, adjoint)
    jax.block_until_ready(args)
    fast = fast_compile and program in ("gradient", "calibrate")
    jitted = jax.jit(fn, compiler_options=jm.compiler_options(fast_compile=True)) if fast else jax.jit(fn)
    hits.clear()
    t0, c0 = time.perf_counter(), time.process_time()
    traced = jitted.trace(*args)
    t1, c1 = time.perf_counter(), time.process_time()
    lowered = traced.lower()
    t2, c2 = time.perf_counter(), time.process_time()
    compiled = lowered.compile()
    t3, c3 = time.perf_counter(), time.process_time()
    cost = compiled.cost_analysis()
    text = compiled.as_text()
    cost = (cost[0] if isinstance(cost, (list, tuple)) else cost) or {}
    row = dict(scene=name, program=program, particles=particles, steps=steps, checkpoint=str(checkpoint),
               adjoint=adjoint or "default", options="fast_compile" if fast else "default",
               trace_s=t1 - t0, lower_s=t2 - t1, compile_s=t3 - t2, trace_cpu_s=c1 - c0, lower_cpu_s=c2 - c1,
               compile_cpu_s=c3 - c2, first_call_s=t3 - t0, first_call_cpu_s=c3 - c0,
               jaxpr_eqns=_count_eqns(traced.jaxpr.jaxpr), stablehlo_ops=_count_instructions(lowered.as_text()),
               hlo_instructions=_count_instructions(text), hlo_op_counts=_op_counts(text),
               flops=float(cost.get("flops", float("nan"))),
               bytes_accessed=float(cost.get("bytes accessed", float("nan"))), hits=len(hits))
    if timed_run:
        jax.block_until_ready(compiled(*args))
        best = float("inf")
        for _ in range(repeat):
            start = time.perf_counter()
            jax.block_until_ready(compiled(*args))
            best = min(best, time.perf_counter() - start)
        row["run_s"] = best
    return row


def worker(args) -> None:
    import jax

    jax.config.update("jax_enable_x64", True)
    jax.config.update("jax_compilation_cache_dir", args.cache)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    row = measure(args.worker[0], args.worker[1], args.steps, args.repeat, not args.warm,
                  CHECKPOINTS[args.checkpoint], args.adjoint, args.fast_compile)
    print("RESULT " + json.dumps(row), flush=True)


# ---------------------------------------------------------------------------------------------
# which changes recompile (one process)


def recompiles(steps: int) -> list[dict]:
    """After a first ``sim.run`` of bar (XPIC(2)), the XLA compilations each change triggers."""
    import jax
    import jax.numpy as jnp

    jax.config.update("jax_enable_x64", True)
    import jaxmpm as jm

    jm.compilation_cache(False)  # XLA's compile seconds, not programs read back from the persistent cache
    compiles = []
    jax.monitoring.register_event_duration_secs_listener(
        lambda event, secs, **kw: compiles.append((kw.get("fun_name", "?"), secs))
        if event == "/jax/core/compile/backend_compile_duration" else None)

    rows = []

    def record(change, action, warmup=None):
        if warmup is not None:
            warmup()
        compiles.clear()
        jax.block_until_ready(action())
        names = sorted({n for n, s in compiles if s >= 0.1})
        small = sum(1 for _, s in compiles if s < 0.1)
        programs = " ".join(names) + (f" (+{small} under 0.1 s)" if small else "")
        rows.append(dict(change=change, compiles=len(compiles), compile_s=sum(s for _, s in compiles),
                         programs=programs))
        print(f"| {change} | {len(compiles)} | {rows[-1]['compile_s']:.2f} | {programs} |", flush=True)

    setup = jm.scene("bar", scheme="xpic:2")
    sim, state, dt = setup.sim, setup.state, setup.dt
    save = max(1, steps // FRAMES)

    def run(model=sim, dt=dt, steps=steps, state=state):
        return model.run(state, dt, steps, save)[0].v

    print("| change (after a first run) | XLA compilations | compile s | programs compiled |\n|---|---|---|---|")
    record("first sim.run (bar, XPIC(2))", run)
    record("same run again", run)
    record("set_params(E=2 E)", lambda: run(jm.set_params(sim, E=2 * float(jm.get_params(sim, "E")["E"]))))
    record("set_params(beta=0.5)", lambda: run(jm.set_params(sim, beta=0.5)))
    record("dt / 2", lambda: run(dt=dt / 2))
    record(f"steps {steps} -> {2 * steps}", lambda: run(steps=2 * steps))
    record("jm.scene('bar') built again, same options", lambda: run(jm.scene("bar", scheme="xpic:2").sim))
    record("jm.scene('bar', E=200) (a scene option)", lambda: run(jm.scene("bar", scheme="xpic:2", E=200.0).sim))
    record("jm.scene('bar', cfl=0.05) (smaller dt)", lambda: (lambda s: run(s.sim, dt=s.dt))(
        jm.scene("bar", scheme="xpic:2", cfl=0.05)))
    record("float32 state (cast)", lambda: run(state=jm.scenes.cast_state(state, jnp.float32)))

    def grad_at(model, e):
        return jax.grad(lambda p: jnp.sum(jm.set_params(model, E=p).run(state, dt, steps, save)[1].v ** 2))(e)

    record("jax.grad through sim.run", lambda: grad_at(sim, 100.0))
    record("jax.grad again at another E", lambda: grad_at(sim, 150.0))
    record("jm.ensemble (4 E)",
           lambda: jm.ensemble(sim, state, dt, steps, save, params={"E": jnp.linspace(90, 110, 4)}))
    record("jm.ensemble again, other E values",
           lambda: jm.ensemble(sim, state, dt, steps, save, params={"E": jnp.linspace(80, 120, 4)}))
    record(f"jm.ensemble, steps {steps} -> {2 * steps} (vmapped)",
           lambda: jm.ensemble(sim, state, dt, 2 * steps, save, params={"E": jnp.linspace(80, 120, 4)}))
    record("jm.ensemble(strategy='sequential') (single runs on the CPU)",
           lambda: jm.ensemble(sim, state, dt, steps, save, params={"E": jnp.linspace(80, 120, 4)},
                               strategy="sequential"))
    record(f"the same, steps {steps} -> {2 * steps}",
           lambda: jm.ensemble(sim, state, dt, 2 * steps, save, params={"E": jnp.linspace(80, 120, 4)},
                               strategy="sequential"))

    def loss(p):
        return jnp.sum(jm.set_params(sim, **p).run(state, dt, steps, save)[1].v ** 2)

    def calibrate():
        return jnp.asarray(jm.calibrate(loss, {"E": 100.0}, steps=1).losses)

    record("jm.calibrate(loss, steps=1)", calibrate)
    record("jm.calibrate(loss, steps=1) again, the same loss function", calibrate)

    def calibrate_free(name):
        return lambda: jnp.asarray(jm.calibrate(loss, {"E": 100.0, "beta": 0.5}, steps=1, free=name).losses)

    record("jm.calibrate(loss, {E, beta}, free='E')", calibrate_free("E"))
    record("the same with free='beta', then free=None (both)", lambda: (calibrate_free("beta")(),
                                                                       calibrate_free(None)()))

    def run_scene(name, t=None, **options):
        s = jm.scene(name, **options)
        return s.sim.run(s.state, s.dt, 10, 10)[1 if t else 0].time

    # numbers that were static fields: the contact's separation and specified normal, and scenes built again
    # (heat1d's initial temperature and the cylinder's traction were lambdas, slide's gravity ramp a static float)
    disks = jm.scene("disks", contact="frictionless")
    record("disks contact: first run", lambda: disks.sim.run(disks.state, disks.dt, 10, 10)[0].v)
    record("disks contact: jm.scene built again", lambda: (lambda s: s.sim.run(s.state, s.dt, 10, 10)[0].v)(
        jm.scene("disks", contact="frictionless")))
    record("disks contact: separation=0.5", lambda: (lambda s: s.sim.run(s.state, s.dt, 10, 10)[0].v)(
        jm.scene("disks", contact="frictionless", separation=0.5)))
    record("disks contact: normal=(1, 1) (a vector: another rule)",
           lambda: run_scene("disks", contact="frictionless", normal=(1.0, 1.0)))
    record("disks contact: normal=(1, 0.8)", lambda: run_scene("disks", contact="frictionless", normal=(1.0, 0.8)))
    heat = jm.scene("heat1d")
    record("heat1d: first run", lambda: heat.sim.run(heat.state, heat.dt, 10, 10)[1].time)
    record("heat1d: jm.scene built again", lambda: (lambda s: s.sim.run(s.state, s.dt, 10, 10)[1].time)(
        jm.scene("heat1d")))
    record("heat1d: amplitude=2 (another initial profile)", lambda: run_scene("heat1d", t=True, amplitude=2.0))
    record("cylinder: first run", lambda: run_scene("cylinder"))
    record("cylinder: jm.scene built again", lambda: run_scene("cylinder"))
    record("slide: ramp=0.05, first run", lambda: run_scene("slide", ramp=0.05))
    record("slide: ramp=0.1", lambda: run_scene("slide", ramp=0.1))
    return rows


# ---------------------------------------------------------------------------------------------
# driver


def _environment():
    import jax

    return dict(jax=jax.__version__, cpus=os.cpu_count())


def _worker_run(scene, program, steps, repeat, cache, warm, checkpoint, adjoint, fast_compile=False) -> dict:
    cmd = [sys.executable, __file__, "--worker", scene, program, "--steps", str(steps), "--repeat", str(repeat),
           "--cache", cache, "--checkpoint", checkpoint] + (["--adjoint", adjoint] if adjoint else []) + \
        (["--warm"] if warm else []) + (["--fast-compile"] if fast_compile else [])
    out = subprocess.run(cmd, capture_output=True, text=True)
    results = [line[7:] for line in out.stdout.splitlines() if line.startswith("RESULT ")]
    if out.returncode or not results:
        raise RuntimeError(f"{' '.join(cmd)} failed:\n{out.stderr[-3000:]}")
    return json.loads(results[-1])


def _print_row(r) -> None:
    print(f"| {r['scene']} | {r['program']} | {r['particles']} | {r['steps']} | {r['trace_cpu_s']:.2f} | "
          f"{r['lower_cpu_s']:.2f} | {r['compile_cpu_s']:.2f} | {r['compile_s']:.2f} | {r['jaxpr_eqns']} | "
          f"{r['stablehlo_ops']} | "
          f"{r['hlo_instructions']} | {r['flops']:.3g} | {r['bytes_accessed']:.3g} | {r['flops_vs_rollout']:.2f} | "
          f"{r['run_s']:.3f} | {r['warm_s']:.2f} ({r['warm_hits']}) | {r['load_1min']:.1f} |", flush=True)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="20 steps, 1 repeat, the XPIC(8) bar left out")
    parser.add_argument("--scenes", nargs="+", choices=list(SCENES), default=None)
    parser.add_argument("--programs", nargs="+", choices=PROGRAMS, default=list(DEFAULT_PROGRAMS))
    parser.add_argument("--steps", type=int, default=None, help="steps of every run (default: the scene's)")
    parser.add_argument("--repeat", type=int, default=None, help="timed calls of each program (default 3)")
    parser.add_argument("--checkpoint", choices=list(CHECKPOINTS), default="auto",
                        help="sim.run's checkpoint in the gradient and calibrate programs (default auto)")
    parser.add_argument("--adjoint", choices=["structured", "autodiff"], default=None,
                        help="Simulation.with_adjoint in the gradient and calibrate programs (default: the scene's)")
    parser.add_argument("--no-warm", action="store_true", help="skip the second, warm-cache process")
    parser.add_argument("--fast-compile", action="store_true",
                        help="compile the gradient and calibrate programs with jm.compiler_options(fast_compile=True)")
    parser.add_argument("--no-recompiles", action="store_true", help="skip the recompilation count")
    parser.add_argument("--csv", default=str(DEFAULT_CSV))
    parser.add_argument("--worker", nargs=2, metavar=("SCENE", "PROGRAM"), help=argparse.SUPPRESS)
    parser.add_argument("--cache", help=argparse.SUPPRESS)
    parser.add_argument("--warm", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.worker:
        args.steps = args.steps or SCENES[args.worker[0]][2]
        args.repeat = args.repeat or 3
        worker(args)
        return 0
    repeat = args.repeat or (1 if args.quick else 3)
    scenes = args.scenes or [s for s in SCENES if not (args.quick and s in QUICK_LEFT_OUT)]
    env = _environment()
    print(f"jax {env['jax']}, {env['cpus']} CPUs, python {platform.python_version()}; load {os.getloadavg()}")
    print("| scene | program | particles | steps | trace CPU s | lower CPU s | XLA compile CPU s | "
          "XLA compile wall s | jaxpr eqns | StableHLO ops | HLO instructions | flops | bytes | flops / rollout's | "
          "run s | warm-cache s (hits) | load |")
    print("|---" * 17 + "|")
    rows = []
    for scene in scenes:
        steps = args.steps or (20 if args.quick else SCENES[scene][2])
        rollout_flops = None
        for program in args.programs:
            with tempfile.TemporaryDirectory(prefix="jaxmpm-compile-time-") as cache:
                load = os.getloadavg()[0]
                r = _worker_run(scene, program, steps, repeat, cache, False, args.checkpoint, args.adjoint,
                                args.fast_compile)
                r.pop("hits")
                if not args.no_warm:
                    w = _worker_run(scene, program, steps, repeat, cache, True, args.checkpoint, args.adjoint,
                                    args.fast_compile)
                    r.update(warm_trace_s=w["trace_s"], warm_lower_s=w["lower_s"], warm_compile_s=w["compile_s"],
                             warm_s=w["first_call_s"], warm_hits=w["hits"])
                else:
                    r.update(warm_trace_s=float("nan"), warm_lower_s=float("nan"), warm_compile_s=float("nan"),
                             warm_s=float("nan"), warm_hits=0)
            if program == "rollout":
                rollout_flops = r["flops"]
            r.update(flops_vs_rollout=r["flops"] / rollout_flops if rollout_flops else float("nan"),
                     load_1min=(load + os.getloadavg()[0]) / 2, **env)
            rows.append(r)
            _print_row(r)
    print(f"wrote {_write(args.csv, FIELDS, rows)}")

    pieces = {"step", "transpose"} <= set(args.programs)
    print("\n| scene | gradient / rollout: XLA compile CPU s | XLA compile wall s | trace + lower + compile CPU s | "
          "flops per step |" + (" pieces: 1 + (step + transpose) / rollout, XLA compile CPU s |" if pieces else ""))
    print("|---" * (6 if pieces else 5) + "|")
    for scene in scenes:
        by = {r["program"]: r for r in rows if r["scene"] == scene}
        if "rollout" in by and "gradient" in by:
            f, g = by["rollout"], by["gradient"]
            apart = ""  # the gradient program's pieces, each compiled on its own
            if pieces:
                held = by["step"]["compile_cpu_s"] + by["transpose"]["compile_cpu_s"]
                apart = f" {1 + held / f['compile_cpu_s']:.2f} |"
            print(f"| {scene} | {g['compile_cpu_s'] / f['compile_cpu_s']:.2f} | "
                  f"{g['compile_s'] / f['compile_s']:.2f} | {g['first_call_cpu_s'] / f['first_call_cpu_s']:.2f} | "
                  f"{g['flops'] / f['flops']:.2f} |" + apart)

    if not args.no_recompiles:
        steps = args.steps or (20 if args.quick else 200)
        out = subprocess.run([sys.executable, "-c", f"import sys; sys.path.insert(0, {str(HERE)!r}); "
                              f"import compile_time, json; print('RESULT ' + json.dumps("
                              f"compile_time.recompiles({steps})))"], capture_output=True, text=True)
        print("\n" + "\n".join(line for line in out.stdout.splitlines() if not line.startswith("RESULT ")))
        results = [line[7:] for line in out.stdout.splitlines() if line.startswith("RESULT ")]
        if out.returncode or not results:
            raise RuntimeError(f"the recompilation count failed:\n{out.stderr[-3000:]}")
        recompile_rows = [dict(r, load_1min=os.getloadavg()[0], **env) for r in json.loads(results[-1])]
        path = Path(args.csv)
        print(f"wrote {_write(path.with_name(path.stem + '_recompiles.csv'), RECOMPILE_FIELDS, recompile_rows)}")
    print(f"load after: {os.getloadavg()}")
    return 0


def _write(path, fields, rows):
    from _results import write_csv

    return write_csv(path, fields, rows)


if __name__ == "__main__":
    sys.exit(main())
