"""A parameter that does not act in a model is refused by set_params and ensembles (``Parameter.acts``), traced
values too: its gradient would be exactly 0 and an ensemble's members equal, with no word said.  Found by an
audit of every registered parameter's gradient against central differences (2026-11-29), which found every
gradient that acts correct; the constructors already refused these combinations."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import pytest

import jaxmpm as jm


def _disks(contact):
    return jm.scene("disks", spacing=0.1, contact=contact, t_end=0.01, frames=1)


@pytest.mark.parametrize("contact", ["stick", "frictionless"])
def test_contact_friction_acts_only_under_coulomb(contact):
    setup = _disks(contact)
    words = f"set_params: friction acts only under the contact law 'coulomb', and this model's is '{contact}'"
    with pytest.raises(jm.InputError, match=words):
        jm.set_params(setup.sim, friction=0.3)
    with pytest.raises(jm.InputError, match=words):  # a traced value: a calibration's gradient would be 0
        jax.grad(lambda mu: jnp.sum(jm.set_params(setup.sim, friction=mu).run(setup.state, setup.dt, 2, 1)[0].x))(0.3)
    with pytest.raises(jm.InputError, match="ensemble member 0: friction acts only under the contact law"):
        jm.ensemble(setup.sim, setup.state, setup.dt, 2, 1, params={"friction": jnp.asarray([0.0, 0.3])})
    assert float(jm.get_params(setup.sim, "friction")["friction"]) == 0.0  # reading it stays possible


def test_friction_on_a_model_without_contact_is_refused():
    """set_params adds a term the model lacks at its neutral default: a jm.Contact, frictionless, where the
    friction would not act (it had been accepted, and an ensemble over it raised KeyError 'material')."""
    bar = jm.scene("bar", cells=4, t_end=0.5, frames=1)
    # "this model's is 'frictionless'"; or, where a part registered by other tests of the process (a material
    # with a friction, tests/test_open_core.py) owns the bare name first, "parameter 'friction' does not exist"
    words = "friction acts only under the contact law 'coulomb', and this model's is 'frictionless'|'friction' does not"
    with pytest.raises(jm.InputError, match=words):
        jm.set_params(bar.sim, friction=0.3)
    with pytest.raises(jm.InputError, match=words):
        jm.ensemble(bar.sim, bar.state, bar.dt, 2, 1, params={"friction": jnp.asarray([0.1, 0.5])})


def test_coulomb_friction_still_acts():
    setup = _disks("coulomb")
    assert float(jm.get_params(jm.set_params(setup.sim, friction=0.3), "friction")["friction"]) == 0.3


def test_collider_friction_acts_only_on_a_friction_collider():
    wall = jm.HalfSpace((0.0, 0.1), (0.0, 1.0))
    grid = jm.Grid((0.0, 0.0), (1.0, 1.0), (8, 8))

    def model(condition):
        return jm.Simulation(grid, "linear", jm.NeoHookean(E=1e3), "flip",
                             terms=[jm.Collider(wall, condition=condition)])

    for condition in ("slip", "sticky"):
        with pytest.raises(jm.InputError, match=f"acts only on a collider of condition 'friction', and this one's "
                                                f"is '{condition}'"):
            jm.set_params(model(condition), friction=0.3)
    jm.set_params(model("friction"), friction=0.3)


def test_tait_exponent_acts_only_under_tait():
    fluid = jm.NewtonianFluid(K=1e4, eta=1e-3, density=1000.0)  # eos="linear"
    sim = jm.Simulation(jm.Grid((0.0, 0.0), (1.0, 1.0), (8, 8)), "linear", fluid, "flip")
    with pytest.raises(jm.InputError, match="gamma is Tait's exponent, and this fluid's equation of state is "
                                            "'linear'"):
        jm.set_params(sim, gamma=5.0)
    tait = jm.Simulation(sim.grid, "linear", jm.NewtonianFluid(K=1e4, density=1000.0, eos="tait"), "flip")
    assert float(jm.get_params(jm.set_params(tait, gamma=5.0), "gamma")["gamma"]) == 5.0


def test_interface_conductance_acts_only_across_a_conductance():
    setup = jm.scene("heat_step")  # jm.Heat(interface="perfect")
    with pytest.raises(jm.InputError, match="interface_conductance acts only across an interface given as a "
                                            "conductance, and this term's is 'perfect'"):
        jm.set_params(setup.sim, interface_conductance=1.0)


def test_an_ensemble_over_the_density_is_refused():
    """The density acts through sim.init only (the particles' masses): an ensemble over it with one shared
    state ran members alike (kinetic energies equal to every digit) and gave a zero gradient."""
    bar = jm.scene("bar", cells=4, t_end=0.5, frames=1)
    for name in ("density", "material.density"):
        with pytest.raises(jm.InputError, match=rf"ensemble: params\['{name}'\] acts through sim.init only \(the "
                                                r"particles' masses\).*with states="):
            jm.ensemble(bar.sim, bar.state, bar.dt, 2, 1, params={name: [1.0, 2.0]}, progress=False)
    # set_params then sim.init: the masses follow it (the way to vary it, member by member through states=)
    particles = jm.fill(bar.sim.grid, jm.Box((0.0,), (25.0,)), ppc=2)
    light, heavy = (jm.set_params(bar.sim, density=rho).init(particles).mass for rho in (1.0, 2.0))
    assert float(jnp.max(jnp.abs(heavy - 2.0 * light))) == 0.0


def test_an_ensemble_over_the_density_with_states_of_its_own_runs():
    """With states= (each member's state made by sim.init at its density) the density is the members'
    own, as the refusal's message advises; their masses differ, and so do their runs."""
    bar = jm.scene("bar", cells=4, t_end=0.5, frames=1)
    particles = jm.fill(bar.sim.grid, jm.Box((0.0,), (25.0,)), ppc=2)
    states = [jm.set_params(bar.sim, density=rho).init(particles) for rho in (1.0, 2.0)]
    batch = jax.tree_util.tree_map(lambda *a: jnp.stack(a), *states)
    final, _, failed = jm.ensemble(bar.sim, states[0], bar.dt, 2, 1, params={"density": jnp.asarray([1.0, 2.0])},
                                   states=batch, progress=False)
    assert [int(f) for f in failed] == [-1, -1]
    assert float(jnp.max(jnp.abs(final.mass[1] - 2.0 * final.mass[0]))) == 0.0
