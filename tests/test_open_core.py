"""The open core (issue 10): the three walks a newcomer takes -- a new scheme, a new per-particle
field, a new material, each defined in this file only and registered -- and the core's contracts:
one registry, the backend policy, the model apart from the driver, mixed precision.

The new scheme is FMPM(1) with a FLIP fraction, the "new PIC" of 003 eq. (2.40) generalised as
jaxmpm's FMPM(k) is (V = theta (V + S a dt) + (1 - theta) S v_tilde, X += (V^n + V^{n+1}) dt / 2,
003 eq. 2.17), so it is checked against ``jm.FMPM(order=1, beta=theta)`` number for number.
"""

import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

import jaxmpm as jm
from jaxmpm.schemes.base import dissipated_energy


# ------------------------------------------------------------------ a scheme in one file
class NewPIC(jm.Scheme):
    """003 eq. (2.40) with a FLIP fraction theta: V = theta (V + S a dt) + (1 - theta) S v_tilde."""

    theta: jnp.ndarray

    def __init__(self, theta=0.0):
        self.theta = jnp.asarray(theta, dtype=jnp.result_type(float))

    def update(self, V, X, transfer, constraint, grid, damping, dt):
        Sv, Sa, Svt = transfer.gather(grid.v), transfer.gather(grid.a), transfer.gather(grid.v_tilde)
        V_new = self.theta * (V + Sa * dt) + (1.0 - self.theta) * Svt - damping.acceleration(Sv, V) * dt
        X_new = X + 0.5 * (V_new + V) * dt  # 003 eq. (2.17)
        diss = dissipated_energy(transfer.particle_mass, Sa, Sv, V_new - V, X_new - X, dt)
        return jm.ParticleUpdate(V_new, X_new, grid.v_tilde, diss)


jm.register_scheme("newpic", NewPIC, spec="newpic:THETA",
                   parse=lambda arg, beta=None: NewPIC(float(arg) if arg else 0.0),
                   parameters=[jm.Parameter("theta", lambda s: s.theta, "FLIP fraction of NewPIC", (0.0, 1.0),
                                            valid=(0.0, 1.0))])


def _bar(scheme, steps=64, **kw):
    setup = jm.scene("bar", scheme=scheme, t_end=steps * 0.015625, frames=8, **kw)
    return setup


@pytest.mark.slow
def test_new_scheme_runs_through_scene_params_calibrate_and_hdf5(tmp_path):
    setup = _bar("newpic:0.3")
    assert isinstance(setup.sim.scheme, NewPIC)
    final, hist = setup.run()
    ref_final, ref_hist = _bar(jm.FMPM(order=1, beta=0.3)).run()
    np.testing.assert_allclose(np.asarray(hist.v), np.asarray(ref_hist.v), rtol=0, atol=1e-15)
    np.testing.assert_allclose(np.asarray(final.F), np.asarray(ref_final.F), rtol=0, atol=1e-15)

    # set_params / get_params / PARAMETERS know theta; the HDF5 attributes carry it
    sim = jm.set_params(setup.sim, theta=0.7)
    assert float(jm.get_params(sim, "theta")["theta"]) == 0.7 and "theta" in jm.PARAMETERS
    with pytest.raises(jm.InputError, match=r"theta = 1.5 must lie in \[0(\.0)?, 1(\.0)?\]"):  # valid=, as registered
        jm.set_params(setup.sim, theta=1.5)
    path = tmp_path / "newpic.h5"
    jm.save_h5(path, sim, hist, state=setup.state, dt=setup.dt, scene="bar")
    res = jm.load_h5(path)
    assert res.attrs["scheme"] == "NewPIC" and res.attrs["theta"] == pytest.approx(0.7)
    np.testing.assert_array_equal(res["particles/v"], np.asarray(hist.v))

    # calibrate theta (bounds (0, 1) from the registration) against a run made at theta = 0.6
    target = np.asarray(_bar(NewPIC(0.6)).run()[1].kinetic)

    def loss(p):
        _, h = jm.set_params(setup.sim, theta=p["theta"]).run(setup.state, setup.dt, setup.steps, setup.save_every)
        return jnp.sum((h.kinetic - target) ** 2) / np.sum(target**2)

    fit = jm.calibrate(loss, {"theta": 0.3}, steps=30, optimizer=optax.lbfgs(), tol=1e-14)
    assert fit.params["theta"] == pytest.approx(0.6, abs=1e-4), fit.params
    assert "newpic" in jm.SCHEMES and "newpic:THETA" in jm.SCHEMES.specs()


def test_scheme_specs_are_parsed_strictly():
    assert isinstance(jm.scheme_from_name("xpic:5"), jm.XPIC) and jm.scheme_from_name("xpic:5").order == 5
    for spec, words in [("pic:3", "takes no ':' argument"), ("flip:0.5", "takes no ':' argument"),
                        ("", "give one of"), ("fmpm:1.5", "order must be a non-negative integer"),
                        ("xpic:two", "order must be a non-negative integer"), ("blend:x", "must be a number"),
                        ("foo", "unknown scheme")]:
        with pytest.raises(jm.InputError, match=words):
            jm.scheme_from_name(spec)


def test_a_taken_name_is_replaced_only_on_request_or_by_the_same_class_defined_anew():
    """A name taken by a built-in or by another class is an error (it was replaced silently: a
    user's ``register_scheme("flip", ...)`` changed every FLIP model, the CLI's included)."""
    class Mine(jm.Scheme):
        def update(self, V, X, transfer, constraint, grid, damping, dt):
            raise NotImplementedError

    entry = jm.SCHEMES["flip"]
    with pytest.raises(jm.InputError, match=r"'flip' is taken by jaxmpm\.schemes\.xpic\.FLIP; choose another name"):
        jm.register_scheme("flip", Mine)
    with pytest.raises(jm.InputError, match=r"'newpic' is taken by \S*test_open_core\.NewPIC"):
        jm.register_scheme("newpic", Mine)
    with pytest.raises(jm.InputError, match="replace = 1 must be True or False"):
        jm.register_scheme("newpic", Mine, replace=1)
    assert jm.SCHEMES["flip"] is entry and jm.SCHEMES["newpic"].cls is NewPIC
    # a class of another kind (it had registered, and failed only when used: "'beta' is an invalid keyword")
    for register, base in ((jm.register_scheme, "Scheme"), (jm.register_shape, "ShapeFunction"),
                           (jm.register_material, "Material"), (jm.register_term, "Term")):
        with pytest.raises(jm.InputError, match=f"int is not a subclass of jm.{base}; derive it from jm.{base}"):
            register("not_a_part", int)
    assert "not_a_part" not in jm.SCHEMES

    # the same class again, or a class of the same name defined anew (a notebook cell run twice)
    jm.register_scheme("mine_again", Mine)
    jm.register_scheme("mine_again", Mine)
    first = Mine

    class Mine(jm.Scheme):  # noqa: F811 -- the cell run again
        def update(self, V, X, transfer, constraint, grid, damping, dt):
            raise NotImplementedError

    jm.register_scheme("mine_again", Mine)
    assert jm.SCHEMES["mine_again"].cls is Mine and Mine is not first

    # a class of that name from another module (another package's) is refused, not replaced silently
    elsewhere = type("Mine", (jm.Scheme,), {"__module__": "another_package.schemes",
                                            "update": lambda self, *a: None})
    with pytest.raises(jm.InputError, match=r"'mine_again' is taken by \S*test_open_core\..*Mine"):
        jm.register_scheme("mine_again", elsewhere)

    # a model made with the class before it was defined anew keeps its name and parameters
    def theta_scheme():
        class Theta(jm.Scheme):  # not derived from a registered scheme, whose entry would serve it
            theta: jnp.ndarray

            def update(self, V, X, transfer, constraint, grid, damping, dt):
                raise NotImplementedError
        return Theta

    old, new = theta_scheme(), theta_scheme()
    jm.register_scheme("theta_again", old, parameters=[jm.Parameter("theta", lambda s: s.theta, "theta")])
    sim = jm.scene("bar", cells=4, t_end=0.5, frames=1, scheme=old(0.25)).sim
    jm.register_scheme("theta_again", new, parameters=[jm.Parameter("theta", lambda s: s.theta, "theta")])
    assert jm.SCHEMES["theta_again"].cls is new and jm.SCHEMES.name_of(sim.scheme) == "theta_again"
    assert float(jm.get_params(jm.set_params(sim, theta=0.5), "theta")["theta"]) == 0.5
    # ... a parameter the new class renamed too
    jm.register_scheme("theta_again", new, parameters=[jm.Parameter("theta2", lambda s: s.theta, "renamed")])
    assert float(jm.get_params(jm.set_params(sim, theta=0.25), "theta")["theta"]) == 0.25
    del jm.SCHEMES._entries["theta_again"], jm.SCHEMES._replaced[old]

    # replace=True replaces even a built-in; put it back
    try:
        jm.register_scheme("flip", Mine, replace=True)
        assert jm.SCHEMES["flip"].cls is Mine
    finally:
        jm.SCHEMES._entries["flip"] = entry
    del jm.SCHEMES._entries["mine_again"]


# ------------------------------------------------------------ a per-particle field in one file
class Age(jm.Term):
    """Declares the per-particle field ``age`` (time since the start) and a vector field
    ``start`` (the initial position), and advances the age by dt each step."""

    def particle_fields(self):
        return (jm.ParticleField("age", doc="time since the start"),
                jm.ParticleField("start", shape=(1,), initial=lambda x: x, doc="initial position"))

    def particle_action(self, sim, old, new, transfer, solution, dt):
        return jm.with_fields(new, age=old.fields["age"] + dt)


@pytest.mark.slow
def test_declared_field_is_carried_saved_and_written(tmp_path):
    setup = jm.scene("bar", t_end=0.25, frames=4)
    sim = setup.sim.with_term(Age())
    state = sim.init(setup.particles)
    assert set(state.fields) == {"age", "start"} and state.fields["start"].shape == (state.x.shape[0], 1)
    final, hist = sim.run(state, setup.dt, setup.steps, setup.save_every)
    np.testing.assert_allclose(np.asarray(hist.fields["age"]), np.broadcast_to(np.asarray(hist.time)[:, None],
                                                                               hist.fields["age"].shape), rtol=1e-13)
    np.testing.assert_array_equal(np.asarray(final.fields["start"]), np.asarray(state.x))
    path = tmp_path / "age.h5"
    with jm.H5Writer(path, sim, state, dt=setup.dt) as writer:
        sim.run(state, setup.dt, setup.steps, setup.save_every, writer=writer)
    res = jm.load_h5(path)
    np.testing.assert_allclose(res["particles/age"], np.asarray(hist.fields["age"]), rtol=1e-13)
    assert res["particles/start"].shape == (len(hist), state.x.shape[0], 1)
    xdmf = path.with_suffix(".xdmf").read_text()
    assert 'Attribute Name="age"' in xdmf and 'Attribute Name="start"' in xdmf
    with pytest.raises(jm.InputError, match="not declared"):
        sim.init(setup.particles, fields={"temperature": 1.0})


# ------------------------------------------------------------------ a material in one file
class PerfectlyPlastic1D(jm.Material):
    """1D elastic-perfectly plastic bar: tau = E (eps - eps_p), |tau| <= Y by return mapping; the
    plastic strain eps_p is the material's per-particle state."""

    E: jnp.ndarray
    yield_stress: jnp.ndarray

    def __init__(self, E, yield_stress, density=1.0):
        self.E, self.yield_stress, self.density = (jnp.asarray(v, jnp.result_type(float))
                                                   for v in (E, yield_stress, density))

    def initial_state(self, particles):
        return jnp.zeros(particles.x.shape[0], particles.x.dtype)

    def elastic_strain(self, F, eps_p):
        return F[:, 0, 0] - 1.0 - eps_p

    def particle_stress(self, F, eps_p):
        return (self.E * self.elastic_strain(F, eps_p))[:, None, None]

    def update_state(self, F, eps_p, dt):
        trial = self.E * self.elastic_strain(F, eps_p)
        excess = jnp.maximum(jnp.abs(trial) - self.yield_stress, 0.0)
        return eps_p + jnp.sign(trial) * excess / self.E

    def kirchhoff_stress(self, F):
        return self.particle_stress(F, jnp.zeros(F.shape[0], F.dtype))

    def energy_density(self, F):
        return 0.5 * self.E * (F[:, 0, 0] - 1.0) ** 2

    def stored_energy_density(self, F, eps_p):
        return 0.5 * self.E * self.elastic_strain(F, eps_p) ** 2

    def wave_speed(self, dim):
        return jnp.sqrt(self.E / self.density)


jm.register_material("plastic1d", PerfectlyPlastic1D,
                     parameters=[jm.Parameter("yield_stress", lambda m: m.yield_stress, "yield stress", "positive")])


def test_new_material_with_state_yields():
    setup = jm.scene("bar", v0=2.0, t_end=4.0, frames=8)
    sim = eqx.tree_at(lambda s: s.material, setup.sim, PerfectlyPlastic1D(E=100.0, yield_stress=5.0))
    state = sim.init(setup.particles)
    final, hist = sim.run(state, setup.dt, setup.steps, setup.save_every)
    tau = np.asarray(sim.material.particle_stress(final.F, final.material_state))
    assert np.max(np.abs(tau)) <= 5.0 * (1 + 1e-12)  # the return mapping holds the yield surface
    assert np.max(np.abs(np.asarray(final.material_state))) > 1e-3  # it did yield (elastic peak stress ~ 20)
    # plastic work leaves the elastic energy: total energy drops, unlike the elastic bar's
    energy = np.asarray(hist.kinetic + hist.strain)
    assert energy[-1] < 0.9 * energy[0]
    assert float(jm.get_params(jm.set_params(sim, yield_stress=7.0), "yield_stress")["yield_stress"]) == 7.0


# ------------------------------------------------------------------------ backend policy
@pytest.mark.slow
@pytest.mark.parametrize("name", ["bar", "spin", "rings"])
def test_backend_policies_give_the_same_numbers(name):
    options = dict(bar=dict(t_end=1.0, frames=4), spin=dict(scheme=jm.APIC(), t_end=0.2, frames=2),
                   rings=dict(spacing=0.2, t_end=0.1, frames=2))[name]  # rings: 228 steps of 4392 particles
    setup = jm.scene(name, **options)
    results = {}
    for backend in ("cpu", "gpu"):
        sim = setup.sim.with_backend(backend)
        results[backend] = sim.run(setup.state, setup.dt, setup.steps, setup.save_every)
    (final_cpu, hist_cpu), (final_gpu, hist_gpu) = results["cpu"], results["gpu"]
    energy = float(np.max(np.asarray(hist_cpu.kinetic + hist_cpu.strain)))
    pairs = {"dissipated": (final_cpu.dissipated, final_gpu.dissipated, energy),  # a cancellation: energy's scale
             "history dissipated": (hist_cpu.dissipated, hist_gpu.dissipated, energy)}
    for field in ("x", "v", "F"):
        pairs[field] = (getattr(final_cpu, field), getattr(final_gpu, field), None)
    for field in ("kinetic", "strain", "x", "v"):
        pairs["history " + field] = (getattr(hist_cpu, field), getattr(hist_gpu, field), None)
    # total momenta cancel (rings: two bodies moving apart), so their scale is sum_p M_p |V_p| (|X_p|)
    m, x, v = (np.asarray(a) for a in (setup.state.mass, hist_cpu.x, hist_cpu.v))
    speed = np.linalg.norm(v, axis=-1)
    pairs["history momentum"] = (hist_cpu.momentum, hist_gpu.momentum, np.max(speed @ m))
    pairs["history angular"] = (hist_cpu.angular, hist_gpu.angular, np.max((speed * np.linalg.norm(x, axis=-1)) @ m))
    for name, (a, b, scale) in pairs.items():
        a, b = np.asarray(a), np.asarray(b)
        scale = np.max(np.abs(a)) if scale is None else scale
        np.testing.assert_allclose(b, a, rtol=0, atol=1e-12 * scale, err_msg=name)


def test_a_stencil_sum_as_one_reduction_gives_the_same_step(monkeypatch):
    """The GPU policy's sums over the stencil's slots as one reduction (backend.STENCIL_SUM "reduce", a
    what-if for a device: benchmarks/gpu.py --stencil-sum reduce) instead of K - 1 adds: the program
    holds the reductions, and an APIC step (gather, affine moment, velocity gradient) and its gradient
    equal the adds' to 1e-12."""
    from jaxmpm.transfer import backend

    setup = jm.scene("spin", scheme=jm.APIC(), t_end=0.05, frames=1)
    sim = setup.sim.with_backend("gpu")

    def loss(v):
        return jnp.sum(sim.step(eqx.tree_at(lambda s: s.v, setup.state, v), setup.dt).x ** 2)

    def run():
        program = str(jax.make_jaxpr(lambda s: sim.step(s, setup.dt))(setup.state))
        return program.count("reduce_sum"), jax.jit(lambda s: sim.step(s, setup.dt))(setup.state), \
            jax.jit(jax.grad(loss))(setup.state.v)

    sums_adds, adds, grad_adds = run()
    monkeypatch.setattr(backend, "STENCIL_SUM", dict(backend.STENCIL_SUM, gpu="reduce"))
    sums_reduce, reduced, grad_reduce = run()
    assert sums_reduce >= sums_adds + 3  # the gather, the affine moment, the velocity gradient at least
    for a, b in zip(jax.tree_util.tree_leaves(adds) + [grad_adds], jax.tree_util.tree_leaves(reduced) + [grad_reduce]):
        if jnp.issubdtype(a.dtype, jnp.floating):
            np.testing.assert_allclose(b, a, rtol=1e-12, atol=1e-12 * float(jnp.abs(a).max()))


@pytest.mark.parametrize("name", ["spin", pytest.param("disks", marks=pytest.mark.slow)])
def test_every_xla_kernel_variant_gives_the_same_step_and_derivatives(name):
    """The XLA kernel's variants under the CPU policy -- P2G planar or by rows, the rows' derivatives
    by rows or by the planar layout (a custom JVP: the values from the rows, the tangents from the
    planar P2G), G2P's gathered values held or free -- give one step, its reverse-mode gradient and its
    forward-mode derivative to 1e-12: APIC (spin: the affine column) and FLIP on uGIMP (disks: the
    force apart).  "auto" picks by precision (backend.XLA_LAYOUT): planar and held in float32, rows with
    planar derivatives and free gathers in float64."""
    from jaxmpm.transfer.backend import use_policy, xla_layout
    from jaxmpm.transfer.kernels import XLAKernel, kernel, register_kernel

    with use_policy("cpu"):
        default = kernel()
        assert xla_layout(jnp.float32) == ("planar", "planar", True)
        assert xla_layout(jnp.float64) == ("rows", "planar", False)
    with use_policy("gpu"):
        assert xla_layout(jnp.float64)[:2] == ("rows", "rows")
    options = dict(spin=dict(scheme=jm.APIC(), t_end=0.05, frames=1), disks=dict(t_end=0.01, frames=1))[name]
    setup = jm.scene(name, **options)
    sim, state, dt = setup.sim.with_backend("cpu"), setup.state, setup.dt

    def loss(v):
        moved = sim.step(eqx.tree_at(lambda s: s.v, state, v), dt)
        return jnp.sum(moved.x ** 2) + jnp.sum(moved.v ** 2) + jnp.sum(moved.F ** 2)

    direction = jnp.asarray(np.random.default_rng(1).standard_normal(state.v.shape))
    variants = [dict(layout="planar", hold_gathers=True), dict(layout="rows", tangent_layout="rows", hold_gathers=True),
                dict(layout="rows", tangent_layout="planar", hold_gathers=False)]
    results = []
    try:
        for options in variants:
            register_kernel("cpu", XLAKernel(**options))
            step = jax.jit(lambda s: sim.step(s, dt))(state)
            grad = jax.jit(jax.grad(loss))(state.v)
            tangent = jax.jit(lambda v: jax.jvp(loss, (v,), (direction,))[1])(state.v)
            results.append([step.x, step.v, step.F, grad, tangent])
    finally:
        register_kernel("cpu", default)
    for options, result in zip(variants[1:], results[1:]):
        for what, a, b in zip(("x", "v", "F", "gradient", "jvp"), results[0], result):
            np.testing.assert_allclose(b, a, rtol=0, atol=1e-12 * float(jnp.abs(a).max()), err_msg=f"{options} {what}")


def test_gpu_policy_has_no_stage_boundaries():
    setup = jm.scene("spin", scheme=jm.APIC(), t_end=0.05, frames=1)

    def conds(backend):
        sim = setup.sim.with_backend(backend)
        return str(jax.make_jaxpr(lambda s: sim.step(s, setup.dt))(setup.state)).count("cond[")

    assert conds("cpu") > 0 and conds("gpu") == 0


def _check_eager_step(monkeypatch, primitive, scheme):
    """One ``spin`` step under ``scheme`` (CPU policy), run eagerly and compiled: the eager one calls
    ``jax.lax.<primitive>`` not once, the traced one does, and the two steps agree to 1e-13."""
    setup = jm.scene("spin", scheme=scheme, t_end=0.05, frames=1)
    sim = setup.sim.with_backend("cpu")
    calls = []
    original = getattr(jax.lax, primitive)
    monkeypatch.setattr(jax.lax, primitive, lambda *args, **kwargs: calls.append(1) or original(*args, **kwargs))
    eager = sim.step(setup.state, setup.dt)
    assert not calls
    compiled = jax.jit(lambda s: sim.step(s, setup.dt))(setup.state)
    assert calls
    for field in ("x", "v", "F"):
        a, b = np.asarray(getattr(compiled, field)), np.asarray(getattr(eager, field))
        np.testing.assert_allclose(b, a, rtol=0, atol=1e-13 * np.max(np.abs(a)), err_msg=field)


def test_an_eager_step_skips_the_stage_boundaries_and_equals_the_compiled_one(monkeypatch):
    """``sim.step`` called without jit runs op by op, so the CPU policy's boundaries have nothing to
    steer and are skipped (jaxmpm.transfer.backend._eager): as conditionals each was compiled anew at
    every call, its branches being new functions (a disks step took 1.19 s eagerly, now 0.041 s).
    Traced, the boundaries stay (as they do inside a loop that an eager step traces, such as XPIC's
    series); both give the same step."""
    _check_eager_step(monkeypatch, "cond", jm.APIC())  # traced, its boundaries are conditionals


@pytest.mark.parametrize("scheme", [jm.XPIC(order=3), jm.FMPM(order=2, boundary="collection")],
                         ids=["xpic3", "fmpm2-collection"])
def test_an_eager_series_runs_as_a_python_loop_and_equals_the_compiled_one(monkeypatch, scheme):
    """The series loops (XPIC/FMPM, 000 eqs. 3.22-3.24; the collection solve, 003 §2.4) go through
    jaxmpm.transfer.backend.fori_loop: outside any trace a Python loop of the same body, since a
    ``lax.fori_loop`` called eagerly is compiled anew at every call (an eager XPIC(2) disks step took
    0.53 s, FLIP's 0.047 s; now 0.067 s).  Traced, the loop stays one ``fori_loop``; both give the
    same step."""
    _check_eager_step(monkeypatch, "fori_loop", scheme)  # traced, its series are loops


def test_scatter_rows_are_widened_to_a_power_of_two_only_under_the_cpu_policy():
    # XLA:CPU adds rows of 3, 5, 6, 7 columns 2-4x slower than rows of 4 or 8 (jaxmpm.transfer.backend);
    # the widened scatter must give the same sums, column by column, bit for bit
    from jaxmpm.transfer.backend import scatter_row_width, use_policy
    from jaxmpm.transfer.operators import scatter_planar

    with use_policy("cpu"):
        assert [scatter_row_width(w) for w in range(1, 10)] == [1, 2, 4, 4, 8, 8, 8, 8, 16]
    with use_policy("gpu"):
        assert [scatter_row_width(w) for w in range(1, 10)] == list(range(1, 10))
    rng = np.random.default_rng(0)
    index = jnp.asarray(np.sort(rng.integers(0, 7, (9, 40)), axis=1), jnp.int32)  # neighbours share nodes
    columns = jnp.asarray(rng.normal(size=(5, 9, 40)))
    expected = np.stack([np.bincount(np.asarray(index).ravel(), np.asarray(c).ravel(), minlength=11)
                         for c in columns], 1)
    nodal = {}
    for policy, width in (("cpu", 8), ("gpu", 5)):
        with use_policy(policy):
            nodal[policy] = np.asarray(jax.jit(lambda i, c: scatter_planar(i, c, 11))(index, columns))
            jaxpr = str(jax.make_jaxpr(lambda i, c: scatter_planar(i, c, 11))(index, columns))
        assert f"f64[11,{width}] = scatter-add" in jaxpr
        np.testing.assert_allclose(nodal[policy], expected, rtol=1e-14, atol=1e-14)
    np.testing.assert_array_equal(nodal["cpu"], nodal["gpu"])


# --------------------------------------------------------------- model apart from driver
@pytest.mark.slow
def test_prescribed_velocity_is_a_differentiable_leaf():
    grid = jm.Grid((0.0,), (1.0,), (8,))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no "JAX array is being set as static"
        sim = jm.Simulation(grid, jm.Linear(), jm.LinearElastic(E=10.0), jm.FLIP(),
                            boundary=jm.Prescribed("x-", 0.1, layers=3))
    hash(jm.Fixed(lambda x: x[:, 0] < 0.1))  # selectors stay hashable; models store their nodes
    state = sim.init(jm.fill(grid, jm.Box((0.2,), (0.8,)), ppc=2, density=1.0))

    def momentum(u):
        s = eqx.tree_at(lambda m: m.boundary[0].velocity, sim, jnp.atleast_1d(u))
        final, _ = s.run(state, 0.01, 10, 10, save_particles=False)
        return jnp.sum(final.mass * final.v[:, 0])

    g = jax.grad(momentum)(0.1)
    fd = (momentum(0.1 + 1e-6) - momentum(0.1 - 1e-6)) / 2e-6
    assert abs(float(g)) > 1e-3 and float(g) == pytest.approx(float(fd), rel=1e-7)


def test_callable_selectors_become_node_sets():
    """Two models built alike from different callables are equal (no hand-written hashing)."""
    grid = jm.Grid((0.0,), (1.0,), (8,))

    def model():
        return jm.Simulation(grid, jm.Linear(), jm.LinearElastic(E=10.0), jm.FLIP(),
                             boundary=jm.Fixed(lambda x: x[:, 0] <= 0.25))

    a, b = model(), model()
    assert a.boundary == b.boundary and isinstance(a.boundary[0].where, jm.NodeSet)
    assert int(a.boundary[0].where.mask.sum()) == 3


def test_mixed_precision_state_runs_in_its_own_precision():
    setup = jm.scene("bar", t_end=0.5, frames=2)
    state32 = jm.scenes.cast_state(setup.state, jnp.float32)
    final, hist = setup.sim.run(state32, setup.dt, setup.steps, setup.save_every)  # a float64 model
    assert final.x.dtype == jnp.float32 and hist.kinetic.dtype == jnp.float32
    ref, _ = jm.scenes.cast_state(setup.sim, jnp.float32).run(state32, setup.dt, setup.steps, setup.save_every)
    np.testing.assert_array_equal(np.asarray(final.v), np.asarray(ref.v))
    mixed = eqx.tree_at(lambda s: s.mass, setup.state, setup.state.mass.astype(jnp.float32))
    with pytest.raises(jm.InputError, match="mixes float precisions.*float32: mass"):
        setup.sim.run(mixed, setup.dt, setup.steps, setup.save_every)


@pytest.mark.slow
def test_chunked_run_keeps_the_checkpoint_option(tmp_path):
    setup = jm.scene("bar", t_end=0.5, frames=4)
    plain, hist = setup.run()
    chunked, _ = setup.sim.run(setup.state, setup.dt, setup.steps, setup.save_every, progress=False,
                               frames_per_chunk=2, checkpoint=2, writer=jm.H5Writer(tmp_path / "c.h5", setup.sim,
                                                                                     setup.state))
    np.testing.assert_array_equal(np.asarray(chunked.x), np.asarray(plain.x))
    with pytest.raises(jm.InputError, match="checkpoint"):
        setup.sim.run(setup.state, setup.dt, setup.steps, setup.save_every, frames_per_chunk=2, checkpoint=3,
                      writer=jm.H5Writer(tmp_path / "d.h5", setup.sim, setup.state))
