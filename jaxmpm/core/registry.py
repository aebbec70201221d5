"""One registry for the parts of a model: schemes, shapes, materials and physics terms.

Each registration gives a part its name, its parser (the command-line form, e.g. ``xpic:5``) and
its float parameters.  Everything that needs to know the parts reads the registry: the CLI's
choices and help, :func:`scheme_from_name` / :func:`shape_from_name`, :func:`jaxmpm.set_params`
and :data:`jaxmpm.PARAMETERS`, the calibration bounds, the HDF5 attributes and the error messages.
Adding a scheme is one class and one call::

    class MyPIC(jm.Scheme): ...
    jm.register_scheme("mypic", MyPIC, parse=lambda arg, beta: MyPIC(),
                       parameters=[jm.Parameter("beta", lambda s: s.beta, "FLIP fraction", (0.0, 1.0))])
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable

from .errors import check
from .validate import as_range


@dataclasses.dataclass(frozen=True)
class Parameter:
    """A float parameter of a registered part (``register_scheme(..., parameters=[...])``).
    ``bounds`` and ``valid`` differ where calibration needs an open interval inside a closed valid
    one (beta: bounds (0, 1) for the logit transform, valid [0, 1]; damping: bounds "positive",
    valid >= 0).

    Args:
        name: the keyword of :func:`jaxmpm.set_params`, an identifier; scoped by its part
            (``"contact.friction"``) where two parts of a model share it.
        get: ``get(part) -> leaf``: the array leaf of the part it names (``lambda s: s.beta``).
        doc: a one-line description (the CLI's help, :data:`jaxmpm.PARAMETERS`).
        bounds: the calibration bounds: None (unbounded, the default), ``"positive"`` or
            ``(lower, upper)``.
        valid: the range :func:`jaxmpm.set_params` and :func:`jaxmpm.ensemble` check concrete
            values against: a ``jaxmpm.core.validate.Range``, ``"finite"`` (the default),
            ``"positive"``, ``"non-negative"``, a closed ``(lower, upper)`` or None (no check).
        acts: ``acts(part) -> None | str``: None where the parameter acts in that part, else why
            not (e.g. a contact's friction under a law other than Coulomb's: ``"acts only under
            law='coulomb'; ..."``).  :func:`jaxmpm.set_params` and :func:`jaxmpm.ensemble` refuse to
            set a parameter that does not act, traced values too: its gradient would be exactly 0
            and an ensemble's members equal.  None (the default): it always acts.
        through_init: True where the parameter acts only through :meth:`jaxmpm.Simulation.init`
            (a material's density: the particles' masses), not in the step: :func:`jaxmpm.ensemble`,
            whose members share one initial state unless ``states=`` gives their own, refuses it.
    """

    name: str
    get: Callable[[Any], Any]
    doc: str
    bounds: Any = None
    valid: Any = "finite"
    acts: Callable[[Any], Any] | None = None
    through_init: bool = False

    def __post_init__(self):
        object.__setattr__(self, "valid", as_range(self.valid))

    def check(self, owner: str, value, label: str | None = None) -> None:
        """Raise InputError unless a concrete ``value`` lies in :attr:`valid` (traced: passes)."""
        if self.valid is not None:
            self.valid.check(owner, label or self.name, value)


@dataclasses.dataclass(frozen=True)
class Entry:
    name: str
    cls: type
    parse: Callable | None  # parse(argument after ':', **options) -> part; None: cls(**options)
    spec: str  # the command-line form, e.g. "xpic:M"; without ':' the part takes no argument
    doc: str
    parameters: tuple


class Registry:
    """Registered parts of one kind.  ``owner(sim)`` is where a model holds its part of this kind
    (``sim.scheme``); for terms, ``owner(sim, cls)`` finds the term of that class."""

    def __init__(self, kind: str, owner: Callable):
        self.kind = kind
        self.owner = owner
        self.base: type | None = None  # the class every registered part derives from (set where it is defined)
        self._entries: dict[str, Entry] = {}
        # the entries of classes replaced under their name (a notebook cell run again): a model made with
        # the old class keeps its name and parameters (set_params, get_params, the HDF5 attributes)
        self._replaced: dict[type, Entry] = {}

    def register(self, name: str, cls: type, *, parse: Callable | None = None, spec: str | None = None,
                 parameters=(), doc: str = "", replace: bool = False) -> type:
        check(isinstance(name, str) and name and name == name.lower() and ":" not in name,
              f"register_{self.kind}: name = {name!r} must be a lower-case word without ':'")
        check(isinstance(cls, type), f"register_{self.kind}: {cls!r} is not a class")
        check(self.base is None or issubclass(cls, self.base),
              f"register_{self.kind}: {cls.__qualname__} is not a subclass of jm.{getattr(self.base, '__name__', '')}; "
              f"derive it from jm.{getattr(self.base, '__name__', '')} (docs/extending.md)")
        check(isinstance(replace, bool), f"register_{self.kind}: replace = {replace!r} must be True or False")
        if name in self._entries and not replace:
            taken = self._entries[name].cls
            check(redefinition(taken, cls),
                  f"register_{self.kind}: the name {name!r} is taken by {_qualified(taken)}; choose another "
                  f"name, or pass replace=True to replace it")
        for p in parameters:
            check(isinstance(p, Parameter), f"register_{self.kind}: parameters must be jm.Parameter, got {p!r}")
            check(isinstance(p.name, str) and p.name.isidentifier(),
                  f"register_{self.kind}: parameter name {p.name!r} must be an identifier (it is a keyword)")
        old = self._entries.get(name)
        if old is not None and old.cls is not cls:
            self._replaced[old.cls] = old
        self._entries[name] = Entry(name, cls, parse, spec or name, doc or (cls.__doc__ or "").strip().split("\n")[0],
                                    tuple(parameters))
        self._replaced.pop(cls, None)
        return cls

    def _known(self):
        """The entries, then those of replaced classes."""
        return (*self._entries.values(), *self._replaced.values())

    # ------------------------------------------------------------------ lookup
    def names(self) -> tuple:
        return tuple(self._entries)

    def specs(self) -> str:
        """The command-line forms, e.g. ``flip | pic | blend:B | xpic:M``."""
        return " | ".join(e.spec for e in self._entries.values())

    def __contains__(self, name) -> bool:
        return name in self._entries

    def __getitem__(self, name: str) -> Entry:
        check(name in self._entries, f"unknown {self.kind} {name!r}; choose one of {', '.join(self._entries)}")
        return self._entries[name]

    def entry_of(self, part) -> Entry | None:
        """The entry of ``part``'s class, or of its nearest registered base class."""
        for cls in type(part).__mro__:
            for e in self._known():
                if e.cls is cls:
                    return e
        return None

    def name_of(self, part) -> str:
        e = self.entry_of(part)
        return e.name if e is not None else type(part).__name__

    def parse(self, spec: str, **options):
        """A part from its command-line form ``name[:argument]``."""
        check(isinstance(spec, str) and spec.strip(), f"{self.kind} {spec!r}: give one of {self.specs()}")
        name, _, arg = spec.strip().partition(":")
        name = name.lower()
        check(name in self._entries, f"unknown {self.kind} {spec!r}; choose {self.specs()}")
        entry = self._entries[name]
        check(not arg or ":" in entry.spec, f"{self.kind} {spec!r}: {name} takes no ':' argument")
        if entry.parse is None:
            return entry.cls(**options)
        return entry.parse(arg, **options)

    def parameters_of(self, part) -> tuple:
        """The registered parameters of ``part`` (of its class and its registered base classes)."""
        out, seen = [], set()
        for cls in type(part).__mro__:
            for e in self._known():
                if e.cls is cls:
                    for p in e.parameters:
                        if p.name not in seen:
                            seen.add(p.name)
                            out.append(p)
        return tuple(out)

    def all_parameters(self) -> dict:
        """{name: Parameter} over every registered part of this kind."""
        return {p.name: p for e in self._entries.values() for p in e.parameters}


def _qualified(cls: type) -> str:
    return f"{cls.__module__}.{cls.__qualname__}"


def redefinition(taken, new) -> bool:
    """Whether registering ``new`` (a class, or a scene's builder) under ``taken``'s name may
    replace it without ``replace=True``: the same object, or a user's class or function of the same
    name in the same module defined anew (a notebook cell run again, a script re-executed; two
    packages' classes of one name are refused).  A built-in part (``jaxmpm.*``) is replaced only on
    request."""
    taken = getattr(taken, "__wrapped__", taken)  # a scene's builder, as jm.register_scene wraps it
    if new is taken:
        return True
    module = getattr(taken, "__module__", None) or ""
    return (not module.startswith("jaxmpm.") and module == getattr(new, "__module__", None)
            and getattr(taken, "__qualname__", None) == getattr(new, "__qualname__", 0))


def _term_of(sim, cls):
    for term in sim.terms:
        if isinstance(term, cls):
            return term
    return None


SCHEMES = Registry("scheme", lambda sim, cls=None: sim.scheme)
SHAPES = Registry("shape", lambda sim, cls=None: sim.shape)
MATERIALS = Registry("material", lambda sim, cls=None: sim.material)
TERMS = Registry("term", _term_of)
REGISTRIES = {"scheme": SCHEMES, "shape": SHAPES, "material": MATERIALS, "term": TERMS}


def register_scheme(name, cls, **kwargs):
    """Register a particle-update scheme: the CLI, :func:`scheme_from_name`, :func:`jaxmpm.set_params`
    and the HDF5 attributes then know it (docs/extending.md).

    Args:
        name: the scheme's name, a lower-case word without ':' (the CLI's ``--scheme name``).
        cls: the :class:`jaxmpm.Scheme` subclass.
        **kwargs: ``parse`` (``parse(argument, beta=...) -> scheme`` of the command-line form
            ``name:argument``; None: ``cls(beta=...)``), ``spec`` (that form as the help shows it,
            e.g. ``"xpic:M"``; default ``name``), ``parameters`` (the :class:`Parameter` of its
            float leaves) and ``doc`` (one line; default the first line of the class docstring).

    Returns:
        ``cls``.
    """
    return SCHEMES.register(name, cls, **kwargs)


def register_shape(name, cls, **kwargs):
    """Register a shape function (``Simulation(shape="name")``, the CLI's ``--shape``).

    Args:
        name: the shape's name, a lower-case word without ':'.
        cls: the :class:`jaxmpm.ShapeFunction` subclass.
        **kwargs: ``parse``, ``spec``, ``parameters``, ``doc`` and ``replace``, as for
            :func:`register_scheme`
            (``parse(argument, **options)``; None: ``cls(**options)``).

    Returns:
        ``cls``.
    """
    return SHAPES.register(name, cls, **kwargs)


def register_material(name, cls, **kwargs):
    """Register a material (the CLI's ``--material``, :func:`jaxmpm.set_params` of its constants).

    Args:
        name: the material's name, a lower-case word without ':'.
        cls: the :class:`jaxmpm.Material` subclass.
        **kwargs: ``parse``, ``spec``, ``parameters`` (e.g. E, nu, density), ``doc`` and ``replace``, as
            for :func:`register_scheme`.

    Returns:
        ``cls``.
    """
    return MATERIALS.register(name, cls, **kwargs)


def register_term(name, cls, **kwargs):
    """Register a physics term; its parameters are then scoped by ``name`` (``"damping.alpha_g"``).

    Args:
        name: the term's name, a lower-case word without ':'.
        cls: the :class:`jaxmpm.Term` subclass.
        **kwargs: ``parse``, ``spec``, ``parameters``, ``doc`` and ``replace``, as for
            :func:`register_scheme`.

    Returns:
        ``cls``.
    """
    return TERMS.register(name, cls, **kwargs)


def scheme_from_name(spec: str, beta: float | None = None):
    """A scheme from its command-line form (``flip``, ``xpic:5``, ...; :data:`SCHEMES`).

    Args:
        spec: ``name`` or ``name:argument``: flip, pic, blend:B, xpic:M, fmpm:K, apic, tpic, rpic
            (``SCHEMES.specs()`` lists the registered ones).
        beta: the FLIP fraction in [0, 1] for the schemes that take one; None (the default):
            the scheme's own (flip 1, blend 0.99, xpic and fmpm 0); pic, apic, tpic and rpic take none.
    """
    return SCHEMES.parse(spec, beta=beta)


def shape_from_name(spec: str, **kwargs):
    """A shape function from its name (``linear``, ``ugimp``, ``quadratic``, ``cubic``).

    Args:
        spec: the registered name (``SHAPES.names()``), with ``:argument`` where the shape
            takes one.
        **kwargs: the shape's options, e.g. ``ppc=2`` for ``ugimp``.
    """
    return SHAPES.parse(spec, **kwargs)


def parts_of(sim):
    """(registry, part) for every part of a model: its scheme, shape, material and terms."""
    out = [(SCHEMES, sim.scheme), (SHAPES, sim.shape), (MATERIALS, sim.material)]
    out += [(TERMS, term) for term in sim.terms]
    return out


def scope_of(reg, part) -> str:
    """The scope of a part's parameters: "scheme", "shape", "material", or a term's registered
    name ("damping", "contact", "heat", ...)."""
    return reg.name_of(part) if reg is TERMS else reg.kind


def scoped_parameters(sim) -> dict:
    """{"scope.name": (where(sim) -> leaf, Parameter)} for every parameter of the parts of ``sim``."""
    out = {}
    for reg, part in parts_of(sim):
        cls = type(part)
        for p in reg.parameters_of(part):
            out[f"{scope_of(reg, part)}.{p.name}"] = (lambda s, p=p, reg=reg, cls=cls: p.get(reg.owner(s, cls)), p)
    return out


def sim_parameters(sim) -> dict:
    """{name: (where(sim) -> leaf, Parameter)} for the parameters the parts of ``sim`` have, by
    the name they are set by: the bare name (``beta``, ``E``, ``friction``) where one part of the
    model has it, else the scoped name (``material.friction``, ``contact.friction``)."""
    scoped = scoped_parameters(sim)
    counts = {}
    for key in scoped:
        counts[key.split(".", 1)[1]] = counts.get(key.split(".", 1)[1], 0) + 1
    return {(key.split(".", 1)[1] if counts[key.split(".", 1)[1]] == 1 else key): value
            for key, value in scoped.items()}


def resolve_parameter(sim, name: str):
    """(where(sim) -> leaf, Parameter) of ``name`` in ``sim``: a scoped name "scope.name" or a bare
    name that one part of the model has.  None if the model has no such parameter; an ambiguous
    bare name raises, naming the scoped ones."""
    scoped = scoped_parameters(sim)
    if name in scoped:
        return scoped[name]
    matches = [key for key in scoped if key.split(".", 1)[1] == name]
    check(len(matches) <= 1, f"parameter {name!r} belongs to several parts of this model; name one: "
                             f"{', '.join(matches)}")
    return scoped[matches[0]] if matches else None


def parameter_part(sim, name: str):
    """The part of ``sim`` (scheme, material, shape or term) that owns the parameter ``name`` as
    :func:`resolve_parameter` finds it, or None."""
    bare = name.rsplit(".", 1)[-1]
    found = []
    for reg, part in parts_of(sim):
        for p in reg.parameters_of(part):
            if f"{scope_of(reg, part)}.{p.name}" == name:
                return part
            if p.name == bare and "." not in name:
                found.append(part)
    return found[0] if len(found) == 1 else None


def all_parameters() -> dict:
    """{name: Parameter} over every registered part, by bare name (the first registration of a
    name shared by parts of different kinds) and by scoped name ("kind.name", terms by their
    registered name)."""
    out = {}
    for reg in REGISTRIES.values():
        for e in reg._entries.values():
            for p in e.parameters:
                out.setdefault(p.name, p)
                out[f"{e.name if reg is TERMS else reg.kind}.{p.name}"] = p
    return out


def owner_registry(name: str):
    """(registry, Parameter, classes) of a registered parameter name (bare or scoped), or None."""
    scope, _, bare = name.rpartition(".")
    for reg in REGISTRIES.values():
        classes = [e.cls for e in reg._entries.values() if any(p.name == bare for p in e.parameters)
                   and (not scope or scope == (e.name if reg is TERMS else reg.kind))]
        if classes:
            p = next(q for e in reg._entries.values() if e.cls is classes[0] for q in e.parameters if q.name == bare)
            return reg, p, classes
    return None
