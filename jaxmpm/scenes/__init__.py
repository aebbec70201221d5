"""Benchmark scenes with known answers (docs/design.md "Scenes").

``jm.scene(name, **options)`` returns a :class:`Setup` with the simulation, its initial state, the
time step and the number of steps; ``setup.run()`` runs it.
"""

from __future__ import annotations

from ._common import Setup, cast_state, resolve_dtype
from .bar import bar
from .bars_impact import bars_impact
from .cylinder import cylinder
from .disks import disks
from .mms import mms
from .mpm88 import mpm88
from .rings import rings
from .slide import slide
from .spin import spin
from .transport import diffusion2d, heat1d, heat_step, thermal_bar
from .vortex import vortex

SCENES = {
    "bar": (bar, "1D fixed-free elastic bar in its first mode (v_cm vs v0/(beta1 L) cos(omega t))"),
    "disks": (disks, "Sulsky 1994: two elastic disks collide and separate (energy, momentum)"),
    "spin": (spin, "force-free (or elastic) spinning disk: angular momentum and kinetic energy"),
    "rings": (rings, "two neo-Hookean rings collide at +-30: total energy per scheme"),
    "mpm88": (mpm88, "Taichi's mpm88 fluid (APIC, 8192 particles, 128^2 grid): throughput"),
    "mms": (mms, "Wallstedt & Guilkey 2008 axis-aligned manufactured solution on [0,1]^D: displacement error "
                 "(velocity='linear': 1D uniform stretch, velocity linear in X)"),
    "vortex": (vortex, "generalized vortex (Kamojjala & Brannon): ring returns to its start at t = T"),
    "bars_impact": (bars_impact, "two 1D elastic bars meet at +-v0: contact lasts 2L/c, velocities exchanged"),
    "slide": (slide, "elastic block slides on a slab under gravity tilted by theta: "
                     "x = g (sin theta - mu cos theta) t^2 / 2"),
    "heat1d": (heat1d, "rod with held ends, T0 = sin(pi x/L): T = exp(-a pi^2 t/L^2) sin(pi x/L)"),
    "heat_step": (heat_step, "rod whose end is held hot from t = 0: T = T_s erfc(x / (2 sqrt(a t)))"),
    "diffusion2d": (diffusion2d, "unit square, boundary held at mu = 1: double sine series (001 §9)"),
    "thermal_bar": (thermal_bar, "free bar heated by dT expands by alpha_T dT L"),
    "cylinder": (cylinder, "axisymmetric thick-walled cylinder under internal pressure, damped to Lame's "
                           "u_r(r) and sigma_tt(r) (001 §7)"),
}


def scene(name: str, **options) -> Setup:
    """Build scene ``name`` (see ``SCENES``) with keyword ``options`` (scheme, shape, cells, ...).

    The options are checked by the builder itself (``scenes._options.checked_options``, one table
    for every scene), so ``jm.SCENES[name][0](**options)`` is checked the same way: an unknown
    option, a count that is not a positive integer, a non-positive or non-finite size, step or
    time, or a material constant out of range raises :class:`jaxmpm.InputError`."""
    from ..core.errors import check

    check(isinstance(name, str) and name in SCENES, f"unknown scene {name!r}; choose one of {', '.join(SCENES)}")
    return SCENES[name][0](**options)


__all__ = ["SCENES", "Setup", "cast_state", "scene", "resolve_dtype"]
