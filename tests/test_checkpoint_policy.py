"""checkpoint="auto": the reverse-mode schedule chosen from a memory budget (jaxmpm.run.memory,
issue 30 item 3).  The choice changes memory and time, never the gradient (every schedule equals the
plain one to round-off: test_differentiable.test_checkpointed_gradient_equals_plain)."""

import jax
import jax.numpy as jnp
import pytest

import jaxmpm as jm
from jaxmpm.run.memory import choose_checkpoint, parse_memory, residual_bytes, tree_bytes


@pytest.fixture(scope="module")
def bar():
    return jm.scene("bar")


def test_parse_memory():
    assert parse_memory("4 GiB") == 4 * 2**30
    assert parse_memory("500MB") == 500 * 10**6
    assert parse_memory(1e6) == 10**6 and parse_memory(None) is None
    for bad in ("lots", "-1 GiB", 0, float("inf"), True, "4 GB/s"):
        with pytest.raises(jm.InputError, match="memory"):
            parse_memory(bad)


def test_cpu_recomputes_within_the_budget(bar):
    """On the CPU storing residuals never paid (jaxmpm.transfer.backend.STORE_RESIDUALS_UP_TO): two
    levels while the kept states fit, three levels when they do not."""
    sim, state = bar.sim.with_backend("cpu"), bar.state
    assert choose_checkpoint(sim, state, bar.dt, 10, 100)[0] is True
    assert choose_checkpoint(sim, state, bar.dt, 10, 100, memory="1 GiB")[0] is True
    states = 10 * 100 // 25 + 25  # _segment_length(100, True, 10) = 25
    tight = (states - 1) * tree_bytes(state)
    choice, why = choose_checkpoint(sim, state, bar.dt, 10, 100, memory=tight)
    assert choice == "low_memory" and "over the budget" in why


def test_gpu_policy_stores_small_residuals(bar):
    """Under the GPU policy a rollout whose residuals fit in 64 MiB (and the budget) stores them:
    measured 0.73-0.75x the recomputing gradient's time for the bar on an H200."""
    sim, state = bar.sim.with_backend("gpu"), bar.state
    per_step = residual_bytes(sim.step, state, bar.dt)
    assert per_step > tree_bytes(state)  # a step keeps more than its state
    assert choose_checkpoint(sim, state, bar.dt, 10, 100)[0] is False
    assert choose_checkpoint(sim, state, bar.dt, 10, 100, memory=per_step * 1000 - 1)[0] is True  # over budget
    big = 64 * 2**20 // per_step + 1  # steps whose residuals exceed the policy's 64 MiB
    assert choose_checkpoint(sim, state, bar.dt, 1, big)[0] is True


def test_auto_gradient_is_the_two_level_gradient(bar):
    """On the CPU "auto" runs checkpoint=True: the same gradient, bit for bit; a tight budget runs
    "low_memory", equal to round-off."""
    def loss(E, checkpoint, memory=None):
        sim = jm.set_params(bar.sim, E=E)
        final, _ = sim.run(bar.state, bar.dt, 200, 20, checkpoint=checkpoint, memory=memory)
        return jm.kinetic_energy(final)

    E = jnp.asarray(100.0)
    auto = jax.grad(loss)(E, "auto")
    assert auto == jax.grad(loss)(E, True)
    tight = jax.grad(loss)(E, "auto", "4 KiB")
    assert abs(tight - auto) <= 1e-10 * abs(auto)


def test_bad_memory_argument(bar):
    with pytest.raises(jm.InputError, match="memory"):
        bar.sim.run(bar.state, bar.dt, 20, 10, memory="plenty")
