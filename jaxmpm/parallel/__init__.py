"""One simulation on many devices: slab domain decomposition on JAX's own runtime (issue 33).

The decomposition and its communication (:class:`Slabs`: windows, the one halo exchange per P2G),
particle migration in fixed-capacity buffers (:func:`migrate`) and the sharded run that composes
them (:class:`ShardedSimulation`: frames, HDF5 output written by process 0, ``jaxmpm run SCENE
--devices N``, slabs that move with the particles: ``rebalance_every``), checked on forced CPU
devices against one device (tests/test_parallel_slabs.py, docs/scaling.md).
"""

from .migration import migrate
from .sharded import ShardedSimulation, local_devices
from .slabs import Slabs, halo_for

__all__ = ["ShardedSimulation", "Slabs", "halo_for", "local_devices", "migrate"]
