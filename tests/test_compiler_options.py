"""The backend's XLA compile options for programs built from the library's steps (jm.compiler_options,
jaxmpm/transfer/backend.py XLA_OPTIONS): on the CPU, reductions stay in XLA's own loops rather than a
library fusion (1.3x on a 131k-particle gradient, benchmarks/README.md).  Speed only: a gradient
compiled with them equals the default program's to round-off; an option this jaxlib does not know is
left out rather than failing the compile."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxmpm as jm
from jaxmpm.transfer import backend


def test_the_options_keep_the_gradient_and_drop_the_library_reductions():
    """d(kinetic energy after 10 mpm88 steps)/dE with and without the options: equal to 1e-12
    (relative); the compiled program with them holds no "ynn" library fusion."""
    setup = jm.scene("mpm88", n_particles=512, n_grid=16)

    def loss(E):
        final = jm.set_params(setup.sim, E=E).rollout(setup.state, setup.dt, 1, save_every=10)[0]
        return jnp.sum(final.mass[:, None] * final.v ** 2)

    options = jm.compiler_options("cpu")
    if not options:  # pragma: no cover - a jaxlib without the option (the registry's 0.10.2 has it)
        pytest.skip("this jaxlib does not know xla_cpu_experimental_ynn_fusion_type")
    assert options == {"xla_cpu_experimental_ynn_fusion_type": ""}
    E = jnp.asarray(400.0)
    plain, tuned = jax.jit(jax.grad(loss)), jax.jit(jax.grad(loss), compiler_options=options)
    assert "ynn" not in tuned.lower(E).compile().as_text()
    np.testing.assert_allclose(float(tuned(E)), float(plain(E)), rtol=1e-12)
    assert float(plain(E)) != 0.0


def test_unknown_options_are_left_out(monkeypatch):
    """A GPU gets none; an option XLA rejects (a renamed flag in another jaxlib) is dropped."""
    assert jm.compiler_options("gpu") == {}
    monkeypatch.setattr(backend, "XLA_OPTIONS", {"cpu": {"xla_cpu_no_such_option": "", **backend.XLA_OPTIONS["cpu"]},
                                                 "gpu": {}})
    assert "xla_cpu_no_such_option" not in jm.compiler_options("cpu")


def test_fast_compile_keeps_the_gradient():
    """``fast_compile=True`` (XLA's older CPU emitters, XLA_FAST_COMPILE): the mpm88 gradient above equal
    to the default program's to 1e-12 (relative); a GPU gets nothing more; a bad value is an InputError."""
    setup = jm.scene("mpm88", n_particles=512, n_grid=16)

    def loss(E):
        final = jm.set_params(setup.sim, E=E).rollout(setup.state, setup.dt, 1, save_every=10)[0]
        return jnp.sum(final.mass[:, None] * final.v ** 2)

    fast = jm.compiler_options("cpu", fast_compile=True)
    assert fast == {**jm.compiler_options("cpu"), "xla_cpu_use_fusion_emitters": False}
    assert jm.compiler_options("gpu", fast_compile=True) == {}
    E = jnp.asarray(400.0)
    plain = jax.jit(jax.grad(loss), compiler_options=jm.compiler_options("cpu"))
    quick = jax.jit(jax.grad(loss), compiler_options=fast)
    np.testing.assert_allclose(float(quick(E)), float(plain(E)), rtol=1e-12)
    with pytest.raises(jm.InputError, match="fast_compile = 'yes'; pass True or False"):
        jm.compiler_options(fast_compile="yes")


def test_calibrate_fast_compile():
    """``jm.calibrate(..., fast_compile=True)``: the same iterates as the default program's (to 1e-12: another
    code generator may round differently), its own compiled update, and a bad value is an InputError."""

    def loss(params):
        return jnp.log(params["scale"] / 2.0) ** 2 + 0.5 * (params["shift"] + 1.0) ** 2

    init, bounds = {"scale": 0.5, "shift": 0.3}, {"scale": "positive", "shift": None}
    default = jm.calibrate(loss, init, bounds=bounds, steps=5)
    fast = jm.calibrate(loss, init, bounds=bounds, steps=5, fast_compile=True)
    assert fast.compile_time > 0  # not the default's program, reused
    np.testing.assert_allclose(fast.losses, default.losses, rtol=1e-12)
    for k in init:
        np.testing.assert_allclose(fast.params[k], default.params[k], rtol=1e-12)
    with pytest.raises(jm.InputError, match="calibrate: fast_compile = 1; pass True or False"):
        jm.calibrate(loss, init, bounds=bounds, steps=5, fast_compile=1)
