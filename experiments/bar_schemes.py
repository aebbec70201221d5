"""The ``bar`` scene under every scheme: error of the centre-of-mass velocity against the exact
modal solution v0/(beta1 L) cos(omega t), energy kept at t = 40, and the energy budget
(kinetic + strain + dissipated, 000 eq. 2.44).  Prints a Markdown table and writes
experiments/results/bar_schemes.csv.

    python experiments/bar_schemes.py [--update USL|MUSL|USF]
"""

import argparse
import csv
import os
import time
import warnings

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

import jaxmpm as jm  # noqa: E402

SCHEMES = {
    "FLIP": lambda: jm.FLIP(),
    "PIC": lambda: jm.PIC(),
    "blend 0.99": lambda: jm.FLIP(beta=0.99),
    "XPIC(2)": lambda: jm.XPIC(order=2),
    "XPIC(5)": lambda: jm.XPIC(order=5),
    "XPIC(8)": lambda: jm.XPIC(order=8),
    "XPIC(3), BCs on result only": lambda: jm.XPIC(order=3, boundary="result"),
    "XPIC(50) binomial": lambda: jm.XPIC(order=50),
    "XPIC(50) neumann": lambda: jm.XPIC(order=50, series="neumann"),
    "FMPM(1)": lambda: jm.FMPM(order=1),
    "FMPM(2)": lambda: jm.FMPM(order=2),
    "FMPM(5)": lambda: jm.FMPM(order=5),
    "FMPM(8)": lambda: jm.FMPM(order=8),
    "FMPM(3), BCs on result only": lambda: jm.FMPM(order=3, boundary="result"),
}
if hasattr(jm, "APIC"):
    SCHEMES["APIC"] = lambda: jm.APIC()
    SCHEMES["TPIC"] = lambda: jm.TPIC()


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--update", default="USL")
    parser.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "results", "bar_schemes.csv"))
    args = parser.parse_args()
    rows = []
    for name, make in SCHEMES.items():
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            scheme = make()
        setup = jm.scene("bar", scheme=scheme, update=args.update)
        start = time.perf_counter()
        try:
            _, hist = setup.run()
        except jm.InstabilityError as err:
            rows.append(dict(scheme=name, l2="", energy="", budget="", wall=time.perf_counter() - start,
                             note=f"unstable at step {err.step}: {err.cause}"))
            continue
        mass = np.asarray(setup.state.mass)
        v_cm = np.asarray(hist.v)[..., 0] @ mass / mass.sum()
        exact = setup.reference(np.asarray(hist.time))
        e = np.asarray(hist.kinetic + hist.strain)
        rows.append(dict(
            scheme=name,
            l2=np.linalg.norm(v_cm - exact) / np.linalg.norm(exact),
            energy=e[-1] / e[0],
            budget=(e[-1] + float(hist.dissipated[-1])) / e[0],
            wall=time.perf_counter() - start,
            note="",
        ))
    os.makedirs(os.path.dirname(args.out), exist_ok=True)
    with open(args.out, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    print(f"bar, {args.update}, 16 cells x 2 ppc, dt = 0.1 h/c, t = 40 (float64)\n")
    print("| scheme | rel. L2 error of v_cm | energy at t=40 / initial | (energy + dissipated) / initial "
          "| wall s (incl. compile) |")
    print("|---|---|---|---|---|")
    for r in rows:
        if r["note"]:
            print(f"| {r['scheme']} | {r['note']} | | | {r['wall']:.1f} |")
        else:
            print(f"| {r['scheme']} | {r['l2']:.4f} | {r['energy']:.4f} | {r['budget']:.4f} | {r['wall']:.1f} |")


if __name__ == "__main__":
    main()
