"""Memory per particle (issue 32 item 7): a compiled rollout's bytes against the particle state's, compiled only.

    python benchmarks/memory_per_particle.py                  # mpm88 2D and mpm3d, float32 and float64
    python benchmarks/memory_per_particle.py --quick          # small sizes, seconds
    python benchmarks/memory_per_particle.py --cases 2d:2097152:f32 3d:1048576:f32 --steps 10

Each case is one of ``gpu.py``'s models (``mpm88`` in 2D on its 128^2 grid, ``mpm3d`` on 64^3 up to 131k
particles and 128^3 above), compiled as ``gpu.py`` compiles its timed rollouts (``compile_rollout``: the steps
in one loop, the state donated) and never run, so the largest sizes cost seconds.  XLA's account of the program
(``compiled.memory_analysis()``), per particle:

* ``state``: the particle state (x, v, F, B, mass, volume, ...), the measure's unit;
* ``arguments``, ``outputs``, ``temporaries``: the program's buffers (the arguments hold the state and the
  model's arrays: the grid's, which dominate when particles per cell are few);
* ``aliased``: the outputs written over donated arguments (the final state over the initial one);
* ``program``: arguments + outputs + temporaries - aliased, the peak a run of this program holds on the device;
* ``program / state``: the issue's measure (goal: at most 2), and the same without donation (one state more).

Rows per case: the step as the library chooses it (``CHUNK_TABLE`` in ``jaxmpm/transfer/backend.py``, and
chunks where the whole step's temporaries would not fit the device, ``chunks_to_fit``), the whole step at once
(``with_chunks(0)``) where that differs, and with ``--chunks N`` the step over chunks of N particles.  Writes
``benchmarks/results/memory_per_particle.csv`` (or ``--csv``).

``--gradient`` adds, for each row, the gradient of the final kinetic energy with respect to the initial
velocities through ``sim.run`` (``checkpoint="auto"``), compiled the same way: its program per particle and
against the state.  Where the step's derivatives go in chunks (``chunks.step_in_chunks``: the backend's
``DERIVATIVE_CHUNK_TABLE``, and wherever the whole step would not fit), the row "library's forward" takes the
library's forward step with the whole step's derivatives (``with_derivative_chunks(0)``).
``--device-memory SIZE`` (e.g. ``"64 MiB"``) is the free memory the library's rules see on a CPU
(``JAXMPM_MEMORY_BYTES``): the choice on a smaller device.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import jax

DEFAULT_CSV = Path(__file__).resolve().parent / "results" / "memory_per_particle.csv"
CASES = ["2d:131072:f32", "2d:524288:f32", "2d:2097152:f32", "2d:131072:f64", "2d:524288:f64",
         "3d:131072:f32", "3d:1048576:f32", "3d:131072:f64"]
QUICK = ["2d:8192:f32", "2d:131072:f64", "3d:2048:f32"]


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--cases", nargs="+", default=None,
                   help="DIM:PARTICLES:DTYPE, DIM 2d (mpm88) or 3d (mpm3d), DTYPE f32 or f64 (default: "
                        + " ".join(CASES) + ")")
    p.add_argument("--quick", action="store_true", help="the cases " + " ".join(QUICK))
    p.add_argument("--steps", type=int, default=10, help="steps in the compiled loop (default 10)")
    p.add_argument("--chunks", type=int, default=0,
                   help="also a row with the step over chunks of this many particles (with_chunks; default: none)")
    p.add_argument("--gradient", action="store_true",
                   help="also the gradient of the final kinetic energy through sim.run, per row (module docstring)")
    p.add_argument("--device-memory", default=None,
                   help="the free memory the library's rules see, e.g. '64 MiB' (CPU: JAXMPM_MEMORY_BYTES)")
    p.add_argument("--csv", default=str(DEFAULT_CSV))
    args = p.parse_args(argv)
    args.cases = args.cases or (QUICK if args.quick else CASES)
    for case in args.cases:
        parts = case.split(":")
        if len(parts) != 3 or parts[0] not in ("2d", "3d") or not parts[1].isdigit() or parts[2] not in ("f32", "f64"):
            p.error(f"--cases: {case!r} is not DIM:PARTICLES:DTYPE, e.g. 2d:131072:f32 or 3d:1048576:f64")
    return args


def model(dim: str, n: int, dtype: str):
    """gpu.py's model: (sim, state, dt)."""
    import gpu

    if dim == "2d":
        return gpu.mpm88(n, dtype)
    return gpu.mpm3d(n, 64 if n <= 131072 else 128, dtype)


def measure(sim, state, dt, steps: int) -> dict:
    """The compiled rollout's buffers per particle (module docstring)."""
    import gpu

    from jaxmpm.run.memory import tree_bytes

    call, _, program_bytes = gpu.compile_rollout(sim, state, dt, steps)  # the bytes gpu.py reports
    memory = call.program.memory_analysis()
    n = int(state.x.shape[0])
    state_b = tree_bytes(state) / n
    out = dict(state=state_b, arguments=memory.argument_size_in_bytes / n, outputs=memory.output_size_in_bytes / n,
               temporaries=memory.temp_size_in_bytes / n, aliased=memory.alias_size_in_bytes / n,
               program=program_bytes / n)
    out["program_over_state"] = out["program"] / state_b
    out["without_donation_over_state"] = (out["program"] + out["aliased"]) / state_b
    return out


def measure_gradient(sim, state, dt, steps: int) -> dict:
    """The compiled gradient's buffers per particle: d/dv0 of the final kinetic energy through ``sim.run``."""
    import equinox as eqx
    import gpu
    import jax.numpy as jnp

    from jaxmpm.run.memory import tree_bytes

    def kinetic(v):
        final = sim.run(eqx.tree_at(lambda s: s.v, state, v), dt, steps, progress=False)[0]
        return jnp.sum(final.mass[:, None] * final.v ** 2)

    memory = jax.jit(jax.grad(kinetic)).lower(state.v).compile().memory_analysis()
    n = int(state.x.shape[0])
    program = gpu.held_bytes(memory) / n
    return dict(gradient_temporaries=memory.temp_size_in_bytes / n, gradient_program=program,
                gradient_over_state=program / (tree_bytes(state) / n))


def main(argv=None) -> int:
    args = parse_args(argv)
    if args.device_memory is not None:
        from jaxmpm.run.memory import parse_memory

        os.environ["JAXMPM_MEMORY_BYTES"] = str(parse_memory(args.device_memory))
    if any(c.endswith(":f64") for c in args.cases):
        jax.config.update("jax_enable_x64", True)
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from _results import write_csv

    import jaxmpm as jm

    print(f"jax {jax.__version__} ({jax.devices()[0].device_kind}), {os.cpu_count()} CPUs, {args.steps} steps "
          "compiled (not run), bytes per particle\n")
    header = ("| case | step | state | arguments | outputs | temporaries | aliased | program | program / state "
              "| without donation |" + (" gradient: program | gradient / state |" if args.gradient else ""))
    print(header)
    print("|---" * (header.count("|") - 1) + "|")
    rows = []
    for case in args.cases:
        dim, n, dtype = case.split(":")
        sim, state, dt = model(dim, int(n), dtype)
        variants = [("library's", sim)]
        info = jm.backend_info(sim, state)
        if info.get("chunk_particles"):  # else the library's choice is the whole step
            variants.append(("whole", sim.with_chunks(0)))
        if args.gradient and info["derivative_chunk_particles"]:
            variants.append(("library's forward", sim.with_derivative_chunks(0)))
        if args.chunks:
            variants.append(("forced", sim.with_chunks(args.chunks)))
        for label, chosen in variants:
            info = jm.backend_info(chosen, state)
            per, derivatives = info["chunk_particles"], info["derivative_chunk_particles"]
            step = f"{label} (chunks of {per})" if per else f"{label} (whole)"
            if args.gradient:
                step += f", derivatives in chunks of {derivatives}" if derivatives else ", whole derivatives"
            r = measure(chosen, state, dt, args.steps)
            if args.gradient:
                r.update(measure_gradient(chosen, state, dt, args.steps))
            gradient = f" {r['gradient_program']:.0f} | {r['gradient_over_state']:.2f} |" if args.gradient else ""
            print(f"| {dim} {int(n)} {dtype} | {step} | {r['state']:.0f} | {r['arguments']:.0f} | "
                  f"{r['outputs']:.0f} | {r['temporaries']:.1f} | {r['aliased']:.0f} | {r['program']:.0f} | "
                  f"**{r['program_over_state']:.2f}** | {r['without_donation_over_state']:.2f} |{gradient}", flush=True)
            rows.append(dict(case=case, step=step, device=jax.devices()[0].device_kind, jax=jax.__version__, **r))
    print(f"\nwrote {write_csv(args.csv, list(rows[0]), rows)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
