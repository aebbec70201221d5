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
