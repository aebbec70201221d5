"""jaxmpm: a differentiable Material Point Method in JAX.

FLIP, PIC and their blend, XPIC(m), FMPM(k), APIC and TPIC as pure, jit-able, differentiable steps.
"""

from ._cache import compilation_cache
from ._calibrate import CalibrationResult, calibrate
from ._ensemble import ensemble
from ._params import PARAMETERS, get_params, set_params
from ._schemes import FLIP, FMPM, PIC, XPIC, mass_matrix_series  # noqa: I001  (flip first in the registry)
from ._registry import (MATERIALS, SCHEMES, SHAPES, TERMS, Parameter, register_material, register_scheme,
                        register_shape, register_term, scheme_from_name, shape_from_name)
from ._boundary import Constraint, Fixed, Mirror, NodeSet, Prescribed, Slip, Wall
from ._diagnostics import angular_momentum, kinetic_energy, linear_momentum, stable_dt, strain_energy
from ._errors import InputError, InstabilityError
from ._fields import GridFields, GridSolution, ParticleField
from ._grid import Grid
from ._io import H5Writer, load_h5, save_h5
from ._materials import HypoElastic, LinearElastic, Material, NeoHookean, NoStress, VolumetricFluid
from ._particles import Ball, Box, Disk, Particles, Region, Ring, fill
from ._scheme_base import ParticleUpdate, Scheme
from ._schemes import FLIP, FMPM, PIC, XPIC, mass_matrix_series
from ._affine import APIC, RPIC, TPIC, with_velocity_gradient
from ._shapes import (AxisymmetricStencil, CubicBSpline, Linear, QuadraticBSpline, ShapeFunction, Stencil, StencilBase,
                      TensorStencil, UGIMP)
from ._driver import History, RunInterrupted, StableTimeStepWarning
from ._resume import resume
from ._simulation import Simulation
from ._state import State, with_fields, with_scheme_state
from ._step import folds_force, grid_solve, g2p, p2g
from ._terms import BodyForce, Damping, StressDivergence, Term
from ._contact import Contact
from ._loads import ParticleForce, Traction
from ._reaction import Reaction
from ._transport import Diffusion, Dirichlet, Heat, Neumann, Transport
from ._transfer import Transfer, gather, scatter
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
