"""A griffe extension for the API reference (mkdocs.yml): the docstrings as written for ``help()``
turned into what mkdocstrings renders well.

* Sphinx roles (``:class:`jaxmpm.Grid```, ``:func:`~jaxmpm.fill```) become links to the public
  object's entry when they name one (``jaxmpm.NAME`` or a bare ``NAME`` of ``jaxmpm.__all__``),
  else inline code: Markdown has no roles, and mkdocstrings would print them as written.
* The ``__init__`` docstrings :func:`jaxmpm.core.docstrings.document_init` copies from the class
  docstring are dropped: ``merge_init_into_class`` would render the parameters a second time (and
  so is the "Initialize self" of an undocumented generated ``__init__``).
* Base classes are named as the reader imports them (``jaxmpm.Region``, ``equinox.Module``), not
  by their defining module's path.
* A class attribute that only has its value's type's docstring (an equinox field's default,
  ``axisymmetric = False``, would show ``bool``'s) loses it, so it is not listed.
"""

from __future__ import annotations

import inspect
import re
import sys

import griffe

import jaxmpm

COPIED = re.compile(r"^The parameters of \w+ \(help\(\w+\) has the whole docstring\)\.")
ROLE = re.compile(r":(?:py:)?(?:class|func|meth|attr|data|mod|exc|obj):`(~?)([\w.]+)(?:\(\))?`")
# what an equinox module's generated __init__ says when nothing documents it
GENERATED = inspect.getdoc(object.__init__)


def anchor(name: str) -> str:
    """The identifier of a public object's entry: ``jaxmpm.NAME``, or the object's own path where
    ``jaxmpm.NAME`` is also a submodule (docs/api renders ``::: jaxmpm.resume.resume``)."""
    if f"jaxmpm.{name}" in sys.modules:
        obj = getattr(jaxmpm, name)
        return f"{obj.__module__}.{obj.__qualname__}"
    return f"jaxmpm.{name}"


ANCHORS = {name: anchor(name) for name in jaxmpm.__all__}


def reference(match: re.Match) -> str:
    """A role as Markdown: a cross-reference to a public object's entry, or inline code."""
    short, target = match.group(1) == "~", match.group(2)
    text = f"`{target.rsplit('.', 1)[-1] if short else target}`"
    name = target.removeprefix("jaxmpm.")
    if name in ANCHORS:
        return f"[{text}][{ANCHORS[name]}]"
    return text


def public_base(path: str) -> str:
    """A base class as the reader imports it: ``jaxmpm.Region`` for
    ``jaxmpm.core.particles.Region``, ``equinox.Module`` for equinox's private path."""
    name = path.rsplit(".", 1)[-1]
    if path.startswith("jaxmpm.") and name in ANCHORS and getattr(jaxmpm, name).__module__ + "." + name == path:
        return f"jaxmpm.{name}"
    return {"equinox._module._module.Module": "equinox.Module"}.get(path, path)


class JaxmpmDocstrings(griffe.Extension):
    """The rewrites of the module docstring, on every object as it is loaded."""

    def on_class_instance(self, *, cls: griffe.Class, **kwargs) -> None:
        cls.bases = [public_base(base) if isinstance(base, str) else base for base in cls.bases]

    def on_instance(self, *, node, obj: griffe.Object, **kwargs) -> None:
        docstring = obj.docstring
        if docstring is None:
            return
        if obj.is_function and obj.name == "__init__" and (COPIED.match(docstring.value)
                                                            or docstring.value == GENERATED):
            obj.docstring = None
        elif obj.is_attribute and isinstance(node, griffe.ObjectNode) and \
                docstring.value == inspect.getdoc(type(node.obj)):
            obj.docstring = None
        else:
            docstring.value = ROLE.sub(reference, docstring.value)
