"""One simulation on many devices: slab domain decomposition on JAX's own runtime (issue 33).

Built so far: the decomposition and its communication (:class:`Slabs`: windows, the one halo
exchange per P2G) and particle migration in fixed-capacity buffers (:func:`migrate`), checked on
forced CPU devices against one device (tests/test_parallel_slabs.py).  The sharded Simulation step
that composes them is not built yet (docs/scaling.md).
"""

from .migration import migrate
from .sharded import ShardedSimulation
from .slabs import Slabs, halo_for

__all__ = ["ShardedSimulation", "Slabs", "halo_for", "migrate"]
