"""Drucker-Prager elastoplasticity (jaxmpm/materials/drucker_prager.py) at the material point, float64.

Every strain path runs as one jitted ``lax.scan`` (the material is an argument, so gradients with
respect to its parameters flow through the same compiled path).  Checked against closed forms:

* the return lands on the cone, f = sqrt(J2) + eta p - xi c = 0, to round-off (uniaxial and
  biaxial strain, plane strain and 3D), and never leaves it (f <= 0 at every step);
* the plastic strain increment follows the flow rule of psi: along dev eps*, with
  tr(d eps_p) / |dev d eps_p| = sqrt(2) eta_bar = sqrt(6) sin psi / sqrt(3 + sin^2 psi);
* simple shear under a fixed normal stress plateaus at Davis's shear stress and dilates at tan psi;
* a path beyond the apex returns to the apex (no deviator, mean stress c cot phi);
* a rigid rotation of a yielded state keeps its invariants; small strains are the Hencky law;
* gradients with respect to phi, psi, c and the strain path equal central differences inside the
  cone, on it, at the apex and on a path that starts to yield midway;
* bad parameters raise a one-line InputError naming the parameter.
"""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from cases import central_difference

import jaxmpm as jm
from jaxmpm.core.registry import MATERIALS
from jaxmpm.materials.drucker_prager import plane_strain_match

E, NU = 1.0e4, 0.3
LAM, MU = E * NU / ((1 + NU) * (1 - 2 * NU)), E / (2 * (1 + NU))
K = LAM + 2 * MU / 3


def material(phi=30.0, psi=0.0, c=0.0, young=E, **kw):
    return jm.DruckerPrager(E=young, nu=NU, friction_angle=phi, dilatancy_angle=psi, cohesion=c, **kw)


class _Points:
    """The particles a material's initial_state reads: N points in D dimensions."""

    def __init__(self, n, d):
        self.x = jnp.zeros((n, d))


def _step(m, state, dF):
    return m.update_state(jm.Increment(dF, dF, jnp.asarray(1.0, dF.dtype)), state)


@jax.jit
def strain_path(m, dFs):
    """(final state, per step: principal Kirchhoff stresses (N, 3), f (N,), Kirchhoff stress (N, D, D))
    for the increments dFs (K, N, D, D) from the initial state."""
    state = m.initial_state(_Points(dFs.shape[1], dFs.shape[-1]))

    def body(state, dF):
        state = _step(m, state, dF)
        t = m.principal_kirchhoff_stress(state)
        return state, (t, m.yield_function(t, state["plastic_strain"]), m.stress(None, state))

    return jax.lax.scan(body, state, dFs)


def repeated(dF, steps):
    dF = np.asarray(dF, dtype=float)
    return jnp.asarray(np.broadcast_to(dF, (steps, 1) + dF.shape).copy())


def path(*pieces):
    """Concatenated increments: pieces of (dF, steps)."""
    return jnp.concatenate([repeated(dF, n) for dF, n in pieces])


def invariants(t):
    """(sqrt(J2), p) of principal stresses (..., 3), tension positive."""
    p = jnp.mean(t, axis=-1)
    dev = t - p[..., None]
    return jnp.sqrt(0.5 * jnp.sum(dev * dev, axis=-1)), p


# --------------------------------------------------------------- the cone
@pytest.mark.parametrize("dF, phi", [(np.diag([0.999, 1.0]), 30.0), (np.diag([0.999, 0.9995]), 15.0),
                                     (np.diag([0.999, 1.0, 1.0]), 30.0), (np.diag([0.999, 0.9995, 1.0]), 15.0)],
                         ids=["uniaxial-2D", "biaxial-2D", "uniaxial-3D", "biaxial-3D"])
def test_return_lands_on_the_cone(dF, phi):
    """Compressive uniaxial and biaxial strain paths (plane strain and 3D) with psi = 10, c = 2
    (phi = 15 for biaxial strain, whose stress path is steeper): the stress leaves the elastic
    range, after which f = 0 to round-off at every step (|f| <= 1e-12 of the mean stress), and
    f <= 0 throughout; the plastic strain grows."""
    m = material(phi, 10.0, 2.0)
    state, (t, f, _) = strain_path(m, repeated(dF, 150))
    sqrt_j2, p = invariants(t[:, 0])
    scale = float(jnp.max(jnp.abs(p)))
    yielded = np.asarray(f[:, 0]) > -1e-12 * scale
    assert 0 < np.argmax(yielded) < 100 and yielded[np.argmax(yielded):].all()  # elastic, then on the cone
    np.testing.assert_array_less(np.asarray(f[:, 0]), 1e-12 * scale)
    eta, xi, _ = plane_strain_match(math.radians(phi), math.radians(10.0))
    on_cone = np.asarray(sqrt_j2 + eta * p - xi * 2.0)[yielded]  # f recomputed from the invariants
    np.testing.assert_allclose(on_cone, 0.0, atol=1e-12 * scale)
    assert float(state["plastic_strain"][0]) > 1e-3


def test_plane_strain_match_limits():
    """psi = phi is de Souza Neto et al. 2008 §6.4.6's plane-strain match: eta = 3 tan phi / sqrt(9 + 12 tan^2 phi),
    xi = 3 / sqrt(9 + 12 tan^2 phi); psi = 0 gives eta = sin phi, xi = cos phi, eta_bar = 0."""
    phi = math.radians(33.0)
    eta, xi, eta_bar = plane_strain_match(phi, phi)
    root = math.sqrt(9 + 12 * math.tan(phi) ** 2)
    np.testing.assert_allclose([eta, xi, eta_bar], [3 * math.tan(phi) / root, 3 / root, 3 * math.tan(phi) / root],
                               rtol=1e-14)
    np.testing.assert_allclose(plane_strain_match(phi, 0.0), [math.sin(phi), math.cos(phi), 0.0], rtol=1e-14, atol=0)


@pytest.mark.parametrize("psi", [0.0, 12.0, 30.0])
def test_plastic_flow_follows_the_dilatancy_angle(psi):
    """The return of trial strains outside the cone (not beyond the apex): the plastic increment
    d eps_p = eps* - eps is parallel to dev eps* in its deviatoric part and its trace is
    sqrt(2) eta_bar |dev d eps_p|, the closed form sqrt(6) sin psi / sqrt(3 + sin^2 psi) |dev|
    (0 for psi = 0: isochoric, Klar et al. 2016)."""
    m = material(30.0, psi, 1.0)
    rng = np.random.default_rng(3)
    direction = rng.normal(size=(8, 3))
    direction -= direction.mean(axis=1, keepdims=True)
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    eps_trial = jnp.asarray(-2e-3 + 1e-2 * rng.uniform(0.8, 1.2, size=(8, 1)) * direction)  # compressed, sheared
    plastic = m.initial_plastic_state(8, eps_trial.dtype)
    eps, new = m.return_mapping(eps_trial, plastic)
    d_eps = eps_trial - eps
    dev_trial = eps_trial - eps_trial.mean(axis=1, keepdims=True)
    dev_p = d_eps - d_eps.mean(axis=1, keepdims=True)
    dev_norm = jnp.linalg.norm(dev_p, axis=1)
    assert (dev_norm > 1e-3).all() and (jnp.linalg.norm(eps - eps.mean(axis=1, keepdims=True), axis=1) > 1e-4).all()
    cos = jnp.sum(dev_p * dev_trial, axis=1) / (dev_norm * jnp.linalg.norm(dev_trial, axis=1))
    np.testing.assert_allclose(cos, 1.0, atol=1e-13)
    s = math.sin(math.radians(psi))
    np.testing.assert_allclose(d_eps.sum(axis=1) / dev_norm, math.sqrt(6) * s / math.sqrt(3 + s * s), atol=1e-12)
    np.testing.assert_allclose(new["plastic_strain"], math.sqrt(2 / 3) * dev_norm, rtol=1e-13)
    np.testing.assert_allclose(new["volumetric_plastic_strain"], d_eps.sum(axis=1), rtol=1e-13, atol=1e-15)
    t = jm.materials.plastic.hencky_stress(m.E, m.nu, eps)
    np.testing.assert_allclose(m.yield_function(t), 0.0, atol=1e-12 * float(jnp.max(jnp.abs(t))))


# --------------------------------------------------------------- simple shear under a normal stress
SIGMA_N, GAMMA_RATE, SHEAR_STEPS, STIFF = 10.0, 5e-5, 400, 1e6  # elastic strains ~1e-5


@jax.jit
def confined_shear(m, rate=GAMMA_RATE):
    """Simple shear dF = [[1, d_gamma], [0, 1 + a]] (plane strain) with each step's a found by
    Newton's method (6 iterations, the derivative through the return mapping) so that the Kirchhoff
    normal stress tau_yy stays -SIGMA_N: first a compression to it (d_gamma = 0), then SHEAR_STEPS
    steps of d_gamma = ``rate``.  Returns per shear step (tau_xy, tau_yy, ln F_yy total)."""
    state = m.initial_state(_Points(1, 2))

    def increment(d_gamma, a):
        return jnp.asarray([[1.0, d_gamma], [0.0, 1.0 + a]])[None]

    def normal_stress(state, d_gamma, a):
        return m.stress(None, _step(m, state, increment(d_gamma, a)))[0, 1, 1] + SIGMA_N

    def body(carry, d_gamma):
        state, stretch = carry
        def newton(_, a):
            r, dr = jax.jvp(lambda a: normal_stress(state, d_gamma, a), (a,), (jnp.ones_like(a),))
            return a - r / dr

        a = jax.lax.fori_loop(0, 6, newton, jnp.asarray(0.0))
        state = _step(m, state, increment(d_gamma, a))
        stretch = stretch + jnp.log1p(a)
        tau = m.stress(None, state)[0]
        return (state, stretch), (tau[0, 1], tau[1, 1], stretch)

    gammas = jnp.concatenate([jnp.zeros(5), jnp.full(SHEAR_STEPS, rate)])
    return jax.lax.scan(body, (state, jnp.asarray(0.0)), gammas)[1]


@pytest.mark.parametrize("phi, psi, c", [(30.0, 0.0, 0.0), (30.0, 30.0, 0.0), (35.0, 10.0, 2.0)],
                         ids=["isochoric", "associated", "dilatant-cohesive"])
def test_confined_simple_shear_plateaus_at_davis_shear_stress(phi, psi, c):
    """Simple shear of one element (plane strain) under a fixed normal stress sigma_n.

    Derivation.  At the plateau the stress is steady, so the strain rate is all plastic:
    d_xx = d_zz = 0 (no stretch along the shear direction, plane strain), d_xy = gamma_dot / 2,
    d_yy free.  The plane-strain match makes Drucker-Prager Mohr-Coulomb in the x-y plane, flow
    included (dilation rate sin psi of the in-plane principal rates).  With Mohr's circle of
    radius r = (c cot phi + m) sin phi about the (compressive) centre m, and the zero-extension
    direction x, the flow rule puts x at the angle (pi/2 + psi)/2 from the major principal axis,
    so the stress on the horizontal plane is tau = r cos psi, sigma_n = m - r sin psi, that is
    (Davis 1968; Vermeer & de Borst 1984):

        tau = (sigma_n + c cot phi) sin phi cos psi / (1 - sin phi sin psi),
        d eps_yy / d gamma = tan psi   (the dilation, with d eps_xx = 0).

    psi = phi: tau = c + sigma_n tan phi (Coulomb on the horizontal plane); psi = 0:
    tau = c cos phi + sigma_n sin phi.  The stresses are Kirchhoff stresses (the yield function's),
    the normal stress held by Newton's method.  The incremental return at finite strain departs
    from the rate form by O(d_gamma) + O(elastic strain) (measured for phi = 30, psi = 0:
    -5.7e-5 at d_gamma = 2e-4, -1.9e-5 at 5e-5 with E = 1e6; -7e-4 with E = 1e4, elastic strains
    1e-3), so E = 1e6 and d_gamma = 5e-5: the plateau is asserted to 1e-4 relative."""
    tau_xy, tau_yy, ln_yy = confined_shear(material(phi, psi, c, young=STIFF))
    np.testing.assert_allclose(tau_yy, -SIGMA_N, rtol=1e-9)  # Newton to round-off: E * 1e-16 ~ 1e-10
    sp, cp, sq, cq = (f(math.radians(a)) for f, a in ((math.sin, phi), (math.cos, phi), (math.sin, psi),
                                                       (math.cos, psi)))
    davis = (SIGMA_N + c * cp / sp) * sp * cq / (1 - sp * sq)
    plateau = np.asarray(tau_xy[-50:])
    np.testing.assert_allclose(plateau, davis, rtol=1e-4)
    dilation = (ln_yy[-1] - ln_yy[-51]) / (50 * GAMMA_RATE)
    np.testing.assert_allclose(dilation, math.tan(math.radians(psi)), rtol=2e-3, atol=1e-6)


def test_friction_hardening_moves_the_plateau():
    """friction_hardening: phi(alpha) = phi + d_phi (1 - exp(-alpha/alpha_ref)); after a shear
    strain of 100 alpha_ref the isochoric plateau is c cos(phi + d_phi) + sigma_n sin(phi + d_phi)
    (softening from 35 to 30 degrees)."""
    m = material(35.0, 0.0, 0.0, young=STIFF, friction_hardening=-5.0, hardening_strain=2e-4)
    tau_xy, _, _ = confined_shear(m)
    np.testing.assert_allclose(tau_xy[-1], SIGMA_N * math.sin(math.radians(30.0)), rtol=1e-4)
    np.testing.assert_allclose(material(35.0).friction_angle_at(jnp.asarray(1.0)), math.radians(35.0), rtol=1e-15)


# --------------------------------------------------------------- the apex
@pytest.mark.parametrize("dF", [np.diag([1.001, 1.0]), np.diag([1.001, 1.0005]), np.eye(2) * 1.001],
                         ids=["uniaxial", "biaxial", "isotropic"])
def test_expansion_returns_to_the_apex(dF):
    """Extension of a cohesive sand (c = 3, phi = 30, psi = 10) past the apex: zero deviatoric
    stress and the mean stress c cot phi (tension), every step after the first."""
    m = material(30.0, 10.0, 3.0)
    state, (t, f, tau) = strain_path(m, repeated(dF, 40))
    sqrt_j2, p = invariants(t[-10:, 0])
    apex = 3.0 / math.tan(math.radians(30.0))
    np.testing.assert_allclose(p, apex, rtol=1e-12)
    np.testing.assert_allclose(sqrt_j2, 0.0, atol=1e-12 * apex)
    np.testing.assert_allclose(m.apex_pressure(), apex, rtol=1e-14)
    np.testing.assert_allclose(tau[-1, 0], apex * np.eye(2), atol=1e-12 * apex)
    assert float(state["volumetric_plastic_strain"][0]) > 0.02  # the expansion is plastic dilation


def test_cohesionless_expansion_is_stress_free():
    """c = 0, psi = 0 (Klar et al. 2016): any expansion goes to the tip, tau = 0."""
    _, (_, _, tau) = strain_path(material(30.0), repeated(np.diag([1.002, 0.9995]), 10))
    np.testing.assert_allclose(tau[-1], 0.0, atol=1e-12)


# --------------------------------------------------------------- objectivity and the elastic limit
def test_rigid_rotation_of_a_yielded_state_keeps_its_invariants():
    """After compression and shear onto the cone, dF = R (a 37 degree rotation): the principal
    stresses, f and the plastic variables are unchanged to 1e-12, and tau turns as R tau R^T."""
    m = material(30.0, 10.0, 1.0)
    c, s = math.cos(math.radians(37.0)), math.sin(math.radians(37.0))
    R = np.array([[c, -s], [s, c]])
    yield_path = path((np.diag([0.999, 0.999]), 10), (np.array([[1.0, 2e-3], [0.0, 1.0]]), 40))
    states, (t, f, tau) = strain_path(m, jnp.concatenate([yield_path, repeated(R, 1)]))
    assert float(f[-2, 0]) > -1e-12 * float(jnp.abs(t[-2]).max())  # on the cone before the rotation
    scale = float(jnp.abs(t[-2]).max())
    np.testing.assert_allclose(jnp.sort(t[-1]), jnp.sort(t[-2]), rtol=0, atol=1e-12 * scale)
    np.testing.assert_allclose(tau[-1, 0], R @ np.asarray(tau[-2, 0]) @ R.T, rtol=0, atol=1e-12 * scale)
    before, _ = strain_path(m, yield_path)
    for name in ("plastic_strain", "volumetric_plastic_strain"):
        np.testing.assert_allclose(states[name], before[name], rtol=1e-12)


def test_small_strains_inside_the_cone_are_the_hencky_law():
    """A confined path that stays inside the cone: tau = lambda tr(eps) I + 2 mu eps with
    eps = 1/2 ln(F F^T) (plane strain: eps_zz = 0), exactly; no plastic strain, no dissipation."""
    dF = np.array([[0.998, 3e-4], [1e-4, 0.9985]])
    state, (_, f, tau) = strain_path(material(30.0, 5.0, 0.5), repeated(dF, 5))
    F = np.linalg.matrix_power(dF, 5)
    w, V = np.linalg.eigh(F @ F.T)
    eps = V @ np.diag(0.5 * np.log(w)) @ V.T
    expected = LAM * np.trace(eps) * np.eye(2) + 2 * MU * eps
    np.testing.assert_allclose(tau[-1, 0], expected, rtol=0, atol=1e-12 * np.abs(expected).max())
    assert (np.asarray(f) < 0).all()
    for name in ("plastic_strain", "volumetric_plastic_strain", "plastic_dissipation"):
        assert float(jnp.abs(state[name]).max()) == 0.0


# --------------------------------------------------------------- gradients
REGIMES = ("elastic", "cone", "apex", "onset")  # the regime at the end of each path (_pieces)


@pytest.mark.parametrize("regime", REGIMES)
def test_gradients_equal_central_differences(regime):
    """d/d(phi, psi, c, s) of a scalar of the final Kirchhoff stress (s scales the strain path's
    increments), by reverse mode through the scan, against fourth-order central differences
    (step 1e-4 relative: the round-off of 36 steps of stresses ~200, ~4e-12, over a step of 1e-6
    would be 4e-6 of the derivative); "onset" yields at about step 21 of 36.  Inside the cone the parameter derivatives
    vanish, on the cone and at the apex they do not."""
    s0 = 1.0
    weights = jnp.asarray([[1.0, 0.3], [0.3, -0.7]])

    def loss(params, s):
        phi, psi, c = params
        m = jm.DruckerPrager(E=E, nu=NU, friction_angle=phi, dilatancy_angle=psi, cohesion=c)
        _, (_, f, tau) = strain_path(m, scaled_path(regime, s))
        return jnp.sum(weights * tau[-1, 0])

    params = jnp.asarray([30.0, 8.0, 1.5])
    g_params, g_s = jax.grad(loss, argnums=(0, 1))(params, jnp.asarray(s0))
    for i in range(3):
        e = np.zeros(3)
        e[i] = 1.0
        fd = central_difference(lambda h: loss(params + h * jnp.asarray(e), jnp.asarray(s0)), 0.0, 1e-4 * 30, order=4)
        np.testing.assert_allclose(g_params[i], fd, rtol=1e-6, atol=1e-9)
    fd_s = central_difference(lambda h: loss(params, jnp.asarray(s0) + h), 0.0, 1e-4, order=4)
    np.testing.assert_allclose(g_s, fd_s, rtol=1e-6)
    if regime == "elastic":
        np.testing.assert_allclose(g_params, 0.0, atol=0)
    else:
        assert abs(float(g_params[0])) > 1e-3 and abs(float(g_params[2])) > 1e-3
    if regime == "onset":
        _, (_, f, _) = strain_path(jm.DruckerPrager(E=E, nu=NU, friction_angle=30.0, dilatancy_angle=8.0,
                                                    cohesion=1.5), scaled_path(regime, jnp.asarray(s0)))
        first = int(np.argmax(np.asarray(f[:, 0]) > -1e-9))
        assert 12 < first < 30, first


def _pieces(regime, s):
    """The regime's path as (dF(s), steps) pieces, traceable in s; 36 steps each (one compilation)."""
    eye = jnp.eye(2)
    if regime == "elastic":
        return [(jnp.diag(jnp.stack([1 - 1e-4 * s, 1 - 5e-5 * s])), 18), (eye.at[0, 1].set(5e-6 * s), 18)]
    if regime == "cone":
        return [(0.999 * eye, 6), (eye.at[0, 1].set(2e-3 * s), 30)]
    if regime == "apex":
        return [(jnp.diag(jnp.stack([1 + 1e-3 * s, 1 + 2e-4 * s])), 36)]
    return [(0.999 * eye, 6), (eye.at[0, 1].set(6e-4 * s), 30)]


def scaled_path(regime, s):
    """The increments (K, 1, 2, 2) of the regime's path with scale s."""
    return jnp.concatenate([jnp.broadcast_to(dF, (n, 1) + dF.shape) for dF, n in _pieces(regime, s)])


# --------------------------------------------------------------- bad input
@pytest.mark.parametrize("kwargs, words", [
    (dict(friction_angle=90.0), "friction_angle = 90"),
    (dict(friction_angle=-1.0), "friction_angle = -1"),
    (dict(dilatancy_angle=-5.0), "dilatancy_angle = -5"),
    (dict(friction_angle=30.0, dilatancy_angle=40.0), "dilatancy_angle = 40 must be <= friction_angle = 30"),
    (dict(cohesion=-1.0), "cohesion = -1"),
    (dict(cohesion=float("nan")), "cohesion = nan"),
    (dict(friction_angle=30.0, friction_hardening=65.0), "friction_hardening = 65"),
    (dict(friction_angle=30.0, dilatancy_angle=20.0, friction_hardening=-15.0), "friction_hardening = -15"),
    (dict(hardening_strain=0.0), "hardening_strain = 0"),
])
def test_bad_parameters_raise_one_line_input_errors(kwargs, words):
    with pytest.raises(jm.InputError) as err:
        jm.DruckerPrager(E=1e5, **kwargs)
    message = str(err.value)
    assert words in message and message.startswith("DruckerPrager: ") and "\n" not in message
    assert ";" in message  # the fix follows


def test_registered_parameters():
    """set_params knows the friction angle and the cohesion (calibration), with their ranges."""
    assert {"friction_angle", "dilatancy_angle", "cohesion"} <= {p.name for p in
                                                                 MATERIALS["drucker_prager"].parameters}


@pytest.mark.parametrize("values, words", [
    (dict(dilatancy_angle=40.0), "set_params: dilatancy_angle = 40 must be <= friction_angle = 30"),
    (dict(friction_angle=5.0), "set_params: dilatancy_angle = 10 must be <= friction_angle = 5"),
    (dict(friction_angle=20.0, dilatancy_angle=25.0), "dilatancy_angle = 25 must be <= friction_angle = 20"),
])
def test_set_params_and_ensembles_keep_psi_below_phi(values, words):
    """set_params and jm.ensemble checked each value's own range only, so psi > phi passed, and with it a
    negative plastic dissipation (the audit of 2026-11-29: min -5.0 at psi = 60 > phi = 20 on one step)."""
    grid = jm.Grid((0.0, 0.0), (1.0, 1.0), (4, 4))
    sim = jm.Simulation(grid, "linear", material(30.0, 10.0, 1.0), "flip")
    with pytest.raises(jm.InputError, match=words):
        jm.set_params(sim, **values)
    jm.set_params(sim, dilatancy_angle=25.0, friction_angle=28.0)  # both at once, still psi <= phi
    state = sim.init(jm.fill(grid, jm.Box((0.25, 0.25), (0.75, 0.75))))
    with pytest.raises(jm.InputError, match="ensemble member 1: dilatancy_angle = 35 must be <= friction_angle = 30"):
        jm.ensemble(sim, state, 1e-4, 1, 1, params={"dilatancy_angle": [5.0, 35.0]})


def test_per_particle_angles_name_the_first_particle_that_breaks_the_condition():
    phi = np.array([30.0, 20.0, 30.0])
    with pytest.raises(jm.InputError, match=r"dilatancy_angle = 25 must be <= friction_angle = 20 \(first at index 1"):
        jm.DruckerPrager(E=1e5, friction_angle=phi, dilatancy_angle=25.0)


@pytest.mark.parametrize("softened", [False, True], ids=["phi=0", "phi softened to 0"])
def test_frictionless_cohesionless_sand_keeps_its_pressure(softened):
    """phi = 0, c = 0: the cone is a cylinder, with no apex.  The return keeps the mean stress and removes the
    deviator.  The apex test mu d_gamma > sqrt(J2) was a tie there, decided by the last bit: 22 of 1000 particles
    under compression and shear went to an apex that is not there, losing their pressure (the audit of
    2026-11-29).  Softened: friction_angle 30 with friction_hardening -30 reaches phi = 0 exactly (expm1 rounds
    to -1 beyond alpha/alpha_ref ~ 37)."""
    m = (material(30.0, 0.0, 0.0, friction_hardening=-30.0, hardening_strain=0.1) if softened
         else material(0.0, 0.0, 0.0))
    rng = np.random.default_rng(7)
    n = 1000
    shear = np.zeros((n, 2, 2))
    shear[:, 0, 1], shear[:, 1, 0] = rng.normal(scale=0.02, size=(2, n))
    dF = jnp.asarray(0.98 * np.eye(2) + shear)  # 2% compression and a random shear, in plane strain
    state = m.initial_state(_Points(n, 2))
    if softened:
        state = dict(state, plastic_strain=jnp.full((n,), 5.0))
        assert float(jnp.rad2deg(m.friction_angle_at(5.0))) == 0.0
    after = _step(m, state, dF)
    sqrt_j2, p = invariants(m.principal_kirchhoff_stress(after))
    trial_p = K * np.log(np.linalg.det(np.asarray(dF)))  # K tr(ln V): the trial's mean stress (F_zz = 1)
    np.testing.assert_allclose(p, trial_p, rtol=1e-12)  # every particle keeps its mean stress
    np.testing.assert_allclose(sqrt_j2, 0.0, atol=1e-9 * np.abs(trial_p).max())  # and loses its deviator
    np.testing.assert_allclose(after["volumetric_plastic_strain"], 0.0, atol=1e-15)  # psi = 0: isochoric flow
