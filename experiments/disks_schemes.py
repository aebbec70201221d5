"""Energy of the colliding ``disks`` (Sulsky, Chen & Schreyer 1994) under eight particle updates.

FLIP, PIC, the 0.99 FLIP/PIC blend (000 eq. 2.86), XPIC(2), XPIC(5) (000 eqs. 3.28-3.29), FMPM(1),
FMPM(4), FMPM(8) (003 Table 2.1), all float64 with the USL update on the default scene (h = 0.05,
2x2 particles per cell, dt = 1e-3, uGIMP shape functions, grid padded by two cells).  For each scheme
it records the kinetic, strain and total energy and the energy the update dissipates relative to
FLIP (000 eq. 2.44), and writes

* ``experiments/results/disks_schemes.csv`` (long format: scheme,time,kinetic,strain,total,dissipated)
* ``experiments/results/disks_schemes.png`` (total energy vs time; kinetic energy in a second panel)

and prints a Markdown table: energy before contact (t = 1) and after separation (t = 3.5 and t = 4)
as fractions of the initial energy E0, the energy lost by t = 4, the minimum energy while the disks
are in contact, and the wall time (run and compile separately).

"In contact" means the two disks share a grid node: some node receives mass from particles of both
disks (computed from the shape function's stencil at every saved frame).  A run that goes unstable
(``jm.InstabilityError``: NaN, J <= 0 or particles leaving the grid) is reported as such, and its
histories are kept up to the last frame before the failure.  The disks come back to the grid edge
near t = 4 (a disk of radius 0.2 started touching it), so "particles left the grid" there is the
scene's geometry, not the scheme.

Sensitivity: the collision amplifies round-off.  With ``--perturb N`` (default 8) each scheme is also
run from N copies of the initial state whose velocities are multiplied by (1 + 1e-13 xi), xi ~ N(0,1)
(a physically invisible change); the table reports the spread of E(t=3.5)/E0 and how many of these
runs went unstable.  Only the unperturbed run goes into the CSV and the chart.

    python experiments/disks_schemes.py               # t_end = 4 (the scene's default), 8 perturbed runs
    python experiments/disks_schemes.py --quick       # t_end = 0.5, no perturbed runs: smoke test
    python experiments/disks_schemes.py --t-end 3.5 --perturb 0
"""

from __future__ import annotations

import argparse
import csv
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import equinox as eqx  # noqa: E402
import numpy as np  # noqa: E402

import jaxmpm as jm  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"
T_BEFORE, T_SEPARATED, T_AFTER = 1.0, 3.5, 4.0
PERTURBATION = 1e-13  # relative, on the initial particle velocities
CAUSE_SHORT = {"J = det F <= 0": "J <= 0", "particles left the grid": "left the grid",
               "NaN or Inf in the particle state": "NaN"}


def schemes():
    """Label -> scheme, in table order."""
    return {
        "FLIP": jm.FLIP(),
        "PIC": jm.PIC(),
        "blend 0.99": jm.FLIP(beta=0.99),
        "XPIC(2)": jm.XPIC(order=2),
        "XPIC(5)": jm.XPIC(order=5),
        "FMPM(1)": jm.FMPM(order=1),
        "FMPM(4)": jm.FMPM(order=4),
        "FMPM(8)": jm.FMPM(order=8),
    }


def energies(history, failure) -> dict:
    """NumPy histories (time, kinetic, strain, total, dissipated, x), cut before any failure."""
    t = np.asarray(history.time)
    keep = np.ones_like(t, bool) if failure is None else t < failure.time
    h = {name: np.asarray(getattr(history, name))[keep] for name in ("time", "kinetic", "strain", "dissipated", "x")}
    h["total"] = h["kinetic"] + h["strain"]
    return h


def run_once(setup, state):
    """One run from ``state``: (history, InstabilityError or None).  A failed run is repeated with
    check_stability=False to get its frames (same compiled function)."""
    try:
        _, history = setup.sim.run(state, setup.dt, setup.steps, setup.save_every)
        return history, None
    except jm.InstabilityError as err:
        _, history = setup.sim.run(state, setup.dt, setup.steps, setup.save_every, check_stability=False)
        return history, err


def perturbed(state, seed: int):
    rng = np.random.default_rng(seed)
    v = np.asarray(state.v)
    return eqx.tree_at(lambda s: s.v, state, v * (1.0 + PERTURBATION * rng.standard_normal(v.shape)))


def run_scheme(scheme, t_end: float, frames: int, n_perturbed: int) -> dict:
    """The unperturbed run (timed twice: the first call compiles) and ``n_perturbed`` perturbed runs."""
    setup = jm.scene("disks", scheme=scheme, dtype="f64", update="USL", t_end=t_end, frames=frames)
    start = time.perf_counter()
    history, failure = run_once(setup, setup.state)
    jax.block_until_ready(history)
    first_call = time.perf_counter() - start
    start = time.perf_counter()
    history, failure = run_once(setup, setup.state)
    jax.block_until_ready(history)
    run_time = time.perf_counter() - start
    ensemble = []
    for seed in range(1, n_perturbed + 1):
        hist, err = run_once(setup, perturbed(setup.state, seed))
        ensemble.append((energies(hist, err), err))
    return dict(setup=setup, history=energies(history, failure), failure=failure, ensemble=ensemble,
                run_s=run_time, compile_s=max(0.0, first_call - run_time))


def contact_frames(setup, x_frames) -> np.ndarray:
    """True at frames where the two disks share a grid node (both put mass on it)."""
    n_first = setup.params["n_first"]
    shape, grid = setup.sim.shape, setup.sim.grid
    out = []
    for x in x_frames:
        st = shape.stencil(grid, x)
        index, weight = np.asarray(st.index).T, np.asarray(st.weight).T  # (N, K)
        nodes_a = set(index[:n_first][weight[:n_first] > 0].tolist())
        nodes_b = set(index[n_first:][weight[n_first:] > 0].tolist())
        out.append(bool(nodes_a & nodes_b))
    return np.array(out)


def at_time(h, t):
    """Total energy / E0 at the saved frame closest to ``t`` (None if the run did not reach it)."""
    times = h["time"]
    if times.size == 0 or times[-1] < t - 1e-9:
        return None
    return float(h["total"][np.argmin(np.abs(times - t))] / h["total"][0])


def summarise(label, res) -> dict:
    h = res["history"]
    e0 = float(h["total"][0])
    row = dict(scheme=label, e0=e0, run_s=res["run_s"], compile_s=res["compile_s"])
    row["before"], row["separated"], row["after"] = (at_time(h, t) for t in (T_BEFORE, T_SEPARATED, T_AFTER))
    row["lost_pct"] = None if row["after"] is None else 100.0 * (1.0 - row["after"])
    contact = contact_frames(res["setup"], h["x"])
    if contact.any():
        first, last = np.flatnonzero(contact)[[0, -1]]
        row["contact"] = (float(h["time"][first]), float(h["time"][last]))
        row["min_contact"] = float(h["total"][first:last + 1].min()) / e0
    else:
        row["contact"], row["min_contact"] = None, None
    err = res["failure"]
    row["status"] = "ok" if err is None else f"unstable at t = {err.time:.3f}: {err.cause.split(' (')[0]}"
    # perturbed ensemble: spread of E(3.5)/E0 and the number of unstable runs before t = 3.5
    sep = [at_time(hh, T_SEPARATED) for hh, _ in res["ensemble"]]
    reached = [s for s in sep if s is not None]
    row["ensemble_n"] = len(sep)
    row["ensemble_range"] = (min(reached), max(reached)) if reached else None
    failed = [err for _, err in res["ensemble"] if err is not None and err.time < T_SEPARATED + 1e-9]
    row["ensemble_failed"] = len(failed)
    causes = [CAUSE_SHORT.get(err.cause.split(" (")[0], err.cause) for err in failed]
    row["ensemble_causes"] = ", ".join(f"{c} x{causes.count(c)}" for c in sorted(set(causes)))
    return row


def fmt(value, spec="{:.4f}"):
    return "—" if value is None else spec.format(value)


def markdown(rows, t_end) -> str:
    lines = [
        f"| scheme | E(t={T_BEFORE:g})/E0 | E(t={T_SEPARATED:g})/E0 | E(t={T_AFTER:g})/E0 | lost by t={T_AFTER:g} (%) "
        "| min E/E0 in contact | contact (t) | run (s) | jit (s) | status "
        f"| perturbed runs: E(t={T_SEPARATED:g})/E0 range, unstable |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        contact = "—" if r["contact"] is None else f"{r['contact'][0]:.2f}–{r['contact'][1]:.2f}"
        if r["ensemble_n"]:
            lo_hi = r["ensemble_range"]
            rng = "—" if lo_hi is None else f"{lo_hi[0]:.3f}–{lo_hi[1]:.3f}"
            ens = f"{rng}, {r['ensemble_failed']}/{r['ensemble_n']} unstable"
            ens += f" ({r['ensemble_causes']})" if r["ensemble_failed"] else ""
        else:
            ens = "not run"
        lines.append(
            f"| {r['scheme']} | {fmt(r['before'])} | {fmt(r['separated'])} | {fmt(r['after'])} "
            f"| {fmt(r['lost_pct'], '{:.2f}')} | {fmt(r['min_contact'])} | {contact} | {r['run_s']:.2f} "
            f"| {r['compile_s']:.2f} | {r['status']} | {ens} |"
        )
    lines.append(
        f"\nE0 = {rows[0]['e0']:.6g} (initial kinetic energy); t_end = {t_end:g}; float64, USL, uGIMP shape "
        f"functions (grid padded by two cells), h = 0.05, 2x2 ppc, dt = 1e-3.  Perturbed runs: initial "
        f"velocities x (1 + {PERTURBATION:g} xi); 'unstable' counts failures before t = {T_SEPARATED:g}.  "
        "The blend reuses FLIP's compiled step (beta is an array leaf), so its jit column is timing noise.")
    return "\n".join(lines)


def write_csv(path: Path, results):
    with path.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["scheme", "time", "kinetic", "strain", "total", "dissipated"])
        for label, res in results.items():
            h = res["history"]
            for row in zip(h["time"], h["kinetic"], h["strain"], h["total"], h["dissipated"]):
                w.writerow([label] + [f"{v:.10g}" for v in row])


def plot(path: Path, results, rows):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax_total, ax_kin) = plt.subplots(2, 1, figsize=(8, 7), sharex=True)
    for (label, res), row in zip(results.items(), rows):
        h = res["history"]
        style = "--" if label.startswith("FMPM") else ("-." if label.startswith("XPIC") else "-")
        name = label if res["failure"] is None else f"{label} (unstable t={res['failure'].time:.2f})"
        ax_total.plot(h["time"], h["total"] / row["e0"], style, label=name)
        ax_kin.plot(h["time"], h["kinetic"] / row["e0"], style, label=label)
    ax_total.set_ylim(0.0, 1.15)  # an unstable run can reach many times E0: keep the others readable
    ax_kin.set_ylim(0.0, 1.15)
    ax_total.set_ylabel("total energy / E0 (clipped at 1.15)")
    ax_kin.set_ylabel("kinetic energy / E0")
    ax_kin.set_xlabel("time")
    ax_total.set_title("disks (Sulsky 1994): energy by particle update, float64, USL")
    ax_total.legend(fontsize=8, ncol=2)
    for ax in (ax_total, ax_kin):
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--t-end", type=float, default=None, help="end time (default 4, the scene's)")
    parser.add_argument("--quick", action="store_true", help="t_end = 0.5, no perturbed runs: a smoke test")
    parser.add_argument("--frames", type=int, default=400, help="saved frames (default 400: every 0.01 s)")
    parser.add_argument("--perturb", type=int, default=None,
                        help="perturbed runs per scheme (default 8; 0 with --quick)")
    parser.add_argument("--out", type=Path, default=RESULTS, help="results folder")
    args = parser.parse_args(argv)
    t_end = args.t_end if args.t_end is not None else (0.5 if args.quick else 4.0)
    frames = min(args.frames, 50) if args.quick else args.frames
    n_perturbed = args.perturb if args.perturb is not None else (0 if args.quick else 8)
    args.out.mkdir(parents=True, exist_ok=True)

    results, rows = {}, []
    for label, scheme in schemes().items():
        print(f"running {label} ...", flush=True)
        results[label] = run_scheme(scheme, t_end, frames, n_perturbed)
        rows.append(summarise(label, results[label]))
        print(f"  {rows[-1]['status']}, run {rows[-1]['run_s']:.2f} s, jit {rows[-1]['compile_s']:.2f} s", flush=True)
    csv_path, png_path = args.out / "disks_schemes.csv", args.out / "disks_schemes.png"
    write_csv(csv_path, results)
    plot(png_path, results, rows)
    print()
    print(markdown(rows, t_end))
    print(f"\nwrote {csv_path} and {png_path}")


if __name__ == "__main__":
    main()
