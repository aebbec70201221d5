"""Smoke test of experiments/speed_vs_accuracy.py: the --quick configuration's sweep on the bar
(2 resolutions x 2 schemes), its CSV rows, the bar error measure against the exact modal solution,
and the Pareto / "cheapest scheme" logic on hand-made tables."""

import csv
import math
from types import SimpleNamespace

import numpy as np
import pytest

import jaxmpm as jm
from experiments import speed_vs_accuracy as sva


@pytest.fixture(scope="module")
def quick_bar_rows():
    config = sva.configuration(quick=True)
    cases = sva.bar_cases(config.bar_cells, ("Linear",))
    return config, sva.sweep(cases, config.schemes, repeats=1, log=lambda msg: None)


@pytest.mark.slow
def test_quick_bar_sweep_rows_csv_and_convergence(quick_bar_rows, tmp_path):
    config, rows = quick_bar_rows
    assert config.bar_cells == (8, 16) and config.schemes == ("FLIP", "FMPM(2)")
    assert [(r["scheme"], r["resolution"]) for r in rows] == [
        ("FLIP", 8), ("FLIP", 16), ("FMPM(2)", 8), ("FMPM(2)", 16)]
    for r in rows:
        cells = r["resolution"]
        h = 25.0 / cells
        assert r["status"] == "ok" and r["scene"] == "bar" and r["variant"] == "Linear"
        assert r["h"] == pytest.approx(h, rel=1e-12)
        assert r["dt"] == pytest.approx(0.1 * h / 10.0, rel=1e-12)  # cfl 0.1, c = sqrt(E/rho) = 10
        assert r["steps"] * r["dt"] == pytest.approx(40.0, rel=1e-9)
        assert r["particles"] == 2 * cells
        assert 0.0 < r["error"] < 0.1 and r["wall_s"] > 0.0 and math.isfinite(r["compile_s"])  # repeats = 1
    err = {(r["scheme"], r["resolution"]): r["error"] for r in rows}
    # FMPM(2) converges: the error falls by more than 2x from 8 to 16 cells (measured 2.6e-2 -> 4.1e-3)
    assert err["FMPM(2)", 16] < 0.5 * err["FMPM(2)", 8]
    assert err["FLIP", 16] < err["FLIP", 8]
    # secondary = E(40)/E0 - 1; the exact solution keeps its energy, and both updates approach that:
    # measured FLIP -6.1e-3, -7.6e-4 and FMPM(2) -6.3e-2, -8.1e-3 at 8 and 16 cells
    drift = {(r["scheme"], r["resolution"]): r["secondary"] for r in rows}
    for scheme in config.schemes:
        assert abs(drift[scheme, 16]) < 0.25 * abs(drift[scheme, 8])
    assert abs(drift["FLIP", 16]) < 1e-3

    path = tmp_path / "bar.csv"
    sva.write_csv(path, rows)
    with path.open() as f:
        reader = csv.DictReader(f)
        assert reader.fieldnames == sva.FIELDS
        back = list(reader)
    assert len(back) == len(rows)
    front = sva.pareto_front(rows)
    for i, (b, r) in enumerate(zip(back, rows)):
        assert b["scheme"] == r["scheme"] and int(b["resolution"]) == r["resolution"]
        assert float(b["error"]) == pytest.approx(r["error"], rel=1e-9)
        assert float(b["wall_s"]) == pytest.approx(r["wall_s"], rel=1e-9)
        assert b["pareto"] == str(i in front)


def test_bar_error_against_exact_modal_solution():
    """bar_error on made-up histories: a mass-weighted velocity profile whose centre-of-mass value
    is the exact v_cm gives 0; 1.1 x the exact v_cm gives exactly 0.1; frames after t = 40 are left out."""
    setup = jm.scene("bar", cells=8)
    mass = np.asarray(setup.state.mass)
    n = mass.size
    t = np.linspace(0.0, 44.0, 111)  # the frames past t = 40 carry garbage that must be ignored
    exact = setup.reference(t)
    profile = np.linspace(0.2, 1.0, n)
    profile = profile / (profile @ mass / mass.sum())  # mass-weighted mean 1
    energy = np.ones_like(t)

    def history(v_cm_factor):
        v = (v_cm_factor * exact)[:, None] * profile[None, :]
        v[t > 40.0] = 1e3
        return SimpleNamespace(time=t, v=v[..., None], kinetic=energy, strain=0.0 * energy)

    assert sva.bar_error(setup, history(1.0))[0] == pytest.approx(0.0, abs=1e-14)
    assert sva.bar_error(setup, history(1.1))[0] == pytest.approx(0.1, rel=1e-12)
    assert sva.bar_error(setup, history(1.0))[1] == 0.0


def _row(scheme, wall, error, status="ok", resolution=8):
    return dict(scene="bar", variant="Linear", scheme=scheme, resolution_name="cells", resolution=resolution,
                wall_s=wall, error=error, status=status)


HAND_MADE = [
    _row("A", 1.0, 0.05),
    _row("B", 0.5, 0.2),
    _row("C", 2.0, 0.005),
    _row("D", 0.1, math.nan, status="unstable at t = 1: J = det F <= 0"),
    _row("E", 3.0, 8e-4),
    _row("G", 1.5, 0.06),  # slower and less accurate than A: dominated
    _row("H", 2.0, 0.01),  # exactly at the 1% threshold but slower than... nothing below 1% is cheaper than 2.0
]


def test_cheapest_picks_least_time_below_each_threshold():
    pick = {t: sva.cheapest(HAND_MADE, t) for t in (0.1, 0.01, 0.001, 1e-4)}
    assert pick[0.1]["scheme"] == "A"  # B and D are faster, but B's error is 0.2 and D went unstable
    assert pick[0.01]["scheme"] == "C"  # C and H tie at 2.0 s; C has the smaller error
    assert pick[0.001]["scheme"] == "E"
    assert pick[1e-4] is None
    # the threshold is inclusive: H alone reaches 1% exactly
    assert sva.cheapest([r for r in HAND_MADE if r["scheme"] in ("H", "B")], 0.01)["scheme"] == "H"
    table = sva.markdown(HAND_MADE)
    line = table.splitlines()[2]
    assert "A, 8 cells: 1 s" in line and "C, 8 cells: 2 s" in line and "E, 8 cells: 3 s" in line
    assert "| 1: D@8 |" in line  # one unstable run
    assert "none" in sva.markdown([r for r in HAND_MADE if r["scheme"] in ("A", "B")]).splitlines()[2]


def test_pareto_front_hand_made():
    front = {HAND_MADE[i]["scheme"] for i in sva.pareto_front(HAND_MADE)}
    assert front == {"B", "A", "C", "E"}  # D unstable, G dominated by A, H dominated by C
