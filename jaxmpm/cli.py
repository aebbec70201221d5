"""The ``jaxmpm`` command line (docs/design.md "Public API", last paragraph).

``jaxmpm scenes`` lists the scenes with their options and defaults; ``jaxmpm run SCENE [options]
--out FILE.h5`` runs one with a progress bar, writes HDF5 (plus an XDMF sidecar) as it goes
(:class:`jaxmpm.H5Writer`: with every chunk's frames and state, replaced by rename so that a kill
at any moment leaves a complete file) and prints a summary; ``jaxmpm resume FILE.h5`` continues a
run that Ctrl-C, SIGTERM or a kill stopped.  SCENE is a registered scene (``jm.register_scene``, the
entry points of the group ``jaxmpm.scenes``) or a Python file whose function ``scene`` builds it;
``jaxmpm run SCENE --help`` lists the options SCENE takes, with its defaults.  Input errors (bad
values, a run too large for the machine) and instabilities print one line and exit with status 2;
an interrupted run exits with 130 (SIGINT) or 143 (SIGTERM) after saving its frames and state.
"""

from __future__ import annotations

import argparse
import inspect
import math
import sys
import time

from .io.plot import PLOT_COMMANDS, add_plot_commands, run_plot_command
from .scenes.command import SCENE_OPTIONS, build_setup, setup_from_options, stored_options  # noqa: F401  (re-exported)

EXIT_ERROR = 2
_IMPORTED = time.perf_counter()  # the origin of seconds_since_start where /proc is missing
EXIT_SIGNAL = {"SIGINT": 130, "SIGTERM": 143}
NO_CACHE_HELP = ("do not keep compiled programs on disk.  By default they are kept (jm.compilation_cache: "
                 "$JAXMPM_CACHE_DIR, else the user cache folder, ~/.cache/jaxmpm/xla on Linux; at most "
                 "$JAXMPM_CACHE_MAX_BYTES, 1 GiB), so that the same command run again, or its resume, skips most "
                 "of XLA's compilation; JAXMPM_CACHE=0 in the environment switches it off too")
CACHE_HELP = "the default (the cache is on unless --no-cache); accepted for older command lines"

#: the options of ``jaxmpm run`` that are not scene options (kept out of the stored command)
RUN_ONLY = ("out", "force", "no_progress", "command", "cache", "no_cache", "devices", "rebalance_every", "capacity",
            "exchange", "cpu_devices")
CPU_DEVICES_HELP = ("start JAX with N CPU devices: each step shares its particles among them where the backend "
                    "table says (2D from 60k particles; docs/performance.md, \"Particles shared among the CPU's "
                    "devices\"), and --devices may use them (default: JAX's one CPU device)")


class _OneLineErrors(argparse.ArgumentParser):
    """argparse with its usage errors on one line (status 2), like every other input error."""

    def error(self, message):
        fail(f"{message} (see `{self.prog} --help`)")


#: what an option means for one scene, where the option's help names several scenes' meanings (``jaxmpm run
#: SCENE --help`` prints this instead)
SCENE_HELP = {
    ("bar", "--v0"): "amplitude v0 of the initial velocity v0 sin(beta1 x)",
    ("bars_impact", "--v0"): "speed v0 at which each bar meets the other",
    ("taylor_bar", "--v0"): "impact speed v0 of the rod, m/s",
}


def _scene_defaults() -> dict:
    """{scene: {keyword: default}} from the builders' signatures and the scenes' part defaults."""
    from jaxmpm.scenes import SCENES

    return {name: _builder_defaults(name, builder) for name, (builder, _) in SCENES.items()}


def _builder_defaults(name: str, builder) -> dict:
    """{keyword: default} of one scene's builder, its parts as the command line spells them."""
    from jaxmpm.scenes._common import PART_DEFAULTS

    params = inspect.signature(builder).parameters
    return {k: PART_DEFAULTS.get(name, {}).get(k, p.default) for k, p in params.items()
            if p.kind is not inspect.Parameter.VAR_KEYWORD}


def _defaults(keyword: str) -> str:
    """"(default: bar 16, mms 16; other scenes do not take it)" for a scene keyword, or for an option
    ("--alpha-g")."""
    option = keyword if keyword.startswith("--") else next(o for o, k in SCENE_OPTIONS.items() if k == keyword)
    table = _scene_defaults()
    by_scene = {scene: text for scene, d in table.items() if (text := option_default(scene, option, d)) is not None}
    if not by_scene:
        return ""
    shown = ", ".join(f"{scene} {text}" for scene, text in by_scene.items())
    others = "" if len(by_scene) == len(table) else "; other scenes do not take it"
    return f"(default: {shown}{others})"


def option_default(scene: str, option: str, defaults: dict) -> str | None:
    """How ``jaxmpm scenes`` and ``jaxmpm run SCENE --help`` print the default of ``option`` for
    ``scene`` (``defaults``: its builder's, :func:`_builder_defaults`): the value as the option is
    spelled, or what the builder derives it from ("from cfl", "one period"); None where the scene
    does not take the option, or where the option's help states its default itself (--beta,
    --damping-approach, --dtype, --transport-xpic)."""
    from jaxmpm.scenes._common import DERIVED_DEFAULTS

    derived = DERIVED_DEFAULTS.get(scene, {})
    if option in ("--alpha-g", "--alpha-p"):  # the rates of the scene's damping
        if "damping" not in defaults:
            return None
        rate = option[2:].replace("-", "_")
        damping = defaults["damping"]
        if rate in derived or damping is None or damping is False:
            return derived.get(rate, "0")
        return _show(float(getattr(damping, "grid" if rate == "alpha_g" else "particle")))  # a jm.Damping default
    keyword = SCENE_OPTIONS.get(option)
    if keyword not in defaults or option in ("--beta", "--damping-approach", "--dtype", "--transport-xpic"):
        return None
    value = defaults[keyword]
    if value is None:
        return derived.get(keyword, "from cfl" if keyword == "dt" and "cfl" in defaults else "set by the scene")
    return _show(value)


def _show(value) -> str:
    """A default as the option is spelled: 0.1, 1e+08, flip, 0,-9.8 (a vector), off (a flag)."""
    if isinstance(value, bool):  # a flag (--stress)
        return "on" if value else "off"
    if isinstance(value, (tuple, list)):
        return ",".join(_show(v) for v in value)
    return f"{value:g}" if isinstance(value, float) else str(value)


def _rate_defaults(option: str) -> str:
    """"(default 0; cylinder the breathing mode's frequency)": a damping rate, 0 but where a scene damps."""
    others = {scene: text for scene, d in _scene_defaults().items()
              if (text := option_default(scene, option, d)) not in (None, "0")}
    return "(default 0" + "".join(f"; {scene} {text}" for scene, text in others.items()) + ")"


def _vector(text: str):
    """``--gravity`` as given: G (one number, the scene points it) or GX,GY[,GZ] (a vector)."""
    try:
        values = tuple(float(part) for part in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not G or GX,GY[,GZ] (numbers separated by commas)") from None
    if len(values) > 3:
        raise argparse.ArgumentTypeError(f"{text!r} has {len(values)} components; give G or GX,GY[,GZ]")
    return values[0] if len(values) == 1 else values


def version_text() -> str:
    """"jaxmpm 0.1.0 (jax 0.4.38, Python 3.11.9)": what ``jaxmpm --version`` prints."""
    import platform

    import jax

    from jaxmpm.core.version import __version__

    return f"jaxmpm {__version__} (jax {jax.__version__}, Python {platform.python_version()})"


def build_parser() -> argparse.ArgumentParser:
    import jaxmpm  # noqa: F401  (registers the schemes and shapes)
    from jaxmpm.core.registry import SCHEMES, SHAPES
    from jaxmpm.physics.damping import DAMPING_APPROACHES
    from jaxmpm.scenes import SCENES
    from jaxmpm.scenes._common import CONTACT_OPTIONS, FIELD_DEFAULTS

    parser = _OneLineErrors(
        prog="jaxmpm",
        description="Differentiable Material Point Method in JAX: run the benchmark scenes.",
    )
    parser.add_argument("--version", action="version", version=version_text(),
                        help="print the versions of jaxmpm and of jax, and exit")
    sub = parser.add_subparsers(dest="command", metavar="{scenes,run,resume,plot,animate}")
    sub.required = True
    sub.add_parser("scenes", help="list the scenes, their options and defaults",
                   description="List the scenes: a one-line description, then each one's options and defaults.")
    run = sub.add_parser(
        "run",
        help="run a scene and write HDF5",
        description="Run SCENE with a progress bar, writing HDF5 (plus an XDMF sidecar) as it goes. "
        "Options left out keep the scene's defaults (see `jaxmpm scenes`); `jaxmpm run SCENE --help` lists "
        "the options SCENE takes, with its defaults.",
    )
    run.add_argument("scene", metavar="SCENE",
                     help=f"scene name: {', '.join(SCENES)} (see `jaxmpm scenes` for each one's options and "
                          "defaults), or a Python file my_scene.py whose function `scene` builds the scene")
    run.add_argument("--scheme", default=None, metavar=SCHEMES.specs().replace(" ", ""),
                     help="velocity update " + _defaults("scheme"))
    run.add_argument("--beta", type=float, default=None, metavar="B",
                     help="FLIP fraction of flip/xpic/fmpm (default: 1 for flip, 0 for xpic and fmpm); "
                          "alone it means --scheme flip")
    run.add_argument("--alpha-g", type=float, default=None, metavar="A",
                     help="grid damping alpha_g in 1/time " + _rate_defaults("--alpha-g"))
    run.add_argument("--alpha-p", type=float, default=None, metavar="A",
                     help="particle damping alpha_p in 1/time " + _rate_defaults("--alpha-p"))
    run.add_argument("--damping-approach", default=None, choices=list(DAMPING_APPROACHES),
                     help="how grid damping acts (001 §5.1.2-5.2.2; jm.Damping's approach): on the particle update "
                          "(velocity, the default), on the grid momentum extrapolated as momentum (momentum), "
                          "or on the nodal force (force); needs --alpha-g")
    # no argparse choices: a scene file may register a shape of its own (jm.register_shape), and the file is
    # imported after the options are read; an unknown name is refused when the scene is built
    run.add_argument("--shape", default=None, metavar=SHAPES.specs().replace(" ", ""),
                     help="shape function " + _defaults("shape"))
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
                     help="Coulomb friction coefficient mu >= 0, with --contact coulomb (incline: the collider's) "
                          + _defaults("friction"))
    run.add_argument("--separation", type=float, default=None, metavar="S",
                     help="contact separation criterion in cells: the bodies touch where their nodal centres of "
                          "mass are closer than S h along the normal " + _defaults("separation"))
    run.add_argument("--conductivity", type=float, default=None, metavar="K",
                     help="thermal conductivity k >= 0 of a transport scene " + _defaults("conductivity"))
    run.add_argument("--diffusivity", type=float, default=None, metavar="D",
                     help="diffusivity D >= 0 of a diffusion scene " + _defaults("diffusivity"))
    run.add_argument("--transport-xpic", type=int, default=None, metavar="M",
                     help="update the transported field by XPIC(M) (000 §3.6) instead of FLIP; 1 is PIC")
    run.add_argument("--E", type=float, default=None, metavar="E",
                     help="Young's modulus E > 0 (mpm88: the fluid's stiffness, tau = E (J - 1)) " + _defaults("E"))
    run.add_argument("--nu", type=float, default=None, metavar="NU",
                     help="Poisson's ratio nu in (-1, 0.5) " + _defaults("nu"))
    run.add_argument("--density", type=float, default=None, metavar="RHO",
                     help="mass density rho > 0 " + _defaults("density"))
    run.add_argument("--heat-capacity", type=float, default=None, metavar="C",
                     help="heat capacity per unit mass c > 0 " + _defaults("heat_capacity"))
    run.add_argument("--expansion", type=float, default=None, metavar="A",
                     help="thermal expansion coefficient alpha_T " + _defaults("expansion"))
    run.add_argument("--gravity", type=_vector, default=None, metavar="G|GX,GY[,GZ]",
                     help="gravity: its magnitude G, pointed by the scene (mpm88: down; slide: tilted by --theta), "
                          "or the vector GX,GY[,GZ] where the scene takes one (mpm88, scene files) "
                          + _defaults("gravity"))
    run.add_argument("--theta", type=float, default=None, metavar="DEG",
                     help="tilt of gravity in degrees, [0, 90): the slope of slide's incline " + _defaults("theta"))
    run.add_argument("--angle", type=float, default=None, metavar="DEG",
                     help="angle of incline's collider slope in degrees, [0, 90) " + _defaults("angle"))
    run.add_argument("--aspect", type=float, default=None, metavar="A",
                     help="aspect ratio H0/L0 of the granular column " + _defaults("aspect"))
    run.add_argument("--friction-angle", type=float, default=None, metavar="DEG",
                     help="Drucker-Prager friction angle of the sand in degrees, [0, 90) "
                          + _defaults("friction_angle"))
    run.add_argument("--cohesion", type=float, default=None, metavar="C",
                     help="Drucker-Prager cohesion c >= 0 of the sand " + _defaults("cohesion"))
    run.add_argument("--geometry", default=None, choices=["axisymmetric", "3d"],
                     help="the Taylor bar's model: an r-z grid or a 3D quarter rod " + _defaults("geometry"))
    run.add_argument("--v0", type=float, default=None, metavar="V",
                     help="initial speed v0: bar's velocity amplitude, the two bars' and the Taylor bar's impact "
                          "speed (m/s) " + _defaults("v0"))
    run.add_argument("--yield-stress", type=float, default=None, metavar="SY",
                     help="von Mises yield stress sigma_y > 0 of the Taylor bar, Pa " + _defaults("yield_stress"))
    run.add_argument("--hardening", type=float, default=None, metavar="H",
                     help="linear hardening modulus H >= 0 of the Taylor bar, Pa " + _defaults("hardening"))
    run.add_argument("--viscosity", type=float, default=None, metavar="ETA",
                     help="dynamic viscosity eta >= 0 of a viscous fluid, Pa s " + _defaults("viscosity"))
    run.add_argument("--stress", action="store_const", const=True, default=None,
                     help="spin: a neo-Hookean disk (--E, --nu) instead of a stress-free one " + _defaults("stress"))
    run.add_argument("--conventions", default=None, choices=["jaxmpm", "nairnmpm"],
                     help="whose rules where MPM codes differ: jaxmpm (default) or nairnmpm (NairnMPM 19.0: "
                          "the reaction force on fixed nodes, XPIC's series start, the XPIC/PIC position update, "
                          "the grid damping's velocity)")
    run.add_argument("--dtype", default="f64", choices=["f32", "f64"], help="float precision (default f64)")
    run.add_argument("--fields", default=None, metavar="NAME,...",
                     help="per-particle fields saved in every frame besides x and v, comma-separated: stress, "
                          "pressure, J, F (and a material's saved state), or none (default: "
                          + ", ".join(f"{scene} {','.join(names)}" for scene, names in FIELD_DEFAULTS.items())
                          + "; other scenes none)")
    run.add_argument("--set", action="append", default=None, metavar="NAME=VALUE",
                     help="a keyword of the scene that has no option of its own, e.g. --set n_particles=32768 "
                          "(mpm88) or --set dim=2 (mms); repeatable; VALUE a Python literal (a number, a tuple, "
                          "True, 'text') or a bare word (`jaxmpm scenes` lists each scene's keywords)")
    run.add_argument("--max-steps", type=int, default=None, metavar="N",
                     help="refuse a run of more than N steps (default: the step counter's limit 2^31 - 1)")
    run.add_argument("--devices", type=int, default=None, metavar="N",
                     help="run on the first N local devices, the grid cut into N slabs along x "
                          "(jaxmpm.parallel.ShardedSimulation; docs/scaling.md); the same file as one device. On a "
                          "CPU, N devices need --cpu-devices N (or "
                          "XLA_FLAGS=--xla_force_host_platform_device_count=N). `jaxmpm resume` continues such a "
                          "file on one device, or on several with --devices (default: one device, no sharding)")
    run.add_argument("--rebalance-every", type=int, default=None, metavar="K",
                     help="with --devices: move the slab boundaries with the particles every K steps (and before a "
                          "step that would overflow a device's buffer; docs/scaling.md, load balance); default: "
                          "fixed equal slabs")
    add_buffer_options(run)
    run.add_argument("--cpu-devices", type=int, default=None, metavar="N", help=CPU_DEVICES_HELP)
    run.add_argument("--out", required=True, metavar="FILE.h5",
                     help="HDF5 output file (an XDMF sidecar goes beside it)")
    run.add_argument("--force", action="store_true", help="overwrite --out and its XDMF sidecar if they exist")
    run.add_argument("--no-progress", action="store_true", help="no progress bar")
    run.add_argument("--no-cache", action="store_true", help=NO_CACHE_HELP)
    run.add_argument("--cache", action="store_true", help=CACHE_HELP)
    resume = sub.add_parser(
        "resume",
        help="continue an interrupted run",
        description="Continue the run stored in FILE.h5 (stopped by Ctrl-C, SIGTERM or a kill) from its last "
        "saved chunk to its end, appending to the same file; the result equals the uninterrupted run.",
    )
    resume.add_argument("file", metavar="FILE.h5", help="the --out file of an interrupted `jaxmpm run`")
    resume.add_argument("--devices", type=int, default=None, metavar="N",
                        help="continue on the first N local devices, as `jaxmpm run --devices N` (whichever way the "
                             "file was started: the uninterrupted run's file to round-off; default: one device)")
    resume.add_argument("--rebalance-every", type=int, default=None, metavar="K",
                        help="with --devices: move the slab boundaries with the particles every K steps, as "
                             "`jaxmpm run --rebalance-every K` (default: fixed equal slabs)")
    add_buffer_options(resume)
    resume.add_argument("--cpu-devices", type=int, default=None, metavar="N", help=CPU_DEVICES_HELP)
    resume.add_argument("--no-progress", action="store_true", help="no progress bar")
    resume.add_argument("--no-cache", action="store_true", help=NO_CACHE_HELP)
    resume.add_argument("--cache", action="store_true", help=CACHE_HELP)
    add_plot_commands(sub)
    return parser


def main(argv=None) -> int:
    """Entry point of the ``jaxmpm`` console script; returns 0, or exits with status 2 on an error
    (130/143 when a signal interrupts a run).  Warnings print as one line each, ``jaxmpm: warning: ...``."""
    import warnings

    shown = warnings.formatwarning
    warnings.formatwarning = _warning_line
    try:
        return _main(argv)
    finally:
        warnings.formatwarning = shown


def _warning_line(message, category, filename, lineno, line=None) -> str:
    """A warning as the command line prints it: one line, like its errors (not Python's file and source line)."""
    return f"jaxmpm: warning: {message}\n"


def _main(argv) -> int:
    argv = _negative_values_joined(sys.argv[1:] if argv is None else list(argv))
    if argv[:1] in (["scenes"], ["run"]):  # the scenes of installed packages, which these list
        from .scenes import load_scene_entry_points

        load_scene_entry_points()
    parser = build_parser()
    scene = scene_asking_for_help(parser, argv)
    if scene is not None:
        return scene_help(parser, scene)
    args = parser.parse_args(argv)
    if getattr(args, "no_cache", False):  # before anything compiles
        from .run.cache import compilation_cache

        compilation_cache(False)
    if getattr(args, "cpu_devices", None) is not None:  # before JAX's first computation
        start_cpu_devices(args.cpu_devices)
    if args.command == "scenes":
        return list_scenes()
    if args.command == "resume":
        return resume_run(args)
    if args.command in PLOT_COMMANDS:
        return run_plot_command(args)
    return run_scene(args)


def start_cpu_devices(count) -> None:
    """``--cpu-devices N``: JAX's CPU backend started with ``count`` devices (``jax_num_cpu_devices``); exits
    with the reason where ``count`` is not a positive integer or JAX has already computed in this process."""
    import jax

    if count < 1:  # argparse has made it an int
        fail(f"--cpu-devices = {count!r} must be a positive integer (the CPU devices JAX starts with)")
    try:
        jax.config.update("jax_num_cpu_devices", count)
    except RuntimeError:
        fail(f"--cpu-devices {count}: JAX has already computed in this process, so its device count is fixed "
             f"({len(jax.devices())}); give the option to a new `jaxmpm` process")


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
    """A number, or numbers separated by commas (a vector: --gravity -9.8,0)."""
    try:
        [float(part) for part in text.split(",")]
    except ValueError:
        return False
    return True


def _subparser(parser, command: str) -> argparse.ArgumentParser:
    return next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices[command]


def scene_asking_for_help(parser, argv: list) -> str | None:
    """SCENE of ``jaxmpm run ... SCENE ... --help`` (the first word that is not an option or an
    option's value), else None (``jaxmpm run --help`` keeps argparse's help of every option)."""
    if argv[:1] != ["run"] or not {"-h", "--help"} & set(argv[1:]):
        return None
    run = _subparser(parser, "run")
    tokens = iter(argv[1:])
    for token in tokens:
        if token == "--":
            return next(tokens, None)
        if not token.startswith("-"):
            return token
        name = token.split("=", 1)[0]
        matches = {a for o, a in run._option_string_actions.items() if o == name} or \
            {a for o, a in run._option_string_actions.items() if o.startswith(name)}  # argparse's abbreviations
        if "=" not in token and len(matches) == 1 and next(iter(matches)).nargs != 0:
            next(tokens, None)  # the option's value
    return None


def scene_help(parser, scene: str) -> int:
    """``jaxmpm run SCENE --help``: the options SCENE takes, with SCENE's own defaults as values,
    then the run options (those of every scene)."""
    from jaxmpm.core.errors import InputError
    from jaxmpm.scenes._common import FIELD_DEFAULTS
    from jaxmpm.scenes.command import accepted_keywords, other_keywords, scene_builder

    try:
        builder, description, scene_file = scene_builder(scene)
    except InputError as err:
        fail(str(err))
    if scene_file is not None:  # built anew: the help then lists the schemes and shapes the file registers
        parser = build_parser()
    keywords, takes_any = accepted_keywords(builder)
    defaults = _builder_defaults(scene, builder)
    run = _subparser(parser, "run")
    run.description = (f"Run {scene}: {description.rstrip('.')}.  Writes HDF5 (plus an XDMF sidecar) as it goes; "
                       f"options left out keep {scene}'s defaults, shown below.")
    own = run.add_argument_group(f"options of {scene}")
    general = run.add_argument_group("run options")
    for action in list(run._optionals._group_actions):
        option = next((o for o in action.option_strings if o in SCENE_OPTIONS), None)
        run._optionals._group_actions.remove(action)
        if option is None:  # -h, --out, --max-steps, ...: every scene's
            if action.dest == "fields":  # the list of every scene's defaults -> this scene's
                own_fields = ",".join(FIELD_DEFAULTS.get(scene, ())) or "none"
                action.help = f"{action.help[:action.help.rfind(' (default')]} (default {own_fields})"
            if action.dest == "set":  # this scene's keywords without an option, with their defaults
                other = other_keywords(builder)
                action.help = ("a keyword of the scene without an option of its own; repeatable; VALUE a Python "
                               "literal or a bare word; " + (f"{scene}'s: " + ", ".join(
                                   f"{k}={v!r}" for k, v in other.items()) if other else f"{scene} has none"))
                own._group_actions.append(action)
                continue
            general._group_actions.append(action)
            continue
        keyword = SCENE_OPTIONS[option]
        if keyword not in keywords and not takes_any and option != "--dtype":
            action.help = argparse.SUPPRESS  # an option another scene takes
            continue
        text = option_default(scene, option, defaults)
        action.help = SCENE_HELP.get((scene, option), action.help or "")
        cut = action.help.rfind(" (default")
        if (text is not None or keyword not in keywords) and cut >= 0 and action.help.endswith(")"):
            action.help = action.help[:cut]  # the defaults of every scene
        if text is not None:
            action.help = f"{action.help.rstrip()} (default {text})"
        own._group_actions.append(action)
    for action in run._positionals._group_actions:
        if action.dest == "scene":
            action.help = f"{scene}: {description}"
    run.print_help()
    return 0


def list_scenes() -> int:
    """Each scene's description, then its options (as ``jaxmpm run`` spells them) and defaults."""
    from .scenes import ENTRY_POINT_ERRORS, SCENES
    from .scenes.command import other_keywords

    defaults = _scene_defaults()
    width = max(len(name) for name in SCENES)
    for name, (_, description) in SCENES.items():
        print(f"{name:<{width}}  {description}")
        options = [f"{option} {text}" for option in SCENE_OPTIONS
                   if (text := option_default(name, option, defaults[name])) is not None]
        print(f"{'':<{width}}    " + ", ".join(options))
        other = other_keywords(SCENES[name][0])
        if other:
            print(f"{'':<{width}}    --set " + ", ".join(f"{k}={v!r}" for k, v in other.items()))
    for message in ENTRY_POINT_ERRORS.values():  # an installed package's scene that could not be added
        print(f"jaxmpm: warning: {message}", file=sys.stderr)
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
    from jaxmpm.io.xdmf import xdmf_paths

    if not args.out.strip() or os.path.isdir(args.out):
        fail(f"--out {args.out!r} is {'a folder' if args.out.strip() else 'empty'}; give the run's file, e.g. "
             f"{os.path.join(args.out, 'run.h5') if args.out.strip() else 'run.h5'}")
    if os.path.exists(args.out) and not args.force:
        saved = saved_state(args.out)
        unfinished = (f" (it holds an unfinished run, continued by `jaxmpm resume {args.out}`)"
                      if saved and not saved["complete"] else "")
        fail(f"--out {args.out} exists{unfinished}; pass --force to overwrite it, or choose another file")
    sidecars = [p for p in xdmf_paths(args.out) if os.path.exists(p)]
    if sidecars and not args.force:  # the XDMF sidecar written beside --out: another run's, replaced too
        fail(f"--out {args.out}: {' and '.join(sidecars)} {'exists' if len(sidecars) == 1 else 'exist'} (the XDMF "
             "sidecar of an earlier run, which this run would replace); pass --force to overwrite, or choose "
             "another file")
    try:
        check_device_options(args)  # before the scene is built
        setup = build_setup(args)
        if args.max_steps is not None:
            check(args.max_steps >= 1, f"--max-steps = {args.max_steps} must be a positive integer")
            check(setup.steps <= args.max_steps,
                  f"the run needs {setup.steps} steps, more than --max-steps {args.max_steps}; "
                  "shorten --t-end or use a larger --dt/--cfl")
        args.fields = ",".join(frame_fields(args, setup)) or "none"  # stored in the command: resume keeps them
    except jm.InputError as err:
        fail(str(err))
    except MemoryError:
        fail(f"scene {args.scene!r} does not fit in memory; use a coarser --spacing/--cells or fewer --ppc")
    return run_setup(setup, args, stored_options(options_of(args), setup))


def add_buffer_options(parser) -> None:
    """``--capacity`` and ``--exchange`` of ``jaxmpm run`` and ``jaxmpm resume``: the particle buffers
    of a run on several devices (:class:`jaxmpm.parallel.ShardedSimulation`)."""
    parser.add_argument("--capacity", type=int, default=None, metavar="C",
                        help="with --devices: particle slots per device (default: 1.15 x the fullest slab's "
                             "particles at the start, plus 16); raise it when a run stops because particles "
                             "gathered in one slab did not fit")
    parser.add_argument("--exchange", type=int, default=None, metavar="X",
                        help="with --devices: slots per step for the particles moving to each neighbouring device "
                             "(default: the most of a tenth of the capacity, 8 and 1.25 x the fullest cell column's "
                             "particles)")


def check_device_options(args) -> None:
    """The options of a run on several devices, checked before the scene is built: an InputError
    naming the option (not ShardedSimulation's keyword) and its fix."""
    from jaxmpm.core.errors import check

    for name, what in (("rebalance_every", "moves the slabs"), ("capacity", "sizes the particle buffers"),
                       ("exchange", "sizes the exchange buffers")):
        value = getattr(args, name, None)
        option = "--" + name.replace("_", "-")
        check(value is None or args.devices is not None,
              f"{option} {value} {what} of a run on several devices; add --devices N")
        check(value is None or value >= 1, f"{option} {value} must be a positive integer")
    if args.devices is not None:  # enough devices
        from jaxmpm.parallel import local_devices

        local_devices(args.devices, "--devices")


def sharded_model(setup, args):
    """``--devices N``: the scene's model on the first N local devices
    (:class:`jaxmpm.parallel.ShardedSimulation`; ``--rebalance-every K``: its slabs moving with the
    particles; ``--capacity``, ``--exchange``: its buffers), checked before the output file is made; an
    InputError naming the fix when there are fewer devices or the model has terms the sharded path
    does not support."""
    from jaxmpm.parallel import ShardedSimulation, local_devices

    return ShardedSimulation(setup.sim, devices=local_devices(args.devices, "--devices"),
                             rebalance_every=getattr(args, "rebalance_every", None),
                             capacity=getattr(args, "capacity", None), exchange=getattr(args, "exchange", None))


def frame_fields(args, setup) -> tuple:
    """The per-frame fields of ``jaxmpm run`` (jaxmpm.model.frame_fields), checked: ``--fields``, else
    the scene's default (``FIELD_DEFAULTS``)."""
    from jaxmpm.scenes._common import FIELD_DEFAULTS

    names = FIELD_DEFAULTS.get(setup.name, ()) if args.fields is None else fields_option(args.fields)
    return setup.sim.check_frame_fields(setup.state, names, "--fields (comma-separated names, or none)")


def fields_option(text: str) -> tuple:
    """The names of a ``--fields`` value: "stress,J" -> ("stress", "J"); "none" -> ()."""
    return () if text.strip().lower() == "none" else tuple(name.strip() for name in text.split(","))


def resume_run(args) -> int:
    import json

    from jaxmpm.resume import run_info

    try:
        info = run_info(args.file)
        if "command" not in info:
            fail(f"{args.file} was not written by `jaxmpm run`; resume it from Python with jm.resume(path, setup)")
        options = json.loads(info["command"])
        _with_x64(options.get("dtype", "f64"))
        check_device_options(args)  # before the scene is built
        setup = setup_from_options(options)
    except (ValueError, KeyError) as err:  # InputError is a ValueError
        fail(str(err))
    return run_setup(setup, argparse.Namespace(out=args.file, no_progress=args.no_progress, devices=args.devices,
                                               rebalance_every=args.rebalance_every, capacity=args.capacity,
                                               exchange=args.exchange), options, resume=True)


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
    """The model's totals of a state (the terms' thermal energy, solute; the material's dissipated
    energy: ``Simulation.totals``), as floats."""
    return {name: float(value) for name, value in sim.totals(state).items()}


def energy_rows(sim, d0, final) -> list:
    """The summary's energy lines: the total K + U + V_g at the start and the end (with their ratio),
    then each part.  V_g, the potential energy of the particles in the model's gravity g
    (``sim.diagnostics``' ``gravitational``, -sum_p M_p g . X_p), is counted from the start,
    V_g = -sum_p M_p g . (X_p - X_p(0)), so that it starts at 0 whatever the origin.  A body force
    b(x, t) has no potential: its work is in no part.  ``d0``: ``sim.diagnostics`` of the initial state
    (taken before the run, which may reuse the state's memory)."""
    import numpy as np

    d1 = sim.diagnostics(final)
    parts = {"kinetic K": (float(d0["kinetic"]), float(d1["kinetic"])),
             "strain U": (float(d0["strain"]), float(d1["strain"])),
             "gravitational V_g": (0.0, float(d1["gravitational"] - d0["gravitational"]))}
    e0, e1 = (sum(part[i] for part in parts.values()) for i in (0, 1))
    gravity = any(float(g) != 0 for g in np.asarray(sim.gravity).ravel())
    field = "; the body force b(x, t) has no potential and is not counted" if sim.body_force is not None else ""
    rows = [("energy K+U+V_g", f"initial {e0:.6g}, final {e1:.6g}" + ("" if e0 == 0 else f", ratio {e1 / e0:.6f}"))]
    for key, (start, end) in parts.items():
        value = f"initial {start:.6g}, final {end:.6g}"
        if key.startswith("gravitational"):
            value = (f"{value} (-sum m g.(x - x0): from the start)" if gravity else "0 (no gravity)") + field
        rows.append(("  " + key, value))
    return rows


def seconds_since_start() -> float:
    """Seconds since this process started (Linux: its start time in /proc/self/stat against
    /proc/uptime), else since :mod:`jaxmpm.cli` was imported: the wall time a user waited,
    Python's and JAX's start-up included."""
    import os

    try:
        with open("/proc/self/stat") as f:
            after_name = f.read().rsplit(")", 1)[1].split()  # from field 3 on; the name may hold spaces
        with open("/proc/uptime") as f:
            uptime = float(f.read().split()[0])
        age = uptime - int(after_name[19]) / os.sysconf("SC_CLK_TCK")  # field 22: starttime, clock ticks
    except (OSError, ValueError, IndexError):
        age = -1.0
    return age if age >= 0 else time.perf_counter() - _IMPORTED


def time_rows(timings: dict, particles: int, steps: int, resume: bool) -> list:
    """The summary's time lines: the wall time since the process started and its parts, the
    compilation and the run apart, and particle-steps/s over the run alone."""
    wall = seconds_since_start()
    compile_s, run_s = timings.get("compile", 0.0), timings.get("run", 0.0)
    resumed = f" ({steps} steps resumed)" if resume else ""
    return [
        ("wall time", f"{wall:.3f} s since the process started (start-up and set-up "
                      f"{max(0.0, wall - compile_s - run_s):.3f} s, compile {compile_s:.3f} s, run {run_s:.3f} s)"),
        ("compile time", f"{compile_s:.3f} s (the step loop, before the first step)"),
        ("run time", f"{run_s:.3f} s ({steps} steps, writing included)"),
        ("particle-steps/s", (f"{particles * steps / run_s:.4g} (over the run time){resumed}" if steps and run_s > 0
                              else "n/a (no steps run)")),
    ]


def run_setup(setup, args, options: dict, resume: bool = False) -> int:
    """Run with the HDF5 writer attached (or continue the run in ``args.out``), then print the
    summary; with ``--devices N`` the run steps the scene's model on N devices (:func:`sharded_model`)."""
    import json
    import os

    import jax
    import numpy as np

    import jaxmpm as jm
    from jaxmpm.io.xdmf import xdmf_paths

    sim, state = setup.sim, setup.state
    n = int(state.x.shape[0])
    # what the summary says of the initial state, read before the run computes its states in place of it
    d0, totals0 = sim.diagnostics(state), totals(sim, state)
    p0 = np.asarray(d0["momentum"], dtype=float)
    shared = jm.backend_info(sim, state)["particle_devices"]
    dtype = str(state.x.dtype)
    first_step = int(state.step)
    if resume:
        import h5py

        with h5py.File(args.out, "r") as f:
            first_step = int(f["state/step"][()]) if "state/step" in f else first_step
    timings = {}  # compile and run seconds (jm.run's timings)
    sharded = None
    try:
        if getattr(args, "devices", None) is not None:  # checked before the file is made (or continued)
            sharded = sharded_model(setup, args)
        if resume:
            final = jm.resume(args.out, setup, progress=not args.no_progress, timings=timings, devices=sharded)
        else:
            with jm.H5Writer(args.out, sim, state, dt=setup.dt, scene=setup.name, params=setup.params,
                             ppc=setup.params.get("ppc"), attrs={"command": json.dumps(options)},
                             fields=fields_option(options.get("fields", "none")),
                             overwrite=args.force) as writer:
                if sharded is None:
                    final, _ = setup.run(progress=not args.no_progress, writer=writer,  # `command`: for resume
                                         timings=timings, donate=True)  # the scene's state is the CLI's own
                else:
                    final, _ = sharded.run(state, setup.dt, setup.steps, setup.save_every, writer=writer,
                                           progress=not args.no_progress, timings=timings)
        jax.block_until_ready(final)
    except jm.ParticlesLeftGrid as err:  # the grid is too small: not an instability
        when = f" (t = {err.time:.6g})" if err.time is not None else ""
        fail(f"particles left the grid at step {err.step}{when}: {err.detail}; the scene's grid is too small for "
             f"this long a run (not a numerical instability): shorten --t-end; the frames before it were kept in "
             f"{args.out}")
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
    p1 = np.asarray(sim.diagnostics(final)["momentum"], dtype=float)
    shared = shared if sharded is None else 1
    scheme = sim.scheme
    name = type(scheme).__name__
    order = getattr(scheme, "order", None)
    label = f"{name}({order})" if name in ("XPIC", "FMPM") else name
    if hasattr(scheme, "beta"):
        label += f", beta = {float(np.asarray(scheme.beta)):g}"
    dissipated = float(final.dissipated)
    rows = [
        ("scene", setup.name),
        ("scheme", label),
        ("shape / update", f"{type(sim.shape).__name__} / {sim.update}"),
        ("dtype", dtype),
        ("particles", f"{n}"),
        *([] if sharded is not None or shared < 2 else
          [("particle devices", f"{shared} CPU devices, each holding the whole grid")]),
        *([] if sharded is None else [("devices", f"{sharded.devices} (slabs along x), {sharded.stats['migrated']} "
                                                  "particle moves between them"
                                                  + (f", {sharded.stats.get('rebalances', 0)} rebalance(s)"
                                                     if sharded.rebalance_every else ""))]),
        ("steps", f"{setup.steps} (t_end = {setup.t_end:.6g})"),
        ("dt", f"{setup.dt:.6g}"),
        *time_rows(timings, n, int(final.step) - first_step, resume),
        *energy_rows(sim, d0, final),
        *[(name.replace("_", " "), f"initial {value:.6g}, final {totals(sim, final)[name]:.6g}")
          for name, value in totals0.items()],
        ("dissipated", f"n/a (not tracked by {name})" if math.isnan(dissipated) else f"{dissipated:.6g}"),
        ("|p - p0|", f"{float(np.linalg.norm(p1 - p0)):.3e} (change of linear momentum)"),
        ("output", ", ".join(files)),
    ]
    width = max(len(k) for k, _ in rows)
    for key, value in rows:
        print(f"{key:<{width}}  {value}")
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
