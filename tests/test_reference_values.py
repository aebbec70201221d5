"""Behaviour preserved: numbers stored before a refactor, compared with what the library computes now.

* ``values.npz`` -- stored before the open-core refactor (issue 10), on commit 025c38f: one step of
  every scheme x shape x dimension (plus USF/MUSL, the folded affine P2G with walls and a fluid, and
  the XPIC/FMPM options) to 1e-13 relative, whole ``bar`` and ``spin`` runs to 1e-10 (float64).
* ``values_v2.npz`` -- stored before the core v2 refactor (issue 27), on commit 6c6f418: USAVG-/USAVG+
  for every scheme, every contact law with every scheme (1D-3D, three materials, both normals, the
  separation criterion, walls), the damping variants, the transport / load / reaction / stress-XPIC
  terms, r-z grids, the exponential increment -- one step each to 1e-13 with every particle field --
  and whole ``disks``, ``bars_impact`` and ``heat1d`` runs to 1e-10.

``tests/reference/configs.py`` builds every case through the public API; ``generate.py`` wrote the
files.  Each one-step case compiles its step, as the stored values were computed.  They once ran
eagerly (``jax.disable_jit``), but lowering each primitive anew per case cost more than compiling the
step: the 259 one-step cases took 277 s eagerly against 216 s jitted (2-core machine, the two runs
side by side)."""

import os

import jax
import numpy as np
import pytest
from reference import configs

HERE = os.path.join(os.path.dirname(__file__), "reference")
STORED = {name: np.load(os.path.join(HERE, name)) for name in ("values.npz", "values_v2.npz")}


def tiered(cases):
    """The one-step cases, the 1D ones (and the r-z ones) in the fast tier and the 2D and 3D ones
    (three quarters of the module's time) in the slow tier."""
    return [name if "-1d" in name or name.startswith("rz-") else pytest.param(name, marks=pytest.mark.slow)
            for name in cases]


def _jitted_step(sim, state, dt):
    return jax.jit(lambda s, d: sim.step(s, d))(state, dt)


ENERGIES = ("kinetic", "strain", "dissipated", "material_kinetic", "material_strain")
MOMENTA = ("momentum", "angular", "material_momentum")


def _compare(store, prefix, values, rtol, energy_scale=0.0, force_scale=0.0, momentum_scale=0.0):
    """Every stored array to ``rtol`` of its largest entry, or of its physical scale where the
    quantity is round-off of a zero: an energy (the dissipated energy, a difference of two energies
    that cancel to 1e-17 against 1e-2 under FLIP with walls; the strain energy of stress-free disks
    before they meet, 1e-33) to ``rtol`` of the starting kinetic energy (``energy_scale``); a force
    field (contact, reaction), round-off where no force acts (1e-16 against 1e1 when the bodies
    already move apart), to ``rtol`` of the momentum change per step sum_p M_p |V_p| / dt
    (``force_scale``); a total momentum or angular momentum, round-off for a spinning disk or two
    equal bodies meeting head on, to ``rtol`` of sum_p M_p |V_p| at the start
    (``momentum_scale``).  Round-off is not reproducible across compilers and optimisation levels;
    these scales keep every comparison at ``rtol`` of what the physics sets."""
    stored = STORED[store]
    keys = sorted(k[len(prefix):] for k in stored.files if k.startswith(prefix))
    assert keys and sorted(values) == keys
    for key in keys:
        ref, got = stored[prefix + key], values[key]
        assert got.shape == ref.shape and got.dtype == ref.dtype, key
        scale = np.max(np.abs(ref[np.isfinite(ref)]), initial=0.0)
        if key in ENERGIES:
            scale = max(scale, energy_scale)
        if key.endswith("_force"):
            scale = max(scale, force_scale)
        if key in MOMENTA:
            scale = max(scale, momentum_scale)
        np.testing.assert_allclose(got, ref, rtol=0, atol=rtol * max(scale, 1e-300), equal_nan=True,
                                   err_msg=f"{prefix}{key}")


def _kinetic(state):
    return 0.5 * float(np.sum(np.asarray(state.mass)[:, None] * np.asarray(state.v) ** 2))


def _momentum(state):
    """sum_p M_p |V_p|: the scale of a momentum."""
    return float(np.sum(np.asarray(state.mass) * np.linalg.norm(np.asarray(state.v), axis=-1)))


@pytest.mark.parametrize("name", tiered(configs.one_step_cases()))
def test_one_step_matches_stored(name):
    sim, state, dt = configs.build(**configs.one_step_cases()[name])
    _compare("values.npz", f"step/{name}/", configs.one_step_values(sim, state, dt, _jitted_step), 1e-13,
             _kinetic(state))


@pytest.mark.parametrize("name", tiered(configs.v2_step_cases()))
def test_core_v2_step_matches_stored(name):
    sim, state, dt = configs.build_v2(**configs.v2_step_cases()[name])
    _compare("values_v2.npz", f"step/{name}/", configs.v2_step_values(sim, state, dt, _jitted_step), 1e-13,
             _kinetic(state), _momentum(state) / dt)


@pytest.mark.slow
@pytest.mark.parametrize("name", list(configs.RUNS))
def test_run_matches_stored(name):
    setup = configs.run_setup(name)
    _compare("values.npz", f"run/{name}/", configs.run_values(setup), 1e-10, _kinetic(setup.state),
             _momentum(setup.state) / setup.dt, _momentum(setup.state))


@pytest.mark.slow
@pytest.mark.parametrize("name", list(configs.RUNS_V2))
def test_core_v2_run_matches_stored(name):
    setup = configs.run_setup_v2(name)
    start = setup.state
    _compare("values_v2.npz", f"run/{name}/", configs.run_values_v2(setup), 1e-10, _kinetic(start),
             _momentum(start) / setup.dt, _momentum(start))
