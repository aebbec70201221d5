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

The normal comes from the material mass gradients g^a_i = sum_p M_p G_pi (000 §4.2).  G_pi is the
gradient of S_i at the particle, so g^a points out of material a (a particle on the -x side of
node i has G_pi > 0).  ``normal="first"`` uses material 0's, n = g^0 / |g^0|; ``normal="average"``
(default) uses both, n = (g^0 - g^1) / |g^0 - g^1| -- symmetric in the two materials.

Contact nodes are the nodes where both materials have mass -- the bodies then interact from about
one cell apart.  The optional separation criterion (``separation=s``, in cells) narrows them to
the nodes where the materials' nodal centres of mass x^a_i = sum_p S_pi M_p X_p / m^a_i are closer
along the normal than s h: (x^1 - x^0) . n <= s h (a displacement check in the spirit of
NairnMPM's contact by displacements).

More than two materials (``materials=M``): each material a meets *the rest* on a node -- the
other materials' mass m - m^a and momentum p - p^a as one body (NairnMPM's multimaterial contact)
-- with the normal n^a from a into the rest ("average": g^a - sum_{b != a} g^b; "first": the
gradient of the lowest-numbered material present on the node, +- for that material and the
others).  The law gives Dp^a for every a; where more than two materials meet, sum_a Dp^a need not
vanish, and the imbalance r = sum_a Dp^a is taken back in proportion to mass, Dp^a -= m^a r / m:
the same velocity change r / m for every material, so the relative velocities the law set are
kept and sum_a Dp^a = 0 (000 eq. 4.12).  With two materials the rest is the other material,
n^1 = -n^0 and Dp^1 = -Dp^0 exactly; the two-material code path is that special case.

Order with velocity boundary conditions on the same node: contact first, on momenta, then the
conditions on the velocities (NairnMPM's order, 003 §2.1 "Reimpose velocity boundary
conditions"): a fixed node stays fixed whatever contact asked.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..core.errors import check
from ..core.fields import ParticleField
from ..core.registry import Parameter, register_term
from ..transfer.contractions import Gradient, Weighted
from ..transfer.operators import safe_divide
from .term import Term
from ..core.validate import FINITE, NON_NEGATIVE, concrete, positive_int

LAWS = ("stick", "frictionless", "coulomb")
NORMALS = ("average", "first")


def _safe_unit(u):
    """u / |u| along the last axis, 0 where u = 0 (NaN-safe under autodiff)."""
    sq = jnp.sum(u * u, axis=-1, keepdims=True)
    positive = sq > 0
    return jnp.where(positive, u / jnp.sqrt(jnp.where(positive, sq, 1.0)), 0.0)


def _safe_norm(u):
    sq = jnp.sum(u * u, axis=-1)
    positive = sq > 0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, sq, 1.0)), 0.0)


class Contact(Term):
    """``materials`` (default 2) materials, each with its own velocity field, coupled by a contact
    law on the nodes where two or more have mass (module docstring).  ``law``: "stick",
    "frictionless" or "coulomb" (with ``friction`` mu >= 0); ``normal``: "average" or "first".
    Particles carry their material id in the field ``material`` (0..M-1;
    ``sim.init(particles, fields={"material": ids})``)."""

    law: str = eqx.field(static=True)
    normal: str = eqx.field(static=True)
    materials: int = eqx.field(static=True)
    friction: jnp.ndarray
    separation: float | None = eqx.field(static=True)
    series_correction: bool = eqx.field(static=True)

    def __init__(self, law: str = "frictionless", friction=0.0, normal: str = "average", materials: int = 2,
                 separation: float | None = None, series_correction: bool = True):
        check(law in LAWS, f"Contact: law = {law!r}; choose one of {', '.join(LAWS)}")
        check(normal in NORMALS, f"Contact: normal = {normal!r}; choose one of {', '.join(NORMALS)}")
        materials = positive_int("Contact", "materials", materials)
        check(materials >= 2, f"Contact: materials = {materials}; contact needs at least two materials "
                              "(each body its own material id 0..M-1)")
        self.law = law
        self.normal = normal
        self.materials = materials
        self.separation = None if separation is None else FINITE.real(
            "Contact", "separation", separation, fix="the gap, in cells, below which the bodies touch (e.g. 0.5)")
        check(isinstance(series_correction, bool), f"Contact: series_correction = {series_correction!r}; use True or False")
        self.series_correction = series_correction
        self.friction = NON_NEGATIVE.leaf("Contact", "friction", friction, fix="the Coulomb coefficient mu")
        mu = concrete(self.friction)
        check(law == "coulomb" or mu is None or not np.any(mu), f"Contact: friction = {friction} needs law='coulomb'")

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
        """sum_p M_p G_pi: the material mass gradients (000 §4.2), for the contact normals; with a
        ``separation`` criterion also sum_p S_pi M_p X_p, the materials' nodal mass moments."""
        out = {"mass_gradient": Gradient(state.mass)}
        if self.separation is not None:
            out["mass_moment"] = Weighted(state.mass[:, None] * state.x)
        return out

    def touching(self, fields, m0, m1, normal, h):
        """The separation criterion: True where the materials' nodal centres of mass x^a = (S^T M X)^a / m^a
        are closer along n than ``separation`` cells, (x^1 - x^0) . n <= separation h."""
        x0, x1 = (safe_divide(q, mass) for q, mass in zip(self.split(fields.values["mass_moment"]), (m0, m1)))
        return jnp.sum((x1 - x0) * normal, axis=-1) <= self.separation * h

    # ------------------------------------------------------------------ the contact law
    def per_material(self, a):
        """A stacked nodal array (M n, ...) as (M, n, ...): material a's field is [a]."""
        return a.reshape((self.materials, a.shape[0] // self.materials) + a.shape[1:])

    def split(self, a):
        """(field of material 0, field of material 1) of a two-material stacked array (2n, ...)."""
        return tuple(self.per_material(a))

    def contact_normal(self, grad_m):
        """Two materials: the unit normal from material 0 into material 1 on every node, (n, D)."""
        g0, g1 = self.split(grad_m)
        return _safe_unit(g0 if self.normal == "first" else g0 - g1)

    def material_normals(self, grad_m, m):
        """M materials: the unit normal n^a from material a into the rest on every node, (M, n, D)
        (module docstring); for two materials (n^0, -n^0) with n^0 = :meth:`contact_normal`."""
        g = self.per_material(grad_m)
        if self.normal == "average":
            return _safe_unit(2.0 * g - jnp.sum(g, axis=0))  # g^a - sum_{b != a} g^b
        first = jnp.argmax(self.per_material(m) > 0, axis=0)  # the lowest-numbered material present
        g_first = jnp.take_along_axis(g, first[None, :, None], axis=0)[0]
        own = first[None, :] == jnp.arange(self.materials)[:, None]
        return jnp.where(own[..., None], 1.0, -1.0) * _safe_unit(g_first)[None]

    def momentum_change(self, m0, m1, p0, p1, normal, touching=None):
        """Dp of material 0 on every node (Dp of material 1 is -Dp): the law applied to the
        stick change (m0 p1 - m1 p0)/m on contact nodes (003 eqs. 3.9, 3.12); ``touching``
        (the separation criterion) narrows the contact nodes.  With more materials, material 1
        is the rest (module docstring)."""
        m = m0 + m1
        contact = (m0 > 0) & (m1 > 0)
        if touching is not None:
            contact = contact & touching
        stick = safe_divide(m0[:, None] * p1 - m1[:, None] * p0, m)  # 003 eq. (3.12)
        if self.law == "stick":
            return jnp.where(contact[:, None], stick, 0.0)
        dpn = jnp.sum(stick * normal, axis=-1)  # < 0: the materials approach along n
        approach = contact & (dpn < 0)
        normal_part = dpn[:, None] * normal
        if self.law == "frictionless":
            return jnp.where(approach[:, None], normal_part, 0.0)
        tangential = stick - normal_part
        t_norm = _safe_norm(tangential)
        limit = self.friction * jnp.abs(dpn)
        slides = t_norm > limit
        sliding = normal_part + limit[:, None] * _safe_unit(tangential)
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
        law = jax.vmap(lambda mass, mom, nrm, near: self.momentum_change(mass, m_all - mass, mom, p_all - mom, nrm, near),
                       in_axes=(0, 0, 0, None if touching is None else 0))
        dp = law(ma, pa, normal, touching)  # each material against the rest
        dp = dp - safe_divide(ma[..., None] * jnp.sum(dp, axis=0), m_all)  # sum_a Dp^a = 0 (000 eq. 4.12)
        change = dp.reshape(p.shape)
        return p + change, change

    def touching_rest(self, fields, m, normals, h):
        """The separation criterion for M materials, (M, n): material a against the rest's nodal
        centre of mass, (x^rest - x^a) . n^a <= separation h."""
        ma, q = self.per_material(m), self.per_material(fields.values["mass_moment"])
        m_all, q_all = jnp.sum(ma, axis=0), jnp.sum(q, axis=0)
        x_own = safe_divide(q, ma)
        x_rest = safe_divide(q_all - q, m_all - ma)
        return jnp.sum((x_rest - x_own) * normals, axis=-1) <= self.separation * h

    # ------------------------------------------------------------------ the term's hooks
    def velocity_fields(self) -> int:
        return self.materials

    def field_index(self, state):
        return state.fields["material"]

    def grid_reads(self, sim) -> frozenset:
        return frozenset({"momentum", "force"})  # the law acts on p and on p + f dt (003 eq. 3.19)

    def exchange_momentum(self, sim, fields, p):
        """The contact law on stacked nodal momenta ``p`` (M n, D): (p after contact, the change)
        (module docstring; 003 eqs. 3.9, 3.12).  The exchange phase applies it to p and to
        p + f dt, then the velocity conditions follow."""
        m = fields.mass
        if self.materials == 2:
            normal = self.contact_normal(fields["mass_gradient"])
            touching = None if self.separation is None else self.touching(fields, *self.split(m), normal, sim.grid.h)
        else:
            normal = self.material_normals(fields["mass_gradient"], m)
            touching = None if self.separation is None else self.touching_rest(fields, m, normal, sim.grid.h)
        return self.apply(p, m, normal, touching)

    def particle_action(self, sim, old, new, transfer, solution, dt):
        """Record each particle's share of the contact force, M_p S (Dp^a+ / (m^a dt))."""
        force = transfer.particle_share(solution["exchange_acceleration"])
        return eqx.tree_at(lambda s: s.fields, new, {**new.fields, "contact_force": force})


register_term("contact", Contact, doc="materials with their own velocity fields and a contact law (003 ch. 3)",
              parameters=[Parameter("friction", lambda t: t.friction, "Coulomb friction coefficient mu",
                                    "positive", valid="non-negative")])
