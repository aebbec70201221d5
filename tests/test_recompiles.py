"""No avoidable recompiles (issue 30): a new value of a number compiles nothing new.  Counted with
``jax.monitoring``'s XLA compilation events (benchmarks/compile_time.py counts them the same way; the
event fires for a program read from the test session's persistent cache too): a second
``jm.calibrate`` with the same loss, ``free=`` picking other parameters, a contact's separation or
specified normal, a transport term's initial value, a rebuilt scene (heat1d, cylinder, slide's ramp)
and a new E, beta or dt compile no new program; the stable time step is one program for any cfl.
Which values the programs compute with is checked too: a reused program must see the new value."""

import gc
import weakref

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxmpm as jm

_COMPILED = []
_RECORDING = [False]


def _listen(event, seconds, **kw):
    if _RECORDING[0] and event == "/jax/core/compile/backend_compile_duration":
        _COMPILED.append(kw.get("fun_name", "?"))


jax.monitoring.register_event_duration_secs_listener(_listen)


def compiled_by(action):
    """(the result of ``action()``, run to completion, and the names of the programs it compiled)."""
    _COMPILED.clear()
    _RECORDING[0] = True
    try:
        out = jax.block_until_ready(action())
    finally:
        _RECORDING[0] = False
    return out, list(_COMPILED)


def run_in_place(run, state):
    """``run(start)`` of a copy of ``state``, donated: (final state, history), the final state checked to lie in the
    memory of the initial one."""
    start = jax.tree_util.tree_map(lambda a: a.copy(), state)
    before = [leaf.unsafe_buffer_pointer() for leaf in jax.tree_util.tree_leaves(start)]
    out = run(start)
    assert [leaf.unsafe_buffer_pointer() for leaf in jax.tree_util.tree_leaves(out[0])] == before
    return out


def assert_same(got, want):
    """Every leaf equal, bit for bit."""
    for g, w in zip(jax.tree_util.tree_leaves(got), jax.tree_util.tree_leaves(want), strict=True):
        np.testing.assert_array_equal(g, w)


def a_run(name: str) -> bool:
    """Whether a compiled program is a run's loop: ``sim.run``'s (its chunked runner's loop, which an in-memory run
    also calls) or a traced rollout's."""
    return "advance" in name or "rollout" in name


def quadratic(p):
    return (p["a"] - 2.0) ** 2 + (jnp.log(p["b"]) - 1.0) ** 2 + 0.1 * p["a"] * jnp.log(p["b"])


INIT = {"a": 0.0, "b": 1.0}
BOUNDS = {"a": None, "b": "positive"}


def test_a_second_calibrate_with_the_same_loss_compiles_nothing():
    first, names = compiled_by(lambda: jm.calibrate(quadratic, INIT, bounds=BOUNDS, steps=4))
    assert any("update" in n for n in names) and first.compile_time > 0
    second, names = compiled_by(lambda: jm.calibrate(quadratic, INIT, bounds=BOUNDS, steps=4))
    assert names == [] and second.compile_time == 0.0
    np.testing.assert_array_equal(second.losses, first.losses)
    for k in INIT:
        np.testing.assert_array_equal(second.params[k], first.params[k])
    # another start of the same shapes: the same program, its own numbers
    third, names = compiled_by(lambda: jm.calibrate(quadratic, {"a": 1.0, "b": 2.0}, bounds=BOUNDS, steps=4))
    assert names == [] and third.losses[0] != first.losses[0]


def test_free_picks_the_fitted_parameters_of_one_program():
    """free="a", then "b", then both: one compiled update; the held parameter keeps its initial
    value exactly, and the fitted one follows the calibration of it alone."""
    def loss(p):
        return quadratic(p)

    results, compiled = {}, []
    for free in ("a", "b", None, ["a", "b"]):
        results[str(free)], names = compiled_by(
            lambda: jm.calibrate(loss, INIT, bounds=BOUNDS, steps=6, free=free))  # noqa: B023
        compiled.append(names)
    assert any("update" in n for n in compiled[0]) and compiled[1:] == [[], [], []]
    assert float(results["a"].params["b"]) == 1.0 and np.all(results["a"].trajectory["b"] == 1.0)
    assert float(results["b"].params["a"]) == 0.0
    np.testing.assert_array_equal(results["None"].losses, results["['a', 'b']"].losses)
    alone = jm.calibrate(lambda p: quadratic({"a": p["a"], "b": 1.0}), {"a": 0.0}, steps=6)
    np.testing.assert_allclose(results["a"].losses, alone.losses, rtol=1e-13)
    np.testing.assert_allclose(results["a"].params["a"], alone.params["a"], rtol=1e-13)
    for bad in ("c", [], 3):
        with pytest.raises(jm.InputError, match="free"):
            jm.calibrate(loss, INIT, free=bad)


def test_the_kept_update_does_not_keep_the_loss_alive():
    """The compiled update is kept for the loss function weakly: the function, and what it holds
    (here a large target), go when the caller drops them."""
    from jaxmpm.run import calibrate as module

    target = jnp.arange(100_000.0)

    def loss(p):
        return jnp.mean((p["a"] * target - 2.0 * target) ** 2)

    jm.calibrate(loss, {"a": 1.0}, bounds={"a": None}, steps=2)
    held = weakref.ref(loss)
    assert loss in module._UPDATES
    del loss
    gc.collect()
    assert held() is None


def two_bars(separation, normal):
    """Two 1D bars approaching at +-0.5 across a gap smaller than a cell, one material each."""
    grid = jm.Grid((0.0,), (4.0,), (16,))
    shape = jm.Linear()
    a = jm.fill(grid, jm.Box((1.0,), (1.9,)), ppc=2, velocity=0.5)
    b = jm.fill(grid, jm.Box((2.1,), (3.0,)), ppc=2, velocity=-0.5)
    particles = jm.Particles(x=jnp.concatenate([a.x, b.x]), v=jnp.concatenate([a.v, b.v]),
                             volume=jnp.concatenate([a.volume, b.volume]), mass=None, ppc=2)
    sim = jm.Simulation(grid=grid, shape=shape, material=jm.LinearElastic(E=100.0, nu=0.0, density=1.0),
                        scheme=jm.FLIP(), terms=(jm.Contact(separation=separation, normal=normal),))
    ids = jnp.concatenate([jnp.zeros(a.x.shape[0]), jnp.ones(b.x.shape[0])])
    return sim, sim.init(particles, fields={"material": ids})


def test_contact_separation_and_normal_vector_compile_nothing():
    def run(separation, normal):
        sim, state = two_bars(separation, normal)
        return sim.run(state, 0.01, 3, 3)[0].v

    touching, names = compiled_by(lambda: run(2.0, (1.0,)))
    assert any(a_run(n) for n in names)
    apart, names = compiled_by(lambda: run(-2.0, (1.0,)))  # never touch
    assert not any(a_run(n) for n in names)
    reversed_normal, names = compiled_by(lambda: run(2.0, (-1.0,)))
    assert not any(a_run(n) for n in names)
    assert not np.array_equal(touching, apart) and not np.array_equal(touching, reversed_normal)
    contact = jm.Contact(separation=0.5, normal=(0.0, 2.0))
    assert isinstance(contact.separation, jax.Array) and contact.normal == (0.0, 1.0)
    assert all(eqx.is_array(leaf) for leaf in (contact.separation, contact.direction))


def test_a_transport_terms_initial_value_compiles_nothing():
    """Heat(initial=T0): the held end's switch-on jump (value - T0 at the node) follows the new T0."""
    grid = jm.Grid((0.0,), (1.0,), (8,))
    particles = jm.fill(grid, jm.Box((0.0,), (1.0,)), ppc=2)
    end = jm.Dirichlet("x-", 1.0)

    def first_step(initial):
        sim = jm.Simulation(grid=grid, shape=jm.Linear(), material=jm.NoStress(density=1.0), scheme=jm.FLIP(),
                            terms=(jm.Heat(conductivity=0.0, initial=initial, boundary=end),), damping=False)
        return sim.run(sim.init(particles), 1e-3, 1, 1)[0].fields["temperature"]

    cold, names = compiled_by(lambda: first_step(0.0))
    assert any(a_run(n) for n in names)
    warm, names = compiled_by(lambda: first_step(0.25))
    assert not any(a_run(n) for n in names)
    # k = 0: only the switch-on moves the particles beside the held end, by (1 - T0) S
    np.testing.assert_allclose(np.asarray(warm) - 0.25, 0.75 * np.asarray(cold), rtol=1e-12, atol=1e-15)


def test_new_E_beta_and_dt_compile_nothing():
    setup = jm.scene("bar", scheme="xpic:2", cells=8)
    sim, state, dt = setup.sim, setup.state, setup.dt

    def run(model=sim, step=dt):
        return model.run(state, step, 4, 4)[0].v

    _, names = compiled_by(run)
    assert any(a_run(n) for n in names)
    for change in (lambda: run(jm.set_params(sim, E=2.0 * float(jm.get_params(sim, "E")["E"]))),
                   lambda: run(jm.set_params(sim, beta=0.5)), lambda: run(step=dt / 2)):
        assert not any(a_run(n) for n in compiled_by(change)[1])


def test_a_new_step_count_or_save_every_compiles_nothing():
    """sim.run outside a trace calls one compiled loop whose frame and step counts are runtime values (issue 30
    item 2: "a new E, beta, dt or step count must not recompile"): after a first run, runs of other lengths and
    another save_every compile nothing, and each equals the rollout traced for its own lengths (static scans, what
    jax.grad differentiates), bit for bit, history and final state."""
    setup = jm.scene("bar", scheme="xpic:2", cells=8)
    sim, state, dt = setup.sim, setup.state, setup.dt
    traced = jax.jit(lambda s, steps, every: sim.run(s, dt, steps, every), static_argnums=(1, 2))
    _, names = compiled_by(lambda: sim.run(state, dt, 40, 4))  # the loop, unless a test before compiled it
    assert set(names) <= {"jit(_advance_in_place)", "jit(_time_step_limits)"}, names
    for steps, every in ((40, 4), (12, 4), (200, 2), (7, 7), (0, 1)):
        got, names = compiled_by(lambda: sim.run(state, dt, steps, every))  # noqa: B023
        assert names == [], (steps, every, names)
        want = traced(state, steps, every)
        assert got[1].time.shape == (steps // every + 1,)
        for g, w in zip(jax.tree_util.tree_leaves(got), jax.tree_util.tree_leaves(want)):
            np.testing.assert_array_equal(g, w)


def test_a_run_of_closed_over_arrays_is_traced_under_jit():
    """A function of no arguments that runs closed-over arrays, under jax.jit or jax.eval_shape, is traced (until
    2026-11-29 sim.run took it for a run outside any trace and failed reading dt back to the host: "The
    numpy.ndarray conversion method __array__() was called on traced array"); the same numbers as a run outside."""
    setup = jm.scene("bar", cells=8)
    sim, state, dt = setup.sim, setup.state, setup.dt
    want = sim.run(state, dt, 12, 4)
    assert_same(jax.jit(lambda: sim.run(state, dt, 12, 4))(), want)
    shapes = jax.eval_shape(lambda: sim.run(state, dt, 12, 4))
    assert [a.shape for a in jax.tree_util.tree_leaves(shapes)] == [a.shape for a in jax.tree_util.tree_leaves(want)]


def test_an_ensemble_of_another_length_compiles_nothing():
    """On the CPU, members that run one after another ("sequential", what "auto" picks from 257 particles) are single
    runs outside a trace (jaxmpm.run.ensemble._one_by_one): an ensemble after a sim.run of its model compiles no run
    of its own, nor does one of another length or save_every, or of a batch of states; each equals the traced
    ensemble (lax.map over the members' static rollouts, what jax.grad differentiates) bit for bit."""
    setup = jm.scene("bar", scheme="xpic:2", cells=8)
    sim, state, dt = setup.sim, setup.state, setup.dt
    E = float(jm.get_params(sim, "E")["E"])
    values = jnp.asarray([E, 2.0 * E, 1e4 * E])  # the last member fails, and the others go on
    states = jax.tree_util.tree_map(lambda a: jnp.stack([a, a]), state)
    states = eqx.tree_at(lambda s: s.v, states, states.v * jnp.asarray([1.0, 0.5])[:, None, None])

    def ensemble(steps, every, **batch):
        return jm.ensemble(sim, state, dt, steps, every, strategy="sequential", progress=False, **batch)

    traced = jax.jit(ensemble, static_argnums=(0, 1))
    compiled_by(lambda: sim.run(state, dt, 40, 4, save_particles=False))  # the loop, unless a test before compiled it
    for steps, every, batch in ((40, 4, {"params": {"E": values}}), (12, 3, {"params": {"E": values}}),
                                (40, 40, {"states": states}), (8, 2, {"states": states, "params": {"E": values[:2]}})):
        got, names = compiled_by(lambda: ensemble(steps, every, **batch))  # noqa: B023
        assert not any(a_run(n) for n in names), (steps, every, names)
        assert got[1].time.shape == (len(got[2]), steps // every + 1)
        assert_same(got, traced(steps, every, **batch))
    failed = np.asarray(ensemble(40, 4, params={"E": values})[2])
    assert failed[0] == failed[1] == -1 and failed[2] > 0, failed


def test_a_vmapped_ensemble_of_another_length_compiles_nothing():
    """Vmapped members outside a trace on the CPU (what "auto" picks for scenes under 257 particles) run in one
    compiled loop whose frame and step counts are runtime values (jaxmpm.run.ensemble._vmapped_at_once): after a
    first ensemble, one of another length or save_every, or in chunks of members, compiles no run.  Each equals
    single runs of its members (the sequential strategy's) and the traced ensemble (static scans, what jax.grad
    differentiates) to round-off: a frame's sums over the particles may add in another order (2e-16 of the bar's
    momentum against the traced ensemble)."""
    setup = jm.scene("bar", scheme="xpic:2", cells=8)
    sim, state, dt = setup.sim, setup.state, setup.dt
    E = float(jm.get_params(sim, "E")["E"])
    values = jnp.asarray([E, 2.0 * E, 1e4 * E])  # the last member fails, and the others go on
    states = jax.tree_util.tree_map(lambda a: jnp.stack([a, a, a]), state)
    states = eqx.tree_at(lambda s: s.v, states, states.v * jnp.asarray([1.0, 0.5, 0.25])[:, None, None])

    def ensemble(steps, every, strategy="vmap", **batch):
        return jm.ensemble(sim, state, dt, steps, every, strategy=strategy, progress=False, **batch)

    traced = jax.jit(ensemble, static_argnums=(0, 1, 2))
    compiled_by(lambda: ensemble(40, 4, params={"E": values}))  # its loop, unless a test before compiled it
    for steps, every, batch in ((40, 4, {"params": {"E": values}}), (12, 3, {"params": {"E": values}}),
                                (90, 45, {"params": {"E": values}}), (0, 1, {"params": {"E": values}})):
        got, names = compiled_by(lambda: ensemble(steps, every, **batch))  # noqa: B023
        assert not any(a_run(n) for n in names), (steps, every, names)
        assert got[1].time.shape == (3, steps // every + 1)
        for want in (traced(steps, every, "vmap", **batch), ensemble(steps, every, "sequential", **batch)):
            np.testing.assert_array_equal(got[2], want[2])
            for g, w in zip(jax.tree_util.tree_leaves(got[:2]), jax.tree_util.tree_leaves(want[:2]), strict=True):
                np.testing.assert_allclose(g, w, rtol=1e-13, atol=1e-300)
    compiled_by(lambda: ensemble(8, 2, states=states, params={"E": values}))
    got, names = compiled_by(lambda: ensemble(20, 5, states=states, params={"E": values}))
    assert not any(a_run(n) for n in names), names
    assert not any(a.is_deleted() for a in jax.tree_util.tree_leaves(states))  # the loop computed in a copy
    want = traced(20, 5, "vmap", states=states, params={"E": values})
    for g, w in zip(jax.tree_util.tree_leaves(got), jax.tree_util.tree_leaves(want), strict=True):
        np.testing.assert_allclose(g, w, rtol=1e-13, atol=1e-300)
    failed = np.asarray(ensemble(40, 4, params={"E": values})[2])
    assert failed[0] == failed[1] == -1 and failed[2] > 0, failed
    in_chunks = {"params": {"E": values}, "chunk": 2}  # lax.map over chunks of 2 members (the last one of 1)
    compiled_by(lambda: ensemble(8, 2, **in_chunks))
    got, names = compiled_by(lambda: ensemble(24, 6, **in_chunks))
    assert not any(a_run(n) for n in names), names
    want = jax.jit(lambda: ensemble(24, 6, **in_chunks))()  # chunk, a Python int, closed over
    for g, w in zip(jax.tree_util.tree_leaves(got), jax.tree_util.tree_leaves(want), strict=True):
        np.testing.assert_allclose(g, w, rtol=1e-13, atol=1e-300)


@pytest.mark.parametrize("strategy", ["sequential", "vmap"])
def test_an_ensemble_runs_in_its_members_precision(strategy):
    """Members (single runs, or the run loop vmapped) of float32 states from a float64 template state (the model and
    dt cast to the members' precision, as Simulation.rollout casts them): float32 results, bit for bit the traced
    ensemble's."""
    setup = jm.scene("bar", scheme="xpic:2", cells=8)
    sim, state, dt = setup.sim, setup.state, setup.dt
    states = jax.tree_util.tree_map(lambda a: jnp.stack([a, a]), jm.scenes.cast_state(state, jnp.float32))
    states = eqx.tree_at(lambda s: s.v, states, states.v * jnp.asarray([1.0, 0.5], jnp.float32)[:, None, None])

    def ensemble(batch):
        return jm.ensemble(sim, state, dt, 12, 4, states=batch, strategy=strategy, progress=False)

    got = ensemble(states)
    assert got[0].x.dtype == got[1].time.dtype == jnp.float32
    assert_same(got, jax.jit(ensemble)(states))


def test_under_the_gpu_policy_a_run_keeps_static_scans():
    """backend.RUNTIME_COUNTS: under the GPU policy (traced here on the CPU) sim.run keeps the rollout's static scans
    (XLA:GPU would read a runtime trip count's predicate back to the host every step), so another length
    compiles its rollout again; donated, the final state lies in the initial one's memory, equal to the kept run."""
    setup = jm.scene("bar", cells=8)
    sim, state, dt = setup.sim.with_backend("gpu"), setup.state, setup.dt
    kept, names = compiled_by(lambda: sim.run(state, dt, 24, 4))
    _, names = compiled_by(lambda: sim.run(state, dt, 28, 4))
    assert "jit(_jit_rollout)" in names and "jit(_advance_in_place)" not in names, names
    assert_same(run_in_place(lambda start: sim.run(start, dt, 24, 4, donate=True), state), kept)


def test_a_long_run_in_memory_fills_its_buffers_in_order(monkeypatch):
    """Buffers of a few frames (a frame's bytes against a small _CHUNK_BYTES), joined on the host and, for a
    history larger than _CHUNK_BYTES, by a program on the device: the frames in order, bit for bit the traced
    rollout's; donated, the final state lies in the initial state's memory."""
    from jaxmpm.run import driver

    setup = jm.scene("bar", cells=8)
    sim, state, dt = setup.sim, setup.state, setup.dt
    want = jax.jit(lambda s: sim.run(s, dt, 60, 3))(state)
    frame = driver._frame_bytes(sim, state, True)
    for limit in (4 * frame, 40 * frame):  # buffers of 4 frames: the 21 frames' history on the device, the host
        monkeypatch.setattr(driver, "_CHUNK_BYTES", limit)
        assert_same(run_in_place(lambda start: sim.run(start, dt, 60, 3, donate=True), state), want)


def test_a_vmapped_ensemble_fills_its_buffers_in_order(monkeypatch):
    """Vmapped members' frames in buffers of 3 frames (a small _CHUNK_BYTES: 11 frames in 4 calls), joined on the
    host along each member's frame axis (driver._joined, axis 1): the traced ensemble's history to round-off."""
    from jaxmpm.run import driver

    setup = jm.scene("bar", scheme="xpic:2", cells=8)
    sim, state, dt = setup.sim, setup.state, setup.dt

    def ensemble():
        return jm.ensemble(sim, state, dt, 40, 4, params={"beta": jnp.asarray([0.1, 0.5, 0.9])}, strategy="vmap",
                           save_particles=True, progress=False)

    want = jax.jit(ensemble)()
    monkeypatch.setattr(driver, "_CHUNK_BYTES", 3 * 3 * driver._frame_bytes(sim, state, True))
    got = ensemble()
    assert got[1].time.shape == (3, 11)
    for g, w in zip(jax.tree_util.tree_leaves(got), jax.tree_util.tree_leaves(want), strict=True):
        np.testing.assert_allclose(g, w, rtol=1e-13, atol=1e-300)


def test_the_stable_time_step_is_one_program_for_any_cfl():
    """sim.stable_dt (a scene's dt) and sim.time_step_limits (sim.run's check of dt) on concrete inputs
    compile one program, the same for both, and jm.stable_dt one, where op by op they compiled one
    per operation (15 for heat1d's limits on a first call); a new cfl compiles nothing.  Their numbers
    are those of the same arithmetic op by op and inside the caller's own jit, bit for bit."""
    s = jm.scene("heat1d", cells=8)
    sim, state = s.sim, s.state
    for action, program in ((lambda c: sim.stable_dt(state, c), "_time_step_limits"),
                            (lambda c: sim.time_step_limits(state, c), "_time_step_limits"),
                            (lambda c: jm.stable_dt(sim.grid, sim.material, state.v, c), "_cfl_limit")):
        jax.clear_caches()
        first, names = compiled_by(lambda: action(0.5))
        assert names == [f"jit({program})"], names
        other, names = compiled_by(lambda: action(0.7))
        assert names == []
        with jax.disable_jit():
            op_by_op = action(0.7)
        for got, want in ((other, op_by_op), (other, jax.jit(action)(0.7))):
            assert jax.tree_util.tree_structure(got) == jax.tree_util.tree_structure(want)
            for g, w in zip(jax.tree_util.tree_leaves(got), jax.tree_util.tree_leaves(want)):
                np.testing.assert_array_equal(g, w)
    assert set(sim.time_step_limits(state, 0.5)) == {"CFL", "heat"}


def test_diagnostics_and_a_written_run_compile_no_small_programs(tmp_path):
    """sim.diagnostics on a concrete state is one compiled program (some thirty op by op: the CLI's
    energy summary), equal bit for bit to the same arithmetic op by op and inside the caller's jit; a
    run written to a file (the chunked path of `jaxmpm run`) compiles its check of dt and its loop (its
    first frame a frame of no steps of that loop), and nothing op by op."""
    s = jm.scene("disks")
    sim, state = s.sim, s.state
    jax.clear_caches()
    got, names = compiled_by(lambda: sim.diagnostics(state))
    assert names == ["jit(_diagnostics)"]
    with jax.disable_jit():
        op_by_op = sim.diagnostics(state)
    for want in (op_by_op, jax.jit(lambda st: sim.diagnostics(st))(state)):
        assert sorted(got) == sorted(want)
        for key in got:
            np.testing.assert_array_equal(got[key], want[key], err_msg=key)

    def written():
        with jm.H5Writer(tmp_path / "disks.h5", sim, state, dt=s.dt) as writer:
            return sim.run(state, s.dt, 4, 1, writer=writer, frames_per_chunk=2)[0].x

    _, names = compiled_by(written)
    assert sorted(names) == ["jit(_advance_in_place)", "jit(_time_step_limits)"]


@pytest.mark.slow
def test_rebuilt_scenes_compile_nothing():
    """heat1d (its initial profile), the cylinder (its traction's particles) and slide's gravity ramp
    are callables and numbers that compare equal when built again, or leaves."""
    def heat1d():
        s = jm.scene("heat1d", cells=8)
        return s.sim.run(s.state, s.dt, 2, 2)[1].fields["temperature"]

    def cylinder():
        s = jm.scene("cylinder", cells=4)
        return s.sim.run(s.state, s.dt, 2, 2)[0].v

    def slide(ramp):
        s = jm.scene("slide", spacing=0.05, ramp=ramp)
        return s.sim.run(s.state, s.dt, 2, 2)[0].v

    for build in (heat1d, cylinder, lambda: slide(0.05)):
        first, names = compiled_by(build)
        assert any(a_run(n) for n in names)
        again, names = compiled_by(build)
        assert not any(a_run(n) for n in names)
        np.testing.assert_array_equal(again, first)
    other, names = compiled_by(lambda: slide(0.1))
    assert not any(a_run(n) for n in names)
