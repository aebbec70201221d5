"""jaxmpm: a differentiable Material Point Method in JAX.

FLIP, PIC and their blend, XPIC(m), FMPM(k), APIC and TPIC as pure, jit-able, differentiable steps.
"""

from .core.host_memory import reuse_host_memory  # first: JAXMPM_REUSE_HOST_MEMORY=1 acts before JAX starts threads
from .core.version import __version__  # noqa: F401
from .core.docstrings import document_init as _document_init
from .core.errors import InputError, InstabilityError, ParticlesLeftGrid
from .core.registry import (MATERIALS, SCHEMES, SHAPES, TERMS, Parameter, register_material, register_scheme,
                            register_shape, register_term, scheme_from_name, shape_from_name)
from .core.params import PARAMETERS, get_params, set_params
from .core.fields import GridFields, GridSolution, ParticleField
from .core.grid import Grid
from .core.particles import Ball, Box, Disk, Particles, Region, Ring, fill
from .core.geometry import Mesh, Polygon, point_cloud
from .core.state import State, with_fields, with_scheme_state
from .core.measures import angular_momentum, kinetic_energy, linear_momentum, stable_dt, strain_energy
from .transfer.shapes import (AxisymmetricStencil, CubicBSpline, Linear, QuadraticBSpline, ShapeFunction, Stencil,
                              StencilBase, TensorStencil, UGIMP)
from .transfer.contractions import Affine, Contraction, Divergence, Gradient, Hoop, PerSlot, Weighted
from .transfer.backend import compiler_options
from .transfer.kernels import Kernel, register_kernel
from .transfer.operators import Transfer, gather, scatter
from .transfer.series import exchange_series, mass_matrix_series, series
from .schemes import (APIC, FLIP, FMPM, PIC, RPIC, TPIC, XPIC, ParticleDamping, ParticleUpdate, Scheme,
                      with_velocity_gradient)
from .materials import (ElasticMaterial, HypoElastic, Increment, IncrementalElastic, InelasticMaterial, LinearElastic,
                        Material, NeoHookean, NoStress, VolumetricFluid)
from .materials import HenckyPlastic, VonMises
from .materials import DruckerPrager
from .materials import CamClay
from .materials import NewtonianFluid
from .physics import (BodyForce, Constraint, Contact, Damping, Diffusion, Dirichlet, Fixed, Heat, Mirror, Neumann,
                      NodeSet, ParticleForce, Prescribed, Reaction, Slip, StressDivergence, Term, Traction, Transport,
                      Wall)
from .physics import Collider, HalfSpace, LevelSet, SolidBox, SolidCylinder, SolidSphere, SolidUnion
from .run.cache import compilation_cache, enable_by_default as _enable_compilation_cache
from .run.calibrate import CalibrationResult, calibrate
from .run.driver import History, RunInterrupted, StableTimeStepWarning
from .run.ensemble import ensemble
from .run.memory import gradient_schedule
from .model.simulation import Simulation, backend_info
from .model.step import folds_force, g2p, grid_phases, grid_solve, p2g
from .io.hdf5 import H5Writer, load_h5, save_h5
from .io.plot import animate, plot_frames
from .resume import resume
from .scenes import SCENES, register_scene, scene


__all__ = [
    "CalibrationResult", "PARAMETERS", "calibrate", "ensemble", "get_params", "set_params",
    "MATERIALS", "SCHEMES", "SHAPES", "TERMS", "Parameter", "register_material", "register_scheme",
    "register_shape", "register_term", "scheme_from_name", "shape_from_name",
    "Ball", "BodyForce", "Box", "Constraint", "Contact", "CubicBSpline", "Damping", "Disk", "FLIP", "FMPM", "Fixed",
    "Grid", "GridFields", "GridSolution", "H5Writer", "History", "InputError", "InstabilityError", "Linear",
    "ParticlesLeftGrid",
    "LinearElastic",
    "Material", "NeoHookean", "NodeSet", "PIC", "ParticleField", "ParticleUpdate", "Particles", "Prescribed",
    "QuadraticBSpline", "Region", "Ring", "RunInterrupted", "SCENES", "Scheme", "ShapeFunction", "Simulation", "Slip",
    "StableTimeStepWarning", "State", "Stencil", "StencilBase", "StressDivergence", "TensorStencil", "Term",
    "AxisymmetricStencil",
    "Transfer", "UGIMP", "XPIC", "angular_momentum", "fill", "folds_force", "g2p", "gather", "grid_solve",
    "kinetic_energy", "linear_momentum", "load_h5", "resume", "mass_matrix_series", "p2g", "save_h5", "scatter",
    "register_scene", "scene", "stable_dt", "strain_energy", "with_fields", "with_scheme_state",
    "APIC", "RPIC", "TPIC", "with_velocity_gradient", "Wall", "NoStress", "VolumetricFluid",
    "Diffusion", "Dirichlet", "Heat", "Neumann", "Transport", "HypoElastic", "IncrementalElastic", "ParticleForce",
    "Traction", "Reaction", "Mirror", "compilation_cache", "reuse_host_memory",
    "ElasticMaterial", "InelasticMaterial", "Increment", "ParticleDamping", "Contraction", "Weighted", "Gradient",
    "Divergence", "Affine", "Hoop", "PerSlot", "Kernel", "register_kernel", "series", "exchange_series",
    "grid_phases", "Mesh", "Polygon", "point_cloud", "animate", "plot_frames",
    "Collider", "HalfSpace", "LevelSet", "SolidBox", "SolidCylinder", "SolidSphere", "SolidUnion",
    "HenckyPlastic", "VonMises",
    "DruckerPrager",
    "CamClay",
    "NewtonianFluid",
    "backend_info", "gradient_schedule", "compiler_options",
]

# help(jm.Grid.__init__) and call tips show the Args of the class docstring (an equinox module's
# generated __init__ has no docstring of its own)
for _public in map(globals().get, __all__):
    if isinstance(_public, type):
        _document_init(_public)
del _public

# the persistent compilation cache, on by default (jaxmpm/run/cache.py; JAXMPM_CACHE=0 switches it
# off): last, so that a compilation while importing would not open it
_enable_compilation_cache()
del _enable_compilation_cache
