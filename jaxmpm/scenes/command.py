"""Scenes from command-line options: the table of ``jaxmpm run``'s scene options and the
:class:`~jaxmpm.scenes.Setup` they build.  The command line (``jaxmpm.cli``) parses the options;
``jaxmpm.resume`` rebuilds a run from the options stored in its file."""

from __future__ import annotations

import argparse
import inspect

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
}


def setup_from_options(options: dict):
    """The scene ``Setup`` of stored command-line options (see :func:`options_of`)."""
    defaults = {_attr(option): None for option in SCENE_OPTIONS} | {"max_steps": None, "conventions": None}
    return build_setup(argparse.Namespace(**{**defaults, "dtype": "f64", **options}))


def _attr(option: str) -> str:
    """The argparse attribute of a command-line option: --t-end -> t_end."""
    return option[2:].replace("-", "_")


def given_options(args) -> list[str]:
    """The scene options given on the command line (dtype always applies)."""
    given = ["--dtype"]
    for option in SCENE_OPTIONS:
        if option not in given and getattr(args, _attr(option)) is not None:
            given.append(option)
    return given


def build_setup(args):
    """Scene builder keyword arguments from ``args``; an option the builder does not take is an error."""
    from ..core.errors import check
    from ..core.registry import scheme_from_name, shape_from_name
    from ..physics.damping import Damping
    from . import SCENES, scene

    check(args.scene in SCENES,
          f"unknown scene {args.scene!r}; choose one of {', '.join(SCENES)} (see `jaxmpm scenes`)")
    builder = SCENES[args.scene][0]
    accepted = inspect.signature(builder).parameters
    options = given_options(args)
    for option in options:
        if SCENE_OPTIONS[option] not in accepted:
            takes = sorted(o for o, k in SCENE_OPTIONS.items() if k in accepted)
            check(False, f"option {option} does not apply to scene {args.scene!r}; it takes "
                         f"{', '.join(takes)}")
    # the values themselves are checked where every caller meets them: the scene builders
    # (jaxmpm/scenes/_options.py), the damping and the scheme parsers
    kwargs = dict(dtype=args.dtype)
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
        if getattr(args, name) is not None:
            kwargs[name] = getattr(args, name)
    setup = scene(args.scene, **kwargs)
    conventions = getattr(args, "conventions", None)
    if conventions is not None:  # every scene: the model's conventions (jm.Simulation.with_conventions)
        setup.sim = setup.sim.with_conventions(conventions)
    return setup
