"""jaxmpm against NairnMPM on the ``bar`` scene, without NairnMPM installed (issue 28).

Source: NairnMPM 19.0 (J. A. Nairn, github.com/nairnj/nairn-mpm-fea, commit 7f47b022), run by
``NAIRN_BIN=... python -m experiments.nairnmpm --store`` on the inputs
``experiments.nairnmpm.nairnmpm_input(case)`` writes: a plane-strain strip one cell thick,
E = 100, rho = 1, L = 25, v0 = 0.1, 16 cells x 2 ppc, dt = 0.1 h/c, NairnMPM's ``Isotropic``
material, the end fixed (x <= 0) or free; ``experiments.nairnmpm.CASES``: uGIMP under USL- for
every scheme and both ends over 2560 steps, and over 640 steps (one period) linear shapes under
USL+, uGIMP under USL+, USF, USAVG+ and USAVG-, and grid damping, particle damping and both.  Its
global archive (p_x, kinetic and strain energy after every step, seven significant digits) is
stored per case in tests/reference/nairnmpm/<case>.npz with the XML input and the version that
produced it.

jaxmpm runs the 1D bar with :class:`jaxmpm.IncrementalElastic`, under each case's conventions
(``Case.conventions``: ``"nairnmpm"`` where the codes' rules differ, jaxmpm's default where they
agree), and must equal NairnMPM at every archived step to the archive's precision: within half a
unit in the 7th significant digit of the archived value (times 1.001 for the float64 round-off
between the codes), which is 1.28e-7 v0 in v_cm at the largest momentum and 5.1e-8 E0 in each
energy.  The tolerances are the archive's digits, not the observed errors."""

import numpy as np
import pytest

import jaxmpm as jm
from experiments import nairnmpm as nm

# the archive's rounding (half a unit in the last digit), and float64 round-off between the two codes
ROUNDING = 0.5 * 1.001


def assert_agrees(case, ref, out):
    """Every archived p_x, E_kin, E_strain within the archive's rounding of jaxmpm's."""
    steps = ref["step"]
    np.testing.assert_allclose(out["time"][steps], ref["time"], rtol=1e-15, atol=0)
    for key in nm.QUANTITIES:
        diff = np.abs(out[key][steps] - ref[key])
        tol = ROUNDING * ref[f"{key}_unit"]
        worst = int(np.argmax(diff / tol))
        assert np.all(diff <= tol), (f"{case.name} {key}: step {steps[worst]}: jaxmpm {out[key][steps[worst]]!r}, "
                                     f"NairnMPM {ref[key][worst]!r} (archive digits), tolerance {tol[worst]:.3g}")


def test_cases():
    """The case set: the 14 uGIMP/USL- cases under their old names, 46 in all, names unique and
    systematic, and the inputs NairnMPM refuses refused here too."""
    names = [c.name for c in nm.CASES]
    assert len(names) == len(set(names)) == 46
    assert names[:14] == [f"{s}-{e}" for s in ("flip", "pic", "xpic2", "xpic5", "fmpm1", "fmpm2", "fmpm5")
                          for e in ("fixed", "free")]
    assert {"xpic2-fixed-linear-musl-steps640", "fmpm2-fixed-usavgm-steps640",
            "pic-fixed-damp-gp-steps640"} <= set(names)
    assert all(nm.case_named(n).name == n for n in names)
    with pytest.raises(ValueError, match="refuses linear"):
        nm.nairnmpm_input(nm.Case("flip", shape="linear", update="USAVG-"))


@pytest.mark.parametrize("case", [pytest.param(c, id=c.name) for c in nm.CASES])
def test_stored_reference_is_this_input(case):
    """Each stored output names NairnMPM 19.0 at commit 7f47b022 and was produced by the input the
    experiment writes today (same grid, particles, velocities, conditions, shape, update, damping
    and scheme), so the comparison below is the one the data answers."""
    ref = nm.load_reference(case)
    assert ref["version"].startswith("NairnMPM 19.0") and "7f47b022" in ref["version"]
    assert ref["xml"] == nm.nairnmpm_input(case)
    np.testing.assert_array_equal(ref["step"], np.arange(1, case.steps + 1))
    assert ref["mass"] == nm.RHO * nm.LENGTH * case.h * nm.THICKNESS
    x, y, v, m = nm.particles(case)
    assert np.sum(m) == ref["mass"]
    setup = nm.bar_setup(case)
    np.testing.assert_array_equal(x[::2], np.asarray(setup.particles.x)[:, 0])
    np.testing.assert_array_equal(v[::2], np.asarray(setup.particles.v)[:, 0])


@pytest.mark.slow
@pytest.mark.parametrize("case", [pytest.param(c, id=c.name) for c in nm.CASES])
def test_agrees_with_nairnmpm(case):
    """v_cm, kinetic and strain energy equal NairnMPM's at every step to its archive's precision."""
    ref = nm.load_reference(case)
    out = nm.run_jaxmpm(case)
    assert_agrees(case, ref, out)
    # the same in the units: v_cm to 1.28e-7 v0 (half a unit in p_x's 7th digit at its largest, over M)
    bound = ROUNDING * np.max(ref["px_unit"]) / ref["mass"]
    assert np.max(np.abs(out["v_cm"][ref["step"]] - ref["v_cm"])) <= bound <= 1.3e-7 * nm.V0


# the preset spelled out as options, with the other damped velocity: alpha_g S v+ for FLIP, alpha_g S v for
# PIC, XPIC and FMPM (jaxmpm's default, "lumped") in place of NairnMPM's S(p/m), S(v(m) + a dt), S v+
OTHER_DAMPED_VELOCITY = {
    "flip": jm.FLIP(damping_velocity="updated"),
    "pic": jm.PIC(position="PV_tilde", damping_velocity="lumped"),
    "xpic:2": jm.XPIC(2, position="PV_tilde", boundary="unconstrained_start", damping_velocity="lumped"),
    "fmpm:2": jm.FMPM(2, damping_velocity="lumped"),
}


@pytest.mark.slow
@pytest.mark.parametrize("case", [pytest.param(c, id=c.name) for c in nm.DAMPING_CASES if c.damping == nm.DAMPING["g"]])
def test_grid_damping_velocity_is_nairnmpms(case):
    """NairnMPM's damped velocity is the preset's (``damping_velocity``), seen in its data: with the
    rest of the preset kept and the other velocity damped, v_cm leaves NairnMPM's by 1e-4 v0 or more
    (the preset itself agrees to the archive's digits, test_agrees_with_nairnmpm)."""
    ref = nm.load_reference(case)
    out = nm.run_jaxmpm(case, "jaxmpm", scheme=OTHER_DAMPED_VELOCITY[case.scheme], constrained_force="reaction")
    assert np.max(np.abs(out["v_cm"][ref["step"]] - ref["v_cm"])) > 1e-4 * nm.V0
