"""jaxmpm against NairnMPM 19.0 (J. A. Nairn's MPM code, the seeds' reference implementation) on
the ``bar`` scene (issue 28): each case is written as a NairnMPM XML input, run by NairnMPM when
``$NAIRN_BIN`` names a build (otherwise its stored outputs, tests/reference/nairnmpm/, are used),
run the same way in jaxmpm, and the two compared step by step.

The matched set-up.  NairnMPM has no 1D mode: the bar is a plane-strain strip (``<Analysis>10``)
one cell thick in y, nu = 0, y fixed on every node, a unit out-of-plane thickness; jaxmpm runs the
1D bar of :func:`jaxmpm.scenes.bar` (its grid and particles).  E = 100, rho = 1, L = 25, v0 = 0.1,
V(x, 0) = v0 sin(pi x / 2L), 16 cells x 2 particles per cell along x, dt = 0.1 h/c, the
small-strain incremental law tau += E dv/dx dt in both (NairnMPM's ``Isotropic`` material;
:class:`jaxmpm.IncrementalElastic`) and ``ConsistentUnits`` (every number as written, no unit
conversion).  The end: ``fixed`` (jaxmpm's bar fixes the nodes x <= 0; NairnMPM fixes x on the
same nodes, x = 0 and -h, and on the extra node layer it adds around a generated grid, x = -2h)
or ``free`` (no condition in x at all: the bar floats, its centre of mass drifting at v0 2/pi).

The cases (:data:`CASES`; ``Case.name`` is the stored file's name):

* :data:`BASE_CASES`: uGIMP, USL-, undamped, every scheme (FLIP, PIC, XPIC(2), XPIC(5), FMPM(1),
  FMPM(2), FMPM(5)), both ends, 2560 steps (four periods of the bar's mode);
* :data:`LINEAR_CASES`: linear shapes under USL+ (NairnMPM refuses them under USL- and USAVG-),
  FLIP, PIC, XPIC(2), FMPM(2), both ends;
* :data:`UPDATE_CASES`: uGIMP under USL+, USF, USAVG+ and USAVG-, FLIP, XPIC(2), FMPM(2), fixed;
* :data:`DAMPING_CASES`: grid damping alpha_g = 0.05, particle damping alpha_p = 0.03 and both
  (1/time), FLIP, PIC, XPIC(2), FMPM(2), fixed, uGIMP, USL-;

the last three over 640 steps (:data:`PERIOD`, one period), which keeps the stored data small.

What the NairnMPM input is (worked out from NairnMPM's reader; see :func:`nairnmpm_input`):

* the grid: NairnMPM's ``<Grid>`` covers jaxmpm's grid ([-h, 18h] in x) and [0, h] in y, and
  NairnMPM adds one element layer on every side (its GIMP border; a particle entering it has
  "left the grid"), so its nodes run from -2h to 19h and -h to 2h; the nodes jaxmpm lacks carry
  no mass during these runs;
* the particles: 2 x 2 per cell (``<mp>`` points of a ``<PointList>``, each with its own initial
  velocity, positions and velocities written with 17 significant digits so that they read back
  as jaxmpm's float64 values), at x = (2k + 1) h/4 (jaxmpm's) and y = h/4, 3h/4, each of
  semi-size h/4 (NairnMPM's default particle size, ``lpx = lpy = 0.5`` of a cell) and mass
  rho (h/2)^2 x 1 (NairnMPM's rho x area x thickness; the grid's thickness is 1).  The two rows
  give the nodes y = 0 and y = h the same velocities, so dv_x/dy = 0 and the strip is 1D;
* the shape: ``<GIMP type="uGIMP"/>`` or ``<GIMP type="Dirac"/>`` (linear; NairnMPM also reads
  "Classic" or "0" for it);
* the update (``<MPMMethod>``, NairnMPM's USF_METHOD 0, USAVG_METHOD 2, USL_METHOD 3):
  USL- is 3 with ``<SkipPostExtrapolation/>`` (jaxmpm ``update="USL"``), USL+ 3 without it
  (``"MUSL"``: the strain update re-extrapolates the updated particle momenta), USF 0, USAVG- 2
  with ``<SkipPostExtrapolation/>`` and USAVG+ 2 without (each strain update over dt/2, NairnMPM's
  ``fractionUSF`` = 0.5); NairnMPM's default is USAVG, so the method is always written;
* the damping: ``<Damping>`` alpha_g and ``<PDamping>`` alpha_p in the ``<MPMHeader>``, read as
  written (no unit conversion in the reader; printed as "/time"), constant in time, and applied
  only in the particle update as A_damp = alpha_g u + alpha_p V^n -- jaxmpm's
  ``jm.Damping(grid=alpha_g, particle=alpha_p)``, with u NairnMPM's damped velocity (the preset's
  ``damping_velocity``: S(p/m) for FLIP, S(v(m) + a dt) for PIC and XPIC, S v+ for FMPM);
* the factor between the codes: NairnMPM's strip has the cross-section h x 1 where jaxmpm's bar
  has a unit one, so its momentum and energies are jaxmpm's times h (:data:`THICKNESS` = 1);
  v_cm = p_x / M is the same in both;
* the time step: ``<TimeStep>`` dt (NairnMPM keeps it: it only shortens a step beyond its CFL
  limit, 0.5 h/c by default) and ``<MaxTime>`` (steps - 1/2) dt (NairnMPM steps while t <= MaxTime);
* the archive: ``<GlobalArchive>`` "Step number", "px", "Kinetic Energy", "Strain Energy",
  written after every step (``<GlobalArchiveTime>`` dt/2: the archive is written when t has
  passed the next archive time, which then advances by dt/2 only, so no step is skipped); the
  file ``<root>.global`` is tab-separated, time (``%g``) then each quantity in ``%e`` -- seven
  significant digits, which bound the agreement; the step-0 values are not in it;
* the schemes: FLIP is NairnMPM's default; PIC is ``XPICOrder`` 1, XPIC(m) ``XPICOrder`` m,
  FMPM(k) ``FMPMOrder`` k of the ``PeriodicXPIC`` custom task with ``periodicSteps`` 1 (every step).

No FLIP/PIC blend.  NairnMPM 19.0 has no FLIP fraction for the mechanics, so no case compares
jaxmpm's ``FLIP(beta)``/``blend:B``: a step's scheme is one integer (``BodyForce::XPICOrder``,
Global_Quantities/BodyForce.cpp, ``SetXPICOrder``/``GetXPICOrder``: 0 FLIP, m XPIC(m) or FMPM(m)),
and ``MatPoint2D::MoveParticle`` (MPM_Classes/MatPoint2D.cpp) has exactly three branches, FMPM,
FLIP and XPIC, none mixing the others' velocities.  The ``PeriodicXPIC`` task's ``periodicSteps``
(an integer, Custom_Tasks/PeriodicXPIC.cpp ``InputParam``) switches whole steps between FLIP and
XPIC/FMPM (``PrepareForStep``, ``StepCalculation``), which is not a blend; its fractional
settings (``periodicStepsConduction``, ``periodicStepsDiffusion`` < 1: FMPM and FLIP mixed every
step) exist for conduction and diffusion only; and the old ``<Damping PIC="...">`` attribute is
rejected by the reader (Read_MPM/MPMReadHandler.cpp: "use PeriodicXPIC task instead").

Table columns: max |v_cm jaxmpm - v_cm NairnMPM| / v0 over the steps, max |E_kin| and |E_strain|
differences / E0 (E0 the initial kinetic energy) and E/E0 at the end in each code; the ``bound``
columns are the archive's rounding (half a unit in its 7th digit) at the largest value, the
agreement one can see; the last, max |dv_cm| / v0 and max |dE| / E0 with jaxmpm under the other
conventions.
Written to experiments/results/nairnmpm.md.

    python -m experiments.nairnmpm                       # stored NairnMPM outputs (or $NAIRN_BIN)
    NAIRN_BIN=/path/to/NairnMPM python -m experiments.nairnmpm --store   # rerun NairnMPM, store
    python -m experiments.nairnmpm --case fmpm:2-fixed --xml   # print one case's XML input

``--conventions`` runs jaxmpm under "jaxmpm" or "nairnmpm" for every case instead of each case's
own (``Case.conventions``: "nairnmpm" where the codes' rules differ -- FLIP, PIC and XPIC with the
fixed end (the constrained nodes' reaction), PIC and XPIC on the free bar (XPIC's series start and
position update), PIC, XPIC and FMPM with grid damping (the damped velocity) -- and jaxmpm's
default elsewhere).  Every case agrees with NairnMPM to its archive's digits under its own
conventions, and every case agrees under "nairnmpm".
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import re
import subprocess
import tempfile
import time
from xml.sax.saxutils import escape

import jax

jax.config.update("jax_enable_x64", True)

import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jaxmpm as jm  # noqa: E402

E, RHO, LENGTH, V0 = 100.0, 1.0, 25.0, 0.1
THICKNESS = 1.0  # NairnMPM's out-of-plane thickness (its <Grid thickness>; 1 is its default)
REFERENCE_DIR = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "tests", "reference",
                             "nairnmpm")
RESULTS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "results", "nairnmpm.md")
ARCHIVE_DIGITS = 7  # NairnMPM's global archive: "%e", seven significant digits
QUANTITIES = ("px", "kinetic", "strain")  # the stored archive columns besides the step number
ARCHIVE_TYPES = {"step": "Step number", "px": "px", "kinetic": "Kinetic Energy", "strain": "Strain Energy"}

# jaxmpm update -> NairnMPM (<MPMMethod>, <SkipPostExtrapolation/>): USF 0, USAVG 2, USL 3; "-" skips
# the post-update extrapolation (NairnMPM's USL-/USAVG-), "+" does it (USL+ = jaxmpm's MUSL)
UPDATES = {"USL": (3, True), "MUSL": (3, False), "USF": (0, False), "USAVG-": (2, True), "USAVG+": (2, False)}
UPDATE_NAMES = {"USL": "usl", "MUSL": "musl", "USF": "usf", "USAVG-": "usavgm", "USAVG+": "usavgp"}  # in case names
# the damped cases' rates (alpha_g, alpha_p) in 1/time, by their name's suffix
DAMPING = {"g": (0.05, 0.0), "p": (0.0, 0.03), "gp": (0.05, 0.03)}
# jaxmpm shape -> NairnMPM <GIMP type>
SHAPES = {"ugimp": ("uGIMP", jm.UGIMP), "linear": ("Dirac", jm.Linear)}


@dataclasses.dataclass(frozen=True)
class Case:
    """One comparison.  ``scheme`` in jaxmpm's command-line form (``flip``, ``pic``, ``xpic:m``,
    ``fmpm:k``), ``end`` "fixed" (x fixed on the nodes x <= 0) or "free" (no condition in x),
    ``shape`` "ugimp" or "linear", ``update`` jaxmpm's ("USL" is USL-, "MUSL" USL+, "USF",
    "USAVG-", "USAVG+"), ``damping`` (grid alpha, particle alpha) in 1/time, ``steps`` at
    dt = ``cfl`` h/c, ``cells`` along the bar with ``ppc`` particles each along x."""

    scheme: str
    end: str = "fixed"
    shape: str = "ugimp"
    update: str = "USL"
    damping: tuple = (0.0, 0.0)
    steps: int = 2560
    cells: int = 16
    ppc: int = 2
    cfl: float = 0.1

    def __post_init__(self):
        scheme_name, _, order = self.scheme.partition(":")
        if scheme_name not in ("flip", "pic", "xpic", "fmpm") or (scheme_name in ("xpic", "fmpm") and not order):
            raise ValueError(f"Case: scheme {self.scheme!r}; use flip, pic, xpic:m or fmpm:k")
        if self.end not in ("fixed", "free"):
            raise ValueError(f"Case: end {self.end!r}; use 'fixed' or 'free'")
        if self.shape not in SHAPES:
            raise ValueError(f"Case: shape {self.shape!r}; use one of {', '.join(SHAPES)}")
        if self.update not in UPDATES:
            raise ValueError(f"Case: update {self.update!r}; use one of {', '.join(UPDATES)}")

    @property
    def name(self) -> str:
        """The file name of the case: scheme and end (``fmpm5-fixed``), then each setting off the
        defaults: the shape (``linear``), the update (``musl``, ``usf``, ``usavgm``, ``usavgp``),
        the damping (``damp-g``, ``damp-p``, ``damp-gp`` at :data:`DAMPING`'s rates, else
        ``damp-g<alpha_g>-p<alpha_p>``), then ``steps<n>``, ``cells<n>``, ``ppc<n>``, ``cfl<x>``."""
        parts = [self.scheme.replace(":", ""), self.end]
        if self.shape != "ugimp":
            parts.append(self.shape)
        if self.update != "USL":
            parts.append(UPDATE_NAMES[self.update])
        if self.damping != (0.0, 0.0):
            named = {v: k for k, v in DAMPING.items()}
            parts.append(f"damp-{named[self.damping]}" if self.damping in named
                         else "damp-g{:g}-p{:g}".format(*self.damping))
        defaults = Case(self.scheme)
        for field in ("steps", "cells", "ppc", "cfl"):
            value = getattr(self, field)
            if value != getattr(defaults, field):
                parts.append(f"{field}{value:g}")
        return "-".join(parts)

    @property
    def label(self) -> str:
        scheme_name, _, order = self.scheme.partition(":")
        return f"{scheme_name.upper()}({order})" if order else scheme_name.upper()

    @property
    def description(self) -> str:
        """The case in words for the table: ``XPIC(2) fixed, linear, USL+, alpha_g 0.05, 640 steps``."""
        update = {"USL": "USL-", "MUSL": "USL+"}.get(self.update, self.update)
        words = [f"{self.label} {self.end}", "uGIMP" if self.shape == "ugimp" else self.shape, update]
        grid_alpha, particle_alpha = self.damping
        words += [f"alpha_g {grid_alpha:g}"] if grid_alpha else []
        words += [f"alpha_p {particle_alpha:g}"] if particle_alpha else []
        return ", ".join(words + [f"{self.steps} steps"])

    @property
    def conventions(self) -> str:
        """The jaxmpm conventions the case is run under: "nairnmpm" where the codes' rules
        differ (FLIP, PIC, XPIC with the fixed end: the constrained nodes' force; PIC, XPIC:
        the series start and position update; PIC, XPIC, FMPM with grid damping: the damped
        velocity), jaxmpm's default where they agree (FMPM without grid damping; FLIP on the
        free bar)."""
        scheme_name = self.scheme.partition(":")[0]
        if (scheme_name == "fmpm" and not self.damping[0]) or (scheme_name == "flip" and self.end == "free"):
            return "jaxmpm"
        return "nairnmpm"

    # the matched set-up's numbers
    @property
    def h(self) -> float:
        return LENGTH / self.cells

    @property
    def dt(self) -> float:
        return self.cfl * self.h / math.sqrt(E / RHO)


# uGIMP, USL-, undamped: every scheme, both ends, 2560 steps (four periods)
BASE_CASES = tuple(Case(scheme, end) for scheme in ("flip", "pic", "xpic:2", "xpic:5", "fmpm:1", "fmpm:2", "fmpm:5")
                   for end in ("fixed", "free"))
PERIOD = 640  # steps in one period of the fixed-free bar's mode, 4L/c = 10 at dt = 0.1 h/c (h = L/16)
# linear shapes (NairnMPM's Dirac) under USL+ (it refuses them under USL-), both ends; one period
LINEAR_CASES = tuple(Case(scheme, end, shape="linear", update="MUSL", steps=PERIOD)
                     for scheme in ("flip", "pic", "xpic:2", "fmpm:2") for end in ("fixed", "free"))
# uGIMP under USL+, USF, USAVG+ and USAVG-, fixed end; one period
UPDATE_CASES = tuple(Case(scheme, update=update, steps=PERIOD) for update in ("MUSL", "USF", "USAVG+", "USAVG-")
                     for scheme in ("flip", "xpic:2", "fmpm:2"))
# grid damping, particle damping and both, fixed end, uGIMP, USL-; one period
DAMPING_CASES = tuple(Case(scheme, damping=rates, steps=PERIOD) for rates in DAMPING.values()
                      for scheme in ("flip", "pic", "xpic:2", "fmpm:2"))
CASES = BASE_CASES + LINEAR_CASES + UPDATE_CASES + DAMPING_CASES


def case_named(name: str) -> Case:
    """The case of :data:`CASES` called ``name`` (``fmpm5-fixed``; ``fmpm:5-fixed`` works too)."""
    key = name.replace(":", "")
    for case in CASES:
        if case.name == key:
            return case
    raise ValueError(f"unknown case {name!r}; choose {', '.join(c.name for c in CASES)}")


# ------------------------------------------------------------------------------------- jaxmpm
def bar_setup(case: Case):
    """jaxmpm's ``bar`` scene for the case (its grid and particles), float64."""
    return jm.scenes.bar(scheme=jm.FLIP(), shape=SHAPES[case.shape][1](), cells=case.cells, ppc=case.ppc,
                         cfl=case.cfl, update=case.update, dtype="f64")


def simulation(case: Case, conventions: str | None = None, **options):
    """(sim, state, setup) for the case in jaxmpm; ``conventions`` None takes the case's own.
    ``options`` go to :class:`jaxmpm.Simulation` (``scheme=`` a jm.Scheme in place of the case's,
    ``constrained_force=``): a convention's rules one by one."""
    setup = bar_setup(case)
    grid_alpha, particle_alpha = case.damping
    # the bar scene's own condition (x <= 0 fixed, jm.Fixed) for the fixed end, none for the free one
    boundary = setup.sim.boundary if case.end == "fixed" else None
    options = {"scheme": jm.scheme_from_name(case.scheme), **options}
    sim = jm.Simulation(grid=setup.sim.grid, shape=setup.sim.shape, material=jm.IncrementalElastic(E, 0.0, RHO),
                        damping=jm.Damping(grid_alpha, particle_alpha), update=case.update, boundary=boundary,
                        conventions=case.conventions if conventions is None else conventions, **options)
    state = sim.init(setup.particles)
    state = jax.tree_util.tree_map(lambda a: a.astype(jnp.float64) if jnp.issubdtype(a.dtype, jnp.floating) else a,
                                   state)
    return sim, state, setup


@eqx.filter_jit
def _rollout(sim, state, dt, steps):
    _, hist, failure = sim.rollout(state, dt, steps, 1, save_particles=False, checkpoint=False)
    return hist.momentum[:, 0], hist.kinetic, hist.strain, hist.time, failure.step


def run_jaxmpm(case: Case, conventions: str | None = None, **options) -> dict:
    """The case in jaxmpm: every step's time, p_x, E_kin, E_strain and v_cm, steps 0..N, in
    NairnMPM's units (momentum and energies times the strip's cross-section h x THICKNESS);
    ``conventions`` and ``options`` as :func:`simulation`'s."""
    sim, state, _ = simulation(case, conventions, **options)
    mass = float(jnp.sum(state.mass))
    px, kinetic, strain, t, failed = _rollout(sim, state, jnp.float64(case.dt), case.steps)
    if int(failed) >= 0:
        raise jm.InstabilityError(int(failed), f"{case.name}: jaxmpm's run failed")
    section = case.h * THICKNESS
    px = np.asarray(px)
    return dict(step=np.arange(case.steps + 1), time=np.asarray(t), px=px * section,
                kinetic=np.asarray(kinetic) * section, strain=np.asarray(strain) * section, v_cm=px / mass,
                mass=mass * section)


# ----------------------------------------------------------------------------------- NairnMPM
def _num(x: float) -> str:
    """A float as NairnMPM reads it back exactly (sscanf %lf of the shortest round-trip repr)."""
    return repr(float(x))


def particles(case: Case):
    """NairnMPM's material points: (x, y, vx, mass) arrays, 2 rows in y (module docstring)."""
    setup = bar_setup(case)
    x = np.asarray(setup.particles.x, dtype=np.float64)[:, 0]
    v = np.asarray(setup.particles.v, dtype=np.float64)[:, 0]
    h = case.h
    rows = np.array([0.25 * h, 0.75 * h])
    xs, ys = np.meshgrid(x, rows, indexing="ij")
    vs = np.repeat(v[:, None], 2, axis=1)
    mass = RHO * (h / case.ppc) * (h / 2.0) * THICKNESS  # rho x (lpx h)(lpy h) x thickness
    return xs.ravel(), ys.ravel(), vs.ravel(), np.full(xs.size, mass)


def nairnmpm_input(case: Case, root: str = "bar") -> str:
    """The NairnMPM XML input of the case; the archives go to ``<root>.global`` (and particle
    archives ``<root>.<step>`` at the first and last step) next to the input."""
    if case.update in ("USL", "USAVG-") and case.shape == "linear":
        raise ValueError("NairnMPM refuses linear (Dirac) shapes under USL- and USAVG- (MPMMethod 3 or 2 with "
                         "SkipPostExtrapolation)")
    setup = bar_setup(case)
    grid = setup.sim.grid
    h = case.h
    dt = case.dt
    xmin, xmax = float(grid.lower[0]), float(grid.upper[0])
    method, skip = UPDATES[case.update]
    scheme_name, _, order = case.scheme.partition(":")
    x, y, vx, _ = particles(case)
    pad = 0.5 * h  # the BC rectangles reach half a cell past the nodes they select
    lines = [
        "<?xml version='1.0'?>",
        '<!DOCTYPE JANFEAInput SYSTEM "NairnMPM.dtd">',
        '<JANFEAInput version="3">',
        "  <Header>",
        f"    <Description>{escape(f'jaxmpm experiments/nairnmpm.py, bar, case {case.name}')}</Description>",
        "    <Analysis>10</Analysis>",
        "    <ConsistentUnits/>",
        "  </Header>",
        "  <MPMHeader>",
        f"    <MPMMethod>{method}</MPMMethod>",
    ]
    if skip:
        lines.append("    <SkipPostExtrapolation/>")
    lines += [
        f'    <GIMP type="{SHAPES[case.shape][0]}"/>',
        "    <MatlPtsPerElement>4</MatlPtsPerElement>",
        f"    <ArchiveRoot>{root}</ArchiveRoot>",
        f"    <ArchiveTime>{_num(10 * case.steps * dt)}</ArchiveTime>",
        f"    <TimeStep>{_num(dt)}</TimeStep>",
        f"    <MaxTime>{_num((case.steps - 0.5) * dt)}</MaxTime>",
        f"    <GlobalArchiveTime>{_num(0.5 * dt)}</GlobalArchiveTime>",
    ]
    lines += [f'    <GlobalArchive type="{ARCHIVE_TYPES[k]}"/>' for k in ("step",) + QUANTITIES]
    grid_alpha, particle_alpha = case.damping
    # NairnMPM's grid and particle damping, jm.Damping(grid=, particle=): read as written (1/time,
    # no unit conversion), the constants alpha_g, alpha_p of its particle update
    if grid_alpha:
        lines.append(f"    <Damping>{_num(grid_alpha)}</Damping>")
    if particle_alpha:
        lines.append(f"    <PDamping>{_num(particle_alpha)}</PDamping>")
    lines += [
        "  </MPMHeader>",
        "  <Mesh>",
        f'    <Grid xmin="{_num(xmin)}" xmax="{_num(xmax)}" ymin="0.0" ymax="{_num(h)}" thickness="{_num(THICKNESS)}">',
        f'      <Horiz nx="{grid.cells[0]}"/>',
        '      <Vert ny="1"/>',
        "    </Grid>",
        "  </Mesh>",
        "  <MaterialPoints>",
        "    <PointList>",
    ]
    lines += [f'      <mp mat="1"><pt x="{_num(xi)}" y="{_num(yi)}"/><vel x="{_num(vi)}" y="0.0"/></mp>'
              for xi, yi, vi in zip(x, y, vx)]
    lines += [
        "    </PointList>",
        "  </MaterialPoints>",
        '  <Material Type="1" Name="bar">',
        f"    <rho>{_num(RHO)}</rho>",
        f"    <E>{_num(E)}</E>",
        "    <nu>0.0</nu>",
        "    <alpha>0.0</alpha>",
        "  </Material>",
        "  <GridBCs>",
        # y fixed on every node (NairnMPM's grid with its border layer: x in [xmin - h, xmax + h], y in [-h, 2h])
        "    <BCShape>",
        f'      <Rect xmin="{_num(xmin - h - pad)}" xmax="{_num(xmax + h + pad)}" ymin="{_num(-h - pad)}" '
        f'ymax="{_num(2 * h + pad)}"/>',
        '      <DisBC dir="2" style="1" vel="0.0"/>',
        "    </BCShape>",
    ]
    if case.end == "fixed":  # x fixed on the nodes x <= 0: 0, -h and NairnMPM's border node -2h
        lines += [
            "    <BCShape>",
            f'      <Rect xmin="{_num(xmin - h - pad)}" xmax="{_num(0.25 * h)}" ymin="{_num(-h - pad)}" '
            f'ymax="{_num(2 * h + pad)}"/>',
            '      <DisBC dir="1" style="1" vel="0.0"/>',
            "    </BCShape>",
        ]
    lines.append("  </GridBCs>")
    lines += periodic_xpic_task(case.scheme)
    lines.append("</JANFEAInput>")
    return "\n".join(lines) + "\n"


def periodic_xpic_task(scheme: str) -> list:
    """The XML lines of NairnMPM's ``PeriodicXPIC`` custom task, every step, for a scheme in
    jaxmpm's command-line form: ``XPICOrder`` (PIC is 1) or ``FMPMOrder``; none for FLIP."""
    scheme_name, _, order = scheme.partition(":")
    if scheme_name == "flip":
        return []
    parameter = "FMPMOrder" if scheme_name == "fmpm" else "XPICOrder"
    return ["  <CustomTasks>",
            '    <Schedule name="PeriodicXPIC">',
            f'      <Parameter name="{parameter}">{order or 1}</Parameter>',
            '      <Parameter name="periodicSteps">1</Parameter>',
            "    </Schedule>",
            "  </CustomTasks>"]


def parse_global(path: str) -> dict:
    """NairnMPM's global archive: {"time": ..., column name: ...} as float arrays, and the
    columns' text (``"text"``: {name: list of strings}) for exact storage."""
    names, rows = None, []
    with open(path) as f:
        for line in f:
            line = line.rstrip("\n")
            if not line:
                continue
            if line.startswith("#setColor"):
                continue
            if line.startswith("#"):
                names = re.findall(r'"([^"]*)"', line)
                continue
            rows.append(line.split("\t"))
    if names is None or not rows:
        raise RuntimeError(f"{path}: no column names or no rows (NairnMPM's global archive format changed?)")
    columns = list(zip(*rows))
    if len(columns) != len(names) + 1:
        raise RuntimeError(f"{path}: {len(columns)} columns for the names {names} and the time")
    out = {"time": np.array(columns[0], dtype=np.float64), "text": {}}
    for name, col in zip(names, columns[1:]):
        out[name] = np.array(col, dtype=np.float64)
        out["text"][name] = list(col)
    return out


def nairn_version(binary: str) -> str:
    """The version NairnMPM prints ("NairnMPM 19.0 build 0") and, where its source is a git
    checkout or ``$NAIRN_COMMIT`` is set, the commit."""
    out = subprocess.run([binary, "-H"], capture_output=True, text=True, timeout=60).stdout
    version = out.strip().splitlines()[0].strip() if out.strip() else "NairnMPM (unknown version)"
    commit = os.environ.get("NAIRN_COMMIT", "")
    if not commit:
        try:
            commit = subprocess.run(["git", "-C", os.path.dirname(os.path.realpath(binary)), "rev-parse", "HEAD"],
                                    capture_output=True, text=True, timeout=30).stdout.strip()
        except OSError:
            commit = ""
    return f"{version}, commit {commit}" if commit else version


def execute_nairnmpm(name: str, xml: str, workdir: str, binary: str | None, timeout: float) -> str:
    """Write ``xml`` to ``workdir/<name>.xml`` and run NairnMPM (``binary`` or ``$NAIRN_BIN``) on it,
    one thread, its output kept in ``<name>.out``; returns the binary, raises when it fails."""
    binary = binary or os.environ.get("NAIRN_BIN")
    if not binary:
        raise RuntimeError("run_nairnmpm: set $NAIRN_BIN to a NairnMPM executable")
    os.makedirs(workdir, exist_ok=True)
    path = os.path.join(workdir, f"{name}.xml")
    with open(path, "w") as f:
        f.write(xml)
    proc = subprocess.run([binary, "-np", "1", path], capture_output=True, text=True, timeout=timeout, cwd=workdir)
    with open(os.path.join(workdir, f"{name}.out"), "w") as f:
        f.write(proc.stdout + proc.stderr)
    if proc.returncode != 0 or "ABNORMAL TERMINATION" in proc.stdout:
        raise RuntimeError(f"NairnMPM failed on {name} (exit {proc.returncode}):\n{proc.stdout[-3000:]}"
                           f"\n{proc.stderr[-3000:]}")
    return binary


def run_nairnmpm(case: Case, workdir: str, binary: str | None = None, timeout: float = 600.0) -> dict:
    """Run NairnMPM (``binary`` or ``$NAIRN_BIN``) on the case's input in ``workdir``, one thread;
    returns the steps 1..N: step, time, px, kinetic, strain (NairnMPM's per-strip values),
    v_cm = px / M, the archive's text of each quantity, the input and the version."""
    xml = nairnmpm_input(case)
    binary = execute_nairnmpm(case.name, xml, workdir, binary, timeout)
    arch = parse_global(os.path.join(workdir, "bar.global"))
    step = arch[ARCHIVE_TYPES["step"]].astype(np.int64)
    if not np.array_equal(step, np.arange(1, case.steps + 1)):
        raise RuntimeError(f"{case.name}: NairnMPM archived steps {step[:3]}...{step[-3:]} ({step.size}), "
                           f"expected 1..{case.steps}")
    out = dict(step=step, time=arch["time"], text={k: arch["text"][ARCHIVE_TYPES[k]] for k in QUANTITIES},
               xml=xml, version=nairn_version(binary))
    for k in QUANTITIES:
        out[k] = arch[ARCHIVE_TYPES[k]]
        out[f"{k}_unit"] = archive_unit(_encode(out["text"][k])[1])
    out["mass"] = float(np.sum(particles(case)[3]))
    out["v_cm"] = out["px"] / out["mass"]
    return out


# ------------------------------------------------------------------------- the stored outputs
def _encode(texts):
    """NairnMPM's '%e' strings as (signed 7-digit mantissa int32, exponent int16): exactly the
    archive's digits, compressing to a fraction of float64."""
    digits, exps = [], []
    for s in texts:
        mant, _, ex = s.strip().lower().partition("e")
        sign = -1 if mant.startswith("-") else 1
        whole, _, frac = mant.lstrip("+-").partition(".")
        if len(whole) != 1 or len(frac) != ARCHIVE_DIGITS - 1:
            raise ValueError(f"not a NairnMPM %e number: {s!r}")
        digits.append(sign * int(whole + frac))
        exps.append(int(ex))
    return np.array(digits, np.int32), np.array(exps, np.int16)


def _decode(digits, exps):
    return digits.astype(np.float64) * 10.0 ** (exps.astype(np.float64) - (ARCHIVE_DIGITS - 1))


def archive_unit(exp10):
    """One unit in the 7th significant digit of archived values of decimal exponents ``exp10``
    (the archive's resolution; the exponents as stored, not recomputed from the floats)."""
    return 10.0 ** (np.asarray(exp10, dtype=np.float64) - (ARCHIVE_DIGITS - 1))


def store(case: Case, out: dict, directory: str = REFERENCE_DIR) -> str:
    """Write NairnMPM's outputs for the case to ``<directory>/<case>.npz``: each quantity's
    archive digits, the steps, dt, the strip's mass, the XML input and NairnMPM's version."""
    os.makedirs(directory, exist_ok=True)
    arrays = {}
    for k in QUANTITIES:
        arrays[f"{k}_digits"], arrays[f"{k}_exp10"] = _encode(out["text"][k])
    path = os.path.join(directory, f"{case.name}.npz")
    np.savez_compressed(path, first_step=np.int32(out["step"][0]), steps=np.int32(out["step"].size),
                        dt=np.float64(case.dt), mass=np.float64(out["mass"]), xml=np.str_(out["xml"]),
                        version=np.str_(out["version"]), case=np.str_(repr(case)), **arrays)
    return path


def load_reference(case: Case, directory: str = REFERENCE_DIR) -> dict:
    """NairnMPM's stored outputs for the case (:func:`store`): step, time (= step dt), px,
    kinetic, strain (floats of the archive's digits), v_cm, mass, xml, version."""
    with np.load(os.path.join(directory, f"{case.name}.npz")) as z:
        step = np.arange(int(z["first_step"]), int(z["first_step"]) + int(z["steps"]))
        out = dict(step=step, time=step * float(z["dt"]), mass=float(z["mass"]), xml=str(z["xml"]),
                   version=str(z["version"]))
        for k in QUANTITIES:
            out[k] = _decode(z[f"{k}_digits"], z[f"{k}_exp10"])
            out[f"{k}_unit"] = archive_unit(z[f"{k}_exp10"])
    out["v_cm"] = out["px"] / out["mass"]
    return out


def compare(case: Case, nairn: dict, jaxm: dict) -> dict:
    """The agreement over NairnMPM's archived steps: max |dv_cm| / v0, max |dE_kin| / E0,
    max |dE_strain| / E0, max |d(E_kin + E_strain)| / E0, E/E0 at the end in each code, and
    each difference over the archive's resolution (half a unit in the 7th digit) at each step
    (``*_ulps``: <= 1 is agreement to the archive's precision)."""
    idx = nairn["step"]
    e0 = float(jaxm["kinetic"][0] + jaxm["strain"][0])
    out = dict(case=case.name, label=case.description)
    for k in ("px", "kinetic", "strain"):
        diff = np.abs(jaxm[k][idx] - nairn[k])
        out[f"{k}_ulps"] = float(np.max(diff / (0.5 * nairn[f"{k}_unit"])))
        out[f"{k}_max"] = float(np.max(diff))
    out["v_cm"] = float(np.max(np.abs(jaxm["v_cm"][idx] - nairn["v_cm"]))) / V0
    out["v_cm_bound"] = float(0.5 * np.max(nairn["px_unit"])) / nairn["mass"] / V0
    out["kinetic"] = out["kinetic_max"] / e0
    out["strain"] = out["strain_max"] / e0
    total_j = jaxm["kinetic"][idx] + jaxm["strain"][idx]
    total_n = nairn["kinetic"] + nairn["strain"]
    out["energy"] = float(np.max(np.abs(total_j - total_n))) / e0
    out["energy_bound"] = float(0.5 * (np.max(nairn["kinetic_unit"]) + np.max(nairn["strain_unit"])))
    out["energy_bound"] /= e0
    out["final_jaxmpm"] = float(total_j[-1]) / e0
    out["final_nairnmpm"] = float(total_n[-1]) / e0
    return out


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--case", action="append", help="a case name (fmpm5-fixed; repeatable); default all of CASES")
    parser.add_argument("--store", action="store_true",
                        help="store NairnMPM's outputs under tests/reference/nairnmpm/ (needs $NAIRN_BIN)")
    parser.add_argument("--xml", action="store_true", help="print the cases' NairnMPM inputs and stop")
    parser.add_argument("--conventions", choices=("case", "jaxmpm", "nairnmpm"), default="case",
                        help="jaxmpm's conventions: each case's own (default) or one for all")
    parser.add_argument("--workdir", help="where NairnMPM runs (default a temporary folder)")
    parser.add_argument("--out", default=RESULTS)
    args = parser.parse_args(argv)
    cases = [case_named(n) for n in args.case] if args.case else list(CASES)
    if args.xml:
        for case in cases:
            print(nairnmpm_input(case))
        return
    binary = os.environ.get("NAIRN_BIN")
    if args.store and not binary:
        parser.error("--store needs $NAIRN_BIN (a NairnMPM executable)")
    conventions = None if args.conventions == "case" else args.conventions
    rows, version = [], None
    with tempfile.TemporaryDirectory() as tmp:
        for case in cases:
            start = time.perf_counter()
            if binary:
                nairn = run_nairnmpm(case, os.path.join(args.workdir or tmp, case.name), binary)
                if args.store:
                    print(f"stored {store(case, nairn)}")
            else:
                nairn = load_reference(case)
            version = nairn["version"]
            wall_nairn = time.perf_counter() - start
            conv = case.conventions if conventions is None else conventions
            start = time.perf_counter()
            row = compare(case, nairn, run_jaxmpm(case, conv))
            row.update(conventions=conv, wall_nairn=wall_nairn, wall_jaxmpm=time.perf_counter() - start)
            # the same case under the other conventions: how far the rules that differ move the result
            other = "jaxmpm" if conv == "nairnmpm" else "nairnmpm"
            off = compare(case, nairn, run_jaxmpm(case, other))
            row.update(other=other, v_cm_other=off["v_cm"], energy_other=off["energy"])
            rows.append(row)
            print(f"{case.name:34s} v_cm {row['v_cm']:.2e} v0 (bound {row['v_cm_bound']:.1e}), "
                  f"E_kin {row['kinetic']:.2e}, E_strain {row['strain']:.2e} E0; "
                  f"ulps px {row['px_ulps']:.2f} kin {row['kinetic_ulps']:.2f} strain {row['strain_ulps']:.2f}; "
                  f"E/E0 end {row['final_jaxmpm']:.6f} / {row['final_nairnmpm']:.6f}; "
                  f"under {other}: v_cm {row['v_cm_other']:.2e} v0, E {row['energy_other']:.2e} E0", flush=True)
    source = "run now" if binary else "stored, tests/reference/nairnmpm/"
    text = [
        "# jaxmpm against NairnMPM on `bar` (`python -m experiments.nairnmpm`)\n",
        f"NairnMPM: {version} ({source}).  Plane-strain strip one cell thick (NairnMPM) against the 1D bar "
        "(jaxmpm); E = 100, rho = 1, L = 25, v0 = 0.1, 16 cells x 2 ppc, dt = 0.1 h/c, the incremental "
        "small-strain law in both; float64; each case's shape, update, damping and length in its row (640 steps "
        "are one period).  Differences over NairnMPM's archived steps 1..N; E0 the initial energy.  `ulps`: the "
        "largest difference over half a unit in the archive's 7th digit of the value (p_x, E_kin, E_strain); "
        "<= 1 is agreement to the archive's precision.  The last column: max abs(dv_cm)/v0 and max abs(dE)/E0 "
        "with jaxmpm run under the other conventions (how far the rules that differ move the result).\n",
        "| case | jaxmpm conventions | max abs(dv_cm)/v0 | bound | max abs(dE_kin)/E0 | max abs(dE_strain)/E0 "
        "| max abs(dE)/E0 | bound | ulps p_x, E_kin, E_strain | E/E0 end jaxmpm | E/E0 end NairnMPM "
        "| other conventions: max abs(dv_cm)/v0, max abs(dE)/E0 |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        text.append(f"| {r['label']} | {r['conventions']} | {r['v_cm']:.2e} | {r['v_cm_bound']:.2e} "
                    f"| {r['kinetic']:.2e} | {r['strain']:.2e} | {r['energy']:.2e} | {r['energy_bound']:.2e} "
                    f"| {r['px_ulps']:.2f}, {r['kinetic_ulps']:.2f}, {r['strain_ulps']:.2f} "
                    f"| {r['final_jaxmpm']:.7f} | {r['final_nairnmpm']:.7f} "
                    f"| {r['other']}: {r['v_cm_other']:.2e}, {r['energy_other']:.2e} |")
    print("\n" + "\n".join(text))
    if args.out:
        os.makedirs(os.path.dirname(args.out), exist_ok=True)
        with open(args.out, "w") as f:
            f.write("\n".join(text) + "\n")


if __name__ == "__main__":
    main()
