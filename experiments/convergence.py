"""Spatial convergence on the axis-aligned manufactured solution (``mms`` scene, Wallstedt &
Guilkey 2008) in 1D: error against cell size for every shape function and particle update.

For each amplitude (small A = 1e-4, large A = 0.05), shape function (Linear, uGIMP, quadratic and
cubic B-splines), particle update (FLIP, XPIC(5), FMPM(4) and APIC when ``jm.APIC`` exists) and cell
count, one period of the motion is run (float64, USL, 2 particles per cell) and the error is

    e_x = max over saved frames of RMS_p |x_p - X_p - u(X_p, t)| / A
    e_v = max over saved frames of RMS_p |V_p - du/dt(X_p, t)| / (A c pi)

over the particles of [0, 1].  The observed order is the least-squares slope of log e against
log h.  Choices that matter (see ``jaxmpm/scenes/mms.py``):

* ``boundary="extended"`` (main study): the body is the odd continuation of the solution on
  [-1/2, 3/2], so the walls X = 0, 1 are interior symmetry planes and B-splines are not truncated
  there.  With plain walls (``boundary="walls"``, nodes on and beyond the wall zeroed) B-splines
  and uGIMP lose an O(h) error next to the wall; that study is run for FLIP only (``--walls``).
  ``boundary="mirror"``: the body is [0, 1] and the walls are symmetry planes in the core
  (``jm.Mirror``: the particles' images folded onto the grid) -- the extension without extra
  material; run for FLIP (``--mirror``).

``--mirror-study`` runs only the mirror rows, for the B-splines: the mms rows (walls, mirror,
extended; FLIP) and the ``bar`` scene (fixed-free bar, x = 0 held by ``jm.Fixed`` on the nodes
x <= 0 or by ``jm.Mirror``), whose error is the relative L2 error of the centre-of-mass velocity
against the exact first mode over t in [0, 40], at the scene's v0 = 0.1 ("large": the free end
swings 0.16, up to a cell at 128 cells) and at v0 = 1e-4 ("small"); cfl = 0.1 * 16 / cells
(dt ~ h^2).  Writes ``convergence_mirror.csv`` and ``convergence_mirror.md``.
* dt shrinks like h^2 (cfl = 0.2 * 8 / cells, ``--dt-scaling h2``): USL's particle velocities and
  FLIP/XPIC/FMPM's positions lag the exact solution by half a step, an O(dt) error; at a fixed CFL
  (``--dt-scaling h``) it would cap every observed order at 1 once the grid is fine.

Writes ``experiments/results/convergence.csv`` (one row per run), ``convergence_small.png`` and
``convergence_large.png`` (error against h, one panel per shape function), and prints a Markdown
table of observed orders (also written to ``convergence.md``).

    python experiments/convergence.py            # cells 8..128, ~10 min on 2 CPU cores
    python experiments/convergence.py --quick    # cells 8, 16, 32; FLIP and APIC only
    python experiments/convergence.py --mirror-study   # B-spline mirror rows (mms and bar), ~10 min
"""

from __future__ import annotations

import argparse
import csv
import math
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

import jaxmpm as jm  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"
AMPLITUDES = {"small": 1e-4, "large": 0.05}
CFL_COARSE, CELLS_COARSE = 0.2, 8
PPC = 2


def shapes() -> dict:
    return {"Linear": jm.Linear(), "UGIMP": jm.UGIMP(ppc=PPC), "Quadratic": jm.QuadraticBSpline(),
            "Cubic": jm.CubicBSpline()}


def schemes(quick: bool) -> dict:
    out = {"FLIP": jm.FLIP(), "XPIC(5)": jm.XPIC(order=5), "FMPM(4)": jm.FMPM(order=4)}
    if hasattr(jm, "APIC"):
        out["APIC"] = jm.APIC()
    if quick:
        out = {k: v for k, v in out.items() if k in ("FLIP", "APIC")}
    return out


def cfl_for(cells: int, scaling: str) -> float:
    """cfl = 0.2 (8 / cells) for dt ~ h^2, or 0.2 for dt ~ h."""
    return CFL_COARSE * CELLS_COARSE / cells if scaling == "h2" else CFL_COARSE


def run_one(amplitude, boundary, shape, scheme, cells, scaling, frames) -> dict:
    """One period of the MMS; errors relative to A and A c pi, or NaN if the run went unstable."""
    setup = jm.scene("mms", dim=1, cells=cells, ppc=PPC, shape=shape, scheme=scheme, amplitude=amplitude,
                     boundary=boundary, cfl=cfl_for(cells, scaling), frames=frames)
    c = setup.params["c"]
    row = dict(amplitude=amplitude, boundary=boundary, cells=cells, h=1.0 / cells, dt=setup.dt, steps=setup.steps,
               status="ok")
    start = time.perf_counter()
    try:
        _, history = setup.run()
        jax.block_until_ready(history)
    except jm.InstabilityError as err:
        row.update(status=f"unstable at t = {err.time:.3g}: {err.cause.split(' (')[0]}",
                   disp_error=math.nan, vel_error=math.nan, wall_s=time.perf_counter() - start)
        return row
    row["wall_s"] = time.perf_counter() - start
    ex, ev = setup.reference.errors(history.time, history.x, history.v)
    row["disp_error"] = float(ex.max() / amplitude)
    row["vel_error"] = float(ev.max() / (amplitude * c * math.pi))
    return row


BAR_V0 = {"small": 1e-4, "large": 0.1}
BAR_CELLS = (16, 32, 64)


def run_bar(v0, boundary, shape, cells) -> dict:
    """The fixed-free ``bar`` to t = 40 (four periods) at cfl = 0.1 * 16 / cells; the relative L2
    error of v_cm(t) against v0/(beta1 L) cos(omega t) over the saved frames."""
    setup = jm.scene("bar", cells=cells, shape=shape, scheme=jm.FLIP(), boundary=boundary, v0=v0,
                     cfl=0.1 * BAR_CELLS[0] / cells, frames=200)
    start = time.perf_counter()
    _, history = setup.run()
    mass = np.asarray(setup.state.mass)
    v_cm = np.asarray(history.v)[..., 0] @ mass / mass.sum()
    exact = setup.reference(np.asarray(history.time))
    error = float(np.linalg.norm(v_cm - exact) / np.linalg.norm(exact))
    return dict(v0=v0, boundary=boundary, cells=cells, h=setup.params["length"] / cells, dt=setup.dt,
                steps=setup.steps, error=error, wall_s=time.perf_counter() - start)


def mirror_study(out: Path, frames: int, mms_cells=(8, 16, 32), parts=("mms", "bar"),
                 boundaries=("walls", "mirror", "extended")):
    """The B-spline rows of the mirror boundary: mms (``boundaries``) and bar (fixed / mirror)."""
    rows, bar_rows = [], []
    start = time.perf_counter()
    for size, amplitude in (AMPLITUDES.items() if "mms" in parts else ()):
        for shape_name in ("Quadratic", "Cubic"):
            for boundary in boundaries:
                for n in mms_cells:
                    row = run_one(amplitude, boundary, shapes()[shape_name], jm.FLIP(), n, "h2", frames)
                    row.update(shape=shape_name, scheme="FLIP")
                    rows.append(row)
                errs = " ".join(fmt(r["disp_error"], "{:.2e}") for r in rows[-len(mms_cells):])
                print(f"[{time.perf_counter() - start:6.0f} s] mms {size:5s} {boundary:8s} {shape_name:9s} e_x: {errs}",
                      flush=True)
    for size, v0 in (BAR_V0.items() if "bar" in parts else ()):
        for shape_name in ("Quadratic", "Cubic"):
            for boundary in ("fixed", "mirror"):
                for n in BAR_CELLS:
                    row = run_bar(v0, boundary, shapes()[shape_name], n)
                    row.update(shape=shape_name, size=size)
                    bar_rows.append(row)
                errs = " ".join(f"{r['error']:.3e}" for r in bar_rows[-len(BAR_CELLS):])
                print(f"[{time.perf_counter() - start:6.0f} s] bar {size:5s} {boundary:8s} {shape_name:9s} e: {errs}",
                      flush=True)
    suffix = "" if len(parts) == 2 else f"_{parts[0]}"
    lines = []
    if "mms" in parts:
        write_csv(out / "convergence_mirror_mms.csv", rows)
        lines += [markdown(summarise(rows), list(mms_cells), "h2"), ""]
    if "bar" in parts:
        with (out / "convergence_mirror_bar.csv").open("w", newline="") as f:
            fields = ["size", "v0", "boundary", "shape", "cells", "h", "dt", "steps", "error", "wall_s"]
            w = csv.DictWriter(f, fieldnames=fields)
            w.writeheader()
            for r in bar_rows:
                w.writerow({k: (f"{r[k]:.10g}" if isinstance(r[k], float) else r[k]) for k in fields})
        lines += ["| scene | boundary | shape | small: errors | small: order | large: errors | large: order |",
                  "|---|---|---|---|---|---|---|"]
    for shape_name in (("Quadratic", "Cubic") if "bar" in parts else ()):
        for boundary in ("fixed", "mirror"):
            cells_of = {size: [r for r in bar_rows if (r["shape"], r["boundary"], r["size"])
                               == (shape_name, boundary, size)] for size in BAR_V0}
            cols = []
            for size in BAR_V0:
                sel = cells_of[size]
                cols += [", ".join(f"{r['error']:.2e}" for r in sel),
                         fmt(observed_order([r["h"] for r in sel], [r["error"] for r in sel]))]
            lines.append(f"| bar | {boundary} | {shape_name} | " + " | ".join(cols) + " |")
    if "bar" in parts:
        lines.append(f"\nbar: FLIP, USL, 2 particles per cell, cells {', '.join(map(str, BAR_CELLS))} along the bar, "
                     "cfl = 0.1 * 16/cells; error = relative L2 error of v_cm over t in [0, 40]; small v0 = 1e-4, "
                     "large v0 = 0.1 (the scene's).  Orders: least-squares slopes over all cell counts.")
    table = "\n".join(lines)
    (out / f"convergence_mirror{suffix}.md").write_text(table + "\n")
    print()
    print(table)
    print(f"\nwrote {out / f'convergence_mirror{suffix}.md'} ({time.perf_counter() - start:.0f} s)")


def observed_order(h, err) -> float:
    """Least-squares slope of log(err) against log(h) over the finite errors (NaN if < 2)."""
    h, err = np.asarray(h, float), np.asarray(err, float)
    ok = np.isfinite(err) & (err > 0)
    if ok.sum() < 2:
        return math.nan
    return float(np.polyfit(np.log(h[ok]), np.log(err[ok]), 1)[0])


def monotone(err) -> bool:
    """True if the error falls at every refinement."""
    err = np.asarray(err, float)
    return bool(np.all(np.isfinite(err)) and np.all(np.diff(err) < 0))


def summarise(rows) -> list[dict]:
    """One entry per (boundary, shape, scheme): orders and finest errors for both amplitudes."""
    keys = []
    for r in rows:
        k = (r["boundary"], r["shape"], r["scheme"])
        if k not in keys:
            keys.append(k)
    table = []
    for boundary, shape, scheme in keys:
        entry = dict(boundary=boundary, shape=shape, scheme=scheme)
        for size, amplitude in AMPLITUDES.items():
            sel = sorted((r for r in rows if (r["boundary"], r["shape"], r["scheme"], r["amplitude"])
                          == (boundary, shape, scheme, amplitude)), key=lambda r: r["cells"])
            h = [r["h"] for r in sel]
            ex, ev = [r["disp_error"] for r in sel], [r["vel_error"] for r in sel]
            entry[f"{size}_disp_order"] = observed_order(h, ex)
            entry[f"{size}_vel_order"] = observed_order(h, ev)
            entry[f"{size}_disp_finest"] = ex[-1] if ex else math.nan
            entry[f"{size}_monotone"] = monotone(ex)
            entry[f"{size}_failed"] = sum(r["status"] != "ok" for r in sel)
        table.append(entry)
    return table


def fmt(v, spec="{:.2f}"):
    return "—" if v is None or not math.isfinite(v) else spec.format(v)


def markdown(table, cells, scaling) -> str:
    lines = [
        "| boundary | shape | scheme | small: order e_x | small: order e_v | small: e_x finest | "
        "large: order e_x | large: order e_v | large: e_x finest | notes |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for t in table:
        notes = []
        for size in AMPLITUDES:
            if t[f"{size}_failed"]:
                notes.append(f"{size}: {t[f'{size}_failed']} unstable")
            elif not t[f"{size}_monotone"]:
                notes.append(f"{size}: e_x not monotone")
        lines.append(
            f"| {t['boundary']} | {t['shape']} | {t['scheme']} | {fmt(t['small_disp_order'])} | "
            f"{fmt(t['small_vel_order'])} | {fmt(t['small_disp_finest'], '{:.2e}')} | {fmt(t['large_disp_order'])} | "
            f"{fmt(t['large_vel_order'])} | {fmt(t['large_disp_finest'], '{:.2e}')} | {'; '.join(notes)} |")
    lines.append(
        f"\n1D axis-aligned MMS (Wallstedt & Guilkey 2008), neo-Hookean E = 1e4, nu = 0.3, rho0 = 1, one period; "
        f"cells {', '.join(map(str, cells))}; {PPC} particles per cell; float64, USL; "
        f"dt ~ {'h^2 (cfl = 0.2 * 8/cells)' if scaling == 'h2' else 'h (cfl = 0.2)'}.  Orders: least-squares slope "
        "of log error against log h over all cell counts.  e_x = max_t RMS displacement error / A, "
        "e_v = max_t RMS velocity error / (A c pi); small A = 1e-4, large A = 0.05.")
    return "\n".join(lines)


def write_csv(path: Path, rows):
    fields = ["amplitude", "boundary", "shape", "scheme", "cells", "h", "dt", "steps", "disp_error", "vel_error",
              "status", "wall_s"]
    with path.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=fields)
        w.writeheader()
        for r in rows:
            w.writerow({k: (f"{r[k]:.10g}" if isinstance(r[k], float) else r[k]) for k in fields})


def plot(path: Path, rows, amplitude, label):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(shapes())
    fig, axes = plt.subplots(1, len(names), figsize=(4.2 * len(names), 4.2), sharey=True)
    for ax, shape in zip(axes, names):
        sel = [r for r in rows if r["shape"] == shape and r["amplitude"] == amplitude]
        for boundary, scheme in sorted({(r["boundary"], r["scheme"]) for r in sel}):
            pts = sorted((r for r in sel if (r["boundary"], r["scheme"]) == (boundary, scheme)), key=lambda r: r["h"])
            h = np.array([r["h"] for r in pts])
            style = {"walls": ":", "mirror": "--"}.get(boundary, "-")
            name = scheme if boundary == "extended" else f"{scheme}, {boundary}"
            line, = ax.loglog(h, [r["disp_error"] for r in pts], style, marker="o", ms=3, label=f"{name}: e_x")
            ax.loglog(h, [r["vel_error"] for r in pts], style, marker="x", ms=4, color=line.get_color(), alpha=0.45)
        h_ref = np.array(sorted({r["h"] for r in sel}))
        if h_ref.size:
            ax.loglog(h_ref, 0.5 * (h_ref / h_ref[-1]) ** 2, "k--", lw=0.8, label="h^2")
            ax.loglog(h_ref, 0.5 * (h_ref / h_ref[-1]), "k-.", lw=0.8, label="h")
        ax.set_title(shape)
        ax.set_xlabel("h")
        ax.grid(alpha=0.3, which="both")
    axes[0].set_ylabel("max_t RMS error (o: e_x / A, x: e_v / (A c pi))")
    axes[0].legend(fontsize=7)
    fig.suptitle(f"1D axis-aligned MMS, {label} deformation (A = {amplitude:g}): error against cell size")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="cells 8, 16, 32; FLIP and APIC only (CI size)")
    parser.add_argument("--cells", type=int, nargs="+", default=None, help="cell counts (even; default 8 16 32 64 128)")
    parser.add_argument("--dt-scaling", choices=["h2", "h"], default="h2",
                        help="h2: cfl = 0.2*8/cells (default); h: fixed cfl = 0.2")
    parser.add_argument("--walls", choices=["flip", "all", "none"], default="flip",
                        help="also run boundary='walls' for FLIP (default), every scheme, or none")
    parser.add_argument("--mirror", choices=["flip", "all", "none"], default="flip",
                        help="also run boundary='mirror' (jm.Mirror) for FLIP (default), every scheme, or none")
    parser.add_argument("--mirror-study", action="store_true",
                        help="only the B-spline mirror rows: mms (walls/mirror/extended) and bar (fixed/mirror)")
    parser.add_argument("--part", nargs="+", choices=["mms", "bar"], default=["mms", "bar"],
                        help="with --mirror-study: the scenes to run (each part alone writes *_mms / *_bar files)")
    parser.add_argument("--mms-boundaries", nargs="+", choices=["walls", "mirror", "extended"],
                        default=["walls", "mirror", "extended"], help="with --mirror-study: the mms boundaries")
    parser.add_argument("--frames", type=int, default=40, help="saved frames per period (the max over time uses them)")
    parser.add_argument("--out", type=Path, default=RESULTS, help="results folder")
    args = parser.parse_args(argv)
    cells = args.cells or ([8, 16, 32] if args.quick else [8, 16, 32, 64, 128])
    args.out.mkdir(parents=True, exist_ok=True)
    if args.mirror_study:
        mirror_study(args.out, args.frames, tuple(args.cells or (8, 16, 32)), tuple(args.part),
                     tuple(args.mms_boundaries))
        return

    rows = []
    start = time.perf_counter()
    for size, amplitude in AMPLITUDES.items():
        for shape_name, shape in shapes().items():
            for scheme_name, scheme in schemes(args.quick).items():
                boundaries = ["extended"]
                if args.walls == "all" or (args.walls == "flip" and scheme_name == "FLIP"):
                    boundaries.append("walls")
                if args.mirror == "all" or (args.mirror == "flip" and scheme_name == "FLIP"):
                    boundaries.append("mirror")
                for boundary in boundaries:
                    for n in cells:
                        row = run_one(amplitude, boundary, shape, scheme, n, args.dt_scaling, args.frames)
                        row.update(shape=shape_name, scheme=scheme_name)
                        rows.append(row)
                    errs = " ".join(fmt(r["disp_error"], "{:.2e}") for r in rows[-len(cells):])
                    print(f"[{time.perf_counter() - start:6.0f} s] {size:5s} {boundary:8s} {shape_name:9s} "
                          f"{scheme_name:7s} e_x: {errs}", flush=True)
    suffix = "_quick" if args.quick else ""
    csv_path = args.out / f"convergence{suffix}.csv"
    write_csv(csv_path, rows)
    pngs = []
    for size, amplitude in AMPLITUDES.items():
        png = args.out / f"convergence_{size}{suffix}.png"
        plot(png, rows, amplitude, size)
        pngs.append(png)
    table = markdown(summarise(rows), cells, args.dt_scaling)
    (args.out / f"convergence{suffix}.md").write_text(table + "\n")
    print()
    print(table)
    print(f"\nwrote {csv_path}, {', '.join(map(str, pngs))} ({time.perf_counter() - start:.0f} s)")


if __name__ == "__main__":
    main()
