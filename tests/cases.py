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
