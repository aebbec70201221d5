"""Behaviour preserved: the numbers stored before the open-core refactor (issue 10), on commit
025c38f, by ``tests/reference/generate.py`` -- one step of every scheme x shape x dimension
(plus USF/MUSL, the folded affine P2G with walls and a fluid, and the XPIC/FMPM options) agrees
to 1e-13 relative, whole ``bar`` and ``spin`` runs to 1e-10 (float64)."""

import os

import equinox as eqx
import numpy as np
import pytest

from reference import configs

STORED = np.load(os.path.join(os.path.dirname(__file__), "reference", "values.npz"))


@eqx.filter_jit
def _step(sim, state, dt):
    # jitted, as the stored values were: each case compiles in about a second, where running it
    # eagerly op by op (each conditional and loop compiled on its own) takes 2-5 s
    return sim.step(state, dt)


def _compare(prefix, values, rtol, energy_scale=0.0):
    """Every stored array to ``rtol`` of its largest entry; the dissipated energy, a difference of
    two energies that can cancel to round-off (1e-17 against 1e-2 under FLIP with walls), to
    ``rtol`` of the energies it is the difference of (``energy_scale``)."""
    stored = sorted(k[len(prefix):] for k in STORED.files if k.startswith(prefix))
    assert sorted(values) == stored
    for key in stored:
        ref, got = STORED[prefix + key], values[key]
        assert got.shape == ref.shape and got.dtype == ref.dtype, key
        scale = np.max(np.abs(ref[np.isfinite(ref)]), initial=0.0)
        if key == "dissipated":
            scale = max(scale, energy_scale)
        np.testing.assert_allclose(got, ref, rtol=0, atol=rtol * max(scale, 1e-300), equal_nan=True,
                                   err_msg=f"{prefix}{key}")


@pytest.mark.parametrize("name", list(configs.one_step_cases()))
def test_one_step_matches_stored(name):
    sim, state, dt = configs.build(**configs.one_step_cases()[name])
    kinetic = 0.5 * float(np.sum(np.asarray(state.mass)[:, None] * np.asarray(state.v) ** 2))
    _compare(f"step/{name}/", configs.one_step_values(sim, state, dt, _step), 1e-13, kinetic)


@pytest.mark.parametrize("name", list(configs.RUNS))
def test_run_matches_stored(name):
    _compare(f"run/{name}/", configs.run_values(configs.run_setup(name)), 1e-10)
