"""Progress of jm.calibrate and jm.ensemble (jaxmpm/run/progress.py): the compilation timed apart and
shown when asked, nothing shown otherwise (pytest's captured stderr is not a terminal: the default is
off), and not one number changed, neither by showing progress nor by compiling ahead of time (the
losses and parameters equal, bit for bit, those of the plain jax.jit loop calibrate ran before)."""

import sys
import types

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from cases import small_simulation

import jaxmpm as jm
from jaxmpm.run import progress as progress_module

COMPILING = "jaxmpm calibrate: compiling the loss and its gradient ..."


def quadratic(params):
    """A bounded and an unbounded parameter, minimum at scale = 2, shift = -1."""
    return (jnp.log(params["scale"] / 2.0)) ** 2 + 0.5 * (params["shift"] + 1.0) ** 2


INIT = {"scale": 0.5, "shift": 0.3}
BOUNDS = {"scale": "positive", "shift": None}


def plain_jit_calibrate(loss, init, bounds, optimizer, steps):
    """The loop jm.calibrate ran before it compiled ahead of time (a plain jax.jit update, called on
    the first iteration): the reference the results must equal bit for bit."""
    from jaxmpm.run.calibrate import _transform

    transforms = {k: _transform(bounds[k]) for k in init}
    raw = {k: transforms[k][1](jnp.asarray(v, dtype=jnp.result_type(float))) for k, v in init.items()}

    def constrained(r):
        return {k: transforms[k][0](r[k]) for k in r}

    state = optimizer.init(raw)
    state = jax.tree_util.tree_map(lambda a: jnp.asarray(a, dtype=a.dtype) if hasattr(a, "dtype") else a, state)

    def raw_loss(rr):
        return loss(constrained(rr))

    @jax.jit
    def update(r, s):
        value, grads = jax.value_and_grad(raw_loss)(r)
        with jax.numpy_dtype_promotion("standard"):
            updates, s = optimizer.update(grads, s, r, value=value, grad=grads, value_fn=raw_loss)
        return optax.apply_updates(r, updates), s, value

    losses, trajectory = [], {k: [] for k in init}
    for _ in range(steps):
        params = constrained(raw)
        raw, state, value = update(raw, state)
        losses.append(float(value))
        for k in init:
            trajectory[k].append(np.asarray(params[k]))
    return np.asarray(losses), {k: np.asarray(v) for k, v in trajectory.items()}, constrained(raw)


def assert_same(result, losses, trajectory, final):
    np.testing.assert_array_equal(result.losses, losses)
    for k in final:
        np.testing.assert_array_equal(result.trajectory[k], trajectory[k])
        np.testing.assert_array_equal(result.params[k], np.asarray(final[k]))


@pytest.mark.parametrize("optimizer", [optax.adam(0.1), optax.lbfgs()], ids=["adam", "lbfgs"])
def test_results_bit_for_bit_as_before_with_and_without_progress(optimizer, capsys):
    reference = plain_jit_calibrate(quadratic, INIT, BOUNDS, optimizer, 12)
    quiet = jm.calibrate(quadratic, INIT, bounds=BOUNDS, optimizer=optimizer, steps=12, progress=False)
    # a new loss function, so that this call compiles too (the same one reuses quiet's program, issue 30)
    shown = jm.calibrate(lambda p: quadratic(p), INIT, bounds=BOUNDS, optimizer=optimizer, steps=12, progress=True)
    assert quiet.iterations == shown.iterations == 12
    assert_same(quiet, *reference)
    assert_same(shown, *reference)
    assert 0 < quiet.compile_time <= quiet.wall_time and 0 < shown.compile_time <= shown.wall_time
    capsys.readouterr()


@pytest.mark.slow
def test_an_mpm_calibration_bit_for_bit_as_before():
    """A simulation's loss (16 cells, 20 steps of FLIP): L-BFGS on E from 1.5, truth 2."""
    sim = small_simulation()
    state = sim.init(jm.fill(sim.grid, jm.Box((6.0,), (10.0,)), ppc=2, velocity=lambda x: 0.1 * (x - 8.0)))

    def observe(params):
        _, history = jm.set_params(sim, **params).run(state, 0.1, 20, 5)
        return history.v

    target = observe({"E": 2.0})

    def loss(params):
        return jnp.mean((observe(params) - target) ** 2) / jnp.mean(target**2)

    lbfgs = optax.lbfgs(linesearch=optax.scale_by_backtracking_linesearch(max_backtracking_steps=20))
    reference = plain_jit_calibrate(loss, {"E": 1.5}, {"E": "positive"}, lbfgs, 4)
    result = jm.calibrate(loss, {"E": 1.5}, optimizer=lbfgs, steps=4)
    assert_same(result, *reference)
    assert result.losses[-1] < result.losses[0]


def test_progress_shows_the_compilation_then_the_iterations(capsys):
    result = jm.calibrate(lambda p: quadratic(p), INIT, bounds=BOUNDS, steps=5, progress=True)  # compiled anew
    err = capsys.readouterr().err
    assert COMPILING in err and err.index(COMPILING) < err.index("jaxmpm calibrate: ", len(COMPILING))
    compiled = err.split(COMPILING, 1)[1].split("\n", 1)[0]
    assert compiled.strip().endswith(" s") and float(compiled.split()[0]) >= 0  # " 0.021 s"
    assert "5/5" in err and "loss" in err and "|grad|" in err  # the bar's last state
    assert f"loss {result.losses[-1]:.3e}" in err


def test_no_progress_when_off_or_not_interactive(capfd):
    jm.calibrate(quadratic, INIT, bounds=BOUNDS, steps=3, progress=False)
    jm.calibrate(quadratic, INIT, bounds=BOUNDS, steps=3)  # the default: pytest's stderr is no terminal
    out, err = capfd.readouterr()
    assert out == "" and err == ""


def test_tol_stops_the_bar_early(capsys):
    result = jm.calibrate(quadratic, INIT, bounds=BOUNDS, optimizer=optax.lbfgs(), steps=50, tol=1e-6, progress=True)
    assert result.iterations < 50
    assert f"{result.iterations}/50" in capsys.readouterr().err


def test_bad_progress_is_an_input_error():
    with pytest.raises(jm.InputError, match="progress = 'yes' must be True, False or None"):
        jm.calibrate(quadratic, INIT, bounds=BOUNDS, progress="yes")
    with pytest.raises(jm.InputError, match="ensemble: progress = 1"):
        jm.ensemble(small_simulation(), None, 0.1, 4, params={"beta": [0.5]}, progress=1)


def test_an_optimizer_whose_state_changes_type_compiles_again():
    """As a plain jax.jit would: a weakly typed counter (here kept weak on purpose) becomes strong
    after the first update, so the program for the second iteration's arguments is compiled too."""
    compiled = progress_module.AheadOfTime(jax.jit(lambda x, n: (x * 2.0, n + jnp.int32(1))), "test", False)
    x, n = jnp.ones(3), jnp.asarray(0)
    assert jax.typeof(n).weak_type
    x, n = compiled(x, n)
    x, n = compiled(x, n)
    assert len(compiled.programs) == 2 and compiled.compile_time > 0
    np.testing.assert_array_equal(x, 4.0 * np.ones(3))
    assert int(n) == 2


def test_ensemble_progress(capfd):
    sim = small_simulation()
    state = sim.init(jm.fill(sim.grid, jm.Box((6.0,), (10.0,)), ppc=2, velocity=lambda x: 0.1 * (x - 8.0)))
    betas = jnp.asarray([0.0, 0.5, 1.0])
    quiet = jm.ensemble(sim, state, 0.1, 8, 4, params={"beta": betas}, progress=False)
    default = jm.ensemble(sim, state, 0.1, 8, 4, params={"beta": betas})
    assert capfd.readouterr() == ("", "")
    shown = jm.ensemble(sim, state, 0.1, 8, 4, params={"beta": betas}, progress=True)
    err = capfd.readouterr().err
    assert "jaxmpm ensemble: 3 members x 8 steps: compiling ..." in err
    assert "jaxmpm ensemble: 3 members x 8 steps: running ..." in err
    for a, b, c in zip(*(jax.tree_util.tree_leaves(r) for r in (quiet, default, shown))):
        np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(a, c)


def test_interactive_is_a_terminal_or_a_jupyter_kernel(monkeypatch):
    assert not progress_module.interactive()  # pytest captures stderr
    monkeypatch.setattr(sys, "stderr", types.SimpleNamespace(isatty=lambda: True))
    assert progress_module.interactive()
    monkeypatch.setattr(sys, "stderr", types.SimpleNamespace(isatty=lambda: False))
    shell = types.SimpleNamespace(kernel=None)
    monkeypatch.setitem(sys.modules, "IPython", types.SimpleNamespace(get_ipython=lambda: shell))
    assert not progress_module.interactive()  # the terminal IPython (its stderr a terminal: above)
    shell.kernel = object()
    assert progress_module.interactive()  # a Jupyter kernel
