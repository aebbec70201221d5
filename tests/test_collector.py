"""Python's garbage collector while jaxmpm traces (jaxmpm/run/collector.py): the first threshold
raised for the span of jaxmpm's tracing calls and restored after them, a user's own setting kept.
The speed-up itself is measured in benchmarks/tracing_gc.py, not here."""

import gc

import pytest

import jaxmpm as jm
from jaxmpm.run import collector


@pytest.fixture
def thresholds():
    """CPython's default thresholds for the test (tests/conftest.py raises them for the suite),
    the suite's restored after it."""
    saved = gc.get_threshold()
    gc.set_threshold(700, 10, 10)
    yield
    gc.set_threshold(*saved)


def test_raised_inside_and_restored_after(thresholds):
    with collector.fewer_collections():
        assert gc.get_threshold() == (collector.TRACING_THRESHOLD, 10, 10)
    assert gc.get_threshold() == (700, 10, 10)
    with pytest.raises(ZeroDivisionError), collector.fewer_collections():
        1 / 0
    assert gc.get_threshold() == (700, 10, 10)  # restored on an error too


def test_a_higher_threshold_and_a_disabled_collector_are_left_alone(thresholds):
    gc.set_threshold(10 * collector.TRACING_THRESHOLD, 5, 5)
    with collector.fewer_collections():
        assert gc.get_threshold() == (10 * collector.TRACING_THRESHOLD, 5, 5)
    gc.set_threshold(700, 10, 10)
    gc.disable()
    try:
        with collector.fewer_collections():
            assert gc.get_threshold() == (700, 10, 10)
    finally:
        gc.enable()


def test_run_traces_inside_and_restores(thresholds):
    """sim.run (and so a rollout traced inside a user's jax.jit) runs inside the block; the
    process's thresholds are back after the call."""
    seen = []

    class Probe(jm.Simulation):
        def step(self, state, dt):
            seen.append(gc.get_threshold()[0])
            return super().step(state, dt)

    setup = jm.scene("bar", cells=8)
    sim = Probe(**{f: getattr(setup.sim, f) for f in setup.sim.__dataclass_fields__})
    sim.run(setup.state, setup.dt, 2, 2, progress=False)
    assert seen and set(seen) == {collector.TRACING_THRESHOLD}
    assert gc.get_threshold() == (700, 10, 10)
