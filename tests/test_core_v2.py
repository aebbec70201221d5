"""Core v2 (issue 27): grid phases that compose, contact under every update, heat across contact
interfaces, and the checks a model makes of its terms when it is built.

1. Force-form damping acts with contact, whatever the order the terms were given in, and equals a
   hand computation of the phases (forces -> exchange -> conditions) on a two-node grid.
2. Contact runs under USF, MUSL, USAVG- and USAVG+: linear momentum is conserved to round-off, and
   a stick interface is single-field MPM (003 §3.1: stick contact moves both materials with the
   centre-of-mass velocity) step for step.
3. The phases refuse what would overwrite: two terms setting one grid result, two exchanging terms.
4. Heat across a contact interface: perfect contact is single-body conduction, an insulated
   interface passes nothing, an interface conductance relaxes two blocks at the analytic rate.
"""

import math

import equinox as eqx
import jax
import jax.extend
import jax.numpy as jnp
import numpy as np
import pytest

import jaxmpm as jm


@eqx.filter_jit
def _steps(sim, state, dt, n):
    return jax.lax.fori_loop(0, n, lambda i, s: sim.step(s, dt), state)


# ------------------------------------------------------------------ 1. damping acts with contact
@pytest.mark.slow
def test_force_damping_acts_with_contact_in_either_order():
    """The issue's reproducer: bars_impact, 8 cells, frictionless contact, grid damping alpha_g = 50
    on the nodal force (001 eqs. 58-60), 5 steps.  Before core v2 the contact term rebuilt v, a and
    v~ from the P2G fields and the damping changed the particle velocities by exactly 0.0 (0.0276
    without contact).  Now: a change of the same size, and the damping given to the constructor
    (before the contact term) or added after it (``with_term``) gives the same numbers to
    round-off (measured max |dv| 0.0276, order difference 0.0)."""
    damping = jm.Damping(grid=50.0, approach="force")
    plain = jm.scene("bars_impact", cells=8, contact="frictionless", dtype="f64")
    first = jm.scene("bars_impact", cells=8, contact="frictionless", damping=damping, dtype="f64")
    undamped = plain.sim.with_term(jm.Damping(grid=0.0, approach="force"))
    after = undamped.with_term(damping)  # the damping term now comes after the contact term
    assert [type(t).__name__ for t in after.terms][-2:] == ["Contact", "Damping"]
    assert [type(t).__name__ for t in first.sim.terms].index("Damping") < [
        type(t).__name__ for t in first.sim.terms].index("Contact")
    v0 = np.asarray(_steps(plain.sim, plain.state, plain.dt, 5).v)
    v1 = np.asarray(_steps(first.sim, first.state, first.dt, 5).v)
    v2 = np.asarray(_steps(after, plain.state, plain.dt, 5).v)
    change = np.abs(v1 - v0).max()
    assert change > 0.01, change
    np.testing.assert_allclose(v2, v1, rtol=0, atol=1e-15 * np.abs(v1).max())


@pytest.mark.slow
def test_phases_on_two_nodes_by_hand():
    """One cell, two nodes, one particle of each material (no stress, no gravity): the step's grid
    solve is, per material a, f^a = -alpha p^a (forces), then frictionless contact on p and on
    p + f dt (exchange: on the approaching normal the materials share the centre-of-mass
    momentum, 003 eqs. 3.9, 3.12), then v~ = p+/m (no conditions); FLIP then gives
    V_p = V_p^n + sum_i S_pi (v~^a_i - v^a_i).  Written out in NumPy; agreement 1e-14."""
    alpha, dt = 3.0, 0.01
    grid = jm.Grid((0.0,), (1.0,), (1,))
    x = np.array([[0.3], [0.6]])
    v = np.array([[1.0], [-0.5]])
    particles = jm.Particles(x=jnp.asarray(x), v=jnp.asarray(v), volume=jnp.asarray([0.5, 0.4]), ppc=1)
    sim = jm.Simulation(grid=grid, shape=jm.Linear(), material=jm.NoStress(density=2.0), scheme=jm.FLIP(),
                        damping=jm.Damping(grid=alpha, approach="force"),
                        terms=(jm.Contact("frictionless", normal="average"),))
    state = sim.init(particles, fields={"material": jnp.asarray([0.0, 1.0])})
    new = sim.step(state, dt)

    M = np.array([1.0, 0.8])
    S = np.array([[0.7, 0.3], [0.4, 0.6]])  # S_pi of the tents at x = 0.3, 0.6
    m = S * M[:, None]  # m^a_i: row a = material a (one particle each)
    p = m * v  # p^a_i
    f = -alpha * p  # forces phase: the damping force of 001 eq. (58)
    # normal="average": n ~ g^0 - g^1, g^a_i = sum_p M_p G_pi, G = (-1, +1) on the two nodes (h = 1)
    normal = np.sign((M[0] - M[1]) * np.array([-1.0, 1.0]))

    def frictionless(q):  # the law on stacked momenta, per node
        out = q.copy()
        for i in range(2):
            dp = (m[0, i] * q[1, i] - m[1, i] * q[0, i]) / m[:, i].sum()
            if dp * normal[i] < 0:  # approaching along n
                out[0, i] += dp
                out[1, i] -= dp
        return out

    p1 = frictionless(p)
    p_plus = frictionless(p1 + f * dt)
    v_grid, v_tilde = p1 / m, p_plus / m
    expected = v[:, 0] + np.array([S[a] @ (v_tilde[a] - v_grid[a]) for a in range(2)])
    np.testing.assert_allclose(np.asarray(new.v)[:, 0], expected, rtol=0, atol=1e-14)


# ------------------------------------------------------------------ 2. contact under every update
UPDATES = ["USL", "USF", "MUSL", "USAVG-", "USAVG+"]


def _bodies(update, law, scheme=None):
    """Two elastic blocks side by side in 2D meeting head on (uGIMP, no gravity, no conditions)."""
    shape = jm.UGIMP(ppc=2)
    grid = jm.Grid.covering((0.0, 0.0), (1.0, 0.5), 1.0 / 16, shape=shape, pad=2.0 / 16)
    a = jm.fill(grid, jm.Box((0.1, 0.1), (0.45, 0.4)), ppc=2, velocity=(0.4, 0.05))
    b = jm.fill(grid, jm.Box((0.5, 0.1), (0.85, 0.4)), ppc=2, velocity=(-0.3, -0.05))
    particles = jm.Particles(x=jnp.concatenate([a.x, b.x]), v=jnp.concatenate([a.v, b.v]),
                             volume=jnp.concatenate([a.volume, b.volume]), ppc=2)
    terms = () if law is None else (jm.Contact(law=law),)
    sim = jm.Simulation(grid=grid, shape=shape, material=jm.LinearElastic(E=400.0, nu=0.3, density=10.0),
                        scheme=jm.FLIP() if scheme is None else scheme, update=update, damping=False, terms=terms)
    ids = np.concatenate([np.zeros(a.num), np.ones(b.num)])
    state = sim.init(particles, fields=None if law is None else {"material": jnp.asarray(ids)})
    return sim, state, 0.2 * float(sim.stable_dt(state))


def _momentum_scale(state):
    return float(np.sum(np.asarray(state.mass) * np.linalg.norm(np.asarray(state.v), axis=-1)))


@pytest.mark.slow
@pytest.mark.parametrize("update", UPDATES)
def test_contact_under_every_update(update):
    """Two blocks meeting head on, 30 steps through their impact, under USL, USF, MUSL, USAVG-,
    USAVG+ (the exchange acts on the start-of-step momenta and on the re-extrapolated ones too):

    * stick is single-field MPM (FLIP): a stick interface moves every material with the node's
      centre-of-mass velocity, so with a lumped mass matrix the two-material run is the one-field
      run (000 §4.6); x, v and F to 1e-12 (measured <= 2e-15).  (XPIC(k)/FMPM(k) do not revert
      exactly, 003 §3.3: their series run on each material's S+S; tests/test_contact.py measures how
      far.)
    * frictionless FMPM(2): linear momentum conserved to round-off (every exchange sums to zero
      over the materials, 000 eq. 4.12, its series term too, 003 eq. 3.22; measured <= 3e-16 of
      sum M |V|), and the blocks exchange momentum (each block's changes by > 1 %)."""
    single, state1, dt = _bodies(update, None)
    stick, state2, _ = _bodies(update, "stick")
    a, b = _steps(single, state1, dt, 30), _steps(stick, state2, dt, 30)
    for x, y in ((a.x, b.x), (a.v, b.v), (a.F, b.F)):
        np.testing.assert_allclose(np.asarray(y), np.asarray(x), rtol=0, atol=1e-12 * np.abs(np.asarray(x)).max())
    sim, state, _ = _bodies(update, "frictionless", jm.FMPM(order=2))
    final = _steps(sim, state, dt, 30)
    drift = np.abs(np.asarray(jm.linear_momentum(final) - jm.linear_momentum(state))).max()
    assert drift <= 1e-13 * _momentum_scale(state)
    ids = np.asarray(state.fields["material"]) == 0
    px0 = float(np.sum(np.asarray(state.mass)[ids] * np.asarray(state.v)[ids, 0]))
    px1 = float(np.sum(np.asarray(final.mass)[ids] * np.asarray(final.v)[ids, 0]))
    assert abs(px1 - px0) > 0.01 * abs(px0)


# ------------------------------------------------------------------ 3. what the phases refuse
class _Echo(jm.Term):
    """A reader that adds a grid result named ``name``."""

    name: str = eqx.field(static=True)

    def read_grid(self, sim, fields, solution, dt):
        return {self.name: solution.v_tilde}


class _Echo2(_Echo):
    pass


@pytest.mark.slow
def test_two_terms_cannot_set_one_grid_result():
    setup = jm.scene("bar", cells=4, t_end=0.1, dtype="f64")
    fine = setup.sim.with_term(_Echo("echo"))
    fine.step(setup.state, setup.dt)
    clash = fine.with_term(_Echo2("echo"))
    with pytest.raises(jm.InputError, match="echo"):
        clash.step(setup.state, setup.dt)
    with pytest.raises(jm.InputError, match="v_tilde"):
        setup.sim.with_term(_Echo("v_tilde")).step(setup.state, setup.dt)


class _Swap(jm.Term):
    """A second momentum exchange (no physics: it returns the momenta unchanged)."""

    def exchange_momentum(self, sim, fields, p):
        return p, jnp.zeros_like(p)


def test_one_exchanging_term_per_model():
    setup = jm.scene("bars_impact", cells=8, contact="frictionless", dtype="f64")
    with pytest.raises(jm.InputError, match="exchange momentum"):
        setup.sim.with_term(_Swap())


# ------------------------------------------------------------------ 4. heat across contact interfaces
def _hot_and_cold(interface, law="frictionless", cells=32, contact=True):
    """A 1D bar of two halves (materials 0 and 1, at rest, no stress) at temperatures 1 and 0,
    conductivity k = 1, rho = c_p = 1 (diffusivity 1), insulated outer ends."""
    grid = jm.Grid((-2.0 / cells,), (1.0 + 2.0 / cells,), (cells + 4,))
    particles = jm.fill(grid, jm.Box((0.0,), (1.0,)), ppc=2)
    heat = jm.Heat(conductivity=1.0, initial=lambda x: np.where(x[:, 0] < 0.5, 1.0, 0.0),
                   **({} if interface is None else {"interface": interface}))
    terms = (heat,) + ((jm.Contact(law=law),) if contact else ())
    sim = jm.Simulation(grid=grid, shape=jm.Linear(), material=jm.NoStress(), scheme=jm.FLIP(), damping=False,
                        terms=terms)
    fields = {"material": jnp.asarray((np.asarray(particles.x)[:, 0] > 0.5).astype(float))} if contact else None
    state = sim.init(particles, fields=fields)
    return sim, state, 0.2 * float(sim.stable_dt(state))


@pytest.mark.slow
def test_perfect_thermal_contact_is_one_body():
    """interface="perfect" (the default): heat crosses the contact interface as within one body --
    the temperatures equal the single-body conduction run (no contact term) to round-off after 200
    steps (measured 4e-16), and the heat has crossed (the cold half warmed by > 0.1)."""
    sim, state, dt = _hot_and_cold(None)
    single, state1, _ = _hot_and_cold(None, contact=False)
    T = np.asarray(_steps(sim, state, dt, 200).fields["temperature"])
    T1 = np.asarray(_steps(single, state1, dt, 200).fields["temperature"])
    np.testing.assert_allclose(T, T1, rtol=0, atol=1e-13)
    assert T[np.asarray(state.x)[:, 0] > 0.5].mean() > 0.1


def test_insulated_interface_passes_no_heat():
    """interface="insulated": each material conducts within itself; the thermal energy of each
    half stays what it was (to round-off: 1e-15 measured) while it evens out inside the half."""
    sim, state, dt = _hot_and_cold("insulated")
    final = _steps(sim, state, dt, 200)
    hot = np.asarray(state.fields["material"]) == 0
    for part in (hot, ~hot):
        e0 = np.sum(np.asarray(state.mass)[part] * np.asarray(state.fields["temperature"])[part])
        e1 = np.sum(np.asarray(final.mass)[part] * np.asarray(final.fields["temperature"])[part])
        assert abs(e1 - e0) <= 1e-13 * max(abs(e0), 1.0)


def test_interface_conductance_relaxes_at_the_analytic_rate():
    """interface=h_c: two identical slabs of length L = 0.5 (diffusivity a = k/(rho c_p) = 1,
    insulated outer ends) joined by a contact conductance h_c = 0.5.  By symmetry each slab sees the
    mid-plane through the conductance 2 h_c, and the difference of their temperatures decays as
    exp(-lambda t) with lambda = a beta^2 / L^2, beta tan beta = 2 h_c L / k (the slab with a
    surface conductance, Carslaw & Jaeger 1959 §3.10): beta = 0.6533, lambda = 1.7071 (the lumped
    estimate h_c (1/C0 + 1/C1) = 2 would ignore the gradients inside the slabs, Biot number 0.5).
    Fitted over t in [0.3, 1.0]: lambda = 1.7027 measured (32 cells); within 2 %.  Energy is
    conserved to round-off (the exchange sums to zero over the fields)."""
    sim, state, dt = _hot_and_cold(0.5)
    steps = int(round(1.0 / dt))
    hot = np.asarray(state.fields["material"]) == 0
    mass = np.asarray(state.mass)

    def means(s):
        T = np.asarray(s.fields["temperature"])
        return np.sum(mass[hot] * T[hot]) / mass[hot].sum(), np.sum(mass[~hot] * T[~hot]) / mass[~hot].sum()

    times, gaps, s = [], [], state
    chunk = max(steps // 20, 1)
    for k in range(20):
        s = _steps(sim, s, dt, chunk)
        t = (k + 1) * chunk * dt
        if t >= 0.3:
            a, b = means(s)
            times.append(t)
            gaps.append(a - b)
    rate = -np.polyfit(times, np.log(gaps), 1)[0]
    beta = 0.5  # beta tan beta = 2 h_c L / k = 0.5, by Newton's method
    for _ in range(50):
        beta -= (beta * math.tan(beta) - 0.5) / (math.tan(beta) + beta / math.cos(beta) ** 2)
    assert rate == pytest.approx(beta**2 / 0.5**2, rel=0.02), (rate, beta**2 / 0.25)
    e0 = np.sum(mass * np.asarray(state.fields["temperature"]))
    e1 = np.sum(mass * np.asarray(s.fields["temperature"]))
    assert abs(e1 - e0) <= 1e-13 * e0


def test_bad_interface_option():
    with pytest.raises(jm.InputError, match="interface"):
        jm.Heat(1.0, interface="glued")
    with pytest.raises(jm.InputError, match="interface"):
        jm.Heat(1.0, interface=-1.0)


# ------------------------------------------------------------------ 5. a history-dependent law, scoped parameters
class HardeningBar(jm.InelasticMaterial):
    """A toy 1D elastic-plastic law with linear isotropic hardening, written against the material
    protocol: its state is the elastic strain and the accumulated plastic strain; each strain
    update hands it the increment dF (thermal stretch removed), and a return mapping keeps
    |E eps_e| <= Y + H eps_p (the classic 1D algorithm, Simo & Hughes 1998, box 1.4)."""

    E: jnp.ndarray
    yield_stress: jnp.ndarray
    hardening: jnp.ndarray
    friction: jnp.ndarray  # a parameter named like the contact's, to show that names are scoped

    def __init__(self, E=100.0, yield_stress=0.05, hardening=20.0, friction=0.0, density=1.0):
        self.E, self.yield_stress, self.hardening, self.friction, self.density = (
            jnp.asarray(v, jnp.result_type(float)) for v in (E, yield_stress, hardening, friction, density))

    def initial_state(self, particles):
        n = np.shape(particles.x)[0]
        return {"elastic": jnp.zeros(n), "plastic": jnp.zeros(n)}

    def update_state(self, increment, state):
        trial = state["elastic"] + (increment.dF[:, 0, 0] - 1.0)  # small strain: d eps = dF - 1
        stress = self.E * trial
        limit = self.yield_stress + self.hardening * state["plastic"]
        excess = jnp.maximum(jnp.abs(stress) - limit, 0.0)
        d_plastic = excess / (self.E + self.hardening)
        return {"elastic": trial - jnp.sign(stress) * d_plastic, "plastic": state["plastic"] + d_plastic}

    def stress(self, F, state):
        return (self.E * state["elastic"])[:, None, None]

    def stored_energy_density(self, F, state):
        return 0.5 * self.E * state["elastic"] ** 2

    def wave_speed(self, dim):
        return jnp.sqrt(self.E / self.density)


jm.register_material("hardening_bar", HardeningBar, parameters=[
    jm.Parameter("yield_stress", lambda m: m.yield_stress, "initial yield stress Y", "positive"),
    jm.Parameter("hardening", lambda m: m.hardening, "hardening modulus H", "positive"),
    jm.Parameter("friction", lambda m: m.friction, "a toy parameter sharing the contact's name"),
])


def test_history_dependent_law_through_the_protocol():
    """The law's return mapping on a strain path (load past yield, unload, reload): the stress
    follows E eps up to Y, then the hardening line Y + H eps_p with slope E H / (E + H), unloads
    elastically, and reloads elastically to where it left the line (1D plasticity, closed form).
    Then a bar pulled at its end through yield in a simulation: every particle satisfies the
    yield condition |sigma| <= Y + H eps_p, several have yielded, and the plastic strain only grows."""
    law = HardeningBar()
    E, Y, H = 100.0, 0.05, 20.0
    state = {"elastic": jnp.zeros(1), "plastic": jnp.zeros(1)}
    eps, path = 0.0, np.concatenate([np.full(20, 1e-4), np.full(10, -1e-4), np.full(15, 1e-4)])
    for d in path:
        eps += d
        state = law.update_state(jm.Increment(jnp.full((1, 1, 1), 1.0 + d), jnp.full((1, 1, 1), 1.0 + eps),
                                              jnp.asarray(0.01)), state)
    # closed form: the path ends at eps = 2.5e-3, beyond its earlier maximum 2e-3, so on the
    # hardening line: E (eps - eps_p) = Y + H eps_p, eps_p = (E eps - Y)/(E + H)
    eps_p = (E * 2.5e-3 - Y) / (E + H)
    assert eps == pytest.approx(2.5e-3, rel=1e-12)
    assert float(state["plastic"][0]) == pytest.approx(eps_p, rel=1e-12)
    assert float(law.stress(None, state)[0, 0, 0]) == pytest.approx(Y + H * eps_p, rel=1e-12)

    grid = jm.Grid((-1.0 / 16,), (2.0,), (33,))
    particles = jm.fill(grid, jm.Box((0.0,), (1.0,)), ppc=2)
    sim = jm.Simulation(grid=grid, shape=jm.Linear(), material=law, scheme=jm.FLIP(), damping=False,
                        boundary=[jm.Fixed(lambda x: x[:, 0] <= 1e-9),
                                  jm.Prescribed(lambda x: x[:, 0] >= 1.0 - 1e-9, 0.02, layers=1)])
    state = sim.init(particles)
    dt = 0.2 * float(sim.stable_dt(state))
    half, _ = sim.run(state, dt, 200, 100)
    final, _ = sim.run(half, dt, 200, 100)
    plastic = np.asarray(final.material_state["plastic"])
    sigma = law.E * np.asarray(final.material_state["elastic"])
    assert (plastic > 1e-6).sum() >= 4
    assert np.all(np.abs(sigma) <= Y + H * plastic + 1e-12)
    assert np.all(plastic >= np.asarray(half.material_state["plastic"]))


def test_parameter_names_are_scoped_per_part():
    """The toy law's ``friction`` and the contact's ``friction`` live side by side: set_params and
    get_params take the scoped names, the bare name is an error naming both, and the HDF5
    attributes carry both scoped."""
    setup = jm.scene("bars_impact", cells=8, contact="coulomb", dtype="f64")
    sim = eqx.tree_at(lambda s: s.material, setup.sim, HardeningBar())
    with pytest.raises(jm.InputError, match="contact.friction"):
        jm.set_params(sim, friction=0.3)
    sim = jm.set_params(sim, **{"contact.friction": 0.3, "material.friction": 0.7})
    got = jm.get_params(sim, "contact.friction", "material.friction", "yield_stress")
    assert float(got["contact.friction"]) == 0.3 and float(got["material.friction"]) == 0.7
    assert float(got["yield_stress"]) == 0.05
    from jaxmpm.io.hdf5 import run_attributes

    attrs = run_attributes(sim)
    assert attrs["contact.friction"] == 0.3 and attrs["material.friction"] == 0.7 and "friction" not in attrs


# ------------------------------------------------------------------ 6. the kernel seam
def _concatenations(fn, *args):
    """The output sizes of every concatenate in the jaxpr of ``fn(*args)`` (nested jaxprs included)."""
    sizes = []

    def walk(jaxpr):
        for eqn in jaxpr.eqns:
            if eqn.primitive.name == "concatenate":
                sizes.append(int(np.prod(eqn.outvars[0].aval.shape)))
            for sub in jax.extend.core.jaxprs_in_params(eqn.params):
                walk(sub)

    walk(jax.make_jaxpr(fn)(*args).jaxpr)
    return sizes


@pytest.mark.slow
@pytest.mark.parametrize("shape", [jm.Linear(), jm.UGIMP(ppc=2), jm.QuadraticBSpline(), jm.CubicBSpline()],
                         ids=["linear", "ugimp", "quadratic", "cubic"])
@pytest.mark.parametrize("dim", [1, 2, 3])
def test_kernel_layouts_give_the_same_nodal_sums(dim, shape):
    """The XLA kernel's two layouts of P2G's rows -- per-slot columns stacked ("planar"), or
    per-particle coefficients times the weight basis ("rows") -- give the same nodal sums to
    round-off for every contraction, mixed in one pass as a step mixes them: a scalar and a vector
    Weighted, a Gradient, a Divergence, an Affine, a PerSlot, and columns summing several (the
    force: Divergence + Weighted).  Both compared with the dense matrix form S, G of the stencil
    (1e-13 relative).  Whole steps under both: tests/test_open_core.py (the "gpu" policy runs the
    rows layout) and the stored reference values (the "cpu" policy, planar)."""
    from jaxmpm.transfer.kernels import XLAKernel

    rng = np.random.default_rng(dim)
    grid = jm.Grid((0.0,) * dim, (1.0,) * dim, (6,) * dim)
    n = 40
    x = jnp.asarray(0.25 + 0.5 * rng.random((n, dim)))
    stencil = shape.stencil(grid, x)
    q1, qv = jnp.asarray(rng.standard_normal(n)), jnp.asarray(rng.standard_normal((n, dim)))
    qt, qa = jnp.asarray(rng.standard_normal((n, dim, dim))), jnp.asarray(rng.standard_normal((n, 2, dim)))
    slots = jnp.asarray(rng.standard_normal((3,) + stencil.weight.shape))
    columns = {"mass": jm.Weighted(q1), "momentum": (jm.Weighted(qv), jm.Affine(qt)), "grad": jm.Gradient(q1),
               "force": (jm.Divergence(qt), jm.Weighted(qv)), "affine2": jm.Affine(qa), "slots": jm.PerSlot(slots)}
    S, G = stencil.matrices(grid.num_nodes)  # dense (N, n), (N, n, D)
    X = np.asarray(grid.node_coordinates())
    offset = X[None, :, :] - np.asarray(x)[:, None, :]  # x_i - X_p
    q1n, qvn, qtn, qan = (np.asarray(a) for a in (q1, qv, qt, qa))
    affine = lambda q: np.einsum("pi,pcd,pid->ic", S, q, offset)  # noqa: E731
    dense = {"mass": S.T @ q1n, "momentum": S.T @ qvn + affine(qtn), "grad": np.einsum("p,pid->id", q1n, G),
             "force": np.einsum("pcd,pid->ic", qtn, G) + S.T @ qvn, "affine2": affine(qan),
             "slots": np.stack([np.bincount(np.asarray(stencil.index).ravel(), np.asarray(slots[c]).ravel(),
                                            grid.num_nodes) for c in range(3)], -1)}
    for layout in ("planar", "rows"):
        out = XLAKernel(layout=layout).p2g(stencil, columns, grid.num_nodes)
        assert set(out) == set(dense)
        for name, ref in dense.items():
            got = np.asarray(out[name])
            np.testing.assert_allclose(got, ref.reshape(got.shape), rtol=0, atol=1e-13 * np.abs(ref).max(),
                                       err_msg=f"{layout} {name}")


@pytest.mark.slow
def test_rows_layout_has_no_per_slot_concatenation():
    """Under the rows layout the compiled P2G concatenates only per-particle arrays (N x C); the
    planar layout concatenates per-slot columns (K x N x C, K = 9 here: the 2.04 ms of an H100 3D
    step that issue 27 names)."""
    from jaxmpm.transfer.backend import use_policy
    from jaxmpm.transfer.kernels import XLAKernel, kernel, register_kernel

    setup = jm.scene("mpm88", n_particles=512, n_grid=32, dtype="f64")
    sim, state = setup.sim, setup.state
    n, k = state.x.shape[0], 9
    with use_policy("gpu"):
        default = kernel()
    try:
        register_kernel("gpu", XLAKernel(layout="planar"))
        with use_policy("gpu"):
            planar = _concatenations(lambda s: jm.p2g(sim, s).values, state)
        register_kernel("gpu", XLAKernel(layout="rows"))
        with use_policy("gpu"):
            rows = _concatenations(lambda s: jm.p2g(sim, s).values, state)
    finally:
        register_kernel("gpu", default)
    assert max(planar) >= k * n
    assert all(size < k * n for size in rows), rows
