"""jaxmpm's warnings name the user's line (jaxmpm.core.warn.warn), not a jaxmpm, equinox or JAX file."""

import inspect
import os
import warnings

import equinox
import jax
import pytest

import jaxmpm as jm
from jaxmpm.core.warn import warn


def line_of(marker: str) -> int:
    """The line of this file holding ``marker`` (a comment after the call that warns)."""
    lines = inspect.getsource(inspect.getmodule(line_of)).splitlines()
    hits = [i + 1 for i, line in enumerate(lines) if line.rstrip().endswith(marker) and "line_of(" not in line]
    assert len(hits) == 1, marker
    return hits[0]


def only_warning(record):
    assert len(record) == 1, [str(w.message) for w in record]
    return record[0]


def test_high_order_warning_names_the_callers_line():
    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter("always")
        jm.XPIC(order=41)  # xpic
        jm.FMPM(order=45)  # fmpm
        jm.scheme_from_name("xpic:50")  # by name
    assert all("order" in str(w.message) and issubclass(w.category, UserWarning) for w in record)
    # before: equinox/_module/_better_abstract.py, line 233, for all three
    assert [(w.filename, w.lineno) for w in record] == [
        (__file__, line_of(m)) for m in ("# xpic", "# fmpm", "# by name")]


def test_warning_inside_a_traced_function_names_the_callers_line():
    def loss(beta):
        return jm.XPIC(order=42, beta=beta).beta  # traced

    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter("always")
        jax.jit(loss)(0.5)
    w = only_warning(record)
    assert w.filename == __file__ and w.lineno == line_of("# traced")


def compiled(source: str, filename: str, name: str):
    """A function compiled as if it lived in ``filename`` (frames there count as that package's)."""
    namespace = {}
    exec(compile(source, filename, "exec"), namespace)
    return namespace[name]


def test_any_depth_of_jaxmpm_equinox_and_jax_frames_is_skipped():
    """user -> 'jax' frame -> 'equinox' frame -> 'jaxmpm' frame -> warn: the user's line."""
    inner = compiled("def inner(warn):\n    warn('deep', RuntimeWarning)\n",
                     os.path.join(os.path.dirname(jm.__file__), "_not_a_module.py"), "inner")
    middle = compiled("def middle(f, warn):\n    f(warn)\n",
                      os.path.join(os.path.dirname(equinox.__file__), "_not_a_module.py"), "middle")
    outer = compiled("def outer(g, f, warn):\n    g(f, warn)\n",
                     os.path.join(os.path.dirname(jax.__file__), "_not_a_module.py"), "outer")
    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter("always")
        outer(middle, inner, warn)  # deep
    w = only_warning(record)
    assert w.category is RuntimeWarning and w.filename == __file__ and w.lineno == line_of("# deep")


def test_filters_still_apply():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(UserWarning, match="order 41"):
            jm.XPIC(order=41)


def test_cfl_warning_names_the_callers_line():
    """sim.run above the CFL limit: through Simulation.run (an equinox method) and the driver."""
    setup = jm.scene("bar", cells=4, t_end=2.0, frames=1)
    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter("always")
        setup.sim.run(setup.state, 20 * setup.dt, 1, check_stability=False)  # cfl
    w = only_warning(record)
    assert w.category is jm.StableTimeStepWarning and w.filename == __file__ and w.lineno == line_of("# cfl")
