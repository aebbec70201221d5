"""XPIC(m) and FMPM(k) against their matrix definitions on small dense problems.

With S (N x n) the shape-function matrix, M = diag(M_p), the lumped mass m = diag(S^T M 1) and
S+ = m^{-1} S^T M (000 eq. 1.10, 003 eq. 1.7; rows of nodes without mass dropped), built with
NumPy from the ``Stencil``:

* XPIC: S v(m) = P_m V with P_m = I - (I - S S+)^m and v = S+ V (000 eqs. 3.12-3.15, 3.25),
  and the whole particle update of 000 eqs. (3.28)-(3.29)
* FMPM: v+ = m~_k^{-1} p+ with m~_k^{-1} = sum_l (-1)^{l+1} C(k,l) (S+S)^{l-1} m^{-1}
  (003 eq. 1.23) = the truncated Neumann series (003 eqs. 1.12-1.13), P_k = S m~_k^{-1} S^T M
  (003 eq. 1.41) = I - (I - S S+)^k (003 eq. 1.32), and the update of 003 eq. (2.17)
* the limit k -> infinity: the full mass matrix solve m~ v = p, m~ = S^T M S (003 eq. 1.9),
  and with a fixed node the constrained solve of 003 eqs. (1.49)-(1.50)
* velocity boundary conditions inside the series (003 §1.5, docs/design.md): the three ``boundary`` modes
* XPIC(1) = PIC over a whole ``bar`` run (000 eq. 3.25 with m = 1)

Run with ``pytest tests/test_matrix_forms.py -s`` to see the measured convergence rates.
"""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from cases import FOUR_SHAPES, UNIT_GRIDS, at_cells, dense_weights, interior_cells

import jaxmpm as jm
from jaxmpm.core.fields import GridSolution
from jaxmpm.physics.conditions import build_constraint
from jaxmpm.physics.damping import Damping
from jaxmpm.transfer.operators import Transfer
from jaxmpm.transfer.series import mass_matrix_series

N_PARTICLES = 40
CASES = [pytest.param(name, dim, id=f"{name}-{dim}d") for name in FOUR_SHAPES for dim in UNIT_GRIDS]
STENCIL_SIZE = {1: 4, 2: 16}  # the cubic B-spline's 4^D nodes: every stencil is padded to this size
ORDERS = (1, 2, 3, 4, 5, 6)
TOL = 1e-12  # relative, the brief's round-off tolerance for orders <= 6
DT = 0.01


# --------------------------------------------------------------------------- dense reference
class Dense:
    """Dense S, M, m, S+, S+S, S S+ and m~ on the nodes with mass (000 ch. 1, 003 §1.2-1.3)."""

    def __init__(self, stencil, mass, num_nodes):
        full, _ = dense_weights(stencil, num_nodes)  # (N, num_nodes)
        lumped = full.T @ mass
        self.active = lumped > 0
        self.S = full[:, self.active]  # (N, n_a)
        self.M = np.asarray(mass)
        self.m = lumped[self.active]  # lumped nodal mass, m = S^T M 1
        self.S_plus = (self.S.T * self.M) / self.m[:, None]  # 000 eq. (1.10)
        self.SpS = self.S_plus @ self.S  # S+S (n_a x n_a)
        self.SSp = self.S @ self.S_plus  # S S+ (N x N)
        self.m_tilde = self.S.T @ (self.M[:, None] * self.S)  # 003 eq. (1.9)

    @property
    def n(self):
        return self.S.shape[1]

    def restrict(self, nodal):
        """Nodal field (num_nodes, D) -> active rows."""
        return np.asarray(nodal)[self.active]

    def xpic_projector(self, m):
        """P_m = I - (I - S S+)^m  (000 eq. 3.12, 003 eq. 1.32)."""
        eye = np.eye(self.S.shape[0])
        return eye - np.linalg.matrix_power(eye - self.SSp, m)

    def binomial_series(self, k, SpS=None):
        """sum_{l=1}^{k} (-1)^{l+1} C(k,l) (S+S)^{l-1}  (000 eq. 3.25, 003 eq. 1.23 without m^{-1})."""
        SpS = self.SpS if SpS is None else SpS
        return sum((-1) ** (j + 1) * math.comb(k, j) * np.linalg.matrix_power(SpS, j - 1) for j in range(1, k + 1))

    def m_tilde_k_inv(self, k):
        """m~_k^{-1} = (sum_l C_kl (S+S)^{l-1}) m^{-1}, C_kl = (-1)^{l+1} C(k,l)  (003 eqs. 1.23, 1.30)."""
        return self.binomial_series(k) / self.m[None, :]

    def m_tilde_k_inv_neumann(self, k):
        """m~_k^{-1} = (I + A + ... + A^{k-1}) m^{-1}, A = I - S+S  (003 eqs. 1.11-1.13)."""
        A = np.eye(self.n) - self.SpS
        return sum(np.linalg.matrix_power(A, j) for j in range(k)) / self.m[None, :]


def rel_err(actual, expected):
    actual, expected = np.asarray(actual), np.asarray(expected)
    return float(np.max(np.abs(actual - expected)) / np.max(np.abs(expected)))


def random_positions(shape, grid, rng, n=N_PARTICLES):
    """Uniform random positions whose whole stencil lies on the grid."""
    return at_cells(grid, interior_cells(shape, grid, rng, n))


def jittered_positions(shape, grid, rng, n=N_PARTICLES):
    """1D: one random particle in each of n equal slots of the band the stencil allows, so every
    node has support (a well-conditioned m~, 003 §1.3)."""
    (cells,), (h,), (lower,) = grid.cells, grid.spacing, grid.lower
    lo = lower + (float(shape.margin) + 1e-3) * h
    hi = lower + (cells - float(shape.margin) - 1e-3) * h
    return (lo + (hi - lo) * (np.arange(n) + rng.uniform(0.05, 0.95, n)) / n)[:, None]


def padded(stencil, size):
    """The same S with each particle's stencil padded by zero-weight entries (on node 0) to ``size``
    entries: S u and S^T q gain exact zeros only, and every shape function then has the same array
    shapes, so each jitted check compiles once per dimension instead of once per shape."""
    extra = size - stencil.size

    def pad(a):  # planar arrays: the slot axis K is second to last
        return jnp.pad(a, [(0, 0)] * (a.ndim - 2) + [(0, extra), (0, 0)])

    return jm.Stencil(index=pad(stencil.index), weight=pad(stencil.weight), gradient=pad(stencil.gradient),
                      offset=pad(stencil.offset))


def problem(name, dim, seed=0, positions=random_positions):
    """Random particles, masses, velocities; the eager Transfer and its dense matrices."""
    rng = np.random.default_rng(seed)
    shape, grid = FOUR_SHAPES[name], UNIT_GRIDS[dim]
    x = positions(shape, grid, rng)
    mass = rng.uniform(0.5, 2.0, N_PARTICLES)
    V = rng.normal(size=(N_PARTICLES, dim))
    stencil = padded(build_stencil(shape, grid, jnp.asarray(x)), STENCIL_SIZE[dim])
    transfer = Transfer.build(stencil, jnp.asarray(mass), grid.num_nodes)
    return grid, transfer, Dense(stencil, mass, grid.num_nodes), x, V, rng


def no_constraint(grid):
    """No boundary condition: an all-False mask."""
    shape = (grid.num_nodes, grid.dim)
    return jm.Constraint(mask=jnp.zeros(shape, bool), value=jnp.zeros(shape))


def nodal_random(dense, grid, rng):
    """A random nodal field on the nodes with mass, zero elsewhere."""
    out = np.zeros((grid.num_nodes, grid.dim))
    out[dense.active] = rng.normal(size=(dense.n, grid.dim))
    return out


# ------------------------------------------------------------------ jitted implementation
@eqx.filter_jit
def build_stencil(shape, grid, x):
    return shape.stencil(grid, x)


@eqx.filter_jit
def series_orders(u, transfer, constraint, orders, boundary="iterates", form=None):
    """mass_matrix_series(u, m) for every m in ``orders`` (one compilation per call site)."""
    extra = {} if form is None else {"form": form}
    return [mass_matrix_series(u, m, transfer, constraint, boundary, **extra) for m in orders]


@eqx.filter_jit
def scheme_updates(schemes, V, X, transfer, constraint, grid_solution, dt):
    """Each scheme's particle update (no damping)."""
    return [s.update(V, X, transfer, constraint, grid_solution, Damping(), dt) for s in schemes]


# ======================================================================== XPIC(m): 000 ch. 3
@pytest.mark.slow
@pytest.mark.parametrize("name, dim", CASES)
def test_xpic_series_equals_projector(name, dim):
    """S v(m) = P_m V, P_m = I - (I - S S+)^m, v = S+ V  (000 eqs. 3.12-3.15 and 3.25), m = 1..6,
    for both evaluation forms of the series."""
    grid, transfer, dense, _, V, _ = problem(name, dim)
    v = transfer.s_plus(jnp.asarray(V))
    assert rel_err(dense.restrict(v), dense.S_plus @ V) < TOL  # 000 eq. (1.10)
    assert np.all(np.asarray(v)[~dense.active] == 0.0)
    for form in (None, "neumann"):
        results = series_orders(v, transfer, no_constraint(grid), ORDERS, form=form)
        for m, vm in zip(ORDERS, results):
            assert np.all(np.asarray(vm)[~dense.active] == 0.0)
            err = rel_err(transfer.gather(vm), dense.xpic_projector(m) @ V)
            assert err < TOL, f"{name} {dim}D form={form} m={m}: |S v(m) - P_m V| / |P_m V| = {err:.2e}"


@pytest.mark.slow
@pytest.mark.parametrize("name, dim", CASES)
def test_xpic_update_matches_000_eq_3_28(name, dim):
    """XPIC(m, beta) particle update against 000 eqs. (3.28)-(3.29) with S v(m) = P_m V:
    V+ = beta V + (1-beta) P_m V + S a dt, X+ = X + (S v + dV/2) dt (VV = S v) or
    X + (beta S v + (1-beta) P_m V + dV/2) dt (VV = P V)."""
    grid, transfer, dense, x, V, rng = problem(name, dim, seed=1)
    beta = 0.3
    v = transfer.s_plus(jnp.asarray(V))
    a = nodal_random(dense, grid, rng)
    sol = GridSolution(v=v, a=jnp.asarray(a), v_tilde=v + DT * jnp.asarray(a))
    schemes = [jm.XPIC(order=m, beta=beta, position=pos) for m in ORDERS for pos in ("Sv", "PV")]
    updates = scheme_updates(schemes, jnp.asarray(V), jnp.asarray(x), transfer, no_constraint(grid), sol, DT)
    Sv = dense.S @ dense.restrict(v)
    Sa = dense.S @ dense.restrict(a)
    for scheme, upd in zip(schemes, updates):
        PV = dense.xpic_projector(scheme.order) @ V
        V_new = beta * V + (1 - beta) * PV + Sa * DT  # 000 eq. (3.28)
        VV = Sv if scheme.position == "Sv" else beta * Sv + (1 - beta) * PV  # 000 eq. (3.29)
        X_new = x + (VV + 0.5 * (V_new - V)) * DT
        assert rel_err(upd.velocity, V_new) < TOL, (scheme.order, scheme.position)
        assert rel_err(upd.position - x, X_new - x) < TOL, (scheme.order, scheme.position)


# ======================================================================== FMPM(k): 003 ch. 1
@pytest.mark.slow
@pytest.mark.parametrize("name, dim", CASES)
def test_fmpm_velocity_is_truncated_inverse(name, dim):
    """FMPM(k): v+ = sum_l (-1)^{l+1} C(k,l) (S+S)^{l-1} m^{-1} p+ (003 eq. 1.23),
    V+ = S v+, X+ = X + (V+ + V)/2 dt (003 eq. 2.17), k = 1..6; and P_k = S m~_k^{-1} S^T M
    (003 eq. 1.41) = I - (I - S S+)^k (003 eq. 1.32), with m~_k^{-1} = the Neumann form (1.13)."""
    grid, transfer, dense, x, V, rng = problem(name, dim, seed=2)
    p_plus = nodal_random(dense, grid, rng)
    v_tilde = np.zeros_like(p_plus)
    v_tilde[dense.active] = dense.restrict(p_plus) / dense.m[:, None]  # lumped v~ = m^{-1} p+
    v_old = nodal_random(dense, grid, rng)
    sol = GridSolution(v=jnp.asarray(v_old), a=jnp.asarray((v_tilde - v_old) / DT), v_tilde=jnp.asarray(v_tilde))
    schemes = [jm.FMPM(order=k) for k in ORDERS]
    updates = scheme_updates(schemes, jnp.asarray(V), jnp.asarray(x), transfer, no_constraint(grid), sol, DT)
    for k, upd in zip(ORDERS, updates):
        inv_k = dense.m_tilde_k_inv(k)
        assert rel_err(inv_k, dense.m_tilde_k_inv_neumann(k)) < TOL  # 003 eqs. (1.13) = (1.23)
        P_k = dense.S @ inv_k @ dense.S.T @ np.diag(dense.M)  # 003 eq. (1.41)
        assert rel_err(P_k, dense.xpic_projector(k)) < TOL  # 003 eq. (1.32)
        v_plus = inv_k @ dense.restrict(p_plus)  # 003 eq. (1.23)
        assert rel_err(dense.restrict(upd.strain_velocity), v_plus) < TOL, k
        assert np.all(np.asarray(upd.strain_velocity)[~dense.active] == 0.0)
        assert rel_err(upd.velocity, dense.S @ v_plus) < TOL, k  # 003 eq. (2.17), beta = 0
        X_new = x + 0.5 * (dense.S @ v_plus + V) * DT
        assert rel_err(upd.position - x, X_new - x) < TOL, k


# ================================================== FMPM(k)'s stable time step (jaxmpm.FMPM.time_step_factor)
@pytest.mark.parametrize("name, dim", CASES)
def test_fmpm_mass_inverse_bounded_by_k_lumped(name, dim):
    """m~_k^{-1} <= k m^{-1} (Loewner order) for the series of 003 eqs. (1.13)/(1.23): the
    eigenvalues of m^{1/2} m~_k^{-1} m^{1/2} are p_k(x) = sum_{j<k} (1 - x)^j over the eigenvalues
    x in [0, 1] of X = m^{-1/2} m~ m^{-1/2}, hence in [1, k].  So for any stiffness K the largest
    frequency of m~_k^{-1} K is at most sqrt(k) times the lumped one: the stable step of FMPM(k) is
    at least the CFL one over sqrt(k), FMPM.time_step_factor.  Checked with K = G^T diag(V) G, the
    Laplacian-like stiffness of the particles' shape-function gradients, as well."""
    grid, transfer, dense, x, V, rng = problem(name, dim, seed=3)
    root = np.sqrt(dense.m)
    X = dense.m_tilde / np.outer(root, root)
    x_eig = np.linalg.eigvalsh(X)
    assert x_eig.min() > -1e-12 and x_eig.max() < 1.0 + 1e-12  # m - m~ is positive semi-definite
    full, gradient = dense_weights(build_stencil(FOUR_SHAPES[name], grid, jnp.asarray(x)), grid.num_nodes)
    G = np.concatenate([np.asarray(gradient)[..., a][:, dense.active] for a in range(dim)])  # (D N, n_a)
    K = G.T @ G  # particle volumes 1
    omega_lumped = np.max(np.abs(np.linalg.eigvals(K / dense.m[:, None])))
    for k in ORDERS:
        inv_k = dense.m_tilde_k_inv(k)
        sym = root[:, None] * inv_k * root[None, :]  # m^{1/2} m~_k^{-1} m^{1/2}, symmetric
        scaled = np.linalg.eigvalsh(0.5 * (sym + sym.T))
        expected = np.sort([sum((1.0 - xi) ** j for j in range(k)) for xi in x_eig])
        assert np.max(np.abs(np.sort(scaled) - expected)) < 1e-10 * k
        assert scaled.min() > 1.0 - 1e-10 and scaled.max() < k + 1e-10
        omega_k = np.max(np.abs(np.linalg.eigvals(inv_k @ K)))  # squared frequencies
        assert omega_k <= k * omega_lumped * (1 + 1e-10)
        assert jm.FMPM(order=k).time_step_factor() == pytest.approx(1.0 / np.sqrt(k), rel=1e-15)
    assert jm.FMPM(order=0).time_step_factor() == 1.0  # FLIP


@pytest.mark.slow
def test_fmpm_runs_at_its_stable_step_and_blew_up_at_the_lumped_one():
    """mpm88 (2D, quadratic B-splines, 2048 particles, float64) with FMPM(8): at half the CFL limit
    h / (c + |V|) -- the step stable_dt(cfl=0.5) gave before it knew FMPM's order -- the run turns
    inverted within 300 steps (the largest stable step measured for FMPM(8) is 0.37 of the CFL
    limit); at stable_dt(cfl=0.5) now, the CFL limit over 2 sqrt(8), it runs 300 steps with every
    particle upright and finite, as FLIP does at the same step."""
    setup = jm.scene("mpm88", scheme="fmpm:8", n_particles=2048, n_grid=64)
    sim, state = setup.sim, setup.state
    limits = sim.time_step_limits(state, 0.5)
    assert float(limits["fmpm"]) == pytest.approx(float(limits["CFL"]) / np.sqrt(8), rel=1e-14)
    assert float(sim.stable_dt(state, 0.5)) == float(limits["fmpm"])

    @eqx.filter_jit
    def run(sim, state, dt):
        return jax.lax.fori_loop(0, 300, lambda i, s: sim.step(s, dt), state)

    def upright(sim, dt):
        out = run(sim, state, jnp.asarray(dt))
        J = np.linalg.det(np.asarray(out.F))
        return bool(np.all(np.isfinite(np.asarray(out.v))) and np.all(np.isfinite(J)) and J.min() > 0.5)

    assert not upright(sim, float(limits["CFL"]))  # cfl = 0.5 of the lumped limit
    assert upright(sim, float(sim.stable_dt(state, 0.5)))
    assert upright(eqx.tree_at(lambda s: s.scheme, sim, jm.FLIP()), float(sim.stable_dt(state, 0.5)))


# ============================================================ the limit k -> infinity (003 §1.3)
CONVERGENCE_ORDERS = tuple(range(1, 25))


def m_norm(e, m):
    """Lumped-mass norm sqrt(e^T m e)."""
    return float(np.sqrt(np.sum(m[:, None] * np.asarray(e) ** 2)))


@pytest.mark.slow
@pytest.mark.parametrize("name", ["linear", "quadratic"])
def test_series_converges_to_full_mass_solve(name):
    """m~_k^{-1} p -> m~^{-1} p (003 eq. 1.12).  The error is e_k = -A^k m~^{-1} p with A = I - m^{-1} m~
    (003 eq. 1.11); A is self-adjoint in the lumped-mass inner product (m A = m - m~ is symmetric) with
    eigenvalues in [0, 1), so |e_k|_m falls monotonically, |e_{k+1}|_m <= rho(A) |e_k|_m, and the series
    converges iff rho(A) < 1, i.e. m~ is non-singular.  1D, 40 particles (one per slot, ~5 per cell)."""
    grid, transfer, dense, _, _, rng = problem(name, 1, seed=3, positions=jittered_positions)
    assert dense.n == grid.num_nodes  # every node has support
    A = np.eye(dense.n) - dense.SpS
    eig = np.linalg.eigvals(A)
    rho = float(np.max(np.abs(eig)))
    assert np.all(np.abs(eig.imag) < 1e-12) and np.all(eig.real > -1e-12)
    assert rho < 1.0, f"the series diverges: spectral radius of I - m^-1 m~ = {rho}"
    p = rng.normal(size=(dense.n, 1))
    v_full = np.linalg.solve(dense.m_tilde, p)  # 003 eq. (1.9): m~ v = p
    u = jnp.asarray(p / dense.m[:, None])
    results = series_orders(u, transfer, no_constraint(grid), CONVERGENCE_ORDERS)
    errors = np.array([m_norm(np.asarray(r) - v_full, dense.m) for r in results])
    e0 = m_norm(v_full, dense.m)  # the k = 0 approximation, v = 0
    ratios = errors[1:] / errors[:-1]
    print(f"\n{name}: rho(I - m^-1 m~) = {rho:.4f}, cond(m~) = {np.linalg.cond(dense.m_tilde):.1f}")
    print("  k   |e_k|_m/|v|_m   |e_k|/|e_k-1|")
    for k, e, r in zip(CONVERGENCE_ORDERS, errors, np.r_[errors[0] / e0, ratios]):
        print(f"  {k:2d}  {e / e0:.3e}       {r:.4f}")
    assert np.all(np.diff(np.r_[e0, errors]) < 0), "the error must fall monotonically with k"
    assert np.all(ratios <= rho), f"observed rates {ratios} exceed rho(A) = {rho}"
    ks = np.array(CONVERGENCE_ORDERS)
    assert np.all(errors <= rho**ks * e0)


@pytest.mark.slow
def test_constrained_series_converges_to_constrained_solve():
    """Fixed first node: ``boundary="iterates"`` converges to the constrained full-mass solve of
    003 eqs. (1.49)-(1.50), m~_ff v_f = p_f, v_b = 0, at a rate bounded by rho(I_ff - m_f^{-1} m~_ff);
    ``boundary="result"`` converges to the unconstrained m~^{-1} p with v_b zeroed instead."""
    grid, transfer, dense, _, _, rng = problem("linear", 1, seed=3, positions=jittered_positions)
    constraint = build_constraint(grid, [jm.Fixed("x-")], jnp.float64)
    free = ~np.asarray(constraint.mask)[:, 0]
    p = rng.normal(size=(dense.n, 1))
    u = jnp.asarray(np.where(free[:, None], p / dense.m[:, None], 0.0))
    v_con = np.zeros_like(p)
    v_con[free] = np.linalg.solve(dense.m_tilde[np.ix_(free, free)], p[free])  # 003 eq. (1.49)
    v_res = np.where(free[:, None], np.linalg.solve(dense.m_tilde, np.where(free[:, None], p, 0.0)), 0.0)
    A_ff = np.eye(free.sum()) - dense.SpS[np.ix_(free, free)]
    rho_ff = float(np.max(np.abs(np.linalg.eigvals(A_ff))))
    rho = float(np.max(np.abs(np.linalg.eigvals(np.eye(dense.n) - dense.SpS))))
    e_con = [m_norm(np.asarray(r) - v_con, dense.m) for r in series_orders(u, transfer, constraint, CONVERGENCE_ORDERS)]
    e_res = [m_norm(np.asarray(r) - v_res, dense.m)
             for r in series_orders(u, transfer, constraint, CONVERGENCE_ORDERS, boundary="result")]
    gap = m_norm(v_con - v_res, dense.m) / m_norm(v_con, dense.m)
    print(f"\nfixed x-: rho_ff = {rho_ff:.4f}; |e_24|/|v| iterates {e_con[-1] / m_norm(v_con, dense.m):.2e}, "
          f"result (to its own limit) {e_res[-1] / m_norm(v_res, dense.m):.2e}; "
          f"the two limits differ by {gap:.3f} (relative)")
    ks = np.array(CONVERGENCE_ORDERS)
    assert np.all(np.diff(np.r_[m_norm(v_con, dense.m), e_con]) < 0)  # |A_ff^k v|_m falls, k = 0, 1, ...
    assert np.all(np.array(e_con[1:]) <= rho_ff * np.array(e_con[:-1]))
    # "result": e_k = -Z A^k m~^{-1} Z p, so |e_k|_m <= rho(A)^k |m~^{-1} Z p|_m
    w = np.linalg.solve(dense.m_tilde, np.where(free[:, None], p, 0.0))
    assert np.all(np.array(e_res) <= rho**ks * m_norm(w, dense.m))
    assert gap > 1e-2  # "result" solves a different system than 003 eq. (1.49)


# ====================================================== velocity conditions inside the series
def constrained_series_dense(dense, u_a, order, keep):
    """u_1 = m Z u, u_r = ((m - r + 1)/r) Z S+S u_{r-1}, sum_r (-1)^{r+1} u_r  (000 eqs. 3.22-3.24
    with the selector Z = diag(keep) after every S+S: 003 §1.5)."""
    term = order * np.where(keep, u_a, 0.0)
    total = term.copy()
    for r in range(2, order + 1):
        term = np.where(keep, (order - r + 1) / r * (dense.SpS @ term), 0.0)
        total = total + (-1) ** (r + 1) * term
    return total


def series_dense(dense, u_a, order):
    return dense.binomial_series(order) @ u_a


@pytest.mark.slow
@pytest.mark.parametrize("name", list(FOUR_SHAPES))
def test_fixed_boundary_modes(name):
    """1D, first node Fixed: ``iterates`` = the series of the constrained operator Z S+S from Z u
    with exactly zero on the fixed node; ``result`` = the unconstrained series, then zeroed;
    ``lumped`` = the unconstrained series of the BC-applied input (003 eq. 2.52)."""
    grid, transfer, dense, _, _, rng = problem(name, 1, seed=4)
    constraint = build_constraint(grid, [jm.Fixed("x-")], jnp.float64)
    keep = ~dense.restrict(constraint.mask)
    assert not keep[0, 0] and keep[1:].all()
    u = nodal_random(dense, grid, rng)  # not BC-applied: the series itself must impose the condition
    u_a = dense.restrict(u)
    orders = ORDERS[1:]  # order 1 returns its input unchanged (the scheme's input has BCs applied)
    iterates = series_orders(jnp.asarray(u), transfer, constraint, orders, "iterates")
    result = series_orders(jnp.asarray(u), transfer, constraint, orders, "result")
    lumped = series_orders(constraint.apply(jnp.asarray(u)), transfer, constraint, orders, "lumped")
    for m, it, rs, lp in zip(orders, iterates, result, lumped):
        it, rs, lp = dense.restrict(it), dense.restrict(rs), dense.restrict(lp)
        assert rel_err(it, constrained_series_dense(dense, u_a, m, keep)) < TOL, m
        assert np.all(it[~keep] == 0.0), m
        assert rel_err(rs, np.where(keep, series_dense(dense, u_a, m), 0.0)) < TOL, m
        assert np.all(rs[~keep] == 0.0), m
        assert rel_err(lp, series_dense(dense, np.where(keep, u_a, 0.0), m)) < TOL, m
    # order 1 on a BC-applied input is that input (XPIC(1) = PIC with boundary conditions)
    (first,) = series_orders(constraint.apply(jnp.asarray(u)), transfer, constraint, (1,), "iterates")
    assert np.array_equal(np.asarray(first), np.asarray(constraint.apply(jnp.asarray(u))))


def test_slip_boundary_per_component():
    """2D, Slip on x-: only the normal (x) component is constrained; ``iterates`` applies the
    per-component selector after every S+S (each component has its own Z)."""
    grid, transfer, dense, _, _, rng = problem("quadratic", 2, seed=5)
    constraint = build_constraint(grid, [jm.Slip("x-")], jnp.float64)
    keep = ~dense.restrict(constraint.mask)
    assert keep[:, 1].all() and not keep[:, 0].all()
    u = nodal_random(dense, grid, rng)
    u_a = dense.restrict(u)
    for m, it in zip(ORDERS[1:], series_orders(jnp.asarray(u), transfer, constraint, ORDERS[1:])):
        it = dense.restrict(it)
        expected = np.stack([constrained_series_dense(dense, u_a[:, [c]], m, keep[:, [c]])[:, 0] for c in range(2)], -1)
        assert rel_err(it, expected) < TOL, m
        assert np.all(it[~keep] == 0.0)


def neumann_constrained_dense(dense, w, order, keep):
    """sum_{j<order} (I - Z S+S)^j w, Z = diag(keep) (the Neumann form of the constrained series)."""
    total = np.zeros_like(w)
    term = w.copy()
    for _ in range(order):
        total = total + term
        term = term - np.where(keep, dense.SpS @ term, 0.0)
    return total


@pytest.mark.slow
@pytest.mark.parametrize("form", ["binomial", "neumann"])
def test_prescribed_velocity_solves_constrained_system(form):
    """1D, Prescribed velocity g = 0.7 on x-.  ``iterates`` returns the order-m Richardson iterate
    of the constrained system Z (S+S v - u) = 0 from v_0 = g + Z u:

        v = g + sum_{j<m} (I - Z S+S)^j Z u - sum_{j<m-1} (I - Z S+S)^j Z S+S g,

    exactly g on the constrained node; it keeps a body moving with the wall exactly (u = g
    everywhere gives v = g), and as m grows it converges to the constrained full-mass solve
    m~_ff v_f = p_f - m~_fb g_b (003 eq. 1.49)."""
    grid, transfer, dense, _, _, rng = problem("linear", 1, seed=6)
    constraint = build_constraint(grid, [jm.Prescribed("x-", 0.7)], jnp.float64)
    assert constraint.inhomogeneous
    keep = ~dense.restrict(constraint.mask)
    g = dense.restrict(constraint.prescribed(jnp.zeros((grid.num_nodes, 1))))
    assert g[0, 0] == 0.7 and np.all(g[1:] == 0.0)
    u = constraint.apply(jnp.asarray(nodal_random(dense, grid, rng)))
    u_a = dense.restrict(u)
    zu = np.where(keep, u_a, 0.0)
    zag = np.where(keep, dense.SpS @ g, 0.0)
    for m, it in zip(ORDERS[1:], series_orders(u, transfer, constraint, ORDERS[1:], form=form)):
        it = dense.restrict(it)
        expected = (g + neumann_constrained_dense(dense, zu, m, keep)
                    - neumann_constrained_dense(dense, zag, m - 1, keep))
        assert rel_err(it, expected) < TOL, m
        assert np.all(it[~keep] == 0.7)
    # a body moving with the wall stays in uniform motion at every order
    uniform = constraint.apply(jnp.where(jnp.asarray(dense.active)[:, None], 0.7, 0.0))
    for m, it in zip(ORDERS[1:], series_orders(uniform, transfer, constraint, ORDERS[1:], form=form)):
        np.testing.assert_allclose(dense.restrict(it), 0.7, rtol=1e-13)
    # the limit is the constrained full-mass solve (003 eq. 1.49), in the Neumann form
    if form == "neumann":
        free = keep[:, 0]
        p = dense.m[:, None] * u_a
        exact = g.copy()
        mt = dense.m_tilde
        exact[free] = np.linalg.solve(mt[np.ix_(free, free)], p[free] - mt[np.ix_(free, ~free)] @ g[~free])
        (far,) = series_orders(u, transfer, constraint, (200,), form="neumann")
        assert rel_err(dense.restrict(far), exact) < 1e-8


# ================================================================== XPIC(1) = PIC on the bar
@pytest.mark.slow
def test_xpic1_equals_pic_on_bar():
    """XPIC(m = 1, beta = 0) is PIC (v(1) = v, 000 eq. 3.25): a whole ``bar`` run agrees to round-off."""
    finals = []
    for scheme in (jm.XPIC(order=1, beta=0.0), jm.PIC()):
        setup = jm.scene("bar", scheme=scheme, dtype="f64")
        final, history = setup.run(save_particles=False)
        finals.append((final, history))
    (a, ha), (b, hb) = finals
    assert int(a.step) == int(b.step) > 0
    assert rel_err(a.x, b.x) <= 1e-14
    assert rel_err(a.v, b.v) <= 1e-14
    assert rel_err(ha.kinetic, hb.kinetic) <= 1e-14
