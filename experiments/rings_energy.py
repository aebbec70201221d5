"""Total energy of the ``rings`` collision per particle update (docs/design.md "Scenes": rings).

Two neo-Hookean rings (E = 100e6, nu = 0.2, rho = 1e3, r_i = 3, r_o = 4) meet head-on at +-30;
no boundary or body force acts, so the exact total energy (kinetic + neo-Hookean strain) is
constant and what a scheme loses is its dissipation.  For FLIP, PIC, XPIC(2), FMPM(2), APIC and
TPIC this prints E(0.2) and E(0.6) (and their ratio to E0) as a Markdown table and writes
``experiments/results/rings_energy[_quick].{md,csv}``.

dt is the scene's CFL 0.8 step h / (c + max|V|), shortened just enough that t = 0.2 and 0.6 fall
on steps.  A scheme that goes unstable is reported with its step and cause and rerun at half the
CFL number (a second row).

    python experiments/rings_energy.py             # full size: h = 0.1 (about 17,600 particles)
    python experiments/rings_energy.py --quick     # h = 0.5, seconds
    python experiments/rings_energy.py --spacing 0.2 --dtype f32
"""

from __future__ import annotations

import argparse
import csv
import math
import pathlib
import sys
import time

import jax

RESULTS = pathlib.Path(__file__).resolve().parent / "results"
TIMES = (0.2, 0.6)
SCHEMES = ("flip", "pic", "xpic:2", "fmpm:2", "apic", "tpic")
LABELS = {"flip": "FLIP", "pic": "PIC", "xpic:2": "XPIC(2)", "fmpm:2": "FMPM(2)", "apic": "APIC", "tpic": "TPIC"}


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true", help="h = 0.5 (a smoke run in seconds)")
    p.add_argument("--spacing", type=float, default=None, help="grid spacing h (default 0.1, or 0.5 with --quick)")
    p.add_argument("--cfl", type=float, default=0.8, help="CFL number (default 0.8, the scene's)")
    p.add_argument("--dtype", default="f64", choices=["f32", "f64"])
    p.add_argument("--schemes", default=",".join(SCHEMES), help="comma-separated, e.g. flip,apic,xpic:3")
    p.add_argument("--out", default=None, help="results file stem (default experiments/results/rings_energy)")
    return p.parse_args(argv)


def energy(sim, state) -> float:
    d = sim.diagnostics(state)
    return float(d["kinetic"] + d["strain"])


def run_scheme(spec: str, spacing: float, cfl: float, dtype: str) -> dict:
    import jaxmpm as jm
    from jaxmpm.core.registry import scheme_from_name

    setup = jm.scene("rings", scheme=scheme_from_name(spec), spacing=spacing, cfl=cfl, dtype=dtype)
    sim, state = setup.sim, setup.state
    # steps so that every time in TIMES is hit exactly, dt no larger than the CFL step
    unit = min(TIMES)
    per_unit = math.ceil(unit / setup.dt - 1e-9)
    dt = unit / per_unit
    row = dict(scheme=LABELS.get(spec, spec), spacing=spacing, cfl=cfl, dtype=dtype, particles=int(state.x.shape[0]),
               dt=dt, steps=int(round(max(TIMES) / dt)), E0=energy(sim, state), status="ok")
    start = time.perf_counter()
    t_now = 0.0
    try:
        for t in TIMES:
            n = int(round((t - t_now) / dt))
            state, _ = sim.run(state, dt, n, n, save_particles=False)
            jax.block_until_ready(state.x)
            row[f"E({t:g})"] = energy(sim, state)
            row[f"E({t:g})/E0"] = row[f"E({t:g})"] / row["E0"]
            t_now = t
    except jm.InstabilityError as err:
        row["status"] = f"unstable at step {err.step} (t = {err.time:.4g}): {err.cause}"
    row["wall_s"] = time.perf_counter() - start
    return row


def markdown(rows) -> str:
    head = ["scheme", "CFL", "dt", "steps", "E0", *[f"E({t:g})" for t in TIMES], *[f"E({t:g})/E0" for t in TIMES],
            "wall s", "status"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        cells = [r["scheme"], f"{r['cfl']:g}", f"{r['dt']:.4g}", str(r["steps"]), f"{r['E0']:.6g}"]
        cells += [f"{r[f'E({t:g})']:.6g}" if f"E({t:g})" in r else "-" for t in TIMES]
        cells += [f"{r[f'E({t:g})/E0']:.4f}" if f"E({t:g})/E0" in r else "-" for t in TIMES]
        cells += [f"{r['wall_s']:.1f}", r["status"]]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv=None) -> int:
    args = parse_args(argv)
    if args.dtype == "f64":
        jax.config.update("jax_enable_x64", True)
    spacing = args.spacing if args.spacing is not None else (0.5 if args.quick else 0.1)
    rows = []
    for spec in args.schemes.split(","):
        row = run_scheme(spec, spacing, args.cfl, args.dtype)
        rows.append(row)
        print(f"{row['scheme']:8s} CFL {row['cfl']:g}: " + ", ".join(
            f"E({t:g})/E0 = {row[f'E({t:g})/E0']:.4f}" for t in TIMES if f"E({t:g})/E0" in row)
            + f"  [{row['status']}, {row['wall_s']:.1f} s]", flush=True)
        if row["status"] != "ok":
            row = run_scheme(spec, spacing, args.cfl / 2, args.dtype)
            rows.append(row)
            print(f"{row['scheme']:8s} CFL {row['cfl']:g}: " + ", ".join(
                f"E({t:g})/E0 = {row[f'E({t:g})/E0']:.4f}" for t in TIMES if f"E({t:g})/E0" in row)
                + f"  [{row['status']}, {row['wall_s']:.1f} s]", flush=True)
    title = (f"rings: h = {spacing:g}, {rows[0]['particles']} particles, {args.dtype}, "
             f"jax {jax.__version__} on {jax.devices()[0].platform}")
    table = markdown(rows)
    print("\n" + title + "\n\n" + table)
    stem = pathlib.Path(args.out) if args.out else RESULTS / ("rings_energy_quick" if args.quick else "rings_energy")
    stem.parent.mkdir(parents=True, exist_ok=True)
    stem.with_suffix(".md").write_text(f"{title}\n\n{table}\n")
    with open(stem.with_suffix(".csv"), "w", newline="") as f:
        keys = list(dict.fromkeys(k for r in rows for k in r))
        writer = csv.DictWriter(f, fieldnames=keys)
        writer.writeheader()
        writer.writerows(rows)
    print(f"\nwrote {stem.with_suffix('.md')} and {stem.with_suffix('.csv')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
