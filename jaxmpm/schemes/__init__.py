"""Particle updates, one family per module: ``xpic`` (XPIC(m), FLIP, PIC and their blend), ``fmpm``
(FMPM(k)), ``affine`` (APIC, TPIC), ``rpic`` (RPIC); ``base`` is the :class:`Scheme` interface and
the damping protocol.  Importing a module registers its schemes (in this order: the CLI lists them
so)."""

from .base import (NO_DAMPING, ParticleDamping, ParticleUpdate, RateDamping, Scheme, combine_damping,  # noqa: F401
                   dissipated_energy, with_velocity_gradient)
from .xpic import FLIP, PIC, XPIC  # noqa: F401
from .fmpm import FMPM  # noqa: F401
from .affine import APIC, TPIC  # noqa: F401
from .rpic import RPIC  # noqa: F401
