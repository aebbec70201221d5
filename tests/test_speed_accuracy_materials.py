"""experiments/speed_accuracy_materials.py: the speed/accuracy chart and stability map on the material
scenes (issue 31 item 6).

* the stability flags on made-up histories (no run, no compilation): an affine velocity field has no
  intra-cell scatter and a checkerboard jitter its amplitude; particles crowding into one cell read as
  clumping; a kinetic energy that grows while nothing falls reads as energy growth; a sand column
  still moving at the end reads as not at rest; the table prints a failure with its cause;
* (slow: one compilation, ~10 s) the main loop on FLIP and PIC (one compiled loop) for a handful of
  steps of ``column_collapse`` gives well-formed rows, and a NaN planted in the state is caught
  as a failure with its step and cause.
"""

import math
from types import SimpleNamespace

import jax.numpy as jnp
import numpy as np
import pytest

import jaxmpm as jm
from experiments import speed_accuracy_materials as sam

GRID = jm.Grid((0.0, 0.0), (1.0, 1.0), (4, 4))  # cells of 0.25


def test_velocity_scatter_of_smooth_and_noisy_fields():
    """Four particles in a cell at the corners of a square and two in another: an affine velocity
    field scatters by 0 (round-off); a checkerboard jitter +-u on the square, orthogonal to every
    affine field there, scatters by exactly u; the cell of two (fewer than D + 2 particles) is
    left out; cell_counts counts the particles per cell."""
    square = np.array([[0.05, 0.05], [0.2, 0.05], [0.05, 0.2], [0.2, 0.2]])
    x = np.vstack([square, [[0.6, 0.6], [0.7, 0.7]]])
    affine = np.array([[1.0 + 3.0 * p[0] - p[1], 2.0 * p[1]] for p in x])
    assert sam.velocity_scatter(x, affine, GRID) == pytest.approx(0.0, abs=1e-14)
    jitter = affine.copy()
    jitter[:4, 0] += 0.3 * np.array([1.0, -1.0, -1.0, 1.0])
    jitter[4:] += [[5.0, 0.0], [-5.0, 0.0]]  # in the cell of two: not counted
    assert sam.velocity_scatter(x, jitter, GRID) == pytest.approx(0.3, rel=1e-13)
    assert math.isnan(sam.velocity_scatter(x[4:], jitter[4:], GRID))
    counts = sam.cell_counts(x[None], GRID)
    assert len(counts) == 1 and sorted(counts[0].tolist()) == [2, 4]


def _history(x, v, kinetic, strain):
    return SimpleNamespace(x=np.asarray(x), v=np.asarray(v), kinetic=np.asarray(kinetic), strain=np.asarray(strain))


def _setup(n):
    return SimpleNamespace(sim=SimpleNamespace(grid=GRID), state=SimpleNamespace(mass=np.ones(n)),
                           params={"gravity": 10.0})


def test_flags_of_made_up_histories():
    """Four particles, one per cell, at rest then: (a) falling 0.1 with the kinetic energy the fall
    released (m g dy = 4) and resting again: stable, in the column its KE end/peak is 0; (b) the
    same with a kinetic energy that ends at 5 > 4 released: energy growth (+25% of the released)
    and, as the sand still moves at its peak kinetic energy, not at rest; (c) all four crowded
    into one cell: clumping 4 > 3 (initially one per cell)."""
    x0 = np.array([[0.1, 0.6], [0.4, 0.6], [0.6, 0.6], [0.9, 0.6]])
    x1 = x0 - [0.0, 0.1]
    v = np.zeros((3, 4, 2))
    v[1, :, 1] = -1.0
    calm = _history([x0, x1, x1], v, [0.0, 4.0, 0.0], [0.0, 0.0, 0.0])
    flags = sam.stability_flags("column_collapse", calm, _setup(4))
    assert flags["flags"] == "" and flags["ke_end"] == 0.0 and flags["clumping"] == 1.0
    assert flags["energy_growth"] == pytest.approx(0.0, abs=1e-12)
    growing = _history([x0, x1, x1], v, [0.0, 4.0, 5.0], [0.0, 0.0, 0.0])
    flags = sam.stability_flags("column_collapse", growing, _setup(4))
    assert flags["energy_growth"] == pytest.approx(0.25, rel=1e-12)
    assert flags["ke_end"] == 1.0 and flags["flags"] == "not at rest, energy growth"
    crowded = np.full((4, 2), 0.6)
    clumped = _history([x0, crowded, crowded], np.zeros((3, 4, 2)), [0.0, 0.0, 0.0], [0.0, 0.0, 0.0])
    flags = sam.stability_flags("dam_break", clumped, _setup(4))
    assert flags["clumping"] == 4.0 and flags["flags"] == "clumping" and math.isnan(flags["ke_end"])


def test_table_prints_a_failure_with_its_cause():
    row = {"scene": "dam_break", "scheme": "FLIP", "family": "FLIP/PIC", "shape": "linear", "cells": 8,
           "particles": 512, "steps": 1372, "compile_s": 7.0, "run_s": 0.03,
           "failure": "J = det F <= 0 (step 72, t = 0.0156 s)"} | sam.EMPTY
    line = sam.table([row]).splitlines()[-1]
    assert line.startswith("| dam_break | FLIP | linear |")
    assert line.endswith("| failed: J = det F <= 0 (step 72, t = 0.0156 s) |")


class _NaNForce(jm.Term):
    """A nodal force that is NaN: the first step's particles turn NaN."""

    def grid_force(self, sim, fields, dt):
        return {"force": fields.force * jnp.nan}


@pytest.mark.slow
def test_main_loop_rows_and_a_planted_nan():
    """FLIP and PIC on 8 steps of a 2-cell column: each row has the table's columns, a finite error,
    compile and run times, and measures; a NaN planted in the first step's nodal force fails at step 1
    with the driver's cause, its row empty of measures."""
    rows = [sam.run_case("column_collapse", scheme, "quadratic", column_cells=2, steps=8)
            for scheme in ("flip", "pic")]
    for row, label in zip(rows, ("FLIP", "PIC")):
        assert row["scheme"] == label and row["family"] == "FLIP/PIC" and row["steps"] == 8
        assert row["failure"] == "" and math.isfinite(row["error"]) and row["run_s"] > 0
        assert all(math.isfinite(row[k]) for k in ("noise", "ke_end", "clumping", "energy_growth"))
        assert row.keys() == rows[0].keys()
    setup = sam.build("column_collapse", jm.FLIP(), jm.QuadraticBSpline(), 2, steps=8)
    setup.sim = setup.sim.with_term(_NaNForce())  # a NaN made by the first step (a NaN state is refused as input)
    failed = sam.run_case("column_collapse", "flip", "quadratic", setup=setup)
    assert failed["failure"].startswith("NaN or Inf in the particle state (step 1")
    assert math.isnan(failed["error"]) and failed["flags"] == ""
    assert failed.keys() == rows[0].keys()
    assert "failed: NaN or Inf" in sam.table([failed])
