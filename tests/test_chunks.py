"""A step over the particles in chunks (jaxmpm/model/chunks.py, backend tuning for the CPU's cache): the
same USL step, P2G a sum and G2P a map over the particles (003 §2.1), so that stepping chunk by chunk
equals the whole step to round-off -- states, gradients and vmapped ensembles -- and a model whose
step sums over all particles (an S+ S series, MUSL's second P2G) stays whole.  Small mpm88 scenes
(16^2 grid, 512 particles in random order, float64), chunks of 128 particles."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxmpm as jm
from jaxmpm.model.chunks import num_chunks
from jaxmpm.transfer import backend
from jaxmpm.transfer.backend import CHUNK_TABLE, choose_chunking

STEPS = 20


def _scene(**options):
    setup = jm.scene("mpm88", n_particles=512, n_grid=16, **options)
    return setup.sim, setup.state, setup.dt


def _assert_same(a, b, tol=1e-12):
    """Every float leaf of ``b`` equals ``a``'s to ``tol`` of the leaf's scale -- the dissipated energy's
    scale being the kinetic energy (undamped it is a sum of cancellations at round-off, ~1e-17, summed
    over the chunks in another order); integers exactly."""
    kinetic = 0.5 * float(jnp.sum(a.mass[:, None] * a.v ** 2))
    for (path, x), y in zip(jax.tree_util.tree_leaves_with_path(a), jax.tree_util.tree_leaves(b)):
        x, y = np.asarray(x), np.asarray(y)
        if np.issubdtype(x.dtype, np.floating):
            finite = np.abs(x[np.isfinite(x)])  # APIC's dissipated energy is NaN ("not computed") in both
            scale = max(finite.max(initial=0.0), kinetic if "dissipated" in jax.tree_util.keystr(path) else 0.0)
            np.testing.assert_allclose(y, x, rtol=0, atol=tol * max(1e-300, scale), err_msg=jax.tree_util.keystr(path))
        else:
            np.testing.assert_array_equal(y, x, err_msg=jax.tree_util.keystr(path))


@eqx.filter_jit
def _advance(sim, state, dt):
    return jax.lax.scan(lambda s, _: (sim.step(s, dt), None), state, None, length=STEPS)[0]


@pytest.mark.parametrize("name, options", [
    ("APIC (mpm88's own: p + f dt folded)", {}),
    ("FLIP with grid and particle damping", {"scheme": jm.FLIP(), "damping": jm.Damping(grid=2.0, particle=1.0)}),
    ("PIC/FLIP blend, force-form damping", {"scheme": jm.XPIC(order=1, beta=0.9),
                                            "damping": jm.Damping(grid=2.0, approach="force")}),
])
@pytest.mark.parametrize("output", ["in_place", "stacked"])
def test_a_step_in_chunks_equals_the_whole_step(name, options, output, monkeypatch):
    """20 steps in 4 chunks of 128 particles against the whole step, the G2P pass writing its rows in
    place or stacking them (backend.CHUNK_OUTPUT): every leaf of the state (x, v, F, APIC's B_p, time,
    step, the dissipated energy summed over the chunks) to 1e-12 of its scale."""
    monkeypatch.setattr(backend, "CHUNK_OUTPUT", {("cpu", 8): output, ("cpu", 4): output})
    sim, state, dt = _scene(**options)
    chunked = sim.with_chunks(128)
    info = jm.backend_info(chunked, state)
    assert info["chunk_particles"] == 128, info["chunk_reason"]
    assert "4 chunks of 128 particles" in info["chunk_reason"]
    whole = _advance(sim.with_chunks(0), state, dt)
    assert int(whole.step) == STEPS and float(jnp.max(jnp.abs(whole.x - state.x))) > 1e-3  # the particles moved
    fresh = eqx.filter_jit(_advance.__wrapped__)  # traced anew under this CHUNK_OUTPUT (the jit cache ignores it)
    _assert_same(whole, fresh(chunked, state, dt))


def test_a_3d_step_in_chunks_equals_the_whole_step():
    """mpm88's physics in 3D (benchmarks/gpu.py's mpm3d: 27 stencil slots a particle, APIC, walls on six
    faces), 256 particles on an 8^3 grid in 4 chunks of 64, 20 steps: every leaf to 1e-12."""
    x = np.random.default_rng(0).random((256, 3)) * 0.4 + 0.2
    particles = jm.Particles(x=x, v=np.tile([0.0, -1.0, 0.0], (256, 1)), volume=np.full(256, (0.5 / 8) ** 3), ppc=2)
    sim = jm.Simulation(grid=jm.Grid((0.0,) * 3, (1.0,) * 3, (8,) * 3), shape=jm.QuadraticBSpline(),
                        material=jm.VolumetricFluid(E=400.0, density=1.0), scheme=jm.APIC(), damping=False,
                        boundary=tuple(jm.Wall(face, layers=2) for face in ("x-", "x+", "y-", "y+", "z-", "z+")),
                        gravity=(0.0, -9.8, 0.0))
    state = sim.init(particles)
    assert jm.backend_info(sim.with_chunks(64), state)["chunk_particles"] == 64
    whole = _advance(sim.with_chunks(0), state, 2e-4)
    assert float(jnp.max(jnp.abs(whole.x - state.x))) > 1e-4  # the particles moved
    _assert_same(whole, _advance(sim.with_chunks(64), state, 2e-4))


def test_a_collider_scene_steps_in_chunks():
    """The incline (a rigid level-set solid, jm.Collider: a condition on the nodes, each particle's share
    of its force gathered at its own nodes) in 4 chunks of 32 particles equals the whole step over 20
    steps, the particles' force shares included."""
    setup = jm.scene("incline")
    chunked = setup.sim.with_chunks(setup.state.x.shape[0] // 4)
    assert jm.backend_info(chunked, setup.state)["chunk_particles"] > 0
    whole = _advance(setup.sim.with_chunks(0), setup.state, setup.dt)
    assert float(jnp.max(jnp.abs(whole.fields["incline_force"]))) > 0  # the solid pushes back
    _assert_same(whole, _advance(chunked, setup.state, setup.dt))


@pytest.mark.parametrize("forward, derivatives", [(128, 128), (128, 0), (0, 128)])
def test_gradients_and_ensembles_through_the_chunked_step(forward, derivatives):
    """d(kinetic energy after 20 steps)/d(E, V0) of a model in chunks equals the whole step's to 1e-10
    (relative), whether its derivatives go in chunks, each recomputed in the reverse pass, or differentiate the
    whole step, and whether the forward step goes in chunks or not (chunks.step_in_chunks); and a vmapped
    ensemble of two initial velocities equals the members stepped alone."""
    sim, state, dt = _scene()
    model = sim.with_chunks(forward).with_derivative_chunks(derivatives)
    info = jm.backend_info(model, state)
    assert (info["chunk_particles"], info["derivative_chunk_particles"]) == (forward, derivatives), info

    def loss(E, v, model):
        final = _advance(jm.set_params(model, E=E), eqx.tree_at(lambda s: s.v, state, v), dt)
        return jnp.sum(final.mass[:, None] * final.v ** 2)

    def grad(model):
        return jax.jit(jax.grad(lambda E, v: loss(E, v, model), argnums=(0, 1)))(jnp.asarray(400.0), state.v)

    whole, chunked = grad(sim.with_chunks(0)), grad(model)
    assert abs(float(whole[0])) > 0
    np.testing.assert_allclose(float(chunked[0]), float(whole[0]), rtol=1e-10)
    np.testing.assert_allclose(np.asarray(chunked[1]), np.asarray(whole[1]), rtol=0,
                               atol=1e-10 * float(jnp.max(jnp.abs(whole[1]))))

    members = [state, eqx.tree_at(lambda s: s.v, state, state.v * 0.5)]
    batch = jax.tree_util.tree_map(lambda *a: jnp.stack(a), *members)
    together = jax.vmap(lambda s: _advance(model, s, dt))(batch)
    for i, member in enumerate(members):
        _assert_same(_advance(sim.with_chunks(0), member, dt), jax.tree_util.tree_map(lambda a, i=i: a[i], together))


def test_the_chunks_derivatives_are_traced_in_the_models_context(monkeypatch):
    """JAX traces the derivative of a jitted rollout's steps after the call (jax.grad from outside the jit):
    the chunks' derivatives are traced with the model's adjoint and backend policy all the same."""
    from jaxmpm.model import chunks

    seen, chunked_step = [], chunks.chunked_step

    def spy(*args, **options):
        seen.append((options.get("recompute", False), backend._adjoint.get(), backend.active()))
        return chunked_step(*args, **options)

    monkeypatch.setattr(chunks, "chunked_step", spy)
    sim, state, dt = _scene()
    model = sim.with_chunks(128).with_adjoint("autodiff").with_backend("cpu")

    def kinetic(v):
        final = model.run(eqx.tree_at(lambda s: s.v, state, v), dt, 2, progress=False)[0]
        return jnp.sum(final.v ** 2)

    jax.grad(kinetic)(state.v)
    assert (True, "autodiff", "cpu") in seen and {adjoint for _, adjoint, _ in seen} == {"autodiff"}, seen


@pytest.mark.parametrize("options, reason", [
    ({"scheme": jm.XPIC(order=2)}, "XPIC's update sums over all particles"),
    ({"scheme": jm.FLIP(), "update": "MUSL"}, "only USL steps in chunks"),
])
def test_a_step_that_sums_over_all_particles_stays_whole(options, reason):
    """XPIC(2)'s S+ S series and MUSL's re-extrapolated P2G read every particle: forced chunks leave
    the step whole and backend_info says why."""
    sim, state, _ = _scene(**options)
    info = jm.backend_info(sim.with_chunks(128), state)
    assert info["chunk_particles"] == 0 and reason in info["chunk_reason"], info["chunk_reason"]


def test_chunk_count_and_the_backend_table():
    """num_chunks picks the least divisor between ceil(N / per_chunk) and twice that (none for a prime
    count); CHUNK_TABLE chunks CPU steps from 100k particles (16k float64, 32k float32), not smaller
    ones and not on a GPU; a bad chunk_particles is an InputError naming it."""
    assert num_chunks(131072, 16384) == 8
    assert num_chunks(524288, 16384) == 32
    assert num_chunks(100, 30) == 4  # 25 particles a chunk
    assert num_chunks(150_000, 16384) == 10  # ceil is 10: 15000 a chunk
    assert num_chunks(97, 10) == 0  # prime
    assert choose_chunking("cpu", 2, 131072, jnp.float64)[0] == 16384
    assert choose_chunking("cpu", 2, 131072, jnp.float32)[0] == 32768
    assert choose_chunking("cpu", 2, 65536, jnp.float64)[0] == 16384
    assert choose_chunking("cpu", 2, 32768, jnp.float64)[0] == 0
    assert choose_chunking("cpu", 2, 65536, jnp.float32)[0] == 0
    assert choose_chunking("cpu", 3, 131072, jnp.float64)[0] == 4096  # 3D: 27 slots a particle, smaller chunks
    assert choose_chunking("cpu", 3, 32768, jnp.float32)[0] == 8192
    assert choose_chunking("cpu", 3, 8192, jnp.float64)[0] == 0
    assert choose_chunking("cpu", 1, 10**6, jnp.float64)[0] == 0  # 1D float64: chunks lost (1.2-1.4x at 1M)
    assert choose_chunking("cpu", 1, 262144, jnp.float32)[0] == 65536  # 1D float32: 1.04-1.23x
    assert choose_chunking("cpu", 1, 131072, jnp.float32)[0] == 0
    assert choose_chunking("gpu", 2, 2_000_000, jnp.float32)[0] == 0
    assert all(len(key) == 4 and len(row) == 2 for key, row in CHUNK_TABLE)
    sim, state, _ = _scene()
    assert jm.backend_info(sim, state)["chunk_particles"] == 0  # 512 particles: whole
    info = jm.backend_info(sim.with_chunks(97), jm.scene("mpm88", n_particles=509, n_grid=16).state)
    assert info["chunk_particles"] == 0 and "no divisor" in info["chunk_reason"]
    with pytest.raises(jm.InputError, match="chunk_particles"):
        sim.with_chunks(-1)
    with pytest.raises(jm.InputError, match="derivative_chunk_particles = 1.5; give the particles per chunk"):
        sim.with_derivative_chunks(1.5)


def test_a_step_too_large_for_the_memory_goes_in_chunks():
    """chunks_to_fit (issue 32 item 7): the whole step when its temporaries (STEP_FLOATS_PER_SLOT floats per
    slot and particle) take at most a quarter of the free memory; else chunks, a power of two of at least
    SMALLEST_CHUNK particles, whose temporaries take at most that quarter, and a reason naming the sizes.  Several
    velocity fields a node take more (step_floats)."""
    per_particle = backend.STEP_FLOATS_PER_SLOT[2] * 9 * 4  # 2D quadratic, float32: 684 bytes
    assert backend.chunks_to_fit(2, 10**6, 9, jnp.float32, 4 * per_particle * 10**6) == (0, "")
    per, why = backend.chunks_to_fit(2, 10**8, 9, jnp.float32, 80 * 2**30)  # 10^8 particles, 80 GiB free
    assert per & (per - 1) == 0 and per * per_particle <= 0.25 * 80 * 2**30 < 2 * per * per_particle
    assert "63.7 GiB" in why and "80.0 GiB" in why and f"chunks of at most {per} particles" in why
    assert backend.chunks_to_fit(3, 10**6, 27, jnp.float64, 2**20)[0] == backend.SMALLEST_CHUNK
    two = backend.step_floats(2, 9, fields=2) * 4  # two velocity fields (contact): (19 + 13) 9 + 19 floats
    assert two == 1228 and backend.chunks_to_fit(2, 10**6, 9, jnp.float32, 4 * two * 10**6, fields=2) == (0, "")
    assert backend.chunks_to_fit(2, 10**6, 9, jnp.float32, 4 * per_particle * 10**6, fields=2)[0] > 0


def test_the_library_chunks_a_step_that_would_not_fit(monkeypatch):
    """Under "auto", a step whose temporaries would not fit (here: a device of 1 MiB, JAXMPM_MEMORY_BYTES)
    runs in chunks (backend_info says why) and equals the step with those chunks forced bit for bit; with
    the machine's memory it stays whole.  A forced choice stays as given."""
    sim, state, dt = _scene()  # 512 particles
    assert jm.backend_info(sim, state)["chunk_particles"] == 0
    monkeypatch.setattr(backend, "SMALLEST_CHUNK", 128)
    monkeypatch.setenv("JAXMPM_MEMORY_BYTES", str(2**20))
    info = jm.backend_info(sim, state)
    assert info["chunk_particles"] == 128 and "would take more than 25%" in info["chunk_reason"], info
    assert jm.backend_info(sim.with_chunks(0), state)["chunk_particles"] == 0
    step = jax.jit(lambda m, s: m.step(s, dt))
    _assert_same(step(sim.with_chunks(128), state), step(sim, state), tol=0.0)


@pytest.mark.parametrize("dim, fields", [(1, 1), (2, 1), (3, 1), (2, 2), (2, 3)])
@pytest.mark.parametrize("scheme", ["APIC", "FLIP"])
def test_the_memory_table_bounds_the_whole_steps_temporaries(dim, fields, scheme):
    """STEP_FLOATS_PER_SLOT holds: XLA's temporary buffers of a compiled 3-step loop of the whole step, per
    particle and stencil slot, stay within the table (quadratic B-splines, the grid's arrays included); with
    several velocity fields (jm.Contact(materials=fields), the bodies slabs along x, the separation criterion on:
    the contact's heaviest program), within step_floats' MULTIFIELD_FLOATS_PER_SLOT and
    FIELD_FLOATS_PER_PARTICLE more."""
    cells, ppc = {1: (64, 64), 2: (32, 8), 3: (12, 4)}[dim]
    grid = jm.Grid((0.0,) * dim, (1.0,) * dim, (cells,) * dim)
    material = jm.LinearElastic(E=1e3, density=1.0) if dim == 1 else jm.LinearElastic(E=1e3, nu=0.3, density=1.0)
    terms = (jm.Contact(materials=fields, separation=0.5),) if fields > 1 else ()
    sim = jm.Simulation(grid=grid, shape=jm.QuadraticBSpline(), material=material, scheme=getattr(jm, scheme)(),
                        damping=False, terms=terms).with_chunks(0)
    assert sim.velocity_fields == fields
    particles = jm.fill(grid, jm.Box((0.2,) * dim, (0.8,) * dim), ppc=ppc)
    ids = np.minimum(np.floor((np.asarray(particles.x)[:, 0] - 0.2) / 0.6 * fields), fields - 1)
    state = sim.init(particles, fields={"material": jnp.asarray(ids)} if fields > 1 else None)
    arrays, static = eqx.partition((sim, state), eqx.is_array)

    def loop(arrays):
        sim, state = eqx.combine(arrays, static)
        return jax.lax.fori_loop(0, 3, lambda _, s: sim.step(s, 1e-5), state)

    temporaries = jax.jit(loop).lower(arrays).compile().memory_analysis().temp_size_in_bytes
    n, slots, itemsize = state.x.shape[0], 3 ** dim, state.x.dtype.itemsize
    floats, bound = temporaries / (n * slots * itemsize), backend.step_floats(dim, slots, fields) / slots
    assert 0.3 * bound < floats <= bound, (floats, bound)


@pytest.mark.parametrize("dim", [1, 2, 3])
@pytest.mark.parametrize("scheme", ["APIC", "FLIP"])
def test_the_memory_table_bounds_a_steps_gradient_too(dim, scheme):
    """The derivatives' chunks are sized by the same table (Simulation._derivative_row): XLA's temporary buffers
    of one step's gradient, the step and its pullback in one program (float64, quadratic B-splines), stay within
    STEP_FLOATS_PER_SLOT too.  Measured on the CPU (2026-11-29, Linear to cubic, float32 and float64): a step's
    gradient took 0.7-1.6x its forward step's temporaries, at most 12.6, 17.6 and 24.7 floats a slot in 1D-3D
    against the table's 14, 19 and 25."""
    cells, ppc = {1: (64, 64), 2: (32, 8), 3: (12, 4)}[dim]
    grid = jm.Grid((0.0,) * dim, (1.0,) * dim, (cells,) * dim)
    material = jm.LinearElastic(E=1e3, density=1.0) if dim == 1 else jm.LinearElastic(E=1e3, nu=0.3, density=1.0)
    sim = jm.Simulation(grid=grid, shape=jm.QuadraticBSpline(), material=material, scheme=getattr(jm, scheme)(),
                        damping=False).with_chunks(0).with_derivative_chunks(0)
    state = sim.init(jm.fill(grid, jm.Box((0.2,) * dim, (0.8,) * dim), ppc=ppc))
    arrays, static = eqx.partition((sim, state), eqx.is_array)

    def gradient(arrays):
        sim, state = eqx.combine(arrays, static)

        def loss(v):
            new = sim.step(eqx.tree_at(lambda s: s.v, state, v), 1e-5)
            return jnp.sum(new.v ** 2) + jnp.sum(new.x ** 2) + jnp.sum(new.F ** 2)

        return jax.grad(loss)(state.v)

    temporaries = jax.jit(gradient).lower(arrays).compile().memory_analysis().temp_size_in_bytes
    n, slots, itemsize = state.x.shape[0], 3 ** dim, state.x.dtype.itemsize
    floats, bound = temporaries / (n * slots * itemsize), backend.STEP_FLOATS_PER_SLOT[dim]
    assert 0.3 * bound < floats <= bound, (floats, bound)


@pytest.mark.parametrize("scheme", ["APIC", "FLIP"])
def test_a_frames_sums_over_the_steps_chunks_equal_the_whole_sums(scheme):
    """Where the step goes in chunks, a frame's energies and momenta are summed chunk by chunk (sums_in_chunks:
    their per-particle terms take one chunk's memory): equal to the whole sums to round-off, the dissipated
    energy the state's own, and their derivatives the whole sums' (a custom JVP)."""
    sim, state, dt = _scene(scheme=getattr(jm, scheme)())
    state = _advance(sim, state, dt)  # moving and strained: no sum is zero
    chunked, whole = sim.with_chunks(128), sim.with_chunks(0)
    assert jm.backend_info(chunked, state)["chunk_particles"] == 128
    frame = eqx.filter_jit(lambda model, s: model._frame_diagnostics(s))
    got, want = frame(chunked, state), frame(whole, state)
    assert sorted(got) == sorted(want) == ["angular", "dissipated", "kinetic", "momentum", "strain"]
    for key in want:
        np.testing.assert_allclose(got[key], want[key], rtol=1e-13, atol=1e-15 * float(jnp.max(jnp.abs(want[key]))),
                                   err_msg=key)

    def energy(model, v):
        frame = model._frame_diagnostics(eqx.tree_at(lambda s: s.v, state, v))
        return frame["kinetic"] + frame["strain"] + jnp.sum(frame["angular"])

    np.testing.assert_array_equal(jax.grad(lambda v: energy(chunked, v))(state.v),
                                  jax.grad(lambda v: energy(whole, v))(state.v))
