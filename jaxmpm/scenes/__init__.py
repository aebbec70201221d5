"""Benchmark scenes with known answers (DESIGN.md "Scenes").

``jm.scene(name, **options)`` returns a :class:`Setup` with the simulation, its initial state, the
time step and the number of steps; ``setup.run()`` runs it.
"""

from __future__ import annotations

from ._common import Setup, resolve_dtype
from .bar import bar
from .disks import disks

SCENES = {
    "bar": (bar, "1D fixed-free elastic bar in its first mode (v_cm vs v0/(beta1 L) cos(omega t))"),
    "disks": (disks, "Sulsky 1994: two elastic disks collide and separate (energy, momentum)"),
}


def scene(name: str, **options) -> Setup:
    """Build scene ``name`` (see ``SCENES``) with keyword ``options`` (scheme, shape, cells, ...)."""
    from .._errors import check

    check(name in SCENES, f"unknown scene {name!r}; choose one of {', '.join(SCENES)}")
    return SCENES[name][0](**options)


__all__ = ["SCENES", "Setup", "scene", "resolve_dtype"]
