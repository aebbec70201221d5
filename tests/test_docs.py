"""The API reference (mkdocs.yml, docs/api/*.md): every public object has a page and documents its
parameters, and the site builds with ``mkdocs build --strict``."""

import importlib.util
import inspect
import os
import pathlib
import re
import subprocess
import sys

import pytest

import jaxmpm as jm
from jaxmpm.core.docstrings import INIT_SUMMARY, args_section

ROOT = pathlib.Path(__file__).resolve().parents[1]
DIRECTIVE = re.compile(r"^::: (jaxmpm(?:\.\w+)+)\s*$", re.M)
# a Google-style entry: "name: description" or "name (type): description" (``*args``, ``**kwargs`` too)
ENTRY = re.compile(r"^(\*{0,2}\w+)(?: \([^)]*\))?: \S")


def public_callables():
    """(name, object) for every class and function of ``jaxmpm.__all__``."""
    return [(name, getattr(jm, name)) for name in jm.__all__
            if inspect.isclass(getattr(jm, name)) or inspect.isfunction(getattr(jm, name))]


def signature_parameters(obj) -> list:
    """The names a call of ``obj`` takes, less ``self``, ``*args``, ``**kwargs`` and private ones
    (``_cli``); a class's are its constructor's (an equinox module's: its init fields)."""
    try:
        signature = inspect.signature(obj)
    except (TypeError, ValueError):  # a built-in constructor (an exception class): nothing to name
        return []
    return [p.name for p in signature.parameters.values()
            if p.name != "self" and not p.name.startswith("_") and p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD)]


def documented_parameters(doc: str | None):
    """The names the ``Args:`` section of a docstring documents (None without one), and the lines
    at its entries' indentation that are not ``name: description`` entries."""
    section = args_section(doc)
    if section is None:
        return None, []
    lines = [line for line in section.splitlines()[1:] if line.strip()]
    indent = min(len(line) - len(line.lstrip()) for line in lines)
    entries = [line.strip() for line in lines if len(line) - len(line.lstrip()) == indent]
    names = [m.group(1) for m in map(ENTRY.match, entries) if m]
    return names, [e for e in entries if not ENTRY.match(e)]


def resolve(path: str):
    """The object a ``::: path`` directive renders: the longest importable module prefix, then attributes."""
    parts = path.split(".")
    for cut in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:cut]))
        except ImportError:
            continue
        for part in parts[cut:]:
            obj = getattr(obj, part)
        return obj
    raise ImportError(path)


def test_every_public_object_has_a_page():
    """docs/api names each object of ``jaxmpm.__all__`` once, and nothing else: ``::: jaxmpm.NAME``,
    or the object's own path where ``jaxmpm.NAME`` is also a submodule (``jaxmpm.resume.resume``)."""
    pages = sorted((ROOT / "docs" / "api").glob("*.md"))
    paths = [path for page in pages for path in DIRECTIVE.findall(page.read_text())]
    named = [path.rsplit(".", 1)[1] for path in paths]
    wrong = [path for path, name in zip(paths, named) if name in jm.__all__ and resolve(path) is not getattr(jm, name)]
    assert not wrong, f"directives that render another object than jaxmpm.NAME: {wrong}"
    missing = sorted(set(jm.__all__) - set(named))
    assert not missing, f"public objects without a `::: jaxmpm.NAME` in docs/api/*.md: {missing}"
    unknown = sorted(set(named) - set(jm.__all__))
    assert not unknown, f"docs/api/*.md document names that are not in jaxmpm.__all__: {unknown}"
    twice = sorted({name for name in named if named.count(name) > 1})
    assert not twice, f"documented on two pages (one anchor each): {twice}"


def test_every_public_callable_documents_its_parameters():
    """Each public class and function has an ``Args:`` section with one entry per parameter of its
    signature (for a class: its constructor's), and no entry for a parameter it does not take."""
    problems = []
    for name, obj in public_callables():
        parameters = signature_parameters(obj)
        documented, malformed = documented_parameters(obj.__doc__)  # the object's own, not a base class's
        if documented is None:
            if parameters:
                problems.append(f"{name}: no Args: section for {parameters}")
            continue
        missing = [p for p in parameters if p not in documented]
        extra = [p for p in documented if p not in parameters and not p.startswith("*")]
        if missing or extra or malformed:
            problems.append(f"{name}: undocumented {missing}, not parameters {extra}, malformed entries {malformed}")
    assert not problems, "\n".join(problems)


def test_help_shows_the_constructor_parameters():
    """An equinox module's generated ``__init__`` (and a hand-written one without a docstring) carries
    the Args section of its class docstring, so help(jm.X.__init__) and call tips list the parameters."""
    for cls in (jm.Simulation, jm.Grid, jm.Particles, jm.XPIC):
        doc = cls.__init__.__doc__
        assert doc.startswith(INIT_SUMMARY.format(name=cls.__name__)), cls
        assert args_section(doc) == args_section(cls.__doc__), cls
    assert "kinematics:" in jm.Simulation.__init__.__doc__
    assert jm.Disk.__init__ is jm.Ball.__init__  # inherited: documented once, by Ball


@pytest.mark.slow
@pytest.mark.skipif(any(importlib.util.find_spec(tool) is None for tool in ("mkdocs", "mkdocstrings", "material")),
                    reason="the docs tools are not installed (pip install -e '.[docs]')")
def test_the_api_reference_builds(tmp_path):
    """``mkdocs build --strict``: a broken ``::: jaxmpm.X``, a docstring entry naming no parameter of
    its signature or an unresolved cross-reference fails the build."""
    site = tmp_path / "site"
    done = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(site)], cwd=ROOT,
                          capture_output=True, text=True, timeout=600,
                          env={**os.environ, "NO_MKDOCS_2_WARNING": "1", "JAX_PLATFORMS": "cpu"})
    assert done.returncode == 0, done.stdout[-4000:] + done.stderr[-4000:]
    page = (site / "api" / "simulation" / "index.html").read_text()
    assert 'id="jaxmpm.Simulation"' in page and "kinematics" in page


def test_running_md_names_every_command_line_option():
    """docs/running.md is the command line's full reference (README, "Documentation"): every option of every
    subcommand appears in it, spelled as the parser takes it."""
    from jaxmpm.cli import _subparser, build_parser

    text = (ROOT / "docs" / "running.md").read_text()
    parser = build_parser()
    missing = []
    for command in ("run", "resume", "plot", "animate", "scenes"):
        for action in _subparser(parser, command)._actions:
            for option in action.option_strings:
                if option.startswith("--") and option != "--help" and not re.search(re.escape(option) + r"\b", text):
                    missing.append(f"{command} {option}")
    assert not missing, f"docs/running.md does not name: {', '.join(missing)}"
