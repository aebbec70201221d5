"""jaxmpm: a differentiable Material Point Method in JAX.

FLIP, PIC and their blend, XPIC(m), FMPM(k), APIC and TPIC as pure, jit-able, differentiable steps.
"""

from .run.cache import compilation_cache
from .run.calibrate import CalibrationResult, calibrate
from .run.ensemble import ensemble
from .core.params import PARAMETERS, get_params, set_params
from .schemes.xpic import FLIP, FMPM, PIC, XPIC, mass_matrix_series  # noqa: I001  (flip first in the registry)
from .core.registry import (MATERIALS, SCHEMES, SHAPES, TERMS, Parameter, register_material, register_scheme,
                        register_shape, register_term, scheme_from_name, shape_from_name)
from .physics.conditions import Constraint, Fixed, Mirror, NodeSet, Prescribed, Slip, Wall
from .core.measures import angular_momentum, kinetic_energy, linear_momentum, stable_dt, strain_energy
from .core.errors import InputError, InstabilityError
from .core.fields import GridFields, GridSolution, ParticleField
from .core.grid import Grid
from .io.hdf5 import H5Writer, load_h5, save_h5
from .materials.base import HypoElastic, LinearElastic, Material, NeoHookean, NoStress, VolumetricFluid
from .core.particles import Ball, Box, Disk, Particles, Region, Ring, fill
from .schemes.base import ParticleUpdate, Scheme
from .schemes.xpic import FLIP, FMPM, PIC, XPIC, mass_matrix_series
from .schemes.affine import APIC, RPIC, TPIC, with_velocity_gradient
from .transfer.shapes import (AxisymmetricStencil, CubicBSpline, Linear, QuadraticBSpline, ShapeFunction, Stencil, StencilBase,
                      TensorStencil, UGIMP)
from .run.driver import History, RunInterrupted, StableTimeStepWarning
from .resume import resume
from .model.simulation import Simulation
from .core.state import State, with_fields, with_scheme_state
from .model.step import folds_force, grid_solve, g2p, p2g
from .physics.term import BodyForce, Damping, StressDivergence, Term
from .physics.contact import Contact
from .physics.loads import ParticleForce, Traction
from .physics.reaction import Reaction
from .physics.transport import Diffusion, Dirichlet, Heat, Neumann, Transport
from .transfer.operators import Transfer, gather, scatter
from .scenes import SCENES, scene

__version__ = "0.1.0"

__all__ = [
    "CalibrationResult", "PARAMETERS", "calibrate", "ensemble", "get_params", "set_params",
    "MATERIALS", "SCHEMES", "SHAPES", "TERMS", "Parameter", "register_material", "register_scheme",
    "register_shape", "register_term", "scheme_from_name", "shape_from_name",
    "Ball", "BodyForce", "Box", "Constraint", "Contact", "CubicBSpline", "Damping", "Disk", "FLIP", "FMPM", "Fixed", "Grid",
    "GridFields", "GridSolution", "H5Writer", "History", "InputError", "InstabilityError", "Linear", "LinearElastic",
    "Material", "NeoHookean", "NodeSet", "PIC", "ParticleField", "ParticleUpdate", "Particles", "Prescribed",
    "QuadraticBSpline", "Region", "Ring", "RunInterrupted", "SCENES", "Scheme", "ShapeFunction", "Simulation", "Slip",
    "StableTimeStepWarning", "State", "Stencil", "StencilBase", "StressDivergence", "TensorStencil", "Term",
    "AxisymmetricStencil",
    "Transfer", "UGIMP", "XPIC", "angular_momentum", "fill", "folds_force", "g2p", "gather", "grid_solve",
    "kinetic_energy", "linear_momentum", "load_h5", "resume", "mass_matrix_series", "p2g", "save_h5", "scatter",
    "scene", "stable_dt", "strain_energy", "with_fields", "with_scheme_state",
    "APIC", "RPIC", "TPIC", "with_velocity_gradient", "Wall", "NoStress", "VolumetricFluid",
    "Diffusion", "Dirichlet", "Heat", "Neumann", "Transport", "HypoElastic", "ParticleForce", "Traction", "Reaction",
    "Mirror", "compilation_cache",
]
