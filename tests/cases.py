"""Problem definitions shared by the shape-function and transfer tests."""

import jaxmpm as jm

# one of each shape function (uGIMP with 2 particles per cell per axis)
FOUR_SHAPES = {
    "linear": jm.Linear(),
    "ugimp": jm.UGIMP(ppc=2),
    "quadratic": jm.QuadraticBSpline(),
    "cubic": jm.CubicBSpline(),
}

# anisotropic, off-origin grids: a wrong spacing or lower corner anywhere shows up
GRIDS = {
    1: jm.Grid(lower=(-1.0,), upper=(3.0,), cells=(8,)),
    2: jm.Grid(lower=(-1.0, 0.5), upper=(3.0, 2.5), cells=(8, 6)),
    3: jm.Grid(lower=(-1.0, 0.5, 2.0), upper=(3.0, 2.5, 4.4), cells=(7, 6, 5)),
}


def particle_major(stencil):
    """A stencil's arrays per particle, as NumPy: ``index``, ``weight`` (N, K), ``gradient``,
    ``offset`` (N, K, D) -- the library stores them planar, (K, N) and (D, K, N)."""
    import types

    import numpy as np

    return types.SimpleNamespace(
        index=np.asarray(stencil.index).T,
        weight=np.asarray(stencil.weight).T,
        gradient=np.transpose(np.asarray(stencil.gradient), (2, 1, 0)),
        offset=np.transpose(np.asarray(stencil.offset), (2, 1, 0)),
    )
