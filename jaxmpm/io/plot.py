"""Pictures of a run without writing code: :func:`plot_frames` (chosen frames side by side, a PNG)
and :func:`animate` (every frame, a GIF or MP4), and the ``jaxmpm plot`` and ``jaxmpm animate``
commands built on them (:func:`add_plot_commands`, :func:`run_plot_command`).

The particles are drawn as a scatter coloured by a field -- ``speed`` (|v|), a velocity component
(``vx``, ``vy``, ``vz``), ``displacement`` (|x - x0|), ``material`` (multimaterial runs), or any
per-particle dataset the file stores under ``/particles`` (``temperature``, ``mass``, ``pressure``,
``J``, the norm of a vector field such as ``contact_force`` or one of its components,
``contact_force_x``, the norm of a tensor such as ``stress`` or one of its components, ``stress_xy``;
on an axisymmetric grid in (r, z, theta): ``stress_rr``, ``stress_tt``) -- inside the
grid box (``grid_lower``/``grid_upper``), with equal aspect and each frame's time in its title.
Markers are equal-area discs of the particle spacing (the grid spacing over ``ppc``, else the
particles' volume), so a body looks filled.  A 1D run is drawn as position against the field, a 3D
run as its projection on two axes (``axes="xy"``, ``"xz"``, ``"yz"``).

Matplotlib draws on its own ``Figure`` with an Agg canvas: no pyplot state, the user's backend is
left alone (in a notebook the returned figure shows as the cell's value).  matplotlib and imageio
(with Pillow, for GIFs) are the ``plots`` extra; MP4 needs ``imageio-ffmpeg`` besides.
"""

from __future__ import annotations

import importlib.util
import math
import os
import sys

import numpy as np

from ..core.errors import InputError, check

#: the subcommands :func:`add_plot_commands` adds to the ``jaxmpm`` parser
PLOT_COMMANDS = ("plot", "animate")
#: what :func:`animate` writes
MOVIE_EXTENSIONS = (".gif", ".mp4")
#: the file kinds :func:`plot_frames` writes (matplotlib's Agg canvas)
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".pdf", ".svg")
_AXIS_NAMES = "xyz"
_INSTALL = "pip install 'jaxmpm[plots]' (matplotlib, imageio)"


def _say(option: str, value, cli: bool) -> str:
    """An option and its value as the caller wrote them: ``--frames 0,9`` on the command line,
    ``frames=(0, 9)`` in Python."""
    if not cli:
        return f"{'path_or_result' if option == 'source' else option}={value!r}"
    if isinstance(value, (list, tuple)):
        value = ",".join(str(v) for v in value)
    elif isinstance(value, float):
        value = f"{value:g}"
    return f"{'FILE.h5' if option == 'source' else '--' + option.replace('_', '-')} {value}"


# --------------------------------------------------------------------------------------------------
# the run: frames from a file, a jm.load_h5 result or a History
# --------------------------------------------------------------------------------------------------


class _Run:
    """The frames of a run, read lazily from a file (h5py datasets) or held in memory.

    ``data`` maps the layout's paths (``time``, ``particles/x``, ...) to arrays or datasets;
    ``attrs`` holds the root attributes that are known (grid_lower, grid_upper, cells, ppc, scene,
    scheme)."""

    def __init__(self, data, attrs: dict, name: str, cli: bool = False, handle=None):
        self.data, self.attrs, self.name, self.cli, self._handle = data, attrs, name, cli, handle
        self.time = np.asarray(data["time"][()], dtype=float).reshape(-1)
        self.frames = int(self.time.shape[0])
        x = data["particles/x"]
        check(len(x.shape) == 3 and x.shape[0] == self.frames,
              f"{name}: /particles/x has shape {tuple(x.shape)}, not (frames, particles, dimension) with "
              f"{self.frames} frames; is it a jaxmpm run?")
        check(self.frames > 0, f"{name} holds no frames yet (its run stopped before the first frame was "
                               "saved); run it again, or wait for its first frame")
        _, self.n, self.dim = (int(s) for s in x.shape)
        self.lower = _vector(attrs.get("grid_lower"), self.dim)
        self.upper = _vector(attrs.get("grid_upper"), self.dim)
        self._fields = self._catalogue()

    def close(self) -> None:
        if self._handle is not None:
            self._handle.close()
            self._handle = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    # the fields ---------------------------------------------------------------------------------

    def _catalogue(self) -> dict:
        """{field name: (label, values(frame) -> (N,), categorical)} for every field this run has."""
        fields = {}
        has_v = "particles/v" in self.data
        if has_v:
            fields["speed"] = ("speed |v|", lambda i: _norm(self._frame("particles/v", i)), False)
            for k in range(self.dim):
                fields["v" + _AXIS_NAMES[k]] = (f"velocity v{_AXIS_NAMES[k]}",
                                                 lambda i, k=k: self._frame("particles/v", i)[:, k], False)
        fields["displacement"] = ("displacement |x - x0|",
                                  lambda i: _norm(self._frame("particles/x", i) - self._frame("particles/x", 0)),
                                  False)
        for path in sorted(self.data):
            if not path.startswith("particles/") or path.count("/") != 1 or path in ("particles/x", "particles/v"):
                continue
            name = path.split("/", 1)[1]
            shape = tuple(self.data[path].shape)
            if len(shape) == 1 and shape[0] == self.n:  # one value per particle for the whole run
                values = np.asarray(self.data[path][()])
                fields[name] = (name, lambda i, values=values: values, name == "material")
            elif len(shape) >= 2 and shape[:2] == (self.frames, self.n):
                if len(shape) == 2:
                    fields[name] = (name, lambda i, path=path: self._frame(path, i), False)
                else:  # a vector or tensor per particle: its norm, and a vector's components
                    fields[name] = (f"|{name}|", lambda i, path=path: _norm(self._frame(path, i)), False)
                    if len(shape) == 3 and shape[2] <= 3:
                        for k in range(shape[2]):
                            fields[f"{name}_{_AXIS_NAMES[k]}"] = (
                                f"{name} ({_AXIS_NAMES[k]})", lambda i, path=path, k=k: self._frame(path, i)[:, k],
                                False)
                    elif len(shape) == 4 and shape[2] == shape[3] in (self.dim, self.dim + 1) and shape[2] <= 3:
                        # a tensor (stress, F): each component, stress_xy; on an axisymmetric grid (d = D + 1)
                        # in (r, z, theta), stress_tt the hoop stress
                        axes = _AXIS_NAMES if shape[2] == self.dim else "rzt"
                        for a in range(shape[2]):
                            for b in range(shape[3]):
                                fields[f"{name}_{axes[a]}{axes[b]}"] = (
                                    f"{name} ({axes[a]}{axes[b]})",
                                    lambda i, path=path, a=a, b=b: self._frame(path, i)[:, a, b], False)
        return fields

    @property
    def fields(self) -> list[str]:
        return list(self._fields)

    def check_field(self, field) -> str:
        check(isinstance(field, str) and field in self._fields,
              f"{_say('field', field, self.cli)} is not a field of {self.name}; choose one of "
              f"{', '.join(self._fields)}")
        return field

    def label(self, field: str) -> str:
        return self._fields[field][0]

    def categorical(self, field: str) -> bool:
        return self._fields[field][2]

    def values(self, field: str, i: int) -> np.ndarray:
        return np.asarray(self._fields[field][1](i), dtype=float).reshape(self.n)

    def _frame(self, path: str, i: int) -> np.ndarray:
        return np.asarray(self.data[path][i], dtype=float)

    def positions(self, i: int) -> np.ndarray:
        return self._frame("particles/x", i).reshape(self.n, self.dim)

    # frames, box, spacing -----------------------------------------------------------------------

    def frame_indices(self, frames) -> list[int]:
        """The chosen frames as non-negative indices (negative ones count from the end, as in Python)."""
        if isinstance(frames, str) and frames.strip().lower() == "all":
            return list(range(self.frames))
        if isinstance(frames, (int, np.integer)) and not isinstance(frames, bool):
            frames = (frames,)
        try:
            chosen = list(frames)
        except TypeError:
            chosen = None
        check(chosen is not None and len(chosen) > 0
              and all(isinstance(f, (int, np.integer)) and not isinstance(f, bool) for f in chosen),
              f"{_say('frames', frames, self.cli)} must be frame indices (integers, negative from the end) or 'all'")
        for f in chosen:
            check(-self.frames <= f < self.frames,
                  f"{_say('frames', frames, self.cli)}: frame {f} is out of range: {self.name} holds "
                  f"{self.frames} frame{'s' * (self.frames != 1)} (0..{self.frames - 1}, or -{self.frames}..-1 "
                  "from the end)")
        return [int(f) % self.frames for f in chosen]

    def box(self, axes: tuple[int, ...]):
        """(lower, upper) of the plotted axes: the grid box, else the particles' extent over the run."""
        if self.lower is not None and self.upper is not None:
            return self.lower[list(axes)], self.upper[list(axes)]
        lo, hi = np.full(self.dim, np.inf), np.full(self.dim, -np.inf)
        for i in range(self.frames):
            x = self.positions(i)
            lo, hi = np.fmin(lo, np.nanmin(x, axis=0)), np.fmax(hi, np.nanmax(x, axis=0))
        pad = 0.05 * np.maximum(hi - lo, 1e-12)
        return (lo - pad)[list(axes)], (hi + pad)[list(axes)]

    def spacing(self) -> float | None:
        """The particle spacing: the grid spacing over the particles per cell, else volume^(1/D)."""
        cells, ppc = self.attrs.get("cells"), self.attrs.get("ppc")
        if self.lower is not None and self.upper is not None and cells is not None and ppc is not None:
            cells = _vector(cells, self.dim)
            if cells is not None and np.all(cells > 0) and float(ppc) > 0:
                return float(np.min((self.upper - self.lower) / cells)) / float(ppc)
        if "particles/volume0" in self.data:
            volume = np.asarray(self.data["particles/volume0"][()], dtype=float)
            volume = volume[np.isfinite(volume) & (volume > 0)]
            if volume.size:
                return float(np.median(volume)) ** (1.0 / self.dim)
        return None

    def title(self) -> str:
        scene, scheme = str(self.attrs.get("scene", "") or ""), str(self.attrs.get("scheme", "") or "")
        words = [w for w in (scene, f"({scheme})" if scheme else "") if w]
        return " ".join(words) if words else os.path.basename(self.name)


def _vector(value, dim: int):
    if value is None:
        return None
    value = np.asarray(value, dtype=float).reshape(-1)
    return value if value.shape == (dim,) and np.all(np.isfinite(value)) else None


def _norm(a) -> np.ndarray:
    a = np.asarray(a, dtype=float)
    return np.sqrt(np.sum(a.reshape(a.shape[0], -1) ** 2, axis=1))


def _open(source, sim=None, state=None, cli: bool = False) -> _Run:
    """A :class:`_Run` for a path, a :func:`jaxmpm.load_h5` result or a :class:`jaxmpm.History`."""
    if isinstance(source, (str, os.PathLike)):
        return _open_file(os.fspath(source), cli)
    if hasattr(source, "attrs") and isinstance(source, dict):  # jm.load_h5's Results
        check("time" in source and "particles/x" in source,
              "path_or_result: the loaded results hold no /time and /particles/x; load a jaxmpm run's file "
              "(jm.load_h5), or pass its path")
        return _Run(source, dict(source.attrs), "the loaded run", cli)
    if hasattr(source, "time") and hasattr(source, "x") and hasattr(source, "fields"):  # a History
        return _from_history(source, sim, state, cli)
    raise InputError(f"path_or_result: a {type(source).__name__} is not a run; pass the path of a jaxmpm "
                     "HDF5 file, jm.load_h5(path), or a History (with sim= for the grid box)")


def _open_file(path: str, cli: bool) -> _Run:
    import h5py

    what = _say("source", path, cli)
    check(os.path.exists(path), f"{what}: no such file; give a file written by `jaxmpm run --out` or "
                                "jm.save_h5")
    check(os.path.isfile(path), f"{what} is a directory; give a jaxmpm run's HDF5 file")
    try:
        f = h5py.File(path, "r")
    except OSError:
        raise InputError(f"{what} is not an HDF5 file; give a file written by `jaxmpm run --out` "
                         "or jm.save_h5") from None
    try:
        begun = "particles/mass" in f and "jaxmpm version" in f.attrs  # a run's header, published first
        check("time" in f or not begun, f"{what} holds no frames yet: its run has just begun, or stopped before "
                                        "its first frame was saved; wait for a frame, or run it again")
        check("time" in f and "particles/x" in f,
              f"{what} is not a jaxmpm run (no /time and /particles/x); give a file written by "
              "`jaxmpm run --out` or jm.save_h5" if not begun else
              f"{what} holds no particle positions (/particles/x): its run saved none (save_particles=False); "
              "run it with the particles saved")
        data = {}
        f.visititems(lambda name, obj: data.__setitem__(name, obj)
                     if isinstance(obj, h5py.Dataset) and not name.startswith("state/") else None)
        attrs = {k: (v.decode() if isinstance(v, bytes) else v) for k, v in f.attrs.items()}
        return _Run(data, attrs, path, cli, handle=f)
    except BaseException:
        f.close()
        raise


def _from_history(history, sim, state, cli: bool) -> _Run:
    check(history.x is not None, "path_or_result: the History holds no particle positions (the run "
                                 "was made with save_particles=False); run with the particles saved")
    data = {"time": np.asarray(history.time), "particles/x": np.asarray(history.x)}
    if history.v is not None:
        data["particles/v"] = np.asarray(history.v)
    data.update({f"particles/{k}": np.asarray(v) for k, v in history.fields.items()})
    attrs = {}
    if sim is not None:
        attrs.update(grid_lower=np.asarray(sim.grid.lower), grid_upper=np.asarray(sim.grid.upper),
                     cells=np.asarray(sim.grid.cells), ppc=int(getattr(sim.shape, "ppc", 0) or 0))
    if state is not None:
        data["particles/volume0"] = np.asarray(state.volume0)
        data["particles/mass"] = np.asarray(state.mass)
        if "material" in state.fields:
            data["particles/material"] = np.asarray(state.fields["material"])
    return _Run(data, attrs, "the History", cli)


# --------------------------------------------------------------------------------------------------
# drawing
# --------------------------------------------------------------------------------------------------


def _have(module: str) -> bool:
    """Whether ``module`` can be imported (the optional plotting packages)."""
    return importlib.util.find_spec(module) is not None


def _matplotlib(cli: bool):
    if not _have("matplotlib"):
        raise InputError(f"{'jaxmpm plot and animate need' if cli else 'plotting needs'} matplotlib: {_INSTALL}")
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    return Figure, FigureCanvasAgg


def _plane(run: _Run, axes) -> tuple[int, ...]:
    """The plotted axes: (0,) in 1D, (0, 1) in 2D, the two chosen ones in 3D."""
    if run.dim < 3:  # the default "xy" is the only projection of a 1D or 2D run
        check(axes == "xy", f"{_say('axes', axes, run.cli)}: a {run.dim}D run has one view; leave axes out (xz and "
                            "yz are views of a 3D run)")
        return (0,) if run.dim == 1 else (0, 1)
    ok = isinstance(axes, str) and len(axes) == 2 and set(axes) <= set("xyz") and axes[0] != axes[1]
    check(ok, f"{_say('axes', axes, run.cli)}: give two of x, y, z for the projection of a 3D run (xy, xz or yz)")
    return tuple(_AXIS_NAMES.index(a) for a in axes)


def _limits(run: _Run, field: str, frames, clim, cli: bool) -> tuple[float, float]:
    """Colour limits: ``clim`` if given, else the field's range over ``frames`` (a material's ids:
    one colour each)."""
    if clim is not None:
        ok = isinstance(clim, (tuple, list)) and len(clim) == 2 and all(np.isfinite(np.asarray(clim, dtype=float)))
        check(ok and float(clim[0]) < float(clim[1]),
              f"{_say('clim', clim, cli)} must be two finite numbers (low, high) with low < high")
        return float(clim[0]), float(clim[1])
    lo, hi = math.inf, -math.inf
    for i in frames:
        v = run.values(field, i)
        v = v[np.isfinite(v)]
        if v.size:
            lo, hi = min(lo, float(v.min())), max(hi, float(v.max()))
    if run.categorical(field):
        return -0.5, (max(hi, 0.0) if math.isfinite(hi) else 0.0) + 0.5
    if not math.isfinite(lo):
        return 0.0, 1.0
    if hi - lo <= 1e-12 * max(abs(lo), abs(hi), 1e-300):
        pad = 0.5 * abs(lo) if lo else 1.0
        return lo - pad, hi + pad
    return lo, hi


def _colours(run: _Run, field: str, limits, cmap):
    """(colormap, norm) for a field: a continuous map, or one colour per material id."""
    import matplotlib
    from matplotlib.colors import BoundaryNorm, Normalize

    if run.categorical(field):
        count = int(round(limits[1] + 0.5))
        base = matplotlib.colormaps[cmap or ("tab10" if count <= 10 else "tab20")]
        colours = base.resampled(count) if base.N < count else base
        listed = matplotlib.colors.ListedColormap([colours(k) for k in range(count)])
        return listed, BoundaryNorm(np.arange(count + 1) - 0.5, count)
    try:
        return matplotlib.colormaps[cmap or "viridis"], Normalize(*limits)
    except KeyError:
        raise InputError(f"{_say('cmap', cmap, run.cli)} is not a matplotlib colormap; try viridis, plasma, "
                         "coolwarm or turbo") from None


class _Panel:
    """One axes showing one frame; :meth:`show` moves it to another frame (for the animation)."""

    def __init__(self, ax, run: _Run, field: str, plane, cmap, norm, height, height_limits, marker_scale):
        from matplotlib.patches import Rectangle

        self.ax, self.run, self.field, self.plane, self.height = ax, run, field, plane, height
        lower, upper = run.box(plane)
        if run.dim == 1:  # position against ``height`` (the field, or the velocity coloured by material)
            self.points = ax.scatter([], [], c=[], cmap=cmap, norm=norm, s=12, linewidths=0)
            for edge in (lower[0], upper[0]):
                ax.axvline(edge, color="0.35", lw=1.0)
            low, high = height_limits
            ax.set_ylim(low - 0.06 * (high - low), high + 0.06 * (high - low))
            ax.set_ylabel(run.label(height))
        else:
            self.points = ax.scatter([], [], c=[], cmap=cmap, norm=norm, s=4, linewidths=0)
            if run.lower is not None and run.upper is not None:
                ax.add_patch(Rectangle((lower[0], lower[1]), upper[0] - lower[0], upper[1] - lower[1],
                                       fill=False, edgecolor="0.35", lw=1.0))
            ax.set_aspect("equal")
            ax.set_ylabel(_AXIS_NAMES[plane[1]])
        pad = 0.03 * (upper - lower)
        ax.set_xlim(lower[0] - pad[0], upper[0] + pad[0])
        if run.dim > 1:
            ax.set_ylim(lower[1] - pad[1], upper[1] + pad[1])
        ax.set_xlabel(_AXIS_NAMES[plane[0]])
        self.marker_scale = marker_scale

    def show(self, i: int) -> None:
        x = self.run.positions(i)
        values = self.run.values(self.field, i)
        if self.run.dim == 1:
            heights = values if self.height == self.field else self.run.values(self.height, i)
            offsets = np.stack([x[:, 0], heights], axis=1)
        else:
            offsets = x[:, list(self.plane)]
        self.points.set_offsets(offsets)
        self.points.set_array(values)
        self.ax.set_title(f"t = {self.run.time[i]:.4g}  (frame {i})", fontsize="medium")

    def size_markers(self, spacing: float | None) -> None:
        """Markers of the particle spacing: discs of the same area as a particle's square (2D, 3D).
        Call after the figure is drawn once (the axes have their final size then)."""
        if self.run.dim == 1 or spacing is None:
            return
        fig = self.ax.figure
        box = self.ax.get_window_extent()
        x0, x1 = self.ax.get_xlim()
        points_per_unit = box.width / abs(x1 - x0) * 72.0 / fig.dpi
        diameter = 2.0 / math.sqrt(math.pi) * spacing * points_per_unit * self.marker_scale
        least = 72.0 / fig.dpi  # at least one pixel across
        self.points.set_sizes([max(diameter, least) ** 2])


#: the largest image a figure may make: Agg's limit on a side, and 1e8 pixels in all (400 MB of RGBA)
MAX_SIDE_PIXELS = 2**16
MAX_PIXELS = 1e8


def _figure(run: _Run, count: int, plane, figsize, dpi, cli: bool):
    Figure, FigureCanvasAgg = _matplotlib(cli)
    check(isinstance(dpi, (int, float, np.integer, np.floating)) and not isinstance(dpi, bool) and dpi > 0,
          f"{_say('dpi', dpi, cli)} must be a positive number of dots per inch (e.g. 100)")
    ncols = min(count, 4)
    nrows = -(-count // ncols)
    if figsize is None:
        if run.dim == 1:
            figsize = (4.2 * ncols + 1.2, 3.0 * nrows + 0.6)
        else:
            lower, upper = run.box(plane)
            aspect = float(np.clip((upper[1] - lower[1]) / max(upper[0] - lower[0], 1e-300), 0.25, 4.0))
            width = 3.8
            figsize = (width * ncols + 1.2, min(width * aspect, 6.0) * nrows + 0.9)
    ok = (isinstance(figsize, (tuple, list)) and len(figsize) == 2
          and all(isinstance(s, (int, float)) and not isinstance(s, bool) and s > 0 for s in figsize))
    check(ok, f"{_say('figsize', figsize, cli)} must be (width, height) in inches, both positive")
    width_px, height_px = (float(s) * float(dpi) for s in figsize)
    check(max(width_px, height_px) < MAX_SIDE_PIXELS and width_px * height_px <= MAX_PIXELS,
          f"{_say('dpi', dpi, cli)} with figsize {float(figsize[0]):g} x {float(figsize[1]):g} in makes an image of "
          f"{width_px:.4g} x {height_px:.4g} pixels; the most is {MAX_SIDE_PIXELS - 1} a side and {MAX_PIXELS:.0e} "
          "in all: lower dpi (e.g. 100) or figsize")
    fig = Figure(figsize=tuple(float(s) for s in figsize), dpi=float(dpi), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(nrows, ncols, squeeze=False).ravel()
    for ax in axes[count:]:
        ax.remove()
    return fig, list(axes[:count])


def _output(out, allowed, option: str, cli: bool) -> str:
    check(isinstance(out, (str, os.PathLike)), f"{_say(option, out, cli)} must be a file name")
    out = os.fspath(out)
    extension = os.path.splitext(out)[1].lower()
    check(extension in allowed, f"{_say(option, out, cli)}: unknown extension {extension or '(none)'!r}; "
                                f"end the name in {', '.join(allowed[:-1])} or {allowed[-1]}")
    folder = os.path.dirname(os.path.abspath(out))
    check(os.path.isdir(folder), f"{_say(option, out, cli)}: the folder {folder} does not exist; create it or "
                                 "choose another file")
    return out


def _refuse_overwrite(out: str, overwrite, cli: bool) -> None:
    """An existing ``out`` is replaced only with consent (``overwrite=True``, the CLI's ``--force``)."""
    check(isinstance(overwrite, bool), f"{_say('overwrite', overwrite, cli)} must be True or False")
    check(overwrite or not os.path.exists(out),
          f"{_say('out', out, cli)} exists; pass {'--force' if cli else 'overwrite=True'} to replace it, or "
          "choose another file")


def _draw(run: _Run, frames, field, plane, figsize, dpi, cmap, clim, limit_frames, title, marker_scale):
    """A figure with one panel per frame and a shared colour bar."""
    limits = _limits(run, field, limit_frames, clim, run.cli)
    colormap, norm = _colours(run, field, limits, cmap)
    fig, axes = _figure(run, len(frames), plane, figsize, dpi, run.cli)
    height = "vx" if run.dim == 1 and run.categorical(field) and "vx" in run.fields else field
    height_limits = limits if height == field else _limits(run, height, limit_frames, None, run.cli)
    panels = [_Panel(ax, run, field, plane, colormap, norm, height, height_limits, marker_scale) for ax in axes]
    for panel, i in zip(panels, frames):
        panel.show(i)
    bar = fig.colorbar(panels[0].points, ax=axes, label=run.label(field), shrink=0.9)
    if run.categorical(field):
        bar.set_ticks(np.arange(int(round(limits[1] + 0.5))))
    fig.suptitle(run.title() if title is None else title, fontsize="medium")
    fig.canvas.draw()  # the layout, then markers of the particle spacing in its final axes
    fig.set_layout_engine("none")  # kept from here on: the frames of an animation do not move
    spacing = run.spacing()
    for panel in panels:
        panel.size_markers(spacing)
    return fig, panels


# --------------------------------------------------------------------------------------------------
# the API
# --------------------------------------------------------------------------------------------------


def plot_frames(path_or_result, frames=(0, -1), field: str = "speed", out=None, *, axes: str = "xy",
                figsize=None, dpi: float = 100, cmap: str | None = None, clim=None, title: str | None = None,
                marker_scale: float = 1.0, sim=None, state=None, overwrite: bool = False, _cli: bool = False):
    """Draw chosen frames of a run side by side; returns the matplotlib ``Figure``.

    The colour limits are shared by the panels.  The figure uses its own Agg canvas (no pyplot,
    the backend is left alone); in a notebook it shows as the cell's value.

    Args:
        path_or_result: a jaxmpm HDF5 file (``jaxmpm run --out``, :func:`jaxmpm.save_h5`), the
            result of :func:`jaxmpm.load_h5`, or a :class:`jaxmpm.History` (then ``sim`` and
            ``state`` are needed).
        frames: frame indices, negative from the end (default ``(0, -1)``: the first and the
            last), or ``"all"``.
        field: the colour: ``speed`` (|v|, the default), ``vx``, ``vy``, ``vz``,
            ``displacement``, ``material``, or a per-particle dataset of the run
            (``temperature``, ``mass``, ``contact_force`` (its norm), ``contact_force_x``,
            ``pressure``, ``J``, ``stress`` (its norm), ``stress_xx``, ``stress_tt``
            (axisymmetric hoop), ...); an unknown name raises :class:`jaxmpm.InputError`
            listing the run's fields.
        out: also write the figure to this file (PNG, or JPG, PDF, SVG); None (the default):
            only return it.
        axes: the projection of a 3D run: "xy" (default), "xz" or "yz".
        figsize: the figure's size in inches, (width, height); None (the default): from the
            panels and the grid box.
        dpi: pixels per inch (default 100).
        cmap: a matplotlib colormap name; None (the default): viridis (``material``: tab10 or
            tab20).
        clim: the colour limits ``(low, high)``; None (the default): the field's range over the
            frames drawn.
        title: the figure's title; None (the default): the scene and the scheme.
        marker_scale: scales the markers (default 1: discs of the particles' area).
        sim: with a History, the :class:`jaxmpm.Simulation` (the grid box and spacing).
        state: with a History, a :class:`jaxmpm.State` (the volumes and material ids).
        overwrite: replace an existing ``out`` (default False: an InputError).
    """
    run = _open(path_or_result, sim, state, _cli)
    with run:
        field = run.check_field(field)
        plane = _plane(run, axes)
        chosen = run.frame_indices(frames)
        if out is not None:
            out = _output(out, IMAGE_EXTENSIONS, "out", _cli)
            _refuse_overwrite(out, overwrite, _cli)
        fig, _ = _draw(run, chosen, field, plane, figsize, dpi, cmap, clim, chosen, title, marker_scale)
    if out is not None:
        fig.savefig(out, dpi=fig.dpi)
    return fig


def animate(path_or_result, out="run.gif", field: str = "speed", *, fps: float = 10, every: int = 1,
            axes: str = "xy", figsize=None, dpi: float = 100, cmap: str | None = None, clim=None,
            title: str | None = None, marker_scale: float = 1.0, sim=None, state=None, progress: bool = False,
            overwrite: bool = False, _cli: bool = False) -> str:
    """Write every ``every``-th frame of a run as an animation; returns the path written.

    ``out`` ending in ``.gif`` is written with imageio and Pillow; ``.mp4`` needs imageio-ffmpeg
    (``pip install imageio-ffmpeg``).  The colour limits are the field's range over the whole run
    (or ``clim``) and the axes are the grid box, so the frames are comparable; each frame is
    ``figsize`` inches times ``dpi`` pixels.  The other arguments are those of
    :func:`plot_frames`; ``progress`` shows a progress bar; an existing ``out`` is replaced only with
    ``overwrite=True``.

    Args:
        path_or_result: a jaxmpm HDF5 file, the result of :func:`jaxmpm.load_h5`, or a
            :class:`jaxmpm.History` (then ``sim`` and ``state`` are needed).
        out: the file to write, ``.gif`` (default "run.gif") or ``.mp4``.
        field: the colour, as for :func:`plot_frames` (default ``speed``).
        fps: frames per second, positive (default 10).
        every: draw every ``every``-th frame, a positive integer (default 1).
        axes: the projection of a 3D run: "xy" (default), "xz" or "yz".
        figsize: each frame's size in inches; None (the default): from the grid box.
        dpi: pixels per inch (default 100).
        cmap: a matplotlib colormap name; None (the default): viridis.
        clim: the colour limits ``(low, high)``; None (the default): the field's range over the
            whole run.
        title: the title; None (the default): the scene and the scheme.
        marker_scale: scales the markers (default 1: discs of the particles' area).
        sim: with a History, the :class:`jaxmpm.Simulation`.
        state: with a History, a :class:`jaxmpm.State`.
        progress: show a progress bar (default False).
        overwrite: replace an existing ``out`` (default False: an InputError).
    """
    return _animate(path_or_result, out, field, fps, every, axes, figsize, dpi, cmap, clim, title, marker_scale,
                    sim, state, progress, _cli, overwrite)[0]


def _animate(path_or_result, out, field, fps, every, axes, figsize, dpi, cmap, clim, title, marker_scale, sim,
             state, progress, _cli, overwrite=False) -> tuple[str, int]:
    """:func:`animate`, returning the path written and the number of frames."""
    out = _output(out, MOVIE_EXTENSIONS, "out", _cli)
    mp4 = out.lower().endswith(".mp4")
    for module in ("matplotlib", "imageio"):
        if not _have(module):
            raise InputError(f"{'jaxmpm animate needs' if _cli else 'animate needs'} {module}: {_INSTALL}")
    if mp4 and not _have("imageio_ffmpeg"):
        raise InputError(f"{_say('out', out, _cli)}: writing MP4 needs imageio-ffmpeg: pip install imageio-ffmpeg "
                         f"(or write a GIF: {os.path.splitext(out)[0]}.gif)")
    check(isinstance(fps, (int, float, np.integer, np.floating)) and not isinstance(fps, bool)
          and math.isfinite(fps) and fps > 0, f"{_say('fps', fps, _cli)} must be a positive number of frames "
                                              "per second")
    check(mp4 or fps >= GIF_MIN_FPS,  # a GIF keeps each frame's delay in hundredths of a second, in 16 bits
          f"{_say('fps', fps, _cli)}: a GIF shows a frame for at most 655.35 s, fps >= {GIF_MIN_FPS:.4g}; "
          "give a larger fps")
    check(isinstance(every, (int, np.integer)) and not isinstance(every, bool) and every >= 1,
          f"{_say('every', every, _cli)} must be a positive integer (1: every frame)")
    _refuse_overwrite(out, overwrite, _cli)
    run = _open(path_or_result, sim, state, _cli)
    with run:
        field = run.check_field(field)
        plane = _plane(run, axes)
        chosen = list(range(0, run.frames, int(every)))
        fig, (panel,) = _draw(run, chosen[:1], field, plane, figsize, dpi, cmap, clim, range(run.frames), title,
                              marker_scale)
        images = _frames_of(fig, panel, chosen, progress)
        root, extension = os.path.splitext(out)
        partial = f"{root}.partial{extension}"  # the animation appears under its name only once whole (the
        # extension kept: ffmpeg chooses the container by it)
        try:
            if mp4:
                _write_mp4(partial, images, fps)
            else:
                _write_gif(partial, list(images), fps)
            os.replace(partial, out)
        finally:
            if os.path.exists(partial):
                os.remove(partial)
    return out, len(chosen)


#: the fewest frames per second a GIF can show: its frame delays are hundredths of a second, 16 bits
GIF_MIN_FPS = 100.0 / 65535


def _frames_of(fig, panel: _Panel, chosen, progress: bool):
    """The RGB image (H, W, 3) of each chosen frame, drawn on one figure."""
    from tqdm.auto import tqdm

    for i in tqdm(chosen, desc="frames", unit="frame", disable=not progress, file=sys.stderr):
        panel.show(i)
        fig.canvas.draw()
        yield np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()


def _write_gif(out: str, images: list, fps: float) -> None:
    import imageio.v3 as iio

    # Pillow keeps every frame (a frame equal to the one before would be merged into it; the titles differ)
    iio.imwrite(out, np.stack(images), extension=".gif", plugin="pillow", duration=1000.0 / float(fps), loop=0)


def _write_mp4(out: str, images, fps: float) -> None:
    import imageio.v2 as imageio

    with imageio.get_writer(out, format="FFMPEG", mode="I", fps=float(fps), codec="libx264",
                            macro_block_size=2, pixelformat="yuv420p") as writer:
        for image in images:
            h, w = image.shape[:2]  # yuv420p wants an even width and height: pad with white
            writer.append_data(np.pad(image, ((0, h % 2), (0, w % 2), (0, 0)), constant_values=255))


# --------------------------------------------------------------------------------------------------
# the command line
# --------------------------------------------------------------------------------------------------


def add_plot_commands(subparsers) -> None:
    """Add ``plot`` and ``animate`` to the ``jaxmpm`` subparsers (``build_parser``)."""
    plot = subparsers.add_parser(
        "plot", help="draw chosen frames of a run's file as a PNG",
        description="Draw chosen frames of FILE.h5 side by side: the particles coloured by a field, in the grid "
                    "box, each frame's time in its title.")
    plot.add_argument("file", metavar="FILE.h5", help="a file written by `jaxmpm run --out` (or jm.save_h5)")
    plot.add_argument("--frames", default="0,-1", metavar="I,J,...",
                      help="frame indices, comma-separated, negative from the end, or 'all' (default: 0,-1, the "
                           "first and the last)")
    animate_ = subparsers.add_parser(
        "animate", help="write a run's frames as a GIF or MP4",
        description="Write the frames of FILE.h5 as an animation (GIF with Pillow; MP4 with imageio-ffmpeg), "
                    "with colour limits fixed over the whole run and the grid box as the axes.")
    animate_.add_argument("file", metavar="FILE.h5", help="a file written by `jaxmpm run --out` (or jm.save_h5)")
    for parser, kind in ((plot, "png"), (animate_, "gif")):
        parser.add_argument("--field", default="speed", metavar="NAME",
                            help="colour the particles by: speed (default), vx, vy, vz, displacement, material "
                                 "(multimaterial runs), or a per-particle dataset of the file (temperature, "
                                 "contact_force, contact_force_x, pressure, J, stress_xx, stress_tt, ...); an "
                                 "unknown name lists the file's fields")
        parser.add_argument("--out", default=None, metavar=f"FILE.{kind}",
                            help=f"output file (default: FILE.{kind} beside FILE.h5)"
                                 + ("; .mp4 needs imageio-ffmpeg" if kind == "gif" else ""))
        parser.add_argument("--axes", default="xy", choices=["xy", "xz", "yz"],
                            help="the two axes a 3D run is projected on (default xy)")
        parser.add_argument("--dpi", type=float, default=100, metavar="N", help="pixels per inch (default 100)")
        parser.add_argument("--force", action="store_true", help="replace the output file if it exists")
    animate_.add_argument("--fps", type=float, default=10, metavar="N", help="frames per second (default 10)")
    animate_.add_argument("--every", type=int, default=1, metavar="K", help="every K-th frame (default 1: all)")
    animate_.add_argument("--no-progress", action="store_true", help="no progress bar")


def _parse_frames(text: str):
    if text.strip().lower() == "all":
        return "all"
    try:
        return [int(part) for part in text.split(",")]
    except ValueError:
        raise InputError(f"--frames {text!r}: give frame indices separated by commas (0,-1 is the first and the "
                         "last frame; -1 counts from the end) or 'all'") from None


def run_plot_command(args) -> int:
    """Carry out ``jaxmpm plot`` or ``jaxmpm animate`` (``args`` from the parser that
    :func:`add_plot_commands` built); returns 0.  An input error prints one line and exits with
    status 2, as every ``jaxmpm`` error does."""
    try:
        stem = os.path.splitext(args.file)[0]
        if args.command == "plot":
            out = args.out if args.out is not None else stem + ".png"
            fig = plot_frames(args.file, _parse_frames(args.frames), args.field, out, axes=args.axes, dpi=args.dpi,
                              overwrite=args.force, _cli=True)
            width, height = (round(s * fig.dpi) for s in fig.get_size_inches())
            count = len(fig.axes) - 1  # the panels, and the colour bar
            print(f"wrote {out} ({width} x {height} pixels: {count} frame{'s' * (count != 1)} of {args.field})")
        else:
            out = args.out if args.out is not None else stem + ".gif"
            out, count = _animate(args.file, out, args.field, args.fps, args.every, args.axes, None, args.dpi, None,
                                  None, None, 1.0, None, None, not args.no_progress, True, args.force)
            print(f"wrote {out} ({count} frame{'s' * (count != 1)} of {args.field}, {args.fps:g} per second)")
    except InputError as err:
        print(f"jaxmpm: error: {err}", file=sys.stderr)
        raise SystemExit(2) from None
    return 0
