"""Differentiable rollouts, checkpointing, calibration and ensembles (issue "Differentiable
rollouts").  Gradients are checked against central finite differences in float64 (docs/design.md)."""

import subprocess
import sys
import textwrap

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from cases import central_difference

import jaxmpm as jm

SCHEMES = {
    "flip": lambda: jm.FLIP(),
    "pic": lambda: jm.PIC(),
    "blend": lambda: jm.FLIP(beta=0.9),
    "xpic3": lambda: jm.XPIC(order=3, beta=0.2),
    "fmpm2": lambda: jm.FMPM(order=2, beta=0.1),
}


def make_loss(setup, steps, names, checkpoint=True, start=None):
    """Loss of a rollout as a function of named parameters plus the initial velocity amplitude.
    ``start`` replaces the initial positions/velocities/F (to begin a window mid-run).  ``checkpoint``
    is ``run``'s default, the schedule users differentiate (and whose gradient compiles faster than
    the plain one's: fewer, smaller programs); test_checkpointed_gradient_equals_plain compares them."""
    def loss(p):
        sim = jm.set_params(setup.sim, **{k: v for k, v in p.items() if k != "amplitude"})
        state = sim.init(setup.particles)  # masses follow the density
        if start is not None:
            state = eqx.tree_at(lambda s: (s.x, s.v, s.F), state, (start.x, start.v, start.F))
        state = eqx.tree_at(lambda s: s.v, state, p["amplitude"] * state.v)
        final, hist = sim.run(state, setup.dt, steps, steps // 4, checkpoint=checkpoint)
        return jm.kinetic_energy(final) + jnp.mean(hist.strain) + 1e-3 * jnp.sum(final.x**2) / final.x.shape[0]
    return loss


def step_size(name, value, beta_step=0.025):
    """Finite-difference step h of the fourth-order central difference (points x +- h, x +- 2h):
    relative 5e-5, except beta on the bar, whose effect over a short rollout is ~1e-7 of the loss,
    so round-off needs a wide step."""
    return beta_step if name == "beta" else 5e-5 * max(abs(float(value)), 1e-2)


def check_gradient(loss, params, rtol, beta_step=0.025):
    # the gradient once; the difference points (4 per parameter) through the forward program, which
    # compiles in a fraction of the gradient's time and runs 10-15x faster (disks, 100 steps)
    grad = jax.jit(jax.grad(loss))(params)
    f = jax.jit(loss)

    for name, value in params.items():
        def along(x, name=name):
            return f({**params, name: x})
        fd = central_difference(along, jnp.asarray(value), step_size(name, value, beta_step), order=4)
        g = grad[name]
        assert np.isfinite(g), name
        assert abs(g - fd) <= rtol * max(abs(fd), 1e-12), (name, float(g), float(fd))


@pytest.mark.slow
@pytest.mark.parametrize("scheme", list(SCHEMES))
def test_bar_gradients_all_parameters(scheme):
    setup = jm.scene("bar", scheme=SCHEMES[scheme](), damping=jm.Damping(0.02, 0.01))
    names = {"alpha_g": 0.02, "alpha_p": 0.01, "E": 100.0, "density": 1.0, "gravity": 0.01, "amplitude": 1.0}
    if scheme not in ("flip", "pic"):
        names["beta"] = float(jm.get_params(setup.sim, "beta")["beta"])
    params = {k: jnp.asarray(v) for k, v in names.items()}
    params["gravity"] = jnp.asarray([0.01])  # small: no particle crosses a node (S is only C0 there)
    loss = make_loss(setup, 100, names)
    # one compiled program: its gradient at params, its value (the forward loss) at the difference points
    value_and_grad = jax.jit(jax.value_and_grad(loss))
    grad = value_and_grad(params)[1]

    def f(p):
        return value_and_grad(p)[0]

    for name in params:
        def along(x, name=name):
            if name == "gravity":
                x = jnp.reshape(x, (1,))
            return f({**params, name: x})
        x0 = params[name][0] if name == "gravity" else params[name]
        fd = central_difference(along, x0, step_size(name, x0), order=4)
        g = grad[name][0] if name == "gravity" else grad[name]
        assert np.isfinite(g)
        assert abs(g - fd) <= 1e-6 * abs(fd), (name, float(g), float(fd))


# Linear shape functions make a rollout only piecewise smooth in its parameters: the loss has a
# kink wherever a particle crosses a node (S is C0 there), and the disks' particles cross nodes
# densely during contact, so central differences straddle kinks (measured: 10-1000% mismatch).
# Quadratic B-splines are C1; with them AD and Richardson differences agree to ~1e-9.
SMOOTH = jm.QuadraticBSpline()


@pytest.fixture(scope="module")
def disks_in_contact():
    """The disks (approaching at 0.5) after 250 FLIP steps: contact falls in the next 100 steps,
    so every parameter, beta included, acts on the window."""
    setup = jm.scene("disks", speed=0.5, shape=SMOOTH)
    final, _ = setup.sim.run(setup.state, setup.dt, 250, 250)
    return final


@pytest.mark.slow
@pytest.mark.parametrize("scheme", list(SCHEMES))
def test_disks_gradients(scheme, disks_in_contact):
    setup = jm.scene("disks", scheme=SCHEMES[scheme](), damping=jm.Damping(0.01, 0.01), speed=0.5, shape=SMOOTH)
    names = {"alpha_g": 0.01, "alpha_p": 0.01, "E": 1000.0, "nu": 0.3, "amplitude": 1.0}
    if scheme not in ("flip", "pic"):
        names["beta"] = float(jm.get_params(setup.sim, "beta")["beta"])
    params = {k: jnp.asarray(v) for k, v in names.items()}
    # in contact beta acts strongly; with C1 (quadratic) shapes the loss still has curvature
    # kinks, so the stencil must stay inside one smooth piece: reaching beta +- 1e-3 misses by
    # 3e-6, beta +- 1e-4 (h = 5e-5) agrees to 2e-12
    check_gradient(make_loss(setup, 100, names, start=disks_in_contact), params, 1e-6, beta_step=5e-5)


@pytest.mark.slow
def test_long_bar_rollout_gradient():
    """2000 steps (about 3 periods of the bar) under FLIP, d/d alpha_g and d/dE to 1e-4."""
    setup = jm.scene("bar", scheme=jm.XPIC(order=2), damping=jm.Damping(0.01, 0.0))
    params = {"alpha_g": jnp.asarray(0.01), "E": jnp.asarray(100.0), "amplitude": jnp.asarray(1.0)}
    check_gradient(make_loss(setup, 2000, params), params, 1e-4)


@pytest.mark.slow
def test_checkpointed_gradient_equals_plain():
    setup = jm.scene("bar", scheme=jm.FMPM(order=2))
    params = {"alpha_g": jnp.asarray(0.05), "E": jnp.asarray(100.0), "amplitude": jnp.asarray(1.0)}
    plain = jax.jit(jax.grad(make_loss(setup, 400, params, checkpoint=False)))(params)
    for checkpoint in ("states", True, "low_memory"):  # (an int L runs True's code: test_checkpoint_segments)
        remat = jax.jit(jax.grad(make_loss(setup, 400, params, checkpoint=checkpoint)))(params)
        for k in params:
            assert abs(remat[k] - plain[k]) <= 1e-10 * abs(plain[k]), (k, checkpoint)


def test_checkpoint_validation():
    setup = jm.scene("bar")
    with pytest.raises(jm.InputError, match="checkpoint"):
        setup.sim.run(setup.state, setup.dt, 20, 10, checkpoint=3)
    with pytest.raises(jm.InputError, match="low_memory"):
        setup.sim.run(setup.state, setup.dt, 20, 10, checkpoint="fast")


def test_checkpoint_segments():
    """checkpoint=True keeps the fewest states, frames * save_every / L segment starts plus the L
    step states of one segment (L | save_every); "low_memory" takes L ~ sqrt(save_every)."""
    from jaxmpm.run.driver import _segment_length

    assert _segment_length(1000, True, frames=1) == 25  # 40 + 25 states (the tie with 40 goes to the shorter)
    assert _segment_length(100, True, frames=10) == 25  # 40 + 25, against 20 + 50 or 100 + 10
    assert _segment_length(10, True, frames=10) == 10  # 10 + 10
    assert _segment_length(100, "low_memory", frames=10) == 10
    assert _segment_length(100, "states", frames=10) == 100  # one level: a frame's steps, each state kept
    assert _segment_length(100, 4, frames=10) == 4 and _segment_length(100, False) is None


# ------------------------------------------------------------------------------ calibration
# alpha_g (bar, FLIP, 0.2 -> 0.05) and alpha_p (bar, FMPM(2), 0.01 -> 0.05) fitted alone from the
# centre-of-mass velocity history (400 steps, a frame every 20) by Adam(0.1) within 1%, and E under
# FLIP on the disks (600 -> 1000): asserted by notebook 03, which tests/test_notebooks.py executes.
def relative_misfit(observe, target):
    def loss(params):
        return jnp.mean((observe(params) - target) ** 2) / jnp.mean(target**2)
    return loss


def particle_velocities(setup, start, steps, save_every):
    def observe(params):
        sim = jm.set_params(setup.sim, **params)
        state = eqx.tree_at(lambda s: (s.x, s.v, s.F), setup.state, (start.x, start.v, start.F))
        _, hist = sim.run(state, setup.dt, steps, save_every)
        return hist.v
    return observe


@pytest.mark.slow
@pytest.mark.parametrize("scheme, name, truth, guess", [
    (jm.XPIC(order=2, beta=0.3), "beta", 0.3, 0.7),
], ids=["xpic2-beta"])
def test_calibrate_on_disks(disks_in_contact, scheme, name, truth, guess):
    """beta of XPIC(2) from the particle velocities through the impact (null-space noise is what
    beta keeps or removes), over a 50-step window in contact.  L-BFGS reaches 1% for beta in 7
    iterations here (0.7 -> 0.300013); Adam(0.1) needs ~100.  (E under FLIP, 600 -> 1000 within 1%, is asserted by
    notebook 03 on its disks window, 20 steps at the size tests/test_notebooks.py runs it.)"""
    setup = jm.scene("disks", scheme=scheme, speed=0.5, shape=SMOOTH)
    observe = particle_velocities(setup, disks_in_contact, 50, 10)
    target = observe({name: truth})
    # L-BFGS with the backtracking line search of notebooks 03 and 05, which needs only the loss
    # (optax.lbfgs()'s default zoom search also takes gradients, a second copy of the gradient
    # program to compile: tests/test_open_core.py and test_transport.py run that one)
    lbfgs = optax.lbfgs(linesearch=optax.scale_by_backtracking_linesearch(max_backtracking_steps=20))
    result = jm.calibrate(relative_misfit(observe, target), {name: guess}, optimizer=lbfgs, steps=200, tol=1e-9)
    assert result.iterations <= 200
    assert abs(result.params[name] / truth - 1) <= 0.01, result.params


def test_calibrate_rejects_bad_input():
    with pytest.raises(jm.InputError, match="beta"):
        jm.calibrate(lambda p: p["beta"] ** 2, {"beta": 1.5})
    with pytest.raises(jm.InputError, match="unknown parameter"):
        jm.set_params(jm.scene("bar").sim, zeta=1.0)


# -------------------------------------------------------------------------------- ensembles
@pytest.mark.slow
def test_ensemble_equals_single_runs():
    setup = jm.scene("bar", scheme=jm.XPIC(order=2))
    betas = jnp.linspace(0.0, 0.9, 8)
    alphas = jnp.linspace(0.0, 0.1, 8)
    betas, alphas = jnp.concatenate([betas, betas]), jnp.concatenate([alphas, alphas[::-1]])
    final, hist, failed = jm.ensemble(setup.sim, setup.state, setup.dt, 100, 25,
                                      params={"beta": betas, "alpha_g": alphas})
    assert final.x.shape[0] == 16 and np.all(np.asarray(failed) == -1)
    for b in range(16):
        sim = jm.set_params(setup.sim, beta=betas[b], alpha_g=alphas[b])
        f1, h1 = sim.run(setup.state, setup.dt, 100, 25, save_particles=False)
        np.testing.assert_allclose(final.v[b], f1.v, rtol=1e-12, atol=1e-15)
        np.testing.assert_allclose(hist.kinetic[b], h1.kinetic, rtol=1e-12, atol=1e-15)


SHARDED = textwrap.dedent("""
    import os, sys
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=2").strip()
    import jax
    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp, numpy as np
    import jaxmpm as jm
    assert len(jax.devices()) == 2
    setup = jm.scene("bar", scheme=jm.XPIC(order=2))
    betas = jnp.linspace(0.0, 0.9, 16)
    # each device runs its 8 members (shard_map) batched, one after another, and in chunks of 2
    out = {s + str(c): np.asarray(jm.ensemble(setup.sim, setup.state, setup.dt, 100, 25, params={"beta": betas},
                                              strategy=s, chunk=c)[0].v)
           for s, c in (("auto", None), ("sequential", None), ("vmap", 2))}
    # and the gradient of a loss of the sharded ensemble (vmapped members), d/d beta
    def loss(b):
        final = jm.ensemble(setup.sim, setup.state, setup.dt, 100, 25, params={"beta": b}, strategy="vmap")[0]
        return jnp.sum(jax.vmap(jm.kinetic_energy)(final))
    out["grad"] = np.asarray(jax.grad(loss)(betas))
    np.savez(sys.argv[1], **out)
""")


@pytest.mark.slow
def test_ensemble_sharded_over_two_host_devices(tmp_path):
    out = tmp_path / "sharded.npz"
    subprocess.run([sys.executable, "-c", SHARDED, str(out)], check=True, timeout=300)
    setup = jm.scene("bar", scheme=jm.XPIC(order=2))
    betas = jnp.linspace(0.0, 0.9, 16)
    final, _, _ = jm.ensemble(setup.sim, setup.state, setup.dt, 100, 25, params={"beta": betas})
    sharded = np.load(out)
    assert sorted(sharded.files) == ["autoNone", "grad", "sequentialNone", "vmap2"]
    for name in ("autoNone", "sequentialNone", "vmap2"):
        np.testing.assert_allclose(sharded[name], np.asarray(final.v), rtol=1e-12, atol=1e-15)

    def loss(b):
        final = jm.ensemble(setup.sim, setup.state, setup.dt, 100, 25, params={"beta": b}, strategy="vmap")[0]
        return jnp.sum(jax.vmap(jm.kinetic_energy)(final))

    one_device = np.asarray(jax.grad(loss)(betas))
    assert np.all(np.isfinite(one_device)) and np.any(one_device != 0)
    np.testing.assert_allclose(sharded["grad"], one_device, rtol=1e-10, atol=1e-300)


def test_forward_over_reverse_through_a_rollout():
    """jax.jacfwd(jax.grad(loss)) (a Hessian, forward over reverse) through sim.run equals central
    differences of the gradient (float64).  It recursed without end until 2026-11-28: the CPU
    policy's stage boundaries were a custom_vmap whose rule called itself, and forward mode over the
    reverse pass vmapped that rule again at every level (now jaxmpm.transfer.backend._barrier)."""
    setup = jm.scene("bar")

    def loss(E):
        final, _ = jm.set_params(setup.sim, E=E).run(setup.state, setup.dt, 100, 20)
        return jm.kinetic_energy(final)

    E, eps = jnp.asarray(100.0), 1e-3
    hessian = jax.jacfwd(jax.grad(loss))(E)
    central = (jax.grad(loss)(E + eps) - jax.grad(loss)(E - eps)) / (2 * eps)
    assert hessian != 0 and abs(hessian - central) <= 1e-8 * abs(central), (hessian, central)  # measured 2.6e-10
