"""Axisymmetric GIMP (001 §7): r-z grids with per-radian masses, the r-weighted shape functions
S_ip, G_ip and the hoop shape function T_ip (001 eqs. 111-116), the hoop term of the internal force
(001 eq. 120) and the hoop strain rate v_r / r (001 eq. 113), checked against dense quadrature of
the seed's integrals, against Lamé's thick-walled cylinder (the ``cylinder`` scene) and against
the kinematics and energy of a radial expansion.  The 32-cell Lamé check (2 %) is in
experiments/axisymmetric.py (experiments/results/axisymmetric.md)."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxmpm as jm
from jaxmpm.model.step import strain_rate
from jaxmpm.transfer.backend import use_policy
from jaxmpm.transfer.operators import Transfer, p2g


@eqx.filter_jit
def _advance(sim, state, dt, steps):
    return jax.lax.fori_loop(0, steps, lambda i, s: sim.step(s, dt), state)


def advance(sim, state, dt, steps):
    """``steps`` steps of ``sim``: dt and steps as arrays, so every run of this module with the
    cylinder's model shares one compiled program."""
    return _advance(sim, state, jnp.asarray(dt, state.x.dtype), jnp.asarray(steps, jnp.int32))


@eqx.filter_jit
def stencil_at(shape, grid, x):
    return shape.stencil(grid, x)


# ----------------------------------------------------------------- grid bases, written out
def tent(s):
    return np.maximum(0.0, 1.0 - np.abs(s)), np.where(np.abs(s) < 1.0, -np.sign(s), 0.0)


def quadratic(s):
    a = np.abs(s)
    return (np.where(a < 0.5, 0.75 - a * a, np.where(a < 1.5, 0.5 * (1.5 - a) ** 2, 0.0)),
            np.where(a < 0.5, -2.0 * s, np.where(a < 1.5, -np.sign(s) * (1.5 - a), 0.0)))


def cubic(s):
    a = np.abs(s)
    return (np.where(a < 1.0, 0.5 * a**3 - a * a + 2.0 / 3.0, np.where(a < 2.0, (2.0 - a) ** 3 / 6.0, 0.0)),
            np.where(a < 1.0, 1.5 * a * s - 2.0 * s, np.where(a < 2.0, -0.5 * np.sign(s) * (2.0 - a) ** 2, 0.0)))


SHAPES = {"linear": (jm.Linear(), tent, 0.0), "ugimp2": (jm.UGIMP(2), tent, 0.25), "ugimp1": (jm.UGIMP(1), tent, 0.5),
          "quadratic": (jm.QuadraticBSpline(), quadratic, 0.0), "cubic": (jm.CubicBSpline(), cubic, 0.0)}


def _points(center, half, h, origin):
    """Gauss-Legendre points and weights (mean over the domain) of [center - half h, center + half h],
    split at the node lines (the grid bases are polynomials between them): exact for these
    piecewise polynomials; the point itself for half = 0 (a point particle)."""
    if half == 0:
        return np.array([center]), np.ones(1)
    lo, hi = center - half * h, center + half * h
    cuts = origin + h * np.arange(np.ceil((lo - origin) / h), np.floor((hi - origin) / h) + 1)
    edges = np.unique(np.concatenate([[lo, hi], cuts[(cuts > lo) & (cuts < hi)]]))
    g, w = np.polynomial.legendre.leggauss(6)
    pts = np.concatenate([0.5 * (a + b) + 0.5 * (b - a) * g for a, b in zip(edges[:-1], edges[1:])])
    wts = np.concatenate([0.5 * (b - a) * w for a, b in zip(edges[:-1], edges[1:])]) / (hi - lo)
    return pts, wts


def seed_matrices(grid, x, basis, half):
    """Dense S (N, n), G (N, n, 2), T (N, n) of 001 eqs. 112, 115, 116 by quadrature over each
    particle's square domain of half-width ``half`` cells (a point particle for 0: the integrals'
    limit, S = N_i(X_p), G = grad N_i(X_p), T = N_i(X_p) / r_p); A_p <r_p> = A_p r_p (eq. 111)."""
    h = np.array(grid.spacing)
    nodes = grid.node_coordinates()
    S, G, T = (np.zeros((len(x), len(nodes))), np.zeros((len(x), len(nodes), 2)), np.zeros((len(x), len(nodes))))
    for p, (rp, zp) in enumerate(x):
        r, wr = _points(rp, half, h[0], grid.lower[0])  # quadrature in r and z
        z, wz = _points(zp, half, h[1], grid.lower[1])
        Nr, dNr = basis((r[None, :] - nodes[:, :1]) / h[0])  # (n, points)
        Nz, dNz = basis((z[None, :] - nodes[:, 1:]) / h[1])
        S[p] = (Nr * r) @ wr / rp * (Nz @ wz)  # (1/(A_p r_p)) int chi N_i r dA
        G[p, :, 0] = (dNr / h[0] * r) @ wr / rp * (Nz @ wz)
        G[p, :, 1] = (Nr * r) @ wr / rp * (dNz / h[1] @ wz)
        T[p] = Nr @ wr / rp * (Nz @ wz)  # (1/(A_p r_p)) int chi N_i dA
    return S, G, T


def test_axisymmetric_inputs_are_checked():
    """The flag is 2D only; particles must lie at r > 0 and match the grid (per-radian masses)."""
    with pytest.raises(jm.InputError, match="axisymmetric=True needs a 2D grid"):
        jm.Grid((0.0,), (1.0,), (4,), axisymmetric=True)
    with pytest.raises(jm.InputError, match="axisymmetric"):
        jm.Grid((0.0, 0.0), (1.0, 1.0), (4, 4), axisymmetric="yes")
    grid = jm.Grid((-0.5, 0.0), (1.0, 1.0), (6, 4), axisymmetric=True)
    with pytest.raises(jm.InputError, match="r > 0"):
        jm.fill(grid, jm.Box((-0.4, 0.0), (0.5, 0.5)), ppc=2)
    plane = jm.Grid((-0.5, 0.0), (1.0, 1.0), (6, 4))
    sim = jm.Simulation(grid=grid, shape=jm.Linear(), material=jm.LinearElastic(E=1.0), scheme=jm.FLIP())
    with pytest.raises(jm.InputError, match="axisymmetric"):
        sim.init(jm.fill(plane, jm.Box((0.25, 0.0), (0.5, 0.5)), ppc=2))
    particles = jm.fill(grid, jm.Box((0.25, 0.0), (0.5, 0.5)), ppc=2)
    np.testing.assert_allclose(np.asarray(particles.volume), (0.25 / 2) ** 2 * np.asarray(particles.x)[:, 0])


GRID = jm.Grid((-0.5, -1.0), (3.0, 1.0), (7, 4), axisymmetric=True)
X = np.column_stack([np.random.default_rng(3).uniform(0.8, 2.0, 8), np.random.default_rng(4).uniform(-0.4, 0.4, 8)])


@pytest.mark.parametrize("name", list(SHAPES))
def test_shape_functions_match_the_seed_integrals(name):
    """S_ip, G_ip, T_ip of the stencil against dense quadrature of 001 eqs. 112, 115, 116; partition
    of unity sum_i S = 1, sum_i G = 0, and the linear field r e_r reproduced: sum_i G_ip r_i = 1 and
    the hoop rate sum_i T_ip r_i = 1 (v_r = r gives v_r / r = 1)."""
    shape, basis, half = SHAPES[name]
    stencil = stencil_at(shape, GRID, jnp.asarray(X))
    assert isinstance(stencil, jm.AxisymmetricStencil)
    S, G = stencil.matrices(GRID.num_nodes)
    T, _ = stencil.hoop_view().matrices(GRID.num_nodes)
    S_seed, G_seed, T_seed = seed_matrices(GRID, X, basis, half)
    np.testing.assert_allclose(S, S_seed, atol=1e-13)
    np.testing.assert_allclose(G, G_seed, atol=1e-12)
    np.testing.assert_allclose(T, T_seed, atol=1e-13)
    r_nodes = GRID.node_coordinates()[:, 0]
    np.testing.assert_allclose(S.sum(1), 1.0, atol=1e-13)
    np.testing.assert_allclose(G.sum(1), 0.0, atol=1e-12)
    np.testing.assert_allclose(G[..., 0] @ r_nodes, 1.0, atol=1e-12)
    np.testing.assert_allclose(T @ r_nodes, 1.0, atol=1e-12)


@pytest.mark.slow
def test_internal_force_and_hoop_rate_matrix_form():
    """uGIMP: the internal force's per-slot columns (what P2G scatters, jm.StressDivergence) summed
    per node against the dense form of 001 eq. 120 with the quadrature matrices,
    f = -sum_p V0_p ([tau_rr tau_rz; tau_rz tau_zz] G_p + (tau_thth, 0) T_p), for random 3x3
    (r, z, theta) deformations; and the velocity gradient of the strain update (001 eq. 113): for
    the nodal field v = (c r, d z) it is diag(c, d, c), the hoop rate v_r / r = c."""
    shape, basis, half = SHAPES["ugimp2"]
    volume = 0.25 * X[:, 0]  # per radian
    particles = jm.Particles(x=jnp.asarray(X), v=jnp.zeros_like(jnp.asarray(X)), volume=jnp.asarray(volume), ppc=2,
                             axisymmetric=True)
    material = jm.LinearElastic(E=7.0, nu=0.3, density=2.0)
    sim = jm.Simulation(grid=GRID, shape=shape, material=material, scheme=jm.FLIP())
    rng = np.random.default_rng(5)
    F = np.tile(np.eye(3), (len(X), 1, 1))
    F[:, :2, :2] += 0.05 * rng.standard_normal((len(X), 2, 2))
    F[:, 2, 2] += 0.05 * rng.standard_normal(len(X))
    state = eqx.tree_at(lambda s: s.F, sim.init(particles), jnp.asarray(F))
    stencil = stencil_at(shape, GRID, state.x)
    c, d = 0.3, -0.2
    nodes = GRID.node_coordinates()
    with use_policy("gpu"):  # eager: stage boundaries as identities
        quantities = jm.StressDivergence().p2g_quantities(sim, state, stencil)
        force = np.asarray(p2g(stencil, quantities, GRID.num_nodes)["force"])
        L = np.asarray(strain_rate(sim, Transfer.build(stencil, state.mass, GRID.num_nodes),
                                   jnp.asarray(nodes * np.array([c, d]))))
    _, G, T = seed_matrices(GRID, X, basis, half)
    tau = np.asarray(material.kirchhoff_stress(jnp.asarray(F)))
    expected = -np.einsum("p,pab,pib->ia", volume, tau[:, :2, :2], G)
    expected[:, 0] -= np.einsum("p,p,pi->i", volume, tau[:, 2, 2], T)
    np.testing.assert_allclose(force, expected, atol=1e-12 * np.abs(expected).max())
    np.testing.assert_allclose(L, np.broadcast_to(np.diag([c, d, c]), L.shape), atol=1e-13)


# ------------------------------------------------------------------- the cylinder scene
CELLS = 16


@pytest.fixture(scope="module")
def cylinder():
    return jm.scene("cylinder", cells=CELLS, shape="linear")


@pytest.mark.slow
def test_cylinder_settles_to_lame(cylinder):
    """The thick-walled cylinder under internal pressure (plane strain, 16 cells through the wall,
    linear shapes, FLIP, grid damping) settles to Lamé's u_r(r) and sigma_thth(r) (Timoshenko &
    Goodier, ch. 4).  Measured at 16 cells (experiments/axisymmetric.py): u_r from the positions
    1.85 % (the damping lag alpha_g dt = 1.88 % of the displacement: positions move with the damped
    particle velocity, F with the undamped grid velocity), u_r from the hoop stretch R (F_thth - 1)
    0.039 %, sigma_thth 1.89 % (at the loaded particles); at 32 cells 0.92 %, 0.029 %, 1.08 %."""
    s = cylinder
    final = advance(s.sim, s.state, s.dt, s.steps)
    R = np.asarray(s.state.x)[:, 0]
    exact = s.reference(R)
    F = np.asarray(final.F)
    u_positions = np.asarray(final.x)[:, 0] - R
    u_hoop = R * (F[:, 2, 2] - 1.0)
    sigma_tt = np.asarray(s.sim.material.kirchhoff_stress(final.F))[:, 2, 2] / np.linalg.det(F)
    assert float(s.sim.diagnostics(final)["kinetic"]) < 1e-12  # settled (peak ~1e-7)
    assert np.max(np.abs(u_positions / exact["u_r"] - 1)) < 0.020
    assert np.max(np.abs(u_hoop / exact["u_r"] - 1)) < 0.001
    assert np.max(np.abs(sigma_tt / exact["sigma_tt"] - 1)) < 0.020
    np.testing.assert_allclose(u_positions - u_hoop, -s.params["alpha_g"] * s.dt * exact["u_r"],
                               atol=0.002 * exact["u_r"].max())
    np.testing.assert_array_equal(np.asarray(final.x)[:, 1], np.asarray(s.state.x)[:, 1])  # plane strain


def _free(setup, material_E=None, speed=0.0):
    """The cylinder's model without its load and damping (and with E replaced), the particles
    given the radial velocity v_r = speed * r: the same compiled program as the Lamé run."""
    sim = setup.sim
    k = next(i for i, t in enumerate(sim.terms) if isinstance(t, jm.Traction))
    d = next(i for i, t in enumerate(sim.terms) if isinstance(t, jm.Damping))
    sim = eqx.tree_at(lambda m: (m.terms[k].traction, m.terms[d].grid), sim,
                      (jnp.zeros_like(sim.terms[k].traction), jnp.zeros_like(sim.terms[d].grid)))
    if material_E is not None:
        sim = eqx.tree_at(lambda m: m.material.E, sim, jnp.asarray(material_E, sim.material.E.dtype))
    x = setup.state.x
    state = eqx.tree_at(lambda s: s.v, setup.state, jnp.stack([speed * x[:, 0], jnp.zeros_like(x[:, 0])], -1))
    return sim, state


def test_diagnostics_are_per_radian(cylinder):
    """Mass, momentum and energies sum per radian (001 §7, m_p = rho A_p r_p): total mass
    rho H (b^2 - a^2)/2 (exact: the particle lattice integrates r exactly), the kinetic energy of
    v = (c r, w) rho H (c^2 (b^4 - a^4)/4 + w^2 (b^2 - a^2)/2)/2 (to the midpoint rule's O(h^2)),
    z-momentum w times the mass, and the strain energy of the uniform strain eps_rr = eps_thth = e,
    eps_zz = 0 (plane strain), 2 (lambda + mu) e^2 per volume, times the volume per radian."""
    s = cylinder
    a, b, rho = s.params["inner"], s.params["outer"], s.params["density"]
    H = (b - a) / CELLS  # the slab is one cell high
    c, w, e = 0.01, 0.02, 1e-3
    x = s.state.x
    state = eqx.tree_at(lambda st: (st.v, st.F), s.state,
                        (jnp.stack([c * x[:, 0], jnp.full_like(x[:, 0], w)], -1),
                         jnp.broadcast_to(jnp.diag(jnp.array([1.0 + e, 1.0, 1.0 + e])), s.state.F.shape)))
    diag = s.sim.diagnostics(state)
    mass = rho * H * (b**2 - a**2) / 2
    np.testing.assert_allclose(float(jnp.sum(state.mass)), mass, rtol=1e-13)
    np.testing.assert_allclose(float(diag["kinetic"]),
                               0.5 * rho * H * (c**2 * (b**4 - a**4) / 4 + w**2 * (b**2 - a**2) / 2),
                               rtol=1e-4)
    np.testing.assert_allclose(np.asarray(diag["momentum"]), [float(jnp.sum(state.mass * x[:, 0])) * c, w * mass],
                               rtol=1e-13)
    lam, mu = (float(v) for v in s.sim.material.lame())
    np.testing.assert_allclose(float(diag["strain"]), 2 * (lam + mu) * e**2 * H * (b**2 - a**2) / 2, rtol=1e-12)


def test_force_free_radial_expansion_keeps_its_energy(cylinder):
    """A stress-free (E = 0) cylinder expanding at v_r = c r (no load, no damping, FLIP): no force
    acts, so every particle keeps its velocity and the kinetic energy per radian stays exactly; with
    linear shapes the hoop stretch follows the kinematics F_thth = r / R to round-off (the hoop rate
    sum_i v_ri T_ip = (S v)_r / r_p is the rate of the particle's radius under X += S v dt)."""
    sim, state = _free(cylinder, material_E=0.0, speed=0.5)
    steps = 200
    final = advance(sim, state, cylinder.dt, steps)
    kinetic0, kinetic = (float(sim.diagnostics(st)["kinetic"]) for st in (state, final))
    np.testing.assert_allclose(kinetic, kinetic0, rtol=1e-13)
    np.testing.assert_array_equal(np.asarray(final.v), np.asarray(state.v))
    R, r = np.asarray(state.x)[:, 0], np.asarray(final.x)[:, 0]
    assert np.min(r / R) > 1.01  # it expanded (by 1 to 2 %)
    F = np.asarray(final.F)
    np.testing.assert_allclose(F[:, 2, 2], r / R, rtol=1e-13)


def test_elastic_breathing_conserves_energy(cylinder):
    """The elastic cylinder released with v_r = c r and no damping breathes; kinetic plus strain
    energy per radian (the strain energy with the hoop strain, W of the 3x3 F) stays at its
    initial value up to the time-stepping error, which is first order in dt: the hoop force's
    power -V0 tau_thth v_r / r is the hoop strain's (an inconsistent hoop term leaves an error
    that does not shrink with dt).  Measured with FLIP over 600 steps (about 2.5 breathing
    periods, frames every 50 steps): largest deviation 1.12 % at the scene's dt, 0.33 % at dt/4,
    while the kinetic energy swings between 1 % and 100 % of its initial value."""
    sim, state = _free(cylinder, speed=0.01)
    deviation = []
    for refine in (1, 4):
        energies, current = [], state
        for _ in range(12):
            current = advance(sim, current, cylinder.dt / refine, 50 * refine)
            d = sim.diagnostics(current)
            energies.append((float(d["kinetic"]), float(d["strain"])))
        kinetic, strain = np.array(energies).T
        d0 = sim.diagnostics(state)
        total0 = float(d0["kinetic"]) + float(d0["strain"])
        assert kinetic.min() < 0.05 * total0 and strain.max() > 0.9 * total0  # it breathes
        deviation.append(np.max(np.abs((kinetic + strain) / total0 - 1)))
    assert deviation[0] < 0.012
    assert deviation[1] < 0.4 * deviation[0]  # first order in dt (a dt-independent error: 1)


# ------------------------------------------------------------ APIC and TPIC on an r-z grid
AFFINE = jnp.array([[0.3, -0.2], [0.5, 0.1]])  # a velocity field v = A x + c in (r, z)
OFFSET = jnp.array([0.05, -0.02])


@eqx.filter_jit
def _affine_round_trip(sim, state, dt):
    """The nodal velocity p_i / m_i of P2G before the step, the state after it, and p_i / m_i of P2G
    from the particles' new velocities and affine state at their old positions: 002 prop. 5.1's
    G2P-then-P2G round trip (nodes without mass: 0)."""
    from jaxmpm.model.step import p2g
    from jaxmpm.transfer.operators import safe_divide

    def nodal_velocity(s):
        fields = p2g(sim, s, force=False)
        return safe_divide(fields.momentum, fields.transfer.nodal_mass), fields.transfer.nodal_mass

    new = sim.step(state, dt)
    return nodal_velocity(state), new, nodal_velocity(eqx.tree_at(lambda s: s.x, new, state.x))


def _assert_affine_nodal(v, m, grid):
    """v_i = A x_i + c at every node with mass m_i > 0."""
    has_mass = np.asarray(m) > 0
    expected = np.asarray(grid.node_coordinates()) @ np.asarray(AFFINE).T + np.asarray(OFFSET)
    np.testing.assert_allclose(np.asarray(v)[has_mass], expected[has_mass], rtol=0, atol=1e-14)


def _affine_setup(shape, scheme):
    h = 0.125
    grid = jm.Grid.covering((1.0, 0.0), (2.0, 1.0), h, shape=shape, pad=(3 * h, 3 * h), axisymmetric=True)
    particles = jm.fill(grid, jm.Box((1.25, 0.25), (1.75, 0.75)), ppc=2)  # stencils well inside the grid
    sim = jm.Simulation(grid=grid, shape=shape, material=jm.LinearElastic(E=1.0, nu=0.3, density=1.0), scheme=scheme)
    state = sim.init(particles)  # F = I: no stress in the first step, so only the transfers act
    state = eqx.tree_at(lambda s: s.v, state, state.x @ AFFINE.T + OFFSET[None, :])
    return sim, jm.with_velocity_gradient(sim, state, AFFINE), grid


@pytest.mark.slow
@pytest.mark.parametrize("scheme", [jm.APIC(), jm.TPIC()], ids=["apic", "tpic"])
@pytest.mark.parametrize("shape", [jm.Linear(), jm.QuadraticBSpline(), jm.CubicBSpline()],
                         ids=["linear", "quadratic", "cubic"])
def test_affine_fields_survive_the_transfers_on_an_rz_grid(shape, scheme):
    """APIC (002 prop. 5.1) and TPIC (004) keep an affine velocity field v = A x + c through
    P2G and G2P on an r-z grid, as in the plane, for shapes evaluated at the particle point (the
    point-particle limit of 001 eqs. 112-116: S_ip = N_i(X_p), G_ip = grad N_i(X_p)).  The
    per-radian masses M_p = rho A_p r_p weight P2G's sums but not their affine exactness.  From
    particles carrying V_p = A X_p + c and the matching affine state (B_p = A D_p, resp.
    grad v_p = A): P2G gives v_i = A x_i + c at every node with mass, G2P gives back V_p and the
    affine state, and P2G of those at the same positions the same nodal field again."""
    sim, state, grid = _affine_setup(shape, scheme)
    (v0, m0), new, (v1, m1) = _affine_round_trip(sim, state, 1e-4)
    _assert_affine_nodal(v0, m0, grid)
    _assert_affine_nodal(v1, m1, grid)
    np.testing.assert_allclose(np.asarray(new.v), np.asarray(state.x @ AFFINE.T + OFFSET[None, :]), rtol=0, atol=1e-14)
    np.testing.assert_allclose(np.asarray(new.scheme_state), np.asarray(state.scheme_state), rtol=0, atol=1e-14)


@pytest.mark.slow
def test_ugimp_samples_an_affine_field_at_the_r_weighted_centroid():
    """With uGIMP on an r-z grid S_ip is the r-weighted mean of N_i over the particle's domain (001
    eq. 112), so sum_i S_ip x_i is the domain's r-weighted centroid, r_p + l^2 / (3 r_p) in r for
    a domain of half-width l (the mean of r^2 over the mean of r), not X_p.  G2P of an affine field
    therefore returns A (X_p + l^2 / (3 r_p) e_r) + c: exactly that (to round-off), and 1e-4 away
    from A X_p + c here (l = h/4, r_p about 1.3).  This is the seed's weighting, not an error of
    APIC or TPIC (point-evaluated shapes keep the field exactly, above); P2G still reproduces the
    affine nodal field from particles that carry it."""
    sim, state, grid = _affine_setup(jm.UGIMP(2), jm.APIC())
    (v0, m0), new, _ = _affine_round_trip(sim, state, 1e-4)
    _assert_affine_nodal(v0, m0, grid)
    half = 0.125 / 4  # uGIMP(2): the particle's domain is h/2 wide
    centroid = state.x.at[:, 0].add(half**2 / (3 * state.x[:, 0]))
    np.testing.assert_allclose(np.asarray(new.v), np.asarray(centroid @ AFFINE.T + OFFSET[None, :]), rtol=0, atol=1e-14)
    assert float(jnp.max(jnp.abs(new.v - (state.x @ AFFINE.T + OFFSET[None, :])))) > 1e-4


def test_velocity_gradient_start_takes_the_grid_dimension():
    """jm.with_velocity_gradient sets a (2, 2) affine state on an r-z grid, whose F is 3x3, and
    names the expected shape for a wrong one."""
    sim, state, _ = _affine_setup(jm.QuadraticBSpline(), jm.TPIC())
    assert state.scheme_state.shape == (state.x.shape[0], 2, 2) and state.F.shape[1:] == (3, 3)
    np.testing.assert_array_equal(np.asarray(state.scheme_state[0]), np.asarray(AFFINE))
    with pytest.raises(jm.InputError, match=r"\(2, 2\) matrix"):
        jm.with_velocity_gradient(sim, state, jnp.eye(3))
