"""Where a GPU step's time goes: the device kernels of a few steps (``jax.profiler`` trace, CUPTI), summed by name.

    python benchmarks/gpu_profile.py                          # mpm3d 1M and mpm88 524k, XLA kernel, random and sorted
    python benchmarks/gpu_profile.py --cases mpm3d --sizes 131072 --steps 10
    python benchmarks/gpu_profile.py --gradient               # also the gradient of mpm88 8k (its reverse pass)

For each case: the GPU kernel time per step, the kernels launched per step, and the 12 kernels that take the most
time (their XLA fusion names: ``scatter``, ``gather``, ``concatenate``, ``loop_*_fusion``, ``input_reduce_*``, the
Pallas kernels' names).  The scenes are ``benchmarks/gpu.py``'s (``mpm88`` and its 3D variant), float32, compiled
as gpu.py compiles them.  On a CPU the trace holds no device kernels and the script says so: run it on a GPU.
"""

from __future__ import annotations

import argparse
import collections
import tempfile
from pathlib import Path

import jax
import jax.numpy as jnp
from cpu_profile import trace_events
from gpu import compile_rollout, mpm3d, mpm88

import jaxmpm as jm


def kernels(call, steps: int, tag: str, top: int = 12) -> None:
    """Trace one call of ``call`` (``steps`` steps) and print its device kernels per step, the costliest first."""
    jax.block_until_ready(call())  # warm
    folder = tempfile.mkdtemp(prefix=f"jaxmpm-trace-{tag}-")
    with jax.profiler.trace(folder, create_perfetto_trace=True):
        jax.block_until_ready(call())
    events = trace_events(folder)
    if events is None:
        print(f"== {tag}: no trace file written")
        return
    processes = {e["pid"]: e["args"]["name"] for e in events if e.get("ph") == "M" and e.get("name") == "process_name"}
    time, count = collections.Counter(), collections.Counter()
    for e in events:
        if e.get("ph") == "X" and "gpu" in processes.get(e.get("pid"), "").lower():
            time[e["name"]] += e.get("dur", 0)
            count[e["name"]] += 1
    if not time:
        print(f"== {tag}: no device kernels in the trace (not a GPU?)")
        return
    total = sum(time.values())
    print(f"== {tag}: {total / 1e3 / steps:.3f} ms of GPU kernels per step, {sum(count.values()) / steps:.1f} "
          f"kernels per step")
    for name, t in time.most_common(top):
        print(f"  {t / 1e3 / steps:8.4f} ms/step {100 * t / total:5.1f}%  x{count[name] / steps:5.1f}  {name[:100]}")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cases", nargs="+", choices=("mpm3d", "mpm88"), default=["mpm3d", "mpm88"])
    parser.add_argument("--sizes", nargs="+", type=int, default=None,
                        help="particles (default: 1048576 for mpm3d on 128^3, 524288 for mpm88)")
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--sort-every", nargs="+", type=int, default=[0, 16], help="sortings to profile (0: none)")
    parser.add_argument("--kernel", choices=("auto", "xla", "pallas"), default="xla")
    parser.add_argument("--gradient", action="store_true", help="also d(mean height)/dE of mpm88 at 8k particles")
    parser.add_argument("--hlo", type=Path, default=None, metavar="DIR",
                        help="also write each profiled rollout's optimised HLO (the compiled program's text) to DIR")
    args = parser.parse_args(argv)
    print(jax.devices(), jax.__version__, flush=True)
    for case in args.cases:
        for n in args.sizes or ([1048576] if case == "mpm3d" else [524288]):
            for every in args.sort_every:
                if case == "mpm3d":
                    sim, state, dt = mpm3d(n, 128 if n > 200_000 else 64, "f32", kernel=args.kernel)
                else:
                    sim, state, dt = mpm88(n, "f32", kernel=args.kernel)
                sim = sim.with_sorting(every)
                call, _, _ = compile_rollout(sim, state, dt, args.steps)
                kernels(call, args.steps, f"{case} {n} {args.kernel} sort_every={every}")
                if args.hlo is not None:
                    args.hlo.mkdir(parents=True, exist_ok=True)
                    path = args.hlo / f"{case}_{n}_{args.kernel}_sort{every}.hlo.txt"
                    path.write_text(call.program.as_text())
                    print(f"  wrote {path}")
    if args.gradient:
        sim, state, dt = mpm88(8192, "f32")
        steps, dt = 200, jnp.asarray(dt, jnp.float32)

        def loss(E):
            final, _ = jm.set_params(sim, E=E).run(state, dt, steps, 20, save_particles=False)
            return jnp.mean(final.x[:, 1])

        E0 = jnp.asarray(400.0, jnp.float32)
        forward, gradient = jax.jit(loss), jax.jit(jax.grad(loss))
        kernels(lambda: forward(E0), steps, "mpm88 8192 forward (sim.run)")
        kernels(lambda: gradient(E0), steps, "mpm88 8192 gradient (sim.run, checkpoint auto)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
