"""The ``jaxmpm`` command line (docs/design.md "Public API", last paragraph).

``jaxmpm scenes`` lists the scenes with their options and defaults; ``jaxmpm run SCENE [options]
--out FILE.h5`` runs one with a progress bar, writes HDF5 (plus an XDMF sidecar) as it goes
(:class:`jaxmpm.H5Writer`: with every chunk's frames and state, replaced by rename so that a kill
at any moment leaves a complete file) and prints a summary; ``jaxmpm resume FILE.h5`` continues a
run that Ctrl-C, SIGTERM or a kill stopped.  Input errors (bad values, a run too large for the
machine) and instabilities print one line and exit with status 2; an interrupted run exits with
130 (SIGINT) or 143 (SIGTERM) after saving its frames and state.
"""

from __future__ import annotations

import argparse
import inspect
import math
import sys
import time

from .io.plot import PLOT_COMMANDS, add_plot_commands, run_plot_command
from .scenes.command import SCENE_OPTIONS, build_setup, setup_from_options  # noqa: F401  (re-exported)

EXIT_ERROR = 2
EXIT_SIGNAL = {"SIGINT": 130, "SIGTERM": 143}
CACHE_HELP = ("keep compiled programs on disk (jm.compilation_cache: $JAXMPM_CACHE_DIR, else ~/.cache/jaxmpm/xla), "
              "so that the same command run again skips most of XLA's compilation")

#: the options of ``jaxmpm run`` that are not scene options (kept out of the stored command)
RUN_ONLY = ("out", "force", "no_progress", "command", "cache")


class _OneLineErrors(argparse.ArgumentParser):
    """argparse with its usage errors on one line (status 2), like every other input error."""

    def error(self, message):
        fail(f"{message} (see `{self.prog} --help`)")


def _scene_defaults() -> dict:
    """{scene: {keyword: default}} from the builders' signatures and the scenes' part defaults."""
    from jaxmpm.scenes import SCENES
    from jaxmpm.scenes._common import PART_DEFAULTS

    table = {}
    for name, (builder, _) in SCENES.items():
        params = inspect.signature(builder).parameters
        table[name] = {k: PART_DEFAULTS.get(name, {}).get(k, p.default) for k, p in params.items()}
    return table


def _defaults(keyword: str) -> str:
    """"(default: bar 16, mms 16; other scenes do not take it)" for a scene keyword."""
    by_scene = {scene: d[keyword] for scene, d in _scene_defaults().items() if keyword in d}
    if not by_scene:
        return ""
    shown = ", ".join(f"{scene} {_show(value)}" for scene, value in by_scene.items())
    others = "" if len(by_scene) == len(_scene_defaults()) else "; other scenes do not take it"
    return f"(default: {shown}{others})"


def _show(value) -> str:
    return "derived" if value is None else f"{value:g}" if isinstance(value, float) else str(value)


def build_parser() -> argparse.ArgumentParser:
    import jaxmpm  # noqa: F401  (registers the schemes and shapes)
    from jaxmpm.core.registry import SCHEMES, SHAPES
    from jaxmpm.physics.damping import DAMPING_APPROACHES
    from jaxmpm.scenes import SCENES
    from jaxmpm.scenes._common import CONTACT_OPTIONS

    parser = _OneLineErrors(
        prog="jaxmpm",
        description="Differentiable Material Point Method in JAX: run the benchmark scenes.",
    )
    sub = parser.add_subparsers(dest="command", metavar="{scenes,run,resume,plot,animate}")
    sub.required = True
    sub.add_parser("scenes", help="list the scenes, their options and defaults",
                   description="List the scenes: a one-line description, then each one's options and defaults.")
    run = sub.add_parser(
        "run",
        help="run a scene and write HDF5",
        description="Run SCENE with a progress bar, writing HDF5 (plus an XDMF sidecar) as it goes. "
        "Options left out keep the scene's defaults (see `jaxmpm scenes`).",
    )
    run.add_argument("scene", metavar="SCENE",
                     help=f"scene name: {', '.join(SCENES)} (see `jaxmpm scenes` for each one's options and defaults)")
    run.add_argument("--scheme", default=None, metavar=SCHEMES.specs().replace(" ", ""),
                     help="velocity update " + _defaults("scheme"))
    run.add_argument("--beta", type=float, default=None, metavar="B",
                     help="FLIP fraction of flip/xpic/fmpm (default: 1 for flip, 0 for xpic and fmpm); "
                          "alone it means --scheme flip")
    run.add_argument("--alpha-g", type=float, default=None, metavar="A",
                     help="grid damping alpha_g in 1/time (default 0)")
    run.add_argument("--alpha-p", type=float, default=None, metavar="A",
                     help="particle damping alpha_p in 1/time (default 0)")
    run.add_argument("--damping-approach", default=None, choices=list(DAMPING_APPROACHES),
                     help="how grid damping acts (001 §5.1.2-5.2.2; jm.Damping's approach): on the particle update "
                          "(velocity, the default), on the grid momentum extrapolated as momentum (momentum), "
                          "or on the nodal force (force); needs --alpha-g")
    run.add_argument("--shape", default=None, choices=list(SHAPES.names()), help="shape function " + _defaults("shape"))
    run.add_argument("--update", default=None, choices=["USL", "USF", "MUSL", "USAVG-", "USAVG+"],
                     help="stress update " + _defaults("update"))
    run.add_argument("--cells", type=int, default=None, metavar="N", help="cells along each axis " + _defaults("cells"))
    run.add_argument("--spacing", type=float, default=None, metavar="H", help="grid spacing " + _defaults("spacing"))
    run.add_argument("--ppc", type=int, default=None, metavar="N",
                     help="particles per cell along each axis " + _defaults("ppc"))
    run.add_argument("--cfl", type=float, default=None, metavar="C",
                     help="time step dt = C h / c " + _defaults("cfl"))
    run.add_argument("--dt", type=float, default=None, metavar="DT", help="time step " + _defaults("dt"))
    run.add_argument("--t-end", type=float, default=None, metavar="T", help="end time " + _defaults("t_end"))
    run.add_argument("--frames", type=int, default=None, metavar="F",
                     help="about F saved frames " + _defaults("frames"))
    run.add_argument("--contact", default=None, choices=list(CONTACT_OPTIONS),
                     help="contact between the bodies: none (one velocity field) or a law, each body its own "
                          "material " + _defaults("contact"))
    run.add_argument("--friction", type=float, default=None, metavar="MU",
                     help="Coulomb friction coefficient mu >= 0, with --contact coulomb " + _defaults("friction"))
    run.add_argument("--separation", type=float, default=None, metavar="S",
                     help="contact separation criterion in cells: the bodies touch where their nodal centres of "
                          "mass are closer than S h along the normal " + _defaults("separation"))
    run.add_argument("--conductivity", type=float, default=None, metavar="K",
                     help="thermal conductivity k >= 0 of a transport scene " + _defaults("conductivity"))
    run.add_argument("--diffusivity", type=float, default=None, metavar="D",
                     help="diffusivity D >= 0 of a diffusion scene " + _defaults("diffusivity"))
    run.add_argument("--transport-xpic", type=int, default=None, metavar="M",
                     help="update the transported field by XPIC(M) (000 §3.6) instead of FLIP; 1 is PIC")
    run.add_argument("--conventions", default=None, choices=["jaxmpm", "nairnmpm"],
                     help="whose rules where MPM codes differ: jaxmpm (default) or nairnmpm (NairnMPM 19.0: "
                          "the reaction force on fixed nodes, XPIC's series start, the XPIC/PIC position update, "
                          "the grid damping's velocity)")
    run.add_argument("--dtype", default="f64", choices=["f32", "f64"], help="float precision (default f64)")
    run.add_argument("--max-steps", type=int, default=None, metavar="N",
                     help="refuse a run of more than N steps (default: the step counter's limit 2^31 - 1)")
    run.add_argument("--out", required=True, metavar="FILE.h5",
                     help="HDF5 output file (an XDMF sidecar goes beside it)")
    run.add_argument("--force", action="store_true", help="overwrite --out if it exists")
    run.add_argument("--no-progress", action="store_true", help="no progress bar")
    run.add_argument("--cache", action="store_true", help=CACHE_HELP)
    resume = sub.add_parser(
        "resume",
        help="continue an interrupted run",
        description="Continue the run stored in FILE.h5 (stopped by Ctrl-C, SIGTERM or a kill) from its last "
        "saved chunk to its end, appending to the same file; the result equals the uninterrupted run.",
    )
    resume.add_argument("file", metavar="FILE.h5", help="the --out file of an interrupted `jaxmpm run`")
    resume.add_argument("--no-progress", action="store_true", help="no progress bar")
    resume.add_argument("--cache", action="store_true", help=CACHE_HELP)
    add_plot_commands(sub)
    return parser


def main(argv=None) -> int:
    """Entry point of the ``jaxmpm`` console script; returns 0, or exits with status 2 on an error
    (130/143 when a signal interrupts a run)."""
    args = build_parser().parse_args(_negative_values_joined(sys.argv[1:] if argv is None else list(argv)))
    if args.command == "scenes":
        return list_scenes()
    if args.command == "resume":
        return resume_run(args)
    if args.command in PLOT_COMMANDS:
        return run_plot_command(args)
    return run_scene(args)


def _negative_values_joined(argv: list) -> list:
    """``--dt -1e-3`` as ``--dt=-1e-3``: argparse takes a value that starts with "-" and is not a plain
    integer or decimal (an exponent) for an option, and says "expected one argument"; joined, the
    value reaches the option's own check, which says what is wrong with it."""
    out = []
    for token in argv:
        if out and out[-1].startswith("--") and "=" not in out[-1] and token.startswith("-") and _is_number(token):
            out[-1] = f"{out[-1]}={token}"
        else:
            out.append(token)
    return out


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def list_scenes() -> int:
    """Each scene's description, then its options (as ``jaxmpm run`` spells them) and defaults."""
    from .scenes import SCENES

    defaults = _scene_defaults()
    width = max(len(name) for name in SCENES)
    for name, (_, description) in SCENES.items():
        print(f"{name:<{width}}  {description}")
        options = [f"{option} {_show(defaults[name][keyword])}" for option, keyword in SCENE_OPTIONS.items()
                   if keyword in defaults[name]
                   and option not in ("--beta", "--alpha-g", "--alpha-p", "--dtype", "--transport-xpic")]
        print(f"{'':<{width}}    " + ", ".join(options))
    return 0


def fail(message: str):
    print(f"jaxmpm: error: {message}", file=sys.stderr)
    raise SystemExit(EXIT_ERROR)


def _with_x64(dtype: str):
    import jax

    if dtype == "f64":
        jax.config.update("jax_enable_x64", True)  # before any array is built


def run_scene(args) -> int:
    import os

    _with_x64(args.dtype)
    import jaxmpm as jm
    from jaxmpm.core.errors import check

    if os.path.exists(args.out) and not args.force:
        saved = saved_state(args.out)
        unfinished = (f" (it holds an unfinished run, continued by `jaxmpm resume {args.out}`)"
                      if saved and not saved["complete"] else "")
        fail(f"--out {args.out} exists{unfinished}; pass --force to overwrite it, or choose another file")
    try:
        setup = build_setup(args)
        if args.max_steps is not None:
            check(args.max_steps >= 1, f"--max-steps = {args.max_steps} must be a positive integer")
            check(setup.steps <= args.max_steps,
                  f"the run needs {setup.steps} steps, more than --max-steps {args.max_steps}; "
                  "shorten --t-end or use a larger --dt/--cfl")
    except jm.InputError as err:
        fail(str(err))
    except MemoryError:
        fail(f"scene {args.scene!r} does not fit in memory; use a coarser --spacing/--cells or fewer --ppc")
    return run_setup(setup, args, options_of(args))


def resume_run(args) -> int:
    import json

    from jaxmpm.resume import run_info

    try:
        info = run_info(args.file)
        if "command" not in info:
            fail(f"{args.file} was not written by `jaxmpm run`; resume it from Python with jm.resume(path, setup)")
        options = json.loads(info["command"])
        _with_x64(options.get("dtype", "f64"))

        setup = setup_from_options(options)
    except (ValueError, KeyError) as err:  # InputError is a ValueError
        fail(str(err))
    return run_setup(setup, argparse.Namespace(out=args.file, no_progress=args.no_progress, cache=args.cache), options,
                     resume=True)


def saved_state(path) -> dict | None:
    """``{"frames", "step", "complete"}`` of the state saved in a run's file, or None (no file, no
    state, not readable)."""
    import h5py

    try:
        with h5py.File(path, "r") as f:
            if "state/step" not in f:
                return None
            return {"frames": int(f["time"].shape[0]) if "time" in f else 0, "step": int(f["state/step"][()]),
                    "complete": bool(f["state"].attrs.get("complete", False))}
    except (OSError, KeyError, ValueError):
        return None


def options_of(args) -> dict:
    """The scene options of a parsed ``jaxmpm run`` command line, as stored in the HDF5 file
    (attribute ``command``) for ``jaxmpm resume``."""
    return {k: v for k, v in vars(args).items() if k not in RUN_ONLY and v is not None}


def totals(sim, state) -> dict:
    """The model's terms' totals of a state (thermal energy, solute), as floats."""
    return {name: float(value) for term in sim.terms for name, value in term.totals(sim, state).items()}


def energy_and_momentum(sim, state):
    """(kinetic + strain energy, linear momentum) of a state."""
    import numpy as np

    d = sim.diagnostics(state)
    return float(d["kinetic"] + d["strain"]), np.asarray(d["momentum"], dtype=float)


def run_setup(setup, args, options: dict, resume: bool = False) -> int:
    """Run with the HDF5 writer attached (or continue the run in ``args.out``), then print the
    summary."""
    import json
    import os

    import jax
    import numpy as np

    import jaxmpm as jm
    from jaxmpm.io.xdmf import xdmf_paths

    if args.cache:
        try:
            jm.compilation_cache()
        except jm.InputError as err:
            fail(str(err))
    sim, state = setup.sim, setup.state
    n = int(state.x.shape[0])
    e0, p0 = energy_and_momentum(sim, state)
    first_step = int(state.step)
    if resume:
        import h5py

        with h5py.File(args.out, "r") as f:
            first_step = int(f["state/step"][()]) if "state/step" in f else first_step
    start = time.perf_counter()
    try:
        if resume:
            final = jm.resume(args.out, setup, progress=not args.no_progress)
        else:
            with jm.H5Writer(args.out, sim, state, dt=setup.dt, scene=setup.name, params=setup.params,
                             ppc=setup.params.get("ppc"), attrs={"command": json.dumps(options)}) as writer:
                final, _ = setup.run(progress=not args.no_progress, writer=writer)  # `command`: for resume
        jax.block_until_ready(final)
    except jm.InstabilityError as err:
        when = f" (t = {err.time:.6g})" if err.time is not None else ""
        fail(f"run went unstable at step {err.step}{when}: {err.cause}; "
             f"the frames before it were kept in {args.out}")
    except jm.InputError as err:
        fail(str(err))
    except MemoryError:
        fail("the run ran out of memory; save fewer --frames or use a coarser --spacing/--cells")
    except OSError as err:
        fail(f"cannot write --out {args.out}: {err}")
    except jm.RunInterrupted as err:
        print(f"jaxmpm: {err.signal} at step {int(err.state.step)} (t = {float(err.state.time):.6g}): "
              f"{err.frames} frame{'' if err.frames == 1 else 's'} and the state reached are saved in {args.out}; "
              f"continue with `jaxmpm resume {args.out}`", file=sys.stderr)
        raise SystemExit(EXIT_SIGNAL.get(err.signal, 130)) from None
    except KeyboardInterrupt:  # before the run's first chunk, or a second Ctrl-C
        saved = saved_state(args.out)
        if saved is None:
            print("jaxmpm: interrupted before the run's first frame was saved; start it again", file=sys.stderr)
        else:
            print(f"jaxmpm: interrupted; {args.out} keeps {saved['frames']} frame{'' if saved['frames'] == 1 else 's'} "
                  f"and the state of step {saved['step']}; continue with `jaxmpm resume {args.out}`", file=sys.stderr)
        raise SystemExit(130) from None
    files = [args.out] + [p for p in xdmf_paths(args.out) if os.path.exists(p)]
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
        ("particle-steps/s", f"{n * (int(final.step) - first_step) / wall:.4g}"
                             + (f" ({int(final.step) - first_step} steps resumed)" if resume else "")),
        ("energy K+U", f"initial {e0:.6g}, final {e1:.6g}" + ("" if e0 == 0 else f", ratio {ratio:.6f}")),
        *[(name.replace("_", " "), f"initial {value:.6g}, final {totals(sim, final)[name]:.6g}")
          for name, value in totals(sim, state).items()],
        ("dissipated", f"{float(final.dissipated):.6g}"),
        ("|p - p0|", f"{float(np.linalg.norm(p1 - p0)):.3e} (change of linear momentum)"),
        ("output", ", ".join(files)),
    ]
    width = max(len(k) for k, _ in rows)
    for key, value in rows:
        print(f"{key:<{width}}  {value}")
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
