"""Definitions shared by the tests: shape functions, grids, random particles on a grid, a
stencil's arrays per particle, and the finite-difference helper."""

import os
import types

import numpy as np

import jaxmpm as jm

# one of each shape function (uGIMP with 2 particles per cell per axis)
FOUR_SHAPES = {
    "linear": jm.Linear(),
    "ugimp": jm.UGIMP(ppc=2),
    "quadratic": jm.QuadraticBSpline(),
    "cubic": jm.CubicBSpline(),
}

# the same with uGIMP at 1, 2 and 3 particles per cell per axis
SIX_SHAPES = {
    "linear": FOUR_SHAPES["linear"],
    "ugimp1": jm.UGIMP(ppc=1),
    "ugimp2": FOUR_SHAPES["ugimp"],
    "ugimp3": jm.UGIMP(ppc=3),
    "quadratic": FOUR_SHAPES["quadratic"],
    "cubic": FOUR_SHAPES["cubic"],
}

# anisotropic, off-origin grids: a wrong spacing or lower corner anywhere shows up
GRIDS = {
    1: jm.Grid(lower=(-1.0,), upper=(3.0,), cells=(8,)),
    2: jm.Grid(lower=(-1.0, 0.5), upper=(3.0, 2.5), cells=(8, 6)),
    3: jm.Grid(lower=(-1.0, 0.5, 2.0), upper=(3.0, 2.5, 4.4), cells=(7, 6, 5)),
}

# anisotropic, off-origin 2D and 3D grids of the APIC/TPIC transfer checks (test_affine.py):
# h = (0.5, 0.4) in 2D and (0.5, 0.4, 0.4) in 3D
AFFINE_GRIDS = {
    2: jm.Grid(lower=(-1.0, 0.5), upper=(3.0, 2.5), cells=(8, 5)),
    3: jm.Grid(lower=(-1.0, 0.5, 2.0), upper=(2.0, 2.5, 4.4), cells=(6, 5, 6)),
}

# small unit grids for the dense-matrix checks (test_matrix_forms.py): 9 and 36 nodes
UNIT_GRIDS = {1: jm.Grid((0.0,), (1.0,), (8,)), 2: jm.Grid((0.0, 0.0), (1.0, 1.0), (5, 5))}

# the unit square in 8 x 8 cells (h = 1/8)
UNIT_SQUARE = jm.Grid(lower=(0.0, 0.0), upper=(1.0, 1.0), cells=(8, 8))


def interior_cells(shape, grid, rng, n, extent=1.0):
    """(n, D) random positions in cell units (0 at the lower corner) whose whole stencil lies on
    the grid: from ``shape.margin`` + 0.01 cells off each edge, in the lower ``extent`` fraction
    of that band."""
    cells = np.array(grid.cells, dtype=float)
    m = float(shape.margin)
    return m + 0.01 + extent * (cells - 2.0 * m - 0.02) * rng.random((n, grid.dim))


def at_cells(grid, xi):
    """Positions x = lower + xi h of cell coordinates ``xi``."""
    return np.array(grid.lower) + xi * np.array(grid.spacing)


def random_particles(shape, grid, rng, n, extent=1.0):
    """Positions as :func:`interior_cells`, masses in [0.5, 2], velocities ~ N(0, 1) (NumPy)."""
    x = at_cells(grid, interior_cells(shape, grid, rng, n, extent))
    return x, 0.5 + 1.5 * rng.random(n), rng.normal(size=(n, grid.dim))


def particle_major(stencil):
    """A stencil's arrays per particle, as NumPy: ``index``, ``weight`` (N, K), ``gradient``,
    ``offset`` (N, K, D) -- the library stores them planar, (K, N) and (D, K, N)."""
    return types.SimpleNamespace(
        index=np.asarray(stencil.index).T,
        weight=np.asarray(stencil.weight).T,
        gradient=np.transpose(np.asarray(stencil.gradient), (2, 1, 0)),
        offset=np.transpose(np.asarray(stencil.offset), (2, 1, 0)),
    )


def dense_weights(stencil, num_nodes):
    """S_pi as a dense (N, n) matrix and G_pi as (N, n, D), from a (planar) stencil."""
    st = particle_major(stencil)
    n_p, k = st.index.shape
    rows, cols = np.repeat(np.arange(n_p), k), st.index.reshape(-1)
    S = np.zeros((n_p, num_nodes))
    np.add.at(S, (rows, cols), st.weight.reshape(-1))
    dim = st.gradient.shape[-1]
    G = np.zeros((n_p, num_nodes, dim))
    np.add.at(G, (rows, cols), st.gradient.reshape(-1, dim))
    return S, G


def central_difference(f, x, eps, derivative=1, order=2):
    """The first or second derivative of ``f`` at ``x`` by central differences with step ``eps``
    (call it in float64: the differences cancel the leading digits of f).

    order=2: (f(x + eps) - f(x - eps)) / (2 eps) and (f(x + eps) - 2 f(x) + f(x - eps)) / eps^2,
    truncation error O(eps^2);
    order=4: the five-point formulas on x, x +- eps, x +- 2 eps, truncation error O(eps^4) -- for
    the first derivative this is one Richardson step on the order-2 formula, (4 D(eps) - D(2 eps)) / 3.
    """
    if (derivative, order) == (1, 2):
        return (f(x + eps) - f(x - eps)) / (2 * eps)
    if (derivative, order) == (1, 4):
        return (-f(x + 2 * eps) + 8 * f(x + eps) - 8 * f(x - eps) + f(x - 2 * eps)) / (12 * eps)
    if (derivative, order) == (2, 2):
        return (f(x + eps) - 2 * f(x) + f(x - eps)) / eps**2
    if (derivative, order) == (2, 4):
        return (-f(x + 2 * eps) + 16 * f(x + eps) - 30 * f(x) + 16 * f(x - eps) - f(x - 2 * eps)) / (12 * eps**2)
    raise ValueError(f"central_difference: derivative {derivative}, order {order}; use 1 or 2, and 2 or 4")


def small_simulation(**options):
    """A 1D elastic body on a 16-cell grid (h = 1), E = 2, rho = 1: c = sqrt(2)."""
    grid = jm.Grid(lower=(0.0,), upper=(16.0,), cells=(16,))
    kwargs = dict(grid=grid, shape=jm.Linear(), material=jm.LinearElastic(E=2.0, nu=0.0, density=1.0),
                  scheme=jm.FLIP())
    kwargs.update(options)
    return jm.Simulation(**kwargs)


def run_cli(argv):
    """``jaxmpm.cli.main(argv)`` in-process: its exit status (stdout and stderr via capsys)."""
    from jaxmpm.cli import main

    try:
        return main(argv)
    except SystemExit as exc:
        return exc.code


def h5_arrays(path) -> dict:
    """Every dataset of an HDF5 file (the /state group included), by path."""
    import h5py

    out = {}
    with h5py.File(path, "r") as f:
        f.visititems(lambda name, obj: out.__setitem__(name, obj[()]) if isinstance(obj, h5py.Dataset) else None)
    return out


def assert_same_files(a, b):
    """Two HDF5 files hold the same datasets, bit for bit (a resumed run against an uninterrupted one)."""
    x, y = h5_arrays(a), h5_arrays(b)
    assert sorted(x) == sorted(y)
    for name in x:
        np.testing.assert_array_equal(y[name], x[name], err_msg=name)


def forced_devices_flags(devices: int) -> str:
    """``XLA_FLAGS`` for a subprocess with ``devices`` forced CPU devices that keeps the suite's other
    XLA flags (its compile settings, tests/conftest.py).  Replacing ``XLA_FLAGS`` outright dropped
    them: tests/parallel/terms_check.py took 65 s to compile and run at XLA's defaults against 44 s
    with them (2-core machine)."""
    kept = [flag for flag in os.environ.get("XLA_FLAGS", "").split()
            if not flag.startswith("--xla_force_host_platform_device_count")]
    return " ".join([*kept, f"--xla_force_host_platform_device_count={devices}"])
