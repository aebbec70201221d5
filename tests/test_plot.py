"""jm.plot_frames, jm.animate and the `jaxmpm plot` / `jaxmpm animate` commands (jaxmpm/io/plot.py):
the images exist, have the size asked for, and differ between frames where the particles differ;
every input error is one line naming the option.

The files are written by jm.H5Writer, as `jaxmpm run` writes them, from the models and initial
states of three scenes -- the 1D bar, the disks with contact (2D, two materials) and a 3D cube --
with made-up frames: a run would spend seconds compiling and draw nothing different."""

import argparse

import numpy as np
import pytest

import jaxmpm as jm
from jaxmpm.io import plot as plot_module

pytest.importorskip("matplotlib")
iio = pytest.importorskip("imageio.v3")

FIGSIZE, DPI = (4.0, 3.0), 50  # 200 x 150 pixels


def _made_up(setup, path, frames=4):
    """``setup``'s model and state written to ``path`` with ``frames`` frames in which the
    particles drift along their velocity (by up to 15% of the body's size) and speed up."""
    x0, v0 = np.asarray(setup.state.x), np.asarray(setup.state.v)
    n, d = x0.shape
    t = np.linspace(0.0, 0.3, frames)
    v = np.stack([v0 * (1.0 + 2.0 * s) + 0.05 * (k + 1) for k, s in enumerate(t)])
    drift = 0.5 * (x0.max(axis=0) - x0.min(axis=0)) * v0 / np.abs(v0).max()
    x = np.stack([x0 + drift * s for s in t])
    zeros = np.zeros(frames)
    history = jm.History(time=t, x=x, v=v, kinetic=zeros, strain=zeros, dissipated=zeros,
                         momentum=np.zeros((frames, d)), angular=np.zeros((frames, 1 if d < 3 else 3)),
                         fields={"temperature": np.stack([np.full(n, 300.0 + 10.0 * k) for k in range(frames)])})
    with jm.H5Writer(path, setup.sim, setup.state, dt=setup.dt, scene=setup.name, params=setup.params,
                     ppc=setup.params.get("ppc"), xdmf=False) as writer:
        writer.append(history)
    return str(path), history


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    folder = tmp_path_factory.mktemp("plots")
    bar = jm.scene("bar", cells=4, frames=2)
    bar_path, history = _made_up(bar, folder / "bar.h5", frames=3)
    disks = jm.scene("disks", spacing=0.1, contact="frictionless", frames=2, t_end=0.01)
    return {"bar": bar_path, "bar_history": (history, bar), "disks": _made_up(disks, folder / "disks.h5")[0],
            "cube": _cube(folder / "cube.h5")}


def _cube(path, frames=3):
    """A 3D run in the HDF5 layout, written with h5py (only what a plot reads): a cube of 4^3
    particles, 2 per cell, in a box of 4^3 cells, moving along (1, 0.5, 0) and speeding up."""
    import h5py

    side = (np.arange(4) + 0.5) / 4
    x0 = np.stack(np.meshgrid(side, side, side, indexing="ij"), axis=-1).reshape(-1, 3) * 0.5 + 0.1
    t = np.linspace(0.0, 0.2, frames)
    with h5py.File(path, "w") as f:
        f["time"] = t
        f["particles/x"] = np.stack([x0 + s * np.array([1.0, 0.5, 0.0]) for s in t])
        f["particles/v"] = np.stack([np.tile([1.0 + s, 0.5, 0.0], (64, 1)) * (1.0 + x0[:, :1]) for s in t])
        f["particles/volume0"] = np.full(64, 0.125 ** 3)
        f.attrs.update(grid_lower=np.zeros(3), grid_upper=np.ones(3), cells=np.array([4, 4, 4]), ppc=2)
    return str(path)


def _inside(fig, image):
    """The pixels inside the first panel of ``fig`` (its frame of axes, without the spines)."""
    box = fig.axes[0].get_window_extent()
    height = image.shape[0]
    return image[int(height - box.y1) + 2:int(height - box.y0) - 2, int(box.x0) + 2:int(box.x1) - 2, :3]


def _png(fig_or_path):
    return iio.imread(fig_or_path)


def test_png_size_and_frames_differ(runs, tmp_path):
    for name in ("bar", "disks", "cube"):
        first, last = tmp_path / f"{name}0.png", tmp_path / f"{name}1.png"
        fig0 = jm.plot_frames(runs[name], frames=0, out=first, figsize=FIGSIZE, dpi=DPI)
        jm.plot_frames(runs[name], frames=-1, out=last, figsize=FIGSIZE, dpi=DPI)
        a, b = _png(first), _png(last)
        assert a.shape[:2] == b.shape[:2] == (150, 200), name  # figsize x dpi, (rows, columns)
        inside_a, inside_b = _inside(fig0, a), _inside(fig0, b)
        assert inside_a.size > 1000
        assert (inside_a != inside_b).any(axis=-1).mean() > 0.002, name  # the particles moved or changed colour
        assert (inside_a != 255).any(), name  # something is drawn


def test_panels_colour_bar_and_titles(runs):
    fig = jm.plot_frames(runs["disks"], frames=(0, 1, -1), field="vx")
    panels = [ax for ax in fig.axes if ax.get_visible() and ax.get_title()]
    assert len(panels) == 3
    assert [ax.get_title().split()[:2] for ax in panels] == [["t", "="]] * 3
    assert panels[0].get_title() != panels[-1].get_title()
    colour_bar = [ax for ax in fig.axes if ax.get_ylabel() == "velocity vx"]
    assert len(colour_bar) == 1  # one, shared
    assert all(ax.get_aspect() == 1.0 for ax in panels)
    lower, upper = jm.load_h5(runs["disks"]).attrs["grid_lower"], jm.load_h5(runs["disks"]).attrs["grid_upper"]
    x0, x1 = panels[0].get_xlim()
    assert x0 < lower[0] < upper[0] < x1 and x1 - x0 < 1.1 * (upper[0] - lower[0])  # the grid box, framed
    # markers of the particle spacing (0.1 / 2): in points, about the spacing in data units
    fig.canvas.draw()
    box = panels[0].get_window_extent()
    points_per_unit = box.width / (x1 - x0) * 72 / fig.dpi
    diameter = np.sqrt(panels[0].collections[0].get_sizes()[0])
    assert diameter == pytest.approx(2 / np.sqrt(np.pi) * 0.05 * points_per_unit, rel=1e-2)
    side = jm.plot_frames(runs["cube"], frames=-1, axes="yz", dpi=30).axes[0]  # 3D: a projection
    assert (side.get_xlabel(), side.get_ylabel()) == ("y", "z")
    assert np.allclose(side.collections[0].get_offsets(), jm.load_h5(runs["cube"])["particles/x"][-1][:, 1:])


def test_fields_sources_and_material(runs, tmp_path):
    fig = jm.plot_frames(runs["disks"], frames="all", field="material", out=tmp_path / "m.png", dpi=40)
    bar = [ax for ax in fig.axes if ax.get_ylabel() == "material"][0]
    assert list(bar.get_yticks()) == [0, 1]  # one colour per material
    values = fig.axes[0].collections[0].get_array()
    assert set(np.unique(values)) == {0.0, 1.0}
    with plot_module._open(runs["disks"]) as run:  # every field of the file, its values per particle
        assert run.fields == ["speed", "vx", "vy", "displacement", "mass", "material", "temperature", "volume0"]
        v = np.asarray(jm.load_h5(runs["disks"])["particles/v"][2])
        assert np.allclose(run.values("speed", 2), np.linalg.norm(v, axis=1))
        assert np.allclose(run.values("vy", 2), v[:, 1]) and run.values("displacement", 0).max() == 0
        assert run.values("temperature", 3).tolist() == [330.0] * run.n
    jm.plot_frames(runs["disks"], frames=-1, field="temperature", dpi=30)
    # the same from a jm.load_h5 result and from a History with its model and state
    loaded = jm.plot_frames(jm.load_h5(runs["bar"]), frames=(0, -1), dpi=30)
    history, setup = runs["bar_history"]
    held = jm.plot_frames(history, frames=(0, -1), dpi=30, sim=setup.sim, state=setup.state)
    for fig in (loaded, held):
        ax = fig.axes[0]
        assert ax.get_ylabel() == "speed |v|" and len(ax.collections[0].get_offsets()) == setup.state.x.shape[0]
    assert np.array_equal(loaded.axes[1].collections[0].get_offsets(), held.axes[1].collections[0].get_offsets())


def test_gif_frames_fixed_limits(runs, tmp_path):
    out = jm.animate(runs["disks"], tmp_path / "d.gif", fps=5, figsize=FIGSIZE, dpi=DPI)
    frames = iio.imread(out, index=None)
    assert frames.shape[:3] == (4, 150, 200)
    fig = jm.plot_frames(runs["disks"], frames=0, figsize=FIGSIZE, dpi=DPI)  # the animation's layout
    insides = [_inside(fig, frame) for frame in frames]
    assert all((a != b).any(axis=-1).mean() > 0.002 for a, b in zip(insides, insides[1:]))
    every = iio.imread(jm.animate(runs["cube"], tmp_path / "c.gif", every=2, dpi=30), index=None)
    assert every.shape[0] == 2  # frames 0 and 2 of 3


@pytest.mark.filterwarnings("ignore:os.fork")  # imageio-ffmpeg starts ffmpeg in a process of JAX's
def test_mp4(runs, tmp_path, monkeypatch):
    if plot_module._have("imageio_ffmpeg"):
        import imageio.v2

        out = jm.animate(runs["bar"], tmp_path / "b.mp4", dpi=30)
        assert imageio.v2.get_reader(out).count_frames() == 3
    monkeypatch.setattr(plot_module, "_have", lambda module: module != "imageio_ffmpeg")
    with pytest.raises(jm.InputError, match=r"out='.*b\.mp4': writing MP4 needs imageio-ffmpeg: pip install "
                                            r"imageio-ffmpeg \(or write a GIF: .*b\.gif\)"):
        jm.animate(runs["bar"], tmp_path / "b.mp4")


def test_errors(runs, tmp_path):
    import h5py

    not_run = tmp_path / "other.h5"
    with h5py.File(not_run, "w") as f:
        f["data"] = np.zeros(3)
    text = tmp_path / "notes.h5"
    text.write_text("not HDF5")
    history, bar = runs["bar_history"]
    jm.H5Writer(tmp_path / "begun.h5", bar.sim, bar.state, xdmf=False).close()  # the header a run publishes first
    cases = [
        (dict(path_or_result=tmp_path / "missing.h5"), r"path_or_result='.*missing\.h5': no such file"),
        (dict(path_or_result=not_run), r"is not a jaxmpm run \(no /time and /particles/x\)"),
        (dict(path_or_result=text), "is not an HDF5 file"),
        (dict(path_or_result=tmp_path / "begun.h5"), r"begun\.h5' holds no frames yet: its run has just begun"),
        (dict(field="pressure"), r"field='pressure' is not a field of .*bar\.h5; choose one of speed, vx, "
                                 r"displacement, mass, temperature, volume0$"),
        (dict(frames=(0, 3)), r"frames=\(0, 3\): frame 3 is out of range: .* holds 3 frames \(0\.\.2, or -3\.\.-1"),
        (dict(frames=-4), r"frame -4 is out of range"),
        (dict(frames=(0.5,)), r"must be frame indices"),
        (dict(out=tmp_path / "a.bmp"), r"out='.*a\.bmp': unknown extension '\.bmp'; end the name in \.png, "),
        (dict(out=tmp_path / "no" / "a.png"), r"the folder .* does not exist"),
        (dict(dpi=0), r"dpi=0 must be a positive number"),
        (dict(clim=(1, 0)), r"clim=\(1, 0\) must be two finite numbers"),
        (dict(cmap="nope"), r"cmap='nope' is not a matplotlib colormap"),
        (dict(path_or_result=runs["cube"], axes="xx"), r"axes='xx': give two of x, y, z"),
        (dict(path_or_result=42), r"path_or_result: a int is not a run"),
    ]
    for kwargs, message in cases:
        kwargs = {"path_or_result": runs["bar"]} | kwargs
        with pytest.raises(jm.InputError, match=message):
            jm.plot_frames(**kwargs)
    for kwargs, message in [(dict(out=tmp_path / "a.avi"), r"end the name in \.gif or \.mp4"),
                            (dict(out=tmp_path / "a.gif", fps=0), r"fps=0 must be a positive number"),
                            (dict(out=tmp_path / "a.gif", every=0), r"every=0 must be a positive integer"),
                            (dict(out=tmp_path / "a.gif", field="material"), r"field='material' is not a field")]:
        with pytest.raises(jm.InputError, match=message):
            jm.animate(runs["bar"], **kwargs)


def _parser():
    """The `jaxmpm` parser as jaxmpm/cli.py builds it, with the plot commands added."""
    parser = argparse.ArgumentParser(prog="jaxmpm")
    sub = parser.add_subparsers(dest="command")
    plot_module.add_plot_commands(sub)
    return parser


def test_commands(runs, tmp_path, capsys):
    parser = _parser()
    source = tmp_path / "run.h5"
    source.write_bytes(open(runs["disks"], "rb").read())
    assert plot_module.run_plot_command(parser.parse_args(["plot", str(source), "--dpi", "40"])) == 0
    image = _png(tmp_path / "run.png")  # beside the file by default
    assert image.shape[0] > 100 and "wrote" in capsys.readouterr().out
    args = parser.parse_args(["plot", str(source), "--frames", "0,-1,2", "--field", "material", "--out",
                              str(tmp_path / "m.png"), "--dpi", "30"])
    assert plot_module.run_plot_command(args) == 0 and (tmp_path / "m.png").exists()
    args = parser.parse_args(["animate", str(source), "--every", "3", "--fps", "4", "--dpi", "30", "--no-progress"])
    assert plot_module.run_plot_command(args) == 0
    assert iio.imread(tmp_path / "run.gif", index=None).shape[0] == 2  # frames 0 and 3
    for argv, message in [
        (["plot", str(tmp_path / "none.h5")], r"FILE\.h5 .*none\.h5: no such file"),
        (["plot", str(source), "--field", "p"], r"--field p is not a field of .*run\.h5; choose one of speed, "),
        (["plot", str(source), "--frames", "0,9"], r"--frames 0,9: frame 9 is out of range"),
        (["plot", str(source), "--frames", "first"], r"--frames 'first': give frame indices separated by commas"),
        (["plot", str(source), "--out", str(tmp_path / "a.gif")], r"--out .*a\.gif: unknown extension '\.gif'"),
        (["animate", str(source), "--out", str(tmp_path / "a.png")], r"--out .*a\.png: unknown extension"),
        (["animate", str(source), "--every", "0"], r"--every 0 must be a positive integer"),
    ]:
        with pytest.raises(SystemExit) as stop:
            plot_module.run_plot_command(parser.parse_args(argv))
        assert stop.value.code == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and err.startswith("jaxmpm: error: "), err
        assert __import__("re").search(message, err), (message, err)


def test_an_existing_image_is_replaced_only_with_consent(runs, tmp_path, capsys):
    """`jaxmpm plot` and `animate` refuse an output file that exists (the default one beside FILE.h5
    included) unless --force; plot_frames and animate likewise unless overwrite=True."""
    parser = _parser()
    source = tmp_path / "run.h5"
    source.write_bytes(open(runs["bar"], "rb").read())
    image, movie = tmp_path / "run.png", tmp_path / "run.gif"
    image.write_bytes(b"precious")
    movie.write_bytes(b"precious")
    for argv, out in ((["plot", str(source), "--dpi", "30"], image), (["animate", str(source), "--dpi", "30"], movie)):
        with pytest.raises(SystemExit) as stop:
            plot_module.run_plot_command(parser.parse_args(argv))
        assert stop.value.code == 2 and out.read_bytes() == b"precious"
        err = capsys.readouterr().err
        assert err == f"jaxmpm: error: --out {out} exists; pass --force to replace it, or choose another file\n"
    assert plot_module.run_plot_command(parser.parse_args(["plot", str(source), "--dpi", "30", "--force"])) == 0
    assert _png(image).shape[0] > 10
    with pytest.raises(jm.InputError, match=r"out='.*run\.png' exists; pass overwrite=True to replace it"):
        jm.plot_frames(runs["bar"], out=image, dpi=30)
    with pytest.raises(jm.InputError, match=r"out='.*run\.gif' exists; pass overwrite=True to replace it"):
        jm.animate(runs["bar"], movie, dpi=30)
    assert movie.read_bytes() == b"precious"
    jm.animate(runs["bar"], movie, dpi=30, overwrite=True)
    assert iio.imread(movie, index=None).shape[0] == 3
