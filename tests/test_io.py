"""HDF5 output (docs/design.md "HDF5 output layout"): save_h5 / H5Writer / load_h5 round trips, the
root attributes, the XDMF sidecar, chunked writing during a run, and an interrupted run."""

import json
import xml.etree.ElementTree as ET

import h5py
import jax.numpy as jnp
import numpy as np
import pytest

import jaxmpm as jm

STEPS, SAVE_EVERY = 40, 10
FRAMES = STEPS // SAVE_EVERY + 1  # the initial frame plus one every SAVE_EVERY steps

# docs/design.md layout: dataset -> (History field or None, shape as a function of T, N, D)
LAYOUT = {
    "time": ("time", lambda T, N, D: (T,)),
    "particles/x": ("x", lambda T, N, D: (T, N, D)),
    "particles/v": ("v", lambda T, N, D: (T, N, D)),
    "particles/mass": (None, lambda T, N, D: (N,)),
    "particles/volume0": (None, lambda T, N, D: (N,)),
    "energy/kinetic": ("kinetic", lambda T, N, D: (T,)),
    "energy/strain": ("strain", lambda T, N, D: (T,)),
    "energy/dissipated": ("dissipated", lambda T, N, D: (T,)),
    "momentum/linear": ("momentum", lambda T, N, D: (T, D)),
    "momentum/angular": ("angular", lambda T, N, D: (T, 1 if D < 3 else 3)),
}
ROOT_ATTRIBUTES = ("scene", "scheme", "order", "beta", "alpha_g", "alpha_p", "shape", "update", "dt", "cells",
                   "ppc", "dtype", "jaxmpm version", "scene parameters")


@pytest.fixture(scope="module")
def bar_run():
    """The bar scene run for 40 steps, a frame every 10: (setup, history)."""
    setup = jm.scene("bar")
    _, history = setup.sim.run(setup.state, setup.dt, STEPS, SAVE_EVERY)
    return setup, history


def save_bar(path, setup, history):
    jm.save_h5(path, setup.sim, history, state=setup.state, dt=setup.dt, scene="bar", params=setup.params,
               ppc=setup.params["ppc"])


def assert_layout(res, history, state):
    """Every dataset of the layout with its shape and dtype, equal to the history / state."""
    T = len(history)
    N, D = np.asarray(state.x).shape
    dtype = np.asarray(state.x).dtype
    for name, (field, shape) in LAYOUT.items():
        assert name in res, f"missing dataset {name}"
        assert res[name].shape == shape(T, N, D), name
        assert res[name].dtype == dtype, name
        expected = np.asarray(getattr(history, field)) if field else np.asarray(getattr(state, name.split("/")[1]))
        np.testing.assert_array_equal(res[name], expected, err_msg=name)


@pytest.mark.slow
def test_save_and_load_roundtrip(tmp_path, bar_run):
    setup, history = bar_run
    path = tmp_path / "bar.h5"
    save_bar(path, setup, history)
    res = jm.load_h5(path)
    assert len(history) == FRAMES
    assert_layout(res, history, setup.state)
    np.testing.assert_allclose(res["time"], setup.dt * SAVE_EVERY * np.arange(FRAMES), rtol=1e-13)


def test_root_attributes(tmp_path, bar_run):
    setup, history = bar_run
    path = tmp_path / "bar.h5"
    save_bar(path, setup, history)
    res = jm.load_h5(path)
    attrs = res.attrs
    for key in ROOT_ATTRIBUTES:
        assert key in attrs, f"missing root attribute {key!r}"
    assert attrs["scene"] == "bar"
    assert attrs["scheme"] == "FLIP" and attrs["order"] == 1 and attrs["beta"] == 1.0
    assert attrs["alpha_g"] == 0.0 and attrs["alpha_p"] == 0.0
    assert attrs["shape"] == "Linear" and attrs["update"] == "USL"
    assert attrs["dt"] == setup.dt
    assert tuple(attrs["cells"]) == setup.sim.grid.cells
    assert attrs["ppc"] == 2
    assert attrs["dtype"] == "float64"
    assert attrs["jaxmpm version"] == jm.__version__
    assert json.loads(attrs["scene parameters"]) == setup.params
    assert res.params == setup.params


def parse_xdmf(h5_path):
    return ET.parse(h5_path.with_suffix(".xdmf")).getroot()


def assert_xdmf_matches(h5_path, res):
    """Well-formed XDMF 3: a temporal collection with one Polyvertex grid per frame, whose time is
    the frame's and whose DataItems are whole HDF5 datasets (what meshio reads): the connectivity
    0..N-1, then the geometry and velocity, views of frame t of /particles/x and /particles/v."""
    T, N, D = res["particles/x"].shape
    root = parse_xdmf(h5_path)
    assert root.tag == "Xdmf"
    collection = root.find("Domain/Grid")
    assert collection.get("GridType") == "Collection" and collection.get("CollectionType") == "Temporal"
    frames = collection.findall("Grid")
    assert len(frames) == T

    def read(item):
        assert item.get("Format") == "HDF"
        file_name, _, dataset = item.text.strip().partition(":")
        with h5py.File(h5_path.parent / file_name, "r") as f:
            value = f[dataset][()]
        assert list(value.shape) == [int(v) for v in item.get("Dimensions").split()]
        return value

    for t, frame in enumerate(frames):
        assert float(frame.find("Time").get("Value")) == res["time"][t]
        topology = frame.find("Topology")
        assert topology.get("TopologyType") == "Polyvertex" and int(topology.get("NumberOfElements")) == N
        np.testing.assert_array_equal(read(topology.find("DataItem")), np.arange(N).reshape(N, 1))
        points = read(frame.find("Geometry/DataItem"))
        np.testing.assert_array_equal(points[:, :D], res["particles/x"][t])
        np.testing.assert_array_equal(points[:, D:], 0.0)  # 1D: XY with y = 0
        attributes = {a.get("Name"): a.find("DataItem") for a in frame.findall("Attribute")}
        np.testing.assert_array_equal(read(attributes["position"]).reshape(N, D), res["particles/x"][t])
        np.testing.assert_array_equal(read(attributes["velocity"]).reshape(N, D), res["particles/v"][t])


def test_xdmf_sidecar(tmp_path, bar_run):
    setup, history = bar_run
    path = tmp_path / "bar.h5"
    save_bar(path, setup, history)
    assert_xdmf_matches(path, jm.load_h5(path))


def test_chunked_writer_equals_one_shot_save(tmp_path, bar_run):
    """sim.run(..., writer=w, frames_per_chunk=2) writes exactly what save_h5 writes at once."""
    setup, history = bar_run
    one_shot = tmp_path / "one_shot.h5"
    save_bar(one_shot, setup, history)
    chunked = tmp_path / "chunked.h5"
    with jm.H5Writer(chunked, setup.sim, setup.state, dt=setup.dt, scene="bar", params=setup.params,
                     ppc=setup.params["ppc"]) as writer:
        final, returned = setup.sim.run(setup.state, setup.dt, STEPS, SAVE_EVERY, writer=writer,
                                        frames_per_chunk=2)
    assert returned is None
    assert int(final.step) == STEPS
    a, b = jm.load_h5(one_shot), jm.load_h5(chunked)
    assert sorted(a) == sorted(b)
    for name in a:
        if LAYOUT[name][0] is None:  # per-particle constants
            np.testing.assert_array_equal(b[name], a[name], err_msg=name)
            continue
        # frames 1.. come from the same compiled rollout: identical bits; the chunked path computes
        # the initial frame eagerly, so its reductions may differ in the last bit
        np.testing.assert_array_equal(b[name][1:], a[name][1:], err_msg=name)
        np.testing.assert_allclose(b[name][0], a[name][0], rtol=4e-16, atol=0, err_msg=name)
    assert a.attrs.keys() == b.attrs.keys()
    for key in a.attrs:
        np.testing.assert_array_equal(b.attrs[key], a.attrs[key], err_msg=key)
    assert_xdmf_matches(chunked, b)


def take(history, frames):
    return jm.History(**{f: None if getattr(history, f) is None else getattr(history, f)[frames]
                         for f in ("time", "x", "v", "kinetic", "strain", "dissipated", "momentum", "angular")})


def test_interrupted_writer_keeps_the_frames_written(tmp_path, bar_run):
    """An exception after two appended chunks leaves a readable file holding those frames."""
    setup, history = bar_run
    path = tmp_path / "interrupted.h5"
    with pytest.raises(KeyboardInterrupt):
        with jm.H5Writer(path, setup.sim, setup.state, dt=setup.dt, scene="bar", params=setup.params) as writer:
            writer.append(take(history, slice(0, 2)))
            writer.append(take(history, slice(2, 4)))
            raise KeyboardInterrupt
    res = jm.load_h5(path)
    assert_layout(res, take(history, slice(0, 4)), setup.state)
    assert_xdmf_matches(path, res)
    with h5py.File(path, "r") as f:  # the file was closed cleanly
        assert f["time"].shape == (4,)


def test_layout_in_3d_float32(tmp_path):
    """A 3D float32 history: angular momentum has 3 components, datasets keep float32, and the
    XDMF geometry is XYZ."""
    T, N, D = 3, 5, 3
    rng = np.random.default_rng(0)
    grid = jm.Grid((0.0,) * D, (1.0,) * D, (4,) * D)
    sim = jm.Simulation(grid=grid, shape=jm.UGIMP(ppc=3), material=jm.NeoHookean(E=10.0, nu=0.3),
                        scheme=jm.XPIC(order=4, beta=0.5), damping=jm.Damping(grid=0.25, particle=0.5),
                        update="MUSL")
    f32 = lambda *s: jnp.asarray(rng.random(s), jnp.float32)  # noqa: E731
    state = jm.State(x=f32(N, D), v=f32(N, D), F=jnp.broadcast_to(jnp.eye(D, dtype=jnp.float32), (N, D, D)),
                     mass=f32(N), volume0=f32(N), time=jnp.zeros((), jnp.float32), step=jnp.zeros((), jnp.int32),
                     dissipated=jnp.zeros((), jnp.float32))
    history = jm.History(time=jnp.arange(T, dtype=jnp.float32), x=f32(T, N, D), v=f32(T, N, D), kinetic=f32(T),
                         strain=f32(T), dissipated=f32(T), momentum=f32(T, D), angular=f32(T, 3))
    path = tmp_path / "cube.h5"
    jm.save_h5(path, sim, history, state=state, dt=0.01)
    res = jm.load_h5(path)
    assert_layout(res, history, state)
    assert res.attrs["dtype"] == "float32" and res.attrs["ppc"] == 3
    assert res.attrs["scheme"] == "XPIC" and res.attrs["order"] == 4 and res.attrs["beta"] == 0.5
    assert res.attrs["alpha_g"] == 0.25 and res.attrs["alpha_p"] == 0.5
    assert res.attrs["shape"] == "UGIMP" and res.attrs["update"] == "MUSL"
    assert tuple(res.attrs["cells"]) == (4, 4, 4)
    assert_xdmf_matches(path, res)
    geometry = parse_xdmf(path).find("Domain/Grid/Grid/Geometry")
    assert geometry.get("GeometryType") == "XYZ"


def test_no_write_replaces_a_file_without_consent(tmp_path, bar_run):
    """save_h5 and H5Writer refuse an existing file, or the XDMF sidecar an earlier run left beside
    the name, unless overwrite=True; the refused file is left as it was."""
    import re

    setup, history = bar_run
    path = tmp_path / "bar.h5"
    xdmf, views = path.with_suffix(".xdmf"), path.with_suffix(".xdmf.h5")
    save_bar(path, setup, history)
    before = path.read_bytes()
    with pytest.raises(jm.InputError, match=re.escape(f"save_h5: {path}, {xdmf} and {views} exist; pass "
                                                      "overwrite=True to replace them, or choose another path")):
        save_bar(path, setup, history)
    assert path.read_bytes() == before
    path.unlink()  # the sidecar stays: another run's views
    with pytest.raises(jm.InputError, match=re.escape(f"H5Writer: {xdmf} and {views} exist (the XDMF sidecar of an "
                                                      "earlier run); pass overwrite=True")):
        jm.H5Writer(path, setup.sim, setup.state)
    assert not path.exists() and not path.with_suffix(".h5.lock").exists()
    jm.H5Writer(path, setup.sim, setup.state, xdmf=False).close()  # writes no sidecar: none is in the way
    with pytest.raises(jm.InputError, match=re.escape(f"H5Writer: {path} exists;")):
        jm.H5Writer(path, setup.sim, setup.state, xdmf=False)
    jm.save_h5(path, setup.sim, history, state=setup.state, dt=setup.dt, overwrite=True)
    assert_layout(jm.load_h5(path), history, setup.state)
