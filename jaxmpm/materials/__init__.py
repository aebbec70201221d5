"""Constitutive models, one law per module; ``base`` is the :class:`Material` protocol with its
elastic and inelastic bases and the :class:`Increment` a strain update hands the law."""

from .base import ElasticMaterial, Increment, InelasticMaterial, Material  # noqa: F401
from .linear import LinearElastic  # noqa: F401
from .hypoelastic import HypoElastic  # noqa: F401
from .incremental import IncrementalElastic  # noqa: F401
from .neohookean import NeoHookean  # noqa: F401
from .fluid import NoStress, VolumetricFluid  # noqa: F401
from .plastic import HenckyPlastic  # noqa: F401
from .von_mises import VonMises  # noqa: F401
from .drucker_prager import DruckerPrager  # noqa: F401
from .cam_clay import CamClay  # noqa: F401
from .newtonian import NewtonianFluid  # noqa: F401
