"""Granular column collapse (``column_collapse``, Drucker-Prager sand) against the experiments' scalings.

For each aspect ratio a = H0/L0 and particle update (APIC, FLIP, XPIC(2), PIC by default) it runs the
scene at its defaults (8 cells across the column, 2x2 particles per cell, quadratic B-splines, USL,
phi = 30, psi = 0, c = 0, E = 1e6 Pa, rho = 1800 kg/m^3, t_end = 5 sqrt(H0/g), float64) and measures
the final deposit: the normalised run-out (L_inf - L0)/L0 and height H_inf/L0
(:func:`jaxmpm.scenes.column_collapse.normalised_deposit`), against the quasi-2D scalings quoted
from Lube et al. 2005 (Phys. Rev. E 72, 041301) and Lajeunesse et al. 2005 (Phys. Fluids 17,
103302): (L_inf - L0)/L0 = 1.2 a (a < 2.3), 1.9 a^(2/3) above; H_inf/L0 = a (a < 1.15), a^(2/5) above.

Writes ``experiments/results/column_collapse.csv`` and ``.md`` (the table) and the figure
``experiments/figures/column_collapse.png`` (run-out and height vs a, each scheme against the
scalings), and prints the Markdown table with the wall time of each run (compilation included: the
CPU this runs on is what a user has).

    python experiments/column_collapse.py                        # a in {0.5, 1, 2, 4, 6}, four schemes
    python experiments/column_collapse.py --aspects 1 2 --schemes apic pic
    python experiments/column_collapse.py --quick                # a in {0.5, 2}, APIC only, 4 cells
    python experiments/column_collapse.py --plot-only            # redraw the figure from the CSV
"""

from __future__ import annotations

import argparse
import csv
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

import jaxmpm as jm  # noqa: E402
from jaxmpm.scenes.column_collapse import height_scaling, normalised_deposit, runout_scaling  # noqa: E402

HERE = Path(__file__).resolve().parent
RESULTS, FIGURES = HERE / "results", HERE / "figures"
SCHEMES = {"apic": ("APIC", jm.APIC), "flip": ("FLIP", jm.FLIP), "xpic2": ("XPIC(2)", lambda: jm.XPIC(order=2)),
           "pic": ("PIC", jm.PIC)}


def run_case(aspect: float, scheme: str, cells: int) -> dict:
    """One collapse: the normalised deposit, the largest speed left at the end and the wall time."""
    label, make = SCHEMES[scheme]
    setup = jm.scene("column_collapse", aspect=aspect, cells=cells, scheme=make(), frames=4)
    start = time.perf_counter()
    try:
        final, _ = setup.run()
        failure = None
    except jm.InstabilityError as err:  # reported, not hidden: its cause and time
        when = "" if err.time is None else f" at t = {err.time:.2f} s"
        final, failure = None, err.cause.split(" (")[0] + when
    wall = time.perf_counter() - start
    row = {"aspect": aspect, "scheme": label, "cells": cells, "particles": int(setup.state.x.shape[0]),
           "steps": setup.steps, "wall_s": wall, "failure": failure or ""}
    if final is None:
        return row | {"runout": np.nan, "height": np.nan, "runout_scaling": float(runout_scaling(aspect)),
                      "height_scaling": float(height_scaling(aspect)), "v_end": np.nan}
    row |= normalised_deposit(setup, final.x)
    row["v_end"] = float(np.abs(np.asarray(final.v)).max())
    return row


def table(rows) -> str:
    lines = ["| a | scheme | (L-L0)/L0 | scaling | error | H/L0 | scaling | error | max v at end (m/s) | steps | "
             "wall (s) |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        if r["failure"]:
            lines.append(f"| {r['aspect']:g} | {r['scheme']} | failed: {r['failure']} | | | | | | | {r['steps']} | "
                         f"{r['wall_s']:.1f} |")
            continue
        e_run = r["runout"] / r["runout_scaling"] - 1
        e_h = r["height"] / r["height_scaling"] - 1
        lines.append(f"| {r['aspect']:g} | {r['scheme']} | {r['runout']:.2f} | {r['runout_scaling']:.2f} | "
                     f"{e_run:+.0%} | {r['height']:.2f} | {r['height_scaling']:.2f} | {e_h:+.0%} | "
                     f"{r['v_end']:.3f} | {r['steps']} | {r['wall_s']:.1f} |")
    return "\n".join(lines)


def figure(rows, path: Path):
    import matplotlib
    import matplotlib.ticker

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    a = np.geomspace(0.4, 8.0, 200)
    fig, (left, right) = plt.subplots(1, 2, figsize=(10, 4))
    left.plot(a, runout_scaling(a), "k-", label="Lube et al. 2005 scaling")
    right.plot(a, height_scaling(a), "k-", label="Lube et al. 2005 scaling")
    for scheme, marker in zip(dict.fromkeys(r["scheme"] for r in rows), "osD^v"):
        mine = [r for r in rows if r["scheme"] == scheme and not r["failure"]]
        left.plot([r["aspect"] for r in mine], [r["runout"] for r in mine], marker, label=scheme, alpha=0.8)
        right.plot([r["aspect"] for r in mine], [r["height"] for r in mine], marker, label=scheme, alpha=0.8)
    for ax, name in ((left, "run-out (L_inf - L0) / L0"), (right, "height H_inf / L0")):
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.xaxis.set_major_locator(matplotlib.ticker.FixedLocator([0.5, 1, 2, 4, 6]))
        ax.xaxis.set_major_formatter(matplotlib.ticker.FormatStrFormatter("%g"))
        ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        ax.set_xlabel("aspect ratio a = H0 / L0")
        ax.set_ylabel(name)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle("column_collapse: Drucker-Prager sand (phi = 30, psi = 0, c = 0), 8 cells across L0")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--aspects", type=float, nargs="+", default=[0.5, 1.0, 2.0, 4.0, 6.0])
    parser.add_argument("--schemes", nargs="+", default=list(SCHEMES), choices=list(SCHEMES))
    parser.add_argument("--cells", type=int, default=8, help="cells across the column (default 8)")
    parser.add_argument("--quick", action="store_true", help="a in {0.5, 2}, APIC, 4 cells: a smoke test")
    parser.add_argument("--plot-only", action="store_true", help="redraw the figure from the stored CSV")
    args = parser.parse_args(argv)
    if args.plot_only:
        with open(RESULTS / "column_collapse.csv") as f:
            text = ("scheme", "failure")
            rows = [{k: v if k in text else float(v) for k, v in r.items()} for r in csv.DictReader(f)]
        figure(rows, FIGURES / "column_collapse.png")
        return
    if args.quick:
        args.aspects, args.schemes, args.cells = [0.5, 2.0], ["apic"], 4
    rows = []
    for aspect in args.aspects:
        for scheme in args.schemes:
            rows.append(run_case(aspect, scheme, args.cells))
            r = rows[-1]
            print(f"a = {aspect:g} {r['scheme']}: run-out {r.get('runout', np.nan):.3f} "
                  f"({r['runout_scaling']:.3f}), height {r.get('height', np.nan):.3f} ({r['height_scaling']:.3f}), "
                  f"{r['wall_s']:.1f} s {r['failure']}", flush=True)
    text = table(rows)
    print(text)
    stem = "column_collapse_quick" if args.quick else "column_collapse"
    RESULTS.mkdir(exist_ok=True)
    with open(RESULTS / f"{stem}.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    (RESULTS / f"{stem}.md").write_text(text + "\n")
    figure(rows, FIGURES / f"{stem}.png")


if __name__ == "__main__":
    main()
