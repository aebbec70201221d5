"""``Simulation``: the static model -- grid, shape function, material, scheme, physics terms,
velocity conditions -- as one equinox module with ``init`` and ``step``.  Running it (``run``,
``rollout``, checkpointing, chunked HDF5 writing, progress, instability detection) is the
driver's job (``jaxmpm.run.driver``); ``sim.run`` and ``sim.rollout`` call it."""

from __future__ import annotations

import copy
import dataclasses
from typing import Callable, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..core import measures as diag
from ..core.device import to_device
from ..core.errors import check
from ..core.grid import Grid
from ..core.limits import require_memory
from ..core.linalg import det, identities
from ..core.particles import Particles
from ..core.registry import MATERIALS, SCHEMES, SHAPES, scheme_from_name, shape_from_name
from ..core.state import State
from ..core.validate import FINITE, POSITIVE, compiled_when_concrete, concrete, one_of, show, traced
from ..core.warn import warn
from ..materials.base import Material
from ..physics.body_force import BodyForce
from ..physics.conditions import CONSTRAINED_FORCES, as_conditions, build_constraint
from ..physics.damping import Damping
from ..physics.stress import StressDivergence
from ..physics.term import Term, overrides
from ..run.driver import History, StableTimeStepWarning, rollout, run  # noqa: F401  (re-exported)
from ..run.memory import members_at_once, step_memory
from ..run.sorting import Sorting
from ..schemes.base import Scheme
from ..transfer.backend import (
    ADJOINTS,
    KERNEL_CHOICES,
    POLICIES,
    choose_chunking,
    choose_derivative_chunking,
    choose_devices,
    choose_kernel,
    choose_sorting,
    chunks_to_fit,
    resolve,
    use_adjoint,
    use_kernel,
    use_policy,
    xla_layout,
)
from ..transfer.kernels.windowed import active_window, on_window
from ..transfer.shapes import UGIMP, ShapeFunction, field_stencil
from . import frame_fields
from .chunks import chunk_obstacle, num_chunks, step_in_chunks, sums_in_chunks
from .devices import device_obstacle, local_devices, step_on_devices
from .step import folds_force
from .step import step as _step

UPDATES = {"USF": "USF", "USL": "USL", "USL-": "USL", "MUSL": "MUSL", "USL+": "MUSL",
           "USAVG-": "USAVG-", "USAVG+": "USAVG+", "usavg-": "USAVG-", "usavg+": "USAVG+"}  # 003 §2.2
# the deformation-gradient increment dF (jaxmpm.model.step.deformation_increment)
KINEMATICS = ("linear", "exponential")
# whose rules the step follows where MPM codes differ (``conventions``): each preset is a set of options
# -- the constrained nodes' force (CONSTRAINED_FORCES) and the scheme's (Scheme.in_conventions)
CONVENTIONS = {"jaxmpm": {"constrained_force": "zero"}, "nairnmpm": {"constrained_force": "reaction"}}


def resolve_conventions(conventions: str, constrained_force: str | None) -> str:
    """The constrained nodes' force of ``conventions`` (:data:`CONVENTIONS`), or ``constrained_force``
    when given; both checked."""
    check(conventions in CONVENTIONS, f"Simulation: conventions = {conventions!r}; choose 'jaxmpm' (the default) "
                                      "or 'nairnmpm' (NairnMPM 19.0's rules where the codes differ)")
    if constrained_force is None:
        constrained_force = CONVENTIONS[conventions]["constrained_force"]
    check(constrained_force in CONSTRAINED_FORCES,
          f"Simulation: constrained_force = {constrained_force!r}; choose 'zero' (v = g, a = 0 on constrained "
          "nodes) or 'reaction' (v = p/m and the reaction force, NairnMPM's rule)")
    return constrained_force


def state_positions(particles: Particles):
    """The positions in the state's precision, by one rule: the precision of ``particles.x``
    (integer positions take the default float: float64 under ``jax_enable_x64``, else float32);
    velocities, volumes and masses are cast to it, with a UserWarning when that narrows one of
    them (float64 velocities with float32 positions run in float32)."""
    x = jnp.asarray(particles.x)
    if not jnp.issubdtype(x.dtype, jnp.floating):
        x = x.astype(jnp.result_type(float))
    for name in ("v", "volume", "mass"):
        value = getattr(particles, name)
        if value is None:
            continue
        dtype = jnp.asarray(value).dtype
        if jnp.issubdtype(dtype, jnp.floating) and jnp.finfo(dtype).bits > jnp.finfo(x.dtype).bits:
            warn(f"Simulation.init: particles.{name} is {dtype} but the positions are {x.dtype}; the run follows "
                 f"the positions' precision and casts {name} to {x.dtype}. Give x as {dtype} for a {dtype} run.",
                 UserWarning)
    return x


class Simulation(eqx.Module):
    """An MPM model.  Float parameters (material constants, beta, damping, gravity, prescribed
    velocities) are array leaves, so ``jax.grad``/``jax.vmap`` reach them; everything that fixes
    shapes or loop lengths is static.

    ``terms`` holds the physics terms of the step in order: the stress divergence, the body
    force (``gravity``, ``body_force``), damping (unless ``damping=False``), then any ``terms=``
    given.  ``backend`` picks the fusion policy ("auto", "cpu", "gpu"; see ``jaxmpm.transfer.backend``):
    it changes speed, never results.  ``kinematics`` is the strain increment: "linear" (default,
    dF = I + grad v dt) or "exponential" (dF = exp(grad v dt), 001 eq. 26).  ``adjoint`` picks the
    derivative rules of reverse mode: "structured" (default; the transfer layer's own rules, whose
    transposes are the cheap adjoint operations) or "autodiff" (JAX differentiates the forward code
    as written, the reference); it too changes speed, never results (``jaxmpm.transfer.backend``).
    ``kernel`` picks the transfer kernel: "auto" (default; the table of ``jaxmpm.transfer.backend``
    by backend, dimension, particles per cell and dtype; :func:`backend_info` says which and why),
    "xla" or "pallas" (fused Pallas kernels; on the CPU in interpret mode, for checking): speed only.

    ``conventions`` picks whose rules the step follows where MPM codes differ: "jaxmpm" (default)
    or "nairnmpm", NairnMPM 19.0's (J. A. Nairn's code, the seeds' reference implementation):
    the reaction force on constrained nodes (``constrained_force="reaction"``), XPIC's series start
    (``XPIC(boundary="unconstrained_start")``), the XPIC/PIC position update
    (``position="PV_tilde"``), the grid damping's velocity (``damping_velocity="updated"``) and
    contact's gradients, separation update and series (``jm.Contact(gradient="volume",
    separation_update="extrapolated", series="incremental")``); the scheme and terms given are
    returned in those options (:meth:`jaxmpm.Scheme.in_conventions`, ``Term.in_conventions``;
    docs/nairnmpm.md).  ``constrained_force`` alone: "zero" (v = g, a = 0 on
    constrained components) or "reaction" (v = p/m, the force the reaction m (g - p/m)/dt); None
    takes the convention's.  A StressDivergence, BodyForce or Damping in ``terms`` replaces the one
    Simulation adds.

    Args:
        grid: the background :class:`jaxmpm.Grid`.
        shape: the shape function: a :class:`jaxmpm.ShapeFunction` (``jm.Linear()``,
            ``jm.UGIMP(ppc=2)``, ...) or its registered name ("linear", "ugimp", "quadratic",
            "cubic").
        material: the constitutive model, a :class:`jaxmpm.Material`.
        scheme: the particle update: a :class:`jaxmpm.Scheme` (``jm.FLIP()``, ``jm.XPIC(order=5)``,
            ...) or its command-line form ("flip", "pic", "blend:B", "xpic:M", "fmpm:K", "apic",
            "tpic", "rpic").
        damping: a :class:`jaxmpm.Damping`; None (the default): zero damping, still a
            differentiable parameter; False: no damping term at all (nothing compiled for it).
        update: when the stress is updated (003 §2.2): "USL" (default; also "USL-"), "USF",
            "MUSL" (also "USL+"), "USAVG-" or "USAVG+".
        boundary: the velocity conditions on the grid: a :class:`jaxmpm.Fixed`, :class:`jaxmpm.Slip`,
            :class:`jaxmpm.Prescribed`, :class:`jaxmpm.Wall` or :class:`jaxmpm.Mirror`, a sequence
            of them (later ones win where they overlap), or None (the default: none).
        gravity: the uniform body acceleration, one number or D components (finite); None (the
            default): zero.  A differentiable leaf (the parameter ``gravity``).
        body_force: a callable b(x, t) -> (N, D), a body force per unit mass added to gravity;
            None (the default): none.
        terms: further physics terms (:class:`jaxmpm.Term`: jm.Contact, jm.Heat, jm.Traction,
            ...), one or a sequence, stepped in this order after Simulation's own; default ().
        backend: the fusion policy, "auto" (default), "cpu" or "gpu": speed only.
        kinematics: the strain increment, "linear" (default, dF = I + grad v dt) or
            "exponential" (dF = exp(grad v dt)).
        adjoint: the reverse-mode derivative rules, "structured" (default) or "autodiff": speed
            only.
        conventions: whose rules the step follows where MPM codes differ, "jaxmpm" (default) or
            "nairnmpm".
        constrained_force: the constrained nodes' force, "zero" or "reaction"; None (the
            default): the one ``conventions`` picks.
        kernel: the transfer kernel, "auto" (default: by the backend table), "xla" or "pallas":
            speed only.
        sort_every: a run (``run``, ``rollout``, ``jm.ensemble``) sorts the particles by cell every
            this many steps (``jaxmpm.run.sorting``; frames and the final state stay in the user's
            order), 0 never; "auto" (default): as the backend table says (``jm.backend_info``).
            Speed only: a sorted run equals an unsorted one to round-off.
        chunk_particles: a step runs over its particles in chunks of about this many
            (``jaxmpm.model.chunks``: USL with a local scheme and local terms), 0 never; "auto"
            (default): as the backend table says (``jm.backend_info``).  Speed only: a step in
            chunks equals the whole step to round-off.
        derivative_chunk_particles: the step's JVPs and gradients go over its particles in chunks of
            about this many, each chunk recomputed in the reverse pass (``jaxmpm.model.chunks.step_in_chunks``),
            0: the whole step's derivatives; "auto" (default): as the backend's derivative table says where
            ``chunk_particles`` is "auto", else the same as ``chunk_particles``.  Both "auto" sizes shrink to
            fit the device's memory.  Speed and memory only: the derivatives equal the whole step's to round-off.
        particle_devices: a step shares its particles among this many of the process's devices,
            each holding the whole grid (``jaxmpm.model.devices``: the conditions of a step in chunks),
            1 never; "auto" (default): as the backend table says, among every local device where the
            process has several (on a CPU: ``jax.config.update("jax_num_cpu_devices", n)`` before JAX's
            first computation).  Speed only: the shared step equals one device's to round-off.
    """

    grid: Grid
    shape: ShapeFunction
    material: Material
    scheme: Scheme
    terms: tuple
    boundary: tuple  # velocity conditions, callable selectors resolved to node sets
    update: str = eqx.field(static=True)
    backend: str = eqx.field(static=True)
    kinematics: str = eqx.field(static=True, default="linear")
    adjoint: str = eqx.field(static=True, default="structured")
    conventions: str = eqx.field(static=True, default="jaxmpm")
    constrained_force: str = eqx.field(static=True, default="zero")
    kernel: str = eqx.field(static=True, default="auto")
    sort_every: object = eqx.field(static=True, default="auto")
    chunk_particles: object = eqx.field(static=True, default="auto")
    derivative_chunk_particles: object = eqx.field(static=True, default="auto")
    particle_devices: object = eqx.field(static=True, default="auto")

    def __init__(
        self,
        grid: Grid,
        shape: ShapeFunction | str,
        material: Material,
        scheme: Scheme | str,
        damping: Damping | None = None,
        update: str = "USL",
        boundary=None,
        gravity=None,
        body_force: Callable | None = None,
        terms=(),
        backend: str = "auto",
        kinematics: str = "linear",
        adjoint: str = "structured",
        conventions: str = "jaxmpm",
        constrained_force: str | None = None,
        kernel: str = "auto",
        sort_every="auto",
        chunk_particles="auto",
        particle_devices="auto",
        derivative_chunk_particles="auto",
    ):
        check(isinstance(grid, Grid), f"Simulation: grid must be a jm.Grid, got {type(grid).__name__}")
        # a step holds a few nodal fields of 1 + D (mass, momentum) up to D^2 columns per node
        require_memory(f"Simulation: a grid of {grid.num_nodes:.4g} nodes ({' x '.join(map(str, grid.node_shape))})",
                       8.0 * grid.num_nodes * 4 * (1 + grid.dim + grid.dim**2),
                       "use a coarser grid (larger spacing or fewer cells)")
        if isinstance(shape, str):
            shape = shape_from_name(shape)
        check(isinstance(shape, ShapeFunction),
              f"Simulation: unknown shape {shape!r}; use one of {', '.join(SHAPES.names())} (jm.Linear(), ...)")
        if isinstance(scheme, str):
            scheme = scheme_from_name(scheme)
        check(isinstance(scheme, Scheme),
              f"Simulation: unknown scheme {scheme!r}; use a jm.Scheme or one of {SCHEMES.specs()}")
        constrained_force = resolve_conventions(conventions, constrained_force)
        scheme = scheme.in_conventions(conventions)
        check(isinstance(material, Material),
              f"Simulation: material must be a jm.Material ({', '.join(MATERIALS.names())}), "
              f"got {type(material).__name__}")
        check(one_of(update, UPDATES),
              f"Simulation: update = {update!r}; choose USF, USL (USL-), MUSL (USL+), USAVG- or USAVG+")
        check(one_of(backend, POLICIES), f"Simulation: backend = {backend!r}; choose one of {', '.join(POLICIES)}")
        check(one_of(adjoint, ADJOINTS),
              f"Simulation: adjoint = {adjoint!r}; choose 'structured' (the transfer layer's derivative rules, the "
              "default) or 'autodiff' (JAX's own, the reference)")
        damping_given = damping is not None and damping is not False
        # None: zero damping, still a differentiable parameter; False: no damping in the model at
        # all (nothing compiled for it -- "model no more than a scene needs")
        if damping is False:
            damping = None
        elif damping is None:
            damping = Damping()
        else:
            check(isinstance(damping, Damping),
                  "Simulation: damping must be jm.Damping(grid=..., particle=...), None (zero) or False (none)")
        g = jnp.zeros(grid.dim) if gravity is None else FINITE.leaf("Simulation", "gravity", gravity)
        g = jnp.broadcast_to(g, (grid.dim,)) if g.ndim == 0 else g
        check(g.shape[-1:] == (grid.dim,), f"Simulation: gravity must have {grid.dim} components, got shape {g.shape}")
        extra = (terms,) if isinstance(terms, Term) else tuple(terms)
        for t in extra:
            check(isinstance(t, Term), f"Simulation: terms must be jm.Term instances, got {t!r}")
        # the terms Simulation adds itself; one of the same class in terms= replaces it (as with_term
        # does), so a scene's sim.terms given back, or jm.StressDivergence(xpic=m), never act twice
        stress, body = StressDivergence(), BodyForce(g, body_force)
        for t in extra:
            if isinstance(t, StressDivergence):
                stress = t
            elif isinstance(t, BodyForce):
                check(gravity is None and body_force is None,
                      "Simulation: terms holds a BodyForce and gravity=/body_force= give another; give it once")
                body = t
            elif isinstance(t, Damping):
                check(not damping_given,
                      "Simulation: terms holds a jm.Damping and damping= gives another; give damping once")
                damping = t
        extra = tuple(t for t in extra if not isinstance(t, (StressDivergence, BodyForce, Damping)))
        self.grid = grid
        self.shape = shape
        self.material = material
        self.scheme = scheme
        self.terms = tuple(t.in_conventions(conventions) for t in (stress, body)
                           + ((damping,) if damping is not None else ()) + extra)
        self.boundary = as_conditions(boundary, grid)
        self.update = UPDATES[update]
        self.backend = backend
        check(kinematics in KINEMATICS, f"Simulation: kinematics = {kinematics!r}; choose 'linear' (dF = I + grad v "
                                        "dt) or 'exponential' (dF = exp(grad v dt), 001 eq. 26)")
        self.kinematics = kinematics
        self.adjoint = adjoint
        self.conventions = conventions
        self.constrained_force = constrained_force
        check(one_of(kernel, KERNEL_CHOICES),
              f"Simulation: kernel = {kernel!r}; choose one of {', '.join(KERNEL_CHOICES)}")
        self.kernel = kernel
        self.sort_every = _checked_sort_every(sort_every)
        self.chunk_particles = _checked_chunk_particles(chunk_particles)
        self.derivative_chunk_particles = _checked_derivative_chunk_particles(derivative_chunk_particles)
        self.particle_devices = _checked_particle_devices(particle_devices)
        self._check_terms()

    def _check_terms(self):
        """The terms fit together and with the model (also after :meth:`with_term`): each particle
        field declared once; at most one term splits the grid into velocity fields and at most one
        exchanges momentum between them (the exchange phase does not commute); a term still using
        the deprecated whole-solution hook ``grid_action`` is named in a DeprecationWarning."""
        names = [f.name for t in self.terms for f in t.particle_fields()]
        check(len(names) == len(set(names)), f"Simulation: two terms declare the same particle field: {names}")
        splitting = [type(t).__name__ for t in self.terms if t.velocity_fields() > 1]
        check(len(splitting) <= 1, f"Simulation: {' and '.join(splitting)} both split the grid into velocity fields; "
                                   "a model has one multimaterial term")
        exchanging = [type(t).__name__ for t in self.terms if overrides(t, "exchange_momentum")]
        check(len(exchanging) <= 1, f"Simulation: {' and '.join(exchanging)} both exchange momentum between velocity "
                                    "fields; the exchange does not commute, so a model has one exchanging term "
                                    "(combine their laws in one term)")
        for t in self.terms:
            if overrides(t, "grid_action"):
                warn(f"{type(t).__name__} overrides Term.grid_action, which is deprecated (its rewrite of the grid "
                     "solution runs after the readers and can overwrite other terms' results); use the phase hooks "
                     "grid_force, exchange_momentum or read_grid (docs/extending.md)", DeprecationWarning)

    # ------------------------------------------------------------- the parts
    def term(self, cls):
        """The model's term of class ``cls``, or None."""
        for t in self.terms:
            if isinstance(t, cls):
                return t
        return None

    def with_term(self, term: Term):
        """A copy with ``term`` added (or replacing the term of the same class)."""
        check(isinstance(term, Term), f"Simulation.with_term: pass a jm.Term instance, got {term!r}")
        kept = tuple(t for t in self.terms if type(t) is not type(term))
        new = eqx.tree_at(lambda s: s.terms, self, kept + (term,))
        new._check_terms()
        return new

    def with_backend(self, backend: str):
        """A copy traced under another fusion policy ("auto", "cpu", "gpu"; jaxmpm.transfer.backend)."""
        check(one_of(backend, POLICIES), f"Simulation: backend = {backend!r}; choose one of {', '.join(POLICIES)}")
        return self._with_static(backend=backend)

    def with_adjoint(self, adjoint: str):
        """A copy differentiated with other derivative rules ("structured", "autodiff"; jaxmpm.transfer.backend)."""
        check(one_of(adjoint, ADJOINTS), f"Simulation: adjoint = {adjoint!r}; choose one of {', '.join(ADJOINTS)}")
        return self._with_static(adjoint=adjoint)

    def with_kernel(self, kernel: str):
        """A copy whose transfers run on another kernel ("auto", "xla", "pallas"; :func:`backend_info`)."""
        check(one_of(kernel, KERNEL_CHOICES),
              f"Simulation: kernel = {kernel!r}; choose one of {', '.join(KERNEL_CHOICES)}")
        return self._with_static(kernel=kernel)

    def with_sorting(self, every):
        """A copy whose runs sort the particles by cell every ``every`` steps (0: never; "auto": the
        backend table's choice; ``sort_every`` in the class docstring)."""
        sorted_copy = self._with_static(sort_every=_checked_sort_every(every))
        if sorted_copy.sort_every not in ("auto", 0):  # refused at once where a term is bound to the particle order
            sorted_copy._sort_row(1, jnp.float64)
        return sorted_copy

    def sorting(self, state: State):
        """The runs' cell sorting for ``state`` (a :class:`jaxmpm.run.sorting.Sorting`), or None
        when they do not sort (:func:`backend_info` says why)."""
        every, _ = self._sort_row(state.x.shape[0], state.x.dtype)
        return Sorting(self.grid, every) if every else None

    def _sort_row(self, num_particles: int, dtype) -> tuple:
        """(steps between sorts, 0 for never; why) for runs of ``num_particles`` particles in ``dtype``."""
        bound = [type(t).__name__ for t in self.terms if not t.order_free]
        if bound:  # a term holding per-particle arrays in the user's order: sorting would mismatch them
            check(self.sort_every in ("auto", 0), f"sort_every={self.sort_every}: the term(s) {', '.join(bound)} hold "
                                                  "per-particle arrays in the particles' order (Term.order_free), "
                                                  "which sorting would hand to other particles; leave sort_every "
                                                  "at 0")
            return 0, f"the term(s) {', '.join(bound)} hold per-particle arrays in the particles' order"
        if self.sort_every != "auto":
            return self.sort_every, f"sort_every={self.sort_every} given"
        kernel = self._kernel_row(num_particles, dtype)[0] or "xla"
        return choose_sorting(self.backend, self.grid.dim, num_particles, kernel)

    def with_chunks(self, particles):
        """A copy whose steps run over the particles in chunks of about ``particles`` (0: never;
        "auto": the backend table's choice; ``chunk_particles`` in the class docstring)."""
        return self._with_static(chunk_particles=_checked_chunk_particles(particles))

    def with_derivative_chunks(self, particles):
        """A copy whose steps' JVPs and gradients go over the particles in chunks of about ``particles``, each
        recomputed in the reverse pass (0: the whole step's derivatives; "auto": the backend table's choice;
        ``derivative_chunk_particles`` in the class docstring)."""
        return self._with_static(derivative_chunk_particles=_checked_derivative_chunk_particles(particles))

    def with_particle_devices(self, devices):
        """A copy whose steps share their particles among ``devices`` of the process's devices (1: one
        device; "auto": the backend table's choice; ``particle_devices`` in the class docstring)."""
        return self._with_static(particle_devices=_checked_particle_devices(devices))

    def _device_row(self, state: State, kernel: str | None = None) -> tuple:
        """(devices, particles per chunk on each, 0 for its share at once; why) for a step of ``state``
        whose transfers run on ``kernel`` (None: looked up, :meth:`_kernel_row`).  A forced count the
        process does not have is an error naming the fix."""
        n, dtype = state.x.shape[0], state.x.dtype
        available = len(local_devices())
        if self.particle_devices == "auto":
            devices, per, why = choose_devices(self.backend, self.grid.dim, n, dtype, available)
        else:
            devices, why = self.particle_devices, f"particle_devices={self.particle_devices} given"
            check(devices <= available,
                  f"Simulation: particle_devices = {devices}, but the process has {available} "
                  f"{jax.default_backend().upper()} device(s); on a CPU call "
                  f"jax.config.update(\"jax_num_cpu_devices\", {devices}) before JAX's first computation, or give "
                  "particle_devices=1")
            row = choose_devices(self.backend, self.grid.dim, n, dtype, devices)
            per = row[1] if row[0] > 1 else choose_chunking(self.backend, self.grid.dim, n // devices, dtype)[0]
        if self.chunk_particles != "auto":
            per = self.chunk_particles
        if devices < 2:
            return 1, 0, why
        if self.chunk_particles == "auto":  # a device's share in chunks that fit its memory
            fit = self._memory_row(n // devices, dtype, devices)
            if fit:
                per, why = (fit[0] if not per or fit[0] < per else per), f"{why}; {fit[1]}"
        kernel = kernel or self._kernel_row(n, dtype)[0] or "xla"
        obstacle = device_obstacle(self, state, devices, kernel)
        if obstacle is not None:
            return 1, 0, f"one device: {obstacle} ({why})"
        share = n // devices
        if per and per < share and num_chunks(share, per):
            return devices, per, f"{why}: {share} particles a device, in chunks of {share // num_chunks(share, per)}"
        return devices, 0, f"{why}: {share} particles a device, at once"

    def _memory_row(self, num_particles: int, dtype, devices: int = 1) -> tuple | None:
        """(particles per chunk, why) where the whole step of ``num_particles`` particles on one of
        ``devices`` devices would not fit its memory (:func:`chunks_to_fit` within
        :func:`~jaxmpm.run.memory.step_memory`); None where it fits."""
        free, shared = step_memory(devices)
        per, why = chunks_to_fit(self.grid.dim, num_particles, self.shape.nodes_per_axis ** self.grid.dim, dtype, free,
                                 self.velocity_fields)
        return (per, why + shared) if per else None

    def _chunk_row(self, state: State, kernel: str | None = None) -> tuple:
        """(particles per chunk, 0 for the whole step; why) for a step of ``state`` whose transfers run on
        ``kernel`` ("xla", "pallas"; None: looked up, :meth:`_kernel_row`): the backend's
        :data:`~jaxmpm.transfer.backend.CHUNK_TABLE`, or ``chunk_particles``, in chunks no larger than fit the
        device's memory (:func:`chunks_to_fit`)."""
        n, dtype = state.x.shape[0], state.x.dtype
        if self.chunk_particles != "auto":
            per, why = self.chunk_particles, f"chunk_particles={self.chunk_particles} given"
        else:
            per, why = self._fitted(*choose_chunking(self.backend, self.grid.dim, n, dtype), n, dtype)
        return self._usable_chunks(state, per, why, kernel)

    def _derivative_row(self, state: State, kernel: str | None = None) -> tuple:
        """(particles per chunk of the step's JVPs and gradients, 0 for the whole step's; why), on one device
        (:func:`~jaxmpm.model.chunks.step_in_chunks`: each chunk recomputed in the reverse pass): the backend's
        :data:`~jaxmpm.transfer.backend.DERIVATIVE_CHUNK_TABLE` in chunks no larger than fit the device's
        memory, or ``derivative_chunk_particles``, else ``chunk_particles``, where given."""
        n, dtype = state.x.shape[0], state.x.dtype
        if self.derivative_chunk_particles != "auto":
            per = self.derivative_chunk_particles
            why = f"derivative_chunk_particles={per} given"
        elif self.chunk_particles != "auto":
            per, why = self.chunk_particles, f"chunk_particles={self.chunk_particles} given"
        else:
            per, why = self._fitted(*choose_derivative_chunking(self.backend, self.grid.dim, n, dtype), n, dtype)
        return self._usable_chunks(state, per, why, kernel)

    def _fitted(self, per: int, why: str, num_particles: int, dtype) -> tuple:
        """(per, why) of a table, or chunks that fit the device's memory where the whole step would not and the
        table's are larger (:meth:`_memory_row`)."""
        fit = self._memory_row(num_particles, dtype)  # None where the whole step's temporaries fit
        if fit is None:
            return per, why
        return fit if not per or fit[0] < per else (per, f"{why}; {fit[1]}")

    def _usable_chunks(self, state: State, per: int, why: str, kernel: str | None) -> tuple:
        """(per, why) as a step of ``state`` can take them: 0 (the whole step) where one chunk holds every
        particle or the model cannot step in chunks (:func:`chunk_obstacle`)."""
        n = state.x.shape[0]
        if not per or per >= n:
            return 0, why if not per else f"{why}; {n} particles fit one chunk: the whole step"
        kernel = kernel or self._kernel_row(n, state.x.dtype)[0] or "xla"
        obstacle = chunk_obstacle(self, state, per, kernel)
        if obstacle is not None:
            return 0, f"the whole step: {obstacle} ({why})"
        count = num_chunks(n, per)
        return per, f"{why}: {count} chunks of {n // count} particles"

    def with_conventions(self, conventions: str, constrained_force: str | None = None):
        """A copy of a model built in jaxmpm's conventions that follows another code's rules where
        MPM codes differ (``conventions`` in the class docstring): ``Simulation(..., conventions=c)``
        for a model already built (a scene's ``setup.sim``; the CLI's ``--conventions``)."""
        force = resolve_conventions(conventions, constrained_force)
        new = self._with_static(conventions=conventions, constrained_force=force)
        object.__setattr__(new, "scheme", self.scheme.in_conventions(conventions))
        object.__setattr__(new, "terms", tuple(t.in_conventions(conventions) for t in self.terms))
        return new

    def _with_static(self, **fields):
        """A copy with static (trace-time) fields replaced: the model's hash changes, so jit retraces."""
        new = copy.copy(self)
        for name, value in fields.items():
            object.__setattr__(new, name, value)
        return new

    @property
    def damping(self) -> Damping | None:
        """The damping term, or None when the model has none (``damping=False``)."""
        return self.term(Damping)

    @property
    def gravity(self):
        return self.term(BodyForce).gravity

    @property
    def body_force(self):
        return self.term(BodyForce).field

    def particle_fields(self) -> tuple:
        """The :class:`jaxmpm.ParticleField` declared by the model's terms."""
        return tuple(f for t in self.terms for f in t.particle_fields())

    # ------------------------------------------------------------------ state
    @property
    def velocity_fields(self) -> int:
        """Velocity fields per node: what a term declares (``Term.velocity_fields``: the contact
        term's materials, multimaterial mode), else 1."""
        return max((t.velocity_fields() for t in self.terms), default=1)

    @property
    def material_fields(self) -> int:
        """Deprecated name of :attr:`velocity_fields`."""
        return self.velocity_fields

    @property
    def exchange_term(self):
        """The term that exchanges momentum between velocity fields (contact), or None."""
        for t in self.terms:
            if overrides(t, "exchange_momentum"):
                return t
        return None

    @property
    def field_nodes(self) -> int:
        """Rows of a nodal field: the grid's nodes times the velocity fields."""
        return self.grid.num_nodes * self.velocity_fields

    def field_index(self, state):
        """(N,) integer: each particle's velocity field (zeros with one field)."""
        for t in self.terms:
            if t.velocity_fields() > 1:
                return t.field_index(state)
        return None

    def stencil(self, state, x=None, shape=None):
        """S_pi, G_pi at the particles (001 eqs. 16-17), or at points ``x`` (N, D) that stand for them
        (a traction's edge points), with ``shape`` in place of the model's (a traction's grid basis);
        with several velocity fields each particle's nodes are those of its own field."""
        stencil = (self.shape if shape is None else shape).stencil(self.grid, state.x if x is None else x)
        field = self.field_index(state)
        return stencil if field is None else field_stencil(stencil, field, self.grid.num_nodes)

    def constraint(self, dtype):
        """The velocity conditions on every velocity field's nodes (on the sharded path, on the
        device's window of them: :mod:`jaxmpm.parallel`)."""
        constraint = build_constraint(self.grid, self.boundary, dtype, self.constrained_force)
        constraint = constraint.tile(self.velocity_fields)
        window = active_window()
        if window is None:
            return constraint
        rows = self.field_nodes
        constraint = jax.tree_util.tree_map(
            lambda a: on_window(a, self.velocity_fields) if getattr(a, "shape", (0,))[:1] == (rows,) else a,
            constraint)
        if constraint.mirror is None:
            return constraint
        # the symmetry planes' node numbers as the window's rows
        return dataclasses.replace(constraint, mirror=constraint.mirror.on_window(window.local_nodes))

    def node_positions(self, dtype):
        """x_i, the positions of every velocity field's nodes, (field_nodes, D) in ``dtype`` (the level
        sets of colliders are evaluated there); on the sharded path the device's window of them
        (:mod:`jaxmpm.parallel`; its planes beyond the grid, which no particle reaches, at 0)."""
        nodes = np.tile(self.grid.node_coordinates(), (self.velocity_fields, 1))
        return on_window(jnp.asarray(nodes, dtype), self.velocity_fields)

    def init(self, particles: Particles, fields: dict | None = None) -> State:
        """Initial state from :func:`jaxmpm.fill` output (or any :class:`Particles`); the fields
        the terms declare start at their declared initial values unless ``fields`` gives them:
        ``{name: value}``, each value a number, one value per particle (N, *shape), one for all
        (*shape), or ``f(x)`` returning one of those for the positions x (N, D); any other value
        (text, complex or non-finite numbers, another shape, a function that raises) is an
        InputError naming the field (:meth:`jaxmpm.ParticleField.initial_value`)."""
        check(isinstance(particles, Particles), "Simulation.init: pass the jm.Particles returned by jm.fill")
        x = state_positions(particles)
        d = self.grid.dim
        check(x.ndim == 2 and x.shape[1] == d, f"Simulation.init: particles have shape {x.shape}; the grid is {d}D")
        check(particles.axisymmetric == self.grid.axisymmetric,  # 001 §7: masses and volumes per radian
              f"Simulation.init: the grid has axisymmetric={self.grid.axisymmetric} but the particles "
              f"axisymmetric={particles.axisymmetric}; fill them on this grid (jm.fill(grid, ...))")
        xc = concrete(x)
        if xc is not None:  # concrete positions: checked on the host, even inside jit
            inside = self.shape.inside(self.grid, np.asarray(xc))
            if not inside.all():
                bad = int(np.argmin(inside))
                raise_msg = (
                    f"Simulation.init: particles outside the grid: {int((~inside).sum())} of {inside.size} "
                    f"(first: particle {bad} at {xc[bad].tolist()}); the {type(self.shape).__name__} stencil needs "
                    f"{self.shape.margin} cells of room. Enlarge the grid, e.g. jm.Grid.covering(..., shape=shape)."
                )
                check(False, raise_msg)
        if isinstance(self.shape, UGIMP):
            check(self.shape.ppc == particles.ppc,
                  f"Simulation.init: UGIMP(ppc={self.shape.ppc}) but particles were filled with ppc={particles.ppc}; "
                  "make them equal (the particle half-width is h / (2 ppc))")
        volume = jnp.asarray(particles.volume)
        if particles.mass is None:
            if volume.dtype != x.dtype:  # in the positions' precision (state_positions)
                volume = volume.astype(x.dtype)
            density, vc = concrete(self.material.density), concrete(volume)
            if density is None or vc is None:
                mass = jnp.asarray(self.material.density, x.dtype) * volume  # a plain float density too
            else:  # on the host: op by op this compiled two small programs on a first call
                mass = to_device(np.asarray(density, x.dtype) * vc)
        else:
            mass = jnp.asarray(particles.mass)
            mc, vc, rc = concrete(mass), concrete(volume), concrete(self.material.density)
            if mc is not None and vc is not None and rc is not None:
                check(np.allclose(mc / vc, rc, rtol=1e-6),
                      f"Simulation.init: particles were filled with density {float(np.mean(mc / vc)):.6g} but the "
                      f"material density is {float(rc):.6g}; drop density from jm.fill or make them agree")
        dtype = x.dtype
        n = x.shape[0]
        declared = {f.name: f for f in self.particle_fields()}
        check(fields is None or isinstance(fields, dict),
              f"Simulation.init: fields = {show(fields)} must be a dict {{name: value}} of the terms' particle "
              f"fields (declared: {sorted(declared) or 'none'})")
        given = dict(fields or {})
        unknown = sorted(set(given) - set(declared), key=str)
        check(not unknown, f"Simulation.init: fields {unknown} are not declared by any term of this model "
                           f"(declared: {sorted(declared) or 'none'})")
        values = {name: (f.initial_value(x, given[name], f"Simulation.init: fields[{name!r}]") if name in given
                         else f.initial_value(x)) for name, f in declared.items()}
        for term in self.terms:
            term.check_fields(values)
        dF = d + self.grid.axisymmetric  # axisymmetric: F is 3x3 in (r, z, theta), 001 §7
        return State(
            x=x,
            v=jnp.asarray(particles.v, dtype),
            F=identities(n, dF, jnp.dtype(dtype)),
            mass=mass.astype(dtype),
            volume0=volume.astype(dtype),
            time=jnp.zeros((), dtype),
            step=jnp.zeros((), jnp.int32),
            dissipated=jnp.zeros((), dtype),
            scheme_state=self.scheme.initial_state(particles),
            material_state=self.material.initial_state(particles),
            fields=values,
        )

    def check_state(self, state, where: str = "run") -> None:
        """That ``state`` is a :class:`State` this model can step: the per-particle state of its scheme
        (APIC's B_p, ...), of its material (a plastic law's F_e and plastic strain, ...) and its terms'
        fields, with the shapes this model's :meth:`init` gives them.  A state made for another model
        (another scheme, material or set of terms) is an InputError naming the part that differs;
        ``where`` names the caller.  Only shapes are compared: it costs a trace, not a computation, and
        holds under ``jit`` and ``vmap``."""
        if isinstance(state, Particles):
            check(False, f"{where}: state is a jm.Particles; make the state first: state = sim.init(particles)")
        if not isinstance(state, State):  # the messages are formatted only where a check fails
            check(False, f"{where}: state = {show(state)} must be a jm.State, the one sim.init(particles) returns")
        expected = _initial_layouts(self.scheme, self.material, self.grid.axisymmetric, state.x)
        for part, owner, have, want in (
                ("scheme_state", type(self.scheme).__name__, state.scheme_state, expected[0]),
                ("material_state", type(self.material).__name__, state.material_state, expected[1])):
            if _layout(have) != _layout(want):
                check(False, f"{where}: the state was made for another model: its {part} holds {_layout_text(have)}, "
                             f"but this model's {owner} needs {_layout_text(want)}; make the state with this model, "
                             "state = sim.init(particles)")
        declared = sorted(f.name for f in self.particle_fields())
        have = sorted(state.fields)
        if have != declared:
            check(False, f"{where}: the state was made for another model: it carries "
                         f"{f'the fields {have}' if have else 'no fields'}, but this model's terms declare "
                         f"{declared if declared else 'none'}; make the state with this model, state = "
                         "sim.init(particles) (a term added after sim.init, also by set_params or ensemble params of "
                         "a term's parameter, brings fields the older state lacks)")

    # ------------------------------------------------------------------- step
    def step(self, state: State, dt) -> State:
        """Advance one time step (pure).  The model computes in its state's precision: float
        parameters of another precision (a float64 model built in a 64-bit process, stepped with a
        float32 state) are cast to the state's dtype on entry."""
        name, options, _ = self._kernel_row(state.x.shape[0], state.x.dtype)
        with use_policy(self.backend), use_adjoint(self.adjoint), use_kernel(name, options):
            kernel = name or "xla"
            devices, per_device, _ = self._device_row(state, kernel)
            derivatives = self._derivative_row(state, kernel)[0]  # on one device, whatever the forward run shares
            if devices > 1:  # backend tuning: the same step on every device of the process at once
                return step_on_devices(self.in_precision(state.x.dtype), state, dt, devices, per_device, derivatives)
            per_chunk = self._chunk_row(state, kernel)[0]
            if per_chunk or derivatives:  # backend tuning (or memory): working sets that fit the cache
                return step_in_chunks(self.in_precision(state.x.dtype), state, dt, per_chunk, derivatives)
            return _step(self.in_precision(state.x.dtype), state, dt)

    def _kernel_row(self, num_particles: int, dtype) -> tuple:
        """(kernel name or None, options, why) for a step of ``num_particles`` particles in
        ``dtype``: None (the kernel registered for the policy) where "auto" finds the XLA kernel,
        so the default path is the one it always was (:func:`backend_info`)."""
        per_cell = num_particles / max(1, int(np.prod(self.grid.cells)))
        name, options, why = choose_kernel(self.backend, self.grid.dim, per_cell, dtype, folds_force(self))
        if self.kernel == "auto":
            return (None if name == "xla" else name), options, why
        if self.kernel == name:
            return name, options, why + " (forced)"
        return self.kernel, {}, f"kernel={self.kernel!r} forced (the table's choice: {name}: {why})"

    def in_precision(self, dtype):
        """The model with its float leaves cast to ``dtype`` (itself if they already are)."""
        try:  # None is no dtype here (jnp.dtype(None) is the default float, which would pass silently)
            floating = dtype is not None and jnp.issubdtype(jnp.dtype(dtype), jnp.floating)
        except TypeError:
            floating = False
        check(floating, f"Simulation.in_precision: dtype = {dtype!r}; give a float dtype, jnp.float32 or jnp.float64")
        leaves = [leaf for leaf in jax.tree_util.tree_leaves(self) if isinstance(leaf, jax.Array)
                  and jnp.issubdtype(leaf.dtype, jnp.floating)]
        if all(leaf.dtype == dtype for leaf in leaves):
            return self
        return jax.tree_util.tree_map(
            lambda a: a.astype(dtype) if isinstance(a, jax.Array) and jnp.issubdtype(a.dtype, jnp.floating) else a,
            self)

    def stable_dt(self, state: State, cfl: float = 1.0):
        """The stable time step times ``cfl``: the smallest of the CFL limit h / max_p(c + |V_p|), the
        scheme's (FMPM(k): over sqrt(k)), the material's and the terms' limits (conduction,
        diffusion: :meth:`time_step_limits`)."""
        limits = list(self.time_step_limits(state, cfl).values())
        if len(limits) == 1:
            return limits[0]
        if traced((self, state, cfl)):
            return jnp.min(jnp.stack(limits))
        # concrete: the smallest picked on the host (exact, as jnp.min; np.argmin, like it, gives the first
        # NaN), so a scene's dt and sim.run's check of it share time_step_limits' one compiled program
        return limits[int(np.argmin([float(limit) for limit in limits]))]

    def time_step_limits(self, state: State, cfl: float = 1.0) -> dict:
        """{name: largest stable dt, times ``cfl``}: "CFL" (h / max_p(c + |V_p|)); the scheme's own
        where its update shrinks that (:meth:`jaxmpm.Scheme.time_step_factor`, named after its class:
        "fmpm", the CFL limit over sqrt(k)); the material's own limit when it has one
        (:meth:`jaxmpm.Material.time_step_limit`, named after its class: e.g. "newtonianfluid", the
        viscous limit); and one per term that limits it (e.g. "heat": h^2 / (2 D a),
        jaxmpm.physics.transport)."""
        POSITIVE.real("stable_dt", "cfl", cfl, fix="the Courant number, e.g. 0.5")  # a traced one passes
        # concrete (sim.run's check of dt): one compiled program, kept per model, instead of the limits'
        # small ones op by op on a first call
        limits = _time_step_limits(self, state, cfl)
        law = type(self.material).__name__.lower()
        value = concrete(limits[law]) if law in limits else None
        if value is not None and np.isposinf(value):
            # no limit of the law's own for these values (a Newtonian fluid with eta = 0: None when
            # concrete, 3 rho h^2 / 0 = +inf once compiled): no entry, as op by op
            del limits[law]
        return limits

    def _time_step_limits(self, state: State, cfl) -> dict:
        model = self.in_precision(state.x.dtype)
        limits = {"CFL": diag.stable_dt(self.grid, model.material, state.v, cfl)}
        factor = model.scheme.time_step_factor()  # e.g. FMPM(k): 1 / sqrt(k)
        if factor < 1.0:
            limits[type(model.scheme).__name__.lower()] = factor * limits["CFL"]
        limit = model.material.time_step_limit(self.grid.h, self.grid.dim)
        if limit is not None:
            limits[type(model.material).__name__.lower()] = cfl * limit
        for term in model.terms:
            limit = term.time_step_limit(model, state)
            if limit is not None:
                limits[type(term).__name__.lower()] = cfl * limit
        return limits

    def stretch(self, state: State):
        """The isotropic stretch (N,) the terms impose on the particles (thermal / moisture
        expansion, jaxmpm.physics.transport): the product of theirs, or None without any."""
        total = None
        for term in self.terms:
            s = term.stretch(state)
            if s is not None:
                total = s if total is None else total * s
        return total

    def elastic_deformation(self, state: State):
        """The deformation gradient the material sees: F, divided by the isotropic stretch of any
        term that imposes one (thermal / moisture expansion, jaxmpm.physics.transport)."""
        stretch = self.stretch(state)
        return state.F if stretch is None else state.F / stretch[:, None, None]

    def instability(self, state: State, dt=None):
        """(cause code, particle index) for the first problem found in ``state``; code 0 = fine, 1 a
        NaN or Inf, 2 an inverted particle, 3 a particle off the grid.  With the step's ``dt``, a
        particle off the grid that moves more than a cell a step (|V| dt > h: no stable step does) is
        code 4, a blow-up rather than a grid too small for the motion."""
        finite = jnp.all(jnp.isfinite(state.x), -1) & jnp.all(jnp.isfinite(state.v), -1)
        finite = finite & jnp.all(jnp.isfinite(state.F), (-1, -2))
        for value in state.fields.values():  # the terms' fields too (e.g. a temperature)
            if jnp.issubdtype(value.dtype, jnp.floating):
                finite = finite & jnp.all(jnp.isfinite(value.reshape(value.shape[0], -1)), -1)
        positive = det(state.F) > 0
        inside = self.shape.inside(self.grid, state.x)
        code = jnp.where(~jnp.all(finite), 1, jnp.where(~jnp.all(positive), 2, jnp.where(~jnp.all(inside), 3, 0)))
        bad = jnp.where(code == 1, ~finite, jnp.where(code == 2, ~positive, ~inside))
        # the first bad particle (0 when none), as jnp.argmax(bad) finds it, but as a plain min-reduction of int32:
        # argmax is a reduction of (value, index) pairs that XLA:CPU does not vectorise, and a run's loop evaluates
        # it every step (64 vmapped members of the bar, 2000 steps in the runtime-count loop: 136 -> 107 ms)
        count = bad.shape[0]
        first = jnp.min(jnp.where(bad, jnp.arange(count, dtype=jnp.int32), count))
        first = jnp.where(first == count, 0, first)
        if dt is not None:  # the particle off the grid: did it leave at a speed no stable step has?
            speed = jnp.sqrt(jnp.sum(jnp.square(state.v[first])))
            code = jnp.where((code == 3) & (speed * dt > min(self.grid.spacing)), 4, code)
        return code.astype(jnp.int32), first

    def diagnostics(self, state: State) -> dict:
        """The energies and momenta of ``state``: ``kinetic`` K, ``strain`` U, ``gravitational`` V_g =
        -sum_p M_p g . X_p (the gravity vector's potential, zero at the origin: only its change means
        something; 0 without gravity, and a body force b(x, t) has none), the ``dissipated`` energy, the
        linear and angular ``momentum``.  K + U + V_g is what a run under gravity conserves.  The saved
        frames hold all but ``gravitational`` (:meth:`diagnostics_frame`)."""
        check(isinstance(state, State), f"diagnostics: state = {type(state).__name__}; give a jm.State of this model")
        # concrete: one compiled program, kept per model, instead of some thirty small ones op by op
        return _diagnostics(self, state)

    def _frame_sums(self, state: State) -> dict:
        """The frame's sums over the particles: kinetic and strain energy, linear and angular momentum."""
        return dict(
            kinetic=diag.kinetic_energy(state),
            strain=diag.strain_energy(state, self.material, self.elastic_deformation(state)),
            momentum=diag.linear_momentum(state),
            angular=self.scheme.angular_momentum(state),
        )

    def _frame_diagnostics(self, state: State) -> dict:
        """The frame's sums, over the step's chunks of particles where it steps in chunks (their per-particle
        terms then exist for one chunk at a time: :func:`jaxmpm.model.chunks.sums_in_chunks`), and the
        dissipated energy."""
        per_chunk = self._chunk_row(state)[0]
        sums = sums_in_chunks(self, state, per_chunk) if per_chunk else self._frame_sums(state)
        return dict(sums, dissipated=state.dissipated)

    def diagnostics_frame(self, state: State, save_particles: bool, fields: tuple = ()) -> History:
        """One saved frame of a run: time, diagnostics and (``save_particles``) the particle
        positions, velocities, the saved fields the terms declare and the chosen ``fields``
        (stress, pressure, J, F, ...: :mod:`jaxmpm.model.frame_fields`)."""
        saved = {f.name for f in self.particle_fields() if f.save}
        materials = self.velocity_fields
        chosen = frame_fields.frame_fields(self, state, fields) if save_particles and fields else {}
        return History(
            time=state.time,
            x=state.x if save_particles else None,
            v=state.v if save_particles else None,
            fields={**{k: v for k, v in state.fields.items() if k in saved}, **chosen} if save_particles else {},
            by_material={} if materials == 1 else
            diag.by_material(state, self.material, self.field_index(state), materials),
            totals=self.totals(state),
            **self._frame_diagnostics(state),
        )

    def totals(self, state: State) -> dict:
        """{name: scalar} saved with every frame (``History.totals``): the terms' sums (thermal
        energy of jm.Heat, solute of jm.Diffusion) and the material's (:meth:`jaxmpm.Material.totals`:
        e.g. the energy a viscous or plastic law has dissipated)."""
        out = {name: value for term in self.terms for name, value in term.totals(self, state).items()}
        material = self.material.totals(state.material_state, state.volume0)
        check(not set(out) & set(material), f"Simulation: the material's totals {sorted(material)} and the terms' "
                                            f"{sorted(out)} share a name; rename one")
        return {**out, **material}

    def check_frame_fields(self, state: State, fields, where: str = "fields") -> tuple:
        """``fields`` as a tuple, checked: names of the per-frame fields a run of this model from
        ``state`` can save (:func:`jaxmpm.model.frame_fields.available`), each once; ``where``
        names the argument in the messages."""
        return frame_fields.chosen(self, state, fields, where)

    # ----------------------------------------------------- the driver's entry points
    def rollout(self, state: State, dt, frames: int, save_every: int = 1, save_particles: bool = True,
                checkpoint="auto", history_gradients: bool = True, fields: tuple = (), memory=None):
        """See :func:`jaxmpm.run.driver.rollout`."""
        return rollout(self, state, dt, frames, save_every, save_particles, checkpoint, history_gradients, fields,
                       memory)

    def run(self, state: State, dt, steps: int, save_every: int = 1, **options):
        """See :func:`jaxmpm.run.driver.run`."""
        return run(self, state, dt, steps, save_every, **options)

    @property
    def dim(self) -> int:
        return self.grid.dim


class _ParticlesLike(NamedTuple):
    """What a scheme's or material's ``initial_state`` reads of :class:`Particles` (Simulation.check_state)."""

    x: jax.Array
    v: jax.Array
    volume: jax.Array
    mass: jax.Array
    axisymmetric: bool
    ppc: int = 1


_INITIAL_LAYOUTS = {}  # (scheme, material structure, axisymmetric, x's shape and dtype) -> their initial states' shapes


def _initial_layouts(scheme, material, axisymmetric: bool, x):
    """The shapes (``jax.ShapeDtypeStruct`` trees) of the scheme's and the material's initial state for particles
    at ``x``, as :meth:`Simulation.init` makes them; kept per model structure, since tracing them costs about a
    millisecond, a third of a small run's call."""
    def initial(x):  # the laws read the particles' count, dimension and dtype
        like = _ParticlesLike(x=x, v=x, volume=x[:, 0], mass=x[:, 0], axisymmetric=axisymmetric)
        return scheme.initial_state(like), material.initial_state(like)

    try:
        key = (jax.tree_util.tree_structure(scheme), jax.tree_util.tree_structure(material), axisymmetric,
               tuple(jnp.shape(x)), jnp.result_type(x))
        hash(key)
    except TypeError:  # a static field that cannot be hashed: traced each time
        return jax.eval_shape(initial, x)
    if key not in _INITIAL_LAYOUTS:
        if len(_INITIAL_LAYOUTS) > 256:
            _INITIAL_LAYOUTS.clear()
        _INITIAL_LAYOUTS[key] = jax.eval_shape(initial, x)
    return _INITIAL_LAYOUTS[key]


def _layout(tree) -> tuple:
    """A pytree's structure and its leaves' shapes."""
    leaves, structure = jax.tree_util.tree_flatten(tree)
    return structure, tuple(tuple(jnp.shape(leaf)) for leaf in leaves)


def _layout_text(tree) -> str:
    """How :meth:`Simulation.check_state` names a part of a state: none, a shape, or {name: shape}."""
    if tree is None:
        return "nothing"
    if isinstance(tree, dict):
        return "{" + ", ".join(f"{k}: {tuple(jnp.shape(v))}" for k, v in sorted(tree.items())) + "}"
    if hasattr(tree, "shape"):
        return f"an array of shape {tuple(tree.shape)}"
    return show(tree)


def backend_info(sim: Simulation, state: State, members: int = 1) -> dict:
    """Which transfer kernel ``sim`` steps ``state`` with, and why: the row of the kernel table
    (``jaxmpm.transfer.backend.KERNEL_TABLE``) that matches the model's backend, dimension,
    particles per cell, dtype and whether its P2G folds the force into the momentum
    (:func:`folds_force`), or the kernel forced by ``Simulation(kernel=...)``.

    Args:
        sim: the model (:class:`Simulation`).
        state: a state it steps (its particle count and dtype decide); an ensemble's batched state gives
            one member's.
        members: how many members step at once on the device, whose steps share its free memory when each
            decides whether its temporaries fit (chunks to fit): 1 (the default), a single run; ``jm.ensemble``'s
            vmapped members, all of a device's or its ``chunk`` of them (:func:`jaxmpm.run.ensemble.plan` says
            which its ``strategy`` picks).

    Returns:
        {"kernel": "xla" or "pallas", "options": the kernel's options, "policy": "cpu" or "gpu",
        "dimension", "particles_per_cell", "dtype", "reason": the table row's reason,
        "sort_every": the steps between the runs' sorts of the particles by cell (0: never),
        "sort_reason": why, "chunk_particles": the particles per chunk of a step (0: the whole step at
        once, ``jaxmpm.model.chunks``; with several devices: on each), "chunk_reason": why,
        "derivative_chunk_particles": the particles per chunk of the step's JVPs and gradients, each chunk
        recomputed in the reverse pass (0: the whole step's derivatives; on one device), "derivative_chunk_reason":
        why,
        "particle_devices": the devices a step shares its particles among (1: one device,
        ``jaxmpm.model.devices``), "devices_reason": why, and for the XLA kernel "xla_layout":
        {"p2g": "planar" or "rows", "p2g_derivatives": "planar" or "rows", "hold_gathers": bool}, its
        "auto" options for this policy and dtype (``jaxmpm.transfer.backend.XLA_LAYOUT``)}.
    """
    check(isinstance(sim, Simulation), f"backend_info: sim must be a jm.Simulation, got {type(sim).__name__}")
    check(isinstance(state, State), f"backend_info: state must be a jm.State, got {type(state).__name__}")
    check(isinstance(members, (int, np.integer)) and not isinstance(members, bool) and members >= 1,
          f"backend_info: members = {members!r}; give how many members step at once (an integer >= 1; 1: a single run)")
    n, dtype = state.x.shape[-2], state.x.dtype
    name, options, why = sim._kernel_row(n, dtype)
    every, sort_why = sim._sort_row(n, dtype)
    member = state if state.x.ndim == 2 else jax.tree_util.tree_map(lambda a: a[0], state)  # an ensemble's
    with use_policy(sim.backend), members_at_once(members):
        devices, per_device, devices_why = sim._device_row(member, name or "xla")
        per_chunk, chunk_why = (per_device, devices_why) if devices > 1 else sim._chunk_row(member, name or "xla")
        derivatives, derivatives_why = sim._derivative_row(member, name or "xla")
    info = {"kernel": name or "xla", "options": dict(options), "policy": resolve(sim.backend),
            "dimension": sim.grid.dim, "particles_per_cell": n / max(1, int(np.prod(sim.grid.cells))),
            "dtype": jnp.dtype(dtype).name, "reason": why, "sort_every": every, "sort_reason": sort_why,
            "chunk_particles": per_chunk, "chunk_reason": chunk_why,
            "derivative_chunk_particles": derivatives, "derivative_chunk_reason": derivatives_why,
            "particle_devices": devices,
            "devices_reason": devices_why}
    if info["kernel"] == "xla":
        with use_policy(sim.backend):
            p2g, derivatives, hold = xla_layout(dtype)
        info["xla_layout"] = {"p2g": p2g, "p2g_derivatives": derivatives, "hold_gathers": hold}
    return info


def _checked_particle_devices(devices):
    auto = one_of(devices, ("auto",))
    check(auto or (isinstance(devices, (int, np.integer)) and not isinstance(devices, bool) and devices >= 1),
          f"Simulation: particle_devices = {devices!r}; give how many of the process's devices a step shares its "
          "particles among (an integer >= 1, 1 = one device) or 'auto' (the backend table's choice)")
    return devices if auto else int(devices)


def _checked_chunk_particles(particles):
    return _auto_or_count(particles, "chunk_particles", "the particles per chunk of a step",
                          "the whole step at once")


def _checked_derivative_chunk_particles(particles):
    return _auto_or_count(particles, "derivative_chunk_particles", "the particles per chunk of a step's derivatives",
                          "the whole step's derivatives")


def _checked_sort_every(every):
    return _auto_or_count(every, "sort_every", "the steps between sorts of the particles by cell", "never")


def _auto_or_count(value, name: str, what: str, zero: str):
    """``value``: "auto" (the backend table's choice) or a non-negative integer (0 meaning ``zero``)."""
    auto = one_of(value, ("auto",))
    check(auto or (isinstance(value, (int, np.integer)) and not isinstance(value, bool) and value >= 0),
          f"Simulation: {name} = {value!r}; give {what} (a non-negative integer, 0 = {zero}) or 'auto' (the "
          "backend table's choice)")
    return value if auto else int(value)


@compiled_when_concrete
def _time_step_limits(sim, state, cfl) -> dict:
    return sim._time_step_limits(state, cfl)


@compiled_when_concrete
def _diagnostics(sim, state) -> dict:
    body = sim.term(BodyForce)
    gravity = jnp.zeros(sim.grid.dim, state.x.dtype) if body is None else body.gravity
    return dict(sim._frame_diagnostics(state), gravitational=diag.gravitational_potential(state, gravity))
