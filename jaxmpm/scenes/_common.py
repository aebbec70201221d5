"""Shared pieces of the scene builders."""

from __future__ import annotations

import dataclasses
import math
import numbers
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

from ..core.device import to_device
from ..core.errors import check
from ..core.limits import require_steps


@dataclasses.dataclass
class Setup:
    """A ready-to-run scene: ``sim``, initial ``state``, ``dt``, ``steps``, ``save_every``,
    ``params`` (the scene's parameters, written to HDF5) and ``reference`` (exact solution, if any)."""

    name: str
    sim: Any
    state: Any
    dt: float
    steps: int
    save_every: int
    params: dict
    reference: Callable | None = None
    particles: Any = None  # the filled particles: sim.init(particles) inside a loss makes d/d(density) flow
    fields: dict | None = None  # the particle fields given to sim.init (material ids in multimaterial scenes):
    #                             sim.init(setup.particles, fields=setup.fields) rebuilds ``state``

    def __post_init__(self):
        # The simulation's float parameters (E, beta, damping, gravity) follow the state's dtype, so a
        # dtype="f32" scene stays float32 in a 64-bit process instead of promoting inside lax.scan.
        self.sim = cast_state(self.sim, self.state.x.dtype)

    @property
    def t_end(self) -> float:
        return self.dt * self.steps

    def run(self, **kwargs):
        """``sim.run(state, dt, steps, save_every, **kwargs)``."""
        return self.sim.run(self.state, self.dt, self.steps, self.save_every, **kwargs)


#: the parts each scene builds when ``scheme``/``shape`` are left out, as the CLI spells them
#: (``jaxmpm scenes``, ``--help``); tests/test_cli.py checks them against the built scenes
PART_DEFAULTS = {
    "bar": {"scheme": "flip", "shape": "linear"},
    "disks": {"scheme": "flip", "shape": "ugimp"},
    "spin": {"scheme": "flip", "shape": "quadratic"},
    "rings": {"scheme": "flip", "shape": "quadratic"},
    "mpm88": {"scheme": "apic", "shape": "quadratic"},
    "mms": {"scheme": "flip", "shape": "linear"},
    "vortex": {"scheme": "flip", "shape": "quadratic"},
    "bars_impact": {"scheme": "flip", "shape": "linear"},
    "slide": {"scheme": "flip", "shape": "ugimp"},
    "incline": {"scheme": "flip", "shape": "ugimp"},
    "column_collapse": {"scheme": "apic", "shape": "quadratic"},
    "heat1d": {"scheme": "flip", "shape": "linear"},
    "heat_step": {"scheme": "flip", "shape": "linear"},
    "diffusion2d": {"scheme": "flip", "shape": "linear"},
    "thermal_bar": {"scheme": "flip", "shape": "ugimp"},
    "cylinder": {"scheme": "flip", "shape": "ugimp"},
    "dam_break": {"scheme": "apic", "shape": "quadratic"},
    "taylor_bar": {"scheme": "flip", "shape": "linear"},
}

#: what a default the builder derives (``None``, or a damping the scene adds itself) amounts to, as
#: ``jaxmpm scenes`` and ``jaxmpm run SCENE --help`` print it; a ``dt=None`` of a scene with ``cfl`` is
#: "from cfl" everywhere, and a damping left out "0" (``alpha_g``/``alpha_p``: the damping's rates,
#: --alpha-g and --alpha-p); tests/test_cli_scenes.py checks the numbers against the built scenes
DERIVED_DEFAULTS = {
    "spin": {"t_end": "1 (with stress: one turn 2 pi/omega)", "E": "100 (with --stress)", "nu": "0.3 (with --stress)"},
    "mms": {"t_end": "one period 2/c"},
    "vortex": {"t_end": "one period"},
    "bars_impact": {"t_end": "4 L/c (twice the contact time)"},
    "thermal_bar": {"alpha_p": "20"},
    "cylinder": {"alpha_g": "the breathing mode's frequency"},
    "dam_break": {"t_end": "T = t sqrt(2 g / a) = 5.5"},
    "column_collapse": {"t_end": "5 sqrt(H0/g)"},
}

#: the ``contact`` option of the multimaterial scenes: "none" keeps one velocity field (the model of a
#: one-material scene), the others give each body its own material and field (jaxmpm/_contact.py)
CONTACT_OPTIONS = ("none", "stick", "frictionless", "coulomb")

#: the per-frame fields ``jaxmpm run SCENE`` saves when ``--fields`` is not given (jaxmpm.model.frame_fields):
#: the stress of the solids (the cylinder's hoop stress stress_tt), the fluid's pressure, the heated bar's
#: expansion J; a scene not listed saves none (the transport scenes' temperature / concentration is saved
#: anyway, the spinning disk has no stress).  The Python API saves none unless asked (fields=)
FIELD_DEFAULTS = {
    "bar": ("stress",),
    "disks": ("stress",),
    "rings": ("stress",),
    "mpm88": ("pressure",),
    "mms": ("stress",),
    "vortex": ("stress",),
    "bars_impact": ("stress",),
    "slide": ("stress",),
    "incline": ("stress",),
    "thermal_bar": ("stress", "J"),
    "cylinder": ("stress",),
    "dam_break": ("pressure",),
    "column_collapse": ("stress", "plastic_strain"),
    "taylor_bar": ("stress", "plastic_strain"),
}


def contact_model(contact: str, friction: float, normal=None, separation: float | None = None) -> tuple:
    """(terms, material_fields): the ``terms=`` of a two-body scene's Simulation and whether its
    particles need material ids.  contact="none" gives ``()`` -- exactly the single-field model;
    a law gives ``(jm.Contact(law=contact, friction=...),)``, with the friction passed only to
    "coulomb" (the option checks reject a friction given with another law); ``normal`` as
    :class:`jaxmpm.Contact` takes it (None: its default), and the ``separation`` criterion (cells;
    None: none)."""
    if contact == "none":
        return (), False
    from ..physics.contact import Contact

    chosen = {} if normal is None else {"normal": normal}
    return (Contact(law=contact, friction=friction if contact == "coulomb" else 0.0, separation=separation,
                    **chosen),), True


def contact_normal_param(terms) -> str | list | None:
    """The contact normal of a scene's ``terms`` (from :func:`contact_model`) for its params: the
    option's name, the specified vector as a list, or None without contact."""
    normal = terms[0].normal if terms else None
    return list(normal) if isinstance(normal, tuple) else normal


def material_ids(counts, dtype=None):
    """Material ids 0, 1, ... for bodies of ``counts`` particles each, concatenated in that order (made on
    the host: op by op jnp compiled a small program per body and one for the concatenation)."""
    dtype = jnp.result_type(float) if dtype is None else dtype
    return to_device(np.concatenate([np.full((int(n),), float(k), dtype=dtype) for k, n in enumerate(counts)]))


def resolve_dtype(dtype):
    """"f32"/"f64"/None -> a JAX float dtype; f64 requires jax_enable_x64."""
    if dtype is None:
        return jnp.result_type(float)
    name = {"f32": "float32", "float32": "float32", "f64": "float64", "float64": "float64"}.get(str(dtype))
    check(name is not None, f"dtype = {dtype!r}; use 'f32' or 'f64'")
    if name == "float64":
        check(jax.config.jax_enable_x64,
              "dtype = 'f64' needs 64-bit JAX: call jax.config.update('jax_enable_x64', True) first")
    return jnp.dtype(name)


def schedule(t_end: float, dt: float, frames: int = 200) -> tuple[int, int]:
    """(steps, save_every): about ``frames`` saved frames covering at least t_end.  Arithmetic, in
    O(frames) whatever the step count: t_end stays exact when some divisor d of the step count
    gives between frames/2 and 2 frames (the one nearest steps/frames), else the step count is
    rounded up to a multiple of round(steps/frames)."""
    check(math.isfinite(t_end) and t_end > 0, f"t_end = {t_end} must be a positive finite time")
    check(math.isfinite(dt) and dt > 0, f"dt = {dt} must be a positive finite time step")
    check(isinstance(frames, numbers.Integral) and not isinstance(frames, bool) and frames >= 1,
          f"frames = {frames!r} must be a positive integer")
    ratio = t_end / dt
    require_steps(ratio, "shorten t_end or use a larger dt (or cfl)")
    steps = max(1, int(math.ceil(ratio - 1e-9)))
    target = steps / frames
    counts = range(max(1, math.ceil(frames / 2)), min(steps, math.floor(2 * frames)) + 1)  # frame counts
    divisors = sorted({steps // f for f in counts if steps % f == 0})
    divisors = [d for d in divisors if frames / 2 <= steps / d <= 2 * frames]
    if divisors:  # keep t_end exact when a divisor gives a sensible frame count
        return steps, min(divisors, key=lambda d: abs(d - target))
    save_every = max(1, int(round(target)))
    return int(math.ceil(steps / save_every)) * save_every, save_every


def cast_state(state, dtype):
    """Cast the float leaves of a state to ``dtype``."""
    return jax.tree_util.tree_map(
        lambda a: a.astype(dtype) if hasattr(a, "dtype") and jnp.issubdtype(a.dtype, jnp.floating) else a, state
    )
