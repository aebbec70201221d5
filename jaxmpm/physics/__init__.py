"""Physics terms, one physical effect per module: ``stress`` (internal force), ``body_force``,
``damping``, ``contact`` (multimaterial contact), ``transport`` (heat conduction, diffusion),
``loads`` (tractions, point forces), ``reaction`` (reaction forces), ``collider`` (rigid level-set
colliders), and ``conditions`` (the
velocity boundary conditions and their :class:`Constraint`); ``term`` is the :class:`Term`
interface with the grid phases."""

from .term import Term  # noqa: F401
from .conditions import Constraint, Fixed, Mirror, NodeSet, Prescribed, Slip, Wall  # noqa: F401
from .stress import StressDivergence  # noqa: F401
from .body_force import BodyForce  # noqa: F401
from .damping import Damping  # noqa: F401
from .contact import Contact  # noqa: F401
from .loads import ParticleForce, Traction  # noqa: F401
from .reaction import Reaction  # noqa: F401
from .collider import (Collider, HalfSpace, LevelSet, SolidBox, SolidCylinder, SolidSphere,  # noqa: F401
                       SolidUnion)
from .transport import Diffusion, Dirichlet, Heat, Neumann, Transport  # noqa: F401
