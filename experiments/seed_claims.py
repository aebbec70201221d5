"""The seeds' claims about the PIC updates, measured (issue 16, item 8).

003 §2.3.4: "PIC derived from FMPM(1) is more stable than the one derived from XPIC(1)
(especially for problems where PIC works well such as MMS with linear velocities)", and 003
§2.3.5 / Table 2.1: "neither XPIC(1) nor FMPM(1) reduce to PIC(Std). Instead they give improved
forms of PIC with FMPM(1) the best."  The three PIC updates share the velocity update V = S v+ and
differ only in the position update:

* ``PIC(Std)`` (003 Table 2.1):      X += S v+ dt                       = ``jm.PIC(position="first_order")``
* ``XPIC(1)`` (003 eq. 2.38):        X += [S v + (S v+ - V^n)/2] dt     = ``jm.XPIC(order=1)`` = ``jm.PIC()``
* ``FMPM(1)`` (003 eq. 2.40):        X += (S v+ + V^n)/2 dt             = ``jm.FMPM(order=1)``

plus XPIC(2), FMPM(2) and FLIP for scale.  Scenes (1D, 2 particles per cell, A = 0.05, the
defaults of ``mms``):

* ``linear``: ``mms(velocity="linear")``, u = A X sin(c pi t), velocity linear in space (the
  "MMS with linear velocities"; 003 does not describe its MMS, see jaxmpm/scenes/mms_linear.py);
* ``sine``: ``mms`` itself, u = A sin(pi X) sin(c pi t) (Wallstedt & Guilkey 2008).

For each scene x shape function x scheme x cells (16, 32) the CFL number (dt = CFL h / (c_d + A c
pi), the scenes' own definition) runs 0.1, 0.2, ..., 1.3 up to the first failure; each run goes to
a horizon of ``--periods`` periods of the motion (default 4; one period = 2/c = 0.02) in calls of a
fixed chunk of steps with dt a dynamic argument (one compile per scene x shape x scheme x cells),
with ``check_stability=True``:

* error: max over the saved frames (t <= horizon) of the RMS particle displacement error / A, and
  of the RMS velocity error / (A c pi) against the exact velocity half a step earlier (USL's
  particle velocities are half-step velocities);
* outcome: ``NaN/Inf``, ``J <= 0`` or ``left grid`` from :class:`jaxmpm.InstabilityError` (its first
  bad step), else ``diverged`` if the displacement error exceeds A (the exact amplitude), else
  ``stable``;
* per scene x shape x scheme x cells, the largest stable CFL: the largest CFL run with it and every
  smaller one stable.

Writes ``experiments/results/seed_claims.md`` (tables) and ``seed_claims.csv`` (every run).  A shape
takes 2-5 min on the shared 2-core machine (compiles dominate), so the results were made one shape
at a time, each invocation adding its rows to the CSV:

    python experiments/seed_claims.py --shapes Linear
    python experiments/seed_claims.py --shapes UGIMP --append
    python experiments/seed_claims.py --shapes Quadratic --scenes linear --append
    python experiments/seed_claims.py --scenes "linear A=1e-4" "sine A=1e-4" --append
    python experiments/seed_claims.py --report-only      # the Markdown again from the CSV
    python experiments/seed_claims.py --quick            # 16 cells, 5 CFL numbers, 2 periods
"""

from __future__ import annotations

import argparse
import csv
import math
import time
import warnings
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jaxmpm as jm  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"
SAVE_EVERY = 4
CHUNK_FRAMES = 32  # one compiled call = 128 steps, reused for every CFL
CAUSES = {"NaN or Inf": "NaN/Inf", "J = det F <= 0": "J <= 0", "particles left the grid": "left grid"}
FAILED = ("NaN/Inf", "J <= 0", "left grid", "diverged")
CELLS = (16, 32)
CFLS = (0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 1.0, 1.1, 1.2, 1.3)
SHAPES = {"Linear": lambda ppc: jm.Linear(), "UGIMP": lambda ppc: jm.UGIMP(ppc=ppc),
          "Quadratic": lambda ppc: jm.QuadraticBSpline()}
SCENES = {"linear": dict(velocity="linear", amplitude=0.05), "sine": dict(velocity="sine", amplitude=0.05),
          # small amplitude: no particle crosses a cell (the stability limits of the updates themselves)
          "linear A=1e-4": dict(velocity="linear", amplitude=1e-4),
          "sine A=1e-4": dict(velocity="sine", amplitude=1e-4)}
APPENDED = "`python experiments/seed_claims.py` in several invocations with `--append` (module docstring)"
FIELDS = ("scene", "shape", "scheme", "cells", "cfl", "dt", "outcome", "step", "time", "err_x", "err_v", "wall_s")


def schemes() -> dict:
    """Label -> scheme factory (003 Table 2.1 and eqs. 2.38, 2.40)."""
    return {
        "PIC(Std)": lambda: jm.PIC(position="first_order"),  # 003 Table 2.1: X += S v+ dt
        "XPIC(1)": lambda: jm.XPIC(order=1),  # 003 eq. (2.38) (= jm.PIC())
        "FMPM(1)": lambda: jm.FMPM(order=1),  # 003 eq. (2.40), the "new PIC"
        "XPIC(2)": lambda: jm.XPIC(order=2),
        "FMPM(2)": lambda: jm.FMPM(order=2),
        "FLIP": lambda: jm.FLIP(),
    }


def build(scene: str, scheme, cells: int, shape: str = "Linear", ppc: int = 2):
    return jm.scene("mms", dim=1, cells=cells, ppc=ppc, scheme=scheme, shape=SHAPES[shape](ppc), frames=1,
                    **SCENES[scene])


def time_step(setup, cfl: float) -> float:
    """dt = CFL h / (c_d + A c pi): the ``mms`` scenes' definition of their CFL number."""
    p = setup.params
    c_d = float(setup.sim.material.wave_speed(1))
    return cfl * p["h"] / (c_d + p["amplitude"] * p["c"] * math.pi)


def _errors(reference, t, x, v, shift):
    """``reference.errors`` for all frames at once: RMS over the particles of |x_p - x(X_p, t)| and
    of |V_p - v(X_p, t - shift)| (USL's particle velocities are half-step velocities)."""
    if t.size == 0:
        return np.zeros(0), np.zeros(0)
    X = jnp.asarray(reference.X)
    u_ex = np.asarray(_frames(reference._u)(X, jnp.asarray(t)))
    v_ex = np.asarray(_frames(reference._v)(X, jnp.asarray(t - shift)))
    keep = reference.measured
    dx = (x - reference.X[None] - u_ex)[:, keep]
    dv = (v - v_ex)[:, keep]
    return np.sqrt(np.mean(np.sum(dx**2, -1), -1)), np.sqrt(np.mean(np.sum(dv**2, -1), -1))


_FRAMES = {}


def _frames(field):
    """field(X (N, D), t) vectorised over a vector of times, compiled once per field."""
    if field not in _FRAMES:
        _FRAMES[field] = jax.jit(jax.vmap(field, in_axes=(None, 0)))
    return _FRAMES[field]


def run_case(setup, dt: float, horizon: float) -> dict:
    """Run ``setup`` with step ``dt`` to ``horizon`` in fixed chunks and measure (module docstring)."""
    chunk = CHUNK_FRAMES * SAVE_EVERY
    A, c = setup.params["amplitude"], setup.params["c"]
    state, tol = setup.state, 1e-9 * horizon
    ex, ev, failure, t_last = [0.0], [0.0], None, 0.0
    start = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", jm.StableTimeStepWarning)  # CFL > 1 is meant to pass the limit
        while float(state.time) < horizon - tol:
            try:
                state, hist = setup.sim.run(state, dt, chunk, SAVE_EVERY, check_stability=True)
            except jm.InstabilityError as err:
                if err.time <= horizon + tol:
                    failure = err
                break
            t = np.asarray(hist.time)[1:]
            keep = t <= horizon + tol
            e_x, e_v = _errors(setup.reference, t[keep], np.asarray(hist.x)[1:][keep], np.asarray(hist.v)[1:][keep],
                               0.5 * dt)
            ex.extend(e_x / A)
            ev.extend(e_v / (A * c * math.pi))
            t_last = float(t[keep][-1]) if keep.any() else t_last
    wall = time.perf_counter() - start
    err_x, err_v = max(ex), max(ev)
    if failure is not None:
        outcome = next((short for long, short in CAUSES.items() if failure.cause.startswith(long)), "NaN/Inf")
        step, when = failure.step, float(failure.time)
    else:
        outcome = "diverged" if not err_x <= 1.0 else "stable"
        step, when = int(round(t_last / dt)), t_last
    return dict(outcome=outcome, step=int(step), time=when, err_x=float(err_x), err_v=float(err_v), wall_s=wall)


def sweep(scenes, shapes, names, cells_list, cfls, horizon, log=print) -> list[dict]:
    """Every (scene, shape, scheme, cells): CFL numbers in increasing order up to the first failure
    (the largest stable CFL is the last one before it)."""
    factories = schemes()
    rows = []
    for scene in scenes:
        for shape in shapes:
            for name in names:
                for cells in cells_list:
                    setup = build(scene, factories[name](), cells, shape)
                    done = []
                    for cfl in cfls:
                        dt = time_step(setup, cfl)
                        done.append(dict(scene=scene, shape=shape, scheme=name, cells=cells, cfl=cfl, dt=dt,
                                         **run_case(setup, dt, horizon)))
                        if done[-1]["outcome"] in FAILED:
                            break
                    rows.extend(done)
                    log(f"{scene:6s} {shape:9s} {name:8s} {cells:3d} cells  "
                        + " ".join("." if r["outcome"] == "stable" else r["outcome"][0] for r in done)
                        + f"  {sum(r['wall_s'] for r in done):5.1f} s", flush=True)
    return rows


def largest_stable(rows, key) -> tuple[float | None, dict | None]:
    """(largest CFL run stable with every smaller one, the failed run or None) of (scene, shape, scheme, cells)."""
    runs = sorted((r for r in rows if (r["scene"], r["shape"], r["scheme"], r["cells"]) == key), key=lambda r: r["cfl"])
    best = None
    for r in runs:
        if r["outcome"] in FAILED:
            return best, r
        best = r["cfl"]
    return best, None


def lookup(rows, key, cfl) -> dict | None:
    return next((r for r in rows if (r["scene"], r["shape"], r["scheme"], r["cells"]) == key and r["cfl"] == cfl),
                None)


def _keys(rows, field):
    return list(dict.fromkeys(r[field] for r in rows))


def report(rows, cfls, horizon, error_cfls, wall, command) -> str:
    names, cells_list = _keys(rows, "scheme"), _keys(rows, "cells")
    out = ["# The seeds' PIC claims, measured (003 §2.3.4, Table 2.1)", "",
           f"Written by {command} ({wall:.0f} s of runs, compiles included). 1D, 2 particles per cell, A = 0.05 "
           "(A = 1e-4 where the scene says so: no particle crosses a cell), USL, horizon "
           f"t = {horizon:g} ({horizon / 0.02:g} periods). `linear`: `mms(velocity='linear')`, u = A X sin(c pi t); "
           "`sine`: `mms`, u = A sin(pi X) sin(c pi t). PIC(Std) = `jm.PIC(position='first_order')` (Table 2.1), "
           "XPIC(1) = `jm.XPIC(order=1)` = `jm.PIC()` (eq. 2.38), FMPM(1) = `jm.FMPM(order=1)` (eq. 2.40).", "",
           "## Largest stable CFL (the first failure: outcome, step)", "",
           "CFL numbers tried in order, up to the first failure: " + ", ".join(f"{c:g}" for c in cfls)
           + ". dt = CFL h / (c_d + A c pi). Failure = jm.InstabilityError (NaN/Inf, J <= 0, left grid) "
           "or RMS displacement error > A (diverged).", ""]
    out.append("| scene | shape | scheme | " + " | ".join(f"{c} cells" for c in cells_list) + " |")
    out.append("|---|---|---|" + "---|" * len(cells_list))
    pairs = list(dict.fromkeys((r["scene"], r["shape"]) for r in rows))  # the (scene, shape) pairs run
    for scene, shape in pairs:
        for name in names:
            cols = []
            for cells in cells_list:
                best, fail = largest_stable(rows, (scene, shape, name, cells))
                text = "none" if best is None else f"{best:g}"
                if fail is not None:
                    text += f" ({fail['outcome']} at CFL {fail['cfl']:g}, step {fail['step']})"
                cols.append(text)
            out.append(f"| {scene} | {shape} | {name} | " + " | ".join(cols) + " |")
    for cfl in error_cfls:
        out += ["", f"## Errors at CFL {cfl:g}: max over t of RMS displacement error / A "
                    "(of RMS velocity error / (A c pi))", ""]
        out.append("| scene | shape | scheme | " + " | ".join(f"{c} cells" for c in cells_list) + " |")
        out.append("|---|---|---|" + "---|" * len(cells_list))
        for scene, shape in pairs:
            for name in names:
                cols = []
                for cells in cells_list:
                    r = lookup(rows, (scene, shape, name, cells), cfl)
                    cols.append("not run (failed at a smaller CFL)" if r is None
                                else f"{r['err_x']:.3e} ({r['err_v']:.2e})" if r["outcome"] == "stable"
                                else f"{r['outcome']} at step {r['step']}")
                out.append(f"| {scene} | {shape} | {name} | " + " | ".join(cols) + " |")
    for other in ("FMPM(1)", "PIC(Std)"):
        lines = []
        for scene, shape in pairs:
            ratios = []
            for cells in cells_list:
                for cfl in cfls:
                    a = lookup(rows, (scene, shape, "XPIC(1)", cells), cfl)
                    b = lookup(rows, (scene, shape, other, cells), cfl)
                    if a and b and a["outcome"] == "stable" and b["outcome"] == "stable":
                        ratios.append(b["err_x"] / a["err_x"])
            if ratios:
                lines.append(f"- {scene}, {shape}: {len(ratios)} pairs, min {min(ratios):.3f}, median "
                             f"{float(np.median(ratios)):.3f}, max {max(ratios):.3f}")
        if lines:
            out += ["", f"## {other} against XPIC(1), same runs", "",
                    f"Ratio of {other}'s displacement error to XPIC(1)'s over every (cells, CFL) where both are "
                    "stable:", ""] + lines
    return "\n".join(out) + "\n"


def read_rows(path) -> list[dict]:
    """The rows of a CSV written by :func:`main`, with their numbers."""
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    for r in rows:
        r["cells"], r["step"] = int(r["cells"]), int(r["step"])
        for k in ("cfl", "dt", "time", "err_x", "err_v", "wall_s"):
            r[k] = float(r[k])
    return rows


def main():
    import sys

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--periods", type=float, default=None)
    parser.add_argument("--schemes", nargs="*", default=list(schemes()))
    parser.add_argument("--scenes", nargs="*", default=["linear", "sine"], choices=list(SCENES))
    parser.add_argument("--shapes", nargs="*", default=["Linear"], choices=list(SHAPES))
    parser.add_argument("--cells", nargs="*", type=int, default=None)
    parser.add_argument("--name", default=None, help="output name under experiments/results (default seed_claims)")
    parser.add_argument("--append", action="store_true",
                        help="keep the rows of <name>.csv for the (scene, shape) pairs not run now, and report all")
    parser.add_argument("--report-only", action="store_true", help="rewrite <name>.md from <name>.csv, run nothing")
    args = parser.parse_args()
    cells = tuple(args.cells) if args.cells else ((16,) if args.quick else CELLS)
    cfls = (0.2, 0.5, 0.8, 1.0, 1.2) if args.quick else CFLS
    periods = args.periods if args.periods is not None else (2.0 if args.quick else 4.0)
    horizon = periods * 0.02
    name = args.name or ("seed_claims_quick" if args.quick else "seed_claims")
    if args.report_only:
        rows = read_rows(RESULTS / f"{name}.csv")
        text = report(rows, cfls, horizon, (0.2,) if args.quick else (0.2, 0.5), sum(r["wall_s"] for r in rows),
                      APPENDED)
        (RESULTS / f"{name}.md").write_text(text)
        print(text)
        return
    start = time.perf_counter()
    rows = sweep(args.scenes, args.shapes, args.schemes, cells, cfls, horizon)
    wall = time.perf_counter() - start
    RESULTS.mkdir(parents=True, exist_ok=True)
    if args.append and (RESULTS / f"{name}.csv").exists():
        ran = {(r["scene"], r["shape"]) for r in rows}
        kept = [r for r in read_rows(RESULTS / f"{name}.csv") if (r["scene"], r["shape"]) not in ran]
        rows = kept + rows
    with open(RESULTS / f"{name}.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=FIELDS)
        w.writeheader()
        for r in rows:
            w.writerow({k: (f"{r[k]:.6g}" if isinstance(r[k], float) else r[k]) for k in FIELDS})
    command = "`" + " ".join(["python experiments/seed_claims.py"] + sys.argv[1:]) + "`"
    if args.append:
        command, wall = APPENDED, sum(r["wall_s"] for r in rows)

    text = report(rows, cfls, horizon, (0.2,) if args.quick else (0.2, 0.5), wall, command.strip())
    (RESULTS / f"{name}.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
