"""Speed against accuracy, and the stability map, of every particle update on the material scenes
(issue 31 item 6): ``column_collapse`` (Drucker-Prager sand, a = H0/L0 = 2) and ``dam_break``
(Martin & Moyce's water column, weakly compressible Newtonian fluid).

Each particle update -- FLIP, the 0.99 FLIP/PIC blend, PIC, XPIC(m) for m = 2, 5, FMPM(k) for
k = 1, 2, 4, APIC, TPIC and RPIC -- runs each scene with three shape functions (``--shapes``): the
scenes' default quadratic B-spline, the linear hat, and uGIMP (the fix of the linear hat's
cell-crossing error).  XPIC(1) is PIC itself (000 eq. 3.12 with m = 1 is the FLIP/PIC blend, and
``jm.XPIC``'s default beta is 0): its row would repeat PIC's, so it is not run again.  FLIP, the
blend and PIC are one pytree type (``jm.XPIC(order=1, beta)``) and share one compiled loop.

Error against the experiment:

* ``column_collapse`` at a = 2, the scene's default 8 cells across the column (``--column-cells``),
  2x2 particles per cell (1024 particles, 2760 steps with the quadratic B-spline),
  t_end = 5 sqrt(H0/g): the relative errors of the final run-out, ((L-L0)/L0) / (1.2 a) - 1, and
  of the final height, (H/L0) / a^(2/5) - 1, against the scalings of Lube et al. 2005
  and Lajeunesse et al. 2005 (:func:`jaxmpm.scenes.column_collapse.runout_scaling`,
  :func:`~jaxmpm.scenes.column_collapse.height_scaling`); the chart plots the mean of their
  magnitudes, the table gives each with its sign (< 0: short of the scaling).
* ``dam_break`` at the scene's defaults (8 cells across the column width a, 2x2 particles per
  cell, T = t sqrt(2 g / a) up to 5.5): the RMS of the surge front Z = x_front / a against Martin &
  Moyce 1952's points (:func:`jaxmpm.scenes.dam_break.front_error`), in column widths a.

Wall time: the seconds of the run's steps alone, compilation apart -- the run goes through the
chunked driver (``progress=True``, its bar switched off by ``TQDM_DISABLE``), which compiles the
loop before the first step and reports ``timings["compile"]`` and ``timings["run"]`` separately;
the best of two runs (the second reuses the compiled loop).  The CPU is shared with other work:
the times are good to tens of percent.

The stability map: a run that raises :class:`jaxmpm.InstabilityError` (a NaN/Inf, J = det F <= 0,
or :class:`jaxmpm.ParticlesLeftGrid`) is a *failure*, recorded with its step, time and cause.  A run
that reaches its end is flagged (the criteria, over the saved frames, 50 per run):

* ``noise`` -- the particle velocities scatter within a cell: at the last frame, the RMS over the
  particles of the residual of V_p against the affine field fitted to the particles of its cell
  (:func:`velocity_scatter`), divided by the largest RMS particle speed of the run, exceeds
  NOISE = 0.05.  (A smooth velocity field is close to affine across a cell; the particle-to-particle
  jitter of FLIP's null-space noise is not, and it does not decay.)
* ``not at rest`` -- ``column_collapse`` only, whose sand is at rest by t = 3 sqrt(H0/g) (Lube et
  al. 2005): the kinetic energy of the last frame (t = 5 sqrt(H0/g)) exceeds AT_REST = 1% of its
  peak.  With ``noise`` it is ringing (the particles jitter in a deposit that should be still);
  without, a deposit still creeping.  (The dam break's water is still surging at T = 5.5, so the
  test does not apply there.)
* ``clumping`` -- the largest number of particles in one cell, over all frames, exceeds
  CLUMPING = 3 times its initial value (2x2 per cell: more than 12 in a cell).
* ``energy growth`` -- the total mechanical energy E = kinetic + strain + m g y (gravity's potential,
  so E(0) + the work of gravity is E(0) - the potential energy released) rises above its initial
  value by more than GROWTH = 1% of the largest potential energy released in the run.  Plasticity,
  viscosity and PIC-type transfers only dissipate, so E must not grow.

Cost on the shared 2-core CPU: 2.4-3.6 min for the 66 cases (11 schemes x 3 shapes x 2 scenes,
each run twice unless it failed) with jaxmpm's compilation cache on disk (``jm.compilation_cache``)
holding the programs of an earlier run -- the table's "compile" column is then mostly loading --
and about 8 min cold (each scheme and shape compiles in 5-15 s; the runs take 0.2-1.6 s).

Outputs: ``experiments/results/speed_accuracy_materials.md`` (the table) and ``.csv``, the figure
``experiments/figures/speed_accuracy_materials.png`` (error against wall time, one panel per scene,
marker by family, colour by shape, the failed runs listed in a box in their panel), and the table
printed.

    python experiments/speed_accuracy_materials.py                    # the whole chart (66 cases)
    python experiments/speed_accuracy_materials.py --schemes apic flip --shapes quadratic --scenes dam_break
    python experiments/speed_accuracy_materials.py --plot-only        # redraw the figure from the CSV
"""

from __future__ import annotations

import argparse
import csv
import math
import os
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

import jaxmpm as jm  # noqa: E402
from jaxmpm.scenes.column_collapse import normalised_deposit  # noqa: E402
from jaxmpm.scenes.dam_break import front_error  # noqa: E402

HERE = Path(__file__).resolve().parent
RESULTS, FIGURES = HERE / "results", HERE / "figures"

#: name -> (label, family, constructor)
SCHEMES = {
    "flip": ("FLIP", "FLIP/PIC", lambda: jm.FLIP()),
    "blend": ("FLIP(0.99)", "FLIP/PIC", lambda: jm.FLIP(beta=0.99)),
    "pic": ("PIC", "FLIP/PIC", lambda: jm.PIC()),
    "xpic2": ("XPIC(2)", "XPIC", lambda: jm.XPIC(order=2)),
    "xpic5": ("XPIC(5)", "XPIC", lambda: jm.XPIC(order=5)),
    "fmpm1": ("FMPM(1)", "FMPM", lambda: jm.FMPM(order=1)),
    "fmpm2": ("FMPM(2)", "FMPM", lambda: jm.FMPM(order=2)),
    "fmpm4": ("FMPM(4)", "FMPM", lambda: jm.FMPM(order=4)),
    "apic": ("APIC", "affine", lambda: jm.APIC()),
    "tpic": ("TPIC", "affine", lambda: jm.TPIC()),
    "rpic": ("RPIC", "affine", lambda: jm.RPIC()),
}
SHAPES = {"quadratic": ("quadratic B-spline", lambda: jm.QuadraticBSpline()), "linear": ("linear", lambda: jm.Linear()),
          "ugimp": ("uGIMP", lambda: jm.UGIMP(ppc=2)), "cubic": ("cubic B-spline", lambda: jm.CubicBSpline())}
SCENES = ("column_collapse", "dam_break")
ASPECT = 2.0  # the column's aspect ratio a = H0 / L0
FRAMES = 50  # saved frames per run, for the flags

NOISE = 0.05  # intra-cell velocity scatter / peak RMS speed
AT_REST = 0.01  # final / peak kinetic energy (column_collapse: the sand must be at rest)
CLUMPING = 3.0  # max particles per cell / its initial value
GROWTH = 0.01  # rise of the mechanical energy / the largest potential energy released


# ---------------------------------------------------------------------------------------- the flags
def cell_counts(x, grid):
    """The number of particles in each occupied cell, per frame: x (T, N, D) -> list of (cells,) arrays
    (the cell of a particle is floor((x - lower) / h) of the grid)."""
    lower = np.asarray(grid.lower)
    h = (np.asarray(grid.upper) - lower) / np.asarray(grid.cells)
    index = np.floor((np.asarray(x) - lower) / h).astype(np.int64)
    return [np.unique(frame, axis=0, return_counts=True)[1] for frame in index]


def velocity_scatter(x, v, grid) -> float:
    """The RMS over the particles of the residual of V_p against the affine field V = a + B (x - x_c)
    fitted (least squares) to the particles of its cell, of one frame x, v (N, D); cells with fewer
    than D + 2 particles (the free surface, a thin front) are left out.  An affine field, the part
    of a smooth velocity field that a cell resolves, scatters by 0; the particle-to-particle
    jitter of FLIP's null-space noise does not fit it."""
    x, v = np.asarray(x), np.asarray(v)
    lower = np.asarray(grid.lower)
    h = (np.asarray(grid.upper) - lower) / np.asarray(grid.cells)
    _, cell = np.unique(np.floor((x - lower) / h).astype(np.int64), axis=0, return_inverse=True)
    cell = cell.ravel()
    squares, count = 0.0, 0
    for members in np.split(np.argsort(cell, kind="stable"), np.cumsum(np.bincount(cell))[:-1]):
        if len(members) < x.shape[1] + 2:
            continue
        basis = np.hstack([np.ones((len(members), 1)), (x[members] - x[members].mean(axis=0)) / h])
        coefficients = np.linalg.lstsq(basis, v[members], rcond=None)[0]
        squares += float(np.sum((v[members] - basis @ coefficients) ** 2))
        count += len(members)
    return math.sqrt(squares / count) if count else math.nan


def stability_flags(scene: str, history, setup) -> dict:
    """The flags of a run that reached its end (the module docstring's criteria) and their measures."""
    sim, state = setup.sim, setup.state
    g = setup.params["gravity"]
    mass = np.asarray(state.mass)
    x, v = np.asarray(history.x), np.asarray(history.v)
    potential = g * (x[..., 1] * mass).sum(axis=1)  # m g y per frame
    mechanical = np.asarray(history.kinetic) + np.asarray(history.strain) + potential
    released = max(float((potential[0] - potential).max()), 1e-300)
    growth = float((mechanical - mechanical[0]).max()) / released
    speed = np.sqrt((np.sum(v**2, axis=2)).mean(axis=1))  # RMS particle speed per frame
    noise = velocity_scatter(x[-1], v[-1], sim.grid) / max(float(speed.max()), 1e-300)
    kinetic = np.asarray(history.kinetic)
    ke_end = float(kinetic[-1] / max(float(kinetic.max()), 1e-300)) if scene == "column_collapse" else math.nan
    counts = cell_counts(x, sim.grid)
    clumping = max(int(c.max()) for c in counts) / int(counts[0].max())
    measures = {"noise": noise, "ke_end": ke_end, "clumping": clumping, "energy_growth": growth}
    return measures | {"flags": flags_of(measures)}


def flags_of(measures: dict) -> str:
    """The flags the measures raise, against the thresholds (a NaN measure raises none)."""
    return ", ".join(name for name, bad in (
        ("noise", measures["noise"] > NOISE), ("not at rest", measures["ke_end"] > AT_REST),
        ("clumping", measures["clumping"] > CLUMPING), ("energy growth", measures["energy_growth"] > GROWTH)) if bad)


# ------------------------------------------------------------------------------------------ one run
def build(scene: str, scheme, shape, column_cells: int, steps: int | None = None):
    """The scene's setup; ``steps`` (a smoke test) cuts the run to that many steps, FRAMES frames."""
    if scene == "column_collapse":
        setup = jm.scene("column_collapse", aspect=ASPECT, cells=column_cells, scheme=scheme, shape=shape,
                         frames=FRAMES)
    else:
        setup = jm.scene("dam_break", scheme=scheme, shape=shape, frames=FRAMES)
    if steps is not None:
        setup.steps, setup.save_every = steps, max(1, steps // FRAMES)
        setup.steps -= setup.steps % setup.save_every
    return setup


def scene_error(scene: str, setup, final, history) -> dict:
    """The error against the experiment (the module docstring; the column's relative errors signed,
    < 0 short of the scaling), ``error`` the one the chart plots."""
    if scene == "column_collapse":
        d = normalised_deposit(setup, final.x)
        runout = d["runout"] / d["runout_scaling"] - 1.0  # signed: < 0 short of the experiments
        height = d["height"] / d["height_scaling"] - 1.0
        return {"runout": d["runout"], "height": d["height"], "runout_error": runout, "height_error": height,
                "front_rms": math.nan, "error": 0.5 * (abs(runout) + abs(height))}
    rms, _ = front_error(history.time, history.x, setup.params)
    return {"runout": math.nan, "height": math.nan, "runout_error": math.nan, "height_error": math.nan,
            "front_rms": rms, "error": rms}


EMPTY = {"runout": math.nan, "height": math.nan, "runout_error": math.nan, "height_error": math.nan,
         "front_rms": math.nan, "error": math.nan, "noise": math.nan, "ke_end": math.nan, "clumping": math.nan,
         "energy_growth": math.nan, "flags": ""}


def run_case(scene: str, scheme: str, shape: str, column_cells: int = 8, steps: int | None = None,
             setup=None, repeats: int = 2) -> dict:
    """One run: the row of the table, its wall time the best of ``repeats`` runs (a failed run's is
    its only one).  ``setup`` (tests: a setup to break) replaces the scene's."""
    label, family, make = SCHEMES[scheme]
    shape_label, make_shape = SHAPES[shape]
    if setup is None:
        setup = build(scene, make(), make_shape(), column_cells, steps)
    timings = {}
    row = {"scene": scene, "scheme": label, "family": family, "shape": shape_label,
           "cells": setup.params["cells"], "particles": int(setup.state.x.shape[0]), "steps": setup.steps}
    try:
        final, history = setup.run(progress=True, timings=timings)
    except jm.InstabilityError as err:  # a failure: the stability map's entry, with its step and cause
        when = "" if err.time is None else f", t = {err.time:.3g} s"
        return row | {"compile_s": timings.get("compile", math.nan), "run_s": timings.get("run", math.nan),
                      "failure": f"{err.cause.split(' (')[0]} (step {err.step}{when})"} | EMPTY
    again = {}
    for _ in range(repeats - 1):  # the compiled loop again: the best time of a shared CPU
        setup.run(progress=True, timings=again)
        timings["run"] = min(timings["run"], again["run"])
    row |= {"compile_s": timings["compile"], "run_s": timings["run"], "failure": ""}
    return row | scene_error(scene, setup, final, history) | stability_flags(scene, history, setup)


# ---------------------------------------------------------------------------------------- outputs
def _percent(value, sign: str = "") -> str:
    return "" if math.isnan(value) else format(value, sign + ".0%")


def caption(rows) -> str:
    """The settings and the flags' thresholds, above the table in the Markdown file."""
    cells = {scene: "/".join(str(c) for c in sorted({int(r["cells"]) for r in rows if r["scene"] == scene}))
             for scene in SCENES}
    return (f"column_collapse at a = {ASPECT:g} ({cells['column_collapse']} cells across the column), dam_break "
            f"at its defaults ({cells['dam_break']} cells across the column); errors against Lube et al. 2005 / "
            "Martin & Moyce 1952; run (s): the "
            "steps' wall time, compile apart, best of two (shared 2-core CPU). Flags: noise = affine-residual "
            f"velocity scatter / peak RMS speed > {NOISE:g}; not at rest = KE end/peak > {AT_REST:.0%} (column "
            f"only); clumping = max particles per cell / initial > {CLUMPING:g}; energy growth = rise of kinetic + "
            f"strain + m g y above its initial value / potential energy released > {GROWTH:.0%}. "
            "`python experiments/speed_accuracy_materials.py`\n\n")


def table(rows) -> str:
    lines = ["| scene | scheme | shape | run-out error | height error | front RMS (Z) | run (s) | compile (s) | "
             "noise | KE end/peak | clumping | energy growth | outcome |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        def number(key, fmt):
            return "" if math.isnan(r[key]) else format(r[key], fmt)
        outcome = f"failed: {r['failure']}" if r["failure"] else (r["flags"] or "stable")
        lines.append(f"| {r['scene']} | {r['scheme']} | {r['shape']} | {_percent(r['runout_error'], '+')} | "
                     f"{_percent(r['height_error'], '+')} | {number('front_rms', '.2f')} | {r['run_s']:.1f} | "
                     f"{r['compile_s']:.1f} | {number('noise', '.3f')} | {_percent(r['ke_end'])} | "
                     f"{number('clumping', '.1f')} | {number('energy_growth', '+.1%')} | {outcome} |")
    return "\n".join(lines)


FAMILY_MARKERS = {"FLIP/PIC": "o", "XPIC": "s", "FMPM": "D", "affine": "^"}


def failures_text(rows, schemes: int) -> str:
    """The failed runs of one scene, a line per shape: "linear: every scheme (J = det F <= 0, steps
    72-87)" where all ``schemes`` failed, else each scheme with its cause and step."""
    lines = []
    for shape in dict.fromkeys(r["shape"] for r in rows):
        failed = [r for r in rows if r["shape"] == shape and r["failure"]]
        if not failed:
            continue
        causes = {r["failure"].split(" (step")[0] for r in failed}
        steps = [int(r["failure"].split("(step ")[1].split(",")[0].rstrip(")")) for r in failed]
        if len(failed) == schemes and len(causes) == 1:
            lines.append(f"{shape}: every scheme ({causes.pop()}, steps {min(steps)}-{max(steps)})")
        else:
            lines += [f"{shape}: {r['scheme']} ({r['failure'].split(', t =')[0]})" for r in failed]
    return "failed:\n" + "\n".join(lines) if lines else ""


def figure(rows, path: Path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scenes = list(dict.fromkeys(r["scene"] for r in rows))
    shapes = list(dict.fromkeys(r["shape"] for r in rows))
    colour = {shape: f"C{i}" for i, shape in enumerate(shapes)}
    schemes = len(dict.fromkeys(r["scheme"] for r in rows))
    fig, axes = plt.subplots(1, len(scenes), figsize=(6.5 * len(scenes), 5.5), squeeze=False)
    for ax, scene in zip(axes[0], scenes):
        mine = [r for r in rows if r["scene"] == scene]
        for r in mine:
            if r["failure"]:  # listed in the panel's box, not on the time axis (its time is the time to fail)
                continue
            ax.plot(r["run_s"], r["error"], FAMILY_MARKERS[r["family"]], ms=7, color=colour[r["shape"]], alpha=0.8)
            ax.annotate(r["scheme"] + ("*" if r["flags"] else ""), (r["run_s"], r["error"]), fontsize=6.5,
                        xytext=(4, 2), textcoords="offset points")
        failed = failures_text(mine, schemes)
        if failed:
            ax.text(0.98, 0.02, failed, transform=ax.transAxes, fontsize=7, ha="right", va="bottom", color="red",
                    bbox=dict(boxstyle="round", fc="white", ec="red", alpha=0.85))
        ax.set_xscale("log")
        ax.set_yscale("log")
        low, high = ax.get_ylim()
        ax.set_ylim(low / 2.2, high * 1.2)  # room for the box of failures below the points, labels above
        ax.set_xlabel("wall time of the run's steps (s, compile apart; shared 2-core CPU)")
        ax.set_ylabel("mean |relative error| of run-out and height" if scene == "column_collapse"
                      else "RMS of the front Z = x/a against Martin & Moyce")
        ax.set_title(f"{scene}" + (f" (a = {ASPECT:g})" if scene == "column_collapse" else ""))
        ax.grid(True, which="both", alpha=0.3)
    handles = [plt.Line2D([], [], marker=m, ls="", color="k", mfc="none", label=f) for f, m in FAMILY_MARKERS.items()]
    handles += [plt.Line2D([], [], marker="o", ls="", color=c, label=s) for s, c in colour.items()]
    fig.legend(handles=handles, fontsize=8, loc="lower center", ncol=len(handles))
    fig.suptitle("Speed against accuracy on the material scenes "
                 "(* = flagged: noise, not at rest, clumping or energy growth)", fontsize=10)
    fig.tight_layout(rect=(0, 0.05, 1, 1))
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)


TEXT = ("scene", "scheme", "family", "shape", "failure", "flags")


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scenes", nargs="+", default=list(SCENES), choices=list(SCENES))
    parser.add_argument("--schemes", nargs="+", default=list(SCHEMES), choices=list(SCHEMES))
    parser.add_argument("--shapes", nargs="+", default=["quadratic", "linear", "ugimp"], choices=list(SHAPES))
    parser.add_argument("--column-cells", type=int, default=8, help="cells across the column (default 8)")
    parser.add_argument("--name", default="speed_accuracy_materials", help="stem of the output files")
    parser.add_argument("--plot-only", action="store_true", help="redraw the figure from the stored CSV")
    args = parser.parse_args(argv)
    # the chunked run is for its timings, not its progress bar: off (tqdm reads this when first imported)
    os.environ.setdefault("TQDM_DISABLE", "1")
    if args.plot_only:
        with open(RESULTS / f"{args.name}.csv") as f:
            rows = [{k: v if k in TEXT else float(v) for k, v in r.items()} for r in csv.DictReader(f)]
        for r in rows:
            r["flags"] = "" if r["failure"] else flags_of(r)  # the thresholds as they stand now
        text = table(rows)
        print(text)
        (RESULTS / f"{args.name}.md").write_text(caption(rows) + text + "\n")
        figure(rows, FIGURES / f"{args.name}.png")
        return rows
    rows = []
    for scene in args.scenes:
        for shape in args.shapes:
            for scheme in args.schemes:
                rows.append(run_case(scene, scheme, shape, args.column_cells))
                r = rows[-1]
                print(f"{scene} {r['scheme']} {r['shape']}: error {r['error']:.3f}, {r['run_s']:.2f} s "
                      f"(+{r['compile_s']:.1f} s compile) {r['failure'] or r['flags']}", flush=True)
    text = table(rows)
    print(text)
    RESULTS.mkdir(exist_ok=True)
    with open(RESULTS / f"{args.name}.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    (RESULTS / f"{args.name}.md").write_text(caption(rows) + text + "\n")
    figure(rows, FIGURES / f"{args.name}.png")
    return rows


if __name__ == "__main__":
    main()
