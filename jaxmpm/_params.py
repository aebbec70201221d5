"""Named float parameters of a :class:`Simulation`, for calibration and ensembles.

``set_params(sim, beta=0.5, alpha_g=0.1)`` returns a new simulation; ``get_params(sim, "beta")``
reads them.  Each name is a path to an array leaf, so ``jax.grad`` and ``jax.vmap`` reach it.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp

from ._errors import check

PARAMETERS = {
    "beta": (lambda s: s.scheme.beta, "the scheme's FLIP fraction (FLIP, XPIC, FMPM)"),
    "alpha_g": (lambda s: s.damping.grid, "grid damping alpha_g (1/time)"),
    "alpha_p": (lambda s: s.damping.particle, "particle damping alpha_p (1/time)"),
    "E": (lambda s: s.material.E, "Young's modulus"),
    "nu": (lambda s: s.material.nu, "Poisson's ratio"),
    "density": (lambda s: s.material.density, "reference density (re-run sim.init for particle masses)"),
    "gravity": (lambda s: s.gravity, "gravity vector"),
}


def _with_damping(sim, name):
    """``sim`` itself, or (built with ``damping=False``, no damping in the model) a copy with zero
    damping put back, so that alpha_g and alpha_p can be read, set and differentiated."""
    if name in ("alpha_g", "alpha_p") and sim.damping is None:
        from ._schemes import Damping

        sim = eqx.tree_at(lambda s: s.damping, sim, Damping(), is_leaf=lambda x: x is None)
    return sim


def _where(sim, name):
    check(name in PARAMETERS, f"unknown parameter {name!r}; choose one of {', '.join(PARAMETERS)}")
    where = PARAMETERS[name][0]
    try:
        where(sim)
    except AttributeError:
        check(False, f"parameter {name!r} does not exist for scheme {type(sim.scheme).__name__} / "
                     f"material {type(sim.material).__name__}")
    return where


def get_params(sim, *names) -> dict:
    """{name: value} for the named parameters."""
    return {n: _where(_with_damping(sim, n), n)(_with_damping(sim, n)) for n in names}


def set_params(sim, **values):
    """A copy of ``sim`` with the named parameters replaced (values may be traced)."""
    for name, value in values.items():
        sim = _with_damping(sim, name)
        where = _where(sim, name)
        old = where(sim)
        sim = eqx.tree_at(where, sim, jnp.asarray(value, dtype=jnp.result_type(old)))
    return sim
