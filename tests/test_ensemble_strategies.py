"""jm.ensemble's strategies (issue 30, item 6): "vmap" (batched), "sequential" (lax.map, one member at
a time) and "vmap" in chunks give the same numbers as each other and as separate sim.run calls, and
report each member's failure; "auto" resolves by backend (jaxmpm.run.ensemble.plan).  Speed lives in
benchmarks/ensemble_throughput.py.  Sharding over devices: tests/test_differentiable.py."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxmpm as jm
from jaxmpm.run.ensemble import CPU_CHUNK_PARTICLES, plan

ALL = [("vmap", None), ("sequential", None), ("auto", None), ("vmap", 2)]  # 3 members: chunks of 2 and 1


def same(a, b):
    for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=1e-13, atol=1e-300)


def check_strategies(setup, name, values, steps, save_every, strategies, failing=()):
    """Each of ``strategies``: the same final states, histories and failures; the stable members
    equal to separate sim.run calls."""
    runs = [jm.ensemble(setup.sim, setup.state, setup.dt, steps, save_every, params={name: values}, strategy=s,
                        chunk=c, progress=False) for s, c in strategies]
    for final, history, failed in runs[1:]:
        same(final, runs[0][0])
        same(history, runs[0][1])
        np.testing.assert_array_equal(failed, runs[0][2])
    failed = np.asarray(runs[0][2])
    assert [b for b in range(len(values)) if failed[b] >= 0] == list(failing)
    for b, value in enumerate(values):
        if b in failing:
            continue
        final, history = jm.set_params(setup.sim, **{name: value}).run(setup.state, setup.dt, steps, save_every,
                                                                      save_particles=False)
        same(jax.tree_util.tree_map(lambda a, b=b: a[b], runs[0][0]), final)
        same(jax.tree_util.tree_map(lambda a, b=b: a[b], runs[0][1]), history)


@pytest.mark.slow
def test_strategies_agree_and_report_each_failure_bar():
    setup = jm.scene("bar", scheme=jm.XPIC(order=2))
    E = float(jm.get_params(setup.sim, "E")["E"])
    # member 1 is far beyond the stable time step: it fails (step 5), the others are unaffected
    check_strategies(setup, "E", jnp.asarray([E, 1e4 * E, 2 * E]), 40, 20, ALL[:3], failing=(1,))


@pytest.mark.slow
def test_strategies_agree_disks():
    setup = jm.scene("disks", scheme=jm.XPIC(order=2))
    check_strategies(setup, "beta", jnp.asarray([0.0, 0.5, 0.9]), 20, 10, ALL)


def test_states_batch_under_sequential():
    """The fast tier's check: a batch of initial states, the same numbers one after another and vmapped."""
    setup = jm.scene("bar", scheme=jm.XPIC(order=2))
    states = jax.tree_util.tree_map(lambda a: jnp.stack([a, a]), setup.state)
    states = eqx.tree_at(lambda s: s.v, states, states.v * jnp.asarray([1.0, 0.5])[:, None, None])
    one = jm.ensemble(setup.sim, setup.state, setup.dt, 10, 10, states=states, strategy="sequential", progress=False)
    two = jm.ensemble(setup.sim, setup.state, setup.dt, 10, 10, states=states, strategy="vmap", progress=False)
    same(one, two)


def test_auto_plan_by_backend():
    # a GPU (any accelerator) batches every member
    assert plan("auto", None, 256, 8192, "gpu") == ("vmap", None)
    # the CPU: one member at a time for scenes of CPU_CHUNK_PARTICLES particles or more
    assert plan("auto", None, 16, 8192, "cpu") == ("sequential", None)
    assert plan("auto", None, 16, CPU_CHUNK_PARTICLES, "cpu") == ("sequential", None)
    # small scenes vmapped in chunks of about CPU_CHUNK_PARTICLES particles; a chunk of all members is a plain vmap
    small = CPU_CHUNK_PARTICLES // 8
    assert plan("auto", None, 64, small, "cpu") == ("vmap", 8)
    assert plan("auto", None, 8, small, "cpu") == ("vmap", None)
    assert plan("vmap", 4, 4, 10, "cpu") == ("vmap", None)
    assert plan("vmap", 4, 16, 10, "gpu") == ("vmap", 4)
    assert plan("sequential", None, 16, 10, "gpu") == ("sequential", None)


def test_strategy_and_chunk_checked():
    setup = jm.scene("bar", scheme=jm.XPIC(order=2))
    run = lambda **kw: jm.ensemble(setup.sim, setup.state, setup.dt, 2, params={"beta": [0.1, 0.2]},  # noqa: E731
                                   progress=False, **kw)
    for kw, words in ((dict(strategy="fast"), ("strategy = 'fast'", "vmap", "sequential")),
                      (dict(strategy="sequential", chunk=2), ("chunk", "strategy='vmap'")),
                      (dict(strategy="auto", chunk=2), ("chunk", "strategy='vmap'")),
                      (dict(strategy="vmap", chunk=0), ("chunk = 0",))):
        with pytest.raises(jm.InputError) as error:
            run(**kw)
        message = str(error.value)
        assert "\n" not in message and all(w in message for w in words), message


def test_batches_checked_and_a_list_is_a_batch():
    """An empty batch and one value where a batch belongs are InputErrors naming the fix (they were a
    ZeroDivisionError and "got []"); a list of members' values runs as the array of them does."""
    setup = jm.scene("bar", scheme=jm.XPIC(order=2))
    run = lambda params, **kw: jm.ensemble(setup.sim, setup.state, setup.dt, 4, 2, params=params,  # noqa: E731
                                           strategy="sequential", progress=False, **kw)
    for params, kw, words in (({"beta": jnp.zeros((0,))}, {}, ("no members", "at least one")),
                              ({"beta": 0.5}, {}, ("params['beta'] = 0.5 is one value", "jm.set_params(sim, beta=")),
                              ({"beta": 0.5}, {"states": jax.tree_util.tree_map(lambda a: jnp.stack([a, a]),
                                                                                setup.state)},
                               ("one value per member",))):
        with pytest.raises(jm.InputError) as error:
            run(params, **kw)
        message = str(error.value)
        assert "\n" not in message and all(w in message for w in words), message
    same(run({"beta": [0.1, 0.2]}), run({"beta": jnp.asarray([0.1, 0.2])}))


# ------------------------------------------------------------------ gradients through an ensemble
def test_gradient_through_the_ensemble_equals_the_members():
    """jax.grad of a loss of jm.ensemble's results equals the sum of each member's sim.run gradient, under
    every strategy (float64, 1e-10).  Under "vmap" it used to fail: the scatter's tangent boundary
    (jaxmpm.transfer.backend.hold_tangent) had a batched predicate, which vmap turns into a select whose
    stop_gradient JAX cannot transpose; the predicate is now unbatched (_taken_for_the_batch)."""
    setup = jm.scene("bar")
    E = jnp.array([90.0, 100.0, 110.0])

    def single(e):
        final, _ = jm.set_params(setup.sim, E=e).run(setup.state, setup.dt, 100, 20)
        return jm.kinetic_energy(final)

    expected = np.array([jax.grad(single)(e) for e in E])
    assert np.all(expected != 0)
    for strategy, chunk in ALL:
        def loss(E):
            final, _, _ = jm.ensemble(setup.sim, setup.state, setup.dt, 100, 20, params={"E": E}, strategy=strategy,
                                      chunk=chunk, progress=False)
            return jnp.sum(jax.vmap(jm.kinetic_energy)(final))

        np.testing.assert_allclose(np.asarray(jax.grad(loss)(E)), expected, rtol=1e-10, err_msg=strategy)


def test_gradient_through_a_vmapped_2d_rollout():
    """The same in 2D with batched initial states (the disks, each member's velocities scaled): the
    gradient of jax.vmap(sim.rollout) equals the members' own, and jm.ensemble's (states=) too."""
    setup = jm.scene("disks")
    scales = jnp.array([0.9, 1.1])

    def member(scale):
        start = eqx.tree_at(lambda s: s.v, setup.state, scale * setup.state.v)
        final, _, _ = setup.sim.rollout(start, setup.dt, 2, 10, save_particles=False)
        return jnp.sum(final.x ** 2)

    expected = np.array([jax.grad(member)(s) for s in scales])
    batched = jax.grad(lambda sc: jnp.sum(jax.vmap(member)(sc)))(scales)
    np.testing.assert_allclose(np.asarray(batched), expected, rtol=1e-10)

    def through_ensemble(sc):
        states = jax.vmap(lambda s: eqx.tree_at(lambda st: st.v, setup.state, s * setup.state.v))(sc)
        final, _, _ = jm.ensemble(setup.sim, setup.state, setup.dt, 20, 10, states=states, strategy="vmap",
                                  progress=False)
        return jnp.sum(final.x ** 2)

    np.testing.assert_allclose(np.asarray(jax.grad(through_ensemble)(scales)), expected, rtol=1e-10)


def test_ensemble_memory_argument():
    setup = jm.scene("bar")
    with pytest.raises(jm.InputError, match="memory"):
        jm.ensemble(setup.sim, setup.state, setup.dt, 20, 10, params={"E": jnp.array([90.0, 110.0])}, memory="lots",
                    progress=False)
