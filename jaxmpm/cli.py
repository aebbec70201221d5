"""The ``jaxmpm`` command line (docs/design.md "Public API", last paragraph).

``jaxmpm scenes`` lists the scenes; ``jaxmpm run SCENE [options] --out FILE.h5`` runs one with a
progress bar, writes HDF5 as it goes (:class:`jaxmpm.H5Writer`) and prints a summary.  Input errors
and instabilities print one line and exit with status 2.
"""

from __future__ import annotations

import argparse
import inspect
import math
import sys
import time

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
    "--dtype": "dtype",
}

EXIT_ERROR = 2


def build_parser() -> argparse.ArgumentParser:
    import jaxmpm  # noqa: F401  (registers the schemes and shapes)
    from jaxmpm._registry import SCHEMES, SHAPES

    parser = argparse.ArgumentParser(
        prog="jaxmpm",
        description="Differentiable Material Point Method in JAX: run the benchmark scenes.",
    )
    sub = parser.add_subparsers(dest="command", metavar="{scenes,run}")
    sub.required = True
    sub.add_parser("scenes", help="list the scenes", description="List the scenes with a one-line description.")
    run = sub.add_parser(
        "run",
        help="run a scene and write HDF5",
        description="Run SCENE with a progress bar, writing HDF5 (plus an XDMF sidecar) as it goes. "
        "Options left out keep the scene's defaults (see `jaxmpm scenes`).",
    )
    run.add_argument("scene", metavar="SCENE", help="scene name (see `jaxmpm scenes`)")
    run.add_argument("--scheme", default=None, metavar=SCHEMES.specs().replace(" ", ""),
                     help="velocity update (default: the scene's, flip for bar and disks)")
    run.add_argument("--beta", type=float, default=None, metavar="B",
                     help="FLIP fraction of flip/xpic/fmpm (default: 1 for flip, 0 for xpic and fmpm); "
                          "alone it means --scheme flip")
    run.add_argument("--alpha-g", type=float, default=None, metavar="A", help="grid damping alpha_g in 1/time (default 0)")
    run.add_argument("--alpha-p", type=float, default=None, metavar="A",
                     help="particle damping alpha_p in 1/time (default 0)")
    run.add_argument("--shape", default=None, choices=list(SHAPES.names()),
                     help="shape function (default: the scene's: linear for bar, ugimp for disks)")
    run.add_argument("--update", default=None, choices=["USL", "USF", "MUSL"], help="stress update (default: the scene's, USL for bar and disks)")
    run.add_argument("--cells", type=int, default=None, metavar="N", help="cells along the bar (bar)")
    run.add_argument("--spacing", type=float, default=None, metavar="H", help="grid spacing (disks)")
    run.add_argument("--ppc", type=int, default=None, metavar="N", help="particles per cell along each axis")
    run.add_argument("--cfl", type=float, default=None, metavar="C", help="time step dt = C h / c (bar)")
    run.add_argument("--dt", type=float, default=None, metavar="DT", help="time step (disks)")
    run.add_argument("--t-end", type=float, default=None, metavar="T", help="end time")
    run.add_argument("--frames", type=int, default=None, metavar="F", help="about F saved frames (default 200)")
    run.add_argument("--dtype", default="f64", choices=["f32", "f64"], help="float precision (default f64)")
    run.add_argument("--out", required=True, metavar="FILE.h5", help="HDF5 output file")
    run.add_argument("--no-progress", action="store_true", help="no progress bar")
    return parser


def main(argv=None) -> int:
    """Entry point of the ``jaxmpm`` console script; returns 0, or exits with status 2 on an error."""
    args = build_parser().parse_args(argv)
    if args.command == "scenes":
        return list_scenes()
    return run_scene(args)


def list_scenes() -> int:
    from .scenes import SCENES

    width = max(len(name) for name in SCENES)
    for name, (_, description) in SCENES.items():
        print(f"{name:<{width}}  {description}")
    return 0


def fail(message: str):
    print(f"jaxmpm: error: {message}", file=sys.stderr)
    raise SystemExit(EXIT_ERROR)


def run_scene(args) -> int:
    import jax

    if args.dtype == "f64":
        jax.config.update("jax_enable_x64", True)  # before any array is built
    import jaxmpm as jm

    try:
        setup = build_setup(args)
    except jm.InputError as err:
        fail(str(err))
    return run_setup(setup, args)


def given_options(args) -> list[str]:
    """The scene options given on the command line (dtype always applies)."""
    given = ["--dtype"]
    for option in SCENE_OPTIONS:
        if option not in given and getattr(args, option[2:].replace("-", "_")) is not None:
            given.append(option)
    return given


def build_setup(args):
    """Scene builder keyword arguments from ``args``; an option the builder does not take is an error."""
    import jaxmpm as jm
    from jaxmpm._errors import check
    from jaxmpm._registry import scheme_from_name, shape_from_name

    check(args.scene in jm.SCENES,
          f"unknown scene {args.scene!r}; choose one of {', '.join(jm.SCENES)} (see `jaxmpm scenes`)")
    builder = jm.SCENES[args.scene][0]
    accepted = inspect.signature(builder).parameters
    options = given_options(args)
    for option in options:
        if SCENE_OPTIONS[option] not in accepted:
            takes = sorted(o for o, k in SCENE_OPTIONS.items() if k in accepted)
            check(False, f"option {option} does not apply to scene {args.scene!r}; it takes "
                         f"{', '.join(takes)}")
    for option, value in (("--cells", args.cells), ("--ppc", args.ppc), ("--frames", args.frames)):
        check(value is None or value >= 1, f"{option} = {value} must be a positive integer")
    for option, value in (("--spacing", args.spacing), ("--cfl", args.cfl), ("--dt", args.dt), ("--t-end", args.t_end)):
        check(value is None or (math.isfinite(value) and value > 0), f"{option} = {value} must be positive")

    kwargs = dict(dtype=args.dtype)
    if args.scheme is not None or args.beta is not None:
        # the scheme's parser rejects a --beta it cannot take (pic, apic, tpic, blend:B)
        kwargs["scheme"] = scheme_from_name(args.scheme or "flip", args.beta)
    if args.shape is not None:
        check(args.shape != "ugimp" or "ppc" in accepted, f"--shape ugimp needs a scene with ppc; {args.scene!r} has none")
        ppc = args.ppc if args.ppc is not None else accepted["ppc"].default if "ppc" in accepted else None
        kwargs["shape"] = shape_from_name(args.shape, ppc=ppc) if args.shape == "ugimp" else shape_from_name(args.shape)
    if args.alpha_g is not None or args.alpha_p is not None:
        kwargs["damping"] = jm.Damping(grid=args.alpha_g or 0.0, particle=args.alpha_p or 0.0)
    for name in ("cells", "spacing", "ppc", "cfl", "dt", "t_end", "frames", "update"):
        if getattr(args, name) is not None:
            kwargs[name] = getattr(args, name)
    return jm.scene(args.scene, **kwargs)


def energy_and_momentum(sim, state):
    """(kinetic + strain energy, linear momentum) of a state."""
    import numpy as np

    d = sim.diagnostics(state)
    return float(d["kinetic"] + d["strain"]), np.asarray(d["momentum"], dtype=float)


def run_setup(setup, args) -> int:
    """Run with the HDF5 writer attached, then print the summary."""
    import jax
    import numpy as np

    import jaxmpm as jm

    sim, state = setup.sim, setup.state
    n = int(state.x.shape[0])
    e0, p0 = energy_and_momentum(sim, state)
    start = time.perf_counter()
    try:
        with jm.H5Writer(args.out, sim, state, dt=setup.dt, scene=setup.name, params=setup.params,
                         ppc=setup.params.get("ppc")) as writer:
            final, _ = setup.run(progress=not args.no_progress, writer=writer)
            jax.block_until_ready(final)
    except jm.InstabilityError as err:
        when = f" (t = {err.time:.6g})" if err.time is not None else ""
        fail(f"run went unstable at step {err.step}{when}: {err.cause}; "
             f"the frames before it were kept in {args.out}")
    except jm.InputError as err:
        fail(str(err))
    except OSError as err:
        fail(f"cannot write --out {args.out}: {err}")
    except KeyboardInterrupt:
        print(f"jaxmpm: interrupted; the frames so far were kept in {args.out}", file=sys.stderr)
        raise SystemExit(130) from None
    wall = time.perf_counter() - start
    e1, p1 = energy_and_momentum(sim, final)
    scheme = sim.scheme
    name = type(scheme).__name__
    order = getattr(scheme, "order", None)
    label = f"{name}({order})" if name in ("XPIC", "FMPM") else name
    if hasattr(scheme, "beta"):
        label += f", beta = {float(np.asarray(scheme.beta)):g}"
    ratio = e1 / e0 if e0 != 0 else math.nan
    rows = [
        ("scene", setup.name),
        ("scheme", label),
        ("shape / update", f"{type(sim.shape).__name__} / {sim.update}"),
        ("dtype", str(state.x.dtype)),
        ("particles", f"{n}"),
        ("steps", f"{setup.steps} (t_end = {setup.t_end:.6g})"),
        ("dt", f"{setup.dt:.6g}"),
        ("wall time", f"{wall:.3f} s (incl. compilation)"),
        ("particle-steps/s", f"{n * setup.steps / wall:.4g}"),
        ("energy K+U", f"initial {e0:.6g}, final {e1:.6g}, ratio {ratio:.6f}"),
        ("dissipated", f"{float(final.dissipated):.6g}"),
        ("|p - p0|", f"{float(np.linalg.norm(p1 - p0)):.3e} (change of linear momentum)"),
        ("output", args.out),
    ]
    width = max(len(k) for k, _ in rows)
    for key, value in rows:
        print(f"{key:<{width}}  {value}")
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
