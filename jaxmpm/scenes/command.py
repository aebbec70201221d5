"""Scenes from command-line options: the table of ``jaxmpm run``'s scene options and the
:class:`~jaxmpm.scenes.Setup` they build.  The command line (``jaxmpm.cli``) parses the options;
``jaxmpm.resume`` rebuilds a run from the options stored in its file.

The scene is a registered name (``jm.SCENES``, :func:`jaxmpm.register_scene`, the entry points of
``jaxmpm.scenes``) or a Python file -- a SCENE that ends in ``.py`` or holds a ``/`` -- whose
function ``scene`` is the builder (:func:`load_scene_file`).  A file's run stores the file's
absolute path and the sha256 of its content, so that resuming it rebuilds the same scene, or says
that the file is gone or has changed."""

from __future__ import annotations

import argparse
import ast
import dataclasses
import hashlib
import inspect
import os
import sys
import traceback

import numpy as np

#: command-line option -> keyword argument of the scene builders (``jaxmpm.scenes``)
SCENE_OPTIONS = {
    "--cells": "cells",
    "--spacing": "spacing",
    "--ppc": "ppc",
    "--cfl": "cfl",
    "--dt": "dt",
    "--t-end": "t_end",
    "--frames": "frames",
    "--update": "update",
    "--shape": "shape",
    "--scheme": "scheme",
    "--beta": "scheme",
    "--alpha-g": "damping",
    "--alpha-p": "damping",
    "--damping-approach": "damping",
    "--dtype": "dtype",
    "--contact": "contact",
    "--friction": "friction",
    "--separation": "separation",
    "--conductivity": "conductivity",
    "--diffusivity": "diffusivity",
    "--transport-xpic": "transport",
    # material constants and loads, where a scene has them
    "--E": "E",
    "--nu": "nu",
    "--density": "density",
    "--heat-capacity": "heat_capacity",
    "--expansion": "expansion",
    "--gravity": "gravity",
    "--theta": "theta",
    "--viscosity": "viscosity",
    "--angle": "angle",
    "--aspect": "aspect",
    "--friction-angle": "friction_angle",
    "--cohesion": "cohesion",
    "--geometry": "geometry",
    "--v0": "v0",
    "--yield-stress": "yield_stress",
    "--hardening": "hardening",
    "--stress": "stress",
}

#: the function of a scene file that builds the scene
SCENE_FUNCTION = "scene"


@dataclasses.dataclass(frozen=True)
class SceneFile:
    """A scene file read and run: its absolute ``path``, the ``sha256`` of the content that ran,
    its ``builder`` (the file's function ``scene``, options checked) and a one-line ``description``."""

    path: str
    sha256: str
    builder: object
    description: str


def is_scene_file(scene: str) -> bool:
    """Whether ``jaxmpm run SCENE`` names a Python file rather than a registered scene."""
    return scene.endswith(".py") or "/" in scene or os.sep in scene


def load_scene_file(path, sha256: str | None = None) -> SceneFile:
    """Import the Python file ``path`` (its directory on ``sys.path`` while it is imported, as for
    ``python path``) and return its function ``scene``.  ``sha256``: the digest its content must
    have (a resumed run's), else the file changed since the run began.  A file that is missing,
    unreadable, fails to import or has no function ``scene`` is an InputError naming the file."""
    from ..core.errors import InputError, check
    from . import scene as registry_lookup
    from ._options import checked_options

    path = os.path.abspath(os.fspath(path))
    resuming = "" if sha256 is None else "; the run being resumed was started from it: restore it to resume the run"
    check(not os.path.isdir(path), f"scene file {path} is a folder; give a Python file in it that defines scene()")
    check(os.path.isfile(path), f"scene file {path} does not exist{resuming}")
    try:
        with open(path, "rb") as f:
            source = f.read()
    except OSError as err:
        raise InputError(f"cannot read scene file {path}: {err.strerror or err}") from None
    digest = hashlib.sha256(source).hexdigest()
    check(sha256 is None or digest == sha256,
          f"scene file {path} changed since the run began (sha256 {sha256[:12] if sha256 else ''}... then, "
          f"{digest[:12]}... now); restore the file as it was to resume the run, or start it again with --force")
    stem = "".join(c if c.isalnum() else "_" for c in os.path.splitext(os.path.basename(path))[0])
    module = type(sys)(f"jaxmpm_scene_file_{stem}_{digest[:12]}")
    module.__file__ = path
    sys.modules[module.__name__] = module  # dataclasses, equinox and pickle look classes up there
    folder = os.path.dirname(path)
    sys.path.insert(0, folder)
    try:
        exec(compile(source, path, "exec"), module.__dict__)
    except Exception as err:  # whatever the file raises while it is imported
        del sys.modules[module.__name__]
        raise InputError(f"cannot import scene file {path}: {_one_line(err, path)}") from None
    finally:
        sys.path.remove(folder)
    builder = getattr(module, SCENE_FUNCTION, None)
    check(builder is not None and builder is not registry_lookup,
          f"scene file {path} defines no function `{SCENE_FUNCTION}`; define `def {SCENE_FUNCTION}(cells=16, ..., "
          "dtype=None)` returning a jm.scenes.Setup (its keywords are the `jaxmpm run` options it takes)")
    check(callable(builder), f"scene file {path}: `{SCENE_FUNCTION}` is a {type(builder).__name__}, not a function "
                             "returning a jm.scenes.Setup")
    lines = (builder.__doc__ or module.__doc__ or "").strip().splitlines()
    description = lines[0].strip() if lines else f"the scene of {path}"
    name = os.path.basename(path)
    return SceneFile(path, digest, checked_options(builder, name=name), description)


def _one_line(err: BaseException, path: str) -> str:
    """``Type: message (line N)`` of an exception, N the deepest line of ``path`` it passed through."""
    lines = [frame.lineno for frame in traceback.extract_tb(err.__traceback__) if frame.filename == path]
    if isinstance(err, SyntaxError):
        lines, message = [err.lineno], err.msg
    else:
        message = " ".join(str(err).split())
    where = f" (line {lines[-1]})" if lines and lines[-1] else ""
    return f"{type(err).__name__}{': ' + message if message else ''}{where}"


def scene_builder(scene: str):
    """(builder, description, scene file or None) of ``jaxmpm run SCENE``: a registered scene, one of
    an installed package's entry points, or a scene file."""
    from ..core.errors import check
    from . import SCENES, load_scene_entry_points, unknown_scene

    if is_scene_file(scene):
        found = load_scene_file(scene)
        return found.builder, found.description, found
    if scene not in SCENES:
        load_scene_entry_points()
    check(scene in SCENES, f"{unknown_scene(scene)} (see `jaxmpm scenes`), or give a scene file such as my_scene.py")
    return *SCENES[scene], None


def accepted_keywords(builder) -> tuple[set, bool]:
    """(the keywords ``builder`` names, whether it takes any keyword as well: ``**options``)."""
    params = inspect.signature(builder).parameters
    return set(params), any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values())


def other_keywords(builder) -> dict:
    """{keyword: default} of a scene builder's keywords that have no option of their own (``jaxmpm run
    SCENE --set NAME=VALUE`` sets them: mpm88's n_particles, mms's dim, the disks' speed)."""
    named = set(SCENE_OPTIONS.values())
    return {k: p.default for k, p in inspect.signature(builder).parameters.items()
            if k not in named and p.kind not in (inspect.Parameter.VAR_KEYWORD, inspect.Parameter.VAR_POSITIONAL)}


def settings(items, builder, scene: str) -> dict:
    """The keywords of ``--set NAME=VALUE`` (``items``: the values given, or None): VALUE a Python literal
    (a number, a tuple, True, 'text') or else the bare word as text; an InputError for a NAME the scene
    does not take, one with an option of its own, or one given twice."""
    from ..core.errors import check

    out = {}
    other = other_keywords(builder)
    keywords, takes_any = accepted_keywords(builder)
    named = {k: o for o, k in reversed(list(SCENE_OPTIONS.items()))}
    for item in items or ():
        name, equals, text = item.partition("=")
        name = name.strip()
        check(equals and name.isidentifier(), f"--set {item!r}: give NAME=VALUE, e.g. --set n_particles=32768")
        check(name not in named or (name not in keywords and not takes_any),  # else: no such keyword, below
              f"--set {name}: {scene!r} takes it as the option {named.get(name)}; use that")
        listing = ", ".join(f"{k}={v!r}" for k, v in other.items()) or "none"
        check(name in other or takes_any, f"--set {name}: scene {scene!r} has no keyword {name!r}; its keywords "
                                          f"without an option of their own: {listing}")
        check(name not in out, f"--set {name} is given twice")
        try:
            out[name] = ast.literal_eval(text.strip())
        except (ValueError, SyntaxError, TypeError, MemoryError, RecursionError):
            out[name] = text.strip()  # a bare word (boundary=mirror), or no literal: the scene checks it
    return out


def setup_from_options(options: dict):
    """The scene ``Setup`` of stored command-line options (see :func:`options_of`)."""
    defaults = {_attr(option): None for option in SCENE_OPTIONS} | {"max_steps": None, "conventions": None,
                                                                    "set": None}
    return build_setup(argparse.Namespace(**{**defaults, "dtype": "f64", **options}))


def _attr(option: str) -> str:
    """The argparse attribute of a command-line option: --t-end -> t_end."""
    return option[2:].replace("-", "_")


def given_options(args) -> list[str]:
    """The scene options given on the command line (dtype always applies)."""
    given = ["--dtype"]
    for option in SCENE_OPTIONS:
        if option not in given and getattr(args, _attr(option), None) is not None:
            given.append(option)
    return given


def build_setup(args):
    """Scene builder keyword arguments from ``args``; an option the builder does not take is an error."""
    from ..core.errors import check
    from ..core.registry import scheme_from_name, shape_from_name
    from ..physics.damping import Damping

    sha256 = getattr(args, "scene_sha256", None)  # a resumed scene file's
    if sha256 is not None:
        found = load_scene_file(args.scene, sha256)
        builder, scene_file = found.builder, found
    else:
        builder, _, scene_file = scene_builder(args.scene)
    keywords, takes_any = accepted_keywords(builder)
    accepted = inspect.signature(builder).parameters
    options = given_options(args)
    if "dtype" not in keywords and not takes_any and args.dtype == "f64":
        options.remove("--dtype")  # a builder without dtype (a scene file's): its own float64 default stands
    for option in options:
        if SCENE_OPTIONS[option] not in keywords and not takes_any:
            takes = sorted(o for o, k in SCENE_OPTIONS.items() if k in accepted)
            check(False, f"option {option} does not apply to scene {args.scene!r}; it takes "
                         f"{', '.join(takes)}")
    # the values themselves are checked where every caller meets them: the scene builders
    # (jaxmpm/scenes/_options.py), the damping and the scheme parsers
    kwargs = dict(dtype=args.dtype) if "--dtype" in options else {}
    if args.scheme is not None or args.beta is not None:
        # the scheme's parser rejects a --beta it cannot take (pic, apic, tpic, blend:B)
        kwargs["scheme"] = scheme_from_name("flip" if args.scheme is None else args.scheme, args.beta)
    if args.shape is not None:
        check(args.shape != "ugimp" or "ppc" in accepted,
              f"--shape ugimp needs a scene with ppc; {args.scene!r} has none")
        ppc = args.ppc if args.ppc is not None else accepted["ppc"].default if "ppc" in accepted else None
        kwargs["shape"] = shape_from_name(args.shape, ppc=ppc) if args.shape == "ugimp" else shape_from_name(args.shape)
    check(args.damping_approach is None or args.alpha_g is not None,
          f"--damping-approach {args.damping_approach} sets how grid damping acts; give its rate with --alpha-g")
    if args.alpha_g is not None or args.alpha_p is not None:
        kwargs["damping"] = Damping(grid=args.alpha_g or 0.0, particle=args.alpha_p or 0.0,
                                       approach=args.damping_approach or "velocity")
    if args.transport_xpic is not None:
        kwargs["transport"] = f"xpic:{args.transport_xpic}"  # checked by the scene (jaxmpm/_transport.py)
    # the options passed through as they are: those named as their scene keyword (not the parts and dtype,
    # built above)
    for name in (k for o, k in SCENE_OPTIONS.items() if _attr(o) == k and k not in ("scheme", "shape", "dtype")):
        if getattr(args, name, None) is not None:
            kwargs[name] = getattr(args, name)
    if "gravity" in kwargs and "gravity" in accepted and isinstance(accepted["gravity"].default, (tuple, list)):
        kwargs["gravity"] = tuple(np.atleast_1d(kwargs["gravity"]).tolist())  # a vector, also when given as G
    kwargs.update(settings(getattr(args, "set", None), builder, args.scene))  # --set NAME=VALUE
    setup = _built(builder, kwargs, scene_file, args.scene)
    conventions = getattr(args, "conventions", None)
    if conventions is not None:  # every scene: the model's conventions (jm.Simulation.with_conventions)
        setup.sim = setup.sim.with_conventions(conventions)
    return setup


def _built(builder, kwargs: dict, scene_file: SceneFile | None, scene: str):
    """``builder(**kwargs)``, a :class:`Setup`.  A scene file's builder (the user's code) raising
    anything but an InputError gives one line naming the file, the exception and the line; a scene
    file's run records the file's path and sha256 in its params (the HDF5 file's parameters)."""
    from ..core.errors import InputError, check
    from ._common import Setup

    label = (f"the builder of scene {scene!r}" if scene_file is None
             else f"scene file {scene_file.path}: `{SCENE_FUNCTION}`")
    try:
        setup = builder(**kwargs)
    except (InputError, MemoryError):
        raise
    except Exception as err:
        if scene_file is None:
            raise
        raise InputError(f"{label} raised {_one_line(err, scene_file.path)}") from None
    check(isinstance(setup, Setup), f"{label} returned {type(setup).__name__}, not a jm.scenes.Setup")
    if scene_file is not None:
        setup.params = {**(setup.params or {}), "scene_file": scene_file.path, "scene_sha256": scene_file.sha256}
    return setup


def stored_options(options: dict, setup) -> dict:
    """The command's options as ``jaxmpm run`` stores them for ``jaxmpm resume``: a scene file as its
    absolute path and the sha256 of the content that ran."""
    if "scene_sha256" not in setup.params:
        return options
    return {**options, "scene": setup.params["scene_file"], "scene_sha256": setup.params["scene_sha256"]}
