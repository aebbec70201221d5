"""One MPM time step as the stages of 003 §2.1, with the model's physics terms plugged in.

``step`` reads as the algorithm:

1. shape functions S_pi, G_pi at the particles               (001 eqs. 16-17)
2. ``p2g``: the nodal fields the scheme and the terms request, in one pass of the transfer
   kernel -- lumped mass m_i, momentum p_i (003 eq. 2.1, plus APIC/TPIC/RPIC's affine part) and
   the terms' quantities (the force f_i: stress divergence and body force, 001 eq. 20, 003 eq.
   2.10; a traction's surface integral, 001 eq. 21)
3. the grid solve, an ordered pipeline of phases (:func:`grid_phases`):
   a. **forces**: the terms' nodal forces from the assembled grid (force-form damping,
      001 eqs. 58-60), added to f;
   b. **exchange**: momentum exchange between velocity fields (contact), on p and on p + f dt
      (003 eqs. 3.9, 3.12, 3.19);
   c. **velocity conditions**: v = p/m, a = f/m, v_tilde = v + a dt with the conditions imposed
      (:func:`impose_conditions`: the model's one :class:`jaxmpm.Constraint`);
   d. **colliders**: rigid level-set solids (:class:`jaxmpm.Collider`) on v_tilde, a taking the
      change (:func:`collide`);
   e. **readers**: named results for later stages (reaction forces, a transport's nodal fields)
4. ``g2p``: the scheme's particle update (000 eq. 3.28, 003 eq. 2.17, 002 eq. 4) with the terms'
   damping; the strain update (USL-: the update's grid velocity; MUSL: re-extrapolated, with the
   exchange and the conditions, 003 §2.1.6); the terms' particle actions; the material's state
   update with the increment (:class:`jaxmpm.materials.Increment`)

USF computes the strain increment before the forces (from the start-of-step velocities, after the
exchange and the conditions); USAVG-/USAVG+ do both, each over dt/2: USF's before the forces, then
USL-'s resp. MUSL's (003 §2.2).

The forces add up, so their order does not matter; a model has at most one exchanging term; the
readers only add names.  So a model's physics does not depend on the order its terms were given
in, except for the particle actions, which run in term order (each term owns what it changes), and
colliders whose solids overlap (each acts on the velocity the one before left).
"""

from __future__ import annotations

import difflib

import equinox as eqx
import jax.numpy as jnp

from ..core.errors import check
from ..core.fields import GridFields, GridSolution
from ..core.linalg import matmul
from ..core.warn import warn
from ..materials.base import Increment
from ..physics.term import overrides
from ..schemes.base import ParticleUpdate, combine_damping
from ..transfer.contractions import Weighted, as_terms
from ..transfer.kernels import shared_reads
from ..transfer.operators import Transfer, gather, safe_divide
from ..transfer.operators import p2g as scatter_quantities

# the lumped grid quantities a part may need apart ("grid_reads"); P2G folds p and f otherwise
LUMPED = frozenset({"v", "a", "momentum", "force"})
# the grid solution's own names: the phases' results may not take them
SOLUTION_NAMES = ("v", "a", "v_tilde", "v_tilde_unconstrained", "v_unconstrained", "condition_dv")


def folds_force(sim) -> bool:
    """Whether P2G may scatter the updated momentum p + f dt in place of p and f ((1 + D) numbers
    per stencil slot instead of 1 + 2D): when no part of the model needs v, a, p or f apart -- the
    scheme reads only v_tilde (APIC, TPIC, RPIC), no term declares those quantities among its
    ``grid_reads`` (damping reads v; contact and force damping read p and f) -- and the update is
    USL or MUSL (USF needs v before the force).

    Args:
        sim: the :class:`jaxmpm.Simulation`.
    """
    if sim.update not in ("USL", "MUSL") or sim.scheme.uses_lumped_velocity:
        return False
    return not any(term.grid_reads(sim) & LUMPED or overrides(term, "grid_force") or
                   overrides(term, "exchange_momentum") for term in sim.terms)  # those act on f apart from p


def strain_dt(sim, dt):
    """The strain update's time step: dt, or dt/2 under USAVG-/USAVG+, which update the stress
    twice per step, before the forces and after the particle update (003 §2.2, steps 2 and 6)."""
    return 0.5 * dt if sim.update in ("USAVG-", "USAVG+") else dt


def deformation_increment(grad_v, dt, kinematics: str = "linear"):
    """dF = I + grad v dt (``kinematics="linear"``, the first-order increment) or dF = exp(grad v dt)
    (``"exponential"``, 001 eq. 26: exact for a velocity gradient constant over the step, so a pure
    spin gives an exact rotation, det dF = 1)."""
    if kinematics == "exponential":
        from jax.scipy.linalg import expm

        return expm(grad_v * dt)  # 001 eq. (26)
    eye = jnp.eye(grad_v.shape[-1], dtype=grad_v.dtype)
    return jnp.broadcast_to(eye, grad_v.shape) + grad_v * dt


def update_deformation(F, grad_v, dt, kinematics: str = "linear"):
    """F <- dF F with dF of :func:`deformation_increment`."""
    return matmul(deformation_increment(grad_v, dt, kinematics), F)


def strain_rate(sim, transfer: Transfer, v):
    """The velocity gradient the strain update uses, (grad v)_p = sum_i v_i (x) G_pi (003 eq. 2.7);
    on an axisymmetric grid the 3x3 (r, z, theta) gradient of 001 eq. 113 with the hoop rate
    v_r / r = sum_i v_ri T_ip in its (theta, theta) slot (T the hoop shape function, 001 eq. 116):
    the rate whose power is that of the hoop force, so the strain energy stays consistent."""
    grad = transfer.velocity_gradient(v)
    if not sim.grid.axisymmetric:
        return grad
    hoop = gather(transfer.stencil.hoop_view(), v[:, 0])  # sum_i v_ri T_ip, (N,)
    zero = jnp.zeros_like(grad[:, :, :1])
    top = jnp.concatenate([grad, zero], axis=2)  # (N, 2, 3)
    bottom = jnp.concatenate([jnp.swapaxes(zero, 1, 2), hoop[:, None, None]], axis=2)  # (N, 1, 3)
    return jnp.concatenate([top, bottom], axis=1)


# ------------------------------------------------------------------------------------------- P2G
def term_quantities(sim, state, stencil, terms=None) -> dict:
    """The terms' P2G quantities, {name: tuple of contractions}, quantities of one name in term order."""
    columns = {}
    for term in sim.terms if terms is None else terms:
        for name, column in term.p2g_quantities(sim, state, stencil).items():
            columns[name] = columns.get(name, ()) + as_terms(column)
    return columns


def _scaled(column: tuple, factor) -> tuple:
    return tuple(type(c)(factor * c.value) for c in column)


def p2g(sim, state, force: bool = True, dt=None) -> GridFields:
    """Lumped mass m_i = sum_p S_pi M_p, momentum p_i = sum_p S_pi M_p V_p (003 eq. 2.1) plus the
    scheme's affine part (APIC/TPIC/RPIC), and (``force=True``) the terms' quantities (the nodal
    force), all in one pass of the transfer kernel.  With ``dt`` (see :func:`folds_force`)
    momentum and force are scattered as one updated momentum p + f dt.  Without the force (USF's
    first P2G) the exchanging term's quantities (contact's mass gradients) are scattered too.

    Args:
        sim: the :class:`jaxmpm.Simulation`.
        state: the :class:`jaxmpm.State` at the step's start.
        force: whether to scatter the terms' quantities (the nodal force); default True.
        dt: the time step, to scatter p + f dt in place of p and f (only where
            :func:`folds_force` allows); None (the default): p and f apart.

    Returns:
        The :class:`jaxmpm.GridFields`, with the step's :class:`jaxmpm.Transfer`.
    """
    stencil, columns = p2g_quantities(sim, state, force, dt)
    nodal = scatter_quantities(stencil, columns, sim.field_nodes)
    if force or dt is not None:
        nodal = with_surface_forces(sim, state, nodal, dt)
    images = sim.constraint(state.x.dtype).mirror  # jm.Mirror: fold in the particles' mirror images
    if images is not None:
        nodal = images.fold_columns(nodal, folded_columns(sim))
    transfer = Transfer(stencil, state.mass, nodal.pop("mass"), sim.field_nodes, images)
    return GridFields(transfer, nodal)


def p2g_quantities(sim, state, force: bool = True, dt=None) -> tuple:
    """(stencil, {nodal field name: contractions}): what :func:`p2g` scatters, before the scatter."""
    stencil = sim.stencil(state)
    columns = {"mass": Weighted(state.mass), "momentum": as_terms(sim.scheme.momentum_contributions(stencil, state))}
    exchanger = sim.exchange_term
    terms = sim.terms if force or dt is not None else ([] if exchanger is None else [exchanger])
    columns.update(term_quantities(sim, state, stencil, terms))
    if dt is not None:
        columns["updated_momentum"] = columns.pop("momentum") + _scaled(columns.pop("force"), dt)
    return stencil, columns


def folded_columns(sim) -> tuple:
    """The nodal fields a symmetry plane folds: the velocity field's mass, momentum and force, and
    the terms' mass-weighted sums (``Term.folded_columns``)."""
    return ("mass", "momentum", "updated_momentum", "force") + tuple(
        name for term in sim.terms for name in term.folded_columns())


def with_surface_forces(sim, state, nodal: dict, dt=None) -> dict:
    """The nodal fields with the terms' own nodal forces (``Term.nodal_force``: tractions, 001
    eq. 21; each reads P2G's nodal sums, ``nodal``) added to the force, or dt times them to a
    folded updated momentum."""
    extra = [f for f in (term.nodal_force(sim, state, nodal) for term in sim.terms) if f is not None]
    if not extra:
        return nodal
    total = sum(extra[1:], extra[0])
    if "updated_momentum" in nodal:
        return {**nodal, "updated_momentum": nodal["updated_momentum"] + dt * total}
    return {**nodal, "force": nodal["force"] + total}


def nodal_terms(sim, state, transfer: Transfer) -> dict:
    """The terms' nodal fields alone (USF: after the strain update), in one pass; the exchanging
    term's, scattered before the strain update, are not repeated."""
    exchanger = sim.exchange_term
    terms = [t for t in sim.terms if t is not exchanger]
    nodal = transfer.p2g(term_quantities(sim, state, transfer.stencil, terms))
    nodal = with_surface_forces(sim, state, {**nodal, "mass": transfer.nodal_mass})
    nodal.pop("mass")
    return nodal if transfer.images is None else transfer.images.fold_columns(nodal, folded_columns(sim))


# ------------------------------------------------------------------------------------------ grid
def impose_conditions(fields: GridFields, dt, constraint) -> GridSolution:
    """Phase "velocity conditions": v = p/m, a = f/m (0 where m = 0), v_tilde = v + a dt, with the
    conditions imposed (two-sided ones on v and a; one-sided walls on v_tilde, as contact:
    :meth:`jaxmpm.Constraint.contact`).  From a folded P2G (:func:`folds_force`) only
    v_tilde = (p + f dt)/m exists (v, a are None); it is the same v_tilde: the conditions act on
    v + a dt in both cases.  ``v_tilde_unconstrained`` is p+/m before any condition (FMPM's
    unlumped boundary variants start from it, 003 §2.4) and ``v_unconstrained`` p/m (XPIC's
    ``boundary="unconstrained_start"``).  With ``constraint.reaction`` (``constrained_force=
    "reaction"``) v keeps p/m on the constrained components too and a takes the reaction,
    a = a_lumped + (v_tilde - (p + f dt)/m)/dt: on free components exactly a_lumped, on
    constrained ones (g - p/m)/dt (NairnMPM's grid forces at its velocity conditions)."""
    m = fields.mass
    if fields.updated_momentum is not None:
        return GridSolution(v=None, a=None, v_tilde=constraint.apply(safe_divide(fields.updated_momentum, m)))
    v_lumped, a_lumped = safe_divide(fields.momentum, m), safe_divide(fields.force, m)
    unconstrained = v_lumped + a_lumped * dt
    if constraint.wall is not None:  # one-sided walls act on v_tilde, as contact (jm.Wall)
        v, a, v_tilde = constraint.contact(constraint.apply_two_sided(v_lumped), constraint.zero(a_lumped), dt)
    else:
        v = constraint.apply(v_lumped)
        a = constraint.zero(a_lumped)
        v_tilde = constraint.apply(v + a * dt)
    impulse = constraint.particle_impulse(v, v_lumped, m)  # jm.Prescribed drives the particles
    if constraint.reaction:  # constrained_force="reaction": v stays p/m, the force is the reaction
        v, a = v_lumped, a_lumped + (v_tilde - unconstrained) / jnp.where(dt > 0, dt, 1.0)  # v + a dt = v_tilde
        impulse = None  # the reaction in S a dt carries a Prescribed velocity's change to the particles
    solution = GridSolution(v=v, a=a, v_tilde=v_tilde, v_tilde_unconstrained=unconstrained, v_unconstrained=v_lumped)
    return solution if impulse is None else GridSolution({**solution.values, "condition_dv": impulse})


def grid_solve(fields: GridFields, force, dt, constraint) -> GridSolution:
    """The velocity conditions alone on P2G's fields with the nodal force ``force``
    (``impose_conditions``): v = p/m, a = f/m, v_tilde = v + a dt with the conditions imposed;
    the model's whole grid solve, with its terms, is :func:`grid_phases`.

    Args:
        fields: the :class:`jaxmpm.GridFields` of :func:`p2g`.
        force: the nodal force (n, D) in place of ``fields.force``, or None to keep it.
        dt: the time step.
        constraint: the velocity conditions, ``sim.constraint(dtype)``.

    Returns:
        The :class:`jaxmpm.GridSolution` (``v``, ``a``, ``v_tilde``, ...).
    """
    return impose_conditions(fields if force is None else fields.replace(force=force), dt, constraint)


def _warn_if_misspelt_force(term, out: dict) -> None:
    """A grid_force result named like "force" but not it ("forces", "Force") is a result for other terms to
    read, not a force: the term would act by nothing.  Warned when the step is traced."""
    for name in out:
        if name != "force" and difflib.get_close_matches(name.lower(), ["force"], n=1, cutoff=0.85):
            warn(f"{type(term).__name__}.grid_force returned {name!r}, which is kept as a named result for "
                 "other terms to read and added to no force; a nodal force is returned as 'force'")


def _add_results(results: dict, new: dict, term) -> None:
    """Record a phase's named results, refusing a name already taken (two terms would overwrite)."""
    for name, value in (new or {}).items():
        check(name not in results and name not in SOLUTION_NAMES,
              f"{type(term).__name__}: the grid result {name!r} is already set by another term of this model "
              "or is one of the grid solution's own names (v, a, v_tilde); rename it")
        results[name] = value


def exchange(sim, term, fields: GridFields, dt, constraint):
    """Phase "exchange": the exchanging term's law on the momenta p and on the updated momenta
    p' + f dt (003 eqs. 3.9, 3.12, 3.19: the second change Dp+ = f^C dt is the exchange force),
    giving p' and f' = (p+' - p')/dt.  Results: ``exchange_acceleration`` (f' - f)/m, each
    velocity field's exchange force per mass, and -- for the XPIC/FMPM series term of 003 eqs.
    3.18, 3.22 -- ``exchange_dv`` = Dp/m, the first change as a velocity; or, where the term applies
    the exchange to the series' increments (``Term.exchange_increments``, contact's
    ``series="incremental"``), ``exchange_series``, its hook cached from the second application."""
    m, force = fields.mass, fields.force
    p, dp = term.exchange_momentum(sim, fields, fields.momentum)
    updated = p + force * dt
    p_plus, dp_plus = term.exchange_updated_momentum(sim, fields, updated, dt)
    safe_dt = jnp.where(dt > 0, dt, 1.0)
    results = {"exchange_acceleration": safe_divide(p_plus - p - force * dt, m) / safe_dt}
    increments = term.exchange_increments(sim, fields, updated, dp_plus, dt, updated=True)
    dv = exchange_dv(term, dp, m, constraint) if increments is None else None
    if increments is not None:
        results["exchange_series"] = increments
    if dv is not None:
        results["exchange_dv"] = dv
    return fields.replace(momentum=p, force=(p_plus - p) / safe_dt), results


def exchange_dv(term, dp, mass, constraint):
    """The exchange's change as a velocity, Dv = Dp/m on the free components, for the XPIC/FMPM
    series term (003 eqs. 3.18, 3.22); None when the term asks for no series term."""
    return constraint.zero(safe_divide(dp, mass)) if term.series_correction else None


def collide(sim, fields: GridFields, solution: GridSolution, dt, time, results: dict) -> GridSolution:
    """Phase "colliders": each term's rigid solid (``Term.collide``, in term order) sets the updated
    velocity v_tilde on its nodes; the lumped v stays free and a takes the change,
    a <- a + (v_tilde' - v_tilde)/dt, so that v + a dt = v_tilde' and FLIP's V + S a dt feels the
    solid as PIC's S v_tilde does -- the convention of the one-sided jm.Wall
    (:meth:`jaxmpm.Constraint.contact`).  The terms' named results go to ``results``."""
    colliders = [term for term in sim.terms if overrides(term, "collide")]
    if not colliders:
        return solution
    v_tilde = before = solution.v_tilde
    for term in colliders:
        v_tilde, out = term.collide(sim, fields, v_tilde, dt, time)
        _add_results(results, out, term)
    values = {**solution.values, "v_tilde": v_tilde}
    if solution.a is not None:
        values["a"] = solution.a + (v_tilde - before) / jnp.where(dt > 0, dt, 1.0)
    return GridSolution(values)


def collided_velocity(sim, fields: GridFields, v, dt, time):
    """A lumped velocity (USF's start-of-step one, MUSL's re-extrapolated one) with the colliders'
    conditions, as it has the walls'; their results are not kept."""
    for term in sim.terms:
        if overrides(term, "collide"):
            v, _ = term.collide(sim, fields, v, 0.0 if dt is None else dt, time)
    return v


def grid_phases(sim, fields: GridFields, dt, constraint, time=None) -> GridSolution:
    """The grid solve of one step: the phases forces -> exchange -> velocity conditions ->
    colliders -> readers (docs/architecture.md), each term acting in the phase its hooks name.

    Args:
        sim: the :class:`jaxmpm.Simulation`.
        fields: the :class:`jaxmpm.GridFields` of :func:`p2g`.
        dt: the time step.
        constraint: the velocity conditions, ``sim.constraint(dtype)``.
        time: the step's start time, where moving colliders stand (:class:`jaxmpm.Collider`);
            None (the default): 0.

    Returns:
        The :class:`jaxmpm.GridSolution` with the terms' named results.
    """
    results = {}
    for term in sim.terms:  # 1. nodal forces from the assembled grid; they add up
        out = term.grid_force(sim, fields, dt)
        if out:
            out = dict(out)
            force = out.pop("force", None)
            if force is not None:
                fields = fields.replace(force=fields.force + force)
            _warn_if_misspelt_force(term, out)
            _add_results(results, out, term)
    exchanger = sim.exchange_term  # 2. momentum exchange between velocity fields
    if exchanger is not None:
        fields, out = exchange(sim, exchanger, fields, dt, constraint)
        _add_results(results, out, exchanger)
    solution = impose_conditions(fields, dt, constraint)  # 3. velocity conditions
    solution = collide(sim, fields, solution, dt, 0.0 if time is None else time, results)  # 4. colliders
    for term in sim.terms:  # 5. readers
        _add_results(results, term.read_grid(sim, fields, solution, dt), term)
    solution = GridSolution({**solution.values, **results})
    for term in sim.terms:  # deprecated whole-solution hooks, after the readers
        if overrides(term, "grid_action"):
            solution = term.grid_action(sim, fields, solution, dt)
    return solution


def lumped_velocity(sim, fields: GridFields, momentum, constraint, dt=None, time=None):
    """(v, Dv): the lumped grid velocity of nodal momenta (USF's start-of-step velocity, MUSL's
    re-extrapolated one) after the momentum exchange and with the velocity conditions and the
    colliders (standing where they are at ``time``; None: 0), and the
    exchange's change as a velocity (None without an exchange or its series term) -- or, where the
    term applies the exchange to the series' increments, its hook (``Term.exchange_increments``,
    cached from this first application; ``dt`` the step's)."""
    exchanger = sim.exchange_term
    dv = None
    if exchanger is not None:
        after, dp = exchanger.exchange_momentum(sim, fields, momentum)
        dv = exchanger.exchange_increments(sim, fields, momentum, dp, 0.0 if dt is None else dt, updated=False)
        if dv is None:
            dv = exchange_dv(exchanger, dp, fields.mass, constraint)
        momentum = after
    v = constraint.apply(safe_divide(momentum, fields.mass))
    return collided_velocity(sim, fields, v, dt, 0.0 if time is None else time), dv


def strain_velocity(sim, v, transfer, constraint, exchange_dv=None):
    """The grid velocity of a USF/MUSL strain update: the scheme's (FMPM: its series), with the
    exchange's series term when velocity fields exchange momentum (003 §2.1.2, §2.1.6), or the
    exchange on the series' increments (``exchange_dv`` the term's hook, :func:`lumped_velocity`)."""
    if exchange_dv is None:
        return sim.scheme.strain_grid_velocity(v, transfer, constraint)
    return sim.scheme.strain_grid_velocity(v, transfer, constraint, exchange_dv=exchange_dv)


# ------------------------------------------------------------------------------------------ step
def material_update(sim, F_new, dF, material_state, old, new, dt):
    """The material's state after a strain update to F_new = dF F_old, with the terms' isotropic
    stretch removed from the increment: dF s(old) / s(new) (thermal strain is part of the
    increment, not of the elastic deformation)."""
    s_old, s_new = sim.stretch(old), sim.stretch(new)
    if s_old is not None:
        dF = dF * (s_old / s_new)[:, None, None]
    return sim.material.update_state(Increment(dF, F_new, dt, sim.kinematics), material_state)


def step(sim, state, dt):
    """One full time step; returns the new state.  Pure: jit, grad and vmap apply."""
    dt = jnp.asarray(dt, state.x.dtype)
    constraint = sim.constraint(state.x.dtype)
    if sim.update in ("USF", "USAVG-", "USAVG+"):  # stress first, with the start-of-step velocity
        fields = p2g(sim, state, force=False)
        transfer = fields.transfer
        v0, dv = lumped_velocity(sim, fields, fields.momentum, constraint, dt, state.time)
        v_strain = strain_velocity(sim, v0, transfer, constraint, dv)
        dF = deformation_increment(strain_rate(sim, transfer, v_strain), strain_dt(sim, dt), sim.kinematics)
        F = matmul(dF, state.F)  # F <- dF F
        moved = eqx.tree_at(lambda s: s.F, state, F)
        material_state = material_update(sim, F, dF, state.material_state, state, state, strain_dt(sim, dt))
        state = eqx.tree_at(lambda s: s.material_state, moved, material_state, is_leaf=lambda x: x is None)
        fields = GridFields(transfer, {**fields.values, **nodal_terms(sim, state, transfer)})
    else:  # USL, MUSL: the stress of the step's start, scattered with the mass and momentum
        fields = p2g(sim, state, dt=dt if folds_force(sim) else None)
    solution = grid_phases(sim, fields, dt, constraint, state.time)
    return g2p(sim, state, fields.transfer, constraint, solution, dt, fields)


def g2p(sim, state, transfer: Transfer, constraint, grid: GridSolution, dt, fields: GridFields | None = None):
    """Particle update by the scheme (with the terms' damping), the USL-/MUSL strain update, the
    terms' particle actions, then the material's state update with the step's increment.
    ``fields`` (the step's P2G fields) is needed by MUSL/USAVG+ when velocity fields exchange
    momentum (the exchange of the re-extrapolated momenta).  Each nodal field is read at the
    particles' slots once, however many operators use it (:func:`jaxmpm.transfer.kernels.shared_reads`).

    Args:
        sim: the :class:`jaxmpm.Simulation`.
        state: the :class:`jaxmpm.State` at the step's start.
        transfer: the step's :class:`jaxmpm.Transfer` (``fields.transfer``).
        constraint: the velocity conditions, ``sim.constraint(dtype)``.
        grid: the :class:`jaxmpm.GridSolution` of :func:`grid_phases`.
        dt: the time step.
        fields: the step's :class:`jaxmpm.GridFields`, or None (the default).

    Returns:
        The :class:`jaxmpm.State` at the step's end.
    """
    read_together = [f for f in (grid.v, grid.a, grid.v_tilde) if f is not None and f.ndim == 2]  # (n, D) each
    with shared_reads(transfer.stencil.index, read_together):
        return _g2p(sim, state, transfer, constraint, grid, dt, fields)


def _check_update(scheme, update, state) -> None:
    """A scheme's ``update`` returned a :class:`~jaxmpm.ParticleUpdate` of the particles' shapes (checked when
    the step is traced: a scheme of one's own had failed inside the step with an AttributeError or JAX's
    while-loop type error)."""
    name = f"{type(scheme).__name__}.update"
    check(isinstance(update, ParticleUpdate), f"{name} returned {type(update).__name__}; return "
          "jm.ParticleUpdate(velocity, position, strain_velocity, dissipated) (docs/extending.md, 'A scheme')")
    for field, value, expected in (("velocity", update.velocity, state.v.shape),
                                   ("position", update.position, state.x.shape),
                                   ("dissipated", update.dissipated, ())):
        check(jnp.shape(value) == expected, f"{name} returned {field} of shape {jnp.shape(value)}; it must have "
              f"shape {expected}" + (" (one energy for all the particles)" if field == "dissipated" else ""))


def _g2p(sim, state, transfer: Transfer, constraint, grid: GridSolution, dt, fields: GridFields | None = None):
    damping = combine_damping(term.particle_damping(sim, state, transfer, grid) for term in sim.terms)
    V = state.v
    if "condition_dv" in grid:  # the conditions' impulse on the particles (jm.Prescribed(impulse=True))
        V = V + transfer.gather(grid["condition_dv"])
    upd = sim.scheme.update(V, state.x, transfer, constraint, grid, damping, dt)
    _check_update(sim.scheme, upd, state)
    scheme_state = sim.scheme.next_state(state, upd, transfer, grid)
    F, dF = state.F, None
    if sim.update in ("USL", "USAVG-"):  # USL-: the velocity the update just used (USAVG-: for dt/2)
        dF = deformation_increment(strain_rate(sim, transfer, upd.strain_velocity), strain_dt(sim, dt), sim.kinematics)
    elif sim.update in ("MUSL", "USAVG+"):  # USL+: re-extrapolate p = S^T M V^{n+1} (003 §2.1.6), affine terms too
        updated = eqx.tree_at(lambda s: (s.v, s.scheme_state), state, (upd.velocity, scheme_state),
                              is_leaf=lambda x: x is None)
        momentum = transfer.fold(sim.scheme.momentum(transfer, updated))
        if fields is None:
            check(sim.exchange_term is None, f"g2p: under {sim.update} a model whose terms exchange momentum "
                                             "(jm.Contact) needs the step's P2G fields: g2p(..., fields=...)")
            fields = GridFields(transfer, {})
        v_new, dv = lumped_velocity(sim, fields, momentum, constraint, dt, state.time + dt)
        v_strain = strain_velocity(sim, v_new, transfer, constraint, dv)
        dF = deformation_increment(strain_rate(sim, transfer, v_strain), strain_dt(sim, dt), sim.kinematics)
    if dF is not None:
        F = matmul(dF, F)  # F <- dF F
    new = eqx.tree_at(
        lambda s: (s.x, s.v, s.F, s.time, s.step, s.dissipated, s.scheme_state),
        state,
        (upd.position, upd.velocity, F, state.time + dt, state.step + 1, state.dissipated + upd.dissipated,
         scheme_state),
        is_leaf=lambda x: x is None,
    )
    for term in sim.terms:
        new = term.particle_action(sim, state, new, transfer, grid, dt)
    material_state = state.material_state
    if dF is not None:  # the material's state with the step's (second-half) increment
        material_state = material_update(sim, F, dF, material_state, state, new, strain_dt(sim, dt))
    elif sim.stretch(state) is not None:  # USF: the step's stretch change alone, at its end
        eye = jnp.eye(F.shape[-1], dtype=F.dtype)
        material_state = material_update(sim, F, jnp.broadcast_to(eye, F.shape), material_state, state, new, dt)
    new = eqx.tree_at(lambda s: (s.F, s.material_state), new, (sim.material.keep_deformation(F), material_state),
                      is_leaf=lambda x: x is None)
    return new
