"""The scene options, checked in one table.

Every builder is decorated with :func:`checked_options`, so a scene is checked the same however it
is reached: ``jm.scene(name, ...)``, ``jm.SCENES[name][0](...)`` or ``jaxmpm.scenes.bar.bar(...)``
(checking only in ``jm.scene`` would leave the other two paths -- which the CLI and the tests use --
raising ZeroDivisionError on ``cfl=0``).  The decorator

* turns an option the builder does not take into :class:`jaxmpm.InputError` listing the options
  it does take (Python's own TypeError names only the bad keyword);
* checks every option the caller gave against :data:`OPTION_CHECKS` (option name -> check):
  counts are positive integers, step sizes and times finite and positive, material constants in
  their physical ranges.  Options left at their defaults are not checked (the defaults are valid);
  None passes where it is the builder's default ("derive it": spin's dt, vortex's t_end, disks' pad);
* turns a scheme or shape given as a string (``scheme="xpic:3"``, ``shape="quadratic"``) into the
  part, as the command line does.

Two checks span two options, because only the decorator knows which options the caller gave: a
``friction`` given with a ``contact`` law other than "coulomb" is an error (the builders use the
friction only with "coulomb", so slide's default friction 0.2 does not stop ``contact="frictionless"``),
and so is a contact ``normal`` given with ``contact="none"`` (one field: no contact normal).
Other checks that need several options at once (mms: an even cell count for the extended boundary,
vortex: spacing below the ring width) stay in the builders.  The builders' own constructors
(``Grid``, ``fill``, the materials, the schemes) check again what they receive.
"""

from __future__ import annotations

import functools
import inspect

import numpy as np

from ..core.validate import (
    FINITE,
    NON_NEGATIVE,
    POISSON,
    POSITIVE,
    Range,
    concrete,
    fail,
    finite_vector,
    ndim,
    positive_int,
    sequence,
    show,
)
from ._common import CONTACT_OPTIONS


def _count(scene, name, value):
    return positive_int(scene, name, value)


def _index(scene, name, value):
    return positive_int(scene, name, value, low=0)


def _range(rng, fix=None):
    def check(scene, name, value):
        rng.real(scene, name, value, fix)
        return value  # unchanged: the builder computes with exactly what it was given
    return check


def _finite_list(scene, name, value):
    for i, v in enumerate(sequence(scene, name, value)):
        FINITE.real(scene, f"{name}[{i}]", v)
    return value


def _gravity(scene, name, value):
    """One finite number (a magnitude g, which the scene points: mpm88 down, slide tilted by theta)
    or a vector of 1 to 3 finite components (GX,GY[,GZ] on the command line)."""
    if ndim(value) == 0:
        return _range(FINITE, "the gravitational acceleration")(scene, name, value)
    vector = finite_vector(scene, name, value)
    if not 1 <= len(vector) <= 3:
        fail(scene, f"{name} = {show(value)} has {len(vector)} components", "give one number or GX,GY[,GZ]")
    return vector


def _contact(scene, name, value):
    if not (isinstance(value, str) and value in CONTACT_OPTIONS):
        fail(scene, f"{name} = {show(value)}; choose one of {', '.join(map(repr, CONTACT_OPTIONS))}",
             "'none' keeps one velocity field, a law gives each body its own (jm.Contact)")
    return value


def _normal(scene, name, value):
    from ..physics.contact import normal_option

    return normal_option(scene, value)  # a name of NORMALS, or a vector (made a unit tuple)


def _transport(scene, name, value):
    from ..physics.transport import _parse_update

    _parse_update(scene, value if isinstance(value, str) else repr(value), name)
    return value


# option name -> check(scene, name, value) returning the value to pass on (a count as an int)
OPTION_CHECKS = {
    # counts
    "cells": _count, "ppc": _count, "frames": _count, "n_particles": _count, "n_grid": _count, "bound": _count,
    "dim": _count, "seed": _index,
    # sizes, steps and times
    "spacing": _range(POSITIVE, "the cell size"),
    "cfl": _range(POSITIVE, "the Courant number, e.g. 0.5"),
    "dt": _range(POSITIVE, "the time step"),
    "t_end": _range(POSITIVE, "the end time"),
    "period": _range(POSITIVE),
    "length": _range(POSITIVE),
    "radius": _range(POSITIVE),
    "inner": _range(NON_NEGATIVE),
    "outer": _range(POSITIVE),
    "pad": _range(NON_NEGATIVE, "room around the body, in length units"),
    "ramp": _range(NON_NEGATIVE, "the time over which the load rises from 0 (0: at once)"),
    # material constants
    "E": _range(POSITIVE), "density": _range(POSITIVE), "nu": _range(POISSON, POISSON.fix),
    "viscosity": _range(NON_NEGATIVE, "the dynamic viscosity eta in Pa s; 0 is inviscid"),
    "sound_speed": _range(POSITIVE, "the speed of sound c_0, e.g. 10 times the flow's largest velocity"),
    "width": _range(POSITIVE), "tank": _range(POSITIVE, "the tank's length in column widths"),
    # motions and loads (any sign)
    "speed": _range(FINITE), "v0": _range(FINITE), "omega": _range(FINITE), "amplitude": _range(FINITE),
    "gravity": _gravity,
    "pressure": _range(FINITE, "the pressure, force per area"),
    "phases": _finite_list,
    "theta": _range(Range(0, 90, high_open=True), "the slope angle in degrees"),
    "angle": _range(Range(0, 90, high_open=True), "the incline's angle in degrees"),
    # granular column (column_collapse): its aspect ratio and the sand's Drucker-Prager constants
    "aspect": _range(POSITIVE, "the column's aspect ratio H0/L0, e.g. 2"),
    "friction_angle": _range(Range(0, 90, high_open=True), "the friction angle phi in degrees, in [0, 90)"),
    "cohesion": _range(NON_NEGATIVE, "the cohesion c >= 0 (stress units)"),
    # the Taylor bar (taylor_bar): its von Mises constants and model
    "yield_stress": _range(POSITIVE, "the initial yield stress sigma_y (stress units)"),
    "hardening": _range(NON_NEGATIVE, "the linear hardening modulus H >= 0 (stress units)"),
    "geometry": lambda scene, name, value: value if value in ("axisymmetric", "3d") else fail(
        scene, f"{name} = {show(value)}; choose 'axisymmetric' or '3d'"),
    # contact between the bodies of a two-body scene (jaxmpm/_contact.py)
    "contact": _contact,
    "friction": _range(NON_NEGATIVE, "the Coulomb friction coefficient mu"),
    "separation": lambda scene, name, value: None if value is None else _range(
        FINITE, "the contact separation criterion in cells, e.g. 1.0 (None: off)")(scene, name, value),
    "normal": _normal,
    # transport (jaxmpm/_transport.py)
    "conductivity": _range(NON_NEGATIVE, "the thermal conductivity k >= 0"),
    "heat_capacity": _range(POSITIVE, "the heat capacity per unit mass"),
    "diffusivity": _range(NON_NEGATIVE, "the diffusivity D >= 0"),
    "expansion": _range(FINITE, "the thermal expansion coefficient alpha_T"),
    "heating": _range(FINITE, "the temperature rise dT"),
    "transport": _transport,
}


def _parts(scene: str, values: dict, signature) -> dict:
    """scheme/shape strings -> parts, as the command line builds them."""
    from ..core.registry import scheme_from_name, shape_from_name

    if isinstance(values.get("scheme"), str):
        values["scheme"] = scheme_from_name(values["scheme"])
    if isinstance(values.get("shape"), str):
        name = values["shape"].strip().lower()
        if name == "ugimp":
            ppc = values.get("ppc", signature.parameters["ppc"].default if "ppc" in signature.parameters else None)
            if ppc is None:
                fail(scene, "shape 'ugimp' needs a scene with ppc (particles per cell)")
            values["shape"] = shape_from_name(name, ppc=ppc)
        else:
            values["shape"] = shape_from_name(name)
    return values


def checked_options(builder, name: str | None = None):
    """Decorate a scene builder: unknown options, bad counts, sizes and constants -> InputError.
    ``name`` (default: the function's name) starts the messages; a builder that already is checked
    is returned as it is (``jm.register_scene`` and scene files wrap the builders they are given)."""
    if getattr(builder, "checked_options", False):
        return builder
    scene = name or builder.__name__
    signature = inspect.signature(builder)
    collected = next((k for k, p in signature.parameters.items() if p.kind is inspect.Parameter.VAR_KEYWORD), None)

    @functools.wraps(builder)
    def build(*args, **options):
        try:
            bound = signature.bind(*args, **options)
        except TypeError as err:
            unknown = sorted(set(options) - set(signature.parameters))
            what = f"unknown option {', '.join(map(repr, unknown))}" if unknown else str(err)
            fail(scene, f"{what}; {scene} takes {', '.join(signature.parameters)}")
        given = dict(bound.arguments)
        if collected is not None:  # a builder with **options: its collected options are checked too
            given.update(given.pop(collected, {}))
        for key, value in given.items():
            check = OPTION_CHECKS.get(key)
            default = signature.parameters[key].default if key in signature.parameters else None
            if check is None or (value is None and default is None):
                continue  # not a checked option, or None where the builder derives the value
            given[key] = check(scene, key, value)
        if "friction" in given and "contact" in signature.parameters:
            contact = given.get("contact", signature.parameters["contact"].default)
            mu = concrete(given["friction"])
            if contact != "coulomb" and mu is not None and np.any(mu != 0):
                fail(scene, f"friction = {show(given['friction'])} applies only to contact='coulomb', "
                            f"not contact={contact!r}", "pass contact='coulomb', or leave friction out")
        if given.get("separation") is not None and "contact" in signature.parameters:
            if given.get("contact", signature.parameters["contact"].default) == "none":
                fail(scene, f"separation = {show(given['separation'])} is the contact law's separation criterion, "
                            "and contact='none' has no law", "pass a contact law ('frictionless', 'coulomb' or "
                                                             "'stick'), or leave separation out")
        if given.get("normal") is not None and "contact" in signature.parameters:
            if given.get("contact", signature.parameters["contact"].default) == "none":
                fail(scene, f"normal = {show(given['normal'])} applies only to a contact law, not contact='none'",
                     "pass contact='frictionless', 'coulomb' or 'stick', or leave normal out")
        return builder(**_parts(scene, given, signature))

    build.checked_options = True
    return build
