"""Run by tests/test_sharded_donation.py in a process of its own with 2 forced CPU devices: the sharded runner's
runs with and without buffer donation (the disks scene, 416 particles, runs of 2 and 4 steps, fixed slabs and
``rebalance_every``), the caller's state after them, and XLA's memory account of the in-place and the public
rollout.  Prints one JSON line."""

import json

DEVICES = 2


def measure() -> dict:
    """The runs with and without donation, the caller's state after them, and XLA's memory account of the
    in-place and the public rollout (lowered and compiled, then called once each)."""
    import jax

    jax.config.update("jax_enable_x64", True)
    import equinox as eqx
    import jax.numpy as jnp
    import numpy as np

    import jaxmpm as jm
    from jaxmpm.parallel import ShardedSimulation, sharded

    assert len(jax.devices()) == DEVICES, jax.devices()
    setup = jm.scene("disks", speed=1.0)
    sim, state, dt = setup.sim, setup.state, jnp.asarray(setup.dt)  # dt: the caller's own array
    shared = eqx.tree_at(lambda s: s.v, state, state.x)  # one array in two leaves
    before = [np.array(a) for a in jax.tree_util.tree_leaves(state)]
    out = {}

    def values(tree):
        return [np.asarray(a) for a in jax.tree_util.tree_leaves(tree)]

    def deleted(tree):
        return any(a.is_deleted() for a in jax.tree_util.tree_leaves(tree) if isinstance(a, jax.Array))

    runs, kept = {}, {}
    for name, options in (("fixed", {}), ("rebalance", {"rebalance_every": 2})):
        for donate in (False, True):
            sharded.DONATE = donate
            runner = ShardedSimulation(sim, **options)
            if name == "fixed":
                final = runner.run(state, dt, 2)
                again = runner.run(shared, dt, 2)
            else:  # two rollouts of 2 steps, the slabs moved between them
                final, again = runner.run(state, dt, 4), None
            rebalances = runner.stats["rebalances"]
            framed = runner.run(state, dt, 4, 2)  # the initial frame and one every 2 steps: 2 rollouts
            runs[name, donate] = values((final, again, framed))
            kept[name, donate] = runner
        out[name] = {"same": all(np.array_equal(a, b) for a, b in zip(runs[name, False], runs[name, True])),
                     "leaves": len(runs[name, True]), "rebalances": rebalances}
    out["state_deleted"], out["dt_deleted"] = deleted((state, shared)), dt.is_deleted()
    out["state_kept"] = all(np.array_equal(a, b) for a, b in zip(before, values(state)))

    # the programs of 2 steps with fixed slabs: the in-place one that run calls, and the public one
    runner = kept["fixed", True]
    buffers, valid, ids = runner.distribute(state)
    args = runner._in_place_args(sim, buffers, valid, ids, dt)
    donated = args[1:]
    in_place = runner._in_place(2).lower(*args).compile()
    public = runner.rollout(2).lower(sim, buffers, valid, ids, dt).compile()
    arrays = jax.tree_util.tree_leaves(donated)
    out["alias_bytes"] = in_place.compiled.memory_analysis().alias_size_in_bytes  # equinox's Compiled wraps jax's
    out["public_alias_bytes"] = public.compiled.memory_analysis().alias_size_in_bytes
    out["donated_bytes_per_device"] = sum(a.addressable_shards[0].data.nbytes for a in arrays)
    out["donated_bytes"] = sum(a.nbytes for a in arrays)
    out["devices"] = runner.devices

    def memory(tree):
        return [shard.data.unsafe_buffer_pointer() for a in jax.tree_util.tree_leaves(tree)
                for shard in a.addressable_shards]

    # called: the public program keeps the buffers; the in-place one writes its buffers where distribute's were
    result = public(sim, buffers, valid, ids, dt)
    out["public_kept"] = not deleted((buffers, valid, ids))
    where = memory(donated)
    reached = in_place(*args)
    out["in_place_deleted"] = all(a.is_deleted() for a in arrays)
    out["in_place_same"] = all(np.array_equal(a, b) for a, b in zip(values(reached[:3]), values(result[:3])))
    rows = runner.devices * runner.capacity
    particles = eqx.filter(reached[0], lambda a: getattr(a, "ndim", 0) >= 1 and a.shape[0] == rows)
    out["in_place_memory"] = memory((particles, reached[1], reached[2])) == where

    # buffers that hold one array in two leaves (v is x itself): donated once, the second leaf a copy
    buffers, valid, ids = runner.distribute(state)
    twice = eqx.tree_at(lambda b: b.v, buffers, buffers.x)
    expected = values(public(sim, twice, valid, ids, dt)[:3])
    reached = runner._in_place(2)(*runner._in_place_args(sim, twice, valid, ids, dt))
    out["shared_same"] = all(np.array_equal(a, b) for a, b in zip(values(reached[:3]), expected))
    out["shared_deleted"] = deleted((twice, valid, ids))
    return out



print(json.dumps(measure()))
