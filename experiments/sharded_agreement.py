"""The sharded path against one device: issue 33's agreement matrix.

Scenes ``bar`` (1D, its x = 0 end a symmetry plane normal to the slabs' axis), ``disks`` (two disks
colliding across the slab faces and rebounding), ``mpm88`` (a falling, splashing block) and
``taylor_bar`` in 3D (a copper rod hitting a wall, its foot spreading across the slab faces), each
under FLIP, APIC, XPIC(3) and FMPM(2), stepped by :class:`jaxmpm.parallel.ShardedSimulation` on 2, 4
and 8 forced CPU devices, float64, against the same model stepped on one device.  Grids whose cells
along x split into equal slabs of at least 2 H + 1 cells use equal slabs; the others slabs that move
(``rebalance_every``).  Each device count runs in a process of its own (XLA_FLAGS is read when jax
starts); the one-device runs are made once, by a first process, and read by the others.

Prints a Markdown table -- scene, scheme, devices, slabs, steps, particles, particle moves between
devices, particles that ended in a slab left / right of where they started, max relative error of x,
v and F (max |a - b| / max |b|), the total mass's and linear momentum's difference (relative to M and
M max|v|) -- and writes ``experiments/results/sharded_agreement.csv`` and ``.md``.

    python experiments/sharded_agreement.py            # the matrix: 240 steps (about 15 minutes on 2 cores)
    python experiments/sharded_agreement.py --quick    # FLIP and XPIC(3), 2 and 8 devices, 50 steps
"""

import argparse
import csv
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results"
SCENES = ("bar", "disks", "mpm88", "taylor_bar_3d")
SCHEMES = ("FLIP", "APIC", "XPIC(3)", "FMPM(2)")
DEVICES = (2, 4, 8)
COLUMNS = ("scene", "scheme", "devices", "slabs", "steps", "particles", "moves", "ended_left", "ended_right",
           "x_rel_err", "v_rel_err", "F_rel_err", "mass_diff", "momentum_diff", "seconds")


# ---------------------------------------------------------------------------------------- worker
def scheme_of(name):
    import jaxmpm as jm

    return {"FLIP": jm.FLIP, "APIC": jm.APIC, "XPIC(3)": lambda: jm.XPIC(order=3),
            "FMPM(2)": lambda: jm.FMPM(order=2)}[name]()


def setup_of(scene, scheme):
    """The scene, small: a few thousand particles at most, its grid wide enough along x for 8 slabs
    of 2 H + 1 cells, its bodies crossing the slab faces within 240 steps."""
    import jaxmpm as jm

    if scene == "bar":  # amplitude v0 / omega = 1.6 cells: the particles cross the faces both ways
        return jm.scene("bar", scheme=scheme, shape=jm.QuadraticBSpline(), boundary="mirror", cells=40, v0=1.0,
                        cfl=0.4, dtype="float64")
    if scene == "disks":  # the disks meet after about 160 steps and rebound
        return jm.scene("disks", scheme=scheme, spacing=0.025, speed=1.0, dtype="float64")
    if scene == "mpm88":  # thrown onto the floor, splashing left and right across the faces
        return jm.scene("mpm88", scheme=scheme, n_particles=2048, n_grid=40, dt=6e-4, speed=3.0,
                        dtype="float64")
    if scene == "taylor_bar_3d":  # a short rod, 10 cells across its radius, one particle per cell; cfl 0.2: APIC
        # with linear shape functions inverts a particle of the impact at step 29 with cfl 0.5 (205 with 0.25), on
        # one device as on several
        return jm.scene("taylor_bar", scheme=scheme, geometry="3d", cells=10, ppc=1, length=7.6e-3, cfl=0.2,
                        dtype="float64")
    raise ValueError(scene)


def one_device(setup, steps):
    import jax

    sim, dt = setup.sim, setup.dt
    return jax.jit(lambda s: jax.lax.fori_loop(0, steps, lambda i, s: sim.step(s, dt), s))(setup.state)


def worker(devices, steps, scenes, schemes, folder):
    """One device count: the one-device runs saved (devices = 1), or the sharded runs against them,
    one JSON line per run."""
    import jax

    jax.config.update("jax_enable_x64", True)
    import numpy as np

    from jaxmpm.parallel import ShardedSimulation
    from jaxmpm.parallel.slabs import halo_for

    for scene in scenes:
        for name in schemes:
            setup = setup_of(scene, scheme_of(name))
            path = os.path.join(folder, f"{scene}-{name}.npz")
            tic = time.perf_counter()
            if devices == 1:
                one = one_device(setup, steps)
                np.savez(path, x=one.x, v=one.v, F=one.F, mass=one.mass, step=one.step)
                print(json.dumps({"scene": scene, "scheme": name, "seconds": time.perf_counter() - tic}), flush=True)
                continue
            one = np.load(path)
            sim, state = setup.sim, setup.state
            cells, halo = sim.grid.cells[0], halo_for(sim.shape)
            equal = cells % devices == 0 and cells // devices > 2 * halo
            row = {"scene": scene, "scheme": name, "devices": devices, "steps": steps,
                   "particles": int(state.x.shape[0])}
            if devices * (2 * halo + 1) > cells:
                row |= {"slabs": f"none: {cells} cells along x < {devices} x {2 * halo + 1}"}
                print(json.dumps(row), flush=True)
                continue
            # slabs that move: a buffer for every particle, and a quarter of them may cross a face in a step
            # (the colliding disks gather in a few slabs; the default buffers overflow at the impact)
            n = int(state.x.shape[0])
            sharded = ShardedSimulation(sim, devices=jax.devices()[:devices], **(
                {} if equal else {"rebalance_every": 20, "capacity": n, "exchange": max(64, n // 4)}))
            try:
                many = sharded.run(state, setup.dt, steps)
            except Exception as error:  # a failed cell of the matrix is reported, not hidden
                row |= {"slabs": "equal" if equal else "moving", "error": f"{type(error).__name__}: {error}"}
                try:  # and whether one device fails the same way
                    sim.run(state, setup.dt, steps, steps)
                    row["one_device"] = "ran to the end"
                except Exception as alone:
                    row["one_device"] = f"{type(alone).__name__}: {alone}"
                print(json.dumps(row), flush=True)
                continue
            bounds = np.asarray(sharded.stats["bounds"][0][1]) if sharded.stats["bounds"] else None
            start = np.asarray(sharded.owner(state.x, bounds))
            end = np.asarray(sharded.owner(many.x, bounds))

            def rel(a, b):
                a, b = np.asarray(a), np.asarray(b)
                return float(np.max(np.abs(a - b)) / np.max(np.abs(b)))

            mass = float(np.sum(one["mass"]))
            p_one = np.sum(one["mass"][:, None] * one["v"], axis=0)
            p_many = np.sum(np.asarray(many.mass)[:, None] * np.asarray(many.v), axis=0)
            row |= {"slabs": "equal" if equal else f"moving ({sharded.stats['rebalances']} rebalances)",
                    "moves": sharded.stats["migrated"], "ended_left": int(np.sum(end < start)),
                    "ended_right": int(np.sum(end > start)), "x_rel_err": rel(many.x, one["x"]),
                    "v_rel_err": rel(many.v, one["v"]), "F_rel_err": rel(many.F, one["F"]),
                    "mass_diff": abs(float(np.sum(np.asarray(many.mass))) - mass) / mass,  # NumPy's sum, both
                    "momentum_diff": float(np.max(np.abs(p_many - p_one)) / (mass * np.max(np.abs(one["v"])))),
                    "seconds": time.perf_counter() - tic, "final_step": int(many.step)}
            print(json.dumps(row), flush=True)


# ---------------------------------------------------------------------------------------- driver
def spawn(devices, args, folder):
    flags = os.environ.get("XLA_FLAGS", "") + f" --xla_force_host_platform_device_count={max(devices, 1)}"
    env = dict(os.environ, XLA_FLAGS=flags.strip(),
               JAX_PLATFORMS="cpu")
    command = [sys.executable, __file__, "--worker", str(devices), "--steps", str(args.steps), "--folder", folder,
               "--scenes", ",".join(args.scenes), "--schemes", ",".join(args.schemes)]
    done = subprocess.run(command, env=env, capture_output=True, text=True)
    if done.returncode != 0:
        sys.exit(f"the {devices}-device process failed:\n{done.stderr[-3000:]}")
    return [json.loads(line) for line in done.stdout.splitlines() if line.startswith("{")]


def cell(value):
    if isinstance(value, float):
        return f"{value:.1e}" if value else "0"
    return "" if value is None else str(value)


def table(rows) -> str:
    head = ("scene", "scheme", "devices", "slabs", "steps", "particles", "moves", "ended left / right",
            "x rel err", "v rel err", "F rel err", "mass diff", "momentum diff")
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        values = [r["scene"], r["scheme"], r["devices"], r.get("slabs"), r["steps"], r["particles"], r.get("moves"),
                  f"{r['ended_left']} / {r['ended_right']}" if "ended_left" in r else
                  f"{r.get('error', '')} (one device: {r.get('one_device')})",
                  *(r.get(k) for k in ("x_rel_err", "v_rel_err", "F_rel_err", "mass_diff", "momentum_diff"))]
        lines.append("| " + " | ".join(cell(v) for v in values) + " |")
    return "\n".join(lines)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="FLIP and XPIC(3) on 2 and 8 devices, 50 steps")
    parser.add_argument("--steps", type=int, default=None, help="steps per run (default 240; 50 with --quick)")
    parser.add_argument("--scenes", default=",".join(SCENES), help="comma-separated, of " + ", ".join(SCENES))
    parser.add_argument("--schemes", default=None, help="comma-separated, of " + ", ".join(SCHEMES))
    parser.add_argument("--devices", default=None, help="comma-separated device counts (default 2,4,8)")
    parser.add_argument("--out", type=Path, default=RESULTS, help="results folder")
    parser.add_argument("--worker", type=int, default=None, help=argparse.SUPPRESS)
    parser.add_argument("--folder", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    args.scenes = args.scenes.split(",")
    args.schemes = (args.schemes or ("FLIP,XPIC(3)" if args.quick else ",".join(SCHEMES))).split(",")
    args.steps = args.steps or (50 if args.quick else 240)
    if args.worker is not None:
        return worker(args.worker, args.steps, args.scenes, args.schemes, args.folder)
    devices = [int(d) for d in (args.devices or ("2,8" if args.quick else "2,4,8")).split(",")]
    tic = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="sharded-agreement-") as folder:
        spawn(1, args, folder)
        rows = [row for d in devices for row in spawn(d, args, folder)]
    rows.sort(key=lambda r: (SCENES.index(r["scene"]), SCHEMES.index(r["scheme"]), r["devices"]))
    text = table(rows)
    print(text)
    print(f"\n{len(rows)} runs in {time.perf_counter() - tic:.0f} s")
    args.out.mkdir(parents=True, exist_ok=True)
    stem = "sharded_agreement" + ("_quick" if args.quick else "")
    with open(args.out / f"{stem}.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(COLUMNS) + ["error", "one_device"], extrasaction="ignore")
        writer.writeheader()
        writer.writerows(rows)
    (args.out / f"{stem}.md").write_text(text + "\n")


if __name__ == "__main__":
    main()
