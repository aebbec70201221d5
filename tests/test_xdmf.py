"""The XDMF sidecar read back by meshio (``meshio.xdmf.TimeSeriesReader``) for every scene, 1D to 3D:
every frame (its time), every particle, and position / velocity / mass / volume0 equal to the HDF5
arrays; per-particle fields of any rank; a sidecar left by another run is rebuilt.  VTK's
``vtkXdmfReader`` is checked too where ``vtk`` is installed (it is not a test dependency)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxmpm as jm

meshio = pytest.importorskip("meshio")

# The smallest run of each scene: a few steps, frames=2 (so 2-3 frames), few particles.
SMALL = {
    "bar": dict(cells=4, t_end=0.5),
    "disks": dict(spacing=0.1, dt=1e-3, t_end=4e-3),
    "spin": dict(spacing=0.1, dt=1e-3, t_end=4e-3),
    "rings": dict(spacing=0.5, dt=1e-4, t_end=4e-4),
    "mpm88": dict(n_particles=64, n_grid=16, dt=2e-4, t_end=8e-4),
    "mms": dict(dim=3, cells=2, t_end=0.01),
    "vortex": dict(spacing=0.25, t_end=0.02),
    "bars_impact": dict(cells=4, t_end=0.05),
    "slide": dict(spacing=0.05, t_end=0.005),
    "heat1d": dict(cells=4, t_end=0.01),
    "heat_step": dict(cells=4, t_end=0.01),
    "diffusion2d": dict(cells=4, t_end=0.01),
    "thermal_bar": dict(cells=4, t_end=0.01),
    "cylinder": dict(cells=4, t_end=0.01),
    "column_collapse": dict(cells=2, aspect=1.0, t_end=0.01),
    "incline": dict(spacing=0.05, t_end=0.005),
    "taylor_bar": dict(cells=1, t_end=2e-6),
    "dam_break": dict(cells=2, t_end=0.005),
}


def write_in_two_chunks(path, sim, state, history, **attrs):
    """H5Writer.append twice, as a chunked run does: the sidecar is written, then extended."""
    first = max(1, len(history) // 2)
    with jm.H5Writer(path, sim, state, **attrs) as writer:
        writer.append(jax.tree_util.tree_map(lambda a: a[:first], history))
        writer.append(jax.tree_util.tree_map(lambda a: a[first:], history))


def read_xdmf(h5_path):
    """(points, cells, [(time, point_data)] per frame) through meshio's time-series reader."""
    with meshio.xdmf.TimeSeriesReader(h5_path.with_suffix(".xdmf")) as reader:
        points, cells = reader.read_points_cells()
        frames = []
        for k in range(reader.num_steps):
            t, point_data, _ = reader.read_data(k)
            frames.append((t, {name: np.array(value) for name, value in point_data.items()}))
    return np.array(points), cells, frames


def assert_meshio_reads(h5_path):
    """Every frame and every particle of the HDF5 file, through the sidecar."""
    res = jm.load_h5(h5_path)
    x, v, time = res["particles/x"], res["particles/v"], res["time"]
    T, N, D = x.shape
    points, cells, frames = read_xdmf(h5_path)
    assert points.shape == (N, max(D, 2))  # 1D: XY points with y = 0 (meshio reads XY or XYZ only)
    np.testing.assert_array_equal(points[:, :D], x[0])
    np.testing.assert_array_equal(points[:, D:], 0.0)
    assert len(cells) == 1 and cells[0].type == "vertex"
    np.testing.assert_array_equal(cells[0].data, np.arange(N).reshape(N, 1))
    assert len(frames) == T
    for k, (t, data) in enumerate(frames):
        assert t == time[k]
        np.testing.assert_array_equal(data["position"].reshape(N, D), x[k], err_msg=f"frame {k}")
        np.testing.assert_array_equal(data["velocity"].reshape(N, D), v[k], err_msg=f"frame {k}")
        np.testing.assert_array_equal(data["mass"], res["particles/mass"])
        np.testing.assert_array_equal(data["volume0"], res["particles/volume0"])
    return res, frames


def test_every_scene_has_a_small_configuration():
    assert set(SMALL) == set(jm.SCENES), "give each new scene a small configuration in SMALL"


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(SMALL))
def test_meshio_reads_every_frame_and_particle(tmp_path, name):
    setup = jm.scene(name, frames=2, **SMALL[name])
    _, history = setup.run()
    path = tmp_path / f"{name}.h5"
    write_in_two_chunks(path, setup.sim, setup.state, history, dt=setup.dt, scene=setup.name, params=setup.params)
    res, _ = assert_meshio_reads(path)
    assert len(res["time"]) == len(history) >= 2
    assert res["particles/x"].shape[0] == len(history)


def synthetic_history(T, N, D, fields=None, seed=0):
    rng = np.random.default_rng(seed)
    r = lambda *s: jnp.asarray(rng.random(s))  # noqa: E731
    return jm.History(time=jnp.arange(T, dtype=jnp.float64) * 0.1, x=r(T, N, D), v=r(T, N, D), kinetic=r(T),
                      strain=r(T), dissipated=r(T), momentum=r(T, D), angular=r(T, 1 if D < 3 else 3),
                      fields=fields or {})


def synthetic_state(N, D, seed=1):
    rng = np.random.default_rng(seed)
    return jm.State(x=jnp.asarray(rng.random((N, D))), v=jnp.zeros((N, D)),
                    F=jnp.broadcast_to(jnp.eye(D), (N, D, D)), mass=jnp.asarray(rng.random(N)),
                    volume0=jnp.asarray(rng.random(N)), time=jnp.zeros(()), step=jnp.zeros((), jnp.int32),
                    dissipated=jnp.zeros(()))


@pytest.fixture(scope="module")
def sim2d():
    grid = jm.Grid((0.0, 0.0), (1.0, 1.0), (4, 4))
    return jm.Simulation(grid=grid, shape=jm.Linear(), material=jm.LinearElastic(E=1.0, nu=0.2), scheme=jm.FLIP())


def test_fields_of_every_rank_are_point_data(tmp_path, sim2d):
    """A scalar, a vector and a 2x2 matrix per particle: (N,), (N, 2), (N, 4) point data (row-major)."""
    T, N, D = 3, 6, 2
    rng = np.random.default_rng(2)
    fields = {"temperature": jnp.asarray(rng.random((T, N))), "flux": jnp.asarray(rng.random((T, N, D))),
              "stretch": jnp.asarray(rng.random((T, N, D, D)))}
    path = tmp_path / "fields.h5"
    write_in_two_chunks(path, sim2d, synthetic_state(N, D), synthetic_history(T, N, D, fields), dt=0.1)
    res, frames = assert_meshio_reads(path)
    for k, (_, data) in enumerate(frames):
        np.testing.assert_array_equal(data["temperature"], res["particles/temperature"][k])
        np.testing.assert_array_equal(data["flux"], res["particles/flux"][k])
        np.testing.assert_array_equal(data["stretch"], res["particles/stretch"][k].reshape(N, D * D))
    assert 'Name="stretch" AttributeType="Matrix"' in path.with_suffix(".xdmf").read_text()


def test_sidecar_of_another_run_is_rebuilt(tmp_path, sim2d):
    """The same file name written again (overwrite=True) with another particle count: the views follow
    the new file."""
    path = tmp_path / "again.h5"
    jm.save_h5(path, sim2d, synthetic_history(4, 7, 2), state=synthetic_state(7, 2), dt=0.1)
    assert_meshio_reads(path)
    jm.save_h5(path, sim2d, synthetic_history(3, 5, 2, seed=3), state=synthetic_state(5, 2, seed=4), dt=0.1,
               overwrite=True)
    _, frames = assert_meshio_reads(path)
    assert len(frames) == 3


def test_vtk_reads_every_frame_and_particle(tmp_path):
    """VTK's XDMF reader (ParaView's "XDMF Reader"): time steps, points and velocities, 1D and 2D."""
    vtk = pytest.importorskip("vtk")
    from vtk.util.numpy_support import vtk_to_numpy

    for name, options in (("bar", SMALL["bar"]), ("disks", SMALL["disks"])):
        setup = jm.scene(name, frames=2, **options)
        _, history = setup.run()
        path = tmp_path / f"{name}.h5"
        write_in_two_chunks(path, setup.sim, setup.state, history, dt=setup.dt)
        res = jm.load_h5(path)
        T, N, D = res["particles/x"].shape
        reader = vtk.vtkXdmfReader()
        reader.SetFileName(str(path.with_suffix(".xdmf")))
        reader.UpdateInformation()
        times = reader.GetOutputInformation(0).Get(vtk.vtkStreamingDemandDrivenPipeline.TIME_STEPS())
        np.testing.assert_array_equal(times, res["time"])
        for k, t in enumerate(times):
            reader.UpdateTimeStep(t)
            grid = reader.GetOutputDataObject(0)
            assert grid.GetNumberOfPoints() == N and grid.GetNumberOfCells() == N
            points = vtk_to_numpy(grid.GetPoints().GetData())
            velocity = vtk_to_numpy(grid.GetPointData().GetArray("velocity")).reshape(N, -1)
            np.testing.assert_array_equal(points[:, :D], res["particles/x"][k])
            np.testing.assert_array_equal(velocity[:, :D], res["particles/v"][k])
