"""Per-frame particle fields chosen by name (issue 29, item 4): ``stress``, ``pressure``, ``J``, ``F``
and a material's saved state, in memory (``sim.run(fields=...)``), in HDF5 (``jm.H5Writer(...,
fields=...)``: ``/particles/<name>``, the root attribute ``fields``), in the XDMF sidecar (read back
by meshio's time-series reader), in ``jm.plot_frames`` and on the command line (``--fields``, kept by
``jaxmpm resume``).

The stored values are checked against the physics written out here from the frame's state: the
Cauchy stress tau / J of each law, the pressure -tr(sigma_3D) / 3 with the out-of-plane stress of
plane strain and the zero lateral stress of a uniaxial-stress bar, J = det F."""

from __future__ import annotations

import signal

import equinox as eqx
import h5py
import numpy as np
import pytest
from cases import assert_same_files, run_cli

import jaxmpm as jm
from jaxmpm.model import frame_fields

ALL = ("stress", "pressure", "J", "F")
BAR = dict(cells=8, t_end=2.0, frames=4)  # 64 steps, a frame every 16: 5 frames of 16 particles


@pytest.fixture(scope="module")
def bar():
    return jm.scene("bar", **BAR)


@pytest.fixture(scope="module")
def bar_run(bar):
    return bar.run(fields=ALL)


def lame(E, nu):
    return E * nu / ((1 + nu) * (1 - 2 * nu)), E / (2 * (1 + nu))


def test_the_bar_s_frames_hold_its_stress_pressure_J_and_F(bar, bar_run):
    """1D, LinearElastic in uniaxial stress: sigma = E (F - 1) / F, the lateral stresses zero, so
    p = -sigma / 3; the last frame is the final state."""
    final, history = bar_run
    assert set(history.fields) == set(ALL) and len(history) == 5
    F = np.asarray(final.F)[:, 0, 0]
    sigma = 100.0 * (F - 1.0) / F  # E = 100
    np.testing.assert_allclose(history.fields["stress"][-1][:, 0, 0], sigma, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(history.fields["pressure"][-1], -sigma / 3.0, rtol=1e-12, atol=1e-15)
    np.testing.assert_array_equal(history.fields["F"][-1], final.F)
    np.testing.assert_allclose(history.fields["J"], np.asarray(history.fields["F"])[..., 0, 0], rtol=1e-15)
    assert np.ptp(np.asarray(history.fields["J"])) > 1e-4  # the bar does deform: the check has teeth
    np.testing.assert_array_equal(history.fields["J"][0], 1.0)  # the initial frame: undeformed, no stress
    np.testing.assert_array_equal(history.fields["stress"][0], 0.0)


@pytest.fixture(scope="module")
def disks_file(tmp_path_factory):
    """The disks (2D, LinearElastic in plane strain) spreading apart, written with their stress
    and pressure: (setup, final state, path)."""
    disks = jm.scene("disks", spacing=0.1, dt=1e-3, t_end=4e-3, frames=2)
    spreading = eqx.tree_at(lambda s: s.v, disks.state, 0.5 * (disks.state.x - 0.5))  # the disks stretch
    path = tmp_path_factory.mktemp("disks") / "disks.h5"
    with jm.H5Writer(path, disks.sim, spreading, dt=disks.dt, fields=("stress", "pressure")) as writer:
        final, _ = disks.sim.run(spreading, disks.dt, disks.steps, disks.save_every, writer=writer)
    return disks, final, path


def test_plane_strain_stress_and_pressure(disks_file):
    """sigma = tau / J, p = -(tau_xx + tau_yy + tau_zz) / 3J with tau_zz = lambda tr eps of plane strain."""
    _, final, path = disks_file
    res = jm.load_h5(path)
    F = np.asarray(final.F)
    J = np.linalg.det(F)
    eps = 0.5 * (F + np.swapaxes(F, 1, 2)) - np.eye(2)
    lam, mu = lame(1000.0, 0.3)
    tr = np.trace(eps, axis1=1, axis2=2)
    tau = lam * tr[:, None, None] * np.eye(2) + 2 * mu * eps
    np.testing.assert_allclose(res["particles/stress"][-1], tau / J[:, None, None], rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(res["particles/pressure"][-1], -(np.trace(tau, axis1=1, axis2=2) + lam * tr) / (3 * J),
                               rtol=1e-10, atol=1e-12)
    assert np.abs(res["particles/pressure"][-1]).max() > 1e-3


def test_the_fluid_s_pressure():
    """mpm88's fluid: sigma = E (J - 1) / J I in every direction, so p = -E (J - 1) / J (E = 400)."""
    fluid = jm.scene("mpm88", n_particles=64, n_grid=16, dt=2e-4, t_end=8e-4, frames=2)
    final, history = fluid.run(fields=("pressure", "J"))
    J = np.linalg.det(np.asarray(final.F))
    np.testing.assert_allclose(history.fields["J"][-1], J, rtol=1e-14)
    np.testing.assert_allclose(history.fields["pressure"][-1], -400.0 * (J - 1) / J, rtol=1e-10, atol=1e-12)
    assert np.abs(J - 1).max() > 1e-6


def test_the_axisymmetric_stress_and_its_hoop_component():
    """The cylinder: the 3x3 (r, z, theta) stress, p = -tr(sigma) / 3; jm.plot_frames names the hoop
    stress stress_tt."""
    cylinder = jm.scene("cylinder", cells=4, t_end=0.01, frames=1)
    final, history = cylinder.run(fields=("stress", "pressure"))
    sigma = np.asarray(history.fields["stress"][-1])
    assert sigma.shape == (final.x.shape[0], 3, 3)
    material = cylinder.sim.material
    F = np.asarray(final.F)
    eps = 0.5 * (F + np.swapaxes(F, 1, 2)) - np.eye(3)
    lam, mu = lame(float(material.E), float(material.nu))
    tau = lam * np.trace(eps, axis1=1, axis2=2)[:, None, None] * np.eye(3) + 2 * mu * eps
    np.testing.assert_allclose(sigma, tau / np.linalg.det(F)[:, None, None], rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(history.fields["pressure"][-1], -np.trace(sigma, axis1=1, axis2=2) / 3, rtol=1e-12)
    assert np.abs(sigma[:, 2, 2]).max() > 0  # the hoop stress the scene is about
    from jaxmpm.io.plot import _open

    with _open(history, cylinder.sim, cylinder.state) as run:
        assert {"stress_rr", "stress_zz", "stress_tt", "stress_rz"} <= set(run.fields)
        np.testing.assert_array_equal(run.values("stress_tt", 1), sigma[:, 2, 2])


class Tracked(jm.IncrementalElastic):
    """IncrementalElastic offering its state's accumulated work per reference volume (the seam a
    plastic law uses for its plastic strain)."""

    saved_state = ("energy",)


def test_a_material_s_saved_state_is_a_field(bar):
    sim = eqx.tree_at(lambda s: s.material, bar.sim, Tracked(E=100.0, nu=0.0, density=1.0))
    state = sim.init(bar.particles)
    assert "energy" in frame_fields.available(sim, state)
    assert "energy" not in frame_fields.available(bar.sim, bar.state)
    final, history = sim.run(state, bar.dt, 32, 16, fields=("energy", "pressure"))
    np.testing.assert_array_equal(history.fields["energy"][-1], final.material_state["energy"])
    assert np.max(history.fields["energy"][-1]) > 0
    tau = np.asarray(final.material_state["stress"])[:, 0, 0]  # the law's Kirchhoff stress, uniaxial
    np.testing.assert_allclose(history.fields["pressure"][-1], -tau / np.asarray(final.F)[:, 0, 0] / 3, rtol=1e-12)


def xdmf_frames(path):
    with pytest.importorskip("meshio").xdmf.TimeSeriesReader(path.with_suffix(".xdmf")) as reader:
        reader.read_points_cells()
        return [reader.read_data(k) for k in range(reader.num_steps)]


def padded(tensors):
    """(N, d, d) -> (N, 9): the 3x3 row-major rows of the XDMF Tensor, zeros beyond d."""
    n, d, _ = tensors.shape
    out = np.zeros((n, 3, 3))
    out[:, :d, :d] = tensors
    return out.reshape(n, 9)


@pytest.fixture(scope="module")
def bar_file(tmp_path_factory, bar):
    """The bar written with every field: the initial frame, then chunks of 2 frames."""
    path = tmp_path_factory.mktemp("bar") / "bar.h5"
    with jm.H5Writer(path, bar.sim, bar.state, dt=bar.dt, fields=ALL) as writer:
        bar.run(writer=writer, frames_per_chunk=2)
    return path


def test_the_file_and_its_xdmf_hold_the_frames_fields(bar_file, bar_run):
    """The writer saves what the in-memory run holds, bit for bit; load_h5 lists the fields; the
    sidecar shows each frame's J and pressure as Scalars and F and the stress as 3x3 Tensors."""
    path = bar_file
    res = jm.load_h5(path)
    assert res.fields == ALL and res.attrs["fields"] == "stress,pressure,J,F"
    for name in ALL:
        np.testing.assert_array_equal(res[f"particles/{name}"], bar_run[1].fields[name], err_msg=name)
    with h5py.File(path, "r") as f:
        assert f["particles/stress"].maxshape == (None, 16, 1, 1)  # grows with the run, as x and v do
    frames = xdmf_frames(path)
    assert len(frames) == 5
    for k, (t, data, _) in enumerate(frames):
        assert t == res["time"][k]
        np.testing.assert_array_equal(data["J"], res["particles/J"][k])
        np.testing.assert_array_equal(data["pressure"], res["particles/pressure"][k])
        np.testing.assert_array_equal(data["stress"], padded(res["particles/stress"][k]))
        np.testing.assert_array_equal(data["F"], padded(res["particles/F"][k]))
    text = path.with_suffix(".xdmf").read_text()
    assert 'Name="stress" AttributeType="Tensor"' in text and 'Name="J" AttributeType="Scalar"' in text


def test_a_saved_part_of_a_run_keeps_its_fields_when_resumed(tmp_path, bar, bar_file):
    """A part of the run kept in memory, saved with its schedule: the file lists its fields, and
    jm.resume goes on saving them, to the file of the whole run bit for bit."""
    part, part_history = bar.sim.run(bar.state, bar.dt, 2 * bar.save_every, bar.save_every, fields=ALL)
    cut = tmp_path / "cut.h5"
    jm.save_h5(cut, bar.sim, part_history, state=part, dt=bar.dt, steps=bar.steps, save_every=bar.save_every)
    assert jm.load_h5(cut).fields == ALL and jm.load_h5(cut)["particles/F"].shape[0] == 3
    jm.resume(cut, bar)
    assert_same_files(bar_file, cut)


def test_a_2d_run_s_tensors_in_the_xdmf_and_the_plot(disks_file):
    """2D: the 2x2 stress as a zero-padded 3x3 Tensor; jm.plot_frames colours by a component."""
    _, _, path = disks_file
    res = jm.load_h5(path)
    for k, (_, data, _) in enumerate(xdmf_frames(path)):
        np.testing.assert_array_equal(data["stress"], padded(res["particles/stress"][k]))
        np.testing.assert_array_equal(data["pressure"], res["particles/pressure"][k])
    pytest.importorskip("matplotlib")
    from jaxmpm.io.plot import _open

    with _open(str(path)) as run:
        assert {"pressure", "stress", "stress_xx", "stress_xy", "stress_yy"} <= set(run.fields)
        np.testing.assert_array_equal(run.values("stress_xy", 1), res["particles/stress"][1][:, 0, 1])
    fig = jm.plot_frames(path, field="stress_xx", frames=(0, -1))
    assert fig.axes[-1].get_ylabel() == "stress (xx)"  # the colour bar's label


def test_vtk_reads_the_fields(disks_file):
    """VTK's XDMF reader (ParaView's): the stress a 9-component tensor array, the pressure a scalar,
    equal to the file's frames (vtk is not a test dependency: skipped without it)."""
    vtk = pytest.importorskip("vtk")
    from vtk.util.numpy_support import vtk_to_numpy

    _, _, path = disks_file
    res = jm.load_h5(path)
    reader = vtk.vtkXdmfReader()
    reader.SetFileName(str(path.with_suffix(".xdmf")))
    reader.UpdateInformation()
    times = reader.GetOutputInformation(0).Get(vtk.vtkStreamingDemandDrivenPipeline.TIME_STEPS())
    assert len(times) == len(res["time"])
    for k, t in enumerate(times):
        reader.UpdateTimeStep(t)
        data = reader.GetOutputDataObject(0).GetPointData()
        assert data.GetArray("stress").GetNumberOfComponents() == 9
        np.testing.assert_array_equal(vtk_to_numpy(data.GetArray("stress")), padded(res["particles/stress"][k]))
        np.testing.assert_array_equal(vtk_to_numpy(data.GetArray("pressure")), res["particles/pressure"][k])


def test_each_scene_s_default_fields_are_fields_every_model_offers():
    """FIELD_DEFAULTS (what `jaxmpm run SCENE` saves without --fields) names scenes and the fields
    any model has (no scene's terms declare one of these names: ParticleField names are theirs),
    or, for a scene whose material is fixed (no ``material`` option: the plastic scenes), the
    entries its material saves (``saved_state``: plastic_strain)."""
    import inspect

    from jaxmpm.scenes._common import FIELD_DEFAULTS

    assert set(FIELD_DEFAULTS) <= set(jm.SCENES)
    for name, fields in FIELD_DEFAULTS.items():
        own = set(fields) - set(frame_fields.FRAME_FIELDS)
        assert fields, name
        if own:
            assert "material" not in inspect.signature(jm.SCENES[name][0]).parameters, name
            assert own <= set(jm.scene(name).sim.material.saved_state), name
    assert FIELD_DEFAULTS["cylinder"] == ("stress",) and FIELD_DEFAULTS["mpm88"] == ("pressure",)


def test_bad_field_choices_are_input_errors(tmp_path, bar):
    sim, state = bar.sim, bar.state
    with pytest.raises(jm.InputError, match=r"H5Writer: fields: unknown field 'sigma'; choose from stress, "
                                            r"pressure, J, F$"):
        jm.H5Writer(tmp_path / "a.h5", sim, state, fields=("sigma",))
    assert not (tmp_path / "a.h5").exists()
    with pytest.raises(jm.InputError, match=r"'J' is named twice"):
        bar.run(fields=("J", "J"))
    with pytest.raises(jm.InputError, match=r"give a tuple of field names, e.g. \('stress', 'J'\)"):
        bar.run(fields="stress")
    with pytest.raises(jm.InputError, match="pass save_particles=True, or no fields"):
        bar.run(fields=("J",), save_particles=False)
    heat = jm.scene("heat1d", cells=4, t_end=0.01, frames=1)
    with pytest.raises(jm.InputError, match="'temperature' is a field a term of the model declares, saved in every "
                                            "frame already"):
        frame_fields.chosen(heat.sim, heat.state, ("temperature",))
    with jm.H5Writer(tmp_path / "b.h5", sim, state, fields=("J",)) as writer:
        with pytest.raises(jm.InputError, match=r"run: fields = \('F',\) but the writer saves \('J',\)"):
            bar.run(writer=writer, fields=("F",))
    with pytest.raises(jm.InputError, match=r"b.h5 saves \('J',\) in every frame; a continued run keeps"):
        jm.H5Writer(tmp_path / "b.h5", sim, state, mode="a", fields=("stress",))


@pytest.mark.slow
def test_cli_fields_default_choice_errors_and_resume(tmp_path, capsys, monkeypatch):
    """--fields is stored in the command; a run stopped by SIGINT and continued by `jaxmpm resume`
    equals the uninterrupted one, fields included; the scene's default; an unknown name exits 2."""
    run = ["run", "bar", "--cells", "8", "--t-end", "2", "--frames", "4", "--no-progress"]
    whole, cut, plain = tmp_path / "whole.h5", tmp_path / "cut.h5", tmp_path / "plain.h5"
    assert run_cli(run + ["--fields", "J,stress", "--out", str(whole)]) == 0
    res = jm.load_h5(whole)
    assert res.fields == ("stress", "J") and '"fields": "stress,J"' in res.attrs["command"]  # in one order

    appended = jm.H5Writer.append

    def append_then_interrupt(self, history):  # Ctrl-C once the initial frame is saved
        appended(self, history)
        if self.frames == 1:
            signal.raise_signal(signal.SIGINT)

    monkeypatch.setattr(jm.H5Writer, "append", append_then_interrupt)
    assert run_cli(run + ["--fields", "J,stress", "--out", str(cut)]) == 130
    monkeypatch.undo()
    assert jm.load_h5(cut)["particles/J"].shape[0] < 5
    assert run_cli(["resume", str(cut), "--no-progress"]) == 0
    assert_same_files(whole, cut)

    assert run_cli(run + ["--out", str(plain)]) == 0  # the bar's default: its stress
    assert jm.load_h5(plain).fields == ("stress",)
    assert run_cli(run + ["--fields", "none", "--out", str(plain), "--force"]) == 0
    assert jm.load_h5(plain).fields == () and "particles/stress" not in jm.load_h5(plain)
    capsys.readouterr()
    assert run_cli(run + ["--fields", "stress,hoop", "--out", str(tmp_path / "bad.h5")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("jaxmpm: error: --fields (comma-separated names, or none): unknown field 'hoop'; "
                          "choose from stress, pressure, J, F") and err.count("\n") == 1
    assert not (tmp_path / "bad.h5").exists()
