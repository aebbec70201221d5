"""NairnMPM's conventions (issue 28): each option at one step against its formula, and the preset.

NairnMPM 19.0 (J. A. Nairn, github.com/nairnj/nairn-mpm-fea, commit 7f47b022) differs from
jaxmpm's defaults in three rules, each an option here, checked on one step of a small 1D problem
(a fixed end, random velocities and a prestrain, so that every nodal force is non-zero) against
dense NumPy matrices (S from the stencil; m = S^T M 1; S+S = m^-1 S^T M S, 000 eqs. 1.9-1.10):

* ``constrained_force="reaction"`` (Boundary_Conditions/NodalVelBC, GRID_FORCES_CALL): on a
  constrained node v keeps p/m and the force becomes the reaction m (g - p/m)/dt, so FLIP's
  increment S a dt carries -v to the particles and FLIP's position update uses S(p/m)
  (MPM_Classes/MatPoint2D MoveParticle, ``vm = S(v+ - a dt)``);
* ``XPIC(boundary="unconstrained_start")`` (NairnMPM_Class/XPICExtrapolationTask, Nodes/
  MatVelocityField XPICSupport): v(m) = sum_{j<m} [Z (I - S+S)]^j (p/m), the start unconstrained
  and only the increments zeroed;
* ``position="PV_tilde"`` (MatPoint2D MoveParticle, XPIC branch): X += [S(v(m) + a dt) + dV/2] dt.

The whole-run agreement with NairnMPM's own output is tests/test_nairnmpm.py.
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from cases import central_difference, dense_weights, run_cli

import jaxmpm as jm
from jaxmpm.model.step import grid_phases, p2g

TOL = 1e-12
DT = 0.05
GRID = jm.Grid((-2.0,), (10.0,), (12,))  # h = 1, nodes at -2 ... 10
FIXED = jm.Fixed(where=lambda x: x[:, 0] <= 1e-9)  # the bar's end: x = 0, -1, -2


def particles(n=16, seed=0):
    rng = np.random.default_rng(seed)
    x = 0.25 + 7.5 * (np.arange(n) + rng.uniform(0.1, 0.9, n)) / n
    return jm.Particles(x=x[:, None], v=rng.normal(size=(n, 1)), volume=np.full(n, 0.5))


def simulation(scheme, **options):
    return jm.Simulation(grid=GRID, shape=jm.Linear(), material=jm.LinearElastic(E=3.0, nu=0.0, density=1.0),
                         scheme=scheme, boundary=FIXED, **options)


@functools.lru_cache(maxsize=None)
def initial_state():
    sim = simulation(jm.FLIP())
    state = sim.init(particles())
    rng = np.random.default_rng(1)
    F = 1.0 + 0.05 * rng.normal(size=(state.x.shape[0], 1, 1))  # a prestrain: non-zero internal forces
    return eqx.tree_at(lambda s: s.F, state, jnp.asarray(F))


class Dense:
    """The step's grid quantities as NumPy: S (N, n), M_p, m_i, p_i, f_i (from the library's P2G,
    tested elsewhere) and the mask Z of the constrained nodes."""

    def __init__(self, sim, state):
        fields = p2g(sim, state)
        self.S, _ = dense_weights(fields.transfer.stencil, GRID.num_nodes)
        self.M = np.asarray(state.mass)
        self.m = np.asarray(fields.mass)
        self.p = np.asarray(fields.momentum)[:, 0]
        self.f = np.asarray(fields.force)[:, 0]
        self.V = np.asarray(state.v)[:, 0]
        self.X = np.asarray(state.x)[:, 0]
        nodes = np.asarray(GRID.node_coordinates())[:, 0]
        self.free = (nodes > 1e-9) & (self.m > 0)
        active = self.m > 0
        self.u = np.where(active, self.p / np.where(active, self.m, 1.0), 0.0)  # p/m, before the conditions
        self.a = np.where(active, self.f / np.where(active, self.m, 1.0), 0.0)
        self.SpS = np.where(active[:, None], (self.S.T * self.M) @ self.S / np.where(active, self.m, 1.0)[:, None], 0.0)

    def Z(self, w):
        return np.where(self.free, w, 0.0)


def step(sim, state):
    new = sim.step(state, DT)
    return np.asarray(new.v)[:, 0], np.asarray(new.x)[:, 0]


def close(actual, expected):
    scale = max(np.max(np.abs(expected)), 1e-300)
    assert np.max(np.abs(actual - expected)) <= TOL * scale, np.max(np.abs(actual - expected)) / scale


# ------------------------------------------------------------------------------ the grid solve
def test_reaction_grid_solve_keeps_p_over_m_and_takes_the_reaction_force():
    """constrained_force="reaction": v = p/m everywhere; a = f/m on free nodes, (0 - p/m)/dt on the
    fixed ones; v + a dt equal to the default's v_tilde (the conditions hold on it)."""
    state = initial_state()
    sim = simulation(jm.FLIP(), constrained_force="reaction")
    d = Dense(sim, state)
    solution = grid_phases(sim, p2g(sim, state), DT, sim.constraint(state.x.dtype))
    plain = simulation(jm.FLIP())
    default = grid_phases(plain, p2g(plain, state), DT, plain.constraint(state.x.dtype))
    fixed = (~d.free) & (d.m > 0)
    assert fixed.sum() == 1  # x = 0 carries mass (linear shapes, particles from x = 0.25)
    close(np.asarray(solution.v)[:, 0], d.u)
    close(np.asarray(solution.a)[:, 0], np.where(fixed, -d.u / DT, d.a))
    np.testing.assert_array_equal(np.asarray(solution.v_tilde), np.asarray(default.v_tilde))
    np.testing.assert_array_equal(np.asarray(solution.a)[d.free], np.asarray(default.a)[d.free])  # bitwise


def test_flip_with_the_reaction_against_nairnmpm_rule():
    """FLIP: V += S a dt with the reaction, X += [S(p/m) + dV/2] dt (NairnMPM's MoveParticle,
    vm = S(v+ - a dt)); the default zeroes v and a on the fixed nodes instead."""
    state = initial_state()
    d = Dense(simulation(jm.FLIP()), state)
    a = np.where(d.free, d.a, np.where(d.m > 0, -d.u / DT, 0.0))
    V_new = d.V + d.S @ a * DT
    X_new = d.X + (d.S @ d.u + 0.5 * (V_new - d.V)) * DT
    for sim in (simulation(jm.FLIP(), constrained_force="reaction"), simulation(jm.FLIP(), conventions="nairnmpm")):
        V, X = step(sim, state)
        close(V, V_new)
        close(X, X_new)
    V0, X0 = step(simulation(jm.FLIP()), state)  # the default: a = 0, v = 0 on the fixed nodes
    close(V0, d.V + d.S @ d.Z(d.a) * DT)
    assert np.max(np.abs(V0 - V_new)) > 1e-3 * np.max(np.abs(V_new))  # the conventions differ here


def nairnmpm_series(d, order):
    """sum_{j<m} [Z (I - S+S)]^j u, NairnMPM's XPIC loop written as it runs: v* = u, Dv = u;
    m - 1 times Dv <- Z (Dv - S+S Dv), v* += Dv."""
    total, dv = d.u.copy(), d.u.copy()
    for _ in range(order - 1):
        dv = d.Z(dv - d.SpS @ dv)
        total = total + dv
    return total


@pytest.mark.parametrize("order", [2, 5])
@pytest.mark.parametrize("force", ["zero", "reaction"])
def test_xpic_unconstrained_start_against_nairnmpm_loop(order, force):
    """XPIC(m, boundary="unconstrained_start", position="PV_tilde"): V = S(v(m) + a dt) and
    X += [S(v(m) + a dt) + dV/2] dt with NairnMPM's v(m), whose fixed nodes meet the condition in
    v(m) + a dt -- under either constrained force."""
    state = initial_state()
    scheme = jm.XPIC(order, boundary="unconstrained_start", position="PV_tilde")
    sim = simulation(scheme, constrained_force=force)
    d = Dense(sim, state)
    vm_a = np.where(d.free, nairnmpm_series(d, order) + d.a * DT, 0.0)  # v(m) + a dt, 0 on the fixed nodes
    V_new = d.S @ vm_a
    V, X = step(sim, state)
    close(V, V_new)
    close(X, d.X + (d.S @ vm_a + 0.5 * (V_new - d.V)) * DT)


@pytest.mark.slow
def test_xpic_series_differs_from_the_default_only_through_the_fixed_nodes():
    """Without constrained nodes carrying velocity the two starts agree: zero the particles'
    velocities near the end, then v(m) is the same series (to round-off)."""
    state = initial_state()
    x = np.asarray(state.x)[:, 0]
    quiet = eqx.tree_at(lambda s: s.v, state, jnp.where(jnp.asarray(x)[:, None] < 1.5, 0.0, state.v))
    a = step(simulation(jm.XPIC(3, boundary="unconstrained_start")), quiet)
    b = step(simulation(jm.XPIC(3)), quiet)
    close(a[0], b[0])
    c = step(simulation(jm.XPIC(3, boundary="unconstrained_start")), state)
    d = step(simulation(jm.XPIC(3)), state)
    assert np.max(np.abs(c[0] - d[0])) > 1e-4 * np.max(np.abs(d[0]))


def test_pic_position_pv_tilde():
    """PIC(position="PV_tilde"): X += [S v_tilde + dV/2] dt (NairnMPM's XPIC(1)); V = S v_tilde as
    in the default."""
    state = initial_state()
    sim = simulation(jm.PIC(position="PV_tilde"))
    d = Dense(sim, state)
    v_tilde = d.Z(d.u + d.a * DT)
    V_new = d.S @ v_tilde
    V, X = step(sim, state)
    close(V, V_new)
    close(X, d.X + (d.S @ v_tilde + 0.5 * (V_new - d.V)) * DT)


def test_xpic_reaction_with_the_default_series_keeps_the_conditions():
    """constrained_force="reaction" with XPIC's default series ("iterates"): v(m) keeps p/m on the
    fixed nodes, so v(m) + a dt = 0 there and the velocity update equals the default's; the
    position update's S v ("Sv") now sees p/m on them: X moves by S (p/m on the fixed nodes) dt more."""
    state = initial_state()
    sim = simulation(jm.XPIC(3), constrained_force="reaction")
    d = Dense(sim, state)
    a = step(sim, state)
    b = step(simulation(jm.XPIC(3)), state)
    close(a[0], b[0])
    close(a[1] - b[1], d.S @ np.where(d.free, 0.0, d.u) * DT)


ALPHA_G, ALPHA_P = 0.3, 0.2


def test_xpic_damping_with_the_updated_velocity():
    """XPIC(2, damping_velocity="updated") in NairnMPM's form: A_damp = alpha_g S(v(m) + a dt) +
    alpha_p V^n, V = S(v(m) + a dt) - A_damp dt, X += [S(v(m) + a dt) + dV/2] dt."""
    state = initial_state()
    scheme = jm.XPIC(2, boundary="unconstrained_start", position="PV_tilde", damping_velocity="updated")
    sim = simulation(scheme, damping=jm.Damping(grid=ALPHA_G, particle=ALPHA_P))
    d = Dense(sim, state)
    Svm = d.S @ np.where(d.free, nairnmpm_series(d, 2) + d.a * DT, 0.0)
    V_new = Svm - (ALPHA_G * Svm + ALPHA_P * d.V) * DT
    V, X = step(sim, state)
    close(V, V_new)
    close(X, d.X + (Svm + 0.5 * (V_new - d.V)) * DT)
    preset = simulation(jm.XPIC(2), damping=jm.Damping(grid=ALPHA_G, particle=ALPHA_P), conventions="nairnmpm")
    close(step(preset, state)[0], V_new)


def test_fmpm_damping_with_the_updated_velocity():
    """FMPM(2, damping_velocity="updated"): A_damp = alpha_g S v+ + alpha_p V^n with v+ the
    full-mass velocity (003 eq. 2.13, constrained iterates); the default damps with S v."""
    state = initial_state()
    sim = simulation(jm.FMPM(2, damping_velocity="updated"), damping=jm.Damping(grid=ALPHA_G, particle=ALPHA_P))
    d = Dense(sim, state)
    v_tilde = d.Z(d.u + d.a * DT)
    v_plus = v_tilde + (v_tilde - d.Z(d.SpS @ v_tilde))  # sum_{j<2} (I - Z S+S)^j Z v_tilde
    Sv_plus = d.S @ v_plus
    V_new = Sv_plus - (ALPHA_G * Sv_plus + ALPHA_P * d.V) * DT
    V, X = step(sim, state)
    close(V, V_new)
    close(X, d.X + 0.5 * (V_new + d.V) * DT)
    default = step(simulation(jm.FMPM(2), damping=jm.Damping(grid=ALPHA_G, particle=ALPHA_P)), state)[0]
    close(default, Sv_plus - (ALPHA_G * (d.S @ d.Z(d.u)) + ALPHA_P * d.V) * DT)


# -------------------------------------------------------------------------------------- preset
def test_preset_selects_each_option():
    cases = [
        (jm.FLIP(), "Sv", "iterates"),
        (jm.PIC(), "PV_tilde", "iterates"),
        (jm.XPIC(2), "PV_tilde", "unconstrained_start"),
        (jm.XPIC(5, beta=0.2), "PV_tilde", "unconstrained_start"),
        (jm.XPIC(0), "Sv", "iterates"),
        (jm.FLIP(beta=0.9), "PV_tilde", "iterates"),
    ]
    for scheme, position, boundary in cases:
        sim = simulation(scheme, conventions="nairnmpm")
        assert (sim.scheme.position, sim.scheme.boundary) == (position, boundary), scheme
        assert sim.constrained_force == "reaction" and sim.conventions == "nairnmpm"
        assert type(sim.scheme) is type(scheme)
        default = simulation(scheme)
        assert default.scheme is scheme and default.constrained_force == "zero"
    for scheme, damping_velocity in [(jm.FLIP(), "lumped"), (jm.PIC(), "updated"), (jm.XPIC(3), "updated"),
                                     (jm.FMPM(2), "updated"), (jm.FMPM(0), "lumped")]:
        assert simulation(scheme, conventions="nairnmpm").scheme.damping_velocity == damping_velocity, scheme
    fmpm = jm.FMPM(0)
    assert simulation(fmpm, conventions="nairnmpm").scheme is fmpm  # FMPM(0) is FLIP
    explicit = simulation(jm.FLIP(), conventions="nairnmpm", constrained_force="zero")
    assert explicit.constrained_force == "zero"
    later = simulation(jm.XPIC(2)).with_conventions("nairnmpm")
    assert later.scheme.boundary == "unconstrained_start" and later.constrained_force == "reaction"


def test_preset_refuses_options_it_would_override():
    with pytest.raises(jm.InputError, match="position = 'V'.*conventions='nairnmpm'"):
        simulation(jm.XPIC(2, position="V"), conventions="nairnmpm")
    with pytest.raises(jm.InputError, match="boundary = 'result'.*conventions='nairnmpm'"):
        simulation(jm.XPIC(2, boundary="result"), conventions="nairnmpm")
    with pytest.raises(jm.InputError, match="damping_velocity = 'fast'"):
        jm.FMPM(2, damping_velocity="fast")
    with pytest.raises(jm.InputError, match="conventions = 'nairn'"):
        simulation(jm.FLIP(), conventions="nairn")
    with pytest.raises(jm.InputError, match="constrained_force = 'fixed'"):
        simulation(jm.FLIP(), constrained_force="fixed")
    with pytest.raises(jm.InputError, match="unconstrained_start.*FMPM|FMPM: boundary = 'unconstrained_start'"):
        jm.FMPM(2, boundary="unconstrained_start")
    # one-sided walls, inclined planes and mirrors are not NairnMPM's: the series says so
    sim = jm.Simulation(grid=GRID, shape=jm.Linear(), material=jm.LinearElastic(E=3.0), boundary=jm.Wall("x-"),
                        scheme=jm.XPIC(2, boundary="unconstrained_start"))
    with pytest.raises(jm.InputError, match="unconstrained_start.*grid-axis"):
        sim.step(sim.init(particles()), DT)


def test_cli_conventions(tmp_path, capsys):
    """`jaxmpm run bar --conventions nairnmpm` runs NairnMPM's rules; the stored command resumes them."""
    import h5py

    out = tmp_path / "bar.h5"
    status = run_cli(["run", "bar", "--scheme", "xpic:2", "--conventions", "nairnmpm", "--t-end", "2",
                      "--frames", "2", "--out", str(out), "--no-progress"])
    assert status == 0
    with h5py.File(out) as f:
        assert '"conventions": "nairnmpm"' in f.attrs["command"]
        assert (f.attrs["conventions"], f.attrs["constrained force"]) == ("nairnmpm", "reaction")
        assert (f.attrs["position"], f.attrs["series boundary"]) == ("PV_tilde", "unconstrained_start")
    from jaxmpm.scenes.command import setup_from_options

    setup = setup_from_options({"scene": "bar", "scheme": "xpic:2", "conventions": "nairnmpm"})
    assert setup.sim.conventions == "nairnmpm" and setup.sim.scheme.position == "PV_tilde"
    assert run_cli(["run", "bar", "--conventions", "other", "--out", str(tmp_path / "x.h5")]) == 2


@pytest.mark.slow
def test_gradient_under_the_preset_against_central_differences():
    """d/d(alpha_g, E) of a loss after 6 steps of XPIC(3) in NairnMPM's conventions (the reaction,
    the unconstrained series start, PV_tilde and the updated damping velocity all on the path)
    equals central differences in float64."""
    state = initial_state()
    base = simulation(jm.XPIC(3), damping=jm.Damping(grid=ALPHA_G, particle=ALPHA_P), conventions="nairnmpm")

    def loss(alpha_g, E):
        sim = jm.set_params(base, alpha_g=alpha_g, E=E)
        s = jax.lax.fori_loop(0, 6, lambda _, s: sim.step(s, DT), state)
        return jnp.sum(s.mass[:, None] * s.v**2) + jnp.sum((s.x - state.x) ** 2)

    grad = jax.jit(jax.grad(loss, argnums=(0, 1)))(ALPHA_G, 3.0)
    f = jax.jit(loss)
    fd_alpha = central_difference(lambda a: f(a, 3.0), ALPHA_G, 1e-3, order=4)
    fd_E = central_difference(lambda e: f(ALPHA_G, e), 3.0, 1e-3, order=4)
    np.testing.assert_allclose(float(grad[0]), float(fd_alpha), rtol=1e-8)
    np.testing.assert_allclose(float(grad[1]), float(fd_E), rtol=1e-8)
    assert abs(float(grad[0])) > 1e-3 and abs(float(grad[1])) > 1e-3  # the parameters act


# ------------------------------------------------------------------------- contact (NairnMPM's rules)
def contact_pair(**contact):
    """Two 2D blocks meeting at x = 0.5 (material 0 left), approaching at +-0.2, with a prestrain
    (so J != 1 and the nodal forces act); quadratic B-splines, h = 0.1."""
    grid = jm.Grid((0.0, 0.0), (1.0, 1.0), (10, 10))
    a = jm.fill(grid, jm.Box((0.2, 0.3), (0.5, 0.7)), ppc=2, velocity=(0.2, 0.0))
    b = jm.fill(grid, jm.Box((0.5, 0.3), (0.8, 0.7)), ppc=2, velocity=(-0.2, 0.05))
    particles = jm.Particles(x=np.concatenate([a.x, b.x]), v=np.concatenate([a.v, b.v]),
                             volume=np.concatenate([a.volume, b.volume]), ppc=2)
    sim = jm.Simulation(grid=grid, shape=jm.QuadraticBSpline(), material=jm.LinearElastic(E=50.0, nu=0.3),
                        scheme=jm.FLIP(), terms=(jm.Contact(**contact),))
    ids = np.concatenate([np.zeros(a.num), np.ones(b.num)])
    state = sim.init(particles, fields={"material": jnp.asarray(ids)})
    rng = np.random.default_rng(3)
    F = np.eye(2) + 0.03 * rng.normal(size=(state.x.shape[0], 2, 2))
    return sim, eqx.tree_at(lambda s: s.F, state, jnp.asarray(F)), ids


def test_contact_volume_gradient_is_deformed_volume():
    """Contact(gradient="volume"): g^a = sum_p J_p V0_p G_pi (NairnMPM's AddVolumeGradient), by
    dense G; the default "mass" is sum_p M_p G_pi."""
    for gradient, weight in (("volume", lambda s: np.linalg.det(np.asarray(s.F)) * np.asarray(s.volume0)),
                             ("mass", lambda s: np.asarray(s.mass))):
        sim, state, ids = contact_pair(gradient=gradient, normal="average")
        fields = p2g(sim, state)
        _, G = dense_weights(sim.shape.stencil(sim.grid, state.x), sim.grid.num_nodes)
        w = weight(state)
        expected = np.concatenate([np.einsum("p,pid->id", w * (ids == a), G) for a in (0, 1)])
        close(np.asarray(fields.values["mass_gradient"]), expected)
    preset = jm.Simulation(grid=sim.grid, shape=sim.shape, material=sim.material, scheme=jm.FLIP(),
                           terms=(jm.Contact(normal="average"),), conventions="nairnmpm")
    assert preset.term(jm.Contact).gradient == "volume" and preset.term(jm.Contact).separation_update == "extrapolated"
    from jaxmpm.io.hdf5 import run_attributes

    attrs = run_attributes(preset, 0.01, "pair", {}, 2)
    assert (attrs["contact gradient"], attrs["contact separation update"]) == ("volume", "extrapolated")
    assert attrs["contact series"] == "incremental" and attrs["contact law"] == "frictionless"


def test_contact_extrapolated_separation_in_the_second_application():
    """Contact(separation=s, separation_update="extrapolated"): on p + f dt the nodes in contact are
    those with gap + dt (Dp+.n - dt Df.n/2)/m_red < 0 (NairnMPM's CoulombFriction), the gap
    (x^1 - x^0).n - s h of the step's start; on p the gap alone.  Checked against the criterion
    computed by hand from the nodal fields, and the default ("start") against gap <= 0."""
    dt = 0.01
    for update in ("extrapolated", "start"):
        sim, state, _ = contact_pair(separation=1.2, separation_update=update, normal=(1.0, 0.0))
        contact = sim.term(jm.Contact)
        fields = p2g(sim, state)
        n = sim.grid.num_nodes
        m = np.asarray(fields.mass)
        m0, m1 = m[:n], m[n:]
        q = np.asarray(fields.values["mass_moment"])
        with np.errstate(invalid="ignore", divide="ignore"):
            x0, x1 = q[:n] / m0[:, None], q[n:] / m1[:, None]
        both = (m0 > 0) & (m1 > 0)
        gap = np.where(both, x1[:, 0] - x0[:, 0], 0.0) - 1.2 * sim.grid.h
        p, f = np.asarray(fields.momentum), np.asarray(fields.force)
        p_plus = p + f * dt
        mt = np.where(both, m0 + m1, 1.0)
        stick_p = (m0[:, None] * p_plus[n:] - m1[:, None] * p_plus[:n]) / mt[:, None]
        stick_f = (m0[:, None] * f[n:] - m1[:, None] * f[:n]) / mt[:, None]
        m_red = np.where(both, m0 * m1 / mt, 1.0)
        moved = gap + dt * (stick_p[:, 0] - 0.5 * dt * stick_f[:, 0]) / m_red
        normal = contact.contact_normal(fields.values["mass_gradient"])
        first = np.asarray(contact.touching(fields, jnp.asarray(m0), jnp.asarray(m1), normal, sim.grid.h))
        second_args = (jnp.asarray(p_plus), fields.force, dt) if update == "extrapolated" else None
        second = np.asarray(contact.touching(fields, jnp.asarray(m0), jnp.asarray(m1), normal, sim.grid.h,
                                             second_args))
        np.testing.assert_array_equal(first[both], gap[both] <= 0)
        np.testing.assert_array_equal(second[both], (moved < 0)[both] if update == "extrapolated" else gap[both] <= 0)
        if update == "extrapolated":
            assert np.any(((moved < 0) != (gap <= 0)) & both)  # the extrapolation changes some node here
        # and the step uses it: its exchange equals the law with that criterion on p + f dt
        plus, _ = contact.exchange_updated_momentum(sim, fields, jnp.asarray(p_plus), dt)
        expected, _ = contact.apply(jnp.asarray(p_plus), fields.mass, normal, jnp.asarray(second))
        close(np.asarray(plus), np.asarray(expected))


# ---------------------------------------------- contact on the XPIC/FMPM series' increments (NairnMPM's rule)
def nairnmpm_law(stick, both, normal, law, mu=0.0):
    """jaxmpm's contact law (003 eq. 3.9) on a stick change, NumPy: material 0's Dp on the nodes ``both``."""
    if law == "stick":
        return np.where(both[:, None], stick, 0.0)
    dpn = stick @ normal
    approach = both & (dpn < 0)
    normal_part = dpn[:, None] * normal[None]
    if law == "frictionless":
        return np.where(approach[:, None], normal_part, 0.0)
    tangential = stick - normal_part
    t_norm = np.linalg.norm(tangential, axis=1)
    limit = mu * np.abs(dpn)
    with np.errstate(invalid="ignore", divide="ignore"):
        sliding = normal_part + limit[:, None] * tangential / t_norm[:, None]
    return np.where(approach[:, None], np.where((t_norm > limit)[:, None], sliding, stick), 0.0)


def nairnmpm_contact_step(sim, state, scheme, law, mu=0.0, separation=None, dt=0.01):
    """One USL step of FMPM(2) or XPIC(2) with NairnMPM's incremental contact, written with dense
    S (N, 2n) and S+S (2n, 2n) over the two materials' stacked fields (NairnMPM_Class/XPICExtrapolationTask,
    Nodes/CrackVelocityFieldMulti MaterialXPICIncrementOnCVF): the lumped law on p and on p' + f dt; the
    series D_1 = v~ (FMPM) or v (XPIC), R = (I - S+S) D_1 and on every contact node A = the stick change of
    p' + f dt plus that of R, L = law(A), D_2 = R + (L - N)/m^a (N the second call's change); v+ = D_1 + D_2,
    V = S v+, X += (V + V^n) dt/2 (FMPM); v* = v~ + D_2, V = S v*, X += (S v* + dV/2) dt (XPIC,
    PV_tilde).  The normal is (1, 0); the separation criterion, the gap moved over the step by A (NairnMPM's
    GetFrictionalDeltaMomentum with the second call's force stick change; at s = 1 both the move by A and
    the force term change the result here, by 0.1 and 0.07 of the velocities)."""
    fields = p2g(sim, state)
    n = sim.grid.num_nodes
    S, _ = dense_weights(sim.stencil(state), 2 * n)  # each particle on its material's copy of the nodes
    M, X, V = np.asarray(state.mass), np.asarray(state.x), np.asarray(state.v)
    m, p, f = np.asarray(fields.mass), np.asarray(fields.momentum), np.asarray(fields.force)
    m0, m1 = m[:n], m[n:]
    both = (m0 > 0) & (m1 > 0)
    active = m > 0
    safe = np.where(active, m, 1.0)
    SpS = np.where(active[:, None], (S.T * M) @ S / safe[:, None], 0.0)
    normal = np.array([1.0, 0.0])
    mt = np.where(both, m0 + m1, 1.0)

    def stick(q):
        return np.where(both[:, None], (m0[:, None] * q[n:] - m1[:, None] * q[:n]) / mt[:, None], 0.0)

    def per_mass(dp):
        return np.concatenate([np.where((m0 > 0)[:, None], dp / np.where(m0 > 0, m0, 1.0)[:, None], 0.0),
                               -np.where((m1 > 0)[:, None], dp / np.where(m1 > 0, m1, 1.0)[:, None], 0.0)])

    touch_first = touch_second = touch_series = None
    if separation is not None:
        q = (S.T * M) @ X
        x_mean = q / safe[:, None]
        gap = (x_mean[n:] - x_mean[:n]) @ normal - separation * sim.grid.h
        m_red = np.where(both, m0 * m1 / mt, 1.0)
        stick_f = stick(f)
        touch_first = gap <= 0

        def touch_series(acc):
            return gap + dt * ((acc - 0.5 * dt * stick_f) @ normal) / m_red < 0

    def lumped_law(stick_change, touching):
        return nairnmpm_law(stick_change, both if touching is None else both & touching, normal, law, mu)

    dp = lumped_law(stick(p), touch_first)
    p1 = p + np.concatenate([dp, -dp])
    up = p1 + f * dt
    if separation is not None:
        touch_second = touch_series(stick(up))
    dp_plus = lumped_law(stick(up), touch_second)
    p_plus = up + np.concatenate([dp_plus, -dp_plus])
    v, v_tilde = p1 / safe[:, None], p_plus / safe[:, None]
    d1 = v_tilde if scheme == "fmpm" else v
    r = d1 - SpS @ d1
    acc = stick(up) + stick(m[:, None] * r)
    L = lumped_law(acc, None if separation is None else touch_series(acc))
    d2 = r + per_mass(L - dp_plus)
    if scheme == "fmpm":
        V_new = S @ (d1 + d2)
        return V_new, X + 0.5 * (V_new + V) * dt, (dp, dp_plus, L)
    Sv_star = S @ (v_tilde + d2)
    return Sv_star, X + (Sv_star + 0.5 * (Sv_star - V)) * dt, (dp, dp_plus, L)


def incremental_sim(pair_sim, scheme, update="USL", **contact):
    return jm.Simulation(grid=pair_sim.grid, shape=pair_sim.shape, material=pair_sim.material, scheme=scheme,
                         update=update, terms=(jm.Contact(normal=(1.0, 0.0), series="incremental", **contact),))


@pytest.mark.parametrize("scheme, law, options", [
    ("fmpm", "stick", {}), ("fmpm", "frictionless", {}), ("xpic", "stick", {}), ("xpic", "frictionless", {}),
    ("fmpm", "coulomb", {"friction": 0.3}),
    ("fmpm", "frictionless", {"separation": 1.0, "separation_update": "extrapolated"}),
])
def test_incremental_contact_series_against_nairnmpm_loop(scheme, law, options):
    """Contact(series="incremental"): one step of FMPM(2) and XPIC(2, position="PV_tilde") on the two
    blocks equals NairnMPM's loop written out densely (:func:`nairnmpm_contact_step`); the law acts in
    the increment (L differs from the second call's change on some node), the result differs from
    the default series="separate" (frictionless), and conventions="nairnmpm" selects it (XPIC, stick)."""
    pair, state, _ = contact_pair()
    dt = 0.01
    make = jm.FMPM(2) if scheme == "fmpm" else jm.XPIC(2, position="PV_tilde")
    sim = incremental_sim(pair, make, law=law, **options)
    V_ref, X_ref, (_, dp_plus, L) = nairnmpm_contact_step(sim, state, scheme, law, options.get("friction", 0.0),
                                                          options.get("separation"), dt)
    assert np.max(np.abs(L - dp_plus)) > 1e-3 * np.max(np.abs(dp_plus))  # the increment's law acts
    new = sim.step(state, dt)
    close(np.asarray(new.v), V_ref)
    close(np.asarray(new.x) - np.asarray(state.x), X_ref - np.asarray(state.x))
    if law == "frictionless" and not options:  # the default differs
        separate = jm.Simulation(grid=pair.grid, shape=pair.shape, material=pair.material, scheme=make,
                                 terms=(jm.Contact(law=law, normal=(1.0, 0.0)),)).step(state, dt)
        assert np.max(np.abs(np.asarray(separate.v) - V_ref)) > 1e-6 * np.max(np.abs(V_ref))
    if scheme == "xpic" and law == "stick":  # the preset: XPIC's NairnMPM options and the incremental contact
        preset = jm.Simulation(grid=pair.grid, shape=pair.shape, material=pair.material, scheme=jm.XPIC(2),
                               terms=(jm.Contact(law=law, normal=(1.0, 0.0)),), conventions="nairnmpm")
        assert preset.term(jm.Contact).series == "incremental"
        close(np.asarray(preset.step(state, dt).v), V_ref)


@pytest.mark.parametrize("update", ["USL", "USF", "MUSL"])
def test_incremental_stick_equals_the_one_field_run(update):
    """With stick every increment moves with the centre of mass, so FMPM(2) with Contact(law="stick",
    series="incremental") is the one-field FMPM(2) (positions, velocities, F over 4 steps, to round-off),
    the strain-update series of USF and MUSL included; the default series="separate" is not."""
    pair, state, _ = contact_pair()
    dt = 0.01
    one = jm.Simulation(grid=pair.grid, shape=pair.shape, material=pair.material, scheme=jm.FMPM(2), update=update)
    single = one.init(jm.Particles(x=np.asarray(state.x), v=np.asarray(state.v), volume=np.asarray(state.volume0)))
    single = eqx.tree_at(lambda s: s.F, single, state.F)
    np.testing.assert_array_equal(np.asarray(single.mass), np.asarray(state.mass))

    def run(sim, s):
        return jax.jit(lambda s: jax.lax.fori_loop(0, 4, lambda _, s: sim.step(s, dt), s))(s)

    ref = run(one, single)
    new = run(incremental_sim(pair, jm.FMPM(2), update, law="stick"), state)
    for name in ("x", "v", "F"):
        close(np.asarray(getattr(new, name)) - np.asarray(getattr(state, name)),
              np.asarray(getattr(ref, name)) - np.asarray(getattr(state, name)))
    separate = jm.Simulation(grid=pair.grid, shape=pair.shape, material=pair.material, scheme=jm.FMPM(2),
                             update=update, terms=(jm.Contact(law="stick", normal=(1.0, 0.0)),))
    dv = np.max(np.abs(np.asarray(run(separate, state).v) - np.asarray(ref.v)))
    assert dv > 1e-6 * np.max(np.abs(np.asarray(ref.v)))


def test_incremental_series_refusals():
    """series="incremental": two materials only, not with series_correction=False, not with a series
    mode other than the constrained iterates; the preset leaves more materials "separate"."""
    with pytest.raises(jm.InputError, match="series = 'fast'"):
        jm.Contact(series="fast")
    with pytest.raises(jm.InputError, match="materials = 3"):
        jm.Contact(series="incremental", materials=3)
    with pytest.raises(jm.InputError, match="series_correction=False"):
        jm.Contact(series="incremental", series_correction=False)
    pair, state, _ = contact_pair()
    with pytest.raises(jm.InputError, match="boundary = 'result' with the exchange on the series' increments"):
        incremental_sim(pair, jm.FMPM(2, boundary="result")).step(state, 0.01)
    assert jm.Contact(materials=3).in_conventions("nairnmpm").series == "separate"
    assert jm.Contact(series_correction=False).in_conventions("nairnmpm").series == "separate"
    assert jm.Contact().in_conventions("nairnmpm").series == "incremental"


@pytest.mark.slow
def test_gradient_through_the_incremental_series_against_central_differences():
    """d/d(mu, E) of a loss after 2 steps of FMPM(2) with Coulomb contact on the series' increments
    (Contact(series="incremental"): the law inside the series' fori_loop) equals central differences
    in float64."""
    pair, state, _ = contact_pair()
    base = incremental_sim(pair, jm.FMPM(2), law="coulomb", friction=0.3)

    def loss(mu, E):
        sim = jm.set_params(base, friction=mu, E=E)
        s = jax.lax.fori_loop(0, 2, lambda _, s: sim.step(s, 0.01), state)
        return jnp.sum(s.mass[:, None] * s.v**2) + jnp.sum((s.x - state.x) ** 2)

    grad = jax.jit(jax.grad(loss, argnums=(0, 1)))(0.3, 50.0)
    f = jax.jit(loss)
    fd_mu = central_difference(lambda mu: f(mu, 50.0), 0.3, 1e-4, order=4)
    fd_E = central_difference(lambda e: f(0.3, e), 50.0, 1e-2, order=4)
    np.testing.assert_allclose(float(grad[0]), float(fd_mu), rtol=1e-7)
    np.testing.assert_allclose(float(grad[1]), float(fd_E), rtol=1e-7)
    assert abs(float(grad[0])) > 1e-4 and abs(float(grad[1])) > 1e-4  # the parameters act


def apart_bars(scheme, conventions, **contact):
    """Two 1D bars apart (no node carries both materials), a fixed end (x = 0) and a prescribed velocity
    0.2 on the last node of the second bar (x = 3.75, with mass), a prestrain: one step's (V, X - X^n)."""
    grid = jm.Grid((0.0,), (4.0,), (16,))
    a = jm.fill(grid, jm.Box((0.0,), (1.5,)), ppc=2, velocity=0.4)
    b = jm.fill(grid, jm.Box((2.5,), (3.75,)), ppc=2, velocity=-0.3)
    scale = np.linspace(0.5, 1.5, a.num + b.num)[:, None]  # non-uniform velocities
    particles = jm.Particles(x=np.concatenate([a.x, b.x]), v=np.concatenate([a.v, b.v]) * scale,
                             volume=np.concatenate([a.volume, b.volume]), ppc=2)
    boundary = [jm.Fixed(where=lambda x: x[:, 0] <= 1e-9),
                jm.Prescribed(lambda x: np.abs(x[:, 0] - 3.75) < 1e-9, 0.2)]
    sim = jm.Simulation(grid=grid, shape=jm.Linear(), material=jm.LinearElastic(E=3.0, nu=0.0, density=1.0),
                        scheme=scheme, boundary=boundary, conventions=conventions,
                        terms=(jm.Contact(law="frictionless", **contact),))
    state = sim.init(particles, fields={"material": jnp.asarray(np.concatenate([np.zeros(a.num), np.ones(b.num)]))})
    state = eqx.tree_at(lambda s: s.F, state, 1.0 + 0.05 * jnp.sin(7.0 * state.x[:, :, None]))
    m = np.asarray(p2g(sim, state).mass)
    assert m[0] > 0 and m[grid.num_nodes + 15] > 0 and not np.any((m[:17] > 0) & (m[17:] > 0))
    new = sim.step(state, DT)
    return sim, np.asarray(new.v)[:, 0], np.asarray(new.x - state.x)[:, 0]


@pytest.mark.parametrize("scheme, conventions", [pytest.param(jm.FMPM(3), "jaxmpm", marks=pytest.mark.slow),
                                                 (jm.XPIC(3), "jaxmpm"), (jm.XPIC(3), "nairnmpm")])
def test_incremental_series_without_contact_nodes_is_the_series(scheme, conventions):
    """Without contact nodes (:func:`apart_bars`) the incremental series -- its start (Z u + g, or p/m)
    and the conditions on its result -- equals the plain series: FMPM's v+ and XPIC's v(m) in the
    constrained iterates (an inhomogeneous condition), and under NairnMPM's conventions XPIC's
    unconstrained start with the reaction, to round-off."""
    sim, V, dX = apart_bars(scheme, conventions, series="incremental")
    assert sim.term(jm.Contact).series == "incremental"
    _, V0, dX0 = apart_bars(scheme, conventions, series_correction=False)  # the plain series
    close(V, V0)
    close(dX, dX0)


def test_incremental_series_keeps_the_conditions_on_a_contact_node():
    """The two blocks with Coulomb contact (normal (1, 0)) and v_y = 0 on the contact column x = 0.5
    (jm.Slip, axis 1): the law on the series' increments acts after their zeroing (NairnMPM's order),
    and as the increment's normal stick change moves the sliding limit mu |Dp.n| it changes the
    constrained v_y inside the series; FMPM(2)'s v+ (the strain velocity) keeps v_y = 0 there for both
    materials: the conditions hold on the result."""
    from jaxmpm.schemes.base import combine_damping

    pair, state, _ = contact_pair()
    where = lambda x: np.abs(x[:, 0] - 0.5) < 1e-9  # noqa: E731
    sim = jm.Simulation(grid=pair.grid, shape=pair.shape, material=pair.material, scheme=jm.FMPM(2),
                        boundary=[jm.Slip(where, axis=1)],
                        terms=(jm.Contact(law="coulomb", friction=0.3, normal=(1.0, 0.0), series="incremental"),))
    dt = jnp.asarray(0.01)
    constraint = sim.constraint(state.x.dtype)
    fields = p2g(sim, state)
    solution = grid_phases(sim, fields, dt, constraint)
    upd = sim.scheme.update(state.v, state.x, fields.transfer, constraint, solution, combine_damping([]), dt)
    n = sim.grid.num_nodes
    column = where(np.asarray(sim.grid.node_coordinates()))
    m = np.asarray(fields.mass)
    on = column & (m[:n] > 0) & (m[n:] > 0)  # the constrained contact nodes
    assert on.sum() >= 3
    v_plus = np.asarray(upd.strain_velocity)
    assert np.all(v_plus[:n][on, 1] == 0.0) and np.all(v_plus[n:][on, 1] == 0.0)
    hook = solution["exchange_series"]
    v_tilde = solution.v_tilde
    change, _ = hook.adjust(constraint.zero(v_tilde - fields.transfer.s_plus_s(v_tilde)), hook.initial())
    assert np.max(np.abs(np.asarray(change)[:n][on, 1])) > 1e-6  # the law moves the constrained component
