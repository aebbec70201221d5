"""jaxmpm against NairnMPM 19.0 in 2D (issue 28, part 4): the two colliding elastic disks of
Sulsky, Chen & Schreyer (1994), in one velocity field and as two materials in contact.  Each case
is written as a NairnMPM XML input, run by NairnMPM when ``$NAIRN_BIN`` names a build (otherwise
its stored outputs, tests/reference/nairnmpm_2d/, are used), run the same way in jaxmpm, and the
two compared step by step (NairnMPM's global archive) and, at the end, particle by particle
(its particle archive, float64).

The matched set-up.  jaxmpm's ``disks`` scene (:func:`jaxmpm.scenes.disks`: its grid, particles
and parameters) with NairnMPM's ``Isotropic`` law (:class:`jaxmpm.IncrementalElastic`) in place of
its material: disks of radius 0.2 centred at (0.2, 0.2) and (0.8, 0.8) moving at +-(0.1, 0.1),
E = 1000, nu = 0.3, rho = 1000, plane strain, h = 0.05, 2 x 2 particles per cell (208 a disk),
uGIMP, USL-, dt = 1e-3, :data:`STEPS` steps (the disks' grid fields meet at step ~1000, they part
by step ~2700); float64.  NairnMPM: ``<Analysis>10`` (plane strain), ``<MPMMethod>3`` with
``<SkipPostExtrapolation/>`` (USL-), ``<GIMP type="uGIMP"/>``, ``<ConsistentUnits/>`` (numbers as
written), two ``Isotropic`` materials of the same properties, one per disk (the archive then gives
a disk's momentum; without ``<MultiMaterialMode>`` they share one velocity field).

What the NairnMPM input is (worked out from NairnMPM's reader; see :func:`nairnmpm_input`):

* the grid: ``<Grid>`` is jaxmpm's grid ([-0.15, 1.15]^2, 26 x 26 cells); NairnMPM adds one
  element layer on every side, which no particle reaches;
* the particles: one ``<mp>`` each (``matname`` its disk), at jaxmpm's position with its velocity
  (17 significant digits: they read back as jaxmpm's float64 values) and its mass given
  explicitly, ``<mass m="0.6249999999999999"/>`` (jaxmpm's ``state.mass`` = rho V0 with V0 =
  (h/2)^2 from the grid's h = 0.049999999999999996).  Without it NairnMPM computes
  rho x 4 lp_x lp_y x thickness (NairnMPM_Class/NairnMPM.cpp PreliminaryParticleCalcs, lp the
  particle's semi-size from its element) = 0.625 exactly, one bit off.  The particle size is
  NairnMPM's default ``lpx = lpy = 0.5`` of a cell (semi-size h/4, jaxmpm's uGIMP(ppc=2)); the
  thickness is 1 (``<Grid thickness>``: jaxmpm's 2D volumes are areas);
* the time step and archives as in experiments/nairnmpm.py: ``<TimeStep>`` dt, ``<MaxTime>``
  (steps - 1/2) dt, ``<GlobalArchiveTime>`` dt/2 (every step archived; not step 0), and a particle
  archive at step 0 and at the last step (``<ArchiveTime>`` past the end; NairnMPM always archives
  its last step) with ``<MPMArchiveOrder>`` "mYYN...": the defaults and the velocity, whose
  records (88 bytes: a particle's 80 padded to a crack segment's) hold every particle's position,
  original position and velocity in float64 (System/ArchiveData.cpp; :func:`parse_particles`);
* archived quantities: "Step number", "px" and "py" of disk 1 (``matname="disk1"``; the totals
  are zero, which the archive would show as round-off noise), and "Kinetic Energy" and "Strain
  Energy" of both -- seven significant digits ("%e");
* the schemes: FLIP is NairnMPM's default; PIC ``XPICOrder`` 1, XPIC(m) ``XPICOrder`` m, FMPM(k)
  ``FMPMOrder`` k of the ``PeriodicXPIC`` custom task every step; jaxmpm runs PIC and XPIC under
  ``conventions="nairnmpm"`` (the position update from v(m) + a dt; there are no boundary
  conditions, so the series start and the reaction do not matter), FLIP and FMPM on one field in
  its own, every contact case under ``conventions="nairnmpm"`` (:attr:`Case2D.conventions`);
* contact (``Case2D.contact`` other than "none"): ``<MultiMaterialMode>`` (each material its own
  velocity field) with a ``CoulombFriction`` contact law (``<Material Type="61">``: ``coeff`` -1 is
  its stick law, 0 frictionless, mu > 0 Coulomb; Materials/CoulombFriction.cpp) named by
  ``<Friction lawname="contact"/>`` (without a ``<Friction>`` the reader installs frictionless;
  Read_MPM/MPMReadHandler.cpp); jaxmpm :class:`jaxmpm.Contact` with the same law.  The normals
  (``Normals``; the reader's default is 6, logistic regression, which jaxmpm does not have):
  jaxmpm's specified ``normal=(cos a, sin a)`` (from material 0 into 1) is ``Normals="4"`` with
  ``Azimuth="a"`` (a = 45: the line of the impact; the vector as NairnMPM computes it,
  NairnMPM_Class/MeshInfo.cpp SetContactNormal, whose components differ in the last bit);
  ``"average"`` is ``Normals="2"`` (avggrad) and ``"max_gradient"`` ``Normals="0"`` (maxgrad).  The
  detection: NairnMPM's default (no ``<ContactPosition>``) takes the normal separation from the
  nodal displacements, (u^b - u^a).n, and calls the materials in contact where it is negative and
  they approach (Dp.n < 0); the disks move towards each other from t = 0, so the displacement
  separation is negative on every shared node through the impact and the rule is jaxmpm's
  ``separation=None`` (approach only).  ``<ContactPosition>s</ContactPosition>`` (the nodal
  centres of mass closer along n than s cells) is jaxmpm's ``separation=s``.  ``Dcheck`` and
  ``Vmin`` are read and ignored by NairnMPM 19.0, ``Polar`` is 3D only; stick ignores the
  separation in both codes (with ``separation=None`` in jaxmpm).

Where the codes' rules differed, each confirmed by a scratch copy of jaxmpm that followed
NairnMPM's rule and then agreed to the archive's precision (:data:`RULES`): XPIC/FMPM with contact
(NairnMPM applies the contact law to every increment of the series), the gradient normals
(NairnMPM's deformed-volume gradients) and the position separation (NairnMPM extrapolates it over
the step in the second contact call) are now jaxmpm options (``jm.Contact(series="incremental",
gradient="volume", separation_update="extrapolated")``, all selected by ``conventions="nairnmpm"``)
and those cases agree; Coulomb friction on the impact's line (NairnMPM's stick/slide test on a
round-off tangential) still differs (:data:`DIFFERS`).

Table columns: per quantity (disk 1's p_x and p_y, the kinetic and strain energy) the largest
difference over half a unit in the archive's 7th digit of the value (``ulps``; <= 1 is agreement
to the archive's precision; round-off values, the ~1e-35 strain energy of the disks' flight, are
compared to :data:`FLOOR` of p0 or E0), the first step beyond it; the largest |dp| / p0 (p0 =
disk 1's initial momentum component) and |dE| / E0; at the last step the largest particle
position difference / h and velocity difference / v0 (float64: the codes' own agreement, within
:data:`PARTICLE_TOLERANCE` where they agree); E/E0 at the end in each code.  Written to
experiments/results/nairnmpm_2d.md.

    python -m experiments.nairnmpm_2d                   # stored NairnMPM outputs (or $NAIRN_BIN)
    NAIRN_BIN=/path/to/NairnMPM python -m experiments.nairnmpm_2d --store   # rerun NairnMPM, store
    python -m experiments.nairnmpm_2d --case fmpm2-frictionless --xml       # print one case's input
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import struct
import tempfile
import time
from xml.sax.saxutils import escape

import jax

jax.config.update("jax_enable_x64", True)

import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jaxmpm as jm  # noqa: E402
from experiments.nairnmpm import (  # noqa: E402
    UPDATES,
    _decode,
    _encode,
    _num,
    archive_unit,
    execute_nairnmpm,
    nairn_version,
    parse_global,
    periodic_xpic_task,
)

E, NU, RHO, SPEED, SPACING, DT = 1000.0, 0.3, 1000.0, 0.1, 0.05, 1e-3
STEPS = 3000  # t = 3: the disks' grid fields meet at step ~1000, they touch at ~1590 and part by ~2700
REFERENCE_DIR = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "tests", "reference",
                             "nairnmpm_2d")
RESULTS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "results", "nairnmpm_2d.md")
ROOT = "disks"  # NairnMPM's archive root: disks.global, disks.<step>
QUANTITIES = ("px", "py", "kinetic", "strain")
ARCHIVE_TYPES = {"step": ("Step number", None), "px": ("px", "disk1"), "py": ("py", "disk1"),
                 "kinetic": ("Kinetic Energy", None), "strain": ("Strain Energy", None)}
NORMALS = {"specified": "4", "average": "2", "max_gradient": "0"}  # jaxmpm normal -> NairnMPM Normals
LAWS = {"stick": -1.0, "frictionless": 0.0}  # jaxmpm law -> NairnMPM CoulombFriction coeff (coulomb: mu)
FLOOR = 1e-12  # round-off floor of the archive comparisons, relative to p0 or E0 (see tolerance)
PARTICLE_TOLERANCE = 1e-12  # the final particles (float64) where the codes agree: |dx| / h and |dv| / v0


def specified_normal(azimuth: float) -> tuple:
    """NairnMPM's specified normal for ``Azimuth`` a degrees in 2D, (cos a, sin a) with its pi and
    arithmetic (NairnMPM_Class/MeshInfo.cpp SetContactNormal); at 45 degrees the components differ
    in the last bit and have length 1.0, so jaxmpm keeps the vector as given."""
    angle = 3.141592653589793 * azimuth / 180.0
    return (math.cos(angle), math.sin(angle))


@dataclasses.dataclass(frozen=True)
class Case2D:
    """One comparison.  ``scheme`` in jaxmpm's command-line form (``flip``, ``pic``, ``xpic:m``,
    ``fmpm:k``); ``contact`` "none" (one velocity field) or a law ("stick", "frictionless",
    "coulomb" with ``friction`` mu); ``normal`` "specified" (at ``azimuth`` degrees; 45 is the
    impact's line), "average" or "max_gradient"; ``separation`` None (NairnMPM: contact by
    displacements) or s cells (NairnMPM: ``<ContactPosition>s``); ``steps`` at dt = 1e-3."""

    scheme: str
    contact: str = "none"
    friction: float = 0.0
    normal: str = "specified"
    azimuth: float = 45.0
    separation: float | None = None
    steps: int = STEPS

    def __post_init__(self):
        scheme_name, _, order = self.scheme.partition(":")
        if scheme_name not in ("flip", "pic", "xpic", "fmpm") or (scheme_name in ("xpic", "fmpm") and not order):
            raise ValueError(f"Case2D: scheme {self.scheme!r}; use flip, pic, xpic:m or fmpm:k")
        if self.contact not in ("none", "stick", "frictionless", "coulomb"):
            raise ValueError(f"Case2D: contact {self.contact!r}; use none, stick, frictionless or coulomb")
        if self.normal not in NORMALS:
            raise ValueError(f"Case2D: normal {self.normal!r}; use one of {', '.join(NORMALS)}")

    @property
    def name(self) -> str:
        """The file name of the case: ``flip``, ``fmpm2-frictionless`` (plus settings off the defaults)."""
        parts = [self.scheme.replace(":", "")]
        if self.contact != "none":
            parts.append(self.contact if self.contact != "coulomb" else f"coulomb{self.friction:g}")
            if self.normal != "specified":
                parts.append(self.normal.replace("_", ""))
            elif self.azimuth != 45.0:
                parts.append(f"azimuth{self.azimuth:g}")
            if self.separation is not None:
                parts.append(f"sep{self.separation:g}")
        if self.steps != STEPS:
            parts.append(f"steps{self.steps}")
        return "-".join(parts)

    @property
    def label(self) -> str:
        scheme_name, _, order = self.scheme.partition(":")
        text = f"{scheme_name.upper()}({order})" if order else scheme_name.upper()
        if self.contact == "none":
            return f"{text}, one field"
        law = self.contact if self.contact != "coulomb" else f"Coulomb mu = {self.friction:g}"
        normal = f"normal at {self.azimuth:g} deg" if self.normal == "specified" else f"normal {self.normal}"
        detection = "" if self.separation is None else f", separation {self.separation:g} h"
        return f"{text}, {law}, {normal}{detection}"

    @property
    def conventions(self) -> str:
        """jaxmpm's conventions for the case: "nairnmpm" for PIC and XPIC (their position update from
        v(m) + a dt) and with contact (deformed-volume gradient normals, the extrapolated position
        separation, the law on the XPIC/FMPM series' increments), jaxmpm's own for FLIP and FMPM on
        one field (the codes' rules agree)."""
        return "nairnmpm" if self.scheme.partition(":")[0] in ("pic", "xpic") or self.contact != "none" else "jaxmpm"

    @property
    def differs(self) -> str:
        """The rule that differs between the codes on this case ("" where they agree; :data:`DIFFERS`)."""
        return DIFFERS.get(self.name, "")


CASES = (
    # one velocity field
    Case2D("flip"), Case2D("pic"), Case2D("xpic:2"), Case2D("fmpm:2"),
    # multimaterial contact, the normal on the impact's line, detection by displacements
    Case2D("flip", "frictionless"), Case2D("flip", "stick"), Case2D("pic", "frictionless"),
    Case2D("fmpm:2", "frictionless"), Case2D("fmpm:2", "stick"), Case2D("xpic:2", "frictionless"),
    Case2D("flip", "coulomb", friction=0.3), Case2D("flip", "coulomb", friction=0.3, azimuth=40.0),
    # NairnMPM's gradient normals and its position separation
    Case2D("flip", "frictionless", normal="average"), Case2D("flip", "frictionless", normal="max_gradient"),
    Case2D("flip", "frictionless", separation=1.0),
)

# the cases whose rules differ (case name -> the rule), each confirmed in a scratch copy (RULES)
DIFFERS = {
    "flip-coulomb0.3": ("Coulomb stick/slide test: NairnMPM compares Dp.t^ (t^ the unit tangential) with mu |Dp.n|, "
                        "which on the impact's line, where the tangential is round-off, is ~0.7 |Dp.n| and slides "
                        "along a grid axis; jaxmpm compares |Dp_t|"),
}


def case_named(name: str) -> Case2D:
    key = name.replace(":", "")
    for case in CASES:
        if case.name == key:
            return case
    raise ValueError(f"unknown case {name!r}; choose {', '.join(c.name for c in CASES)}")


# ------------------------------------------------------------------------------------- jaxmpm
def scene(case: Case2D):
    """jaxmpm's ``disks`` scene for the case (grid, particles, contact term), float64."""
    normal = specified_normal(case.azimuth) if case.normal == "specified" else case.normal
    kwargs = {}
    if case.contact != "none":
        kwargs = dict(contact=case.contact, friction=case.friction, separation=case.separation, normal=normal)
    return jm.scene("disks", scheme=jm.scheme_from_name(case.scheme), dt=DT, t_end=case.steps * DT, dtype="f64",
                    **kwargs)


def simulation(case: Case2D):
    """(sim, state, setup): the scene with :class:`jaxmpm.IncrementalElastic` for its material."""
    setup = scene(case)
    kwargs = {} if case.conventions == "jaxmpm" else {"conventions": case.conventions}
    # only the scene's contact term: its other terms (stress, body force, damping) are the ones Simulation adds
    # itself, and given again they would count twice
    contact = tuple(term for term in setup.sim.terms if isinstance(term, jm.Contact))
    sim = jm.Simulation(grid=setup.sim.grid, shape=setup.sim.shape, material=jm.IncrementalElastic(E, NU, RHO),
                        scheme=jm.scheme_from_name(case.scheme), update="USL", terms=contact, **kwargs)
    state = sim.init(setup.particles, fields=setup.fields)
    state = jax.tree_util.tree_map(lambda a: a.astype(jnp.float64) if jnp.issubdtype(a.dtype, jnp.floating) else a,
                                   state)
    return sim, state, setup


@eqx.filter_jit
def _rollout(sim, state, dt, steps, first):
    def measures(s):
        m, v = s.mass[:first], s.v[:first]
        d = sim.diagnostics(s)
        return jnp.stack([jnp.sum(m * v[:, 0]), jnp.sum(m * v[:, 1]), d["kinetic"], d["strain"]])

    def body(s, _):
        new = sim.step(s, dt)
        return new, measures(new)

    final, hist = jax.lax.scan(body, state, None, length=steps)
    return jnp.concatenate([measures(state)[None], hist]), final.x, final.v, jnp.min(jnp.linalg.det(final.F))


def run_jaxmpm(case: Case2D) -> dict:
    """The case in jaxmpm: steps 0..N of disk 1's p_x, p_y, the kinetic and strain energy, and the
    particles' final positions and velocities (in the order of the scene, disk 1 first)."""
    sim, state, setup = simulation(case)
    first = int(setup.params["n_first"])
    hist, x, v, min_j = _rollout(sim, state, jnp.float64(DT), case.steps, first)
    hist = np.asarray(hist)
    if not np.all(np.isfinite(hist)) or float(min_j) <= 0:
        raise jm.InstabilityError(case.steps, f"{case.name}: jaxmpm's run failed")
    out = {k: hist[:, i] for i, k in enumerate(QUANTITIES)}
    out.update(step=np.arange(case.steps + 1), x=np.asarray(x), v=np.asarray(v), mass=np.asarray(state.mass),
               first=first)
    return out


# ----------------------------------------------------------------------------------- NairnMPM
def particles(case: Case2D):
    """NairnMPM's material points: (x (N, 2), v (N, 2), mass (N,), material 1 or 2) from jaxmpm's scene."""
    setup = scene(case)
    x = np.asarray(setup.particles.x, dtype=np.float64)
    v = np.asarray(setup.particles.v, dtype=np.float64)
    mass = np.asarray(setup.state.mass, dtype=np.float64)
    first = int(setup.params["n_first"])
    mat = np.where(np.arange(x.shape[0]) < first, 1, 2)
    return x, v, mass, mat


def nairnmpm_input(case: Case2D) -> str:
    """The NairnMPM XML input of the case (module docstring)."""
    setup = scene(case)
    grid = setup.sim.grid
    xmin, ymin = (float(c) for c in grid.lower)
    xmax, ymax = (float(c) for c in grid.upper)
    nx, ny = grid.cells
    method, skip = UPDATES["USL"]
    scheme_name, _, order = case.scheme.partition(":")
    x, v, mass, mat = particles(case)
    lines = [
        "<?xml version='1.0'?>",
        '<!DOCTYPE JANFEAInput SYSTEM "NairnMPM.dtd">',
        '<JANFEAInput version="3">',
        "  <Header>",
        f"    <Description>{escape(f'jaxmpm experiments/nairnmpm_2d.py, disks, case {case.name}')}</Description>",
        "    <Analysis>10</Analysis>",
        "    <ConsistentUnits/>",
        "  </Header>",
        "  <MPMHeader>",
        f"    <MPMMethod>{method}</MPMMethod>",
    ]
    if skip:
        lines.append("    <SkipPostExtrapolation/>")
    lines += [
        '    <GIMP type="uGIMP"/>',
        "    <MatlPtsPerElement>4</MatlPtsPerElement>",
        f"    <ArchiveRoot>{ROOT}</ArchiveRoot>",
        "    <MPMArchiveOrder>mYYNNNNNNNNNNNNNNNN</MPMArchiveOrder>",
        f"    <ArchiveTime>{_num(10 * case.steps * DT)}</ArchiveTime>",
        f"    <TimeStep>{_num(DT)}</TimeStep>",
        f"    <MaxTime>{_num((case.steps - 0.5) * DT)}</MaxTime>",
        f"    <GlobalArchiveTime>{_num(0.5 * DT)}</GlobalArchiveTime>",
    ]
    for key in ("step",) + QUANTITIES:
        kind, material = ARCHIVE_TYPES[key]
        lines.append(f'    <GlobalArchive type="{kind}"' + (f' matname="{material}"/>' if material else "/>"))
    if case.contact != "none":
        attrs = f'Normals="{NORMALS[case.normal]}"'
        if case.normal == "specified":
            attrs += f' Azimuth="{case.azimuth:g}"'
        lines.append(f"    <MultiMaterialMode {attrs}>")
        lines.append('      <Friction lawname="contact"/>')
        if case.separation is not None:
            lines.append(f"      <ContactPosition>{_num(case.separation)}</ContactPosition>")
        lines.append("    </MultiMaterialMode>")
    lines += [
        "  </MPMHeader>",
        "  <Mesh>",
        f'    <Grid xmin="{_num(xmin)}" xmax="{_num(xmax)}" ymin="{_num(ymin)}" ymax="{_num(ymax)}" thickness="1.0">',
        f'      <Horiz nx="{nx}"/>',
        f'      <Vert ny="{ny}"/>',
        "    </Grid>",
        "  </Mesh>",
        "  <MaterialPoints>",
        "    <PointList>",
    ]
    lines += [f'      <mp matname="disk{k}"><pt x="{_num(p[0])}" y="{_num(p[1])}"/>'
              f'<vel x="{_num(u[0])}" y="{_num(u[1])}"/><mass m="{_num(m)}"/></mp>'
              for p, u, m, k in zip(x, v, mass, mat)]
    lines += ["    </PointList>", "  </MaterialPoints>"]
    for k in (1, 2):
        lines += [
            f'  <Material Type="1" Name="disk{k}">',
            f"    <rho>{_num(RHO)}</rho>",
            f"    <E>{_num(E)}</E>",
            f"    <nu>{_num(NU)}</nu>",
            "    <alpha>0.0</alpha>",
            "  </Material>",
        ]
    if case.contact != "none":
        coeff = case.friction if case.contact == "coulomb" else LAWS[case.contact]
        lines += ['  <Material Type="61" Name="contact">', f"    <coeff>{_num(coeff)}</coeff>", "  </Material>"]
    lines += periodic_xpic_task(case.scheme)
    lines.append("</JANFEAInput>")
    return "\n".join(lines) + "\n"


HEADER_LENGTH = 64  # NairnMPM's particle archive: a 64-byte header, then one record per particle
RECORD = struct.Struct("<idh2x" + "d" * 8)  # elem, mass, material, pad, angle, thickness, x, y, x0, y0, vx, vy
# each record is padded to the larger of a particle's and a crack segment's record (2D defaults: 88 bytes)
STRIDE = max(RECORD.size, struct.calcsize("<idh2x") + 2 * 4 + 8 * 8)


def parse_particles(path: str) -> dict:
    """NairnMPM's binary particle archive (``<MPMArchiveOrder>`` "mYY" then N: the defaults and the
    velocity; 2D, little-endian): {mass, material, x (N, 2), x0 (N, 2), v (N, 2)} in its order."""
    with open(path, "rb") as f:
        data = f.read()
    header = data[:HEADER_LENGTH]
    if not header.startswith(b"ver6"):
        raise RuntimeError(f"{path}: not a NairnMPM version-6 archive ({header[:8]!r})")
    order_len = header[4]
    order = header[5:5 + order_len].decode()
    if order[0] != "i" or order[1:3] != "YY" or set(order[3:]) - {"N"}:
        raise RuntimeError(f"{path}: archive order {order!r}; expected 'iYY' then N (little-endian, velocity only)")
    body = data[HEADER_LENGTH:]
    if len(body) % STRIDE:
        raise RuntimeError(f"{path}: {len(body)} bytes of records is not a multiple of {STRIDE}")
    rows = np.array([RECORD.unpack_from(body, k) for k in range(0, len(body), STRIDE)], dtype=np.float64)
    return dict(mass=rows[:, 1], material=rows[:, 2].astype(int), x=rows[:, 5:7], x0=rows[:, 7:9], v=rows[:, 9:11])


def run_nairnmpm(case: Case2D, workdir: str, binary: str | None = None, timeout: float = 1200.0) -> dict:
    """Run NairnMPM on the case's input in ``workdir``, one thread: its archived steps 1..N of the
    quantities (floats and the archive's text), the particles' final positions and velocities in
    jaxmpm's order (matched by their initial positions), the input and the version."""
    xml = nairnmpm_input(case)
    binary = execute_nairnmpm(case.name, xml, workdir, binary, timeout)
    arch = parse_global(os.path.join(workdir, f"{ROOT}.global"))
    # a material's column is "<type> mat <n>", n NairnMPM's number of the material (names are numbered in
    # the order the input first mentions them: disk1, named by the archive's first matname, is 1)
    names = {k: ARCHIVE_TYPES[k][0] + (" mat 1" if ARCHIVE_TYPES[k][1] else "") for k in ("step",) + QUANTITIES}
    step = arch[names["step"]].astype(np.int64)
    if not np.array_equal(step, np.arange(1, case.steps + 1)):
        raise RuntimeError(f"{case.name}: NairnMPM archived steps {step[:3]}...{step[-3:]} ({step.size}), "
                           f"expected 1..{case.steps}")
    out = dict(step=step, text={k: arch["text"][names[k]] for k in QUANTITIES}, xml=xml, version=nairn_version(binary))
    for k in QUANTITIES:
        out[k] = arch[names[k]]
        out[f"{k}_unit"] = archive_unit(_encode(out["text"][k])[1])
    final = parse_particles(os.path.join(workdir, f"{ROOT}.{case.steps}"))
    x, _, mass, _ = particles(case)
    index = {tuple(p): k for k, p in enumerate(final["x0"])}
    order = np.array([index[tuple(p)] for p in x])  # NairnMPM's record of each jaxmpm particle
    if not np.array_equal(final["mass"][order], mass):
        raise RuntimeError(f"{case.name}: NairnMPM's particle masses differ from jaxmpm's")
    out["x"], out["v"] = final["x"][order], final["v"][order]
    return out


# ------------------------------------------------------------------------- the stored outputs
def store(case: Case2D, out: dict, directory: str = REFERENCE_DIR) -> str:
    """Write NairnMPM's outputs for the case to ``<directory>/<case>.npz``: each quantity's archive
    digits, the final particle positions and velocities (float64, jaxmpm's order), the XML input
    (UTF-8 bytes) and NairnMPM's version."""
    os.makedirs(directory, exist_ok=True)
    arrays = {}
    for k in QUANTITIES:
        arrays[f"{k}_digits"], arrays[f"{k}_exp10"] = _encode(out["text"][k])
    path = os.path.join(directory, f"{case.name}.npz")
    np.savez_compressed(path, first_step=np.int32(out["step"][0]), steps=np.int32(out["step"].size),
                        x=out["x"], v=out["v"], xml=np.frombuffer(out["xml"].encode(), dtype=np.uint8),
                        version=np.str_(out["version"]), case=np.str_(repr(case)), **arrays)
    return path


def load_reference(case: Case2D, directory: str = REFERENCE_DIR) -> dict:
    """NairnMPM's stored outputs for the case (:func:`store`): step, the quantities (floats of the
    archive's digits) and their ``*_unit`` (a unit in the 7th digit), x, v, xml, version."""
    with np.load(os.path.join(directory, f"{case.name}.npz")) as z:
        step = np.arange(int(z["first_step"]), int(z["first_step"]) + int(z["steps"]))
        out = dict(step=step, x=z["x"], v=z["v"], xml=z["xml"].tobytes().decode(), version=str(z["version"]))
        for k in QUANTITIES:
            out[k] = _decode(z[f"{k}_digits"], z[f"{k}_exp10"])
            out[f"{k}_unit"] = archive_unit(z[f"{k}_exp10"])
    return out


def tolerance(nairn: dict, key: str, scale: float, rounding: float = 0.5):
    """The archive's resolution at each step: ``rounding`` (half) a unit in the 7th digit of the
    archived value, and not below :data:`FLOOR` x ``scale`` (p0 or E0): a value that is round-off
    in both codes (the strain energy of the disks' flight, ~1e-35 E0) agrees to round-off, not to
    its digits."""
    return np.maximum(rounding * nairn[f"{key}_unit"], FLOOR * scale)


def scales(jaxm: dict) -> dict:
    """Each quantity's scale: p0 (disk 1's initial momentum component) or E0 (the initial energy)."""
    p0 = abs(float(jaxm["px"][0]))
    e0 = float(jaxm["kinetic"][0] + jaxm["strain"][0])
    return {"px": p0, "py": p0, "kinetic": e0, "strain": e0}


def compare(case: Case2D, nairn: dict, jaxm: dict) -> dict:
    """The agreement over NairnMPM's archived steps (``*_ulps``: the largest difference over half a
    unit in the 7th digit of the archived value, <= 1 is agreement to the archive's precision;
    ``*_first`` the first step beyond it), the largest differences relative to p0 or E0, and the
    final particles' differences / h and / v0 (``agrees``: all within the archive's precision and
    :data:`PARTICLE_TOLERANCE`)."""
    idx = nairn["step"]
    scale = scales(jaxm)
    out = dict(case=case.name, label=case.label, conventions=case.conventions, differs=case.differs)
    for k in QUANTITIES:
        diff = np.abs(jaxm[k][idx] - nairn[k])
        ratio = diff / tolerance(nairn, k, scale[k])
        out[f"{k}_ulps"] = float(np.max(ratio))
        out[f"{k}_first"] = int(idx[np.argmax(ratio > 1.001)]) if np.any(ratio > 1.001) else None
        out[f"{k}_rel"] = float(np.max(diff)) / scale[k]
    out["x_rel"] = float(np.max(np.abs(jaxm["x"] - nairn["x"]))) / SPACING
    out["v_rel"] = float(np.max(np.abs(jaxm["v"] - nairn["v"]))) / SPEED
    e0 = scale["kinetic"]
    out["final_jaxmpm"] = float(jaxm["kinetic"][-1] + jaxm["strain"][-1]) / e0
    out["final_nairnmpm"] = float(nairn["kinetic"][-1] + nairn["strain"][-1]) / e0
    first = [out[f"{k}_first"] for k in QUANTITIES if out[f"{k}_first"] is not None]
    out["first_step"] = min(first) if first else None
    out["agrees"] = (not first and out["x_rel"] <= PARTICLE_TOLERANCE and out["v_rel"] <= PARTICLE_TOLERANCE)
    return out


# The rules that differ, as confirmed with scratch copies of jaxmpm (not part of the repository)
RULES = """\
## The rules that differ

Each was located in NairnMPM 19.0's source (commit 7f47b022) and confirmed by a scratch copy of the
jaxmpm rule that follows NairnMPM's (patched at run time outside the repository): with it the case
agrees with NairnMPM to the archive's precision (all four quantities <= 1 ulp at every step) and the
final particles to round-off.

1. **Contact in the XPIC/FMPM series** (FMPM(2) frictionless and stick, XPIC(2) frictionless).
   jaxmpm (003 eqs. 3.18, 3.22): v(k) = series_k(v~) - series_{k-1}(Dv), Dv = Dp/m the change of the
   first contact call.  NairnMPM (NairnMPM_Class/XPICExtrapolationTask.cpp Execute, GetDeltaV ->
   ImposeIncrementalContact, UpdateXStar; Nodes/MatVelocityField.cpp XPICSupport;
   Nodes/CrackVelocityFieldMulti.cpp MaterialXPICIncrementOnCVF, with the cache that the lumped
   contact's calls leave, Nodes/MaterialContactNode.cpp SetContactInfo, ContactSetDelPi): the
   series is summed as increments, D_1 = v~ (FMPM; XPIC: D_1 = v, then v* = v~ + the increments),
   D_k = Z (I - S+S) D_{k-1}, and on every contact node the law is applied again to the accumulated
   stick change, A += (m^a/m) sum_b m^b D_k^b - m^a D_k^a (starting from the stick change of the
   updated momenta, the second contact call's), L = law(A) with the step's normal and
   separation, and D_k^a += (L - N)/m^a, D_k^b -= (L - N)/m^b, N = L (N starting from the second
   call's applied change); for XPIC the changes also go to the force (AddFtotScaled).  With stick
   every increment moves with the centre of mass, so FMPM stick is NairnMPM's one-field FMPM exactly
   (E/E0 0.8066210 both); jaxmpm's does not revert (0.7873).  Effect: FMPM(2) frictionless E/E0 at
   t = 3 0.4447 (jaxmpm) against 0.5800 (NairnMPM), particles 0.29 h apart; XPIC(2) frictionless 0.4893
   against 0.3784.  Scratch (jaxmpm's FMPM/XPIC update with the incremental contact): FMPM(2) stick
   and frictionless, XPIC(2) frictionless <= 1 ulp at every step, final particles 3.6e-14 h, 1.1e-14 v0.
   Now the option ``jm.Contact(series="incremental")`` (set by ``conventions="nairnmpm"``; the law on
   the increments is jaxmpm's :class:`jaxmpm.physics.contact.ContactIncrements`, the loop
   ``jaxmpm.transfer.series.exchange_increments``): these cases agree (final particles <= 4.1e-14 h).
2. **Gradient normals** (``normal="average"``, ``"max_gradient"``).  jaxmpm: g^a = sum_p M_p G_pi.
   NairnMPM: g^a = sum_p V_p G_pi with V_p = det(F_p) m_p / rho_p, the deformed area times the thickness
   (Nodes/CrackVelocityFieldMulti.cpp AddVolumeGradient, MPM_Classes/MatPoint2D.cpp GetVolume
   DEFORMED_AREA_FOR_GRADIENT); avggrad n = (g^0 - g^1)/|.|, maxgrad the larger (GetNormalVector) as in
   jaxmpm.  Effect: from step ~1250, particles 6.4e-3 h (average) and 4.9e-2 h (max_gradient) apart,
   E/E0 at t = 3 0.96995 / 0.96957 and 0.96415 / 0.96875.  Scratch (jaxmpm's Contact with g^a = sum_p
   det(F_p) V0_p G_pi): <= 1 ulp at every step, final particles 2.0e-14 h and 1.6e-14 h.  Now the option
   ``jm.Contact(gradient="volume")`` (set by ``conventions="nairnmpm"``): these cases agree.
3. **Position separation** (``separation=1`` with ``<ContactPosition>1``).  Both take
   deln = (x^1 - x^0).n - s h from the nodal centres of mass of the step's start (NairnMPM:
   Cracks/CrackSurfaceContact.cpp MaterialSeparation, the perpendicular cell size h on a square grid).
   jaxmpm uses deln <= 0 in both contact calls.  NairnMPM, in the second call (on the updated
   momenta), extrapolates it over the step (Materials/CoulombFriction.cpp GetFrictionalDeltaMomentum):
   deln+ = deln + dt (Dp+.n - dt DF.n / 2) / m_red < 0, Dp+ = (m^0/m) p+ - p^0+ the stick change of the
   updated momenta, DF = (m^0/m) f - f^0 that of the nodal forces, m_red = m^0 m^1 / m.  Effect: from
   step ~1490; E/E0 at t = 3 0.9422 (jaxmpm) against 0.8948 (NairnMPM), particles 1.7e-2 h apart.
   Scratch (the second call with deln+ < 0): <= 1 ulp at every step, final particles 1.6e-14 h.  Now the
   option ``jm.Contact(separation_update="extrapolated")`` (set by ``conventions="nairnmpm"``): agrees.
   (In the default detection by displacements the same extrapolation applies to (u^1 - u^0).n, which
   stays far below zero here, so it changes nothing.)
4. **Coulomb stick/slide test on the impact's line** (mu = 0.3, normal at 45 degrees).  jaxmpm slides
   where |Dp_t| > mu |Dp.n|, Dp_t = Dp - (Dp.n) n, to Dp = (Dp.n) n + mu |Dp.n| Dp_t / |Dp_t|.
   NairnMPM (Materials/CoulombFriction.cpp GetFrictionalDeltaMomentum): t^ = Dp_t / |Dp_t| turned so
   that dott = Dp.t^ >= 0, slides where dott > mu (-Dp.n), to Dp = (Dp.n) n + mu (-Dp.n) t^.  The same
   where Dp_t is real; on the nodes of the line of centres, where the tangential stick change is zero
   but for round-off, Dp_t is round-off along a grid axis, n.t^ = +-0.707, so dott = |(Dp.n)(n.t^) +
   |Dp_t|| ~ 0.7 |Dp.n| > 0.3 |Dp.n|: NairnMPM slides, by mu |Dp.n| along that axis.  Seen first at
   step 1002, on the first contact node (m^0 = m^1 = 1e-11): NairnMPM's Coulomb run leaves its own
   frictionless and stick runs (which equal each other and jaxmpm's there) by 7e-16 in position, then
   by 1.3e-13 in velocity at step 1003, on the particle on the line of centres, whose change is no
   longer along the line; jaxmpm's stick changes on those nodes, in NairnMPM's arithmetic, give
   n.t^ = +-0.707 and dott = 0.707 |Dp.n|.  Effect: small, the archive 1.06 (p_y) and 1.16 (E_strain)
   ulps, particles 2.2e-11 h and 2.2e-10 v0 apart (5e-14 in the cases that agree).  Confirmed by the
   case with the normal at 40 degrees, where Dp_t is real on every node: it agrees (<= 1 ulp,
   particles 2.4e-14 h).  NairnMPM's slide direction there is its own round-off, so a scratch copy
   of its arithmetic in jaxmpm (whose sums round differently) does not reproduce it bit for bit
   (1.14 ulps).
"""


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--case", action="append", help="a case name (flip, fmpm2-frictionless; repeatable)")
    parser.add_argument("--store", action="store_true",
                        help="store NairnMPM's outputs under tests/reference/nairnmpm_2d/ (needs $NAIRN_BIN)")
    parser.add_argument("--xml", action="store_true", help="print the cases' NairnMPM inputs and stop")
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
            start = time.perf_counter()
            jaxm = run_jaxmpm(case)
            row = compare(case, nairn, jaxm)
            row.update(wall_nairn=wall_nairn, wall_jaxmpm=time.perf_counter() - start)
            rows.append(row)
            print(f"{case.name:30s} ulps px {row['px_ulps']:.2f} py {row['py_ulps']:.2f} "
                  f"kin {row['kinetic_ulps']:.2f} strain {row['strain_ulps']:.2f} (first > 1: {row['first_step']}); "
                  f"x {row['x_rel']:.1e} h, v {row['v_rel']:.1e} v0; E/E0 end {row['final_jaxmpm']:.6f} / "
                  f"{row['final_nairnmpm']:.6f}", flush=True)
    text = table(rows, version, "run now" if binary else "stored, tests/reference/nairnmpm_2d/", cases[0].steps)
    print("\n" + text)
    if args.out:
        os.makedirs(os.path.dirname(args.out), exist_ok=True)
        with open(args.out, "w") as f:
            f.write(text)


def table(rows, version, source, steps) -> str:
    """The results page: the set-up, one row per case, and :data:`RULES`."""
    text = [
        "# jaxmpm against NairnMPM on `disks` (`python -m experiments.nairnmpm_2d`)\n",
        f"NairnMPM: {version} ({source}).  Two elastic disks (Sulsky et al. 1994; jaxmpm's `disks` scene: grid, "
        "particles, parameters) with NairnMPM's Isotropic law (jm.IncrementalElastic), E = 1000, nu = 0.3, "
        f"rho = 1000, plane strain, h = 0.05, 2x2 ppc, uGIMP, USL-, dt = 1e-3, {steps} steps; float64.  Contact: "
        "NairnMPM's multimaterial mode with its CoulombFriction law, detection by displacements (jaxmpm "
        "`separation=None`) unless a separation is given (NairnMPM `<ContactPosition>`), the normal specified "
        "(`Normals=\"4\"`, `Azimuth`) unless named.  `ulps`: the largest difference over half a unit in the "
        "archive's 7th digit (disk 1's p_x, p_y, the kinetic and strain energy, every step); <= 1 is agreement to "
        "the archive's precision.  dp/p0, dE/E0: the largest differences relative to disk 1's initial momentum "
        "and the initial energy.  Final x, v: the particles at the last step (NairnMPM's float64 particle "
        f"archive), the largest difference / h and / v0 (agreement: <= {PARTICLE_TOLERANCE:g}).\n",
        "| case | jaxmpm conventions | ulps p_x, p_y, E_kin, E_strain | first step > 1 ulp | max dp/p0 "
        "| max dE_kin/E0, dE_strain/E0 | final x / h | final v / v0 | E/E0 end jaxmpm | E/E0 end NairnMPM | verdict |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    def ulps(value):
        return f"{value:.2f}" if value < 100 else f"{value:.2g}"

    for r in rows:
        verdict = "agrees" if r["agrees"] else (f"differs: {r['differs']}" if r["differs"] else "DIFFERS (unexplained)")
        text.append(f"| {r['label']} | {r['conventions']} | "
                    f"{', '.join(ulps(r[k + '_ulps']) for k in QUANTITIES)} | {r['first_step'] or '-'} "
                    f"| {max(r['px_rel'], r['py_rel']):.1e} | {r['kinetic_rel']:.1e}, {r['strain_rel']:.1e} "
                    f"| {r['x_rel']:.1e} | {r['v_rel']:.1e} | {r['final_jaxmpm']:.7f} | {r['final_nairnmpm']:.7f} "
                    f"| {verdict} |")
    return "\n".join(text) + "\n\n" + RULES


if __name__ == "__main__":
    main()
