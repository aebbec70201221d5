"""The ``disks`` scene (Sulsky, Chen & Schreyer 1994, §6): two elastic disks collide and separate.

Checked: conservation of linear momentum (exact for MPM without boundary conditions), the energy
history (conservation law, FLIP vs PIC), and the collision itself.
"""

import numpy as np
import pytest

import jaxmpm as jm


@pytest.fixture(scope="module")
def runs():
    out = {}
    for name, scheme in {"flip": jm.FLIP(), "pic": jm.PIC()}.items():
        setup = jm.scene("disks", scheme=scheme)
        final, hist = setup.run()
        out[name] = (setup, hist)
    return out


def energy(hist):
    e = np.asarray(hist.kinetic + hist.strain)
    return e / e[0]


@pytest.mark.slow
@pytest.mark.parametrize("name", ["flip", "pic"])
def test_linear_momentum_conserved(runs, name):
    setup, hist = runs[name]
    scale = float(np.sum(np.asarray(setup.state.mass) * np.linalg.norm(np.asarray(setup.state.v), axis=1)))
    drift = np.max(np.linalg.norm(np.asarray(hist.momentum) - np.asarray(hist.momentum[0]), axis=1))
    assert drift / scale <= 1e-10


def test_flip_energy(runs):
    """FLIP keeps the energy before contact to 0.1% and ends within 5% at t = 4.

    Measured and reported (issue note, README): during contact (t = 1.3-2.4) the total particle
    energy dips by 10% (min 0.898, uGIMP) and recovers to 0.973 after separation.  The two disks
    share grid nodes in single-velocity-field MPM, so the grid velocity averages their opposing
    velocities (a locally inelastic, sticky impact); the dip does not shrink with dt or h (linear
    shapes: 0.913 at dt = 2.5e-4, 0.905 at h = 0.025) and is not a bound we can hold through contact.
    """
    setup, hist = runs["flip"]
    t = np.asarray(hist.time)
    e = energy(hist)
    assert t[-1] == pytest.approx(4.0)
    assert np.all(np.abs(e[t < 1.2] - 1.0) <= 1e-3)  # grid contact begins ~1.3
    assert abs(e[-1] - 1.0) <= 0.05
    assert 0.85 <= e.min() <= 0.95  # the contact dip, measured 0.898


def test_pic_dissipates_more_than_flip(runs):
    assert energy(runs["pic"][1])[-1] < 0.5 * energy(runs["flip"][1])[-1]


@pytest.mark.parametrize("name", ["flip", "pic"])
def test_disks_collide_and_separate(runs, name):
    setup, hist = runs[name]
    n1 = setup.params["n_first"]
    vx = np.asarray(hist.v)[:, :n1, 0].mean(axis=1)
    assert vx[0] == pytest.approx(0.1)
    assert vx[-1] < 0.0  # the lower-left disk bounced back
    x1 = np.asarray(hist.x)[:, :n1, 0].mean(axis=1)
    assert x1.max() > x1[0] + 0.1 and x1[-1] < x1.max()
