"""The remaining particle updates of 000 ch. 2 / 003 §2.3 against their matrix forms (issue 16, item 6).

Dense NumPy matrices, built independently of the library's transfers (S from the stencil's
weights; m = S^T M 1, S+ = m^{-1} S^T M, 000 eqs. 1.9-1.10; P_m = I - (I - S S+)^m, 000 eq. 3.12):

* every ``position=`` option of the XPIC family (FLIP, PIC, blend, XPIC(m)) with damping
  A_damp = alpha_g S v + alpha_p V^n (000 eq. 2.77), each against its own seed equation:
  "V" 000 eqs. (2.26)-(2.27) (V = V^n with a general P), "Sv_first_order" 000 eq. (2.34) with
  damping and P != I, "PV_first_order" 000 eq. (2.40), "V_end" 000 eq. (2.55) (Modified FLIP
  #2) and the Stomakhin blend of 003 §2.3.4, "second_order" 000 eq. (2.71) (second-order PIC);
  the effective velocities the seeds reverse-engineer (000 eqs. 2.56, 2.72) through eq. (2.8)
* order 0: XPIC(0) = FMPM(0) = FLIP (003 Table 2.1), bitwise per update, damped and undamped
* RPIC (002 §4): P2G and G2P against 002 eqs. (1)-(2) written densely; rigid velocity fields
  preserved (002 prop. 4.1), linear and angular momentum conserved by both transfers (002 props.
  4.2-4.5), in 2D and 3D; and a force-free 2D run that keeps both momenta to round-off
* USAVG-/USAVG+ (003 §2.2, 000 §4.3): one step against a NumPy evaluation of the algorithm
  (strain update before the forces and after the particle update, each over dt/2)
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest
from cases import dense_weights, particle_major

import jaxmpm as jm
from jaxmpm.core.fields import GridSolution
from jaxmpm.physics.conditions import Constraint
from jaxmpm.schemes import NO_DAMPING
from jaxmpm.schemes.rpic import rigid_inertia
from jaxmpm.transfer.operators import Transfer

TOL = 1e-12
DT = 0.01
GRID_1D = jm.Grid((0.0,), (1.0,), (8,))
N_1D = 24


def rel_err(actual, expected):
    actual, expected = np.asarray(actual), np.asarray(expected)
    return float(np.max(np.abs(actual - expected)) / np.max(np.abs(expected)))


def no_constraint(grid):
    shape = (grid.num_nodes, grid.dim)
    return Constraint(mask=jnp.zeros(shape, bool), value=jnp.zeros(shape))


@eqx.filter_jit
def build_stencil(shape, grid, x):
    return shape.stencil(grid, x)


@eqx.filter_jit
def scheme_updates(schemes, V, X, transfer, constraint, solution, damping, dt):
    """Every scheme's particle update in one compiled program."""
    return [s.update(V, X, transfer, constraint, solution, damping, dt) for s in schemes]


class Dense1D:
    """A 1D quadratic-B-spline problem: one jittered particle per slot (every node has mass),
    random masses and velocities, and its dense S, m, S+ (000 eqs. 1.9-1.10)."""

    def __init__(self, seed=0):
        rng = np.random.default_rng(seed)
        shape = jm.QuadraticBSpline()
        lo, hi = 0.5 / 8 + 1e-3, 1.0 - 0.5 / 8 - 1e-3
        self.x = (lo + (hi - lo) * (np.arange(N_1D) + rng.uniform(0.05, 0.95, N_1D)) / N_1D)[:, None]
        self.M = rng.uniform(0.5, 2.0, N_1D)
        self.V = rng.normal(size=(N_1D, 1))
        stencil = build_stencil(shape, GRID_1D, jnp.asarray(self.x))
        self.transfer = Transfer.build(stencil, jnp.asarray(self.M), GRID_1D.num_nodes)
        self.S, _ = dense_weights(stencil, GRID_1D.num_nodes)
        assert np.all(self.S.T @ self.M > 0)  # every node has mass
        self.m = self.S.T @ self.M
        self.S_plus = (self.S.T * self.M) / self.m[:, None]
        self.a = rng.normal(size=(GRID_1D.num_nodes, 1))  # a nodal acceleration

    def projector(self, m):
        """P_m = I - (I - S S+)^m (000 eq. 3.12); P_0 = I by 003 Table 2.1 (XPIC(0) = FLIP)."""
        eye = np.eye(N_1D)
        if m == 0:
            return eye
        return eye - np.linalg.matrix_power(eye - self.S @ self.S_plus, m)

    def solution(self):
        v = self.S_plus @ self.V  # 000 eq. (2.1)
        return GridSolution(v=jnp.asarray(v), a=jnp.asarray(self.a), v_tilde=jnp.asarray(v + DT * self.a))


DENSE = Dense1D()
ALPHA_G, ALPHA_P = 3.0, 2.0  # 1/time: A_damp dt ~ 5% of V
POSITIONS = ("Sv", "PV", "V", "first_order", "Sv_first_order", "PV_first_order", "V_end", "second_order")
# the position update reads the order only through the blend's P V: every option at m = 1 (P = S S+),
# the new options with P != I at m = 3, and m = 0 (P = I) -- fewer programs to compile
CASES_MP = ([(1, pos) for pos in POSITIONS] + [(3, pos) for pos in ("V", "Sv_first_order", "PV_first_order", "V_end")]
            + [(0, pos) for pos in ("V", "Sv_first_order")])
BETA = 0.3


def expected_update(d, order, beta, position, alpha_g, alpha_p):
    """V^{n+1}, X^{n+1} of the seed equations, dense."""
    V, X, dt = d.V, d.x, DT
    v = d.S_plus @ V
    Sv, Sa, Sv_tilde = d.S @ v, d.S @ d.a, d.S @ (v + dt * d.a)
    if order == 0:
        beta = 1.0  # P = I makes beta irrelevant (003 Table 2.1: XPIC(0) = FLIP)
    PmV = d.projector(order) @ V
    A_damp = alpha_g * Sv + alpha_p * V  # 000 eq. (2.77)
    P_blend_V = beta * V + (1 - beta) * PmV  # 000 eq. (2.73): the blend's projection
    V_new = P_blend_V + (Sa - A_damp) * dt  # 000 eqs. (2.20), (3.28)
    dV = V_new - V
    PV = beta * Sv + (1 - beta) * PmV  # 000 eq. (2.74), the VV = P V branch
    X_new = {
        "Sv": X + (Sv + dV / 2) * dt,  # 000 eq. (2.29)
        "PV": X + (PV + dV / 2) * dt,  # 000 eq. (2.74)
        "V": X + (V + V_new) / 2 * dt,  # 000 eq. (2.27)
        "first_order": X + Sv_tilde * dt,  # 000 eq. (2.52)
        "Sv_first_order": X + (Sv_tilde - V / 2 + P_blend_V / 2 - A_damp * dt / 2) * dt,  # 000 eq. (2.34)
        "PV_first_order": X + (PV + dV / 2 + Sa * dt / 2) * dt,  # 000 eq. (2.40)
        "V_end": X + V_new * dt,  # 000 eq. (2.55)
        "second_order": X + Sv * dt + (Sa - A_damp) * dt**2 / 2,  # 000 eq. (2.71), damped
    }[position]
    return V_new, X_new


@pytest.mark.slow
@pytest.mark.parametrize("damped", [False, True], ids=["undamped", "damped"])
def test_position_updates_match_their_seed_equations(damped):
    """Each ``position=`` option with beta = 0.3 (XPIC(1): the PIC/FLIP blend; XPIC(3) and XPIC(0)
    for the options that read P), with and without grid and particle damping, against its seed
    equation above, to 1e-12; the velocity update is 000 eq. (3.28) in every case.  The dissipated
    energy is 000 eq. (2.43) of the same update."""
    d = DENSE
    alpha = (ALPHA_G, ALPHA_P) if damped else (0.0, 0.0)
    schemes = [jm.XPIC(order=m, beta=BETA, position=pos) for m, pos in CASES_MP]
    updates = scheme_updates(schemes, jnp.asarray(d.V), jnp.asarray(d.x), d.transfer, no_constraint(GRID_1D),
                             d.solution(), jm.Damping(*alpha), jnp.asarray(DT))
    Sv = d.S @ (d.S_plus @ d.V)
    Sa = d.S @ d.a
    for scheme, upd in zip(schemes, updates):
        V_new, X_new = expected_update(d, scheme.order, BETA, scheme.position, *alpha)
        what = (scheme.order, scheme.position, damped)
        assert rel_err(upd.velocity, V_new) < TOL, what
        assert rel_err(upd.position - d.x, X_new - d.x) < TOL, what
        # 000 eq. (2.43) with A dt = dV and VV dt = dX - dV dt/2 (000 eqs. 2.7-2.8)
        dV, dX = V_new - d.V, X_new - d.x
        flip = (Sa * DT) * (Sv + Sa * DT / 2)
        diss = np.sum(d.M[:, None] * (flip - dV * dX / DT))
        scale = np.sum(d.M[:, None] * (np.abs(flip) + np.abs(dV * dX) / DT))
        assert abs(float(upd.dissipated) - diss) <= TOL * scale, what


def test_reverse_engineered_effective_velocities():
    """The effective velocities the seeds derive, recovered from the updates by 000 eq. (2.8),
    VV = dX/dt - dV/2 (undamped): Modified FLIP #2 has VV = V^n + S a dt/2 (000 eq. 2.56),
    second-order PIC VV = (S v + V^n)/2 (000 eq. 2.72), "first_order" FLIP VV = S v + S a dt/2
    (000 eq. 2.53), ``position="V"`` VV = V^n (000 §2.3.1) for XPIC(3); and the Stomakhin blend
    (003 §2.3.4): V^{n+1} = alpha (V^n + S m^-1 f dt) + (1 - alpha) S m^-1 p+, X += V^{n+1} dt."""
    d = DENSE
    alpha = 0.7
    # the schemes of CASES_MP with other betas: the program compiled above serves (beta is a leaf)
    by_case = {}
    for betas in ({(1, "V_end"): 1.0, (1, "second_order"): 0.0, (1, "first_order"): 1.0}, {(1, "V_end"): alpha}):
        schemes = [jm.XPIC(order=m, beta=betas.get((m, pos), BETA), position=pos) for m, pos in CASES_MP]
        updates = scheme_updates(schemes, jnp.asarray(d.V), jnp.asarray(d.x), d.transfer, no_constraint(GRID_1D),
                                 d.solution(), jm.Damping(), jnp.asarray(DT))
        by_case.update({(case, betas[case]): upd for case, upd in zip(CASES_MP, updates) if case in betas})
    flip2, pic2, flip1 = by_case[(1, "V_end"), 1.0], by_case[(1, "second_order"), 0.0], by_case[(1, "first_order"), 1.0]
    stomakhin = by_case[(1, "V_end"), alpha]
    xpic_v = updates[CASES_MP.index((3, "V"))]
    v = d.S_plus @ d.V
    Sv, Sa, Sv_tilde = d.S @ v, d.S @ d.a, d.S @ (v + DT * d.a)

    def effective(upd):  # 000 eq. (2.8)
        return (np.asarray(upd.position) - d.x) / DT - (np.asarray(upd.velocity) - d.V) / 2

    assert rel_err(effective(flip2), d.V + Sa * DT / 2) < TOL  # 000 eq. (2.56)
    assert rel_err(effective(pic2), (Sv + d.V) / 2) < TOL  # 000 eq. (2.72)
    assert rel_err(effective(flip1), Sv + Sa * DT / 2) < TOL  # 000 eq. (2.53)
    assert rel_err(effective(xpic_v), d.V) < TOL  # 000 §2.3.1
    V_st = alpha * (d.V + Sa * DT) + (1 - alpha) * Sv_tilde  # 003 §2.3.4
    assert rel_err(stomakhin.velocity, V_st) < TOL
    assert rel_err(stomakhin.position - d.x, V_st * DT) < TOL


def test_order_zero_is_flip_per_update():
    """003 Table 2.1: FMPM(0)/XPIC(0) is FLIP with the second-order position update.  On the
    dense problem, damped, XPIC(0, beta, position) equals FLIP(position) and FMPM(0) equals
    FLIP() bitwise (same arithmetic), strain velocity included; and the update is the table's
    dV = a dt, V += dV, X += (S v~ - dV/2) dt when undamped (round-off)."""
    d = DENSE
    schemes = [jm.FLIP(), jm.XPIC(order=0, beta=0.4), jm.FMPM(order=0, beta=0.2),
               jm.FLIP(position="V_end"), jm.XPIC(order=0, beta=0.4, position="V_end")]
    for damping in (jm.Damping(ALPHA_G, ALPHA_P), jm.Damping()):
        flip, xpic0, fmpm0, flip_end, xpic0_end = scheme_updates(
            schemes, jnp.asarray(d.V), jnp.asarray(d.x), d.transfer, no_constraint(GRID_1D), d.solution(), damping,
            jnp.asarray(DT))
        for other in (xpic0, fmpm0):
            for field in ("velocity", "position", "strain_velocity", "dissipated"):
                assert np.array_equal(np.asarray(getattr(other, field)), np.asarray(getattr(flip, field))), field
        assert np.array_equal(np.asarray(xpic0_end.position), np.asarray(flip_end.position))
    v = d.S_plus @ d.V
    dV = d.S @ d.a * DT  # 003 Table 2.1, column FMPM(0)/XPIC(0)
    assert rel_err(xpic0.velocity, d.V + dV) < TOL
    assert rel_err(xpic0.position - d.x, (d.S @ (v + DT * d.a) - dV / 2) * DT) < TOL
    strain = jm.FMPM(order=0).strain_grid_velocity(jnp.asarray(v), d.transfer, no_constraint(GRID_1D))
    assert np.array_equal(np.asarray(strain), v)  # lumped, as FLIP's (USF, MUSL)


# ====================================================================================== RPIC (002 §4)
def cross_matrix(r):
    """r^* with r^* u = r x u (002 §4), for r (3,)."""
    return np.array([[0.0, -r[2], r[1]], [r[2], 0.0, -r[0]], [-r[1], r[0], 0.0]])


def embed(u):
    """(..., D) -> (..., 3), zero-padded (2D vectors in the xy-plane)."""
    return np.concatenate([u, np.zeros(u.shape[:-1] + (3 - u.shape[-1],))], axis=-1)


RPIC_GRIDS = {2: jm.Grid((-1.0, 0.5), (3.0, 2.5), (8, 5)), 3: jm.Grid((-1.0, 0.5, 2.0), (2.0, 2.5, 4.4), (6, 5, 6))}
RPIC_CASES = [pytest.param("quadratic", 2, id="quadratic-2d"), pytest.param("quadratic", 3, id="quadratic-3d")]
RPIC_SHAPES = {"quadratic": jm.QuadraticBSpline()}
N_RPIC = 16


@eqx.filter_jit
def rpic_transfers(scheme, stencil, state, v_tilde, dt, num_nodes):
    """RPIC's P2G of ``state`` (nodal momentum, mass) and its G2P of ``v_tilde`` (V, X, L)."""
    transfer = Transfer.build(stencil, state.mass, num_nodes)
    p = scheme.momentum(transfer, state)
    sol = GridSolution(v=v_tilde, a=jnp.zeros_like(v_tilde), v_tilde=v_tilde)
    upd = scheme.update(state.v, state.x, transfer, no_constraint_n(num_nodes, state.x.shape[1]), sol, NO_DAMPING, dt)
    L = scheme.next_state(state, upd, transfer, sol)
    K = rigid_inertia(stencil, state.mass)
    return p, transfer.nodal_mass, upd.velocity, upd.position, L, K


def no_constraint_n(num_nodes, dim):
    shape = (num_nodes, dim)
    return Constraint(mask=jnp.zeros(shape, bool), value=jnp.zeros(shape))


def rpic_problem(name, dim, seed=0):
    rng = np.random.default_rng(seed)
    grid, shape = RPIC_GRIDS[dim], RPIC_SHAPES[name]
    cells = np.array(grid.cells, float)
    m = float(shape.margin)
    xi = m + 0.01 + (cells - 2 * m - 0.02) * rng.random((N_RPIC, dim))
    x = np.array(grid.lower) + xi * np.array(grid.spacing)
    mass = rng.uniform(0.5, 2.0, N_RPIC)
    V = rng.normal(size=(N_RPIC, dim))
    L = rng.normal(size=(N_RPIC, dim * (dim - 1) // 2))
    state = jm.State(x=jnp.asarray(x), v=jnp.asarray(V), F=jnp.broadcast_to(jnp.eye(dim), (N_RPIC, dim, dim)),
                     mass=jnp.asarray(mass), volume0=jnp.asarray(mass), time=jnp.zeros(()),
                     step=jnp.zeros((), jnp.int32), dissipated=jnp.zeros(()), scheme_state=jnp.asarray(L))
    stencil = build_stencil(shape, grid, jnp.asarray(x))
    st = particle_major(stencil)
    node_x = np.zeros((grid.num_nodes, dim))  # x_i = X_p + (x_i - X_p) on every stencil node; 0 elsewhere
    for q in range(N_RPIC):
        node_x[st.index[q]] = x[q] + st.offset[q]
    return grid, stencil, state, x, mass, V, L, rng, node_x


def dense_rpic(stencil, num_nodes, x, mass, V, L, v_tilde):
    """002 eqs. (1)-(2) written per particle and node with 3-vectors (NumPy): K_p, the nodal
    momentum m_i v_i, and the G2P's V_p, L_p."""
    st = particle_major(stencil)
    n_p, k = st.index.shape
    dim = x.shape[1]
    p = np.zeros((num_nodes, dim))
    V_new = np.zeros((n_p, dim))
    L_new = np.zeros((n_p, 3))
    K = np.zeros((n_p, 3, 3))
    for q in range(n_p):
        r3 = embed(st.offset[q])  # x_i - X_p, (K, 3)
        K[q] = sum(st.weight[q, j] * mass[q] * cross_matrix(r3[j]) @ cross_matrix(r3[j]).T for j in range(k))
    L3 = embed(L) if dim == 3 else np.concatenate([np.zeros((n_p, 2)), L], axis=1)
    for q in range(n_p):
        sub = [0, 1, 2] if dim == 3 else [2]
        omega = np.zeros(3)
        omega[sub] = np.linalg.solve(K[q][np.ix_(sub, sub)], L3[q, sub])  # K_p^-1 L_p
        r3 = embed(st.offset[q])
        for j in range(k):
            w, i = st.weight[q, j], st.index[q, j]
            p[i] += w * mass[q] * (V[q] + np.cross(omega, r3[j])[:dim])  # 002 eq. (1)
            V_new[q] += w * v_tilde[i]  # 002 eq. (2)
            L_new[q] += w * np.cross(r3[j], mass[q] * embed(v_tilde[i]))  # 002 eq. (2)
    sub = slice(0, 3) if dim == 3 else slice(2, 3)
    return p, V_new, L_new[:, sub], K


@pytest.mark.slow
@pytest.mark.parametrize("name, dim", RPIC_CASES)
def test_rpic_transfers_match_002_eqs_1_2(name, dim):
    """RPIC's P2G (002 eq. 1: K_p, m_i v_i = sum_p S_pi M_p (V_p + (K_p^-1 L_p) x (x_i - X_p))) and
    G2P (002 eq. 2: V_p = sum_i S_pi v~_i, L_p = sum_i S_pi (x_i - X_p) x M_p v~_i, X_p += V_p dt)
    against a per-particle NumPy evaluation with 3-vectors (2D in the xy-plane), to 1e-12."""
    grid, stencil, state, x, mass, V, L, rng, _ = rpic_problem(name, dim)
    v_tilde = rng.normal(size=(grid.num_nodes, dim))
    p, m, V_new, X_new, L_new, K = rpic_transfers(jm.RPIC(), stencil, state, jnp.asarray(v_tilde), jnp.asarray(DT),
                                                  grid.num_nodes)
    p_ref, V_ref, L_ref, K_ref = dense_rpic(stencil, grid.num_nodes, x, mass, V, L, v_tilde)
    sub = slice(0, 3) if dim == 3 else slice(2, 3)
    assert rel_err(K, K_ref[:, sub, sub]) < TOL
    assert rel_err(p, p_ref) < TOL
    assert rel_err(V_new, V_ref) < TOL
    assert rel_err(X_new - x, V_ref * DT) < TOL
    assert rel_err(L_new, L_ref) < TOL


@pytest.mark.parametrize("name, dim", RPIC_CASES)
def test_rpic_rigid_preservation_and_momenta(name, dim):
    """002 prop. 4.1: at dt = 0, G2P then P2G of a rigid grid field v + omega x x_i gives it back
    on every node with mass.  002 props. 4.2 and 4.4: P2G conserves sum_p M_p V_p and
    sum_p (X_p x M_p V_p + L_p) (002 def. 4.1) = sum_i x_i x m_i v_i.  002 props. 4.3 and 4.5:
    G2P conserves them, the grid's angular momentum on the moved nodes x_i + dt v~_i (002 def.
    3.4).  To 1e-12 of the sums of magnitudes."""
    grid, stencil, state, x, mass, V, L, rng, node_x = rpic_problem(name, dim, seed=1)
    scheme = jm.RPIC()
    # prop. 4.1 (dt = 0)
    v0, omega = rng.normal(size=dim), rng.normal(size=3 if dim == 3 else 1)
    omega3 = omega if dim == 3 else np.array([0.0, 0.0, omega[0]])
    rigid = v0 + np.cross(omega3, embed(node_x))[:, :dim]
    _, m, V1, X1, L1, _ = rpic_transfers(scheme, stencil, state, jnp.asarray(rigid), jnp.asarray(0.0), grid.num_nodes)
    assert np.array_equal(np.asarray(X1), x)
    back = eqx.tree_at(lambda s: (s.v, s.scheme_state), state, (V1, L1))
    p_back, m, *_ = rpic_transfers(scheme, stencil, back, jnp.asarray(rigid), jnp.asarray(0.0), grid.num_nodes)
    has_mass = np.asarray(m) > 0
    v_back = np.asarray(p_back)[has_mass] / np.asarray(m)[has_mass, None]
    assert rel_err(v_back, rigid[has_mass]) < TOL

    # props. 4.2, 4.4: P2G
    def cross_z(a, b):
        c = np.cross(embed(a), embed(b))
        return c if dim == 3 else c[..., 2:]

    p, m, *_ = rpic_transfers(scheme, stencil, state, jnp.asarray(rigid), jnp.asarray(DT), grid.num_nodes)
    p = np.asarray(p)
    MV = mass[:, None] * V
    assert rel_err(p.sum(0), MV.sum(0)) < TOL * np.abs(MV).sum() / np.abs(MV.sum(0)).max()
    L_particles = np.asarray(scheme.angular_momentum(state))
    assert rel_err(L_particles, cross_z(x, MV).sum(0) + L.sum(0)) < TOL
    L_grid = cross_z(node_x, p).sum(0)
    scale = np.abs(cross_z(x, MV)).sum() + np.abs(L).sum()
    assert np.max(np.abs(L_grid - L_particles)) < TOL * scale

    # props. 4.3, 4.5: G2P, dt > 0
    v_tilde = rng.normal(size=(grid.num_nodes, dim))
    _, m, V2, X2, L2, _ = rpic_transfers(scheme, stencil, state, jnp.asarray(v_tilde), jnp.asarray(DT), grid.num_nodes)
    m = np.asarray(m)
    mv = m[:, None] * v_tilde
    after = eqx.tree_at(lambda s: (s.x, s.v, s.scheme_state), state, (X2, V2, L2))
    assert np.max(np.abs(np.asarray(jm.linear_momentum(after)) - mv.sum(0))) < TOL * np.abs(mv).sum()
    moved = node_x + DT * v_tilde  # 002 def. 3.4
    L_grid = cross_z(moved, mv).sum(0)
    L_after = np.asarray(scheme.angular_momentum(after))
    assert np.max(np.abs(L_after - L_grid)) < TOL * np.abs(cross_z(moved, mv)).sum()


STEPS_RPIC = 30


@eqx.filter_jit
def one_step(sim, state, dt):
    return sim.step(state, dt)


@eqx.filter_jit
def rigid_start(sim, state, gradient):
    """:func:`jaxmpm.with_velocity_gradient` (compiled: eagerly its stencil costs seconds) and K_p."""
    return jm.with_velocity_gradient(sim, state, gradient), rigid_inertia(sim.shape.stencil(sim.grid, state.x),
                                                                             state.mass)


@pytest.mark.slow
def test_rpic_force_free_run_conserves_momenta():
    """A force-free (NoStress) 2D disk spinning and drifting under RPIC for 30 steps: every step is
    P2G, a grid update with f = 0 and G2P, each conserving linear momentum and angular momentum
    sum_p (X_p x M_p V_p + L_p) (002 props. 4.2-4.5; with f = 0 the grid's x_i x m v~ on the moved
    nodes equals that on the fixed ones), so both stay at their initial values to round-off.
    The disk starts from the rigid field with L_p = K_p omega (:func:`jaxmpm.with_velocity_gradient`)."""
    grid = jm.Grid((0.0, 0.0), (1.0, 1.0), (8, 8))
    sim = jm.Simulation(grid=grid, shape=jm.QuadraticBSpline(), material=jm.NoStress(density=1.0), scheme=jm.RPIC(),
                        damping=False)
    assert jm.folds_force(sim)  # RPIC reads v~ only: P2G scatters p + f dt (with the rigid term)
    particles = jm.fill(grid, jm.Disk((0.5, 0.5), 0.25), ppc=2, density=1.0)
    state = sim.init(particles)
    spin = np.array([[0.0, -1.0], [1.0, 0.0]])  # omega = 1 about (0.5, 0.5), plus a drift
    v = (np.asarray(state.x) - 0.5) @ spin.T + np.array([0.1, -0.05])
    state, K = rigid_start(sim, eqx.tree_at(lambda s: s.v, state, jnp.asarray(v)), jnp.asarray(spin))
    assert rel_err(state.scheme_state[:, 0], K[:, 0, 0]) < TOL  # L_p = K_p omega, omega = 1
    final = state
    for _ in range(STEPS_RPIC):
        final = one_step(sim, final, jnp.asarray(4e-3))
    L0, L1 = (float(sim.scheme.angular_momentum(s)[0]) for s in (state, final))
    P0, P1 = (np.asarray(jm.linear_momentum(s)) for s in (state, final))
    assert np.abs(np.asarray(final.x) - np.asarray(state.x)).max() > 0.01  # it moved and turned
    assert abs(L1 - L0) < 1e-13 * abs(L0), (L0, L1)
    assert np.abs(P1 - P0).max() < 1e-13 * np.abs(P0).max(), (P0, P1)
    assert float(np.sum(np.asarray(final.scheme_state))) > 0.1 * abs(L0)  # the L_p carry a real share


# ============================================================================ USAVG- / USAVG+ (003 §2.2)
def usavg_problem():
    """A free 1D elastic body (E = 2, rho = 1, Linear shape, h = 1), random velocities and strains."""
    from cases import small_simulation

    rng = np.random.default_rng(7)
    sim = small_simulation()
    state = sim.init(jm.fill(sim.grid, jm.Box((4.0,), (12.0,)), ppc=2, density=1.0))
    n = state.x.shape[0]
    V = jnp.asarray(0.3 * rng.normal(size=(n, 1)))
    F = jnp.asarray(1.0 + 0.05 * rng.normal(size=(n, 1, 1)))
    state = eqx.tree_at(lambda s: (s.v, s.F), state, (V, F))
    return sim, state


def numpy_step(sim, state, dt, update):
    """One step of 003 §2.2 with FLIP (000 eqs. 2.48-2.49), 1D, in NumPy: USF strain update over
    dt/2 (USAVG) or dt (USF), force from the updated stress, particle update, then USL-'s (v~) or
    USL+'s (re-extrapolated p = S^T M V^{n+1}) strain update over dt/2 (USAVG) or dt (USL, MUSL)."""
    stencil = sim.shape.stencil(sim.grid, state.x)
    S, G = dense_weights(stencil, sim.grid.num_nodes)
    G = G[..., 0]
    M, V, X, F = (np.asarray(a) for a in (state.mass, state.v, state.x, state.F))
    F = F[:, 0, 0]
    V0 = np.asarray(state.volume0)
    E = float(sim.material.E)
    m = S.T @ M
    live = m > 0

    def grid_velocity(p):
        return np.where(live[:, None], p / np.where(live, m, 1.0)[:, None], 0.0)

    v = grid_velocity(S.T @ (M[:, None] * V))
    half = dt / 2 if update.startswith("USAVG") else dt
    if update in ("USF", "USAVG-", "USAVG+"):
        F = (1.0 + (G @ v)[:, 0] * half) * F  # 003 §2.2 step 2, eq. (2.18)
    tau = E * (F - 1.0)  # 1D uniaxial Kirchhoff stress
    f = -(G.T @ (V0 * tau))[:, None]  # 003 eq. (2.15)
    a = grid_velocity(f)
    v_tilde = v + a * dt
    V_new = V + S @ a * dt  # 000 eq. (2.48)
    X_new = X + (S @ v + 0.5 * (V_new - V)) * dt  # 000 eq. (2.49)
    if update in ("USL", "USAVG-"):
        F = (1.0 + (G @ v_tilde)[:, 0] * half) * F  # 003 §2.2 step 6a
    elif update in ("MUSL", "USAVG+"):
        F = (1.0 + (G @ grid_velocity(S.T @ (M[:, None] * V_new)))[:, 0] * half) * F  # step 6b
    return X_new, V_new, F


@pytest.mark.slow
@pytest.mark.parametrize("update", ["USAVG-", "USAVG+"])
def test_usavg_one_step_matches_algorithm(update):
    """One step of each update order against the NumPy algorithm of 003 §2.2 (USAVG+-: the stress
    updated before the forces and after the particle update, each with dt/2, "Note that for
    USAVG+-, the update uses dt/2"), to 1e-12; USAVG differs from USF and USL by O(dt) in F."""
    sim, state = usavg_problem()
    dt = 0.1
    from cases import small_simulation

    new = one_step(small_simulation(update=update), state, jnp.asarray(dt))
    X, V, F = numpy_step(sim, state, dt, update)
    assert rel_err(new.x - state.x, X - np.asarray(state.x)) < TOL
    assert rel_err(new.v, V) < TOL
    assert rel_err(np.asarray(new.F)[:, 0, 0] - 1.0, F - 1.0) < TOL
    if update == "USAVG-":
        _, _, F_usf = numpy_step(sim, state, dt, "USF")
        _, _, F_usl = numpy_step(sim, state, dt, "USL")
        assert np.abs(F - F_usf).max() > 1e-4 and np.abs(F - F_usl).max() > 1e-4


def test_usavg_spellings():
    """``update="usavg-"``/``"USAVG+"`` are accepted; an unknown name is an InputError naming the choices."""
    from cases import small_simulation

    assert small_simulation(update="usavg-").update == "USAVG-"
    assert small_simulation(update="USAVG+").update == "USAVG+"
    with pytest.raises(jm.InputError, match="USAVG"):
        small_simulation(update="USAVG")
