"""Warnings attributed to the user's line.

``warnings.warn(..., stacklevel=k)`` names the k-th caller, but a jaxmpm warning can be raised
under a varying depth of jaxmpm, equinox (``Module.__init__`` and its checks) and JAX frames, so a
fixed ``k`` points at an equinox or JAX file.  :func:`warn` walks the stack instead and attributes
the warning to the first frame outside those packages (Python 3.12's ``skip_file_prefixes`` does
the same; 3.10 and 3.11 lack it).
"""

from __future__ import annotations

import os
import sys
import warnings


def _package_dir(module) -> str | None:
    path = getattr(module, "__file__", None)
    return None if path is None else os.path.dirname(os.path.abspath(path)) + os.sep


def _internal_prefixes() -> tuple[str, ...]:
    """Directories whose frames are not the user's: jaxmpm, equinox, jax (and jaxlib, jaxtyping)."""
    prefixes = [os.path.dirname(os.path.dirname(os.path.abspath(__file__))) + os.sep]  # the jaxmpm package
    for name in ("equinox", "jax", "jaxlib", "jaxtyping"):
        module = sys.modules.get(name)
        where = _package_dir(module) if module is not None else None
        if where is not None:
            prefixes.append(where)
    return tuple(prefixes)


def _is_internal(filename: str, prefixes: tuple[str, ...]) -> bool:
    return os.path.abspath(filename).startswith(prefixes)


def _is_importlib(frame) -> bool:
    """The frames ``warnings`` itself skips when counting a stacklevel (CPython's _is_internal_frame)."""
    filename = frame.f_code.co_filename
    return "importlib" in filename and "_bootstrap" in filename


def user_stacklevel() -> int:
    """The ``stacklevel`` that makes ``warnings.warn``, called by this function's caller, name the
    first frame outside jaxmpm, equinox and JAX (the outermost frame if there is none)."""
    prefixes = _internal_prefixes()
    frame = sys._getframe(1)  # the caller: what warnings.warn(..., stacklevel=1) would name
    level = 1
    while _is_internal(frame.f_code.co_filename, prefixes):
        outer = frame.f_back
        while outer is not None and _is_importlib(outer):  # counted as warnings counts them
            outer = outer.f_back
        if outer is None:
            break
        frame, level = outer, level + 1
    return level


def warn(message, category: type[Warning] = UserWarning) -> None:
    """``warnings.warn(message, category)`` attributed to the user's line: the first stack frame
    outside the jaxmpm package, equinox and JAX."""
    warnings.warn(message, category, stacklevel=user_stacklevel())
