"""Speed against accuracy: error against steady-state wall time for every particle update over a
range of resolutions, on the ``bar``, ``mms`` and ``disks`` scenes (issue "Speed against accuracy,
convergence and stability maps", item 3).

Schemes: FLIP, PIC, the 0.99 FLIP/PIC blend (000 eq. 2.86), XPIC(2), XPIC(5), XPIC(10) (000 eqs.
3.28-3.29), FMPM(1), FMPM(2), FMPM(4), FMPM(8), FMPM(16) (003 Table 2.1), APIC and TPIC; float64,
USL throughout.

Errors (the ``error`` column; ``secondary`` holds a second measure, named in ``secondary_name``):

* ``bar`` (fixed-free elastic bar in its first mode, 2 particles per cell, cfl = 0.1, dt = cfl h/c):
  relative L2 error of the centre-of-mass velocity history over the saved frames, t in [0, 40],

      e = || v_cm(t_k) - v0/(beta1 L) cos(omega t_k) ||_2 / || v0/(beta1 L) cos(omega t_k) ||_2

  against the exact modal solution ``setup.reference(t)``.  Resolutions: 8, 16, 32, 64 cells along
  the bar.  Run with linear shape functions AND with quadratic B-splines (variants "Linear",
  "Quadratic").  With linear shapes every scheme goes unstable at 64 cells (measured): the bar's
  end sits on a node, and once the free end's amplitude v0/omega = 0.159 exceeds h/4 (cells > 39)
  its last particle crosses that node, is alone in the outer cell and inverts (J <= 0, t ~ 1.06).
  Such runs are caught (``jm.InstabilityError``) and recorded as "unstable" with no error.  With
  quadratic B-splines every run is stable but converges only at first order: the fixed end zeroes
  the nodes at and beyond x = 0 instead of mirroring them (the O(h) wall error described in
  ``jaxmpm/scenes/mms.py`` for ``boundary="walls"``).  Secondary: E(40)/E(0) - 1 (kinetic + strain).
* ``mms`` (the axis-aligned manufactured solution, ``jaxmpm/scenes/mms.py``, dim = 1,
  boundary="extended", one period): the displacement error of ``experiments/convergence.py``,

      e_x = max over the saved frames of RMS_p |x_p - X_p - u(X_p, t)| / A

  from the scene's exact solution (``setup.reference.errors``), with convergence.py's settings
  imported from it (amplitudes A = 1e-4 "small" and 0.05 "large", 2 particles per cell, and
  ``cfl_for(cells, "h2")`` = 0.2 * 8/cells, i.e. dt ~ h^2 so that the O(dt) lag of USL does not
  cap the spatial order; ``--mms-dt-scaling h`` keeps cfl = 0.2 instead).  convergence.py has no
  stand-alone error function (its ``run_one`` also times the compile), so the two lines that
  apply ``reference.errors`` and the 1/A scaling are repeated here.  40 frames per period.
  Resolutions 8, 16, 32, 64 cells; linear and quadratic B-spline shapes.  Secondary: e_v =
  max_t RMS |V_p - du/dt| / (A c pi).
* ``disks`` (Sulsky's colliding elastic disks, uGIMP shapes, 2x2 particles per cell, dt = 1e-3,
  t in [0, 4], grid padded by 0.1 at every spacing): there is no exact solution, so the error is
  taken against a converged reference, a fine run (spacing 0.0125, FMPM(8)):

      e = || v_A(t_k) - v_A^ref(t_k) ||_2 / || v_A^ref(t_k) ||_2

  where v_A is the x-velocity of the centre of mass of the first disk (mass-weighted mean of its
  particles' V_x) at the 201 saved frames.  Why this measure: before contact v_A = 0.1 for every
  update (momentum is conserved), so all the error comes from the collision -- when contact starts
  (MPM disks touch through shared grid nodes, about a cell apart, so coarse grids collide early),
  how long it lasts and the rebound speed (how much kinetic energy the update and the contact
  dissipate).  Secondary: |E(4) - E_ref(4)| / E_ref(0), the total (kinetic + strain) energy
  error at t = 4.  Limits: (i) the reference is itself an MPM solution, so e measures convergence
  to MPM's own no-slip grid contact, not to an elastic-contact solution; (ii) the reference has
  its own error: the same measure between the fine FLIP and fine FMPM(8) runs is printed as the
  "reference floor" -- errors near or below it mean nothing; (iii) the finest spacing (0.025) is
  only two refinements from the reference, so its error is underestimated.  Resolutions: spacing
  0.1, 0.05, 0.025.  dt stays 1e-3 at every spacing (cfl <= 0.1 on the reference grid), so the
  coarse runs are not made cheaper by a longer step.

Wall time (``wall_s``) is the steady-state time of ``setup.run()`` (eager call: one compiled
``lax.scan`` plus the stability check): each point is run once to compile, then ``--repeats``
more times (more, up to 10, while they are very short), and the best repeat is kept; ``compile_s``
= first call - best repeat.  The blend is ``jm.FLIP(beta=0.99)``, FLIP's class with another value of
the array leaf ``beta``, so it reuses FLIP's compiled rollout and shows compile_s ~ 0 (PIC is its
own class and compiles).  The machine is shared, so the timings are noisy: ``uptime`` is printed
before and after.

Outputs in ``experiments/results/`` (``_quick`` added with ``--quick``):

* ``speed_vs_accuracy_<scene>.csv`` -- one row per (variant, scheme, resolution);
* ``speed_vs_accuracy_<scene>.png`` -- error against wall time, log-log, one panel per variant,
  one marker per scheme, its resolutions connected; the Pareto front (no other run is both faster
  and more accurate) is the black step line with ringed points;
* ``speed_vs_accuracy_disks_reference.csv`` -- the reference histories;
* ``speed_vs_accuracy.md`` -- the table printed at the end: for each scene and variant, the
  cheapest run (least wall time) whose error is <= 10%, 1% and 0.1% ("none" if no run reaches it).

    python experiments/speed_vs_accuracy.py                  # default size (~15 min on 2 busy cores)
    python experiments/speed_vs_accuracy.py --quick          # 2 schemes x 2 resolutions (< 3 min)
    python experiments/speed_vs_accuracy.py --scenes bar --schemes FLIP "FMPM(2)" APIC
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import math
import subprocess
import time
import warnings
from pathlib import Path
from typing import Callable

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

import jaxmpm as jm  # noqa: E402

if __package__:  # imported as experiments.speed_vs_accuracy
    from .convergence import AMPLITUDES, cfl_for  # noqa: E402
    from .convergence import PPC as MMS_PPC
else:  # run as a script: convergence.py sits next to this file, on sys.path[0]
    from convergence import AMPLITUDES, cfl_for  # noqa: E402
    from convergence import PPC as MMS_PPC

RESULTS = Path(__file__).resolve().parent / "results"
THRESHOLDS = (0.1, 0.01, 0.001)
MAX_REPEATS, SHORT_RUN_S = 10, 0.05  # very short runs are repeated up to MAX_REPEATS times

SCHEMES: dict[str, Callable[[], jm.Scheme]] = {
    "FLIP": lambda: jm.FLIP(),
    "PIC": lambda: jm.PIC(),
    "blend 0.99": lambda: jm.FLIP(beta=0.99),
    "XPIC(2)": lambda: jm.XPIC(order=2),
    "XPIC(5)": lambda: jm.XPIC(order=5),
    "XPIC(10)": lambda: jm.XPIC(order=10),
    "FMPM(1)": lambda: jm.FMPM(order=1),
    "FMPM(2)": lambda: jm.FMPM(order=2),
    "FMPM(4)": lambda: jm.FMPM(order=4),
    "FMPM(8)": lambda: jm.FMPM(order=8),
    "FMPM(16)": lambda: jm.FMPM(order=16),
    "APIC": lambda: jm.APIC(),
    "TPIC": lambda: jm.TPIC(),
}
SHAPES = {"Linear": lambda: jm.Linear(), "Quadratic": lambda: jm.QuadraticBSpline()}

# bar
BAR_CFL, BAR_T_END = 0.1, 40.0
# mms
MMS_FRAMES = 40  # convergence.py's default: the max over time is taken over these frames
# disks
DISKS_DT, DISKS_T_END, DISKS_PAD, DISKS_FRAMES = 1e-3, 4.0, 0.1, 200
DISKS_REFERENCE_SCHEME, DISKS_CHECK_SCHEME = "FMPM(8)", "FLIP"


@dataclasses.dataclass(frozen=True)
class Config:
    """What to run: schemes, resolutions per scene, shapes of the 1D scenes, disks reference."""

    schemes: tuple
    bar_cells: tuple = (8, 16, 32, 64)
    mms_cells: tuple = (8, 16, 32, 64)
    disks_spacing: tuple = (0.1, 0.05, 0.025)
    shapes: tuple = ("Linear", "Quadratic")
    amplitudes: tuple = tuple(AMPLITUDES)
    mms_dt_scaling: str = "h2"
    disks_reference_spacing: float = 0.0125
    repeats: int = 2


def configuration(quick: bool = False) -> Config:
    """The default size, or ``--quick``: FLIP and FMPM(2), two resolutions per scene, linear shapes."""
    if not quick:
        return Config(schemes=tuple(SCHEMES))
    return Config(schemes=("FLIP", "FMPM(2)"), bar_cells=(8, 16), mms_cells=(8, 16), disks_spacing=(0.1, 0.05),
                  shapes=("Linear",), disks_reference_spacing=0.025)


@dataclasses.dataclass(frozen=True)
class Case:
    """One scene variant: ``build(scheme, resolution) -> Setup`` and
    ``error(setup, history) -> (error, secondary)`` over ``resolutions``."""

    scene: str
    variant: str
    resolution_name: str  # "cells" or "spacing"
    resolutions: tuple
    build: Callable
    error: Callable
    secondary_name: str


# --------------------------------------------------------------------------- error measures
def relative_l2(value, reference) -> float:
    """|| value - reference ||_2 / || reference ||_2 over the saved frames."""
    value, reference = np.asarray(value, float), np.asarray(reference, float)
    return float(np.linalg.norm(value - reference) / np.linalg.norm(reference))


def centre_of_mass_velocity(v, mass, axis: int = 0) -> np.ndarray:
    """Mass-weighted mean of the particles' velocity component ``axis`` per frame: v (T, N, D) -> (T,)."""
    mass = np.asarray(mass, float)
    return np.asarray(v, float)[..., axis] @ mass / mass.sum()


def bar_error(setup, history) -> tuple[float, float]:
    """Relative L2 error of v_cm(t) against v0/(beta1 L) cos(omega t) over the frames with
    t in [0, 40], and E(40)/E(0) - 1 (kinetic + strain)."""
    t = np.asarray(history.time, float)
    keep = t <= BAR_T_END + 1e-9
    v_cm = centre_of_mass_velocity(np.asarray(history.v)[keep], setup.state.mass)
    energy = np.asarray(history.kinetic + history.strain, float)[keep]
    return relative_l2(v_cm, setup.reference(t[keep])), float(energy[-1] / energy[0] - 1.0)


def mms_error(setup, history) -> tuple[float, float]:
    """convergence.py's e_x = max_t RMS displacement error / A and e_v = max_t RMS velocity
    error / (A c pi), from the scene's exact solution."""
    amplitude, c = setup.params["amplitude"], setup.params["c"]
    ex, ev = setup.reference.errors(history.time, history.x, history.v)
    return float(ex.max() / amplitude), float(ev.max() / (amplitude * c * math.pi))


def disk_velocity(setup, history) -> np.ndarray:
    """x-velocity of the first disk's centre of mass at every saved frame."""
    n = setup.params["n_first"]
    return centre_of_mass_velocity(np.asarray(history.v)[:, :n], np.asarray(setup.state.mass)[:n])


def disks_error(reference) -> Callable:
    """Error against a fine reference (dict with time, velocity, energy): relative L2 of the first
    disk's centre-of-mass x-velocity history, and |E(4) - E_ref(4)| / E_ref(0)."""

    def error(setup, history):
        t = np.asarray(history.time, float)
        if t.shape != reference["time"].shape or not np.allclose(t, reference["time"]):
            raise ValueError("disks: the run's frames do not match the reference's (same dt and frames needed)")
        energy = np.asarray(history.kinetic + history.strain, float)
        e_ref = reference["energy"]
        return relative_l2(disk_velocity(setup, history), reference["velocity"]), \
            float(abs(energy[-1] - e_ref[-1]) / e_ref[0])

    return error


# --------------------------------------------------------------------------- scenes
def make_scheme(label: str):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return SCHEMES[label]()


def bar_cases(cells, shapes) -> list[Case]:
    """The bar at ``cells`` cells along its length, one case per shape function."""
    def builder(shape):
        return lambda scheme, n: jm.scene("bar", scheme=scheme, shape=SHAPES[shape](), cells=n, cfl=BAR_CFL,
                                          t_end=BAR_T_END)
    return [Case("bar", shape, "cells", tuple(cells), builder(shape), bar_error, "E(40)/E0 - 1") for shape in shapes]


def mms_cases(cells, shapes, amplitudes, dt_scaling) -> list[Case]:
    """The 1D MMS (extended boundary, one period), one case per (amplitude, shape)."""
    def builder(amplitude, shape):
        return lambda scheme, n: jm.scene(
            "mms", dim=1, cells=n, ppc=MMS_PPC, shape=SHAPES[shape](), scheme=scheme, amplitude=amplitude,
            boundary="extended", cfl=cfl_for(n, dt_scaling), frames=MMS_FRAMES)
    return [Case("mms", f"A={AMPLITUDES[size]:g} ({size}), {shape}", "cells", tuple(cells),
                 builder(AMPLITUDES[size], shape), mms_error, "e_v")
            for size in amplitudes for shape in shapes]


def disks_setup(scheme, spacing):
    return jm.scene("disks", scheme=scheme, spacing=spacing, dt=DISKS_DT, t_end=DISKS_T_END, pad=DISKS_PAD,
                    frames=DISKS_FRAMES, update="USL")


def disks_reference(spacing: float, log=print) -> dict:
    """Fine runs with FMPM(8) (the reference) and FLIP (its check): time, first-disk centre-of-mass
    x-velocity and total energy per frame, the wall time, and the "floor" (the error measures of
    the FLIP run against the FMPM(8) run)."""
    runs = {}
    for label in (DISKS_REFERENCE_SCHEME, DISKS_CHECK_SCHEME):
        setup = disks_setup(make_scheme(label), spacing)
        start = time.perf_counter()
        _, history = setup.run()
        jax.block_until_ready(history)
        runs[label] = dict(time=np.asarray(history.time, float), velocity=disk_velocity(setup, history),
                           energy=np.asarray(history.kinetic + history.strain, float),
                           wall_s=time.perf_counter() - start, particles=int(setup.state.x.shape[0]),
                           setup=setup, history=history)
        log(f"disks reference {label}, spacing {spacing:g}: {runs[label]['particles']} particles, "
            f"{setup.steps} steps, {runs[label]['wall_s']:.1f} s (incl. compile)")
    ref = runs[DISKS_REFERENCE_SCHEME]
    check = runs[DISKS_CHECK_SCHEME]
    floor = disks_error(ref)(check["setup"], check["history"])
    for r in runs.values():
        del r["setup"], r["history"]
    return dict(ref, spacing=spacing, scheme=DISKS_REFERENCE_SCHEME, check=check, floor=floor)


def disks_cases(spacings, reference) -> list[Case]:
    return [Case("disks", "uGIMP", "spacing", tuple(spacings), lambda scheme, s: disks_setup(scheme, s),
                 disks_error(reference), "|E(4) - E_ref(4)|/E_ref(0)")]


# --------------------------------------------------------------------------- timing and the sweep
def time_run(setup, repeats: int):
    """Run once (compile + run), then ``repeats`` more (up to MAX_REPEATS while each takes less
    than SHORT_RUN_S).  Returns (history, best repeat in s, compile s, all repeats).  With
    repeats = 0 the first call is the only timing and compile_s is NaN."""
    start = time.perf_counter()
    final, history = setup.run()
    jax.block_until_ready((final, history))
    first = time.perf_counter() - start
    times, wanted = [], repeats
    while len(times) < wanted:
        start = time.perf_counter()
        jax.block_until_ready(setup.run())
        times.append(time.perf_counter() - start)
        if len(times) == wanted and wanted < MAX_REPEATS and max(times) < SHORT_RUN_S:
            wanted += 1
    if not times:
        return history, first, math.nan, [first]
    best = min(times)
    return history, best, max(0.0, first - best), times


def run_point(case: Case, label: str, resolution, repeats: int) -> dict:
    """One (case, scheme, resolution) point: timings and errors, or status "unstable ..."."""
    setup = case.build(make_scheme(label), resolution)
    grid = setup.sim.grid
    row = dict(scene=case.scene, variant=case.variant, scheme=label, resolution_name=case.resolution_name,
               resolution=resolution, h=float(grid.h), dt=float(setup.dt), steps=int(setup.steps),
               particles=int(setup.state.x.shape[0]), secondary_name=case.secondary_name)
    start = time.perf_counter()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", jm.StableTimeStepWarning)
            history, best, compile_s, times = time_run(setup, repeats)
    except jm.InstabilityError as err:
        row.update(status=f"unstable at t = {err.time:.4g}: {err.cause.split(' (')[0]}", error=math.nan,
                   secondary=math.nan, wall_s=math.nan, compile_s=math.nan,
                   first_call_s=time.perf_counter() - start, repeats_s="")
        return row
    error, secondary = case.error(setup, history)
    row.update(status="ok", error=error, secondary=secondary, wall_s=best, compile_s=compile_s,
               first_call_s=best + (0.0 if math.isnan(compile_s) else compile_s),
               repeats_s=";".join(f"{t:.4g}" for t in times))
    return row


def sweep(cases, schemes, repeats: int = 2, log=print) -> list[dict]:
    """Every case x scheme x resolution; rows in that order, with ``pareto`` marked per case."""
    rows = []
    start = time.perf_counter()
    for case in cases:
        case_rows = []
        for label in schemes:
            for resolution in case.resolutions:
                row = run_point(case, label, resolution, repeats)
                case_rows.append(row)
                what = f"e = {row['error']:.3e}, run {row['wall_s']:.4f} s, jit {row['compile_s']:.2f} s" \
                    if row["status"] == "ok" else row["status"]
                log(f"[{time.perf_counter() - start:6.0f} s] {case.scene} {case.variant} {label} "
                    f"{case.resolution_name} {resolution:g}: {what}")
        front = pareto_front(case_rows)
        for i, row in enumerate(case_rows):
            row["pareto"] = i in front
        rows.extend(case_rows)
        # Each compiled rollout holds ~180 memory mappings on the CPU backend; a few hundred of them
        # exhaust vm.max_map_count (65530) and LLVM fails with "Cannot allocate memory" (then a
        # segfault).  Nothing compiled for one case is reused by the next, so drop them here.
        jax.clear_caches()
    return rows


# --------------------------------------------------------------------------- analysis
def usable(row) -> bool:
    """A finished run with a finite error and wall time."""
    return row["status"] == "ok" and math.isfinite(row["error"]) and math.isfinite(row["wall_s"])


def pareto_front(rows) -> set[int]:
    """Indices of the rows no other usable row beats on both wall time and error (one strictly)."""
    ok = [i for i, r in enumerate(rows) if usable(r)]
    front = set()
    for i in ok:
        ti, ei = rows[i]["wall_s"], rows[i]["error"]
        dominated = any(rows[j]["wall_s"] <= ti and rows[j]["error"] <= ei
                        and (rows[j]["wall_s"] < ti or rows[j]["error"] < ei) for j in ok if j != i)
        if not dominated:
            front.add(i)
    return front


def cheapest(rows, threshold: float):
    """The usable row with the least wall time among those with error <= threshold (ties: the
    smaller error), or None."""
    good = [r for r in rows if usable(r) and r["error"] <= threshold]
    return min(good, key=lambda r: (r["wall_s"], r["error"])) if good else None


def variants(rows) -> list[tuple]:
    out = []
    for r in rows:
        if (r["scene"], r["variant"]) not in out:
            out.append((r["scene"], r["variant"]))
    return out


def describe(row) -> str:
    res = f"{row['resolution']:g} cells" if row["resolution_name"] == "cells" else f"spacing {row['resolution']:g}"
    return f"{row['scheme']}, {res}: {row['wall_s']:.3g} s (e = {row['error']:.2e})"


def markdown(rows, notes: str = "") -> str:
    head = " | ".join(f"error <= {100 * t:g}%" for t in THRESHOLDS)
    lines = [f"| scene | variant | {head} | best error (scheme, resolution) | unstable runs |",
             "|---|---|" + "---|" * len(THRESHOLDS) + "---|---|"]
    for scene, variant in variants(rows):
        sel = [r for r in rows if (r["scene"], r["variant"]) == (scene, variant)]
        cells = []
        for t in THRESHOLDS:
            best = cheapest(sel, t)
            cells.append("none" if best is None else describe(best))
        ok = [r for r in sel if usable(r)]
        most = min(ok, key=lambda r: r["error"]) if ok else None
        best_txt = "—" if most is None else f"{most['error']:.2e} ({most['scheme']}, {most['resolution']:g})"
        unstable = [f"{r['scheme']}@{r['resolution']:g}" for r in sel if r["status"] != "ok"]
        lines.append(f"| {scene} | {variant} | {' | '.join(cells)} | {best_txt} | "
                     f"{len(unstable)}{': ' + ', '.join(unstable) if unstable else ''} |")
    if notes:
        lines.append("\n" + notes)
    return "\n".join(lines)


# --------------------------------------------------------------------------- output
FIELDS = ["scene", "variant", "scheme", "resolution_name", "resolution", "h", "dt", "steps", "particles", "error",
          "secondary", "secondary_name", "status", "wall_s", "compile_s", "first_call_s", "repeats_s", "pareto"]


def write_csv(path: Path, rows):
    with path.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=FIELDS)
        w.writeheader()
        for r in rows:
            w.writerow({k: (f"{r[k]:.10g}" if isinstance(r[k], float) else r[k]) for k in FIELDS})


def read_csv(path: Path) -> list[dict]:
    """Rows written by :func:`write_csv`, with numbers and the pareto flag parsed back."""
    ints, floats = ("steps", "particles"), ("h", "dt", "error", "secondary", "wall_s", "compile_s", "first_call_s")
    rows = []
    with path.open() as f:
        for r in csv.DictReader(f):
            r["resolution"] = int(r["resolution"]) if r["resolution_name"] == "cells" else float(r["resolution"])
            r.update({k: int(r[k]) for k in ints})
            r.update({k: float(r[k]) if r[k] else math.nan for k in floats})
            r["pareto"] = r["pareto"] == "True"
            rows.append(r)
    return rows


def reference_floor(path: Path) -> tuple[float, float]:
    """The disks reference floor from the reference CSV: (velocity, energy) error measures of the
    check run against the reference run."""
    data = np.loadtxt(path, delimiter=",", skiprows=1)
    return relative_l2(data[:, 3], data[:, 1]), float(abs(data[-1, 4] - data[-1, 2]) / data[0, 2])


def write_reference_csv(path: Path, reference):
    check = reference["check"]
    with path.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["time", f"vcm_x_{reference['scheme']}", f"energy_{reference['scheme']}",
                    f"vcm_x_{DISKS_CHECK_SCHEME}", f"energy_{DISKS_CHECK_SCHEME}"])
        for row in zip(reference["time"], reference["velocity"], reference["energy"], check["velocity"],
                       check["energy"]):
            w.writerow([f"{v:.10g}" for v in row])


def _styles(schemes):
    import matplotlib.pyplot as plt

    markers = "o s ^ v D P X * < > h p d".split()
    colours = plt.get_cmap("tab20").colors
    return {s: (markers[i % len(markers)], colours[(2 * i) % 20 if i < 10 else (2 * i + 1) % 20])
            for i, s in enumerate(schemes)}


def _minor_label(value, _pos) -> str:
    """Label the 2x and 5x minor ticks of a log axis (the others stay blank)."""
    if value <= 0:
        return ""
    mantissa = value / 10.0 ** math.floor(math.log10(value) + 1e-9)
    return f"{value:g}" if round(mantissa, 6) in (2.0, 5.0) else ""


def plot(path: Path, rows, title: str, floor: float | None = None):
    """Error against wall time, log-log: one panel per variant (two per row), one marker per
    scheme with its resolutions connected, the Pareto front as a black step line with ringed
    points (labelled with their resolution); ``floor`` (disks) is drawn as a red dashed line."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FuncFormatter

    groups = variants(rows)
    schemes = list(dict.fromkeys(r["scheme"] for r in rows))
    style = _styles(schemes)
    ncols = min(2, len(groups))
    nrows = math.ceil(len(groups) / ncols)
    fig, axes = plt.subplots(nrows, ncols, figsize=(6.0 * ncols + 2.2, 4.8 * nrows + 0.6), squeeze=False)
    for ax in axes.flat[len(groups):]:
        ax.set_visible(False)
    for ax, (scene, variant) in zip(axes.flat, groups):
        sel = [r for r in rows if (r["scene"], r["variant"]) == (scene, variant)]
        for s in schemes:
            pts = [r for r in sel if r["scheme"] == s and usable(r)]
            pts.sort(key=lambda r: r["resolution"] if r["resolution_name"] == "cells" else -r["resolution"])
            marker, colour = style[s]
            ax.loglog([r["wall_s"] for r in pts], [r["error"] for r in pts], "-", marker=marker, color=colour,
                      ms=5, lw=1, label=s)
        front = sorted((r for r in sel if r.get("pareto")), key=lambda r: r["wall_s"])
        if front:
            t = [r["wall_s"] for r in front]
            e = [r["error"] for r in front]
            ax.step(t, e, where="post", color="k", lw=1.6, alpha=0.7, label="Pareto front")
            ax.loglog(t, e, "o", ms=11, mfc="none", mec="k", mew=1.2)
            for r in front:
                ax.annotate(f"{r['resolution']:g}", (r["wall_s"], r["error"]), fontsize=6, xytext=(4, 4),
                            textcoords="offset points")
        for th in THRESHOLDS:
            ax.axhline(th, color="grey", lw=0.6, ls=":")
        if floor is not None:
            ax.axhline(floor, color="tab:red", lw=1.0, ls="--", label="reference floor")
        failed = [f"{r['scheme']}@{r['resolution']:g}" for r in sel if r["status"] != "ok"]
        note = f"\n{len(failed)} unstable runs not shown" if failed else ""
        if 0 < len(failed) <= 4:
            note += ": " + ", ".join(failed)
        ax.set_title(f"{scene}: {variant}{note}", fontsize=9)
        ax.set_xlabel("steady-state wall time of one run (s, best repeat)", fontsize=8)
        ax.set_ylabel("error", fontsize=8)
        ax.xaxis.set_minor_formatter(FuncFormatter(_minor_label))
        ax.tick_params(which="both", labelsize=7)
        ax.grid(alpha=0.3, which="both")
    handles, labels = axes.flat[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="center right", fontsize=8)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout(rect=(0.0, 0.0, 1.0 - 2.0 / (6.0 * ncols + 2.2), 1.0))
    fig.savefig(path, dpi=120)
    plt.close(fig)


def uptime() -> str:
    try:
        return subprocess.run(["uptime"], capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        import os

        return "load average: " + ", ".join(f"{x:.2f}" for x in os.getloadavg())


TITLES = {
    "bar": "bar (fixed-free, first mode), cfl 0.1, t in [0, 40]: relative L2 error of v_cm vs exact",
    "mms": "1D MMS (extended), one period: max_t RMS displacement error / A vs exact",
    "disks": "disks (Sulsky 1994), uGIMP, dt 1e-3, t in [0, 4]: rel. L2 error of disk-1 v_cm,x vs fine reference",
}


def replot(out: Path, scenes, suffix: str) -> list[dict]:
    """Charts and table again from the CSVs of an earlier run (timings and notes as recorded)."""
    all_rows, notes = [], []
    for scene in scenes:
        rows = read_csv(out / f"speed_vs_accuracy_{scene}{suffix}.csv")
        floor_v = floor_e = None
        if scene == "disks":
            floor_v, floor_e = reference_floor(out / f"speed_vs_accuracy_disks_reference{suffix}.csv")
        plot(out / f"speed_vs_accuracy_{scene}{suffix}.png", rows, TITLES[scene], floor=floor_v)
        all_rows.extend(rows)
        if scene == "disks":
            notes.append(f"disks reference floor ({DISKS_CHECK_SCHEME} vs {DISKS_REFERENCE_SCHEME}): velocity error "
                         f"{floor_v:.2e}, energy error {floor_e:.2e}.")
    print(markdown(all_rows, "\n\n".join(notes)))
    return all_rows


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="FLIP and FMPM(2), 2 resolutions per scene (< 3 min)")
    parser.add_argument("--scenes", nargs="+", default=["bar", "mms", "disks"], choices=["bar", "mms", "disks"])
    parser.add_argument("--schemes", nargs="+", default=None, choices=list(SCHEMES), metavar="SCHEME",
                        help=f"scheme labels (default: all): {', '.join(SCHEMES)}")
    parser.add_argument("--shapes", nargs="+", default=None, choices=list(SHAPES),
                        help="shape functions of the bar and mms runs (default Linear Quadratic)")
    parser.add_argument("--repeats", type=int, default=None, help="timed repeats after the compiling call (default 2)")
    parser.add_argument("--mms-dt-scaling", choices=["h2", "h"], default=None,
                        help="h2: cfl = 0.2*8/cells (default, as convergence.py); h: cfl = 0.2")
    parser.add_argument("--out", type=Path, default=RESULTS, help="results folder")
    parser.add_argument("--replot", action="store_true",
                        help="run nothing: redraw the charts and the table from the CSVs already in --out")
    args = parser.parse_args(argv)
    config = configuration(args.quick)
    config = dataclasses.replace(
        config, **{k: v for k, v in dict(schemes=tuple(args.schemes) if args.schemes else None,
                                         shapes=tuple(args.shapes) if args.shapes else None,
                                         repeats=args.repeats, mms_dt_scaling=args.mms_dt_scaling).items()
                   if v is not None})
    args.out.mkdir(parents=True, exist_ok=True)
    suffix = "_quick" if args.quick else ""
    print(f"uptime at start: {uptime()}", flush=True)
    start = time.perf_counter()
    log = lambda msg: print(msg, flush=True)  # noqa: E731

    all_rows, notes = [], []
    if args.replot:
        return replot(args.out, args.scenes, suffix)
    for scene in args.scenes:
        if scene == "bar":
            cases = bar_cases(config.bar_cells, config.shapes)
        elif scene == "mms":
            cases = mms_cases(config.mms_cells, config.shapes, config.amplitudes, config.mms_dt_scaling)
        else:
            reference = disks_reference(config.disks_reference_spacing, log)
            write_reference_csv(args.out / f"speed_vs_accuracy_disks_reference{suffix}.csv", reference)
            cases = disks_cases(config.disks_spacing, reference)
            floor_v, floor_e = reference["floor"]
            notes.append(f"disks reference: {reference['scheme']} at spacing {reference['spacing']:g} "
                         f"({reference['particles']} particles, {reference['wall_s']:.0f} s incl. compile); "
                         f"reference floor ({DISKS_CHECK_SCHEME} vs {reference['scheme']} at that spacing): "
                         f"velocity error {floor_v:.2e}, energy error {floor_e:.2e}.")
        rows = sweep(cases, config.schemes, config.repeats, log)
        write_csv(args.out / f"speed_vs_accuracy_{scene}{suffix}.csv", rows)
        plot(args.out / f"speed_vs_accuracy_{scene}{suffix}.png", rows, TITLES[scene],
             floor=reference["floor"][0] if scene == "disks" else None)
        all_rows.extend(rows)
    elapsed = time.perf_counter() - start
    end_uptime = uptime()
    notes.append(
        f"Cheapest = least steady-state wall time (best of {config.repeats}+ repeats after a compiling call) among "
        f"runs with error <= the threshold; float64, USL, 2 CPU cores shared with other jobs (uptime at end: "
        f"{end_uptime}).  bar: cfl {BAR_CFL}, cells {', '.join(map(str, config.bar_cells))}; mms: dim 1, extended, "
        f"dt ~ {'h^2' if config.mms_dt_scaling == 'h2' else 'h'}, cells {', '.join(map(str, config.mms_cells))}; "
        f"disks: spacing {', '.join(f'{s:g}' for s in config.disks_spacing)}, dt {DISKS_DT:g}.  "
        f"Total time {elapsed:.0f} s.")
    table = markdown(all_rows, "\n\n".join(notes))
    (args.out / f"speed_vs_accuracy{suffix}.md").write_text(table + "\n")
    print()
    print(table)
    print(f"\nuptime at end: {end_uptime}")
    print(f"wrote {args.out}/speed_vs_accuracy_*{suffix}.csv/.png and speed_vs_accuracy{suffix}.md ({elapsed:.0f} s)")
    return all_rows


if __name__ == "__main__":
    main()
