"""One validation layer for the values a user gives: the constructors, :func:`jaxmpm.fill`, the
scenes, :func:`jaxmpm.set_params`, :func:`jaxmpm.ensemble` and :func:`jaxmpm.stable_dt` all check
through these helpers, so every message has one form::

    LinearElastic: nu = 0.7 must lie in (-1, 0.5); 0.5 is incompressible and not supported
    fill: ppc = 2.5 must be a positive integer; particles per cell per axis
    LinearElastic: E must be a number, got 'abc'

Each raises :class:`jaxmpm.InputError` naming the owner, the parameter, the value given, the
allowed range and (``fix``) what to do.  The checks are NaN-safe (NaN and +-inf fail every range)
and one line long.  A value being traced (inside ``jit``/``grad``/``vmap``) cannot be checked and
passes through unchanged; a concrete JAX array or NumPy scalar is checked like a Python number.

* :func:`real` -- one finite number in a range, returned as a Python float;
* :func:`leaf` -- a float array leaf of a model (E, nu, beta, damping, gravity), every entry checked;
* :func:`positive_int` -- a positive (or, with ``low=0``, non-negative) integer;
* :func:`finite_vector` -- a point/velocity/corner: finite numbers, one per axis;
* :class:`Range` -- a range as a value, shared by a constructor and its registered
  :class:`jaxmpm.Parameter` (``valid=``), so that ``set_params`` and ``ensemble`` check the same.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import numbers
import sys

import equinox as eqx
import jax
import numpy as np

from .errors import InputError

_MAX_SHOWN = 60  # characters of a value quoted in a message


# --------------------------------------------------------------------------- basics
def traced(value) -> bool:
    """True when ``value`` (or a leaf of it) is a JAX tracer: inside jit/grad/vmap, not checkable."""
    if isinstance(value, jax.core.Tracer):
        return True
    if isinstance(value, (str, bytes, numbers.Number, np.ndarray, np.generic)) or value is None:
        return False
    try:
        return any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree_util.tree_leaves(value))
    except Exception:  # an object jax cannot flatten: not traced
        return False


def compiled_when_concrete(fn):
    """``fn`` run as one compiled program (``eqx.filter_jit``, kept per static structure) when none of
    its arguments is traced, and inline, as written, inside a caller's jit/grad/vmap.  Op by op, jnp
    compiles a small program for each operation the first time a process runs it.  A Python float
    argument goes in as a weakly typed array (``jax.device_put``; ``jnp.asarray`` compiles a program
    for it), so a new value compiles nothing and rounds to the other operands' precision as before;
    ints and other non-arrays stay static."""
    compiled = eqx.filter_jit(fn)

    @functools.wraps(fn)
    def call(*args):
        if traced(args):
            return fn(*args)
        return compiled(*(jax.device_put(a) if type(a) is float else a for a in args))

    return call


def concrete(x):
    """``x`` as a NumPy array, or None while it is being traced (jit/grad/vmap)."""
    if traced(x):
        return None
    try:
        return np.asarray(x)
    except (jax.errors.TracerArrayConversionError, jax.errors.ConcretizationTypeError):
        return None


def _number_text(v) -> str:
    if isinstance(v, (bool, np.bool_)):
        return repr(bool(v))
    if isinstance(v, numbers.Integral):
        return str(int(v))
    if isinstance(v, numbers.Real):
        return repr(float(v))
    return repr(v)


def show(value) -> str:
    """``value`` as quoted in a message: one line, at most ~60 characters."""
    if isinstance(value, (str, bytes)):
        text = repr(value)
    elif isinstance(value, (numbers.Number, np.generic)):
        text = _number_text(value)
    elif isinstance(value, (np.ndarray, jax.Array)) and not traced(value):
        arr = np.asarray(value)
        if arr.ndim == 0:
            text = _number_text(arr.item())
        elif arr.size <= 8:
            text = show(arr.tolist())
        else:
            text = np.array2string(arr, separator=", ", threshold=8, edgeitems=2, max_line_width=sys.maxsize)
    elif isinstance(value, (tuple, list)):
        inner = ", ".join(show(v) for v in value[:8]) + (", ..." if len(value) > 8 else "")
        text = (f"({inner},)" if len(value) == 1 else f"({inner})") if isinstance(value, tuple) else f"[{inner}]"
    else:
        text = repr(value)
    text = " ".join(text.split())  # one line
    return text if len(text) <= _MAX_SHOWN else text[: _MAX_SHOWN - 3] + "..."


def fail(owner: str, message: str, fix: str | None = None):
    """Raise :class:`InputError` with ``owner: message; fix`` (one line)."""
    text = f"{owner}: {message}" if owner else message
    if fix:
        text += f"; {fix}"
    raise InputError(" ".join(text.split()))


def _is_string_like(value) -> bool:
    return isinstance(value, (str, bytes)) or value is None or isinstance(value, (bool, np.bool_))


def _numeric_array(owner, name, value, fix, what="a number"):
    """``value`` as a NumPy array of real numbers, or an InputError 'must be a number, got ...'."""
    if _is_string_like(value):
        fail(owner, f"{name} must be {what}, got {show(value)}", fix)
    try:
        arr = np.asarray(value)
    except Exception:
        fail(owner, f"{name} must be {what}, got {show(value)}", fix)
    if arr.dtype == object and isinstance(value, numbers.Real):  # Fraction, Decimal, huge ints
        try:
            arr = np.asarray(float(value))
        except (OverflowError, ValueError):
            pass
    if arr.dtype.kind not in "iuf":
        fail(owner, f"{name} must be {what}, got {show(value)}", fix)
    return arr


# --------------------------------------------------------------------------- ranges
def _bound_text(v) -> str:
    return _number_text(v) if isinstance(v, numbers.Integral) or float(v) != int(v) else str(int(v))


@dataclasses.dataclass(frozen=True)
class Range:
    """A range of real numbers: ``low``/``high`` (None: unbounded), open or closed ends, and a
    ``fix`` appended to the message.  ``Range()`` accepts every finite number."""

    low: float | None = None
    high: float | None = None
    low_open: bool = False
    high_open: bool = False
    fix: str | None = None

    def phrase(self) -> str:
        """'be positive', 'be >= 0', 'lie in (-1, 0.5)', 'be a finite number'."""
        lo, hi = self.low, self.high
        if lo is None and hi is None:
            return "be a finite number"
        if hi is None:
            if lo == 0:
                return "be positive" if self.low_open else "be >= 0"
            return f"be {'>' if self.low_open else '>='} {_bound_text(lo)}"
        if lo is None:
            return f"be {'<' if self.high_open else '<='} {_bound_text(hi)}"
        return (f"lie in {'(' if self.low_open else '['}{_bound_text(lo)}, {_bound_text(hi)}"
                f"{')' if self.high_open else ']'}")

    def holds(self, arr) -> bool:
        """Every entry finite and inside the range (NaN fails)."""
        arr = np.asarray(arr, dtype=float)
        ok = np.isfinite(arr)
        if self.low is not None:
            ok &= (arr > self.low) if self.low_open else (arr >= self.low)
        if self.high is not None:
            ok &= (arr < self.high) if self.high_open else (arr <= self.high)
        return bool(np.all(ok))

    def message(self, name, value, arr) -> str:
        finite = bool(np.all(np.isfinite(np.asarray(arr, dtype=float))))
        phrase = self.phrase()
        if not finite and phrase != "be a finite number":
            phrase = "be finite and " + phrase[3:] if phrase.startswith("be ") else "be finite and " + phrase
        return f"{name} = {show(value)} must {phrase}"

    def check(self, owner: str, name: str, value, fix: str | None = None) -> None:
        """Raise InputError unless every entry of ``value`` is a finite number in the range
        (a traced value passes)."""
        if traced(value):
            return
        arr = _numeric_array(owner, name, value, fix or self.fix)
        if not self.holds(arr):
            fail(owner, self.message(name, value, arr), fix or self.fix)

    def real(self, owner: str, name: str, value, fix: str | None = None):
        """One number in the range as a Python float (a traced value is returned unchanged)."""
        if traced(value):
            return value
        arr = _numeric_array(owner, name, value, fix or self.fix)
        if arr.ndim != 0:
            fail(owner, f"{name} must be a single number, got {show(value)}", fix or self.fix)
        if not self.holds(arr):
            fail(owner, self.message(name, value, arr), fix or self.fix)
        return float(arr)

    def leaf(self, owner: str, name: str, value, fix: str | None = None):
        """A float array leaf (the default float dtype), every concrete entry checked."""
        import jax.numpy as jnp

        self.check(owner, name, value, fix)
        return jnp.asarray(value, dtype=jnp.result_type(float))


FINITE = Range()
POSITIVE = Range(low=0, low_open=True)
NON_NEGATIVE = Range(low=0)
POISSON = Range(-1, 0.5, low_open=True, high_open=True, fix="0.5 is incompressible and not supported")
FRACTION = Range(0, 1, fix="the FLIP fraction: 1 is FLIP, 0 is PIC")
DAMPING = Range(low=0, fix="units 1/time; 0 switches it off")


def as_range(valid) -> Range | None:
    """A :class:`Range` from the short forms a :class:`jaxmpm.Parameter` accepts: a Range, None
    (no check), ``"finite"``, ``"positive"``, ``"non-negative"`` or a closed ``(low, high)``."""
    if valid is None or isinstance(valid, Range):
        return valid
    named = {"finite": FINITE, "positive": POSITIVE, "non-negative": NON_NEGATIVE}
    if isinstance(valid, str) and valid in named:
        return named[valid]
    if isinstance(valid, tuple) and len(valid) == 2:
        return Range(float(valid[0]), float(valid[1]))
    raise InputError(f"Parameter: valid = {valid!r}; use a jaxmpm.core.validate.Range, None, 'finite', 'positive', "
                     "'non-negative' or (low, high)")


def real(owner: str, name: str, value, *, low=None, high=None, low_open: bool = False, high_open: bool = False,
         fix: str | None = None):
    """``value`` as a Python float, finite and within [low, high] (``*_open`` for open ends);
    a traced value is returned unchanged."""
    return Range(low, high, low_open, high_open).real(owner, name, value, fix)


def positive(owner: str, name: str, value, fix: str | None = None):
    """A finite number > 0 as a Python float (traced: unchanged)."""
    return POSITIVE.real(owner, name, value, fix)


def leaf(owner: str, name: str, value, *, low=None, high=None, low_open: bool = False, high_open: bool = False,
         fix: str | None = None):
    """A model's float leaf ``jnp.asarray(value, float)`` with every concrete entry finite and in range."""
    return Range(low, high, low_open, high_open).leaf(owner, name, value, fix)


# --------------------------------------------------------------------------- integers
def one_of(value, choices) -> bool:
    """Whether ``value`` is one of the string ``choices`` (``value in choices`` for an array compares it element
    by element, and the result has no truth value)."""
    return isinstance(value, str) and value in choices


def device_list(owner: str, devices) -> list:
    """``devices`` (an iterable of JAX devices, at least one) as a list; anything else is an InputError."""
    try:
        listed = None if isinstance(devices, (str, bytes)) else list(devices)
    except TypeError:
        listed = None
    if not listed or not all(isinstance(d, jax.Device) for d in listed):
        fail(owner, f"devices = {show(devices)}",
             "give a list of JAX devices, e.g. jax.devices() or jax.devices()[:2], or None (all of them)")
    return listed


def file_path(owner: str, value, fix: str = "give a file's path, a str or pathlib.Path") -> str:
    """``value`` as a path string (``os.fspath``): a str, bytes or path-like object; anything else is an InputError."""
    import os

    if not isinstance(value, (str, bytes, os.PathLike)):
        fail(owner, f"path = {show(value)} is not a path", fix)
    path = os.fspath(value)
    return path.decode() if isinstance(path, bytes) else path


def output_file(owner: str, value, fix: str = "give a file's path, a str or pathlib.Path") -> str:
    """:func:`file_path` of a file to be written: a name that is not empty and not a folder, in a folder that
    exists (an InputError otherwise, before anything is written)."""
    import os

    path = file_path(owner, value, fix)
    if not path.strip():
        raise InputError(f"{owner}: path = {path!r} is empty; {fix}")
    if os.path.isdir(path) or path.endswith(("/", os.sep)):
        raise InputError(f"{owner}: {path} is a folder; give a file in it, e.g. {os.path.join(path, 'run.h5')}")
    folder = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(folder):
        raise InputError(f"{owner}: the folder {folder} does not exist; create it first, or {fix}")
    return path


def input_file(owner: str, value, fix: str = "give a file's path, a str or pathlib.Path") -> str:
    """:func:`file_path` of a file to be read: a folder is an InputError (a missing file is the caller's to
    name, with what it means there)."""
    import os

    path = file_path(owner, value, fix)
    if os.path.isdir(path):
        raise InputError(f"{owner}: {path} is a folder, not a file; {fix}")
    return path


def positive_int(owner: str, name: str, value, *, low: int = 1, fix: str | None = None) -> int:
    """``value`` as a Python int >= ``low`` (1: "a positive integer", 0: "a non-negative integer").
    Integral floats (4.0) are accepted; 2.5, True/False, nan, inf, strings and traced values are
    not (an integer here fixes an array shape or a loop length: it must be concrete)."""
    what = "a positive integer" if low == 1 else "a non-negative integer" if low == 0 else f"an integer >= {low}"
    bad = _is_string_like(value) or traced(value)
    number = None
    if not bad:
        if isinstance(value, numbers.Integral):
            number = int(value)
        else:
            try:
                arr = np.asarray(value)
            except Exception:
                arr = np.asarray(None)
            if arr.ndim == 0 and arr.dtype.kind in "iuf":
                f = float(arr)
                if math.isfinite(f) and f == int(f):
                    number = int(f)
    if number is None or number < low:
        fail(owner, f"{name} = {show(value)} must be {what}", fix)
    return number


# --------------------------------------------------------------------------- vectors
def ndim(value) -> int:
    """``np.ndim(value)``, or 1 for a ragged sequence NumPy cannot make an array of."""
    try:
        return np.ndim(value)
    except (ValueError, TypeError):
        return 1


def sequence(owner: str, name: str, value) -> tuple:
    """``value`` as a tuple: a number gives a 1-tuple; a string or a non-iterable is an error."""
    if isinstance(value, (numbers.Number, np.generic)) and not isinstance(value, (bool, np.bool_)):
        return (value,)
    if isinstance(value, (np.ndarray, jax.Array)) and not traced(value) and np.ndim(value) == 0:
        return (value,)
    if _is_string_like(value):
        fail(owner, f"{name} must be a number or a sequence of numbers, got {show(value)}")
    try:
        return tuple(value)
    except TypeError:
        fail(owner, f"{name} must be a number or a sequence of numbers, got {show(value)}")


def finite_vector(owner: str, name: str, value, dim: int | None = None, *, broadcast: bool = True,
                  valid: Range = FINITE, context: str | None = None, fix: str | None = None):
    """A point, velocity or corner: a tuple of Python floats, each finite and in ``valid``, with
    ``dim`` components (``broadcast``: one number stands for every axis; ``context`` says where
    ``dim`` comes from, default "the grid is {dim}D").  Traced: unchanged."""
    if traced(value):
        return value
    items = sequence(owner, name, value)
    if dim is not None:
        if len(items) == 1 and broadcast:
            items = items * dim
        if len(items) != dim:
            one = " (or one number for every axis)" if broadcast else ""
            plural = "s" if len(items) != 1 else ""
            where = context or f"the grid is {dim}D"
            fail(owner, f"{name} = {show(value)} has {len(items)} component{plural} but {where}; give {dim}{one}", fix)
    out = []
    for i, v in enumerate(items):
        label = f"{name}[{i}]" if len(items) > 1 or ndim(value) > 0 else name
        if ndim(v) != 0 and not _is_string_like(v):
            fail(owner, f"{name} must be a flat sequence of numbers, got {show(value)}", fix)
        out.append(valid.real(owner, label, v, fix))
    return tuple(out)


def batch_members(owner: str, name: str, batch, check) -> None:
    """Call ``check(index, member)`` for every member of a concrete batch (its leading axis;
    ``index`` None for a 0-d value); a traced batch passes."""
    if traced(batch):
        return
    arr = _numeric_array(owner, name, batch, None, what="an array of numbers (one per batch member)")
    if arr.ndim == 0:
        check(None, batch)
        return
    for i in range(arr.shape[0]):
        check(i, arr[i])
