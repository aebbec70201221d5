"""jm.reuse_host_memory (jaxmpm/core/host_memory.py): with it, glibc keeps the memory an XLA:CPU program frees, so a
program whose temporaries exceed 32 MiB takes no fresh pages from the kernel at its next call; without it every call
page-faults its temporaries in again.  Counted with the process's minor page faults (getrusage), not timed: speed
lives in benchmarks/gradient_cost.py (--reuse-host-memory)."""

import os
import platform
import subprocess
import sys

import pytest

import jaxmpm as jm
from jaxmpm.core import host_memory

GLIBC = platform.system() == "Linux" and platform.libc_ver()[0] == "glibc"

# programs with a 40 MiB and an 80 MiB temporary (the cumulative sums, read reversed), each called three times after
# a first call.  After reuse_host_memory(False) the larger one is measured: none of the heap's free blocks can hold
# it, so with glibc's defaults it is mapped on its own and unmapped when freed, at every call.  (The 40 MiB one again
# could find the block it freed still resident when that free came after malloc_trim: the heap's state decided.)
PROBE = """
import resource, sys
import jax, jax.numpy as jnp
jax.config.update("jax_enable_x64", True)
import jaxmpm  # applies JAXMPM_REUSE_HOST_MEMORY before JAX starts its threads
def program(n):
    x = jnp.linspace(0.0, 1.0, n)
    f = jax.jit(lambda x: jnp.sum(jnp.cumsum(x)[::-1] * x)).lower(x).compile()
    f(x).block_until_ready()
    return lambda: f(x).block_until_ready()


def faults(call):
    counts = []
    for _ in range(3):
        before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
        call()
        counts.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
    return min(counts)


first = faults(program(5 * 2**20))
print(first, jaxmpm.reuse_host_memory(False), faults(program(10 * 2**20)))
"""


def minor_faults_per_call(reuse: str) -> tuple:
    """(minor page faults of a call of the 40 MiB program, whether reuse_host_memory(False) took, the faults of a call
    of the 80 MiB program after it), in a fresh process with JAXMPM_REUSE_HOST_MEMORY=``reuse``."""
    env = {**os.environ, host_memory.ENVIRONMENT: reuse, "JAX_PLATFORMS": "cpu", "JAXMPM_CACHE": "0"}
    out = subprocess.run([sys.executable, "-c", PROBE], env=env, capture_output=True, text=True, check=True)
    first, restored, after = out.stdout.split()[-3:]
    return int(first), restored == "True", int(after)


@pytest.mark.skipif(not GLIBC, reason="the allocator's settings are glibc's (Linux)")
def test_freed_memory_is_reused_at_the_next_call_until_switched_off():
    pages = 40 * 2**20 // 4096  # the first temporary's 4 KiB pages (at least); the second has twice as many
    assert minor_faults_per_call("0")[0] > pages // 2  # every call maps its temporary afresh
    reused, restored, after = minor_faults_per_call("1")
    assert reused < pages // 50  # the heap's pages again
    assert restored and after > pages  # glibc's defaults again: mapped afresh


def test_bad_input():
    with pytest.raises(jm.InputError, match="enabled = 'yes' must be True or False"):
        jm.reuse_host_memory("yes")
    assert host_memory._glibc() is not None or not host_memory.reuse_host_memory()  # elsewhere: nothing changes
