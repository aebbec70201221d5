"""Benchmark scenes with known answers (docs/design.md "Scenes").

``jm.scene(name, **options)`` returns a :class:`Setup` with the simulation, its initial state, the
time step and the number of steps; ``setup.run()`` runs it.

Scenes of your own join the registry ``SCENES`` by :func:`register_scene`, or from an installed
package through the entry-point group ``jaxmpm.scenes`` (each entry point names a builder; its name
is the scene's), which :func:`load_scene_entry_points` reads once -- the command line does at its
start, ``jm.scene`` when it is asked for a name it does not know.  ``jaxmpm run my_scene.py`` runs
the function ``scene`` of a Python file without registering it (:mod:`jaxmpm.scenes.command`).
"""

from __future__ import annotations

import re

from ..core.errors import InputError, check
from ..core.registry import redefinition
from ._common import Setup, cast_state, resolve_dtype
from .bar import bar
from .bars_impact import bars_impact
from .column_collapse import column_collapse
from .cylinder import cylinder
from .dam_break import dam_break
from .disks import disks
from .incline import incline
from .mms import mms
from .mpm88 import mpm88
from .rings import rings
from .slide import slide
from .spin import spin
from .taylor_bar import taylor_bar
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
    "dam_break": (dam_break, "Martin & Moyce 1952: a 2D water column (a x 2a) collapses in a slip-walled tank; "
                             "surge front Z(T) against their measurements"),
    "cylinder": (cylinder, "axisymmetric thick-walled cylinder under internal pressure, damped to Lame's "
                           "u_r(r) and sigma_tt(r) (001 §7)"),
    "incline": (incline, "elastic block slides down a rigid collider incline of angle theta: "
                         "s = g (sin theta - mu cos theta) t^2 / 2"),
    "taylor_bar": (taylor_bar, "Taylor impact: a copper rod (von Mises) at 190 m/s into a rigid wall, axisymmetric "
                               "or 3D; final length and foot radius vs the MPM literature (Wilkins & Guinan 1973)"),
    "column_collapse": (column_collapse, "2D granular column of aspect ratio a = H0/L0 (Drucker-Prager sand) "
                                         "collapses on a rough floor: run-out and height vs Lube et al. 2005"),
}


def scene(name: str, **options) -> Setup:
    """Build scene ``name`` (see ``SCENES``) with keyword ``options`` (scheme, shape, cells, ...).

    The options are checked by the builder itself (``scenes._options.checked_options``, one table
    for every scene), so ``jm.SCENES[name][0](**options)`` is checked the same way: an unknown
    option, a count that is not a positive integer, a non-positive or non-finite size, step or
    time, or a material constant out of range raises :class:`jaxmpm.InputError`.

    Args:
        name: a registered scene (``SCENES``: "bar", "disks", "spin", ...; an installed
            package's entry point of the group ``jaxmpm.scenes`` too).
        **options: the builder's keyword options (scheme, shape, cells, ppc, dt, t_end, ...:
            each is a ``jaxmpm run`` option).

    Returns:
        The :class:`jaxmpm.scenes.Setup`: ``sim``, ``state``, ``dt``, ``steps``, ...;
        ``setup.run()`` runs it.
    """
    if isinstance(name, str) and name not in SCENES:
        load_scene_entry_points()
    check(isinstance(name, str) and name in SCENES, unknown_scene(name))
    return SCENES[name][0](**options)


def unknown_scene(name) -> str:
    """The message for a scene name that is not registered (a failed entry point's own reason)."""
    if isinstance(name, str) and name in ENTRY_POINT_ERRORS:
        return ENTRY_POINT_ERRORS[name]
    return f"unknown scene {name!r}; choose one of {', '.join(SCENES)}"


def register_scene(name: str, builder, description: str | None = None, *, replace: bool = False) -> None:
    """Add scene ``name`` to ``SCENES``: ``jm.scene(name, ...)``, ``jaxmpm scenes`` and ``jaxmpm run
    name`` then know it.  ``builder`` takes keyword options -- named as the built-in builders name
    those it has (cells, spacing, ppc, cfl, dt, t_end, frames, scheme, shape, update, damping,
    dtype, E, nu, density, gravity, ...: each is a ``jaxmpm run`` option) -- and returns a
    :class:`Setup`; it is wrapped in :func:`~jaxmpm.scenes._options.checked_options`, so its options
    are checked like a built-in scene's.  ``description`` (default: the first line of the builder's
    docstring) is what ``jaxmpm scenes`` prints.  A name already taken is an error unless
    ``replace=True``, or the builder is the one it holds or a function of the same name defined anew
    (a notebook cell run again).

    Args:
        name: the scene's name, a word of letters, digits, '_' and '-' starting with a letter
            (typed as ``jaxmpm run NAME``).
        builder: ``builder(**options) -> Setup``, the function that builds the scene.
        description: one line for ``jaxmpm scenes``; None (the default): the first line of the
            builder's docstring.
        replace: replace a scene of that name (default False: a name taken by another builder is
            an error).
    """
    from ._options import checked_options

    check(isinstance(name, str) and re.fullmatch(r"[A-Za-z][A-Za-z0-9_-]*", name) is not None,
          f"register_scene: name = {name!r} must be a word of letters, digits, '_' and '-' (it is typed as "
          "`jaxmpm run NAME`)")
    check(callable(builder), f"register_scene: builder = {builder!r} must be a function returning a jm.scenes.Setup")
    check(description is None or isinstance(description, str),
          f"register_scene: description = {description!r} must be a string (one line)")
    check(replace or name not in SCENES or redefinition(SCENES[name][0], builder),
          f"register_scene: the scene name {name!r} is taken ({SCENES[name][1] if name in SCENES else ''}); "
          "choose another name, or pass replace=True to replace it")
    if description is None:
        lines = (getattr(builder, "__doc__", None) or "").strip().splitlines()
        description = lines[0].strip() if lines else f"scene {name} (its builder has no docstring)"
    SCENES[name] = (checked_options(builder, name=name), " ".join(description.split()))


#: name -> why the entry point of that name did not become a scene (it failed to load, or the name
#: is taken): ``jaxmpm run name`` says so instead of "unknown scene"
ENTRY_POINT_ERRORS: dict = {}
_entry_points_loaded = False


def scene_entry_points():
    """The installed packages' entry points of the group ``jaxmpm.scenes``."""
    from importlib.metadata import entry_points

    return entry_points(group="jaxmpm.scenes")


def load_scene_entry_points() -> None:
    """Register the scenes of the entry-point group ``jaxmpm.scenes``, once: each entry point's name
    is the scene's, its object the builder, the builder's docstring's first line the description.
    One that fails to load, or whose name is taken, is left out (its reason kept in
    ``ENTRY_POINT_ERRORS``), so that one broken package does not stop the others."""
    global _entry_points_loaded
    if _entry_points_loaded:
        return
    _entry_points_loaded = True
    for point in scene_entry_points():
        where = f"entry point {point.name} = {point.value} (group jaxmpm.scenes)"
        try:
            builder = point.load()
        except Exception as err:  # anything the package's import raises
            ENTRY_POINT_ERRORS[point.name] = f"scene {where} failed to load: {type(err).__name__}: " + \
                " ".join(str(err).split())
            continue
        if point.name in SCENES and getattr(SCENES[point.name][0], "__wrapped__", None) is builder:
            continue  # the package registered it itself when it was imported
        try:
            register_scene(point.name, builder)
        except InputError as err:
            ENTRY_POINT_ERRORS[point.name] = f"scene {where} is not registered: {err}"


__all__ = ["SCENES", "Setup", "cast_state", "load_scene_entry_points", "register_scene", "resolve_dtype", "scene"]
