"""FMPM velocity-condition variants of 003 §1.5 and §2.4 against their matrix forms.

On a tiny 1D problem the dense S (N x n), M = diag(M_p), lumped m = S^T M 1, full mass matrix
m~ = S^T M S (003 eq. 1.9 / 2.2) and m~_k^{-1} = sum_l C_kl (S+S)^{l-1} m^{-1} (003 eq. 1.23) are
built with NumPy, each seed equation is evaluated with dense linear algebra as written -- forces,
momenta and matrix inverses, m~_k = (m~_k^{-1})^{-1} included -- and compared with
``mass_matrix_series(..., boundary=mode, free=p+/m)`` to 1e-12:

* ``unlumped1``        003 eqs. (2.52), (2.54)-(2.55): f dt = m~ m^{-1} f^(L) dt
* ``unlumped2``        003 eq. (2.56) and its steps 2-3: p^(BC) = m~_k Dv^(BC)
* ``unlumped2_mtilde`` the same with m~ for m~_k (003's remark after eq. 2.56)
* ``partial``          "Collection of Boundary Conditions", option 2 (lumped force from eq. 2.47)
* ``collection``       option 1: the n_BC x n_BC system of eq. (2.47) from the columns m^(j) of
                       m~_k^{-1} (003 eq. 1.71), solved densely
* ``series_start``     003 eqs. (1.51)-(1.56)
* ``pinv_start``       003 eqs. (1.57)-(1.63) and (1.69)

plus the conditions each mode meets exactly (or not), order 1, a gradient against central
differences, and the errors for missing input.
"""

import functools
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from cases import UNIT_GRIDS, dense_weights

import jaxmpm as jm
from jaxmpm.physics.conditions import build_constraint
from jaxmpm.transfer.operators import Transfer
from jaxmpm.transfer.series import UNLUMPED_MODES, mass_matrix_series

GRID = UNIT_GRIDS[1]  # 8 cells, 9 nodes on [0, 1]
N_PARTICLES = 16
# (order, form) pairs checked: k = 1-3, k = 2 with the Neumann form of the series
SWEEP = ((1, "binomial"), (2, "neumann"), (3, "binomial"))
ORDERS = tuple(k for k, _ in SWEEP)
MODES = UNLUMPED_MODES
TOL = 1e-12
CONDITIONS = {
    # v = 0 at x- (the bar's condition), written as Prescribed so that both cases share one
    # compiled program (the new modes read only the mask and the values)
    "one": [jm.Prescribed("x-", 0.0)],
    "two": [jm.Prescribed("x-", 0.7), jm.Fixed("x+")],  # two conditions, one inhomogeneous
}
STENCIL_SLOTS = 3  # linear stencils padded to the quadratic B-spline's 3 slots: one compilation


# --------------------------------------------------------------------------- the tiny problem
def problem(shape_name="linear", seed=0):
    """The particles of :func:`particles` and a generator for the nodal fields, seeded ``seed``."""
    transfer, d = particles(shape_name)
    return transfer, d, np.random.default_rng(seed)


@functools.lru_cache(maxsize=None)
def particles(shape_name):
    """Jittered particles (every node carries mass), random masses; the library Transfer and the
    dense matrices of 003 §1.2-1.3 (built once per shape: eager construction is slow)."""
    rng = np.random.default_rng(0)
    shape = {"linear": jm.Linear(), "quadratic": jm.QuadraticBSpline()}[shape_name]
    lo, hi = float(shape.margin) / 8 + 1e-3, 1.0 - float(shape.margin) / 8 - 1e-3
    x = lo + (hi - lo) * (np.arange(N_PARTICLES) + rng.uniform(0.05, 0.95, N_PARTICLES)) / N_PARTICLES
    mass = rng.uniform(0.5, 2.0, N_PARTICLES)
    stencil = padded(shape.stencil(GRID, jnp.asarray(x[:, None])))
    transfer = Transfer.build(stencil, jnp.asarray(mass), GRID.num_nodes)
    S, _ = dense_weights(stencil, GRID.num_nodes)
    d = Dense(S, mass)
    assert np.all(d.m_vec > 0)  # every node has support: m~ is invertible (003 §1.3)
    return transfer, d


def padded(stencil):
    """The same S with zero-weight slots (on node 0) up to STENCIL_SLOTS: exact zeros in S u and S^T q."""
    def pad(a):
        return jnp.pad(a, [(0, 0)] * (a.ndim - 2) + [(0, STENCIL_SLOTS - stencil.size), (0, 0)])

    return jm.Stencil(index=pad(stencil.index), weight=pad(stencil.weight), gradient=pad(stencil.gradient),
                      offset=pad(stencil.offset))


class Dense:
    def __init__(self, S, M):
        self.S, self.M = S, np.diag(M)
        self.m_vec = S.T @ M  # lumped mass, m = S^T M 1
        self.m = np.diag(self.m_vec)
        self.m_inv = np.diag(1.0 / self.m_vec)
        self.SpS = self.m_inv @ S.T @ self.M @ S  # S+S, S+ = m^{-1} S^T M (000 eq. 1.10)
        self.m_tilde = S.T @ self.M @ S  # 003 eq. (2.2)

    def m_tilde_k_inv(self, k):
        """m~_k^{-1} = (sum_l C_kl (S+S)^{l-1}) m^{-1}, C_kl = (-1)^{l+1} C(k, l) (003 eqs. 1.23, 1.30);
        m~_0^{-1} = 0."""
        n = self.SpS.shape[0]
        series = sum(((-1) ** (j + 1) * math.comb(k, j)) * np.linalg.matrix_power(self.SpS, j - 1)
                     for j in range(1, k + 1)) if k > 0 else np.zeros((n, n))
        return series @ self.m_inv


def fields(transfer, d, conditions, rng):
    """A random updated momentum p+ (003 eq. 2.12) as w = p+/m, and u = the lumped method's velocity
    (the conditions imposed on it, as the grid solve does)."""
    constraint = build_constraint(GRID, conditions, jnp.float64)
    w = rng.normal(size=(GRID.num_nodes, 1))
    u = np.asarray(constraint.apply(jnp.asarray(w)))
    mask = np.asarray(constraint.mask)[:, 0]
    g = np.asarray(constraint.value)[:, 0]
    return constraint, w, u, mask, g


# ------------------------------------------------------------------ the seed's equations, dense
def dense_modes(d, k, w, u, mask, g):
    """Each mode as its seed equation, with dense matrices (column vectors, one component)."""
    p_plus = d.m @ w  # p+ = p + f dt before the conditions
    inv_k = d.m_tilde_k_inv(k)
    v_plus = inv_k @ p_plus  # 003 eq. (2.48)
    B = np.flatnonzero(mask)
    out = {}
    # lumped method, 003 eq. (2.52): Dp_j = (m_j v^(b) - p+_j) on the condition's node
    f_L_dt = np.zeros_like(w)
    f_L_dt[B] = d.m_vec[B, None] * g[B, None] - p_plus[B]
    out["lumped"] = inv_k @ (p_plus + f_L_dt)
    # unlumped #1, 003 eqs. (2.54)-(2.55): f^(#1) dt = m~ m^{-1} f^(L) dt
    out["unlumped1"] = inv_k @ (p_plus + d.m_tilde @ d.m_inv @ f_L_dt)
    # unlumped #2, 003 eq. (2.56): Dv_i = v^(b) - (m~_k^{-1} p+)_i on j_b; p^(BC) = m~_k Dv; v = m~_k^{-1}(p+ + p^(BC))
    dv2 = np.zeros_like(w)
    dv2[B] = g[B, None] - v_plus[B]
    m_k = np.linalg.inv(inv_k)  # the approximate full mass matrix m~_k itself
    out["unlumped2"] = inv_k @ (p_plus + m_k @ dv2)
    out["unlumped2_mtilde"] = inv_k @ (p_plus + d.m_tilde @ dv2)  # m~ in place of m~_k
    # collection, option 2: (m~_k^{-1})_ij -> delta_ij / m_i to find the force from eq. (2.47)
    out["partial"] = inv_k @ (p_plus + d.m @ dv2)
    # collection, option 1: columns m^(j) = m~_k^{-1} e_j (003 eq. 1.71), the n_BC x n_BC system of eq. (2.47)
    columns = np.stack([inv_k @ np.eye(len(w))[:, j] for j in B], axis=1)  # (n, n_BC)
    f_B = np.linalg.solve(columns[B], g[B] - v_plus[B, 0])  # force x dt on the condition nodes
    out["collection"] = v_plus + columns @ f_B[:, None]
    # 003 §1.5: p^(0) = m v^(L0) before the conditions, Dp^(L) = m Dv^(L) the lumped change (eq. 1.53)
    dv_L = u - w
    dp_L = d.m @ dv_L
    out["series_start"] = inv_k @ p_plus + (inv_k - k * d.m_inv) @ dp_L  # 003 eq. (1.56)
    inv_k1 = d.m_tilde_k_inv(k - 1)
    out["pinv_start"] = inv_k @ (p_plus + dp_L) - (inv_k1 + d.m_inv) @ dp_L  # 003 eq. (1.69)
    out["_eq_1_62"] = inv_k @ p_plus - inv_k1 @ d.m_tilde @ dv_L  # 003 eq. (1.62)
    out["_eq_1_64_as_printed"] = inv_k @ p_plus - inv_k1 @ d.SpS @ dp_L  # 003 eq. (1.64), S+S as written
    return out


# ------------------------------------------------------------------ jitted implementation
@eqx.filter_jit
def library_modes(u, w, transfer, constraint):
    """mass_matrix_series for every mode and (order, form) of SWEEP: one compilation serves the module."""
    return {(mode, k): mass_matrix_series(u, k, transfer, constraint, mode, form, free=w)
            for mode in MODES for k, form in SWEEP}


def rel_err(actual, expected):
    actual, expected = np.asarray(actual), np.asarray(expected)
    return float(np.max(np.abs(actual - expected)) / np.max(np.abs(expected)))


# ======================================================================== the matrix forms
@pytest.mark.slow
@pytest.mark.parametrize("shape", ["linear", "quadratic"])
@pytest.mark.parametrize("case", list(CONDITIONS))
def test_modes_match_seed_equations(shape, case):
    """Every mode, orders 1-3 (order 2 in the Neumann form, the others binomial), equals its 003
    equation evaluated with dense matrices (module docstring) to 1e-12.  v = 0 at x- (one
    condition) and v = 0.7 at x- with v = 0 at x+ (two, one inhomogeneous); linear shapes and
    quadratic B-splines (a wider m~)."""
    transfer, d, rng = problem(shape, seed=1)
    constraint, w, u, mask, g = fields(transfer, d, CONDITIONS[case], rng)
    got = library_modes(jnp.asarray(u), jnp.asarray(w), transfer, constraint)
    for k, form in SWEEP:
        expected = dense_modes(d, k, w, u, mask, g)
        for mode in MODES:
            err = rel_err(got[mode, k], expected[mode])
            assert err < TOL, f"{shape} {case} {form} k={k} {mode}: relative error {err:.2e}"


def test_pseudo_inverse_route_and_a_transposition_in_eq_1_64():
    """003 eqs. (1.62) and (1.69) agree (dense, 1e-12), but eq. (1.64) as printed, with
    m~_{k-1}^{-1} S+S Dp^(L), does not: S^T M S m^{-1} of eq. (1.63) is m~ m^{-1} = (S+S)^T, not
    S+S (they agree only for uniform nodal masses).  (1.65)-(1.68) hold with (S+S)^T."""
    transfer, d, rng = problem(seed=3)
    _, w, u, mask, g = fields(transfer, d, CONDITIONS["two"], rng)
    for k in (2, 3, 4):
        out = dense_modes(d, k, w, u, mask, g)
        assert rel_err(out["pinv_start"], out["_eq_1_62"]) < TOL, k
        gap = rel_err(out["_eq_1_64_as_printed"], out["pinv_start"])
        assert gap > 1e-3, f"k={k}: eq. (1.64) as printed differs from (1.62) by only {gap:.1e}"
        # eq. (1.67) with (S+S)^T: m~_k^{-1} - m~_{k-1}^{-1} = m^{-1} - m~_{k-1}^{-1} (S+S)^T
        lhs = d.m_tilde_k_inv(k) - d.m_tilde_k_inv(k - 1)
        assert rel_err(lhs, d.m_inv - d.m_tilde_k_inv(k - 1) @ d.SpS.T) < TOL
        assert rel_err(lhs, np.linalg.matrix_power(np.eye(len(w)) - d.SpS, k - 1) @ d.m_inv) < TOL  # (1.65)


def test_collection_and_iterates_share_the_constrained_limit():
    """As k -> infinity the collection solve (option 1: m~ v = p+ + f, f on the conditions' nodes,
    v_b = v^(b)) and the constrained system of 003 eqs. (1.49)-(1.50) (``iterates``) reach the same
    velocities, m~_ff v_f = p_f - m~_fb g_b: dense, k = 400 in the Neumann form (003 eq. 1.13)."""
    transfer, d, rng = problem(seed=8)
    _, w, u, mask, g = fields(transfer, d, CONDITIONS["two"], rng)
    A = np.eye(len(w)) - d.SpS
    term, series = np.eye(len(w)), np.zeros_like(A)
    for _ in range(400):
        series, term = series + term, A @ term
    inv_far = series @ d.m_inv  # m~_400^{-1}
    assert rel_err(inv_far, np.linalg.inv(d.m_tilde)) < 1e-10
    p_plus, B, F = d.m @ w, np.flatnonzero(mask), np.flatnonzero(~mask)
    v_plus = inv_far @ p_plus
    f_B = np.linalg.solve(inv_far[np.ix_(B, B)], g[B] - v_plus[B, 0])
    collection = v_plus[:, 0] + inv_far[:, B] @ f_B
    constrained = g.copy()
    mt = d.m_tilde
    constrained[F] = np.linalg.solve(mt[np.ix_(F, F)], p_plus[F, 0] - mt[np.ix_(F, B)] @ g[B])  # 003 eq. (1.49)
    assert rel_err(collection, constrained) < 1e-10


# ============================================================ which modes meet the conditions
def test_conditions_met_exactly_only_by_velocity_and_collection_modes():
    """On the constrained nodes ``unlumped2`` (= the velocity method, 003's remark) and
    ``collection`` (option 1 solves eq. 2.47 for all conditions at once) give exactly v^(b);
    ``unlumped1``, ``unlumped2_mtilde``, ``partial``, ``series_start`` and ``pinv_start`` only
    approximate it at k >= 2 (003's remarks).  At k = 1 (m~_1^{-1} = m^{-1}) ``partial`` is exact
    too; ``unlumped1`` and ``unlumped2_mtilde`` are not (003: m~ would have to become m), and the
    §1.5 routes return the uncorrected p+/m (their leading term k S+ V keeps v^(L0), 003 eqs. 1.52
    and 1.59)."""
    transfer, d, rng = problem(seed=4)
    constraint, w, u, mask, g = fields(transfer, d, CONDITIONS["two"], rng)
    got = library_modes(jnp.asarray(u), jnp.asarray(w), transfer, constraint)
    miss = {}
    for (mode, k), v in got.items():
        miss[mode, k] = float(np.max(np.abs(np.asarray(v)[mask, 0] - g[mask])))
    for k in ORDERS:
        assert miss["unlumped2", k] < 1e-13 and miss["collection", k] < 1e-13, k
    for mode in ("unlumped1", "unlumped2_mtilde", "partial", "series_start", "pinv_start"):
        assert min(miss[mode, k] for k in ORDERS[1:]) > 1e-3, (mode, [miss[mode, k] for k in ORDERS])
    for mode in ("unlumped2", "partial", "collection"):
        assert miss[mode, 1] < 1e-13, mode
    for mode in ("series_start", "pinv_start"):
        np.testing.assert_allclose(np.asarray(got[mode, 1]), w, rtol=0, atol=1e-15)
    print("\nmax |v_b - v^(b)| on the two conditions, k = 1..3:")
    for mode in MODES:
        print(f"  {mode:18s}" + "".join(f" {miss[mode, k]:.2e}" for k in ORDERS))


def test_unlumped1_boundary_momentum_total_is_the_lumped_reaction():
    """Sum over nodes of f^(#1) dt = m~ m^{-1} f^(L) dt equals that of f^(L) dt (column sums of m~
    are m: partition of unity), so jm.Reaction's total (the lumped reaction R dt = m v~ - (p + f dt))
    is also the total boundary force of ``unlumped1``; its distribution spreads to the neighbours."""
    transfer, d, rng = problem(seed=5)
    _, w, u, mask, _ = fields(transfer, d, CONDITIONS["one"], rng)
    f_L_dt = d.m @ (u - w)
    f_1_dt = d.m_tilde @ d.m_inv @ f_L_dt  # 003 eq. (2.54)
    assert abs(f_1_dt.sum() - f_L_dt.sum()) < 1e-13 * abs(f_L_dt.sum())
    assert np.count_nonzero(np.abs(f_1_dt[:, 0]) > 1e-14) == 2  # the fixed node and its neighbour (linear)


# ===================================================================== gradient and input errors
def collection_objective(velocity, w, transfer, weights):
    constraint = build_constraint(GRID, [jm.Prescribed("x-", velocity), jm.Fixed("x+")], jnp.float64)
    u = constraint.apply(w)
    return jnp.sum(weights * mass_matrix_series(u, 2, transfer, constraint, "collection", free=w))


@eqx.filter_jit
def collection_derivative(velocity, w, transfer, weights):
    """(objective, d objective / d velocity) by forward-mode differentiation."""
    return jax.jvp(lambda v: collection_objective(v, w, transfer, weights), (velocity,), (jnp.ones_like(velocity),))


def test_collection_gradient_matches_central_differences():
    """d/dv^(b) of a weighted sum of the ``collection`` velocities (k = 2, through the
    conjugate-gradient ``fori_loop``; forward mode) against central differences, float64."""
    transfer, d, rng = problem(seed=6)
    w = jnp.asarray(rng.normal(size=(GRID.num_nodes, 1)))
    weights = jnp.asarray(rng.normal(size=(GRID.num_nodes, 1)))
    _, grad = collection_derivative(jnp.asarray(0.7), w, transfer, weights)
    eps = 1e-5
    fd = (collection_derivative(jnp.asarray(0.7 + eps), w, transfer, weights)[0]
          - collection_derivative(jnp.asarray(0.7 - eps), w, transfer, weights)[0]) / (2 * eps)
    assert abs(float(grad)) > 1e-3  # the condition's value reaches the result
    assert abs(float(grad) - float(fd)) < 1e-8 * max(1.0, abs(float(fd)))


def test_modes_need_the_velocity_before_the_conditions():
    """The variants read p+/m before the conditions; without it a clear InputError, and walls
    (one-sided) are refused by the force-solving modes; an unknown mode lists the modes."""
    transfer, d, rng = problem(seed=7)
    constraint = build_constraint(GRID, CONDITIONS["one"], jnp.float64)
    u = jnp.zeros((GRID.num_nodes, 1))
    with pytest.raises(jm.InputError, match="before the velocity conditions"):
        mass_matrix_series(u, 2, transfer, constraint, "unlumped1")
    walls = build_constraint(GRID, [jm.Wall("x-")], jnp.float64)
    with pytest.raises(jm.InputError, match="two-sided"):
        mass_matrix_series(u, 2, transfer, walls, "collection", free=u)
    with pytest.raises(jm.InputError, match="unlumped1"):
        jm.FMPM(order=2, boundary="unlumped")


@eqx.filter_jit
def _bar_step(sim, state, dt):
    return sim.step(state, dt)


@pytest.mark.slow
def test_fmpm_runs_each_mode_from_the_grid_solve_velocity_before_the_conditions():
    """Through ``jm.FMPM(boundary=mode)`` the grid solve hands the series p+/m before the velocity
    conditions (``v_tilde_unconstrained``), so one step equals the update written out here from
    ``mass_matrix_series(..., free=(p + f dt)/m)`` (003 eqs. 2.13, 2.17) to round-off, on ``bar``
    (fixed at x = 0) after 20 steps of motion; and XPIC, USF and MUSL refuse the modes clearly."""
    from jaxmpm.model.step import grid_solve, p2g
    from jaxmpm.transfer.operators import safe_divide

    base = jm.scene("bar", scheme=jm.FMPM(order=2), cells=8)
    state = base.state
    for _ in range(20):
        state = _bar_step(base.sim, state, base.dt)
    dt = jnp.asarray(base.dt)
    for mode in ("unlumped1", "unlumped2", "collection"):
        sim = eqx.tree_at(lambda s: s.scheme, base.sim, jm.FMPM(order=2, boundary=mode))
        new = _bar_step(sim, state, dt)
        fields = p2g(sim, state)
        constraint = sim.constraint(state.x.dtype)
        grid = grid_solve(fields, fields.force, dt, constraint)
        m = fields.transfer.nodal_mass
        free = safe_divide(fields.momentum, m) + safe_divide(fields.force, m) * dt
        v_plus = mass_matrix_series(grid.v_tilde, 2, fields.transfer, constraint, mode, "binomial", free=free)
        V = fields.transfer.gather(v_plus)  # beta = 0, no damping: V^{n+1} = S v+  (003 eq. 2.17)
        X = state.x + 0.5 * (V + state.v) * dt
        np.testing.assert_allclose(np.asarray(new.v), np.asarray(V), rtol=0, atol=1e-13)
        np.testing.assert_allclose(np.asarray(new.x), np.asarray(X), rtol=0, atol=1e-13)
    with pytest.raises(jm.InputError, match="FMPM"):
        jm.XPIC(order=2, boundary="unlumped1")
    for update in ("USF", "MUSL"):
        sim = jm.scene("bar", scheme=jm.FMPM(order=2, boundary="unlumped2"), cells=8, update=update).sim
        with pytest.raises(jm.InputError, match="USL"):
            sim.step(state, dt)
