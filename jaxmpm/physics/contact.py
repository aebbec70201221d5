"""Multimaterial mode and contact (000 ch. 4, 003 ch. 3).

In multimaterial mode each material (body) extrapolates to its own velocity field (003 eq. 3.1:
p = p^a + p^b, m = m^a + m^b).  jaxmpm stores the fields of M materials as one nodal array of
M x n rows -- material a's copy of node i is row a n + i -- and gives each particle's stencil the
offset of its material (:func:`material_stencil`).  Every transfer of the library then works per
material unchanged: the one P2G scatter assembles m^a, p^a and f^a (000 eqs. 4.1-4.13), S+ is
per material (000 eq. 4.10), a gather reads the particle's own material's field, and XPIC/FMPM's
series run on S+^a S.  A one-material model has no offset and runs today's code.

:class:`Contact` is the physics term that couples the fields on *contact nodes*, nodes where both
materials have mass.  Its grid action applies a contact law twice, in the lumped form of 003
eqs. (3.9), (3.12):

1. to the extrapolated momenta p^a0 -> p^a = p^a0 + Dp^a  (velocities v^a for the strain update
   and the position update, 003 eq. 3.21);
2. to the updated momenta p^a + f^a dt -> + Dp^a+  (the contact force f^aC dt = Dp^a+, 003 eq. 3.19).

The stick change of material a (003 eq. 3.12) is  Dp(0) = (m^a p^b - m^b p^a) / m,  the change
that moves both materials with the centre-of-mass velocity; Dp^b = -Dp^a, so sum_a Dp^a = 0
(000 eq. 4.12).  With n the contact normal (pointing from material 0 into material 1) and
Dp(0) = Dp_n n + Dp_t, the laws are (003 eq. 3.9 with k_i t_i the allowed tangential slip):

* ``"stick"``         perfect interface: Dp = Dp(0) on every contact node, approaching or not;
* ``"frictionless"``  Dp = Dp_n n where the materials approach (Dp_n < 0), else 0;
* ``"coulomb"``       where approaching: stick if |Dp_t| <= mu |Dp_n|, else
                      Dp = Dp_n n + mu |Dp_n| Dp_t / |Dp_t| (sliding with friction mu).

**Normals.**  One normal n per node for the pair, from material 0 into material 1 (material 1
uses -n), so the two changes are equal and opposite and momentum is conserved (Nairn contact notes
§3.2: normals found per material that are not equal and opposite do not conserve it).  The
gradient options use the material mass gradients g^a_i = sum_p M_p G_pi.  G_pi is the gradient of
S_i at the particle, so g^a points out of material a (a particle on the -x side of node i has
G_pi > 0).  NairnMPM extrapolates the deformed-volume gradients sum_p J_p V0_p G_pi instead (notes
§3.2, for bodies of different densities; NairnMPM 19.0, CrackVelocityFieldMulti AddVolumeGradient):
``gradient="volume"`` (set by ``Simulation(conventions="nairnmpm")``); they differ from the mass
gradients wherever J != 1, even for bodies of one density.  ``normal=``

* ``"first"`` (default): material 0's, n = g^0 / |g^0| (notes eq. 3.1 for material 0) -- body 0
  is the reference ("master") surface: exact where body 0 is flat, so number the flat (or flatter)
  body 0;
* ``"max_gradient"``: the material whose gradient is larger on the node, n = g^0 / |g^0| if
  |g^0| >= |g^1|, else -g^1 / |g^1| (NairnMPM's "maxgrad", notes eq. 3.3) -- independent of the
  numbering (up to exact ties, which go to material 0);
* ``"average"``: n = (g^0 - g^1) / |g^0 - g^1| (NairnMPM's "avggrad", notes eq. 3.2, which adds
  material 0's gradient to material 1's taken towards 1) -- symmetric in the two materials;
* a vector, e.g. ``normal=(0.0, 1.0)``: that unit vector on every node, from material 0 into
  material 1 (NairnMPM's "specify", notes §3.3), for contact surfaces of one known orientation.

Near a corner of one body on the face of the other, the gradient of the cornered body tilts (its
free face adds to it), and a tilted normal counts tangential sliding as approach: the bodies
plough.  Measured on a block launched at 1 m/s along a flat slab (the ``slide`` scene with
``theta=0, speed=1``, mu = 0.2, gravity ramped over 0.05 s, FLIP, uGIMP; deceleration / mu g at
t = 0.15; tests/test_contact_scenes.py runs h = 1/32):

======================  ======  ======  ======  ========  ========
h                       1/32    1/40    1/48    1/56      1/64
======================  ======  ======  ======  ========  ========
"first" (slab = 0)      0.9974  0.9982  1.0025  1.0052    0.9975
"max_gradient"          0.9972  0.9979  1.0026  unstable  unstable
"average"               1.446   1.361   1.334   2.151     1.778
======================  ======  ======  ======  ========  ========

With g = 0 (no normal load) "first", "max_gradient" and the specified (0, 1) leave the block's
velocity unchanged to round-off; "average" brakes it at 1.75 m/s^2 and lifts it at 0.19 m/s
(h = 1/32, t = 0.05).  "max_gradient" works where the slab's top lies on a node line (1/32, 1/40,
1/48) and fails where it lies half a cell off (1/56, 1/64): on the node row half a cell above the
slab, the block's gradient (its bottom and front faces together) outgrows the slab's tail and the
block's tilted normal wins.  "first" depends on the numbering: with the block numbered 0 it brakes
at 4.06 mu g (1/32) and goes unstable (1/64).  No rule on g^0 and g^1 alone tells a flat face from
a corner; NairnMPM's default, a logistic regression of the particle positions around each node
(notes §3.4), does, but needs per-node particle moments that this term does not scatter.  On the
``disks`` impact (frictionless, separation 1 cell) the energy minimum is 0.955 ("average"), 0.951
("first"), 0.937 ("max_gradient").

Contact nodes are the nodes where both materials have mass -- the bodies then interact from about
one cell apart.  The optional separation criterion (``separation=s``, in cells) narrows them to
the nodes where the materials' nodal centres of mass x^a_i = sum_p S_pi M_p X_p / m^a_i are closer
along the normal than s h: (x^1 - x^0) . n <= s h (NairnMPM's contact by position,
``<ContactPosition>``).  In the second application, on the updated momenta, NairnMPM moves the gap
over the step, (x^1 - x^0) . n - s h + dt (Dp+ . n - dt Df . n / 2) / m_red < 0 (Dp+, Df the stick
changes of p + f dt and of f, m_red = m^0 m^1 / m; CoulombFriction GetFrictionalDeltaMomentum):
``separation_update="extrapolated"`` (set by ``conventions="nairnmpm"``); the default "start" keeps
the gap of the step's start in both applications.

More than two materials (``materials=M``): each material a meets *the rest* on a node -- the
other materials' mass m - m^a and momentum p - p^a as one body (NairnMPM's multimaterial contact)
-- with the normal n^a from a into the rest ("average": g^a - sum_{b != a} g^b; "first": the
gradient of the lowest-numbered material present on the node, +- for that material and the
others; "max_gradient": g^a or -sum_{b != a} g^b, whichever is larger, a tie going to the side of
the lowest-numbered material present; a vector: +- it as for "first").  The law gives Dp^a for
every a; where more than two materials meet, sum_a Dp^a need not vanish, and the imbalance
r = sum_a Dp^a is taken back in proportion to mass, Dp^a -= m^a r / m: the same velocity change
r / m for every material, so the relative velocities the law set are kept and sum_a Dp^a = 0
(000 eq. 4.12).  With two materials the rest is the other material, n^1 = -n^0 and
Dp^1 = -Dp^0 exactly; the two-material code path is that special case.

Order with velocity boundary conditions on the same node: contact first, on momenta, then the
conditions on the velocities (NairnMPM's order, 003 §2.1 "Reimpose velocity boundary
conditions"): a fixed node stays fixed whatever contact asked.

**Contact in XPIC(m)'s and FMPM(k)'s series** (m, k >= 2), ``series=``:

* ``"separate"`` (default, 003 eqs. 3.16-3.22): the series runs on the velocities after the
  exchange and subtracts the series of the first change, v(k) = series_k(v~) - series_{k-1}(Dp/m)
  (:func:`jaxmpm.transfer.series.exchange_series`; ``series_correction=False`` drops that term);
* ``"incremental"`` (NairnMPM 19.0's rule): the series is summed as increments,
  D_1 = v~ (FMPM; XPIC: v, the sum is then v(m) + a dt = v~ + the increments),
  D_k = Z (I - S+S) D_{k-1} (Z the velocity conditions), and on every contact node the law acts
  again on each increment: with A the accumulated stick change (from the stick change of p + f dt,
  the second application's) and N the change applied so far (from the second application's Dp+),
  A += (m^0 m^1 D_k^1 - m^1 m^0 D_k^0)/m, L = law(A) with the step's normal and gap (moved over the
  step by A under ``separation_update="extrapolated"``), D_k^0 += (L - N)/m^0, D_k^1 -= (L - N)/m^1,
  N = L (:class:`ContactIncrements`, summed by :func:`jaxmpm.transfer.series.exchange_increments`).
  After the series the node's change is the law of the whole series' stick change.  For XPIC
  these changes are a force (NairnMPM's ``AddFtotScaled``): a += sum_k (L_k - N_k)/(m dt) and v(m)
  is the rest, so S(v(m) + a dt) is NairnMPM's S v*; FMPM's stay velocities.  The conditions hold
  on the result (the law acts after the increments' zeroing, as in NairnMPM, and may move a
  constrained component within the series).  FMPM's strain-update series (USF, MUSL) does the same
  from the first application (A from the stick change of p, N its Dp; the gap moved by A alone,
  NairnMPM's zero ``startDelFi``).  With stick every increment moves with the centre of mass, so
  FMPM with stick is the one-field FMPM exactly (the default is not).  The series is summed as the
  increments whatever the scheme's ``series=`` form (binomial and Neumann agree to round-off
  without contact).  Sources: NairnMPM_Class/XPICExtrapolationTask (Execute, GetDeltaV,
  ImposeIncrementalContact, UpdateXStar), Nodes/MatVelocityField (XPICSupport),
  Nodes/CrackVelocityFieldMulti (MaterialXPICIncrementOnCVF), Nodes/MaterialContactNode
  (SetContactInfo, ContactSetDelPi), Materials/CoulombFriction (GetFrictionalDeltaMomentum).
  Two materials (more: an InputError; jaxmpm's multimaterial law, which takes the momentum
  imbalance back, is not NairnMPM's either).  Selected by ``conventions="nairnmpm"`` with
  ``gradient="volume"`` and ``separation_update="extrapolated"``.  On the ``disks`` impact
  (experiments/nairnmpm_2d.py): FMPM(2) frictionless E/E0 at t = 3 0.4447 (separate) against
  0.5800 (incremental, = NairnMPM's), XPIC(2) frictionless 0.4893 against 0.3784.  The particles'
  ``contact_force`` is the second application's force in both forms.
"""

from __future__ import annotations

import copy
import math
import numbers

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..core.errors import check
from ..core.fields import ParticleField
from ..core.linalg import det
from ..core.registry import Parameter, register_term
from ..core.safe import safe_norm, safe_unit
from ..core.validate import FINITE, NON_NEGATIVE, concrete, fail, finite_vector, positive_int, show
from ..transfer.contractions import Gradient, Weighted
from ..transfer.operators import safe_divide
from .term import Term

LAWS = ("stick", "frictionless", "coulomb")
# the weights of the gradients behind the normals: "mass", g^a = sum_p M_p G_pi; "volume", the deformed
# volume, g^a = sum_p J_p V0_p G_pi (NairnMPM 19.0, CrackVelocityFieldMulti AddVolumeGradient)
GRADIENTS = ("mass", "volume")
# the separation criterion in the second application (on p + f dt): "start", the gap at the step's
# start; "extrapolated", the gap moved over the step by dt (Dp+ . n - dt Df . n / 2) / m_red (NairnMPM
# 19.0, CoulombFriction GetFrictionalDeltaMomentum)
SEPARATION_UPDATES = ("start", "extrapolated")
NORMALS = ("first", "max_gradient", "average")  # or a vector: the specified normal
# the exchange in XPIC(m)/FMPM(k)'s series (m, k >= 2): "separate", the order k-1 series of the first change
# Dp/m subtracted (003 eqs. 3.18, 3.22); "incremental", the law applied again to every increment of the series
# (NairnMPM 19.0, CrackVelocityFieldMulti MaterialXPICIncrementOnCVF; :class:`ContactIncrements`)
SERIES = ("separate", "incremental")


def normal_option(owner: str, value):
    """The ``normal`` option checked: one of :data:`NORMALS`, or a vector -- the specified normal,
    returned as a unit tuple of floats."""
    if isinstance(value, str):
        if value not in NORMALS:
            fail(owner, f"normal = {show(value)}; choose one of {', '.join(map(repr, NORMALS))}, "
                        "or give a vector (the specified normal from material 0 into material 1)")
        return value
    if isinstance(value, (numbers.Number, np.generic)) or (hasattr(value, "ndim") and value.ndim == 0):
        fail(owner, f"normal = {show(value)}; give a name ({', '.join(map(repr, NORMALS))}) or a vector",
             "a unit vector from material 0 into material 1, e.g. (0, 1)")
    items = finite_vector(owner, "normal", value, fix="a unit vector from material 0 into material 1, e.g. (0, 1)")
    length = math.sqrt(sum(c * c for c in items))
    if not 1 <= len(items) <= 3 or length == 0:
        fail(owner, f"normal = {show(value)} must be a non-zero vector of 1 to 3 components",
             "a unit vector from material 0 into material 1, e.g. (0, 1)")
    return tuple(c / length for c in items)


class Contact(Term):
    """Materials (bodies), each with its own velocity field, coupled by a contact law on the nodes
    where two or more have mass (multimaterial mode; the module ``jaxmpm.physics.contact`` has the
    laws, the normals, the separation criterion and the series in full, 003 ch. 3).  Particles
    carry their material id in the field ``material`` (0..M-1; ``sim.init(particles,
    fields={"material": ids})``).

    Args:
        law: "stick" (perfect interface), "frictionless" (default) or "coulomb".
        friction: the Coulomb coefficient mu >= 0 (default 0.0); a differentiable leaf (the
            parameter ``friction``), non-zero only with ``law="coulomb"``.
        normal: the contact normal, from material 0 into material 1: "first" (default,
            material 0's mass gradient), "max_gradient", "average", or a vector (that unit
            direction on every node; an array leaf, so another vector compiles nothing new).
        materials: M, the number of materials, an integer >= 2 (default 2).
        separation: the gap, in cells, below which the bodies touch: a node is a contact node
            only where the materials' nodal centres of mass are closer than ``separation`` h
            along the normal (an array leaf: another value compiles nothing new); None (the
            default): wherever both have mass.
        series_correction: under XPIC(m)/FMPM(k), subtract the series of the exchange Dp/m
            (003 eqs. 3.18, 3.22; default True); False drops that term.
        gradient: the gradients behind the normals: "mass" (default, sum_p M_p G_pi) or
            "volume" (sum_p J_p V0_p G_pi, NairnMPM's).
        separation_update: the gap of the second application (on p + f dt): "start" (default,
            the step's start) or "extrapolated" (moved over the step, NairnMPM's).
        series: the exchange in XPIC/FMPM's series: "separate" (default, 003 eqs. 3.16-3.22) or
            "incremental" (the law on every increment, NairnMPM's; two materials only).
    """

    law: str = eqx.field(static=True)
    # the normal: a name of NORMALS, or "specified" for ``direction``, the given unit vector (a leaf, so that
    # another vector compiles nothing new; None with a name)
    normal_rule: str = eqx.field(static=True)
    direction: jnp.ndarray | None
    materials: int = eqx.field(static=True)
    friction: jnp.ndarray
    # the separation criterion in cells, a leaf (another value compiles nothing new); None: off (a
    # different program: no mass moments)
    separation: jnp.ndarray | None
    series_correction: bool = eqx.field(static=True)
    gradient: str = eqx.field(static=True, default="mass")
    separation_update: str = eqx.field(static=True, default="start")
    series: str = eqx.field(static=True, default="separate")

    def __init__(self, law: str = "frictionless", friction=0.0, normal="first", materials: int = 2,
                 separation: float | None = None, series_correction: bool = True, gradient: str = "mass",
                 separation_update: str = "start", series: str = "separate"):
        check(law in LAWS, f"Contact: law = {law!r}; choose one of {', '.join(LAWS)}")
        normal = normal_option("Contact", normal)
        materials = positive_int("Contact", "materials", materials)
        check(materials >= 2, f"Contact: materials = {materials}; contact needs at least two materials "
                              "(each body its own material id 0..M-1)")
        self.law = law
        named = isinstance(normal, str)
        self.normal_rule = normal if named else "specified"
        self.direction = None if named else jnp.asarray(normal, dtype=jnp.result_type(float))
        self.materials = materials
        self.separation = None if separation is None else jnp.asarray(FINITE.real(
            "Contact", "separation", separation, fix="the gap, in cells, below which the bodies touch (e.g. 0.5)"),
            dtype=jnp.result_type(float))
        check(isinstance(series_correction, bool),
              f"Contact: series_correction = {series_correction!r}; use True or False")
        self.series_correction = series_correction
        check(gradient in GRADIENTS, f"Contact: gradient = {gradient!r}; choose 'mass' (sum_p M_p G_pi, the default) "
                                     "or 'volume' (sum_p J_p V0_p G_pi, NairnMPM's deformed-volume gradients)")
        self.gradient = gradient
        check(separation_update in SEPARATION_UPDATES,
              f"Contact: separation_update = {separation_update!r}; choose 'start' (the gap at the step's start in "
              "both applications) or 'extrapolated' (NairnMPM: moved over the step in the second)")
        self.separation_update = separation_update
        check(series in SERIES, f"Contact: series = {series!r}; choose 'separate' (003 eqs. 3.18, 3.22: XPIC/FMPM "
                                "subtract the series of the exchange Dp/m, the default) or 'incremental' (NairnMPM: "
                                "the law applied again to every increment of the series)")
        check(series == "separate" or series_correction,
              "Contact: series='incremental' with series_correction=False; the incremental series is the "
              "exchange's series term in NairnMPM's form: drop series_correction=False or use series='separate'")
        check(series == "separate" or materials == 2,
              f"Contact: series='incremental' with materials = {materials}; it is built for two materials (for more, "
              "jaxmpm's law takes the momentum imbalance back in proportion to mass and NairnMPM's does not, so "
              "there is no NairnMPM increment to follow): use series='separate'")
        self.series = series
        self.friction = NON_NEGATIVE.leaf("Contact", "friction", friction, fix="the Coulomb coefficient mu")
        mu = concrete(self.friction)
        check(law == "coulomb" or mu is None or not np.any(mu), f"Contact: friction = {friction} needs law='coulomb'")

    @property
    def normal(self):
        """The ``normal`` option: a name of :data:`NORMALS`, or the specified unit vector as a tuple
        of floats (concrete values only)."""
        if self.direction is None:
            return self.normal_rule
        return tuple(float(c) for c in np.asarray(self.direction))

    def check_fields(self, fields: dict) -> None:
        ids = concrete(fields["material"])
        if ids is not None:
            bad = (ids != np.round(ids)) | (ids < 0) | (ids >= self.materials)
            check(not np.any(bad), f"Contact: particle field material holds {np.unique(ids[bad])[:4].tolist()}; "
                                   f"give each particle its material id 0..{self.materials - 1} "
                                   "(sim.init(particles, fields={'material': ids}))")

    def particle_fields(self) -> tuple:
        return (ParticleField("material", initial=0.0, save=False,
                              doc="material (body) id 0..M-1: which velocity field the particle uses"),
                ParticleField("contact_force", shape=("D",), initial=0.0,
                              doc="contact force on the particle, M_p (S Dp^a+ / (m^a dt))_p; summed over a "
                                  "material it is the material's contact force sum_i Dp^a+_i / dt"))

    def p2g_quantities(self, sim, state, stencil) -> dict:
        """sum_p M_p G_pi: the material mass gradients, for the contact normals (Nairn contact notes
        §3.2; the stacked scatter sums each material's particles only, S^a of 000 eq. 4.4); with a
        ``separation`` criterion also sum_p S_pi M_p X_p, the materials' nodal mass moments."""
        weight = state.mass if self.gradient == "mass" else det(state.F) * state.volume0  # J_p V0_p
        out = {"mass_gradient": Gradient(weight)}
        if self.separation is not None:
            out["mass_moment"] = Weighted(state.mass[:, None] * state.x)
        return out

    def touching(self, fields, m0, m1, normal, h, updated=None):
        """The separation criterion: True where the materials' nodal centres of mass x^a = (S^T M X)^a / m^a
        are closer along n than ``separation`` cells, gap = (x^1 - x^0) . n - separation h <= 0.
        ``updated`` = (p + f dt, f, dt) in the second application under ``separation_update=
        "extrapolated"``: the gap moved over the step, gap + dt (Dp+ . n - dt Df . n / 2) / m_red with
        Dp+ = (m^0 p+^1 - m^1 p+^0)/m, Df likewise of f, m_red = m^0 m^1 / m (NairnMPM 19.0,
        CoulombFriction GetFrictionalDeltaMomentum; there the test is gap < 0)."""
        gap = self.gap(fields, m0, m1, normal, h)
        if updated is None:
            return gap <= 0.0
        p_plus, force, dt = updated
        return self.moved_gap(gap, m0, m1, normal, self.stick(m0, m1, p_plus), self.stick(m0, m1, force), dt) < 0.0

    def gap(self, fields, m0, m1, normal, h):
        """(x^1 - x^0) . n - separation h from the materials' nodal centres of mass x^a = (S^T M X)^a / m^a."""
        x0, x1 = (safe_divide(q, mass) for q, mass in zip(self.split(fields.values["mass_moment"]), (m0, m1)))
        return jnp.sum((x1 - x0) * normal, axis=-1) - self.separation * h

    def stick(self, m0, m1, a):
        """The stick change of material 0 of a stacked nodal momentum (or force) ``a``, (m^0 a^1 - m^1 a^0)/m."""
        a0, a1 = self.split(a)
        return safe_divide(m0[:, None] * a1 - m1[:, None] * a0, m0 + m1)

    @staticmethod
    def moved_gap(gap, m0, m1, normal, stick_p, stick_f, dt):
        """The gap moved over the step, gap + dt (Dp . n - dt Df . n / 2) / m_red (NairnMPM 19.0,
        CoulombFriction GetFrictionalDeltaMomentum), Dp and Df stick changes of material 0."""
        rate = jnp.sum((stick_p - 0.5 * dt * stick_f) * normal, axis=-1)
        return gap + dt * safe_divide(rate, safe_divide(m0 * m1, m0 + m1))

    # ------------------------------------------------------------------ the contact law
    def per_material(self, a):
        """A stacked nodal array (M n, ...) as (M, n, ...): material a's field is [a]."""
        return a.reshape((self.materials, a.shape[0] // self.materials) + a.shape[1:])

    def split(self, a):
        """(field of material 0, field of material 1) of a two-material stacked array (2n, ...)."""
        return tuple(self.per_material(a))

    def specified_normal(self, like):
        """The specified normal (``normal=`` a vector) on every node, shaped and typed as ``like`` (n, D)."""
        size = self.direction.shape[0]
        if size != like.shape[-1]:
            fail("Contact", f"normal = {show(concrete(self.direction))} has {size} components but the grid is "
                            f"{like.shape[-1]}D", f"give a unit vector of {like.shape[-1]} components")
        return jnp.broadcast_to(self.direction.astype(like.dtype), like.shape)

    def contact_normal(self, grad_m):
        """Two materials: the unit normal from material 0 into material 1 on every node, (n, D)."""
        g0, g1 = self.split(grad_m)
        if self.direction is not None:
            return self.specified_normal(g0)
        if self.normal_rule == "max_gradient":  # the larger |g^a| defines it; material 0's on a tie
            own = jnp.sum(g0 * g0, axis=-1) >= jnp.sum(g1 * g1, axis=-1)
            return safe_unit(jnp.where(own[:, None], g0, -g1))
        return safe_unit(g0 if self.normal_rule == "first" else g0 - g1)

    def material_normals(self, grad_m, m):
        """M materials: the unit normal n^a from material a into the rest on every node, (M, n, D)
        (module docstring); for two materials (n^0, -n^0) with n^0 = :meth:`contact_normal`."""
        g = self.per_material(grad_m)
        if self.normal_rule == "average":
            return safe_unit(2.0 * g - jnp.sum(g, axis=0, keepdims=True))  # g^a - sum_{b != a} g^b
        first = jnp.argmax(self.per_material(m) > 0, axis=0)  # the lowest-numbered material present
        own = first[None, :] == jnp.arange(self.materials)[:, None]  # (M, n): a is that material
        if self.normal_rule == "max_gradient":
            # the rest's gradient sum_{b != a} g^b as a sum of the others alone (adding exact zeros), so that
            # with two materials it is the other's g^b bit for bit and n^1 = -n^0 exactly
            others = ~np.eye(self.materials, dtype=bool)[:, :, None, None]
            rest = jnp.sum(jnp.where(others, g[None], 0.0), axis=1)
            g_sq, rest_sq = jnp.sum(g * g, axis=-1), jnp.sum(rest * rest, axis=-1)
            mine = (g_sq > rest_sq) | ((g_sq == rest_sq) & own)  # a tie goes to the lowest-numbered material's side
            return safe_unit(jnp.where(mine[..., None], g, -rest))
        if self.direction is not None:
            direction = self.specified_normal(g[0])[None]
        else:  # "first"
            direction = safe_unit(jnp.take_along_axis(g, first[None, :, None], axis=0)[0])[None]
        return jnp.where(own[..., None], 1.0, -1.0) * direction

    def momentum_change(self, m0, m1, p0, p1, normal, touching=None):
        """Dp of material 0 on every node (Dp of material 1 is -Dp): the law applied to the
        stick change (m0 p1 - m1 p0)/m on contact nodes (003 eqs. 3.9, 3.12); ``touching``
        (the separation criterion) narrows the contact nodes.  With more materials, material 1
        is the rest (module docstring)."""
        stick = safe_divide(m0[:, None] * p1 - m1[:, None] * p0, m0 + m1)  # 003 eq. (3.12)
        return self.law_change(stick, m0, m1, normal, touching)

    def law_change(self, stick, m0, m1, normal, touching=None):
        """The law's Dp of material 0 for the stick change ``stick`` (003 eq. 3.9): ``stick`` itself
        (stick), its normal part where the materials approach (frictionless), or Coulomb's, on the
        contact nodes (both materials present, narrowed by ``touching``); 0 elsewhere."""
        contact = (m0 > 0) & (m1 > 0)
        if touching is not None:
            contact = contact & touching
        if self.law == "stick":
            return jnp.where(contact[:, None], stick, 0.0)
        dpn = jnp.sum(stick * normal, axis=-1)  # < 0: the materials approach along n
        approach = contact & (dpn < 0)
        normal_part = dpn[:, None] * normal
        if self.law == "frictionless":
            return jnp.where(approach[:, None], normal_part, 0.0)
        tangential = stick - normal_part
        t_norm = safe_norm(tangential)
        limit = self.friction * jnp.abs(dpn)
        slides = t_norm > limit
        sliding = normal_part + limit[:, None] * safe_unit(tangential)
        return jnp.where(approach[:, None], jnp.where(slides[:, None], sliding, stick), 0.0)

    def apply(self, p, m, normal, touching=None):
        """Stacked momenta (M n, D) after contact, and the change.  ``normal``: (n, D) from
        :meth:`contact_normal` for two materials, else (M, n, D) from :meth:`material_normals`;
        ``touching`` likewise (n,) or (M, n)."""
        if self.materials == 2:
            m0, m1 = self.split(m)
            p0, p1 = self.split(p)
            dp = self.momentum_change(m0, m1, p0, p1, normal, touching)
            change = jnp.concatenate([dp, -dp])  # 000 eq. (4.12): sum over materials is zero
            return p + change, change
        ma, pa = self.per_material(m), self.per_material(p)
        m_all, p_all = jnp.sum(ma, axis=0), jnp.sum(pa, axis=0)

        def against_the_rest(mass, mom, nrm, near):
            return self.momentum_change(mass, m_all - mass, mom, p_all - mom, nrm, near)

        law = jax.vmap(against_the_rest, in_axes=(0, 0, 0, None if touching is None else 0))
        dp = law(ma, pa, normal, touching)  # each material against the rest
        dp = dp - safe_divide(ma[..., None] * jnp.sum(dp, axis=0)[None], m_all[None])  # sum_a Dp^a = 0 (000 eq. 4.12)
        change = dp.reshape(p.shape)
        return p + change, change

    def touching_rest(self, fields, m, normals, h):
        """The separation criterion for M materials, (M, n): material a against the rest's nodal
        centre of mass, (x^rest - x^a) . n^a <= separation h."""
        ma, q = self.per_material(m), self.per_material(fields.values["mass_moment"])
        m_all, q_all = jnp.sum(ma, axis=0), jnp.sum(q, axis=0)
        x_own = safe_divide(q, ma)
        x_rest = safe_divide(q_all[None] - q, m_all[None] - ma)  # the rest: all materials but a
        return jnp.sum((x_rest - x_own) * normals, axis=-1) <= self.separation * h

    # ------------------------------------------------------------------ the term's hooks
    def velocity_fields(self) -> int:
        return self.materials

    def field_index(self, state):
        return state.fields["material"]

    def grid_reads(self, sim) -> frozenset:
        return frozenset({"momentum", "force"})  # the law acts on p and on p + f dt (003 eq. 3.19)

    def exchange_momentum(self, sim, fields, p, dt=None):
        """The contact law on stacked nodal momenta ``p`` (M n, D): (p after contact, the change)
        (module docstring; 003 eqs. 3.9, 3.12).  The exchange phase applies it to p and to
        p + f dt, then the velocity conditions follow; ``dt`` (the second application with
        ``separation_update="extrapolated"``) moves the gap over the step."""
        m = fields.mass
        if self.materials == 2:
            normal = self.contact_normal(fields["mass_gradient"])
            touching = None
            if self.separation is not None:
                touching = self.touching(fields, *self.split(m), normal, sim.grid.h,
                                         None if dt is None else (p, fields.force, dt))
        else:
            check(dt is None, "Contact: separation_update='extrapolated' is built for two materials; use 'start'")
            normal = self.material_normals(fields["mass_gradient"], m)
            touching = None if self.separation is None else self.touching_rest(fields, m, normal, sim.grid.h)
        return self.apply(p, m, normal, touching)

    def exchange_updated_momentum(self, sim, fields, p_plus, dt):
        """The second application, on p + f dt; with ``separation_update="extrapolated"`` the gap
        moved over the step (:meth:`touching`)."""
        extrapolate = self.separation is not None and self.separation_update == "extrapolated"
        return self.exchange_momentum(sim, fields, p_plus, dt if extrapolate else None)

    def exchange_increments(self, sim, fields, p, change, dt, updated: bool):
        """With ``series="incremental"``: the law on the increments of the XPIC/FMPM series,
        :class:`ContactIncrements`, cached from one application of the law -- ``p`` the momenta it
        was applied to (before it), ``change`` its change; ``updated``: the second application (on
        p + f dt), whose force stick change moves the gap (``separation_update="extrapolated"``); else
        the first (USF's and MUSL's strain-update series).  None with ``series="separate"``."""
        if self.series != "incremental" or not self.series_correction:
            return None
        m0, m1 = self.split(fields.mass)
        normal = self.contact_normal(fields["mass_gradient"])
        stick_f = jnp.zeros_like(normal)
        gap = None
        if self.separation is not None:
            gap = self.gap(fields, m0, m1, normal, sim.grid.h)
            if updated:
                stick_f = self.stick(m0, m1, fields.force)
        return ContactIncrements(self, m0, m1, normal, gap, stick_f, jnp.asarray(dt, p.dtype),
                                 self.stick(m0, m1, p), self.split(change)[0])

    def attributes(self) -> dict:
        """The contact set-up as HDF5 root attributes (the friction is a registered parameter)."""
        return {"contact law": self.law, "contact normal": str(self.normal), "contact materials": self.materials,
                "contact separation": np.nan if self.separation is None else float(self.separation),
                "contact gradient": self.gradient, "contact separation update": self.separation_update,
                "contact series": self.series}

    def in_conventions(self, conventions: str):
        """``conventions="nairnmpm"``: deformed-volume gradients for the normals, the extrapolated
        separation and the law on the series' increments (NairnMPM 19.0's rules; module docstring).
        The increments only for two materials: with more, jaxmpm's law is not NairnMPM's lumped one
        either (it takes the momentum imbalance back), and ``series`` stays "separate"."""
        if conventions != "nairnmpm":
            return self
        series = "incremental" if self.materials == 2 and self.series_correction else self.series
        for name, default, preset in (("gradient", "mass", "volume"), ("separation_update", "start", "extrapolated"),
                                      ("series", "separate", series)):
            value = getattr(self, name)
            check(value in (default, preset), f"Contact: {name} = {value!r} with conventions='nairnmpm', which sets "
                                              f"{name}={preset!r}; drop {name}= or use conventions='jaxmpm'")
        new = copy.copy(self)
        object.__setattr__(new, "gradient", "volume")  # static fields: the model's hash changes
        object.__setattr__(new, "separation_update", "extrapolated")
        object.__setattr__(new, "series", series)
        return new

    def particle_action(self, sim, old, new, transfer, solution, dt):
        """Record each particle's share of the contact force, M_p S (Dp^a+ / (m^a dt))."""
        force = transfer.particle_share(solution["exchange_acceleration"])
        return eqx.tree_at(lambda s: s.fields, new, {**new.fields, "contact_force": force})


class ContactIncrements(eqx.Module):
    """NairnMPM's contact on the increments of the XPIC(m)/FMPM(k) series (``Contact(series=
    "incremental")``), the hook :func:`jaxmpm.transfer.series.exchange_increments` calls on every
    increment D_k = P (I - S+S) D_{k-1} (NairnMPM 19.0: NairnMPM_Class/XPICExtrapolationTask
    GetDeltaV -> ImposeIncrementalContact, Nodes/CrackVelocityFieldMulti MaterialXPICIncrementOnCVF).

    It holds what one application of the law cached (NairnMPM's ``SetContactInfo``/``ContactSetDelPi``,
    Nodes/MaterialContactNode): the masses m^0, m^1, the normal n, the gap (with a ``separation``;
    None: every contact node touches), the stick change Df of the nodal forces (second application;
    zero after the first, as NairnMPM's ``startDelFi``), dt, the stick change of the momenta the law
    was applied to, ``stick`` (its ``priorDelPiZero``), and the law's change, ``applied`` (its
    ``netDelPi``).  On each increment, with A the accumulated stick change and N the change applied
    so far (the carry, starting from (``stick``, ``applied``)):

        A <- A + (m^0 m^1 D^1 - m^1 m^0 D^0) / m          the increment's stick change, material 0
        L  = law(A)                                       n, the gap moved by A (``moved_gap`` with Df) under
                                                          separation_update="extrapolated", else the gap
        D^0 += (L - N) / m^0,   D^1 -= (L - N) / m^1,   N <- L

    so that after the series the law's change on the node is the law of the whole series' stick
    change.  Two materials (``Contact`` refuses more with series="incremental")."""

    contact: Contact
    m0: jnp.ndarray
    m1: jnp.ndarray
    normal: jnp.ndarray
    gap: jnp.ndarray | None
    stick_force: jnp.ndarray
    dt: jnp.ndarray
    stick: jnp.ndarray
    applied: jnp.ndarray

    def initial(self):
        """The carry before the first increment: (accumulated stick change, change applied)."""
        return self.stick, self.applied

    def adjust(self, increment, carry):
        """(the change the law makes to the stacked velocity ``increment`` (2n, D), the new carry)."""
        contact, m0, m1 = self.contact, self.m0, self.m1
        accumulated, applied = carry
        d0, d1 = contact.split(increment)
        accumulated = accumulated + safe_divide(m0[:, None] * (m1[:, None] * d1) - m1[:, None] * (m0[:, None] * d0),
                                                m0 + m1)
        touching = None
        if self.gap is not None:
            if contact.separation_update == "extrapolated":
                touching = contact.moved_gap(self.gap, m0, m1, self.normal, accumulated, self.stick_force,
                                             self.dt) < 0.0
            else:
                touching = self.gap <= 0.0
        law = contact.law_change(accumulated, m0, m1, self.normal, touching)
        delta = law - applied
        return jnp.concatenate([safe_divide(delta, m0), -safe_divide(delta, m1)]), (accumulated, law)


register_term("contact", Contact, doc="materials with their own velocity fields and a contact law (003 ch. 3)",
              parameters=[Parameter("friction", lambda t: t.friction, "Coulomb friction coefficient mu",
                                    "positive", valid="non-negative", acts=lambda t: None if t.law == "coulomb" else (
                                        f"acts only under the contact law 'coulomb', and this model's is {t.law!r}"
                                        " (a model without contact gets jm.Contact() added, 'frictionless'): build "
                                        "it with jm.Contact(law='coulomb', friction=...)"))])
