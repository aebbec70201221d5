"""One validation layer (issue 11, item 1; the constructor half of item 8): every value a user
gives -- scene options, grids, regions, fill, materials, schemes, damping, set_params, ensemble
batches, stable_dt -- is checked where it enters, and a bad one raises jm.InputError with one line
naming the parameter, the value and the allowed range.  Traced values (jit/grad/vmap) pass
unchecked.  A hypothesis fuzz test draws constructor arguments from valid and invalid ranges: every
outcome is a success with finite values or a one-line InputError, never another exception."""

import math
import warnings

import equinox as eqx
import hypothesis.strategies as st
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from cases import small_simulation
from hypothesis import HealthCheck, given, settings

import jaxmpm as jm
from jaxmpm.core.validate import Range, finite_vector, positive_int, real

NAN, INF = math.nan, math.inf


def small_state(sim):
    return sim.init(jm.fill(sim.grid, jm.Box((6.0,), (10.0,)), ppc=2))


def assert_input_error(make, *words):
    """``make()`` raises InputError with a one-line message containing every word."""
    with pytest.raises(jm.InputError) as info:
        make()
    message = str(info.value)
    assert "\n" not in message
    for word in words:
        assert word in message, (word, message)
    return message


GRID2 = jm.Grid((0.0, 0.0), (1.0, 1.0), (4, 4))

# ------------------------------------------------------------------ the issue's table
ISSUE_ROWS = {
    "scene bar cfl=0": (lambda: jm.scene("bar", cfl=0), ["cfl = 0", "positive"]),
    "scene bar frames=0": (lambda: jm.scene("bar", frames=0), ["frames = 0", "positive integer"]),
    "scene bar cells=0": (lambda: jm.scene("bar", cells=0), ["cells = 0", "positive integer"]),
    "scene disks dt=0": (lambda: jm.scene("disks", dt=0), ["dt = 0", "positive"]),
    "scene disks t_end=inf": (lambda: jm.scene("disks", t_end=INF), ["t_end = inf", "finite"]),
    "scene bar cfl=nan": (lambda: jm.scene("bar", cfl=NAN), ["cfl = nan", "finite"]),
    "scene disks cfl=nan": (lambda: jm.scene("rings", cfl=NAN), ["cfl = nan", "finite"]),
    "scene bar frames=-1": (lambda: jm.scene("bar", frames=-1), ["frames = -1", "positive integer"]),
    "scene bar cells=2.5": (lambda: jm.scene("bar", cells=2.5), ["cells = 2.5", "positive integer"]),
    "Grid cells nan": (lambda: jm.Grid((0,), (1,), (NAN,)), ["cells[0] = nan", "positive integer"]),
    "Grid cells inf": (lambda: jm.Grid((0,), (1,), (INF,)), ["cells[0] = inf", "positive integer"]),
    "Grid cells 'ab'": (lambda: jm.Grid((0,), (1,), ("ab",)), ["cells[0] = 'ab'", "positive integer"]),
    "Grid cells string": (lambda: jm.Grid((0,), (1,), "ab"), ["cells", "'ab'"]),
    "Grid lower nan": (lambda: jm.Grid((NAN,), (1,), (4,)), ["lower", "nan", "finite"]),
    # node numbers are int32; np.prod of the node counts wrapped past int64, so the memory check let a grid of
    # 4e35 nodes through to an OverflowError (jaxmpm run incline --t-end 1e8, found by tests/test_cli_fuzz.py)
    "Grid too many nodes": (lambda: jm.Grid((0, 0), (1, 1), (2**16, 2**16)), ["65537 x 65537", "int32",
                                                                            "at most 2147483647 nodes"]),
    "Grid far too many nodes": (lambda: jm.Grid((0, 0), (1, 1), (849570921112534144, 10**17)),
                                ["8.496e+34 nodes", "fewer cells"]),
    "scene incline t_end=1e8": (lambda: jm.scene("incline", t_end=1e8), ["Grid", "nodes", "int32"]),
    "Grid.covering spacing inf": (lambda: jm.Grid.covering((0,), (1,), INF), ["spacing = inf", "finite"]),
    "Grid.covering pad -1": (lambda: jm.Grid.covering((0,), (1,), 0.1, pad=-1.0), ["pad = -1.0", ">= 0"]),
    "Grid.covering axes differ": (lambda: jm.Grid.covering((0, 0), (1,), 0.1), ["upper", "lower has 2"]),
    "fill velocity (1, 2, 3) on 2D": (lambda: jm.fill(GRID2, jm.Box((0, 0), (1, 1)), velocity=(1, 2, 3)),
                                      ["velocity", "3 components", "2D"]),
    "LinearElastic E='abc'": (lambda: jm.LinearElastic(E="abc"), ["LinearElastic", "E must be a number", "'abc'"]),
}


@pytest.mark.parametrize("make, words", list(ISSUE_ROWS.values()), ids=list(ISSUE_ROWS))
def test_issue_rows_raise_input_error_naming_the_parameter(make, words):
    assert_input_error(make, *words)


@pytest.mark.parametrize("values, words", [
    (dict(nu=0.7), ["nu = 0.7", "(-1, 0.5)"]),
    (dict(E=-100), ["E = -100", "positive"]),
    (dict(beta=5), ["beta = 5", "[0, 1]"]),
    (dict(alpha_g=-1), ["alpha_g = -1", ">= 0"]),
    (dict(alpha_p=NAN), ["alpha_p = nan", "finite"]),
    (dict(density=jnp.asarray(0.0)), ["density = 0.0", "positive"]),  # a concrete jax array is checked
    (dict(gravity=(0.0, -9.8)), ["gravity", "shape (2,)", "(1,)"]),
    (dict(gravity=(INF,)), ["gravity", "finite"]),
])
def test_set_params_checks_concrete_values(values, words):
    assert_input_error(lambda: jm.set_params(small_simulation(), **values), "set_params", *words)


def test_set_params_valid_values_and_traced_values_pass():
    sim = small_simulation()
    new = jm.set_params(sim, nu=0.3, E=5.0, beta=0.5, alpha_g=0.0, gravity=(-1.0,))
    got = jm.get_params(new, "nu", "E", "beta", "alpha_g", "gravity")
    assert float(got["nu"]) == 0.3 and float(got["E"]) == 5.0 and float(got["beta"]) == 0.5
    assert float(got["alpha_g"]) == 0.0 and np.asarray(got["gravity"]).tolist() == [-1.0]
    # traced: no check (the value is not known), as inside calibrate or ensemble
    nu = jax.jit(lambda v: jm.get_params(jm.set_params(sim, nu=v), "nu")["nu"])(0.7)
    assert float(nu) == pytest.approx(0.7)


def test_ensemble_checks_every_member_before_tracing():
    sim, state = small_simulation(), None
    message = assert_input_error(
        lambda: jm.ensemble(sim, state, 0.1, 4, params={"beta": jnp.asarray([0.5, -1.0, 3.0])}),
        "ensemble member 1", "beta = -1.0", "[0, 1]")
    assert "member 2" not in message  # the first bad member
    assert_input_error(lambda: jm.ensemble(sim, state, 0.1, 4, params={"beta": [-1, 3]}), "member 0", "beta = -1")
    assert_input_error(lambda: jm.ensemble(sim, state, 0.1, 4, params={"nu": np.array([0.2, 0.5])}),
                       "member 1", "nu = 0.5")
    assert_input_error(lambda: jm.ensemble(sim, state, 0.1, 4, params={"warp": [1.0]}), "warp")
    assert_input_error(lambda: jm.ensemble(sim, state, 0.0, 4, params={"beta": [1.0]}), "dt = 0.0")
    assert_input_error(lambda: jm.ensemble(sim, state, 0.1, 2.5, params={"beta": [1.0]}), "steps = 2.5")


@pytest.mark.parametrize("cfl", [-1, 0, NAN, INF, "fast"])
def test_stable_dt_rejects_a_bad_cfl(cfl):
    sim = small_simulation()
    state = small_state(sim)
    assert_input_error(lambda: sim.stable_dt(state, cfl=cfl), "stable_dt", "cfl")
    assert_input_error(lambda: jm.stable_dt(sim.grid, sim.material, state.v, cfl), "cfl")


def test_stable_dt_unchanged_and_traceable():
    sim = small_simulation()
    state = small_state(sim)
    assert float(sim.stable_dt(state, 0.5)) == pytest.approx(0.5 / math.sqrt(2.0), rel=1e-15)
    grad = jax.grad(lambda c: sim.stable_dt(state, c))(0.5)  # a traced cfl is not checked
    assert float(grad) == pytest.approx(1.0 / math.sqrt(2.0), rel=1e-14)


@pytest.mark.slow
def test_float32_state_with_float64_simulation():
    """A float64 model runs a float32 state in float32 (the model is cast on entry), giving
    exactly what the float32 scene gives."""
    setup64 = jm.scene("bar", cells=8, t_end=2.0, frames=4)
    setup32 = jm.scene("bar", cells=8, t_end=2.0, frames=4, dtype="f32")
    assert setup64.sim.material.E.dtype == jnp.float64 and setup32.state.x.dtype == jnp.float32
    state32 = jm.scenes.cast_state(setup64.state, jnp.float32)
    final, hist = setup64.sim.run(state32, setup64.dt, setup64.steps, setup64.save_every)
    ref, ref_hist = setup32.run()
    assert final.x.dtype == final.v.dtype == final.F.dtype == jnp.float32
    np.testing.assert_array_equal(np.asarray(final.x), np.asarray(ref.x))
    np.testing.assert_array_equal(np.asarray(hist.kinetic), np.asarray(ref_hist.kinetic))
    stepped = setup64.sim.step(state32, setup64.dt)
    assert stepped.x.dtype == jnp.float32 and np.all(np.isfinite(np.asarray(stepped.x)))
    # a state that mixes precisions is a one-line InputError naming the fix
    mixed = eqx.tree_at(lambda s: s.x, state32, setup64.state.x)
    assert_input_error(lambda: setup64.sim.run(mixed, setup64.dt, 4, 1), "precisions", "cast_state")


# ------------------------------------------------------------------ scenes
@pytest.mark.parametrize("name, options, words", [
    ("bar", dict(spacing=0.1), ["unknown option 'spacing'", "cells", "cfl"]),
    ("disks", dict(cells=4), ["unknown option 'cells'", "spacing"]),
    ("bar", dict(ppc=0), ["ppc = 0"]),
    ("bar", dict(ppc=True), ["ppc = True"]),
    ("bar", dict(E=-1.0), ["E = -1.0"]),
    ("bar", dict(length="long"), ["length must be a number", "'long'"]),
    ("disks", dict(nu=0.5), ["nu = 0.5", "(-1, 0.5)"]),
    ("disks", dict(spacing=0), ["spacing = 0"]),
    ("disks", dict(pad=-0.1), ["pad = -0.1"]),
    ("spin", dict(omega=0.0), ["omega = 0", "dt"]),
    ("spin", dict(density=INF), ["density = inf"]),
    ("rings", dict(spacing=100.0), ["spacing = 100.0"]),
    ("rings", dict(speed=NAN), ["speed = nan"]),
    ("mpm88", dict(n_particles=0), ["n_particles = 0"]),
    ("mpm88", dict(seed=-1), ["seed = -1", "non-negative integer"]),
    ("mms", dict(dim=2.5), ["dim = 2.5"]),
    ("mms", dict(phases=(0.0, NAN), dim=2), ["phases[1] = nan"]),
    ("vortex", dict(period=0), ["period = 0"]),
    ("disks", dict(contact="coulomb", friction=-0.1), ["friction = -0.1", ">= 0"]),
    ("disks", dict(contact="glue"), ["contact = 'glue'", "'frictionless'"]),
    ("rings", dict(contact=None), ["contact = None", "'coulomb'"]),
    ("disks", dict(friction=0.2), ["friction = 0.2", "contact='coulomb'", "contact='none'"]),
    ("slide", dict(contact="stick", friction=0.5), ["friction = 0.5", "contact='stick'"]),
    ("bar", dict(contact="stick"), ["unknown option 'contact'"]),
    ("bars_impact", dict(friction=0.1), ["unknown option 'friction'"]),
    ("bars_impact", dict(cells=0), ["cells = 0"]),
    ("slide", dict(theta=90), ["theta = 90", "[0, 90)"]),
    ("slide", dict(normal="mean"), ["normal = 'mean'", "'first'"]),
    ("slide", dict(spacing=0.2), ["spacing = 0.2", "height"]),
])
def test_scene_options_are_checked(name, options, words):
    assert_input_error(lambda: jm.scene(name, **options), name, *words)


def test_builders_are_checked_on_every_path():
    """jm.SCENES[name][0] is the checked builder too; its signature is the builder's."""
    import inspect

    from jaxmpm.scenes.bar import bar

    for builder in (jm.SCENES["bar"][0], bar):
        assert_input_error(lambda: builder(cfl=0), "cfl = 0")
        assert_input_error(lambda: builder(None, None, 0), "cells = 0")  # positional too
    assert "cells" in inspect.signature(jm.SCENES["bar"][0]).parameters


def test_scene_accepts_scheme_and_shape_strings_and_integral_floats():
    setup = jm.scene("disks", scheme="xpic:3", shape="ugimp", spacing=0.25, ppc=1.0, t_end=0.01, frames=2)
    assert isinstance(setup.sim.scheme, jm.XPIC) and setup.sim.scheme.order == 3
    assert isinstance(setup.sim.shape, jm.UGIMP) and setup.sim.shape.ppc == 1


# ------------------------------------------------------------------ constructors
CONSTRUCTOR_ROWS = {
    "Grid upper < lower": (lambda: jm.Grid((0.0,), (-1.0,), (4,)), ["upper[0]"]),
    "Grid lower string": (lambda: jm.Grid("ab", (1.0,), (4,)), ["lower", "'ab'"]),
    "Grid lower None": (lambda: jm.Grid(None, (1.0,), (4,)), ["lower", "None"]),
    "Grid box too wide": (lambda: jm.Grid((-1e308,), (1e308,), (4,)), ["finite"]),
    "Grid cells True": (lambda: jm.Grid((0.0,), (1.0,), (True,)), ["cells[0] = True"]),
    "Grid.covering upper < lower": (lambda: jm.Grid.covering((1.0,), (0.0,), 0.1), ["upper[0]"]),
    "Grid.covering spacing 0": (lambda: jm.Grid.covering((0.0,), (1.0,), 0.0), ["spacing = 0.0"]),
    "Grid.covering spacing tiny": (lambda: jm.Grid.covering((0.0,), (1.0,), 1e-320), ["spacing[0]", "too small"]),
    "Grid.covering spacing per axis": (lambda: jm.Grid.covering((0, 0), (1, 1), (0.1, 0.1, 0.1)), ["spacing"]),
    "Grid.covering pad nan": (lambda: jm.Grid.covering((0.0,), (1.0,), 0.1, pad=NAN), ["pad = nan"]),
    "Grid.covering shape string": (lambda: jm.Grid.covering((0.0,), (1.0,), 0.1, shape="linear"), ["shape"]),
    "fill ppc 2.5": (lambda: jm.fill(GRID2, jm.Box((0, 0), (1, 1)), ppc=2.5), ["ppc = 2.5", "positive integer"]),
    "fill ppc True": (lambda: jm.fill(GRID2, jm.Box((0, 0), (1, 1)), ppc=True), ["ppc = True"]),
    "fill ppc 'a'": (lambda: jm.fill(GRID2, jm.Box((0, 0), (1, 1)), ppc="a"), ["ppc = 'a'"]),
    "fill velocity nan": (lambda: jm.fill(GRID2, jm.Box((0, 0), (1, 1)), velocity=(0.0, NAN)), ["velocity[1]"]),
    "fill velocity string": (lambda: jm.fill(GRID2, jm.Box((0, 0), (1, 1)), velocity="up"), ["velocity"]),
    "fill velocity(x) inf": (lambda: jm.fill(GRID2, jm.Box((0, 0), (1, 1)), velocity=lambda x: np.full_like(x, np.inf)),
                             ["velocity(x)", "non-finite"]),
    "fill density nan": (lambda: jm.fill(GRID2, jm.Box((0, 0), (1, 1)), density=NAN), ["density = nan"]),
    "fill region 3D on 2D": (lambda: jm.fill(GRID2, jm.Ball((0.5, 0.5, 0.5), 0.3)), ["region has 3 axes"]),
    "fill grid not a Grid": (lambda: jm.fill("grid", jm.Box((0,), (1,))), ["grid"]),
    "Disk radius 0": (lambda: jm.Disk((0.5, 0.5), 0.0), ["radius = 0.0", "positive"]),
    "Disk radius nan": (lambda: jm.Disk((0.5, 0.5), NAN), ["radius = nan"]),
    "Disk centre inf": (lambda: jm.Disk((0.5, INF), 0.1), ["center[1] = inf"]),
    "Ring inner > outer": (lambda: jm.Ring((0.0, 0.0), 2.0, 1.0), ["inner", "outer"]),
    "Ring inner nan": (lambda: jm.Ring((0.0, 0.0), NAN, 1.0), ["inner = nan"]),
    "Box upper nan": (lambda: jm.Box((0.0,), (NAN,)), ["upper", "nan"]),
    "NeoHookean nu nan": (lambda: jm.NeoHookean(E=1.0, nu=NAN), ["nu = nan", "finite"]),
    "LinearElastic E inf": (lambda: jm.LinearElastic(E=INF), ["E = inf"]),
    "LinearElastic E None": (lambda: jm.LinearElastic(E=None), ["E must be a number", "None"]),
    "LinearElastic E True": (lambda: jm.LinearElastic(E=True), ["E must be a number", "True"]),
    "VolumetricFluid E array": (lambda: jm.VolumetricFluid(E=np.array([1.0, -1.0])), ["E = [1.0, -1.0]"]),
    "FLIP beta nan": (lambda: jm.FLIP(beta=NAN), ["beta = nan"]),
    "FLIP beta 'half'": (lambda: jm.FLIP(beta="half"), ["beta must be a number"]),
    "XPIC order True": (lambda: jm.XPIC(order=True), ["order = True", "non-negative integer"]),
    "XPIC order inf": (lambda: jm.XPIC(order=INF), ["order = inf", "non-negative integer"]),
    "FMPM order 1.5": (lambda: jm.FMPM(order=1.5), ["order = 1.5", "must be a non-negative integer"]),
    "Damping alpha_g inf": (lambda: jm.Damping(grid=INF), ["grid (alpha_g) = inf"]),
    "Damping alpha_p 'x'": (lambda: jm.Damping(particle="x"), ["particle (alpha_p) must be a number"]),
    "Simulation gravity nan": (lambda: small_simulation(gravity=(NAN,)), ["gravity = (nan,)", "finite"]),
    "Simulation gravity 2 on 1D": (lambda: small_simulation(gravity=(0.0, 1.0)), ["gravity", "1 components"]),
}


@pytest.mark.parametrize("make, words", list(CONSTRUCTOR_ROWS.values()), ids=list(CONSTRUCTOR_ROWS))
def test_constructors_reject_bad_values(make, words):
    assert_input_error(make, *words)


def test_valid_values_keep_working():
    assert jm.Grid((0,), (1,), (4.0,)).cells == (4,)  # an integral float counts
    assert jm.Grid(0.0, 1.0, 4).cells == (4,)
    g = jm.Grid.covering((0.0, 0.0), (1.0, 1.0), 0.25, pad=0.0)
    assert g.cells == (4, 4) and g.upper == (1.0, 1.0)
    assert jm.Grid.covering((0.0,), (0.0,), 0.5).cells == (1,)  # a point is covered by one cell
    p = jm.fill(GRID2, jm.Box((0, 0), (1, 1)), ppc=np.int64(2), velocity=1.0)
    assert p.v.shape == (64, 2) and np.all(np.asarray(p.v) == 1.0)
    assert float(jm.LinearElastic(E=np.float32(2.0), nu=jnp.asarray(0.25)).nu) == 0.25
    assert jm.XPIC(order=np.int32(3)).order == 3
    assert float(jm.FLIP(beta=0).beta) == 0.0 and float(jm.Damping(grid=0).grid) == 0.0


def test_traced_values_pass_unchecked():
    """Inside jit/vmap/grad the values are unknown: the constructors build without checking."""
    E = jax.vmap(lambda e: jm.LinearElastic(E=e, nu=0.2).E)(jnp.asarray([1.0, 2.0]))
    assert np.asarray(E).tolist() == [1.0, 2.0]
    beta = jax.jit(lambda b: jm.FLIP(beta=b).beta)(0.5)
    assert float(beta) == 0.5
    d = jax.grad(lambda a: jm.Damping(grid=a).grid * 2.0)(0.1)
    assert float(d) == 2.0


def test_helpers():
    assert real("o", "x", np.float32(0.5), low=0, high=1) == 0.5
    assert real("o", "x", jnp.asarray(2.0), low=0, low_open=True) == 2.0
    assert positive_int("o", "n", 3.0) == 3 and positive_int("o", "n", np.int64(0), low=0) == 0
    assert finite_vector("o", "v", 1.5, 3) == (1.5, 1.5, 1.5)
    assert finite_vector("o", "v", np.array([1, 2])) == (1.0, 2.0)
    assert Range(-1, 0.5, True, True).phrase() == "lie in (-1, 0.5)"
    assert_input_error(lambda: real("Owner", "x", 2.0, low=0, high=1, fix="do this"),
                       "Owner: x = 2.0 must lie in [0, 1]; do this")
    assert_input_error(lambda: real("o", "x", [1.0, 2.0]), "single number")
    assert_input_error(lambda: positive_int("o", "n", -1), "n = -1 must be a positive integer")
    assert_input_error(lambda: finite_vector("o", "v", [[1.0], [2.0]]), "flat sequence")
    long = assert_input_error(lambda: real("o", "x", np.full(1000, np.nan)), "x")
    assert len(long) < 200


# ------------------------------------------------------------------ fuzz
BAD_NUMBERS = [NAN, INF, -INF, 0.0, -1.0, -1e308, 1e308, 1e-320, -0.0]
ODD = ["abc", "", "1.5", None, True, False, [1.0, 2.0], (), object()]
anything = st.one_of(
    st.sampled_from(BAD_NUMBERS + ODD),
    st.floats(allow_nan=True, allow_infinity=True),
    st.floats(-10.0, 10.0),
    st.integers(-5, 10),
    st.text(max_size=4),
)
small_count = st.one_of(st.integers(-2, 6), st.sampled_from([0.0, 2.0, 2.5, NAN, INF, "2", True, None]))


def _finite_tree(value):
    for leaf in jax.tree_util.tree_leaves(value):
        if isinstance(leaf, (jax.Array, np.ndarray)) and np.issubdtype(np.asarray(leaf).dtype, np.floating):
            assert np.all(np.isfinite(np.asarray(leaf))), value
        elif isinstance(leaf, float):
            assert math.isfinite(leaf), value


def outcome(make):
    """Run ``make``: a success must hold finite values, a failure must be a one-line InputError."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            made = make()
    except jm.InputError as err:
        assert "\n" not in str(err) and str(err), repr(err)
        return None
    _finite_tree(made)
    return made


def _vec(draw, dim, values):
    return tuple(draw(values) for _ in range(dim))


@settings(max_examples=60, deadline=None, suppress_health_check=list(HealthCheck))
@given(st.data())
def test_fuzz_constructors(data):
    draw = data.draw
    kind = draw(st.sampled_from(["grid", "covering", "fill", "material", "scheme", "damping", "set_params",
                                 "region"]))
    number = st.one_of(anything, st.floats(-3.0, 3.0))
    if kind == "grid":
        dim = draw(st.integers(1, 3))
        g = outcome(lambda: jm.Grid(_vec(draw, dim, number), _vec(draw, dim, number), _vec(draw, dim, small_count)))
        if g is not None:
            assert all(math.isfinite(h) and h > 0 for h in g.spacing)
    elif kind == "covering":
        dim = draw(st.integers(1, 3))
        upper_dim = draw(st.sampled_from([dim, dim, 1, 2]))
        spacing = draw(st.one_of(anything, st.floats(0.05, 2.0)))
        pad = draw(st.one_of(st.just(0.0), anything, st.floats(0.0, 1.0)))
        shape = draw(st.sampled_from([None, jm.Linear(), jm.QuadraticBSpline(), "linear"]))
        g = outcome(lambda: jm.Grid.covering(_vec(draw, dim, number), _vec(draw, upper_dim, number), spacing,
                                             shape=shape, pad=pad))
        if g is not None:
            assert g.dim == dim and all(math.isfinite(h) and h > 0 for h in g.spacing)
    elif kind == "fill":
        grid = draw(st.sampled_from([jm.Grid((0.0,), (1.0,), (4,)), GRID2]))
        region = draw(st.sampled_from([jm.Box((0.0,), (0.5,)), jm.Box((0, 0), (1, 1)), jm.Disk((0.5, 0.5), 0.3),
                                       jm.Ring((0.5, 0.5), 0.1, 0.4)]))
        velocity = draw(st.one_of(anything, st.tuples(number, number), st.tuples(number, number, number)))
        density = draw(st.one_of(st.none(), anything))
        p = outcome(lambda: jm.fill(grid, region, ppc=draw(small_count), velocity=velocity, density=density))
        if p is not None:
            assert p.x.shape[1] == grid.dim and p.v.shape == p.x.shape
    elif kind == "material":
        cls = draw(st.sampled_from([jm.LinearElastic, jm.NeoHookean]))
        outcome(lambda: cls(E=draw(number), nu=draw(number), density=draw(number)))
    elif kind == "scheme":
        which = draw(st.sampled_from(["flip", "xpic", "fmpm", "pic"]))
        if which == "flip":
            outcome(lambda: jm.FLIP(beta=draw(number)))
        elif which == "pic":
            outcome(lambda: jm.PIC())
        else:
            cls = jm.XPIC if which == "xpic" else jm.FMPM
            outcome(lambda: cls(order=draw(st.one_of(small_count, st.integers(1, 60))), beta=draw(number)))
    elif kind == "damping":
        outcome(lambda: jm.Damping(grid=draw(number), particle=draw(number)))
    elif kind == "region":
        which = draw(st.sampled_from(["box", "disk", "ring"]))
        if which == "box":
            outcome(lambda: jm.Box(_vec(draw, 2, number), _vec(draw, 2, number)))
        elif which == "disk":
            outcome(lambda: jm.Disk(_vec(draw, 2, number), draw(number)))
        else:
            outcome(lambda: jm.Ring(_vec(draw, 2, number), draw(number), draw(number)))
    else:
        name = draw(st.sampled_from(["E", "nu", "density", "beta", "alpha_g", "alpha_p", "gravity"]))
        value = draw(st.one_of(number, st.tuples(number), st.tuples(number, number)))
        sim = outcome(lambda: jm.set_params(FUZZ_SIM, **{name: value}))
        if sim is not None:
            got = np.asarray(jm.get_params(sim, name)[name])
            assert np.all(np.isfinite(got))


FUZZ_SIM = small_simulation()

SCENE_SIZES = {  # small valid values, so that a successful build is cheap
    "bar": dict(cells=st.integers(1, 8), ppc=st.integers(1, 2), cfl=st.floats(0.05, 0.5), t_end=st.floats(0.1, 2.0),
                frames=st.integers(1, 5), E=st.floats(1.0, 1e3), density=st.floats(0.1, 10.0),
                v0=st.floats(-0.2, 0.2), length=st.floats(1.0, 25.0)),
    "disks": dict(spacing=st.sampled_from([0.1, 0.2, 0.25]), ppc=st.integers(1, 2), dt=st.floats(1e-3, 1e-2),
                  t_end=st.floats(1e-3, 0.02), frames=st.integers(1, 3), E=st.floats(1.0, 1e3),
                  nu=st.floats(-0.9, 0.45), density=st.floats(1.0, 1e3), speed=st.floats(-1.0, 1.0),
                  pad=st.floats(0.0, 0.2)),
    "spin": dict(spacing=st.sampled_from([0.2, 0.25]), ppc=st.integers(1, 2), radius=st.floats(0.1, 0.3),
                 omega=st.floats(0.5, 2.0), cfl=st.floats(0.1, 0.5), t_end=st.floats(0.01, 0.1),
                 frames=st.integers(1, 3), density=st.floats(0.5, 2.0)),
    "mpm88": dict(n_particles=st.integers(1, 32), n_grid=st.integers(8, 16), dt=st.floats(1e-3, 1e-2),
                  t_end=st.floats(1e-3, 0.02), E=st.floats(1.0, 1e3), gravity=st.floats(-10.0, 10.0),
                  bound=st.integers(1, 3), seed=st.integers(0, 5), frames=st.integers(1, 3)),
}
INVALID = st.sampled_from([0, -1, 2.5, NAN, INF, -INF, "x", True, None, [1]])


@pytest.mark.slow
@settings(max_examples=30, deadline=None, suppress_health_check=list(HealthCheck))
@given(st.data())
def test_fuzz_scene_builds(data):
    """Scene builds with a few options, each drawn valid (small) or invalid: a Setup with a finite
    positive dt, at least one step and a finite state, or a one-line InputError.  (No run.)"""
    draw = data.draw
    name = draw(st.sampled_from(sorted(SCENE_SIZES)))
    sizes = SCENE_SIZES[name]
    chosen = draw(st.lists(st.sampled_from(sorted(sizes) + ["bogus"]), min_size=1, max_size=4, unique=True))
    options = {}
    for option in chosen:
        options[option] = draw(INVALID) if option == "bogus" or draw(st.booleans()) else draw(sizes[option])
    if name != "mpm88":  # keep successful builds small
        options.setdefault("t_end", 0.01)
        options.setdefault("frames", 2)
        options.setdefault({"bar": "cells", "disks": "spacing", "spin": "spacing"}[name],
                           {"bar": 4, "disks": 0.25, "spin": 0.25}[name])
    else:
        options.setdefault("n_grid", 8)
        options.setdefault("n_particles", 8)
        options.setdefault("t_end", 0.01)
    setup = outcome(lambda: jm.scene(name, **options))
    if setup is not None:
        assert math.isfinite(setup.dt) and setup.dt > 0 and setup.steps >= 1 and setup.save_every >= 1
        _finite_tree(setup.state)


def test_run_and_ensemble_entry_points_name_a_bad_argument():
    """Found by an ad hoc fuzz of the run and ensemble entry points (2026-11-29): each raised a raw exception, and a
    negative frames_per_chunk ran chunks of negative frames until the process's memory ran out."""
    setup = jm.scene("bar", cells=8)
    sim, state, dt = setup.sim, setup.state, setup.dt
    batch = {"E": [1.0, 2.0]}
    cases = [
        (lambda: sim.run(state, None, 4, 2), ("run: dt must be a number, got None", "setup.dt")),
        (lambda: sim.run(state, np.ones((2, 2)), 4, 2), ("dt must be a single number",)),
        (lambda: sim.run(state, dt, 4, 2, frames_per_chunk=-1, progress=True),
         ("frames_per_chunk = -1 must be a positive integer",)),
        (lambda: jm.ensemble(sim, state, np.zeros(0), 4, 2, params=batch), ("ensemble: dt must be a single number",)),
        (lambda: jm.ensemble(sim, state, dt, 4, 2, params=batch, devices=[]), ("devices = []", "jax.devices()")),
        (lambda: jm.ensemble(sim, state, dt, 4, 2, params=batch, devices="cpu"), ("devices = 'cpu'",)),
        (lambda: jm.ensemble(sim, state, dt, 4, 2, params=batch, devices=3), ("devices = 3",)),
        (lambda: jm.ensemble(sim, state, dt, 4, 2, states=[1, 2]), ("states = list", "leading batch axis")),
        (lambda: jm.ensemble(sim, None, dt, 4, 2, params=batch), ("state = NoneType",)),
        (lambda: jm.get_params(sim, None), ("None is not a parameter name",)),
        (lambda: sim.with_chunks(np.zeros(0)), ("chunk_particles = array([], dtype=float64)", "'auto'")),
        (lambda: jm.stable_dt(sim, state, 0.5), ("stable_dt: grid = Simulation", "sim.stable_dt(state)")),
        (lambda: jm.stable_dt(sim.grid, state, state.v), ("stable_dt: material = State",)),
    ]
    for make, words in cases:
        assert_input_error(make, *words)


def test_io_calibrate_and_model_entry_points_name_a_bad_argument(tmp_path):
    """The same fuzz over the files, the calibration and the model's own methods: each raised a raw exception (a
    TypeError, an AttributeError, "The truth value of an empty array is ambiguous", an MLIRError for rollout's
    frames = -1)."""
    setup = jm.scene("bar", cells=8)
    sim, state, dt = setup.sim, setup.state, setup.dt
    cases = [
        (lambda: jm.load_h5(None), ("load_h5: path = None is not a path",)),
        (lambda: jm.resume(None), ("resume: path = None is not a path",)),
        (lambda: jm.H5Writer(None, sim, state, dt), ("H5Writer: path = None is not a path",)),
        (lambda: jm.H5Writer(tmp_path / "a.h5", sim, state, "x"), ("H5Writer: dt must be a number",)),
        (lambda: jm.H5Writer(tmp_path / "a.h5", sim, state, dt, mode=np.zeros(0)), ("mode = array([]",)),
        (lambda: jm.H5Writer(tmp_path / "a.h5", sim, state, dt, fields=np.zeros(0)), ("fields = array([]",)),
        (lambda: jm.calibrate(None, {"E": 1.0}, steps=1), ("calibrate: loss = None is not a function",)),
        (lambda: jm.calibrate(lambda p: p["E"], {"E": 1.0}, bounds=-1, steps=1), ("bounds = -1",)),
        (lambda: jm.calibrate(lambda p: p["E"], {"E": 1.0}, tol="x", steps=1), ("calibrate: tol must be a number",)),
        (lambda: jm.scene([]), ("unknown scene []",)),
        (lambda: sim.rollout(state, dt, -1), ("rollout: frames = -1 must be a non-negative integer",)),
        (lambda: sim.rollout(state, dt, 2, 0), ("rollout: save_every = 0 must be a positive integer",)),
        (lambda: sim.diagnostics(None), ("diagnostics: state = NoneType",)),
        (lambda: sim.stable_dt(state, []), ("stable_dt: cfl must be a single number",)),
        (lambda: sim.with_backend(np.zeros(0)), ("backend = array([]",)),
        (lambda: sim.with_adjoint(np.zeros(0)), ("adjoint = array([]",)),
        (lambda: sim.with_particle_devices(np.zeros(0)), ("particle_devices = array([]",)),
        (lambda: jm.compiler_options(np.zeros(0)), ("backend = array([]",)),
        (lambda: sim.in_precision(-1), ("dtype = -1", "jnp.float32 or jnp.float64")),
        (lambda: sim.in_precision(None), ("dtype = None", "jnp.float32 or jnp.float64")),
    ]
    for make, words in cases:
        assert_input_error(make, *words)
