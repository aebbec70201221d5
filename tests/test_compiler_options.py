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
