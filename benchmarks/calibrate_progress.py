"""What a calibration's time is made of, and what compiling it ahead of time (for its progress) costs.

The disks beta calibration of tests/test_differentiable.py (XPIC(2) beta from 0.7 to 0.3 on the
particle velocities of a 50-step window in contact, L-BFGS with a backtracking line search) is run,
alternately, by ``jm.calibrate`` (which compiles its update ahead of the first iteration and reports
``compile_time``) and by the plain ``jax.jit`` loop ``jm.calibrate`` ran before (the update compiled
by its first call).  Per run: the wall time, ``compile_time`` and, for the plain loop, the first
iteration (compilation included) and the rest.  Both give the same losses and parameters, bit for
bit (checked).  Each run compiles anew (a new loss closure, as a user's second calibration would).
``rest s``: the wall time less ``compile_time`` (jm.calibrate: every iteration) or less the first
iteration (the plain loop: the iterations after it).

    python benchmarks/calibrate_progress.py             # 3 rounds (about 2 minutes on 2 CPU cores)
    python benchmarks/calibrate_progress.py --rounds 1 --show   # and the progress a user sees
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

import jax
from _results import write_csv

jax.config.update("jax_enable_x64", True)

import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import optax  # noqa: E402

import jaxmpm as jm  # noqa: E402
from jaxmpm.core.params import default_bounds  # noqa: E402
from jaxmpm.run.calibrate import _transform  # noqa: E402

DEFAULT_CSV = Path(__file__).resolve().parent / "results" / "calibrate_progress.csv"
FIELDS = ["method", "round", "iterations", "wall_s", "compile_s", "first_iteration_s", "rest_s", "load_1min", "jax",
          "cpus"]


def disks_beta_problem():
    """(loss, init): beta of XPIC(2) on the disks, as tests/test_differentiable.py::test_calibrate_on_disks."""
    shape = jm.QuadraticBSpline()
    start = jm.scene("disks", speed=0.5, shape=shape)
    start, _ = start.sim.run(start.state, start.dt, 250, 250)
    setup = jm.scene("disks", scheme=jm.XPIC(order=2, beta=0.3), speed=0.5, shape=shape)
    state = eqx.tree_at(lambda s: (s.x, s.v, s.F), setup.state, (start.x, start.v, start.F))

    def observe(params):
        _, history = jm.set_params(setup.sim, **params).run(state, setup.dt, 50, 10)
        return history.v

    target = observe({"beta": 0.3})

    def make_loss():  # a new closure per run: every run compiles, as a new calibration does
        def loss(params):
            return jnp.mean((observe(params) - target) ** 2) / jnp.mean(target**2)
        return loss

    return make_loss, {"beta": 0.7}


def plain_jit_loop(loss, init, optimizer, steps, tol):
    """The loop jm.calibrate ran before it compiled ahead of time; (losses, params, first_s, rest_s)."""
    transforms = {k: _transform(default_bounds(k)) for k in init}
    raw = {k: transforms[k][1](jnp.asarray(v, dtype=jnp.result_type(float))) for k, v in init.items()}

    def constrained(r):
        return {k: transforms[k][0](r[k]) for k in r}

    state = optimizer.init(raw)
    state = jax.tree_util.tree_map(lambda a: jnp.asarray(a, dtype=a.dtype) if hasattr(a, "dtype") else a, state)

    def raw_loss(rr):
        return loss(constrained(rr))

    @jax.jit
    def update(r, s):
        value, grads = jax.value_and_grad(raw_loss)(r)
        with jax.numpy_dtype_promotion("standard"):
            updates, s = optimizer.update(grads, s, r, value=value, grad=grads, value_fn=raw_loss)
        return optax.apply_updates(r, updates), s, value

    losses, tic, first = [], time.perf_counter(), None
    for _ in range(steps):
        raw, state, value = update(raw, state)
        losses.append(float(value))
        first = time.perf_counter() - tic if first is None else first
        if losses[-1] < tol:
            break
    total = time.perf_counter() - tic
    return np.asarray(losses), {k: np.asarray(v) for k, v in constrained(raw).items()}, first, total - first, total


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=3, help="alternating runs of each method (default 3)")
    parser.add_argument("--show", action="store_true", help="jm.calibrate with progress=True (stderr)")
    parser.add_argument("--csv", type=Path, default=DEFAULT_CSV)
    args = parser.parse_args(argv)

    make_loss, init = disks_beta_problem()
    lbfgs = optax.lbfgs(linesearch=optax.scale_by_backtracking_linesearch(max_backtracking_steps=20))
    steps, tol = 200, 1e-9
    rows = []
    for r in range(args.rounds):
        losses, params, first, rest, total = plain_jit_loop(make_loss(), init, lbfgs, steps, tol)
        rows.append(dict(method="plain jax.jit loop (before)", round=r, iterations=len(losses), wall_s=total,
                         compile_s=float("nan"), first_iteration_s=first, rest_s=rest))
        result = jm.calibrate(make_loss(), init, optimizer=lbfgs, steps=steps, tol=tol, progress=args.show)
        assert np.array_equal(result.losses, losses) and np.array_equal(result.params["beta"], params["beta"]), \
            "jm.calibrate and the plain loop differ"
        rows.append(dict(method="jm.calibrate (ahead of time)", round=r, iterations=result.iterations,
                         wall_s=result.wall_time, compile_s=result.compile_time, first_iteration_s=float("nan"),
                         rest_s=result.wall_time - result.compile_time))
    load = os.getloadavg()[0]
    for row in rows:
        row.update(load_1min=load, jax=jax.__version__, cpus=os.cpu_count())
    print(f"disks beta calibration, L-BFGS, {platform.machine()}, {os.cpu_count()} CPUs, jax {jax.__version__}, "
          f"load (1 min) {load:.2f}; losses and parameters equal bit for bit in every round")
    print(f"{'method':>30} {'round':>5} {'iters':>5} {'wall s':>7} {'compile s':>9} {'1st iter s':>10} {'rest s':>7}")
    for row in rows:
        print(f"{row['method']:>30} {row['round']:5d} {row['iterations']:5d} {row['wall_s']:7.2f} "
              f"{row['compile_s']:9.2f} {row['first_iteration_s']:10.2f} {row['rest_s']:7.2f}")
    best = {m: min(row["wall_s"] for row in rows if row["method"] == m) for m in {row["method"] for row in rows}}
    before, after = best["plain jax.jit loop (before)"], best["jm.calibrate (ahead of time)"]
    print(f"best wall: before {before:.2f} s, ahead of time {after:.2f} s, ratio {after / before:.3f}")
    write_csv(args.csv, FIELDS, rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
