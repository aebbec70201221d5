"""Boundaries that B-splines need: the symmetry plane ``jm.Mirror`` and free slip on an inclined
plane ``jm.Slip(normal=..., point=...)``.

* Mirror: the particles' mirror images folded onto the grid (jaxmpm.physics.conditions.MirrorMap) must give
  exactly the run of the doubled body -- the body plus its reflection (x -> 2c - x, normal velocity
  negated) on the doubled domain, no condition at all.  Dense check to round-off over whole runs: 1D
  cubic B-splines with FMPM(2) and MUSL (the fold enters P2G, S+ of the mass-matrix series 003 eqs.
  1.23/2.13, and MUSL's re-extrapolation 003 §2.1.6), 2D quadratic B-splines with APIC and USF
  (the image's affine term R B_p R, 002 eq. 3; USF's forces after the strain update) through two
  planes, so corner nodes carry the double image and the tangential velocity is even.
* Mirror convergence (order 2.0 on ``mms`` and ``bar``) is measured by ``experiments/convergence.py
  --mirror``, not here (each resolution is a compile; the file's time budget).
* Inclined slip (003 §1.5: the constrained system; every iterate of the series projected): the
  projection u - (u.n) n commutes with a rotation of the frame, so the series with an inclined
  plane equals the series with an axis-aligned Slip in the rotated frame to round-off, and leaves
  zero normal momentum on the plane's nodes; with n a grid axis it is exactly jm.Slip on that
  axis; a block on a frictionless 30 degree plane under gravity keeps the exact tangential momentum
  M g.t t and centre-of-mass motion g.t t^2/2 (the plane removes only normal momentum: sum_i G_pi
  = 0 cancels the internal forces, partition of unity carries the nodal momentum to the
  particles, 000 eqs. 2.84-2.86).
"""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxmpm as jm
from jaxmpm.transfer.series import mass_matrix_series


@eqx.filter_jit
def _run(sim, state, dt, steps):
    return jax.lax.fori_loop(0, steps, lambda _, s: sim.step(s, dt), state)


def _mirror_pair(mirrored: bool, dim: int, shape, scheme, update, velocity, cells: int, h: float, damping=None):
    """The body [0, L]^dim with a Mirror on every lower face (``mirrored``), or the doubled body
    [-L, L]^dim (every reflection of it, velocities reflected) with no condition."""
    L = cells * h
    margin = 2 * h
    if mirrored:
        grid = jm.Grid((-margin,) * dim, (L + margin,) * dim, (cells + 4,) * dim)
        boundary = tuple(jm.Mirror(f"{'xyz'[a]}-", 0.0) for a in range(dim))
    else:
        grid = jm.Grid((-L - margin,) * dim, (L + margin,) * dim, (2 * cells + 4,) * dim)
        boundary = None
    body = jm.fill(grid, jm.Box((0.0,) * dim, (L,) * dim), ppc=2)
    x, vol = np.asarray(body.x), np.asarray(body.volume)
    v = velocity(x)
    if not mirrored:
        signs = np.array(np.meshgrid(*[[1.0, -1.0]] * dim, indexing="ij")).reshape(dim, -1).T  # (2^dim, dim)
        x, v, vol = (np.concatenate([x * s for s in signs]), np.concatenate([v * s for s in signs]),
                     np.tile(vol, len(signs)))
    sim = jm.Simulation(grid=grid, shape=shape, material=jm.NeoHookean(E=100.0, nu=0.3, density=1.0), scheme=scheme,
                        update=update, boundary=boundary, damping=damping)
    return sim, sim.init(jm.Particles(x=x, v=v, volume=vol, mass=None, ppc=2)), len(body.x)


# grid damping by the force approach over an even region (its rate column is folded like the mass)
FORCE_DAMPING = jm.Damping(grid=2.0, approach="force", region=lambda x: 1.0 / (1.0 + 4.0 * x[:, 0] ** 2))

MIRROR_CASES = [
    pytest.param(1, jm.CubicBSpline(), jm.FMPM(order=2), "MUSL", 8, None, id="1d-cubic-FMPM2-MUSL"),
    pytest.param(2, jm.QuadraticBSpline(), jm.APIC(), "USF", 4, None, id="2d-quadratic-APIC-USF-corner"),
    pytest.param(1, jm.QuadraticBSpline(), jm.FLIP(), "USL", 8, FORCE_DAMPING, id="1d-quadratic-force-damping-region"),
]


@pytest.mark.slow
@pytest.mark.parametrize("dim, shape, scheme, update, cells, damping", MIRROR_CASES)
def test_mirror_equals_the_doubled_body(dim, shape, scheme, update, cells, damping):
    """jm.Mirror = the doubled (reflected) body on the doubled domain, to round-off, after 12 steps:
    positions, velocities and deformation gradients of the body's particles."""
    h = 0.125

    def velocity(x):  # any smooth field, not symmetric itself: the images carry its reflection
        v = 0.3 * np.sin(np.pi * x) * (1.0 + 0.5 * x[:, ::-1])
        if dim == 2:
            v = v + 0.1 * x[:, ::-1] ** 2
        return v

    mirror, m_state, n = _mirror_pair(True, dim, shape, scheme, update, velocity, cells, h, damping)
    doubled, d_state, _ = _mirror_pair(False, dim, shape, scheme, update, velocity, cells, h, damping)
    # the stencils cross the plane: the body's particles weigh ghost nodes beyond it
    stencil = mirror.shape.stencil(mirror.grid, m_state.x)
    ghost = np.any(mirror.grid.node_coordinates() < -1e-12, axis=1)[np.asarray(stencil.index)]
    assert np.asarray(stencil.weight)[ghost].max() > 0.01
    dt = 0.005
    a = _run(mirror, m_state, dt, 12)
    b = _run(doubled, d_state, dt, 12)
    for name in ("x", "v", "F"):
        got, want = np.asarray(getattr(a, name)), np.asarray(getattr(b, name))[:n]
        scale = np.abs(want).max()
        assert np.abs(got - want).max() <= 1e-13 * scale, name
    # the run moved: the particles' velocities changed by far more than round-off
    assert np.abs(np.asarray(a.v) - np.asarray(m_state.v)).max() > 1e-3


# --------------------------------------------------------------------------- inclined slip
@pytest.mark.slow
def test_inclined_slip_series_equals_axis_aligned_slip_in_the_rotated_frame():
    """FMPM/XPIC's constrained series (003 eqs. 1.49-1.50) with the inclined plane's nodes slipping
    along n equals, in the frame rotated by Q (Q n = e_y), the series with jm.Slip(axis=1) on the same
    nodes: S+S acts on each component alike, so Q commutes with it.  Order 3, to round-off."""
    theta = np.deg2rad(25.0)
    normal = np.array([np.sin(theta), -np.cos(theta)])
    point = (0.3, 0.4)
    grid = jm.Grid((0.0, 0.0), (1.0, 1.0), (8, 8))
    inclined = jm.Slip(normal=tuple(normal), point=point)
    on = (grid.node_coordinates() - np.asarray(point)) @ normal >= 0.0
    axis = jm.Slip(jm.NodeSet(on), axis=1)
    particles = jm.fill(grid, jm.Box((0.1, 0.1), (0.9, 0.9)), ppc=2)
    rng = np.random.default_rng(0)
    Q = np.array([[-normal[1], normal[0]], [normal[0], normal[1]]])  # rows t, n: a rotation with Q n = e_y
    assert np.allclose(Q @ normal, [0.0, 1.0])
    u = jnp.asarray(rng.standard_normal((grid.num_nodes, 2)))
    sims = [jm.Simulation(grid=grid, shape=jm.QuadraticBSpline(), material=jm.LinearElastic(E=1.0, nu=0.3, density=1.0),
                          scheme=jm.FLIP(), boundary=cond) for cond in (inclined, axis)]
    transfer = jm.p2g(sims[0], sims[0].init(particles), force=False).transfer  # the conditions do not enter it
    order = 3
    results = []
    for sim, uu in zip(sims, (u, u @ Q.T)):
        constraint = sim.constraint(u.dtype)
        results.append(np.asarray(mass_matrix_series(constraint.zero(uu), order, transfer, constraint)))
    np.testing.assert_allclose(results[0] @ Q.T, results[1], rtol=0, atol=1e-13)
    assert np.abs(results[0][on] @ normal).max() < 1e-14  # every iterate slips along the plane
    assert np.abs(results[0][~on] @ normal).max() > 0.1  # free nodes keep their normal component
    assert np.abs(results[0] - np.asarray(u)).max() > 0.1  # the series changed u


def test_inclined_slip_along_a_grid_axis_is_axis_aligned_slip():
    """normal = -e_y through y = 0 selects the nodes y <= 0, like Slip(where, axis=1): zero,
    apply and prescribed agree bit for bit (the projection u - (u.n) n with n = e_y is exact)."""
    grid = jm.Grid((0.0, -0.25), (1.0, 1.0), (4, 5))
    a = jm.Slip(normal=(0.0, -2.0), point=(0.5, 0.0))
    b = jm.Slip(lambda x: x[:, 1] <= 1e-12, axis=1)
    ca, cb = (jm.Simulation(grid=grid, shape=jm.Linear(), material=jm.LinearElastic(E=1.0, nu=0.3, density=1.0),
                            scheme=jm.FLIP(), boundary=c).constraint(jnp.float64) for c in (a, b))
    u = jnp.asarray(np.random.default_rng(1).standard_normal((grid.num_nodes, 2)))
    for method in ("zero", "apply"):
        np.testing.assert_array_equal(getattr(ca, method)(u), getattr(cb, method)(u))
    np.testing.assert_array_equal(ca.prescribed(u), cb.prescribed(u))


@pytest.mark.slow
def test_block_on_a_frictionless_inclined_plane():
    """An elastic block resting on a 30 degree frictionless plane (jm.Slip(normal, point); the grid
    is not aligned with it), gravity switched on, FLIP: the total tangential momentum is M (g.t) t and
    the centre of mass moves (g.t) t^2/2 along the plane, both to round-off, after 100 steps; the
    block neither sinks nor lifts off by more than a tenth of a cell (it rings elastically)."""
    theta, g, h = np.deg2rad(30.0), 1.0, 1 / 16
    t_hat, n_hat = np.array([np.cos(theta), np.sin(theta)]), np.array([np.sin(theta), -np.cos(theta)])
    x0 = np.array([0.1, 0.1])
    grid = jm.Grid((0.0, 0.0), (1.0, 1.0), (16, 16))
    d = h / 2  # 2 particles per cell along each of the block's own axes
    s, r = np.meshgrid(np.arange(0.4 + d / 2, 0.7, d), np.arange(d / 2, 0.15, d), indexing="ij")
    x = x0 + s.reshape(-1, 1) * t_hat - r.reshape(-1, 1) * n_hat
    block = jm.Particles(x=x, v=np.zeros_like(x), volume=np.full(len(x), d * d), mass=None, ppc=2)
    sim = jm.Simulation(grid=grid, shape=jm.QuadraticBSpline(), material=jm.LinearElastic(E=1e4, nu=0.3, density=1e3),
                        scheme=jm.FLIP(), boundary=jm.Slip(normal=tuple(n_hat), point=tuple(x0)), gravity=(0.0, -g))
    state = sim.init(block)
    dt = 0.4 * float(sim.stable_dt(state))
    steps = 100
    final = _run(sim, state, dt, steps)
    time = steps * dt
    mass = np.asarray(state.mass)
    M = mass.sum()
    g_t = np.array([0.0, -g]) @ t_hat
    momentum = mass @ np.asarray(final.v)
    assert abs(momentum @ t_hat - M * g_t * time) < 1e-13 * M * g * time
    shift = mass @ (np.asarray(final.x) - np.asarray(state.x)) / M
    assert abs(shift @ t_hat - 0.5 * g_t * time**2) < 1e-13
    assert 0.5 * abs(g_t) * time**2 > h  # it slid more than a cell
    assert abs(shift @ n_hat) < 0.1 * h
    assert abs(momentum @ n_hat) < 0.1 * M * abs(g_t) * time  # the ringing's normal momentum: a few per cent


# --------------------------------------------------------------------------- bad input
@pytest.mark.parametrize("make, words", [
    (lambda: jm.Mirror("left", 0.0), "Mirror: where"),
    (lambda: jm.Mirror("x-", float("nan")), "position"),
    (lambda: jm.Slip(normal=(0.0, 0.0), point=(0.0, 0.0)), "normal"),
    (lambda: jm.Slip(normal=(0.0, 1.0)), "point"),
    (lambda: jm.Slip(), "Slip: give a face"),
])
def test_bad_boundary_input(make, words):
    with pytest.raises(jm.InputError, match=words):
        make()


def test_mirror_off_a_node_plane_is_an_input_error():
    grid = jm.Grid((0.0,), (1.0,), (4,))
    sim = jm.Simulation(grid=grid, shape=jm.Linear(), material=jm.LinearElastic(E=1.0, nu=0.0, density=1.0),
                        scheme=jm.FLIP(), boundary=jm.Mirror("x-", 0.1))
    with pytest.raises(jm.InputError, match="not a node plane"):
        sim.constraint(jnp.float64)


@pytest.mark.slow
def test_bar_with_a_mirrored_end_converges_at_second_order_with_quadratic_b_splines():
    """Issue 16 item 4: with the fixed end as a mirror plane (``bar(boundary="mirror")``) quadratic
    B-splines converge at second order without an odd extension.  Small amplitude (v0 = 1e-4, no
    particle crosses a cell), one period, FLIP, dt ~ h^2 (cfl = 0.1 * 16/cells); error = relative L2
    error of v_cm against the exact first mode v0/(beta1 L) cos(omega t).  Measured 1.326e-2 at
    16 cells and 3.319e-3 at 32: order 2.00 (with ``boundary="fixed"``: order 1.07 over 4 periods,
    experiments/results/convergence_mirror_bar.md).  At the scene's v0 = 0.1 the order is 1.2-1.3:
    the free end crosses cells (README, convergence)."""
    errors = []
    for cells in (16, 32):
        setup = jm.scene("bar", cells=cells, shape="quadratic", scheme=jm.FLIP(), boundary="mirror", v0=1e-4,
                         cfl=0.1 * 16 / cells, t_end=10.0, frames=50)
        _, history = setup.run()
        mass = np.asarray(setup.state.mass)
        v_cm = np.asarray(history.v)[..., 0] @ mass / mass.sum()
        exact = setup.reference(np.asarray(history.time))
        errors.append(np.linalg.norm(v_cm - exact) / np.linalg.norm(exact))
    order = math.log2(errors[0] / errors[1])
    assert order >= 1.8, (errors, order)
    assert errors[1] < 3.5e-3, errors
