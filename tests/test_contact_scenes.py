"""The contact scenes of issue 12: ``disks``/``rings`` with ``contact=``, ``bars_impact`` and
``slide`` (float64, default sizes, about 30 s in all).

* ``disks`` with contact="none" is today's single-field model: the same Simulation and bitwise
  the same steps.
* ``bars_impact`` (frictionless, FLIP, linear shape functions, 32 cells a bar): the bars part with
  their velocities exchanged.  Exit velocity = a bar's momentum / mass at t_end = 4L/c (after
  separation contact is the only force on a bar, so it is constant).  Contact duration = the last
  time the left bar's momentum changes in a step by more than 1e-3 rho c v0 dt (the exact contact
  stress is rho c v0 for 2L/c): in multimaterial mode the contact law is the only coupling of the
  two bars, so that change *is* the interface force times dt.
* ``slide`` (FLIP, uGIMP, jm.Contact's default normal "first" -- the slab's, h = 0.025,
  t_end = 0.315): the block's centre-of-mass displacement along x against
  g (sin theta - mu cos theta) t^2 / 2.
* the contact normal: the ``slide`` block launched along a flat slab (theta = 0, h = 1/32) brakes
  at mu g with the default normal, and without a normal load (g = 0) not at all; the averaged
  normal ploughs (jaxmpm/physics/contact.py lists the normals, their sources and measurements).

Measured (this file's runs): bars exit velocities -+0.09492 (5.1 % short of v0 = 0.1; uGIMP
6.6 %; 64 cells 3.4 %; uGIMP 256 cells FLIP 1.45 %, XPIC(2) 1.40 %, FMPM(2) 1.25 %), contact
duration 0.2031 (+1.6 % of 2L/c; uGIMP +1.9 %).  Slide: mu = 0 0.24279 vs 0.24279 (-0.00 %),
mu = 0.2 0.16045 vs 0.15869 (+1.1 %), mu = 0.7 0.01518 = 6.3 % of the frictionless 0.24279
(creeps: the undamped slab rings; with gravity ramped over 0.05 s 0.13 %; PIC 0.74 %; normal="average"
0.53 %, but "average" slides 12 % and 24 % short at mu = 0 and 0.2).
"""

import math

import equinox as eqx
import jax
import numpy as np
import pytest

import jaxmpm as jm


# ------------------------------------------------------------------ disks: contact="none" is today's model
@pytest.mark.slow
def test_disks_without_contact_is_the_single_field_model_bitwise():
    options = dict(t_end=5e-3, frames=5)  # 5 steps of dt = 1e-3
    none = jm.scene("disks", contact="none", **options)
    default = jm.scene("disks", **options)
    # the model disks built before it took a contact option
    before = jm.Simulation(grid=default.sim.grid, shape=jm.UGIMP(ppc=2),
                           material=jm.LinearElastic(E=1000.0, nu=0.3, density=1000.0), scheme=jm.FLIP())
    before_state = jm.scenes.cast_state(before.init(default.particles), default.state.x.dtype)
    assert bool(eqx.tree_equal(none.sim, default.sim, before))
    assert none.sim.term(jm.Contact) is None and none.fields is None and "material" not in none.state.fields
    assert bool(eqx.tree_equal(none.state, default.state, before_state))
    final, history = none.run()
    rerun = before.run(before_state, default.dt, default.steps, default.save_every)
    for other, other_history in (default.run(), rerun):
        for a, b in zip(jax.tree_util.tree_leaves((final, history)), jax.tree_util.tree_leaves((other, other_history))):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_disks_with_a_law_give_each_disk_its_material():
    setup = jm.scene("disks", contact="coulomb", friction=0.25, spacing=0.1, t_end=2e-3, frames=2)
    contact = setup.sim.term(jm.Contact)
    assert contact.law == "coulomb" and float(contact.friction) == 0.25
    ids = np.asarray(setup.state.fields["material"])
    n = setup.params["n_first"]
    assert np.all(ids[:n] == 0.0) and np.all(ids[n:] == 1.0) and n < ids.size
    np.testing.assert_array_equal(ids, np.asarray(setup.fields["material"]))


# ------------------------------------------------------------------ bars_impact
def bar_run(**options):
    """(time, left and right mean velocities, facing-end gap, interface stress / (rho c v0), setup),
    one frame per step."""
    setup = jm.scene("bars_impact", **options)
    _, h = setup.sim.run(setup.state, setup.dt, setup.steps, 1)
    n = setup.params["n_first"]
    m = np.asarray(setup.state.mass)
    v, x, t = np.asarray(h.v)[..., 0], np.asarray(h.x)[..., 0], np.asarray(h.time)
    left = v[:, :n] @ m[:n] / m[:n].sum()
    right = v[:, n:] @ m[n:] / m[n:].sum()
    gap = x[:, n:].min(axis=1) - x[:, :n].max(axis=1)
    force = -np.diff(left * m[:n].sum()) / np.diff(t) / setup.params["contact_stress"]
    return t, left, right, gap, force, setup


@pytest.fixture(scope="module")
def frictionless_bars():
    return bar_run(scheme="flip", contact="frictionless")


@pytest.mark.slow
def test_bars_part_and_conserve_momentum(frictionless_bars):
    t, left, right, gap, force, setup = frictionless_bars
    v0, duration = setup.params["v0"], setup.params["contact_duration"]
    assert left[0] == pytest.approx(v0, rel=1e-14) and right[0] == pytest.approx(-v0, rel=1e-14)
    np.testing.assert_allclose(left + right, 0.0, atol=1e-14 * v0)  # sum_a Dp^a = 0, identical bars
    assert left[-1] < -0.9 * v0 and right[-1] > 0.9 * v0  # they leave with the velocities (almost) exchanged
    after = t > 1.1 * duration
    assert np.all(np.diff(gap[after]) > 0)  # flying apart
    assert gap[-1] - gap[after][0] > 0.9 * 2 * v0 * (t[-1] - t[after][0])


@pytest.mark.xfail(strict=True, raises=AssertionError,
                   reason="measured exit velocities -+0.09492: 5.1 % of v0 short of the exchange (FLIP, linear, "
                          "32 cells; uGIMP 6.6 %, 64 cells 3.4 %, 128 cells ppc 4 2.4 %)")
def test_bars_exit_velocities_are_exchanged_within_2_percent(frictionless_bars):
    _, left, right, _, _, setup = frictionless_bars
    v0 = setup.params["v0"]
    exit_left, exit_right = setup.params["exit_velocities"]
    assert abs(left[-1] - exit_left) <= 0.02 * v0 and abs(right[-1] - exit_right) <= 0.02 * v0


@pytest.mark.slow
@pytest.mark.parametrize("scheme", ["flip", "xpic:2", "fmpm:2"])
def test_bars_exit_velocities_converge_to_the_exchange(scheme):
    """The exchange converges with h at about order 0.75 (uGIMP, frictionless, exit error / v0 at
    32, 64, 128, 256 cells a bar -- FLIP 6.6, 3.9, 2.3, 1.45 %; XPIC(2) 6.4, 3.7, 2.3, 1.40 %;
    FMPM(2) 6.3, 3.6, 2.1, 1.25 %, measured 2026-11-29): within issue 12's 2 % from 256 cells (1D, 1024 particles,
    10240 steps, ~3 s).  Linear shapes cannot be refined that far: their free ends invert a
    particle (J <= 0) from 128 cells (experiments/results/contact.md)."""
    setup = jm.scene("bars_impact", scheme=scheme, shape="ugimp", cells=256, frames=2)
    final, _ = setup.run()
    n, v0 = setup.params["n_first"], setup.params["v0"]
    m, v = np.asarray(setup.state.mass), np.asarray(final.v)[:, 0]
    exit_left, exit_right = v[:n] @ m[:n] / m[:n].sum(), v[n:] @ m[n:] / m[n:].sum()
    assert abs(exit_left + v0) <= 0.02 * v0 and abs(exit_right - v0) <= 0.02 * v0, (exit_left, exit_right)
    stated = {"flip": 0.0145, "xpic:2": 0.0140, "fmpm:2": 0.0125}[scheme]  # the numbers docs/contact.md gives
    assert abs(exit_left + v0) / v0 == pytest.approx(stated, abs=1e-4), exit_left


def test_bars_contact_lasts_2L_over_c(frictionless_bars):
    """Measured 0.2031 against 2L/c = 0.2 (+1.6 %)."""
    t, _, _, _, force, setup = frictionless_bars
    duration = setup.params["contact_duration"]
    active = np.nonzero(np.abs(force) > 1e-3)[0]
    assert t[active[0]] <= 2 * setup.dt  # the bars touch at t = 0 (FLIP feels it once stress has built up)
    end = t[active[-1] + 1]
    assert abs(end / duration - 1) <= 0.05, end
    # no force once apart (the fields no longer share nodes): the momentum only rounds off
    assert np.all(np.abs(force[t[1:] > end]) <= 1e-12)


def test_single_field_bars_do_not_part():
    """contact="none": one velocity field glues the bars (a free-free bar of length 2L)."""
    t, left, right, gap, _, setup = bar_run(scheme="flip", contact="none")
    h = setup.params["length"] / setup.params["cells_along_bar"]
    assert setup.sim.term(jm.Contact) is None
    assert np.all(gap < h)  # the facing ends never part by a cell
    assert left[-1] > 0 > right[-1]  # measured +-0.0912 at t = 4L/c: no exchange


# ------------------------------------------------------------------ slide
def block_displacement(setup):
    _, h = setup.run()
    n = setup.params["n_first"]
    m = np.asarray(setup.state.mass)[n:]
    com = np.asarray(h.x)[:, n:, 0] @ m / m.sum()
    return float(np.asarray(h.time)[-1]), com[-1] - com[0]


def frictionless_slide(setup, t):
    theta = math.radians(setup.params["theta"])
    return 0.5 * setup.params["gravity"] * math.sin(theta) * t**2


@pytest.mark.slow
@pytest.mark.parametrize("mu", [0.0, 0.2])
def test_slide_follows_the_exact_displacement(mu):
    """Measured: mu = 0 -0.00 %, mu = 0.2 +1.1 % at t = 0.315 (the block slides 9.7 and 6.4 cells)."""
    setup = jm.scene("slide", friction=mu)
    assert setup.params["slides"] and setup.params["mu"] == mu
    t, d = block_displacement(setup)
    exact = float(setup.reference(t))
    assert exact == pytest.approx(0.5 * 9.8 * (0.5 - mu * math.sqrt(3) / 2) * t**2, rel=1e-12)
    assert exact > 4 * setup.params["spacing"]
    assert abs(d / exact - 1) <= 0.02, (d, exact)


@pytest.mark.slow
@pytest.mark.xfail(strict=True, raises=AssertionError,
                   reason="measured 0.01518 = 6.3 % of the frictionless 0.24279 at t = 0.315 (FLIP, uGIMP, "
                          "normal='first', gravity at once): the ringing slab ratchets the block down at ~0.05 "
                          "m/s; under a ramped load it holds (test_slide_under_a_ramped_load)")
def test_slide_with_mu_07_stays_stuck():
    setup = jm.scene("slide", friction=0.7)
    assert not setup.params["slides"] and setup.reference(1.0) == 0.0
    t, d = block_displacement(setup)
    assert abs(d) <= 0.01 * frictionless_slide(setup, t), d


@pytest.mark.slow
@pytest.mark.parametrize("mu", [0.0, 0.7])
def test_slide_under_a_ramped_load(mu):
    """FLIP's creep at mu = 0.7 (previous test) is driven by vibration: gravity switched on at
    t = 0 sets the undamped elastic slab ringing (FLIP keeps the ringing; PIC damps it), and a node
    sticks only while the step's tangential impulse stays inside mu times the normal one -- the
    ringing slab surface breaks that at 7 of 10 contact nodes per step, so the block ratchets down
    the incline at ~0.05 m/s.  Raise gravity over 0.05 s (a quasi-static load) and the block
    holds: measured 0.00027 at t = 0.315 (0.13 % of the frictionless displacement, its elastic shear,
    settled by t = 0.06), while the frictionless block follows the ramped exact solution
    A (t^2/2 - r t/2 + r^2/6) to -0.1 %."""
    setup = jm.scene("slide", friction=mu, ramp=0.05)
    t, d = block_displacement(setup)
    frictionless = 0.5 * 9.8 * 0.5 * (t**2 - 0.05 * t + 0.05**2 / 3)
    if mu == 0.0:
        assert float(setup.reference(t)) == pytest.approx(frictionless, rel=1e-12)
        assert d == pytest.approx(frictionless, rel=0.02), (d, frictionless)
    else:
        assert setup.reference(t) == 0.0
        assert abs(d) <= 0.01 * frictionless, d


@pytest.mark.slow
def test_slide_with_mu_07_stays_stuck_with_pic():
    """PIC: measured 0.00180 = 0.74 % of the frictionless displacement."""
    setup = jm.scene("slide", friction=0.7, scheme="pic")
    t, d = block_displacement(setup)
    assert abs(d) <= 0.01 * frictionless_slide(setup, t), d


@pytest.mark.slow
def test_slide_glued_without_contact():
    """contact="none" (one field) and "stick": the block does not slide (reference 0); measured
    |d| <= 4.1e-4 (it rocks), 0.17 % of the frictionless displacement."""
    for contact in ("none", "stick"):
        setup = jm.scene("slide", contact=contact)
        assert setup.reference(setup.t_end) == 0.0
        t, d = block_displacement(setup)
        assert abs(d) <= 0.01 * frictionless_slide(setup, t), (contact, d)


# ------------------------------------------------------------------ a block braked on a flat slab: the contact normal
V0, MU, G = 1.0, 0.2, 9.8


def braked_block(normal=None, **options):
    """The ``slide`` block launched at V0 = 1 m/s along a flat slab (theta = 0, Coulomb mu = 0.2,
    h = 1/32, FLIP, uGIMP): (t, the block's centre-of-mass velocity and x displacement at t, the
    largest slab particle speed at t, setup).  ``normal``: None is jm.Contact's default."""
    chosen = {} if normal is None else {"normal": normal}
    setup = jm.scene("slide", theta=0.0, speed=V0, friction=MU, spacing=1 / 32, frames=2, **chosen, **options)
    _, h = setup.run()
    n = setup.params["n_first"]
    m = np.asarray(setup.state.mass)[n:]
    v = np.asarray(h.v)[-1, n:].T @ m / m.sum()
    dx = (np.asarray(h.x)[-1, n:, 0] - np.asarray(h.x)[0, n:, 0]) @ m / m.sum()
    slab = float(np.abs(np.asarray(h.v)[-1, :n]).max())
    return float(np.asarray(h.time)[-1]), v, float(dx), slab, setup


@pytest.mark.slow
@pytest.mark.parametrize("normal, low, high", [(None, 0.99, 1.01), ("max_gradient", 0.99, 1.01),
                                               ("average", 1.3, 1.6)])
def test_block_on_a_slab_decelerates_at_mu_g(normal, low, high):
    """Issue: Coulomb contact with the averaged normal ploughs.  A block sliding on a flat slab,
    gravity normal to it, decelerates at mu g (kinetic friction, mu times the normal load).
    Gravity is raised over r = 0.05 s (``ramp``: the block settles on the slab without ringing), so
    the exact velocity is V0 - mu g (t - r/2) and the displacement ``setup.reference(t)``; t = 0.15
    (362 steps).  Measured deceleration / mu g (h = 1/32; jaxmpm/physics/contact.py lists 1/40 to
    1/64 too): the default ``"first"`` (the slab's normal, Nairn contact notes eq. 3.1) 0.9974,
    ``"max_gradient"`` (NairnMPM's maxgrad, notes eq. 3.3) 0.9972, ``"average"`` (avggrad, notes
    eq. 3.2) 1.446 -- its normal tilts at the block's leading corner, where the sliding then counts
    as approach.  At h = 1/64 (the slab's top half a cell off the node lines) "first" gives 0.9975
    and "max_gradient" goes unstable; with the block numbered 0, "first" gives 4.06 at 1/32.
    Displacement against the exact one: +0.054 % ("first"), +0.053 % ("max_gradient")."""
    ramp = 0.05
    t, v, dx, _, setup = braked_block(normal, ramp=ramp, t_end=0.15)
    assert setup.sim.term(jm.Contact).normal == ("first" if normal is None else normal)
    assert setup.params["acceleration"] == pytest.approx(-MU * G, rel=1e-14) and setup.params["stop"] > t
    ratio = (V0 - v[0]) / (MU * G * (t - ramp / 2))
    assert low <= ratio <= high, ratio
    if normal != "average":
        exact = float(setup.reference(t))
        assert exact == pytest.approx(V0 * t - MU * G * (t**2 / 2 - ramp * t / 2 + ramp**2 / 6), rel=1e-12)
        assert abs(dx / exact - 1) <= 1e-3, (dx, exact)


@pytest.mark.slow
@pytest.mark.parametrize("normal", [None, (0.0, 1.0), "average"])
def test_block_on_a_slab_without_load_keeps_its_speed(normal):
    """g = 0: no normal load, so no friction: the block slides on at V0 and the slab stays at rest.
    Measured at t = 0.05 (121 steps, h = 1/32): the default "first" and the specified normal (0, 1)
    (NairnMPM's "specify", Nairn contact notes §3.3) leave the block's velocity at exactly
    (1, 1.7e-17) and the slab at 7e-17; "average" takes 0.088 m/s off it (1.75 m/s^2) and lifts it
    at 0.19 m/s: its tilted normals at the block's corners turn the sliding into approach."""
    t, v, _, slab, setup = braked_block(normal, gravity=0.0, t_end=0.05)
    assert setup.params["acceleration"] == 0.0 and setup.reference(t) == pytest.approx(V0 * t, rel=1e-14)
    if normal == "average":
        assert V0 - v[0] > 0.05 and v[1] > 0.1, v  # the defect, measured
    else:
        np.testing.assert_allclose(v, [V0, 0.0], rtol=0, atol=1e-14)
        assert slab <= 1e-14, slab


# ------------------------------------------------------------------ disks: the energy through a frictionless impact
@pytest.mark.slow
def test_disks_frictionless_contact_keeps_the_energy_through_the_impact():
    """Sulsky's disks (h = 0.05, uGIMP, FLIP, t = 4) with frictionless contact and the scene's
    separation criterion (1 cell): the total energy stays >= 0.95 of its initial value through the
    impact (measured minimum 0.951 with jm.Contact's default normal "first"; 0.955 with "average",
    0.937 with "max_gradient"; single-field 0.898; without the criterion 0.896, because the disks
    then interact from a cell apart) and the disks part (their centres of mass move apart
    again after the closest approach)."""
    setup = jm.scene("disks", contact="frictionless")
    _, hist = setup.run()
    energy = np.asarray(hist.total_energy) / float(hist.total_energy[0])
    assert energy.min() >= 0.95, energy.min()
    n = setup.params["n_first"]
    x, m = np.asarray(hist.x), np.asarray(setup.state.mass)
    gap = np.linalg.norm((x[:, n:] * m[n:, None]).sum(1) / m[n:].sum() - (x[:, :n] * m[:n, None]).sum(1) / m[:n].sum(),
                         axis=1)
    closest = int(gap.argmin())
    assert 0 < closest < len(gap) - 1 and gap[-1] > gap[closest] + 0.3, (gap[closest], gap[-1])
    momentum = np.asarray(hist.momentum)
    assert np.abs(momentum - momentum[0]).max() <= 1e-12 * float(
        (m * np.linalg.norm(np.asarray(hist.v[0]), axis=1)).sum())


def test_separation_criterion_narrows_the_contact_nodes():
    """Two materials share a node; their nodal centres of mass are 0.5 h apart along n: in contact
    for separation >= 0.5, not below (jaxmpm/_contact.py, Contact.touching)."""
    import jax.numpy as jnp

    h = 1.0
    contact = jm.Contact(law="stick", separation=0.5)
    m0, m1 = jnp.array([1.0, 1.0]), jnp.array([1.0, 0.0])
    moments = jnp.array([[0.0], [0.0], [0.5], [0.0]])  # material 0 at 0, material 1 at 0.5 (node 0)

    class Fields:
        values = {"mass_moment": moments}

    normal = jnp.array([[1.0], [1.0]])
    assert bool(contact.touching(Fields, m0, m1, normal, h)[0])
    assert not bool(jm.Contact(law="stick", separation=0.49).touching(Fields, m0, m1, normal, h)[0])
    with pytest.raises(jm.InputError, match="separation"):
        jm.Contact(separation=float("nan"))


def test_separation_criterion_of_three_materials_against_the_rest():
    """M = 3 (000 §4, each material against the rest's nodal centre of mass): at node 0 material 0 sits at 0,
    material 1 (mass 1) at 0.2 and material 2 (mass 3) at 1.0, so the rest of material 0 is at (0.2 + 3) / 4 =
    0.8, of material 1 at 3 / 4 = 0.75, of material 2 at 0.1; along n = +x that is 0.8, 0.55 and -0.9 h away.
    With separation 0.6 materials 1 and 2 touch, 0 does not.  Node 1 holds material 0 alone."""
    import jax.numpy as jnp

    masses = jnp.array([1.0, 1.0, 1.0, 0.0, 3.0, 0.0])  # (M n): material a's nodes at [a n, (a + 1) n)
    moments = jnp.array([[0.0], [0.0], [0.2], [0.0], [3.0], [0.0]])

    class Fields:
        values = {"mass_moment": moments}

    normals = jnp.ones((3, 2, 1))
    touching = jm.Contact(materials=3, separation=0.6).touching_rest(Fields, masses, normals, 1.0)
    assert touching.shape == (3, 2)
    assert touching[:, 0].tolist() == [False, True, True]


# ------------------------------------------------------------------ rings
@pytest.mark.slow
@pytest.mark.parametrize("contact, friction", [("frictionless", 0.0), ("coulomb", 0.3)])
def test_rings_with_contact_conserve_momentum_and_part(contact, friction):
    """The neo-Hookean rings (h = 0.25, FLIP, t = 0.3), each ring its own material: the total
    momentum stays zero to round-off, the contact forces on the two rings are equal and opposite
    at every frame, and the rings part (measured, both laws alike -- head-on, nothing slides:
    centres 4.61 apart at the closest, t = 0.19, from 10 at t = 0 -- the rings flatten -- then
    parting at 0.72 of the approach speed; energy/E0 0.75 at t = 0.3)."""
    setup = jm.scene("rings", contact=contact, friction=friction, spacing=0.25, t_end=0.3, frames=60)
    _, hist = setup.run()
    n = setup.params["n_first"]
    m, x = np.asarray(setup.state.mass), np.asarray(hist.x)
    scale = float((m * np.linalg.norm(np.asarray(hist.v[0]), axis=1)).sum())
    assert np.abs(np.asarray(hist.momentum)).max() <= 1e-12 * scale
    force = np.asarray(hist.by_material["contact_force"])
    np.testing.assert_allclose(force[:, 0] + force[:, 1], 0.0, atol=1e-9 * np.abs(force).max())
    assert np.abs(force).max() > 0
    centre = lambda sl: (x[:, sl] * m[sl, None]).sum(1) / m[sl].sum()  # noqa: E731
    d = np.linalg.norm(centre(slice(n, None)) - centre(slice(0, n)), axis=1)
    t = np.asarray(hist.time)
    closest = int(d.argmin())
    speed = 2 * setup.params["speed"]
    rebound = (d[-1] - d[-6]) / (t[-1] - t[-6]) / speed
    assert 0 < closest < len(d) - 6 and rebound > 0.3
