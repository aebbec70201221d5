"""checkpoint="auto": the reverse-mode schedule chosen from a memory budget (jaxmpm.run.memory,
issue 30 item 3).  The choice changes memory and time, never the gradient (every schedule equals the
plain one to round-off: test_differentiable.test_checkpointed_gradient_equals_plain)."""

import jax
import jax.numpy as jnp
import pytest

import jaxmpm as jm
from jaxmpm.run.memory import choose_checkpoint, parse_memory, residual_bytes, tree_bytes
from jaxmpm.transfer.backend import KEEP_STATES_UP_TO


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
    """On the CPU storing residuals never paid (jaxmpm.transfer.backend.STORE_RESIDUALS_UP_TO): one
    level (every step's state kept) while those states fit, then two levels while theirs fit, then
    three levels."""
    sim, state = bar.sim.with_backend("cpu"), bar.state
    assert choose_checkpoint(sim, state, bar.dt, 10, 100)[0] == "states"
    assert choose_checkpoint(sim, state, bar.dt, 10, 100, memory="1 GiB")[0] == "states"
    every_step = 10 * 100 * tree_bytes(state)
    assert choose_checkpoint(sim, state, bar.dt, 10, 100, memory=every_step)[0] == "states"
    choice, why = choose_checkpoint(sim, state, bar.dt, 10, 100, memory=every_step - 1)
    assert choice is True and "two levels" in why
    states = 10 * 100 // 25 + 25  # _segment_length(100, True, 10) = 25
    tight = (states - 1) * tree_bytes(state)
    choice, why = choose_checkpoint(sim, state, bar.dt, 10, 100, memory=tight)
    assert choice == "low_memory" and "over the budget" in why


def test_one_level_limit_in_1d(bar):
    """KEEP_STATES_UP_TO: in 1D a step costs no more than moving its state through memory, so past 16 MiB
    of states (out of the cache) two levels run; a 2D model keeps every state the budget allows."""
    sim, state = bar.sim.with_backend("cpu"), bar.state
    limit = KEEP_STATES_UP_TO["cpu"][1]
    frames = limit // (100 * tree_bytes(state))
    assert choose_checkpoint(sim, state, bar.dt, frames, 100)[0] == "states"
    assert choose_checkpoint(sim, state, bar.dt, frames + 1, 100)[0] is True
    disks = jm.scene("disks")
    frames = limit // (100 * tree_bytes(disks.state)) + 1
    assert choose_checkpoint(disks.sim.with_backend("cpu"), disks.state, disks.dt, frames, 100)[0] == "states"


def test_gpu_policy_stores_small_residuals(bar):
    """Under the GPU policy a rollout whose residuals fit in 64 MiB (and the budget) stores them:
    measured 0.73-0.75x the recomputing gradient's time for the bar on an H200; beyond that, as on the
    CPU."""
    sim, state = bar.sim.with_backend("gpu"), bar.state
    per_step = residual_bytes(sim.step, state, bar.dt)
    assert per_step > tree_bytes(state)  # a step keeps more than its state
    assert choose_checkpoint(sim, state, bar.dt, 10, 100)[0] is False
    assert choose_checkpoint(sim, state, bar.dt, 10, 100, memory=per_step * 1000 - 1)[0] == "states"  # over budget
    big = 64 * 2**20 // per_step + 1  # steps whose residuals exceed the policy's 64 MiB
    assert choose_checkpoint(sim, state, bar.dt, 1, big)[0] == "states"


def test_auto_gradient_is_the_one_level_gradient(bar):
    """On the CPU "auto" runs checkpoint="states": the same gradient, bit for bit; a budget below
    every step's state runs two levels, a tight one "low_memory", each equal to round-off."""
    def loss(E, checkpoint, memory=None):
        sim = jm.set_params(bar.sim, E=E)
        final, _ = sim.run(bar.state, bar.dt, 200, 20, checkpoint=checkpoint, memory=memory)
        return jm.kinetic_energy(final)

    E = jnp.asarray(100.0)
    auto = jax.grad(loss)(E, "auto")
    assert auto == jax.grad(loss)(E, "states")
    assert abs(jax.grad(loss)(E, True) - auto) <= 1e-10 * abs(auto)
    below = f"{200 * tree_bytes(bar.state) - 1} B"  # one byte short of every step's state
    assert abs(jax.grad(loss)(E, "auto", below) - auto) <= 1e-10 * abs(auto)
    tight = jax.grad(loss)(E, "auto", "4 KiB")
    assert abs(tight - auto) <= 1e-10 * abs(auto)


def test_bad_memory_argument(bar):
    with pytest.raises(jm.InputError, match="memory"):
        bar.sim.run(bar.state, bar.dt, 20, 10, memory="plenty")


def test_one_level_recomputes_each_step_once(bar):
    """checkpoint="states" keeps every step's state, so its gradient program holds one forward step
    fewer than the two-level schedule's (which recomputes each segment, then each step): XLA's
    operation count of the compiled gradient (a loop body is counted once) drops by about one step's
    (measured 1.10-1.15 steps per level, remat included; benchmarks/compile_time.py: bar 2.64e4 ->
    1.91e4 against a rollout of 7.6e3)."""
    def loss(E, checkpoint):
        final, _ = jm.set_params(bar.sim, E=E).run(bar.state, bar.dt, 100, 10, checkpoint=checkpoint,
                                                   check_stability=False)
        return jm.kinetic_energy(final)

    def flops(fn, arg):
        return jax.jit(fn).lower(arg).compile().cost_analysis()["flops"]

    step = flops(lambda s: bar.sim.step(s, bar.dt), bar.state)
    E = jnp.asarray(100.0)
    one, two, three = (flops(jax.grad(lambda E, c=c: loss(E, c)), E) for c in ("states", True, "low_memory"))
    assert 0.9 * step <= two - one <= 1.3 * step, (step, one, two)
    assert 0.9 * step <= three - two <= 1.3 * step, (step, two, three)


def test_gradient_schedule_reports_what_auto_runs(bar):
    """jm.gradient_schedule: the schedule checkpoint="auto" picks, what it keeps, how many forward passes
    the backward pass runs again; nothing compiled."""
    sim, state, dt = bar.sim.with_backend("cpu"), bar.state, bar.dt
    one = jm.gradient_schedule(sim, state, dt, 1000, 100)
    assert one["checkpoint"] == "states" and one["recomputations"] == 1
    assert one["state_bytes"] == tree_bytes(state) and one["kept_bytes"] == 1000 * tree_bytes(state)
    assert one["step_residual_bytes"] == residual_bytes(sim.step, state, dt) > one["state_bytes"]
    assert one["reason"] == choose_checkpoint(sim, state, dt, 10, 100)[1]
    two = jm.gradient_schedule(sim, state, dt, 1000, 100, memory=one["kept_bytes"] - 1)
    assert two["checkpoint"] is True and two["recomputations"] == 2
    assert two["kept_bytes"] == (1000 // 25 + 25) * tree_bytes(state) <= two["budget_bytes"]
    three = jm.gradient_schedule(sim, state, dt, 1000, 100, memory=two["kept_bytes"] - 1)
    assert three["checkpoint"] == "low_memory" and three["recomputations"] == 3
    assert three["kept_bytes"] < two["kept_bytes"]
    for steps, save_every in ((1000, 300), (0, 1), (10.0, 1)):
        with pytest.raises(jm.InputError, match="steps"):
            jm.gradient_schedule(sim, state, dt, steps, save_every)
