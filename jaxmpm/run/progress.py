"""Progress of calibrations and ensembles: whether to show it, and their programs compiled ahead of
time so that the compilation (most of a first iteration) is timed and reported apart from the run.

Shown progress goes to stderr: one ``jaxmpm ...: compiling ... 3.1 s`` line per compilation, then a
tqdm bar (``tqdm.auto``, as :func:`jaxmpm.run.driver.run` uses; the text bar where ipywidgets, which
a notebook's widget bar needs, is missing) for a calibration's iterations, or one ``running ... s``
line for an ensemble.  ``progress=None`` (the default of :func:`jaxmpm.calibrate` and
:func:`jaxmpm.ensemble`) shows it when the call is interactive: stderr is a terminal, or the code
runs in a Jupyter kernel; tests, scripts piped to a file and CI stay quiet."""

from __future__ import annotations

import contextlib
import sys
import time

import jax
import numpy as np

from ..core.errors import check
from .collector import fewer_collections, with_fewer_collections


def interactive() -> bool:
    """Whether the caller watches: stderr is a terminal, or this is a Jupyter (IPython) kernel."""
    try:
        if sys.stderr is not None and sys.stderr.isatty():
            return True
    except (AttributeError, ValueError):  # a replaced or closed stderr
        pass
    ipython = sys.modules.get("IPython")  # only ever imported by an IPython session (or a test of one)
    try:
        shell = ipython.get_ipython() if ipython is not None else None
    except Exception:  # noqa: BLE001  (a partly imported or unusual IPython: not a kernel we know)
        return False
    return getattr(shell, "kernel", None) is not None  # a kernel's shell has one; the terminal's has none


def shown(progress, caller: str) -> bool:
    """``progress`` (True, False or None: on when :func:`interactive`) checked and resolved."""
    check(progress is None or isinstance(progress, bool),
          f"{caller}: progress = {progress!r} must be True, False or None (shown when interactive)")
    return interactive() if progress is None else progress


def _seconds(seconds: float) -> str:
    """3.1 s, 0.042 s: one decimal, or two significant digits below a second."""
    return f"{seconds:.1f} s" if seconds >= 1 else f"{seconds:.2g} s"


class Stage:
    """Times a block (``seconds``); when ``show``, prints ``what ...`` to stderr before it and the
    seconds it took after it, on the same line."""

    def __init__(self, what: str, show: bool):
        self.what, self.show, self.seconds = what, show, 0.0

    def __enter__(self):
        if self.show:
            print(f"{self.what} ...", end="", file=sys.stderr, flush=True)
        self._tic = time.perf_counter()
        return self

    def __exit__(self, kind, *exc):
        self.seconds = time.perf_counter() - self._tic
        if self.show:
            print(" failed" if kind is not None else f" {_seconds(self.seconds)}", file=sys.stderr, flush=True)


def _leaf_key(leaf):
    """An array by its type (shape, dtype, weak type); anything else (static to ``eqx.filter_jit``) by value."""
    if isinstance(leaf, (jax.Array, np.ndarray)):
        return jax.typeof(leaf)
    try:
        hash(leaf)
    except TypeError:
        return type(leaf), id(leaf)
    return type(leaf), leaf


def _signature(args):
    leaves, treedef = jax.tree_util.tree_flatten(args)
    return treedef, tuple(_leaf_key(leaf) for leaf in leaves)


class AheadOfTime:
    """A jitted function (``jax.jit`` or ``eqx.filter_jit``) called through programs compiled ahead
    of time (``.lower(*args).compile()``), one per signature of its arguments (shapes, dtypes, weak
    types, tree structure): the program is the one a plain call compiles (JAX keeps one cache for
    both, so nothing compiles twice) and gives the same numbers.  ``compile_time`` sums the seconds
    spent compiling, each compilation reported as ``what ... 3.1 s`` when ``show``."""

    def __init__(self, jitted, what: str, show: bool):
        self.jitted, self.what, self.show = jitted, what, show
        self.programs = {}
        self.compile_time = 0.0

    def compile(self, *args):
        """The program for ``args``, compiled (and timed) unless it is already."""
        key = _signature(args)
        program = self.programs.get(key)
        if program is None:
            with Stage(self.what, self.show) as stage, fewer_collections():
                program = self.jitted.lower(*args).compile()
            self.compile_time += stage.seconds
            self.programs[key] = program
        return program

    def __call__(self, *args):
        return self.compile(*args)(*args)


@contextlib.contextmanager
def bar(show: bool, **options):
    """A ``tqdm.auto`` bar with ``options`` when ``show``, else None; closed on leaving.  Without
    ipywidgets (what a notebook's widget bar needs) the text bar, without tqdm.auto's warning."""
    if not show:
        yield None
        return
    import importlib.util

    if importlib.util.find_spec("ipywidgets") is not None:
        from tqdm.auto import tqdm
    else:
        from tqdm.std import tqdm

    progress_bar = tqdm(**options)  # to stderr, as the run driver's
    try:
        yield progress_bar
    finally:
        progress_bar.close()


@with_fewer_collections
def shown_call(jitted, args: tuple, what: str, show: bool):
    """``jitted(*args)``; when ``show`` (and no argument is traced: under ``jit``/``grad``/``vmap``
    nothing runs here to time), compiled ahead of time and then run to completion, each timed and
    shown on stderr: ``{what}: compiling ... 3.1 s``, ``{what}: running ... 0.8 s``.  The same
    program either way, so the same numbers."""
    if not show or any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree_util.tree_leaves(args)):
        return jitted(*args)
    program = AheadOfTime(jitted, f"{what}: compiling", True).compile(*args)
    with Stage(f"{what}: running", True):
        return jax.block_until_ready(program(*args))
