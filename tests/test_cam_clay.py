"""Modified Cam-Clay (jaxmpm.materials.cam_clay) at a material point, float64: the return lands on
the ellipse, the flow is normal to it, closed forms of isotropic compression, of the oedometer's
limit and of the undrained critical state, objectivity, the elastic limit, gradients against
central differences, bad input."""

from types import SimpleNamespace

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.special import lambertw

import jaxmpm as jm
from jaxmpm.materials import Increment
from jaxmpm.materials.plastic import hencky_stress

E, NU, M, P0 = 1000.0, 0.3, 1.2, 10.0
K, MU = E / (3.0 * (1.0 - 2.0 * NU)), E / (2.0 * (1.0 + NU))


def clay(M=M, p0=P0, hardening=20.0, beta=0.0):
    return jm.CamClay(E=E, nu=NU, M=M, p0=p0, hardening=hardening, beta=beta)


@jax.jit
def drive(material, F_path):
    """The material point through the deformation gradients F_path (S, N, 3, 3), from F = I:
    per step the principal Kirchhoff stresses (S, N, 3) and the plastic state."""
    state = material.initial_state(SimpleNamespace(x=jnp.zeros(F_path.shape[1:2] + (3,))))

    def step(carry, F):
        state, F_old = carry
        state = material.update_state(Increment(dF=F @ jnp.linalg.inv(F_old), F=F, dt=jnp.asarray(1.0)), state)
        out = {k: state[k] for k in material.saved_state}
        return (state, F), (material.principal_kirchhoff_stress(state), out)

    F0 = jnp.broadcast_to(jnp.eye(3), F_path.shape[1:])
    (state, _), (tau, plastic) = jax.lax.scan(step, (state, F0), F_path)
    return state, tau, plastic


def stretch_path(stretches):
    """diag(stretches) per step: (S, N, 3) -> (S, N, 3, 3)."""
    return stretches[..., :, None] * jnp.broadcast_to(jnp.eye(3), stretches.shape + (3,))


def p_q(tau):
    mean = jnp.mean(tau, axis=-1)
    return -mean, jnp.sqrt(1.5) * jnp.linalg.norm(tau - mean[..., None], axis=-1)


def relative_f(material, tau, p0):
    """f / (M a)^2: the yield function in units of the ellipse's size."""
    return material.yield_function(tau, p0) / (material.M * 0.5 * (1.0 + material.beta) * p0) ** 2


def compression_paths(strain=0.08, steps=40):
    s = jnp.linspace(0.0, strain, steps + 1)[1:]
    one = jnp.ones_like(s)
    return jnp.stack([jnp.stack([jnp.exp(-s), one, one], -1),  # uniaxial strain
                      jnp.stack([jnp.exp(-s), jnp.exp(-s), one], -1),  # biaxial
                      jnp.stack([jnp.exp(-s)] * 3, -1)], 1)  # isotropic


@pytest.mark.parametrize("beta", [0.0, 0.3])
def test_the_return_lands_on_the_ellipse_on_compression_paths(beta):
    m = clay(beta=beta)
    _, tau, plastic = drive(m, stretch_path(compression_paths()))
    f = relative_f(m, tau, plastic["preconsolidation_pressure"])
    yielded = plastic["plastic_strain"] > 0
    assert bool(jnp.all(jnp.any(yielded, axis=0)))  # every path yields ...
    assert bool(jnp.all(jnp.sum(yielded, axis=0) >= 20))  # ... for most of its steps
    assert float(jnp.max(jnp.abs(jnp.where(yielded, f, 0.0)))) < 1e-12
    assert float(jnp.max(jnp.where(yielded, 0.0, f))) <= 0.0  # elastic steps inside
    # compaction hardens: p0 = p0_init exp(-xi ln J_p) grows, eps_v^p < 0
    assert bool(jnp.all(plastic["preconsolidation_pressure"][-1] > P0))
    np.testing.assert_allclose(plastic["preconsolidation_pressure"],
                               P0 * jnp.exp(-20.0 * plastic["volumetric_plastic_strain"]), rtol=1e-14)


def test_the_plastic_flow_is_normal_to_the_ellipse():
    """Associated flow: eps* - eps = d_gamma df/dtau at the returned stress, d_gamma > 0, for
    trial states all around the ellipse (compaction, dilation, tension with cohesion)."""
    m = clay(hardening=5.0, beta=0.2)
    rng = np.random.default_rng(3)
    eps_trial = jnp.asarray(rng.normal(size=(400, 3)) * 0.01)
    plastic = m.initial_plastic_state(400, jnp.float64)
    eps, new = jax.jit(lambda m, eps, plastic: m.return_mapping(eps, plastic))(m, eps_trial, plastic)
    tau = hencky_stress(m.E, m.nu, eps)
    p0 = new["preconsolidation_pressure"]
    yielded = m.yield_function(hencky_stress(m.E, m.nu, eps_trial), P0) > 0
    assert 100 < int(jnp.sum(yielded)) < 400
    d_eps_p, normal = (eps_trial - eps)[yielded], m.flow_direction(tau, p0)[yielded]
    cos = jnp.sum(d_eps_p * normal, -1) / (jnp.linalg.norm(d_eps_p, axis=-1) * jnp.linalg.norm(normal, axis=-1))
    assert float(jnp.max(1.0 - cos)) < 1e-13
    assert float(jnp.max(jnp.abs(relative_f(m, tau, p0)[yielded]))) < 1e-12
    np.testing.assert_allclose(jnp.sum(eps_trial - eps, -1), new["volumetric_plastic_strain"], atol=1e-15)
    np.testing.assert_array_equal(eps[~yielded], eps_trial[~yielded])  # elastic: untouched


@pytest.mark.parametrize("offset", [0.0, 1e-12, -1e-9, 1e-6])
def test_a_trial_above_the_top_returns_to_the_critical_state(offset):
    """A trial with p* at the ellipse's centre p_c = p0 / 2 (beta = 0, no hardening) and q* above
    the top returns along q alone: p = p*, q = M a = M p0 / 2.  There dv and p - p_c both vanish,
    so d_gamma comes from q (jaxmpm.materials.cam_clay, _plastic_multiplier); trials a relative
    1e-12..1e-6 beside the centre take the same branch or its neighbour."""
    m = clay(hardening=0.0)
    p_star, q_star = 0.5 * P0 * (1.0 + offset), 3.0 * M * P0
    eps_trial = jnp.asarray([[q_star / (3.0 * MU) - p_star / (3.0 * K), -q_star / (6.0 * MU) - p_star / (3.0 * K),
                              -q_star / (6.0 * MU) - p_star / (3.0 * K)]])
    eps, new = jax.jit(lambda m, e, pl: m.return_mapping(e, pl))(m, eps_trial, m.initial_plastic_state(1, jnp.float64))
    p, q = p_q(hencky_stress(m.E, m.nu, eps))
    p, q, a = float(p[0]), float(q[0]), 0.5 * P0
    np.testing.assert_allclose(q, M * np.sqrt(a * a - (p - a) ** 2), rtol=1e-13)  # on the ellipse
    d_gamma = (q_star / q - 1.0) / (6.0 * MU)  # q = q* / (1 + 6 mu d_gamma)
    np.testing.assert_allclose(p - a, (p_star - a) / (1.0 + 2.0 * K * M ** 2 * d_gamma), rtol=1e-12, atol=1e-14 * P0)
    dv = float(new["volumetric_plastic_strain"][0])
    np.testing.assert_allclose(dv, (p - p_star) / K, atol=1e-15)  # p = p* + K dv


@pytest.mark.parametrize("scale, xi, beta", [(0.1, 20.0, 0.0), (0.5, 5.0, 0.3)])
def test_large_increments_satisfy_the_return_equations(scale, xi, beta):
    """Random trial strains far outside the ellipse (a tenth and a half in one step), hardening and
    softening: the returned state satisfies the three backward-Euler equations that define it --
    on the ellipse of the updated p0, the flow normal to it, p0 = p0_n exp(-xi dv) -- measured
    against the trial's size, not the (possibly much shrunken) ellipse's."""
    m = clay(hardening=xi, beta=beta)
    rng = np.random.default_rng(5)
    eps_trial = jnp.asarray(rng.normal(size=(300, 3)) * scale)
    plastic = m.initial_plastic_state(300, jnp.float64)
    eps, new = jax.jit(lambda m, e, pl: m.return_mapping(e, pl))(m, eps_trial, plastic)
    tau, tau_trial = hencky_stress(m.E, m.nu, eps), hencky_stress(m.E, m.nu, eps_trial)
    p0 = new["preconsolidation_pressure"]
    size = jnp.max(jnp.abs(tau_trial), -1) + P0  # the trial's stress scale
    np.testing.assert_allclose(p0, P0 * jnp.exp(-xi * new["volumetric_plastic_strain"]), rtol=1e-14)
    p, q = p_q(tau)
    a = 0.5 * (1.0 + beta) * p0
    rho = jnp.sqrt((1.0 + 2.0 * beta) * q * q + M ** 2 * (p - 0.5 * (1.0 - beta) * p0) ** 2)
    assert float(jnp.max(jnp.abs(rho - M * a) / size)) < 1e-13
    d_eps_p, normal = eps_trial - eps, m.flow_direction(tau, p0)
    cos = jnp.sum(d_eps_p * normal, -1) / (jnp.linalg.norm(d_eps_p, axis=-1) * jnp.linalg.norm(normal, axis=-1))
    assert float(jnp.max(1.0 - cos)) < 1e-12


def test_isotropic_compression_follows_the_closed_form():
    """On the p axis the return is onto the right apex, p = p0 = p0_init exp(-xi eps_v^p), with
    eps_v^p = eps_v - eps_v^e = eps_v + p / K (coaxial Hencky strains add), so
    p = (K / xi) W(xi p0_init / K exp(-xi eps_v)), W Lambert's function, after each step whatever its
    size (three particles: steps of 0.4, 0.8 and 1.5 % strain per axis)."""
    xi = 20.0
    m = clay(hardening=xi)
    s = jnp.linspace(0.0, 1.0, 41)[1:, None] * jnp.asarray([0.15, 0.3, 0.6])[None, :]  # (40 steps, 3)
    _, tau, plastic = drive(m, stretch_path(jnp.stack([jnp.exp(-s)] * 3, -1)))
    p, q = p_q(tau)
    loading = np.asarray(plastic["plastic_strain"] > 0)
    exact = K / xi * np.real(lambertw(xi * P0 / K * np.exp(-xi * (-3.0 * np.asarray(s)))))
    assert np.all(np.sum(loading, axis=0) >= 35)
    np.testing.assert_allclose(p[loading], exact[loading], rtol=1e-13)
    np.testing.assert_allclose(q, 0.0, atol=1e-12)
    np.testing.assert_allclose(plastic["preconsolidation_pressure"][loading], p[loading], rtol=1e-13)


def test_oedometer_limit_of_the_perfectly_plastic_ellipse():
    """Uniaxial strain compression on a fixed ellipse (xi = 0) ends where the flow direction is the
    imposed strain rate (-1, 0, 0): df/dq / df/dp = 2/3, i.e. with X = p - p_c,
    q = 2 M^2 X / (3 (1 + 2 beta)) and X = a / sqrt(1 + 4 M^2 / (9 (1 + 2 beta))).  That point is a
    fixed point of the backward-Euler return, which reaches it to round-off."""
    beta = 0.3
    m = clay(hardening=0.0, beta=beta)
    s = jnp.linspace(0.0, 0.3, 301)[1:]
    one = jnp.ones_like(s)
    _, tau, _ = drive(m, stretch_path(jnp.stack([jnp.exp(-s), one, one], -1)[:, None, :]))
    p, q = p_q(tau[-1, 0])
    a, centre = 0.5 * (1.0 + beta) * P0, 0.5 * (1.0 - beta) * P0
    X = a / np.sqrt(1.0 + 4.0 * M ** 2 / (9.0 * (1.0 + 2.0 * beta)))
    np.testing.assert_allclose([float(p), float(q)], [centre + X, 2.0 * M ** 2 * X / (3.0 * (1.0 + 2.0 * beta))],
                               rtol=1e-12)


def test_undrained_shear_reaches_the_critical_state():
    """Isochoric stretching diag(e^g, e^(-g/2), e^(-g/2)) (J = 1, eps_v^p = -eps_v^e = p / K) ends
    at the ellipse's top, where the flow is isochoric: p = p_c = p0 / 2, q / p = M (beta = 0), with
    p0 = p0_init exp(-xi p / K): p = (K / xi) W(xi p0_init / (2 K))."""
    xi = 20.0
    m = clay(hardening=xi)
    g = jnp.linspace(0.0, 0.6, 301)[1:]
    path = jnp.stack([jnp.exp(g), jnp.exp(-0.5 * g), jnp.exp(-0.5 * g)], -1)[:, None, :]
    _, tau, _ = drive(m, stretch_path(path))
    p, q = p_q(tau[-1, 0])
    exact = K / xi * np.real(lambertw(xi * P0 / (2.0 * K)))
    np.testing.assert_allclose(float(p), exact, rtol=1e-12)
    np.testing.assert_allclose(float(q / p), M, rtol=1e-12)


def test_a_rigid_rotation_keeps_the_yielded_state():
    m = clay(hardening=5.0, beta=0.1)
    paths = compression_paths()
    state, tau, plastic = drive(m, stretch_path(paths))
    c, s = np.cos(0.7), np.sin(0.7)
    R = jnp.asarray([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ jnp.asarray([[1.0, 0.0, 0.0], [0.0, c, s],
                                                                                   [0.0, -s, c]])
    F = stretch_path(paths[-1])
    R = jnp.broadcast_to(R, F.shape)
    rotated = jax.jit(lambda m, inc, st: m.update_state(inc, st))(m, Increment(dF=R, F=R @ F, dt=jnp.asarray(1.0)),
                                                                  state)
    np.testing.assert_allclose(jnp.sort(m.principal_kirchhoff_stress(rotated), -1), jnp.sort(tau[-1], -1),
                               rtol=1e-12, atol=1e-12 * P0)
    for name in m.saved_state:
        np.testing.assert_allclose(rotated[name], plastic[name][-1], rtol=1e-12, atol=1e-15)
    tau_rotated = m.stress(None, rotated)
    np.testing.assert_allclose(tau_rotated, R @ m.stress(None, state) @ jnp.swapaxes(R, -1, -2), atol=1e-12 * P0)


def test_inside_the_ellipse_it_is_the_hencky_law():
    m = clay(p0=1e4, beta=0.0)
    rng = np.random.default_rng(5)
    stretches = jnp.exp(-0.004 + 0.002 * jnp.asarray(rng.uniform(-1.0, 1.0, size=(40, 3, 3))))
    state, tau, plastic = drive(m, stretch_path(stretches))
    hencky = hencky_stress(m.E, m.nu, jnp.log(stretches))
    # to the round-off of 40 updates F_e = U diag(sigma) V^T (1e-16 each) times the modulus
    np.testing.assert_allclose(jnp.sort(tau, -1), jnp.sort(hencky, -1), rtol=1e-13, atol=1e-14 * E)
    assert float(jnp.max(jnp.abs(plastic["plastic_strain"]))) == 0.0
    assert float(jnp.max(jnp.abs(state["plastic_dissipation"]))) == 0.0


def test_an_eager_update_runs_its_newton_loop_in_python_and_equals_the_compiled_one(monkeypatch):
    """Called outside any trace the return mapping's safeguarded Newton loop is a Python loop
    (jaxmpm.transfer.backend.while_loop): an eager ``lax.while_loop`` is compiled anew at every call
    (1.0 s an update at 50 points; about 0.2 s now).  Traced it stays one ``while_loop``; both give the
    same stresses and plastic state."""
    m = clay(hardening=20.0, beta=0.2)
    state = m.initial_state(SimpleNamespace(x=jnp.zeros((6, 3))))
    rng = np.random.default_rng(3)
    log_stretch = rng.uniform(-0.03, 0.01, size=(6, 3))
    log_stretch[0] = -1e-5  # a small isotropic compression stays inside the ellipse; the others yield
    F = stretch_path(jnp.exp(jnp.asarray(log_stretch)))
    inc = Increment(dF=F, F=F, dt=jnp.asarray(1.0))
    loops = []
    while_loop = jax.lax.while_loop
    monkeypatch.setattr(jax.lax, "while_loop", lambda *a, **k: loops.append(1) or while_loop(*a, **k))
    eager = m.update_state(inc, state)
    assert not loops
    compiled = jax.jit(lambda i, s: m.update_state(i, s))(inc, state)
    assert loops
    assert float(jnp.max(eager["plastic_strain"])) > 0.0 and float(jnp.min(eager["plastic_strain"])) == 0.0
    for key in eager:
        np.testing.assert_allclose(eager[key], compiled[key], rtol=1e-13, atol=1e-14, err_msg=key)


@pytest.mark.slow  # ~20 s: compiling the reverse pass through the nested Newton loops
def test_gradients_match_central_differences():
    """d/d(M, p0, strain amplitude) of the final stresses and plastic strain on a compression path
    with shear (8 steps), three particles: elastic throughout (amplitude 0.003), yielding first
    within the last step (0.0068; first yield at 0.00629), and yielded over 7 steps (0.05)."""
    steps, amplitudes = 8, jnp.asarray([0.003, 0.0068, 0.05])
    weights = jnp.asarray([1.0, -0.5, 0.3])

    def run(theta):
        M, p0, amplitude = theta[0], theta[1], theta[2:]
        m = jm.CamClay(E=E, nu=NU, M=M, p0=p0, hardening=10.0, beta=0.2)
        s = jnp.linspace(0.0, 1.0, steps + 1)[1:, None] * amplitude[None, :]
        return drive(m, stretch_path(jnp.stack([jnp.exp(-s), jnp.exp(-0.6 * s), jnp.exp(0.1 * s)], -1)))

    @jax.jit
    def loss(theta):
        _, tau, plastic = run(theta)
        return tau[-1] @ weights / P0 + 100.0 * plastic["plastic_strain"][-1]

    theta = jnp.concatenate([jnp.asarray([M, P0]), amplitudes])
    yielded_steps = jnp.sum(run(theta)[2]["plastic_strain"] > 0, axis=0)
    np.testing.assert_array_equal(yielded_steps, [0, 1, 7])
    jacobian = jax.jit(jax.jacrev(loss))(theta)  # (case, parameter): reverse mode, as calibration uses
    h = 1e-6 * theta
    fd = jnp.stack([(loss(theta.at[i].add(h[i])) - loss(theta.at[i].add(-h[i]))) / (2.0 * h[i])
                    for i in range(5)], -1)
    np.testing.assert_allclose(jacobian, fd, rtol=2e-7, atol=1e-9 * float(jnp.max(jnp.abs(fd))))
    assert float(jnp.max(jnp.abs(fd[1:, :2]))) > 0.0  # yielding cases depend on M and p0 ...
    assert float(jnp.max(jnp.abs(fd[0, :2]))) == 0.0  # ... the elastic one does not


@pytest.mark.parametrize("kwargs, name", [({"M": 0.0}, "M"), ({"p0": -1.0}, "p0"), ({"hardening": -0.5}, "hardening"),
                                          ({"beta": -0.1}, "beta"), ({"beta": 2.0}, "beta"),
                                          ({"nu": 0.5}, "nu"), ({"E": 0.0}, "E")])
def test_bad_parameters_raise_one_line_input_errors(kwargs, name):
    with pytest.raises(jm.InputError, match=rf"^CamClay: {name} = ") as info:
        jm.CamClay(**{"E": E, **kwargs})
    assert "\n" not in str(info.value)
