"""Configurations whose results were stored before the open-core refactor (issue 10), so that the
refactor can prove it kept every number.

``generate.py`` ran these on commit 025c38f (the last commit before the refactor) and wrote
``values.npz``; ``tests/test_reference_values.py`` runs them on the current code and compares.
Everything here goes through the public API only.

* ``one_step``: one time step of every scheme x shape x dimension in float64, from a state with
  random velocities, a pre-deformed F (so the stress is not zero), random affine matrices (APIC,
  TPIC), gravity, grid and particle damping and Fixed / Slip / Prescribed nodes that overlap the
  body; plus the USF and MUSL updates, the folded (damping=False) affine path with one-sided
  walls and a fluid, and the XPIC/FMPM options (position update, boundary mode, series form).
* ``runs``: whole ``bar`` and ``spin`` runs (histories and final states).
"""

from __future__ import annotations

import inspect

import equinox as eqx
import numpy as np

import jaxmpm as jm

SCHEMES = {
    "flip": lambda: jm.FLIP(),
    "pic": lambda: jm.PIC(),
    "blend": lambda: jm.FLIP(beta=0.99),
    "xpic3": lambda: jm.XPIC(order=3, beta=0.2),
    "fmpm3": lambda: jm.FMPM(order=3, beta=0.1),
    "apic": lambda: jm.APIC(),
    "tpic": lambda: jm.TPIC(),
}

SHAPES = {
    "linear": lambda: jm.Linear(),
    "ugimp": lambda: jm.UGIMP(ppc=2),
    "quadratic": lambda: jm.QuadraticBSpline(),
    "cubic": lambda: jm.CubicBSpline(),
}

CELLS = {1: (12,), 2: (8, 7), 3: (6, 6, 5)}


def _grid(dim):
    return jm.Grid((0.0,) * dim, (1.0,) * dim, CELLS[dim])


def _layers(grid, axis):
    """Node layers from a face that reach x = 0.4 (into the body at [0.3, 0.7])."""
    return int(np.floor(0.4 / grid.spacing[axis])) + 1


def _prescribed(*args, **kwargs):
    """jm.Prescribed as the stored values knew it: the grid alone holds the velocity (core v2 added
    ``impulse``, default True, which also hands the particles the velocity change)."""
    if "impulse" in inspect.signature(jm.Prescribed.__init__).parameters:
        kwargs["impulse"] = False
    return jm.Prescribed(*args, **kwargs)


def _boundary(grid, kind):
    d = grid.dim
    if kind == "walls":
        return [jm.Wall(f"{a}{s}", layers=_layers(grid, i)) for i, a in enumerate("xyz"[:d]) for s in "-+"]
    conditions = [jm.Fixed("x-", layers=_layers(grid, 0))]
    if d >= 2:
        conditions.append(jm.Slip("y+", layers=_layers(grid, 1)))
        conditions.append(_prescribed("x+", [0.07], axes=(d - 1,), layers=_layers(grid, 0)))
    else:
        conditions.append(_prescribed("x+", 0.05, layers=_layers(grid, 0)))
    return conditions


def _material(kind):
    if kind == "fluid":
        return jm.VolumetricFluid(E=40.0, density=2.0)
    return jm.NeoHookean(E=50.0, nu=0.3, density=2.0)


def with_affine(state, affine):
    """``state`` with the scheme's per-particle affine matrices (APIC's B_p, TPIC's grad v_p) set."""
    return jm.with_scheme_state(state, affine) if hasattr(jm, "with_scheme_state") else eqx.tree_at(
        lambda s: s.affine, state, affine, is_leaf=lambda x: x is None)


def scheme_state(state):
    """The affine matrices of ``state`` or None."""
    return state.scheme_state if hasattr(state, "scheme_state") else state.affine


def build(dim, scheme, shape, update="USL", boundary="fixed", damping=True, material="neohookean", seed=0):
    """(sim, state, dt) of one configuration."""
    grid = _grid(dim)
    shape_fn = SHAPES[shape]()
    scheme_obj = SCHEMES[scheme]() if isinstance(scheme, str) else scheme
    gravity = np.zeros(dim)
    gravity[-1] = -3.0
    sim = jm.Simulation(grid=grid, shape=shape_fn, material=_material(material), scheme=scheme_obj,
                        damping=jm.Damping(grid=0.3, particle=0.2) if damping else False, update=update,
                        boundary=_boundary(grid, boundary), gravity=gravity)
    particles = jm.fill(grid, jm.Box((0.3,) * dim, (0.7,) * dim), ppc=2)
    state = sim.init(particles)
    rng = np.random.default_rng(seed + 17 * dim)
    n = state.x.shape[0]
    v = 0.3 * rng.standard_normal((n, dim))
    F = np.eye(dim) + 0.05 * rng.standard_normal((n, dim, dim))
    state = eqx.tree_at(lambda s: (s.v, s.F), state, (np.asarray(v), np.asarray(F)))
    if scheme in ("apic", "tpic"):
        state = with_affine(state, np.asarray(0.2 * rng.standard_normal((n, dim, dim))))
    return sim, state, 0.002


def one_step_cases():
    """name -> keyword arguments of :func:`build`."""
    cases = {}
    for dim in (1, 2, 3):
        for shape in SHAPES:
            for scheme in SCHEMES:
                cases[f"{scheme}-{shape}-{dim}d"] = dict(dim=dim, scheme=scheme, shape=shape)
    for update in ("USF", "MUSL"):
        for shape in ("linear", "quadratic"):
            for scheme in SCHEMES:
                cases[f"{scheme}-{shape}-2d-{update}"] = dict(dim=2, scheme=scheme, shape=shape, update=update)
    for dim in (2, 3):  # the folded P2G (p + f dt) of APIC/TPIC without damping; one-sided walls; a fluid
        for scheme in ("flip", "apic", "tpic"):
            cases[f"{scheme}-quadratic-{dim}d-walls-fluid"] = dict(dim=dim, scheme=scheme, shape="quadratic",
                                                                   boundary="walls", damping=False,
                                                                   material="fluid")
    options = {
        "xpic-PV": jm.XPIC(order=3, beta=0.2, position="PV"),
        "xpic-first-order": jm.XPIC(order=3, beta=0.2, position="first_order"),
        "xpic-result": jm.XPIC(order=4, boundary="result"),
        "xpic-lumped": jm.XPIC(order=4, boundary="lumped"),
        "xpic-neumann": jm.XPIC(order=5, series="neumann"),
        "fmpm-lumped": jm.FMPM(order=4, boundary="lumped"),
        "fmpm-neumann-MUSL": (jm.FMPM(order=5, series="neumann"), "MUSL"),
        "xpic-USF": (jm.XPIC(order=3), "USF"),
    }
    for name, spec in options.items():
        scheme, update = spec if isinstance(spec, tuple) else (spec, "USL")
        for shape in ("linear", "quadratic"):
            cases[f"{name}-{shape}-2d"] = dict(dim=2, scheme=scheme, shape=shape, update=update)
    return cases


def one_step_values(sim, state, dt, step):
    """The stored numbers of one step: the new particle state and the diagnostics."""
    new = step(sim, state, dt)
    out = dict(x=new.x, v=new.v, F=new.F, time=new.time, dissipated=new.dissipated)
    affine = scheme_state(new)
    if affine is not None:
        out["affine"] = affine
    return {k: np.asarray(v) for k, v in out.items()}


RUNS = {
    "bar-flip": dict(scene="bar", scheme="flip"),
    "bar-xpic3-ugimp": dict(scene="bar", scheme="xpic3", shape="ugimp", t_end=10.0),
    "bar-fmpm2-musl-damped": dict(scene="bar", scheme=lambda: jm.FMPM(order=2), update="MUSL",
                                  damping=lambda: jm.Damping(grid=0.05, particle=0.02), t_end=10.0),
    "bar-apic-quadratic": dict(scene="bar", scheme="apic", shape="quadratic", t_end=10.0),
    "spin-flip": dict(scene="spin", scheme="flip"),
    "spin-apic": dict(scene="spin", scheme="apic"),
    "spin-tpic-stress": dict(scene="spin", scheme="tpic", stress=True, t_end=1.0),
    "spin-xpic2-usf": dict(scene="spin", scheme=lambda: jm.XPIC(order=2), update="USF", t_end=0.5),
}


def run_setup(name):
    spec = dict(RUNS[name])
    scene = spec.pop("scene")
    for key in ("scheme", "damping"):
        if key in spec:
            value = spec[key]
            spec[key] = SCHEMES[value]() if isinstance(value, str) else value()
    if scene == "bar" and "shape" in spec:
        spec["shape"] = SHAPES[spec["shape"]]()
        if isinstance(spec["shape"], jm.UGIMP):
            spec["ppc"] = 2
    return jm.scene(scene, dtype="f64", **spec)


def run_values(setup):
    final, hist = setup.run()
    out = dict(time=hist.time, kinetic=hist.kinetic, strain=hist.strain, dissipated=hist.dissipated,
               momentum=hist.momentum, angular=hist.angular, x=final.x, v=final.v, F=final.F)
    affine = scheme_state(final)
    if affine is not None:
        out["affine"] = affine
    return {k: np.asarray(v) for k, v in out.items()}


# ------------------------------------------------------------------------------------------------
# Core v2 (issue 27): further configurations, stored on commit 6c6f418 (the last commit before the
# core v2 refactor) in ``values_v2.npz`` by ``generate.py --v2``: the USAVG updates, every contact
# law with every scheme, the damping variants, the transport / load / reaction / mirror terms,
# axisymmetric grids and whole disks, bars_impact and heat1d runs.  ``one_step_values`` also stores
# the per-particle fields here (the first set predates them).

CONTACT_LAWS = {
    "stick": dict(law="stick"),
    "frictionless": dict(law="frictionless"),
    "coulomb": dict(law="coulomb", friction=0.3),
}

DAMPINGS = {
    "momentum": lambda: jm.Damping(grid=0.3, particle=0.2, approach="momentum"),
    "force": lambda: jm.Damping(grid=0.3, particle=0.2, approach="force"),
    "force-region": lambda: jm.Damping(grid=0.3, particle=0.2, approach="force", region=lambda x: 1.0 + x[:, 0]),
    "schedule": lambda: jm.Damping(grid=0.3, particle=0.2, schedule=((0.0, 1.0), (1.0, 3.0))),
}


def _insulated():
    """As the stored values knew multimaterial transport: no heat crosses a contact interface (core
    v2 added ``interface``, default "perfect")."""
    return {"interface": "insulated"} if "interface" in inspect.signature(jm.Heat.__init__).parameters else {}


def _terms(kind, dim):
    """Extra physics terms of a configuration."""
    if kind == "heat":
        return (jm.Heat(conductivity=0.5, heat_capacity=2.0, expansion=0.01, boundary=jm.Dirichlet("x-", 1.0),
                        initial=lambda x: 0.2 + np.sin(3.0 * x[:, 0]), **_insulated()),)
    if kind == "heat-xpic":
        return (jm.Heat(conductivity=0.5, heat_capacity=2.0, update="xpic:3", initial=lambda x: np.cos(4.0 * x[:, 0])),)
    if kind == "diffusion":
        return (jm.Diffusion(diffusivity=0.2, expansion=0.02, boundary=jm.Neumann("x+", 0.5),
                             initial=lambda x: 0.5 * x[:, 0]),)
    if kind == "loads":
        return (jm.Traction(lambda x: x[:, 0] > 0.65, [0.4] + [0.1] * (dim - 1), "x+", basis="grid"),
                jm.ParticleForce(lambda x: x[:, -1] < 0.35, [0.0] * (dim - 1) + [-0.5]))
    if kind == "reaction":
        return (jm.Reaction(),)
    if kind == "stress-xpic":
        return (jm.StressDivergence(xpic=2),)
    return ()


def build_v2(dim, scheme, shape, update="USL", boundary="fixed", damping="velocity", material="neohookean", seed=0,
             contact=None, normal="average", materials=2, separation=None, series_correction=True, terms=None,
             axisymmetric=False, kinematics="linear"):
    """(sim, state, dt) of a core v2 configuration: :func:`build`'s body with contact (material ids by
    position, the bodies approaching), a damping variant, extra terms or an r-z grid."""
    grid = jm.Grid((0.0,) * dim, (1.0,) * dim, CELLS[dim], axisymmetric=True) if axisymmetric else _grid(dim)
    shape_fn = SHAPES[shape]()
    scheme_obj = SCHEMES[scheme]() if isinstance(scheme, str) else scheme
    gravity = np.zeros(dim)
    gravity[-1] = -3.0
    damping_obj = (jm.Damping(grid=0.3, particle=0.2) if damping == "velocity" else
                   False if damping is None else DAMPINGS[damping]())
    extra = _terms(terms, dim)
    if contact is not None:
        extra = extra + (jm.Contact(normal=normal, materials=materials, separation=separation,
                                    series_correction=series_correction, **CONTACT_LAWS[contact]),)
    sim = jm.Simulation(grid=grid, shape=shape_fn, material=_material(material), scheme=scheme_obj,
                        damping=damping_obj, update=update, boundary=_boundary(grid, boundary), gravity=gravity,
                        terms=extra, kinematics=kinematics)
    particles = jm.fill(grid, jm.Box((0.3,) * dim, (0.7,) * dim), ppc=2)
    rng = np.random.default_rng(seed + 17 * dim)
    fields = {}
    x = np.asarray(particles.x)
    if contact is not None:  # bodies side by side along x, approaching
        ids = np.minimum(np.floor((x[:, 0] - 0.3) / 0.4 * materials), materials - 1)
        fields["material"] = ids
    state = sim.init(particles, fields=fields)
    n = state.x.shape[0]
    v = 0.3 * rng.standard_normal((n, dim))
    if contact is not None:
        v[:, 0] += 0.5 - fields["material"] * (1.0 / max(materials - 1, 1))
    dF = dim + int(axisymmetric)
    F = np.eye(dF) + 0.05 * rng.standard_normal((n, dF, dF))
    if axisymmetric:
        F[:, 2, :2] = F[:, :2, 2] = 0.0
    state = eqx.tree_at(lambda s: (s.v, s.F), state, (np.asarray(v), np.asarray(F)))
    if scheme in ("apic", "tpic"):
        state = with_affine(state, np.asarray(0.2 * rng.standard_normal((n, dim, dim))))
    return sim, state, 0.002


def v2_step_cases():
    """name -> keyword arguments of :func:`build_v2`."""
    cases = {}
    for update in ("USAVG-", "USAVG+"):
        for shape in ("linear", "quadratic"):
            for scheme in SCHEMES:
                cases[f"{scheme}-{shape}-2d-{update}"] = dict(dim=2, scheme=scheme, shape=shape, update=update)
    for law in CONTACT_LAWS:
        for shape in ("linear", "quadratic"):
            for scheme in SCHEMES:
                cases[f"contact-{law}-{scheme}-{shape}-2d"] = dict(dim=2, scheme=scheme, shape=shape, contact=law)
        for dim in (1, 3):
            for scheme in ("flip", "fmpm3"):
                cases[f"contact-{law}-{scheme}-ugimp-{dim}d"] = dict(dim=dim, scheme=scheme, shape="ugimp",
                                                                     contact=law)
        cases[f"contact-{law}-flip-linear-2d-3materials"] = dict(dim=2, scheme="flip", shape="linear", contact=law,
                                                                 materials=3)
    for scheme in ("flip", "xpic3"):
        cases[f"contact-coulomb-{scheme}-linear-2d-first"] = dict(dim=2, scheme=scheme, shape="linear",
                                                                  contact="coulomb", normal="first")
    cases["contact-frictionless-flip-linear-2d-separation"] = dict(dim=2, scheme="flip", shape="linear",
                                                                   contact="frictionless", separation=0.5)
    cases["contact-stick-xpic3-linear-2d-no-correction"] = dict(dim=2, scheme="xpic3", shape="linear",
                                                                contact="stick", series_correction=False)
    cases["contact-frictionless-apic-quadratic-2d-walls"] = dict(dim=2, scheme="apic", shape="quadratic",
                                                                 contact="frictionless", boundary="walls")
    for damping in DAMPINGS:
        for scheme in ("flip", "xpic3", "fmpm3", "apic"):
            cases[f"damping-{damping}-{scheme}-quadratic-2d"] = dict(dim=2, scheme=scheme, shape="quadratic",
                                                                     damping=damping)
    for terms in ("heat", "heat-xpic", "diffusion", "loads", "reaction", "stress-xpic"):
        for scheme in ("flip", "fmpm3"):
            cases[f"terms-{terms}-{scheme}-linear-2d"] = dict(dim=2, scheme=scheme, shape="linear", terms=terms)
    cases["terms-loads-flip-ugimp-1d"] = dict(dim=1, scheme="flip", shape="ugimp", terms="loads")
    cases["terms-heat-flip-linear-2d-contact"] = dict(dim=2, scheme="flip", shape="linear", terms="heat",
                                                      contact="frictionless")
    for scheme in ("flip", "apic"):
        for shape in ("linear", "ugimp"):
            cases[f"rz-{scheme}-{shape}"] = dict(dim=2, scheme=scheme, shape=shape, axisymmetric=True)
    cases["exponential-flip-quadratic-2d"] = dict(dim=2, scheme="flip", shape="quadratic", kinematics="exponential")
    return cases


def v2_step_values(sim, state, dt, step):
    """:func:`one_step_values` plus every per-particle field of the new state."""
    new = step(sim, state, dt)
    out = one_step_values(sim, state, dt, lambda s, st, d: new)
    out.update({f"field_{k}": np.asarray(v) for k, v in new.fields.items()})
    return out


RUNS_V2 = {
    "disks-flip": dict(scene="disks", t_end=0.5, frames=10),
    "disks-fmpm2-contact": dict(scene="disks", scheme="fmpm:2", contact="frictionless", normal="average", t_end=0.5,
                                frames=10),
    "bars_impact-flip": dict(scene="bars_impact", frames=10),
    "bars_impact-xpic2-coulomb": dict(scene="bars_impact", scheme="xpic:2", contact="coulomb", frames=10),
    "heat1d-flip": dict(scene="heat1d"),
    "heat1d-xpic2": dict(scene="heat1d", transport="xpic:2"),
}


def run_setup_v2(name):
    spec = dict(RUNS_V2[name])
    scene = spec.pop("scene")
    return jm.scene(scene, dtype="f64", **spec)


def run_values_v2(setup):
    """:func:`run_values` plus the saved fields, per-material sums and totals of the history."""
    final, hist = setup.run()
    out = run_values(type("Saved", (), {"run": lambda self: (final, hist)})())
    out.update({f"field_{k}": np.asarray(v) for k, v in hist.fields.items()})
    out.update({f"material_{k}": np.asarray(v) for k, v in hist.by_material.items()})
    out.update({f"total_{k}": np.asarray(v) for k, v in hist.totals.items()})
    return out
