"""What a first ``jm.scene(name)`` and a first ``sim.run`` compile, per shipped scene (issue 30).

Each scene runs in a fresh process with the persistent cache off, so every program is compiled:
building the scene (``jm.scene``: particles, the model, its state and time step) and a first run of
20 steps saved every 10 (``sim.run``: its check of dt, then the rollout).  The programs are counted
with ``jax.monitoring``'s XLA compilation events; a "small" program is any but the rollout: an
operation jnp ran op by op outside a compiled program (``jnp.asarray`` of a NumPy array on jaxlib 0.10
is one too, ``jit(stage)``), or a small jitted helper.

    python benchmarks/first_call.py                        # every shipped 2D/1D scene
    python benchmarks/first_call.py --scenes bar spin --repeat 3

Times are wall seconds, best of ``--repeat`` processes; the compile column is XLA's backend time of
the small programs alone (tracing and lowering them come on top).  A table in markdown on stdout.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time

SCENES = ("bar", "disks", "spin", "rings", "mpm88", "heat1d", "dam_break", "slide", "column_collapse",
          "cylinder")


def child(scene: str) -> dict:
    import jax

    jax.config.update("jax_enable_x64", True)
    compiled = []
    phase = ["import"]

    def listen(event, seconds, **kw):
        if event == "/jax/core/compile/backend_compile_duration":
            compiled.append((phase[0], kw.get("fun_name", "?"), seconds))

    jax.monitoring.register_event_duration_secs_listener(listen)
    import jaxmpm as jm

    jm.compilation_cache(enabled=False)
    phase[0] = "build"
    start = time.perf_counter()
    setup = jm.scene(scene)
    built = time.perf_counter()
    phase[0] = "run"
    jax.block_until_ready(setup.sim.run(setup.state, setup.dt, 20, 10))
    ran = time.perf_counter()
    small = [c for c in compiled if "rollout" not in c[1]]
    return {"scene": scene, "build_s": built - start, "run_s": ran - built, "programs": len(compiled),
            "small": len(small), "small_compile_s": sum(c[2] for c in small),
            "small_names": sorted({f"{p}:{n}" for p, n, _ in small})}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenes", nargs="+", default=list(SCENES))
    parser.add_argument("--repeat", type=int, default=1, help="fresh processes per scene; the best is kept")
    parser.add_argument("--names", action="store_true", help="list the small programs of each scene")
    parser.add_argument("--child", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        print(json.dumps(child(args.child)))
        return
    print("| scene | programs compiled | of them small | small programs' XLA compile s | jm.scene s | "
          "first sim.run s |")
    print("|---|---|---|---|---|---|")
    for scene in args.scenes:
        rows = []
        for _ in range(args.repeat):
            done = subprocess.run([sys.executable, __file__, "--child", scene], capture_output=True, text=True,
                                  check=True)
            rows.append(json.loads(done.stdout.strip().splitlines()[-1]))
        best = min(rows, key=lambda r: r["build_s"] + r["run_s"])
        print(f"| {scene} | {best['programs']} | {best['small']} | {best['small_compile_s']:.2f} | "
              f"{best['build_s']:.2f} | {best['run_s']:.2f} |", flush=True)
        if args.names:
            print(f"|  | {', '.join(best['small_names'])} |  |  |  |  |", flush=True)


if __name__ == "__main__":
    main()
