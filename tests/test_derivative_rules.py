"""Derivative rules that change only how a gradient is computed (jaxmpm.transfer.backend, the structured
adjoint): each gives the values and derivatives, forward and reverse, of the same code differentiated
by JAX itself (``adjoint="autodiff"``), and the helpers
written for a cheaper transpose give the values of the expressions they replace (bit for bit; the fluid's
square root to one unit in the last place).

* ``scatter_planar`` of (C, K, N) columns: its tangent is one scalar scatter per component behind a stage
  boundary, so that in reverse mode each component of the nodal cotangent is gathered planar (K, N);
* ``to_particle_major``: its tangent is held planar, so that the cotangent of a G2P result is evaluated once
  before the per-slot products read it;
* ``isotropic`` (s I stacked) and the fluid's square root (J ** (1/2));
* G2P's shared reads (``jaxmpm.transfer.kernels.shared_reads``): inside a G2P each nodal field is read at
  the slots once and the grid's v, a and v~ together, so the operators' cotangents go back onto the nodes
  in one scatter; the values are those of separate reads, bit for bit.

Timings are in benchmarks/README.md ("Cotangents evaluated once where they are read").
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxmpm as jm
from jaxmpm.core.linalg import det
from jaxmpm.materials.base import isotropic
from jaxmpm.materials.fluid import volumetric_part
from jaxmpm.transfer.backend import use_adjoint
from jaxmpm.transfer.kernels import shared_reads
from jaxmpm.transfer.kernels.xla import scatter_planar, to_particle_major
from jaxmpm.transfer.operators import Transfer

K, N, NODES = 9, 40, 25


def derivatives(fn, x, tangent, cotangent):
    """(value, JVP, VJP) of ``fn`` at ``x``, in one compiled program."""
    def both(x, tangent, cotangent):
        value, jvp = jax.jvp(fn, (x,), (tangent,))
        return value, jvp, jax.vjp(fn, x)[1](cotangent)[0]
    return jax.jit(both)(x, tangent, cotangent)


def assert_same(fn, x, out_shape, seed):
    """``fn``'s value, JVP and VJP under the structured rules equal those of JAX's own autodiff of it."""
    keys = jax.random.split(jax.random.PRNGKey(seed), 2)
    tangent = jax.random.normal(keys[0], x.shape, x.dtype)
    cotangent = jax.random.normal(keys[1], out_shape, x.dtype)
    with use_adjoint("structured"):
        ruled = derivatives(fn, x, tangent, cotangent)
    with use_adjoint("autodiff"):
        expected = derivatives(fn, x, tangent, cotangent)
    for got, want in zip(ruled, expected):
        np.testing.assert_allclose(got, want, rtol=1e-14, atol=1e-14)


@pytest.mark.parametrize("components", [None, 3])
def test_the_planar_scatter_rule_has_the_plain_derivatives(components):
    index = jax.random.randint(jax.random.PRNGKey(0), (K, N), 0, NODES)
    shape = (K, N) if components is None else (components, K, N)
    c = jax.random.normal(jax.random.PRNGKey(1), shape, jnp.float64)
    out_shape = (NODES,) if components is None else (NODES, components)
    assert_same(lambda c: scatter_planar(index, c, NODES), c, out_shape, seed=2)


@pytest.mark.parametrize("shape", [(2, N), (2, 2, N)])
def test_the_particle_major_rule_has_the_plain_derivatives(shape):
    planar = jax.random.normal(jax.random.PRNGKey(3), shape, jnp.float64)
    out_shape = (shape[-1],) + shape[:-1]
    assert_same(to_particle_major, planar, out_shape, seed=4)


@pytest.mark.parametrize("d", [1, 2, 3])
def test_isotropic_is_s_times_the_identity(d):
    s = jax.random.normal(jax.random.PRNGKey(d), (5, 7), jnp.float64)
    eye = jnp.eye(d, dtype=s.dtype)
    np.testing.assert_array_equal(isotropic(s, d), s[..., None, None] * eye[None, None])
    # its transpose: the cotangent of s is the trace of the matrix cotangent
    ct = jax.random.normal(jax.random.PRNGKey(10 + d), (5, 7, d, d), jnp.float64)
    np.testing.assert_allclose(jax.vjp(lambda s: isotropic(s, d), s)[1](ct)[0], jnp.trace(ct, axis1=-2, axis2=-1),
                               rtol=1e-14)  # the diagonal summed in another order


def test_the_fluids_square_root_is_the_power_it_replaced():
    """volumetric_part in 2D: sqrt(J) I, the values of J ** (1/2) I it replaced to the last bit or one unit in
    it (XLA's vectorised power is not always correctly rounded, the square root is); F itself where J <= 0."""
    F = jnp.eye(2)[None] + 0.3 * jax.random.normal(jax.random.PRNGKey(5), (4000, 2, 2), jnp.float64)

    def with_power(F):
        J = det(F)
        iso = (jnp.where(J > 0, J, 1.0) ** 0.5)[:, None, None] * jnp.eye(2)[None]
        return jnp.where((J > 0)[:, None, None], iso, F)

    got, expected = jax.jit(volumetric_part)(F), jax.jit(with_power)(F)
    assert bool(jnp.any(det(F) <= 0)) and bool(jnp.any(det(F) > 0))
    np.testing.assert_allclose(got, expected, rtol=2.3e-16, atol=0)


def _count(fn, name, *args):
    """How many ``name`` equations the jaxpr of ``fn(*args)`` holds, nested jaxprs included."""
    found = 0

    def walk(jaxpr):
        nonlocal found
        for eqn in jaxpr.eqns:
            found += eqn.primitive.name == name
            for sub in jax.extend.core.jaxprs_in_params(eqn.params):
                walk(sub)

    walk(jax.make_jaxpr(fn)(*args).jaxpr)
    return found


def _g2p_reads(shared: bool):
    """Five G2P operators on the grid's v, a and v~ of 60 particles on a 2D quadratic B-spline grid (the
    reads of FLIP's update, APIC's update and affine moment and a strain update), with the kernel's
    reads shared or not; returns (fn of the three fields, the fields)."""
    grid = jm.Grid((0.0, 0.0), (1.0, 1.0), (8, 8))
    x = 0.1 + 0.8 * jax.random.uniform(jax.random.PRNGKey(20), (60, 2), jnp.float64)
    stencil = jm.QuadraticBSpline().stencil(grid, x)
    transfer = Transfer.build(stencil, jnp.ones(60), grid.num_nodes)
    fields = [jax.random.normal(jax.random.PRNGKey(21 + j), (grid.num_nodes, 2), jnp.float64) for j in range(3)]

    def reads(v, a, v_tilde):
        def all_five():
            return (transfer.gather(v), transfer.gather(a), transfer.gather(v_tilde),
                    transfer.affine_moment(v_tilde), transfer.velocity_gradient(v_tilde))
        if not shared:
            return all_five()
        with shared_reads(stencil.index, [v, a, v_tilde]):
            return all_five()

    return reads, fields


def test_shared_reads_give_the_same_values_and_one_scatter_in_reverse():
    separate, fields = _g2p_reads(shared=False)
    shared, _ = _g2p_reads(shared=True)
    got, want = jax.jit(shared)(*fields), jax.jit(separate)(*fields)
    for g, w in zip(got, want):
        np.testing.assert_array_equal(g, w)

    cotangents = [jax.random.normal(jax.random.PRNGKey(30 + j), w.shape, w.dtype) for j, w in enumerate(want)]

    def pullback(fn):
        return lambda *fields: jax.vjp(fn, *fields)[1](tuple(cotangents))

    with use_adjoint("structured"):
        np.testing.assert_allclose(jax.jit(pullback(shared))(*fields), jax.jit(pullback(separate))(*fields),
                                   rtol=1e-13, atol=1e-14)  # the same sums, per slot first
        # five reads of three fields: one scatter of the cotangents shared, five (one per operator) otherwise
        assert _count(pullback(shared), "scatter-add", *fields) == 1
        assert _count(pullback(separate), "scatter-add", *fields) == 5
    with use_adjoint("autodiff"):  # the reference adjoint reads once too, its values the same
        np.testing.assert_allclose(jax.jit(pullback(shared))(*fields), jax.jit(pullback(separate))(*fields),
                                   rtol=1e-13, atol=1e-14)


def test_shared_reads_are_forgotten_when_the_block_ends():
    """A field read inside the block is read again after it (no value outlives its block, so no tracer of
    one trace reaches another)."""
    reads, fields = _g2p_reads(shared=True)
    inside = _count(lambda *f: reads(*f)[2:], "gather", *fields)
    twice = _count(lambda *f: reads(*f)[2:] + reads(*f)[2:], "gather", *fields)
    assert twice == 2 * inside > 0


def test_a_read_inside_a_nested_trace_is_not_kept_for_the_outer_one():
    """A group field read first inside a loop body (its values that trace's) is read again outside it,
    not taken from the body's trace (which would leak its tracers); the values are the same."""
    grid = jm.Grid((0.0, 0.0), (1.0, 1.0), (8, 8))
    x = 0.1 + 0.8 * jax.random.uniform(jax.random.PRNGKey(40), (30, 2), jnp.float64)
    stencil = jm.QuadraticBSpline().stencil(grid, x)
    transfer = Transfer.build(stencil, jnp.ones(30), grid.num_nodes)
    v = jax.random.normal(jax.random.PRNGKey(41), (grid.num_nodes, 2), jnp.float64)

    def reads(v):
        with shared_reads(stencil.index, [v]):
            inside = jax.lax.fori_loop(0, 2, lambda i, total: total + transfer.gather(v), jnp.zeros((30, 2)))
            return inside, transfer.gather(v)

    inside, outside = jax.jit(reads)(v)
    np.testing.assert_array_equal(inside, 2 * outside)


@pytest.mark.parametrize("backend, boundaries", [("gpu", False), ("cpu", True)])
def test_rules_are_traced_under_the_models_policy(backend, boundaries):
    """JAX traces the transfer layer's JVP rules when it differentiates, after the jitted rollout that called them
    has been traced (``jax.grad`` of ``sim.run``): they still follow the model's backend policy.  Under the GPU
    policy, traced here on a CPU, the gradient program holds no stage boundary (``cond``); until 2026-11-29 the
    rules traced late read the platform's policy, and a disks gradient held 16 of the CPU policy's."""
    import equinox as eqx

    setup = jm.scene("disks", spacing=0.1)
    sim, state, dt = setup.sim.with_backend(backend), setup.state, setup.dt

    def loss(v0):
        final, _ = sim.run(eqx.tree_at(lambda s: s.v, state, v0), dt, 2, 2, save_particles=False)
        return jnp.sum(final.v ** 2)

    conds = str(jax.make_jaxpr(jax.grad(loss))(state.v)).count(" cond[")
    assert (conds > 0) == boundaries, conds
