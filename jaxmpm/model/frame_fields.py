"""Per-frame particle fields chosen by name: what a run saves in each frame besides the positions,
velocities and the fields its terms declare (temperature, concentration, contact force), for a
look at the stress, the pressure or the deformation along the run (``jm.H5Writer(...,
fields=("stress", "J"))``, ``sim.run(..., fields=...)``, ``jaxmpm run --fields``).

Only the chosen fields are computed and stored: F of a million 3D particles is 72 MB a frame in
float64.  A frame holds each as ``History.fields[name]`` (N, ...), written to HDF5 as
``/particles/<name>`` (T, N, ...) like a term's field.

* ``stress``   the Cauchy stress sigma = tau / J (N, d, d), tau the material's Kirchhoff stress of
               the deformation it sees (``Simulation.elastic_deformation``: thermal expansion
               removed) and J = det F; d = D, or 3 on an axisymmetric grid, (r, z, theta) order.
* ``pressure`` p = -(sigma_xx + sigma_yy + sigma_zz) / 3, the mean normal stress (N,).  In 3D and
               on an axisymmetric grid (sigma_rr + sigma_zz + sigma_thth) the stored stress holds
               all three.  In 2D (plane strain) and 1D the normal stress along the unresolved axes
               comes from the material (:meth:`Material.out_of_plane_stress`: LinearElastic,
               NeoHookean, VolumetricFluid, IncrementalElastic; zero for a uniaxial-stress law in
               1D); a law that does not give it (HypoElastic in 2D) has p = -tr(sigma) / d, the
               mean over the stored components.
* ``J``        det F (N,), the volume ratio V / V0.
* ``F``        the deformation gradient (N, d, d).
* the material's saved state: the entries of ``State.material_state`` its
  :attr:`Material.saved_state` names: ``plastic_strain`` (VonMises, DruckerPrager, CamClay),
  ``volumetric_plastic_strain`` (DruckerPrager, CamClay), ``preconsolidation_pressure`` (CamClay),
  ``viscous_dissipation`` (NewtonianFluid); none for the elastic laws.
"""

from __future__ import annotations

import jax.numpy as jnp

from ..core.errors import check
from ..core.linalg import det

#: the fields every model offers, with what each one is
FRAME_FIELDS = {
    "stress": "Cauchy stress sigma = tau / J (N, d, d)",
    "pressure": "mean normal stress p = -tr(sigma_3D) / 3 (N,)",
    "J": "volume ratio det F (N,)",
    "F": "deformation gradient (N, d, d)",
}


def available(sim, state) -> dict:
    """{name: what it is} of the fields a run of ``sim`` from ``state`` can save per frame."""
    material = {name: f"{type(sim.material).__name__}'s state entry {name!r}"
                for name in sim.material.state_fields(state.material_state)}
    return {**FRAME_FIELDS, **material}


def chosen(sim, state, fields, where: str = "fields") -> tuple:
    """``fields`` checked (names of :func:`available`, each once, none a term's saved field) as a
    tuple in the order of :func:`available` (stress, pressure, J, F, the material's: one order for
    every file, whatever order they were named in); ``where`` names the argument in the messages."""
    if isinstance(fields, (tuple, list)) and not fields:  # none chosen (every run's default): nothing to check
        return ()
    choices = available(sim, state)
    listed = ", ".join(choices)
    check(isinstance(fields, (tuple, list)) and all(isinstance(name, str) for name in fields),
          f"{where} = {fields!r}: give a tuple of field names, e.g. ('stress', 'J'), from {listed}")
    terms = {f.name for f in sim.particle_fields() if f.save}
    for name in fields:
        check(name not in terms, f"{where}: {name!r} is a field a term of the model declares, saved in every frame "
                                 "already (/particles/<name>); leave it out")
        check(name in choices, f"{where}: unknown field {name!r}; choose from {listed}")
        check(fields.count(name) == 1, f"{where}: {name!r} is named twice; name each field once")
    return tuple(name for name in choices if name in fields)


def cauchy_stress(sim, state):
    """sigma = tau / J (N, d, d)."""
    tau = sim.material.stress(sim.elastic_deformation(state), state.material_state)
    return tau / det(state.F)[:, None, None]


def pressure(sim, state, sigma):
    """p = -tr(sigma_3D) / 3 (module docstring: the out-of-plane stress of 1D and 2D from the
    material, else the mean over the stored components)."""
    d = sigma.shape[-1]
    normal = jnp.trace(sigma, axis1=-2, axis2=-1)
    if d == 3:
        return -normal / 3.0
    tau_out = sim.material.out_of_plane_stress(sim.elastic_deformation(state), state.material_state)
    if tau_out is None:
        return -normal / d
    return -(normal + (3 - d) * tau_out / det(state.F)) / 3.0


def frame_fields(sim, state, names: tuple) -> dict:
    """{name: (N, ...)} of the chosen ``names`` at ``state``; only those are computed."""
    out = {}
    sigma = cauchy_stress(sim, state) if {"stress", "pressure"} & set(names) else None
    material = sim.material.state_fields(state.material_state)
    for name in names:
        if name == "stress":
            out[name] = sigma
        elif name == "pressure":
            out[name] = pressure(sim, state, sigma)
        elif name == "J":
            out[name] = det(state.F)
        elif name == "F":
            out[name] = state.F
        else:
            out[name] = material[name]
    return out
