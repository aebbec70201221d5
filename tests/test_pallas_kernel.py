"""The Pallas transfer kernel (jaxmpm/transfer/kernels/pallas.py) against the XLA kernel, on the CPU
in Pallas' interpret mode: every kernel method, every contraction kind, its derivative rules, and
whole simulation steps (single and vmapped) give the XLA kernel's numbers; and, with no GPU at
hand, the kernels are lowered for CUDA (Triton) to catch what a device would refuse.  Tiny grids
and a few dozen particles (interpret mode compiles the kernels into loops over particle blocks); the
full shape x dimension matrix is in the slow tier, one representative per dimension in the fast one."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxmpm as jm
from jaxmpm.transfer.backend import KERNEL_TABLE, choose_kernel
from jaxmpm.transfer.contractions import Affine, Divergence, Gradient, Hoop, PerSlot, Weighted
from jaxmpm.transfer.kernels.pallas import PallasKernel, _same_nodes
from jaxmpm.transfer.kernels.xla import XLAKernel

XLA = XLAKernel()
PALLAS = PallasKernel(block=32)  # a few blocks for ~50 particles, the last one padded
REDUCED = PallasKernel(block=32, reduce=True)
TUNED = PallasKernel(block=32, planar=True, unroll=True)  # nodal arrays addressed by column, slots unrolled
SHAPES = {"linear": jm.Linear(), "ugimp": jm.UGIMP(ppc=2), "quadratic": jm.QuadraticBSpline(),
          "cubic": jm.CubicBSpline()}
FAST = {(1, "cubic"), (2, "quadratic"), (3, "linear")}
CASES = [pytest.param(d, s, marks=() if (d, s) in FAST else pytest.mark.slow)
         for d in (1, 2, 3) for s in SHAPES]


def _inputs(dim, num_particles=50, cells=5, dtype=jnp.float64, seed=0):
    grid = jm.Grid([0.0] * dim, [1.0] * dim, [cells] * dim)
    keys = jax.random.split(jax.random.PRNGKey(seed), 5)
    x = (0.25 + 0.5 * jax.random.uniform(keys[0], (num_particles, dim))).astype(dtype)
    m = (0.5 + jax.random.uniform(keys[1], (num_particles,))).astype(dtype)
    v = jax.random.normal(keys[2], (num_particles, dim), dtype)
    tau = jax.random.normal(keys[3], (num_particles, dim, dim), dtype)
    u = jax.random.normal(keys[4], (grid.num_nodes, dim + 1), dtype)
    return grid, x, m, v, tau, u


def _columns(stencil, m, v, tau):
    """Every contraction kind, single and summed columns, and two materials' masked columns."""
    material = jnp.arange(m.shape[0]) % 2 == 0
    return {"mass": Weighted(m), "momentum": (Weighted(m[:, None] * v), Affine(m[:, None, None] * tau)),
            "force": (Divergence(-tau), Weighted(v)), "mass_gradient": Gradient(m),
            "materials": Weighted(jnp.stack([jnp.where(material, m, 0.0), jnp.where(material, 0.0, m)], axis=1)),
            "slots": PerSlot(2.0 * stencil.weight), "slot_vectors": PerSlot(stencil.gradient)}


def _transfers(kernel, shape, grid, x, m, v, tau, u, per_slot=True):
    """P2G of every column (``per_slot=False``: but the per-slot ones) and every G2P method of ``kernel``."""
    stencil = shape.stencil(grid, x)
    columns = {k: c for k, c in _columns(stencil, m, v, tau).items() if per_slot or not k.startswith("slot")}
    nodal = kernel.p2g(stencil, columns, grid.num_nodes)
    return nodal, {"gather": kernel.gather(stencil, u), "gather_scalar": kernel.gather(stencil, u[:, 0]),
                   "velocity_gradient": kernel.velocity_gradient(stencil, u[:, :-1]),
                   "scalar_gradient": kernel.scalar_gradient(stencil, u[:, -1]),
                   "affine_moment": kernel.affine_moment(stencil, u)}


def _assert_same(expected, got, rtol):
    for name in expected:
        e, g = np.asarray(expected[name]), np.asarray(got[name])
        np.testing.assert_allclose(g, e, rtol=rtol, atol=rtol * np.abs(e).max(), err_msg=name)


@pytest.mark.parametrize("dim, shape", CASES)
def test_every_method_equals_the_xla_kernel(dim, shape):
    """P2G (every contraction kind, multimaterial columns; with and without the block reduction;
    with the nodal arrays addressed column by column and the slots unrolled) and the four G2P methods
    equal the XLA kernel's to 1e-12 in float64 (the planar, unrolled variant in the fast tier's cases: unrolled
    in interpret mode, 64 slots in 3D cubic took 16 s more to compile)."""
    tuned = (TUNED,) if (dim, shape) in FAST else ()
    _compare_with_xla((PALLAS, REDUCED) + tuned, SHAPES[shape], _inputs(dim))


def _compare_with_xla(kernels, shape, args, per_slot=True):
    """Each kernel's transfers equal the XLA kernel's to 1e-12 (the block reduction changes P2G only)."""
    run = jax.jit(lambda kernel, *a: _transfers(kernel, shape, *a, per_slot=per_slot), static_argnums=0)
    nodal, particle = run(XLA, *args)
    for kernel in kernels:
        got_nodal, got_particle = run(kernel, *args)
        _assert_same(nodal, got_nodal, 1e-12)
        if not kernel.reduce:
            _assert_same(particle, got_particle, 1e-12)


def test_block_reduction_groups_the_particles_of_a_cell():
    """The block reduction's groups: particles with the same nodes in every slot (the same cell),
    one leader each -- fewer atomic adds than particles for these inputs, so the reduced P2G
    checked above did merge contributions."""
    grid, x, *_ = _inputs(2)
    index = np.asarray(SHAPES["quadratic"].stencil(grid, x).index[:, :32])
    same, leader = (np.asarray(a) for a in _same_nodes(jnp.asarray(index), index.shape[0]))
    cells = [tuple(index[:, p]) for p in range(32)]
    assert np.array_equal(same, [[a == b for b in cells] for a in cells])
    assert np.array_equal(leader, [cells.index(c) == p for p, c in enumerate(cells)])
    assert leader.sum() < 16


def test_float32_equals_the_xla_kernel():
    """float32: the same to 1e-5."""
    args = _inputs(2, dtype=jnp.float32)
    run = jax.jit(lambda kernel, *a: _transfers(kernel, SHAPES["quadratic"], *a), static_argnums=0)
    (nodal, particle), (got_nodal, got_particle) = run(XLA, *args), run(PALLAS, *args)
    assert got_nodal["mass"].dtype == jnp.float32
    _assert_same(nodal, got_nodal, 1e-5)
    _assert_same(particle, got_particle, 1e-5)


def test_hoop_contraction_on_an_axisymmetric_grid():
    """The hoop shape function's P2G (r-z grids, 001 eq. 116) equals the XLA kernel's.  (A scalar
    ``Hoop(m)`` of shape (N,) trips the XLA planar kernel's rank promotion, so (N, 1) here.)"""
    grid = jm.Grid([0.0, 0.0], [1.0, 1.0], [5, 5], axisymmetric=True)
    _, x, m, v, _, _ = _inputs(2)

    def run(kernel, x, m, v):
        stencil = jm.QuadraticBSpline().stencil(grid, x)
        return kernel.p2g(stencil, {"hoop": Hoop(m[:, None]), "both": (Hoop(v), Weighted(v))}, grid.num_nodes)

    run = jax.jit(run, static_argnums=0)
    _assert_same(run(XLA, x, m, v), run(PALLAS, x, m, v), 1e-12)


def _assert_gradients_equal(loss, args, names, kernels=(PALLAS,)):
    grad = jax.jit(jax.grad(loss, argnums=tuple(range(1, len(args) + 1))), static_argnums=0)
    expected = grad(XLA, *args)
    for kernel in kernels:
        for name, e, g in zip(names, expected, grad(kernel, *args)):
            np.testing.assert_allclose(g, e, rtol=1e-10, atol=1e-10 * np.abs(e).max(), err_msg=name)


def test_gradients_of_p2g_and_gather_equal_the_xla_kernels():
    """jax.grad of a scalar of P2G and gather outputs with respect to the coefficients, a nodal
    field and the positions (through the stencil's weights) equals the XLA path's to 1e-10, also with
    the nodal arrays addressed by column and the slots unrolled (the transposes keep the options)."""
    grid, x, m, v, tau, u = _inputs(1, num_particles=40)
    shape = SHAPES["quadratic"]

    def loss(kernel, x, m, tau, u):
        stencil = shape.stencil(grid, x)
        nodal = kernel.p2g(stencil, {"m": Weighted(m), "p": (Weighted(m[:, None]), Affine(tau)), "f": Divergence(tau)},
                           grid.num_nodes)
        w = jnp.sin(nodal["p"] + nodal["f"]) * nodal["m"][:, None] + u[:, :1]
        return jnp.sum(kernel.gather(stencil, w) ** 2)

    _assert_gradients_equal(loss, (x, m, tau, u), ("x", "m", "tau", "u"), kernels=(PALLAS, TUNED))


@pytest.mark.slow
def test_gradients_equal_the_xla_kernels():
    """The same in 2D through every G2P method, and a forward-mode derivative (jax.jvp) along the
    positions."""
    grid, x, m, v, tau, u = _inputs(2, num_particles=40)
    shape = SHAPES["quadratic"]

    def loss(kernel, x, m, v, tau, u):
        stencil = shape.stencil(grid, x)
        nodal = kernel.p2g(stencil, {"m": Weighted(m), "p": (Weighted(v), Affine(tau)), "f": Divergence(tau)},
                           grid.num_nodes)
        w = jnp.sin(nodal["p"] + nodal["f"]) * nodal["m"][:, None] + u[:, :-1]
        return (jnp.sum(kernel.gather(stencil, w) ** 2) + jnp.sum(jnp.cos(kernel.velocity_gradient(stencil, w)))
                + jnp.sum(kernel.affine_moment(stencil, w) ** 2)
                + jnp.sum(kernel.scalar_gradient(stencil, w[:, 0]) ** 3))

    _assert_gradients_equal(loss, (x, m, v, tau, u), ("x", "m", "v", "tau", "u"))
    tangent = jnp.ones_like(x)
    (value, slope), (value_p, slope_p) = [jax.jvp(lambda y: loss(k, y, m, v, tau, u), (x,), (tangent,))
                                          for k in (XLA, PALLAS)]
    np.testing.assert_allclose([value_p, slope_p], [value, slope], rtol=1e-10)


def _run(sim, state, dt, steps=10):
    return jax.lax.fori_loop(0, steps, lambda i, s: sim.step(s, dt), state)


def _assert_states_equal(a, b, tol=1e-12):
    for e, g in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):
        if jnp.issubdtype(e.dtype, jnp.floating):
            np.testing.assert_allclose(g, e, rtol=tol, atol=tol * max(1.0, float(jnp.abs(e).max())))


@pytest.mark.parametrize("name, options", [
    pytest.param("disks", {"scheme": "flip"}, id="disks-flip"),
    pytest.param("disks", {"scheme": "apic"}, id="disks-apic"),
    pytest.param("disks", {"scheme": "xpic:2"}, id="disks-xpic2"),
    pytest.param("disks", {"scheme": "fmpm:2"}, id="disks-fmpm2", marks=pytest.mark.slow),
    pytest.param("bars_impact", {"cells": 8, "scheme": "apic"}, id="bars_impact-contact", marks=pytest.mark.slow)])
def test_simulation_steps_equal_the_xla_kernels(name, options):
    """Ten steps with kernel="pallas" equal kernel="xla" to 1e-12: the disks scene under FLIP,
    APIC and XPIC(2) (its S+S series runs through the Pallas kernels too), and the two-material
    bars_impact (jm.Contact: two velocity fields, their masses and mass gradients); the Pallas
    kernels are in the program."""
    setup = jm.scene(name, spacing=0.1, **options) if name == "disks" else jm.scene(name, **options)
    runs = {k: jax.jit(lambda s, sim=setup.sim.with_kernel(k): _run(sim, s, setup.dt)) for k in ("xla", "pallas")}
    program = str(jax.make_jaxpr(runs["pallas"])(setup.state))
    assert "jaxmpm_pallas_scatter" in program and "jaxmpm_pallas_gather" in program
    assert "jaxmpm_pallas" not in str(jax.make_jaxpr(runs["xla"])(setup.state))
    _assert_states_equal(runs["xla"](setup.state), runs["pallas"](setup.state))


@pytest.mark.slow
def test_gradient_through_steps_equals_the_xla_kernels():
    """jax.grad through three APIC steps (the structured adjoint's rules around the Pallas
    primitives' transposes) equals the XLA kernel's to 1e-10."""
    setup = jm.scene("disks", scheme="apic", spacing=0.1)

    def loss(sim, v0):
        state = _run(sim, eqx.tree_at(lambda s: s.v, setup.state, v0), setup.dt, 3)
        return jnp.sum(state.x[:, 1] ** 2) + jnp.sum(state.v ** 3)

    grads = [jax.jit(jax.grad(lambda v, sim=setup.sim.with_kernel(k): loss(sim, v)))(setup.state.v)
             for k in ("xla", "pallas")]
    np.testing.assert_allclose(grads[1], grads[0], rtol=1e-10, atol=1e-10 * float(jnp.abs(grads[0]).max()))


def test_vmapped_steps_equal_the_xla_kernels():
    """A vmapped batch of states (an ensemble's members) stepped with the Pallas kernels -- the
    batch folded into the particles, one kernel launch per transfer -- equals the XLA kernel's."""
    setup = jm.scene("disks", scheme="apic", spacing=0.1)
    states = jax.tree_util.tree_map(lambda a: jnp.stack([a, a]), setup.state)
    states = eqx.tree_at(lambda s: s.v, states, states.v.at[1].multiply(-0.5))  # two different members
    out = {k: jax.jit(jax.vmap(lambda s, sim=setup.sim.with_kernel(k): _run(sim, s, setup.dt, 5)))(states)
           for k in ("xla", "pallas")}
    _assert_states_equal(out["xla"], out["pallas"])
    assert not np.allclose(out["pallas"].x[0], out["pallas"].x[1])


def test_a_vmapped_batch_through_the_planar_unrolled_kernels_equals_the_xla_kernels():
    """Two members vmapped through P2G and the G2P methods with the nodal arrays addressed by column
    and the slots unrolled (the batch folded into the particles, each member on its own copy of the
    grid, so a member's column starts after all members' nodes): the XLA kernel's values to 1e-12."""
    grid, x, m, v, tau, u = _inputs(2)

    def run(kernel, x, v, u):
        return _transfers(kernel, SHAPES["quadratic"], grid, x, m, v, tau, u, per_slot=False)

    members = (jnp.stack([x, 0.9 * x + 0.05]), jnp.stack([v, -v]), jnp.stack([u, 2.0 * u]))
    expected, got = (jax.jit(jax.vmap(lambda *a, k=k: run(k, *a)))(*members) for k in (XLA, TUNED))
    for e, g in zip(jax.tree_util.tree_leaves(expected), jax.tree_util.tree_leaves(got)):
        np.testing.assert_allclose(g, e, rtol=1e-12, atol=1e-12 * float(jnp.abs(e).max()))


@pytest.mark.parametrize("options", [{}, {"reduce": True}, {"planar": True, "unroll": True}],
                         ids=["plain", "reduce", "planar-unrolled"])
def test_kernels_lower_to_triton_for_a_gpu(options):
    """With no GPU at hand, the kernels, their transposes and their batched forms are lowered for
    CUDA: every Pallas call goes to the Triton backend (jax 0.10's default GPU lowering, Mosaic GPU,
    has no atomic adds) and uses only what Triton lowers (no reduce_or, say)."""
    kernel = PallasKernel(interpret=False, **options)
    grid, x, m, v, tau, u = _inputs(3, dtype=jnp.float32)

    def transfers(x, v, u):
        stencil = SHAPES["quadratic"].stencil(grid, x)
        nodal = kernel.p2g(stencil, {"m": Weighted(m), "p": (Weighted(v), Affine(tau)), "f": Divergence(tau)},
                           grid.num_nodes)
        particle = (kernel.gather(stencil, u), kernel.velocity_gradient(stencil, u[:, :-1]),
                    kernel.scalar_gradient(stencil, u[:, 0]), kernel.affine_moment(stencil, u))
        return sum(jnp.sum(t) for t in jax.tree_util.tree_leaves((nodal, particle)))

    for fn, args in ((jax.grad(transfers, argnums=(0, 1, 2)), (x, v, u)),
                     (jax.vmap(transfers), (jnp.stack([x, x]), jnp.stack([v, v]), jnp.stack([u, u])))):
        program = jax.jit(fn).trace(*args).lower(lowering_platforms=("cuda",)).as_text()
        assert program.count("__gpu$xla.gpu.triton") >= 5  # P2G and the four G2P methods, at least


def test_a_gpu_step_lowers_to_triton():
    """A whole float32 XPIC(2) step on kernel="pallas", its gradient and a vmapped batch, compiled
    for CUDA: the Pallas kernels leave interpret mode for the platform lowered for (Triton)."""
    setup = jm.scene("disks", scheme="xpic:2", spacing=0.1, dtype="f32")
    sim = setup.sim.with_kernel("pallas").with_backend("gpu")

    def loss(v):
        return jnp.sum(sim.step(eqx.tree_at(lambda s: s.v, setup.state, v), setup.dt).x ** 2)

    states = jax.tree_util.tree_map(lambda a: jnp.stack([a, a]), setup.state)
    for fn, arg in ((lambda s: sim.step(s, setup.dt), setup.state), (jax.grad(loss), setup.state.v),
                    (jax.vmap(lambda s: sim.step(s, setup.dt)), states)):
        program = jax.jit(fn).trace(arg).lower(lowering_platforms=("cuda",)).as_text()
        assert program.count("__gpu$xla.gpu.triton") >= 7


def test_weights_formed_in_the_kernel_from_the_per_axis_factors():
    """PallasKernel(factors=True), the default: P2G and the G2P methods read a tensor-product
    stencil's per-axis factors (3 D K1 values per particle) and form S, G_d and S (x_i - X_p)_d in the
    kernel -- the jaxpr holds the factor primitives and no basis W -- and give the basis path's values
    (factors=False) and the XLA kernel's to 1e-12, in 2D and 3D.  Per-slot columns take the basis
    path; the gradients come from the basis path's rules (the gradient tests above)."""

    def transfers(kernel, shape, *args):
        return _transfers(kernel, shape, *args, per_slot=False)

    basis = PallasKernel(block=32, factors=False)
    for dim, shape in ((2, "quadratic"), (3, "cubic")):
        args = _inputs(dim)
        _compare_with_xla((PALLAS, basis), SHAPES[shape], args, per_slot=False)
        program = str(jax.make_jaxpr(lambda *a: transfers(PALLAS, SHAPES[shape], *a))(*args))
        assert program.count("jaxmpm_pallas_scatter_factors") == 1
        assert program.count("jaxmpm_pallas_gather_factors") == 5
        assert "jaxmpm_pallas_scatter[" not in program and "jaxmpm_pallas_gather[" not in program
        program = str(jax.make_jaxpr(lambda *a: transfers(basis, SHAPES[shape], *a))(*args))
        assert "factors" not in program and "jaxmpm_pallas_scatter" in program


def test_choosing_and_forcing_a_kernel():
    """backend_info names the kernel and its table row; kernel= forces one; a bad name is an InputError."""
    setup = jm.scene("disks", spacing=0.1)
    info = jm.backend_info(setup.sim, setup.state)
    assert info["kernel"] == "xla" and info["policy"] == "cpu" and info["dimension"] == 2
    assert info["reason"] == KERNEL_TABLE[0][1][2]  # the CPU row
    # the XLA kernel's layout for the precision (backend.XLA_LAYOUT): planar in float32, rows in float64
    assert info["dtype"] == "float64" and info["xla_layout"] == {"p2g": "rows", "p2g_derivatives": "planar",
                                                                 "hold_gathers": False}
    single = jm.scene("disks", spacing=0.1, dtype="f32")
    assert jm.backend_info(single.sim, single.state)["xla_layout"] == {"p2g": "planar", "p2g_derivatives": "planar",
                                                                       "hold_gathers": True}
    forced = jm.backend_info(setup.sim.with_kernel("pallas"), setup.state)
    assert forced["kernel"] == "pallas" and "forced" in forced["reason"] and "xla_layout" not in forced
    # 3D float32 on a GPU with the force folded into the momentum (APIC): the Pallas kernel, as measured
    # on an H100, with the reason; the force apart (FLIP, XPIC, FMPM), dense 2D and float64 (not measured
    # in 3D): the XLA kernel
    name, _, why = choose_kernel("gpu", 3, 8.0, jnp.float32, folds_force=True)
    assert name == "pallas" and "H100" in why and "factors" in why
    assert choose_kernel("gpu", 3, 8.0, jnp.float32, folds_force=False)[0] == "xla"
    assert choose_kernel("gpu", 2, 50.0, jnp.float32, folds_force=True)[0] == "xla"
    assert choose_kernel("gpu", 3, 8.0, jnp.float64, folds_force=True)[0] == "xla"
    folded = jm.scene("mpm88", n_particles=256, dtype="f32")  # APIC, USL, no damping: folds the force
    assert jm.folds_force(folded.sim) and not jm.folds_force(setup.sim)
    gpu = jm.backend_info(folded.sim.with_backend("gpu"), folded.state)  # 2D, sparse here: XLA on a GPU too
    assert gpu["kernel"] == "xla" and gpu["reason"].startswith("GPU")
    with pytest.raises(jm.InputError, match="kernel = 'triton'"):
        setup.sim.with_kernel("triton")
    with pytest.raises(jm.InputError, match="kernel = 'fast'"):
        jm.Simulation(setup.sim.grid, "linear", setup.sim.material, "flip", kernel="fast")
