"""jm.reuse_host_memory (jaxmpm/core/host_memory.py): with it, glibc keeps the memory an XLA:CPU program frees, so a
program whose temporaries exceed 32 MiB takes no fresh pages from the kernel at its later calls (once the heap has
settled, after a call or two); without it every call page-faults its temporaries in again.  Counted with the
process's minor page faults (getrusage), not timed: speed lives in benchmarks/gradient_cost.py
(--reuse-host-memory)."""

import os
import platform
import subprocess
import sys

import pytest

import jaxmpm as jm
from jaxmpm.core import host_memory

GLIBC = platform.system() == "Linux" and platform.libc_ver()[0] == "glibc"

# Two programs of 5M and 20M float64 (the cumulative sums, read reversed: temporaries of about 80 and 330 MiB,
# 21 163 and about 85 000 pages), each called twelve times after a first call; the median call counts.  Reusing,
# the first call or two may still take fresh pages while the heap settles ([21163, 0, 0, ...]; now and then three in
# a row, which failed a minimum of three calls).  After reuse_host_memory(False) the larger one is measured: the heap
# holds a few of the smaller one's blocks at most, none of which can serve it, so glibc's defaults map it on its own
# and unmap it when freed, at every call (a program no larger found freed blocks still resident at times: the last
# call's free can come after malloc_trim).
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
    for _ in range(12):
        before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
        call()
        counts.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
    return sorted(counts)[len(counts) // 2]  # the median call: reusing, the heap settles after a call or two


first = faults(program(5 * 2**20))
if sys.argv[1:] == ["after"]:  # the defaults set again, the larger program
    print(first, jaxmpm.reuse_host_memory(False), faults(program(20 * 2**20)))
else:
    print(first, None, None)
"""


def minor_faults_per_call(reuse: str, after: bool = False) -> tuple:
    """(minor page faults of the median call of the smaller program, and with ``after``: whether
    reuse_host_memory(False) took, the faults of the median call of the larger one after it), in a fresh process
    with JAXMPM_REUSE_HOST_MEMORY=``reuse``."""
    env = {**os.environ, host_memory.ENVIRONMENT: reuse, "JAX_PLATFORMS": "cpu", "JAXMPM_CACHE": "0"}
    out = subprocess.run([sys.executable, "-c", PROBE, *(["after"] if after else [])], env=env, capture_output=True,
                         text=True, check=True)
    first, restored, later = out.stdout.split()[-3:]
    return (int(first), restored == "True", int(later)) if after else (int(first),)


@pytest.mark.skipif(not GLIBC, reason="the allocator's settings are glibc's (Linux)")
def test_freed_memory_is_reused_at_the_next_call_until_switched_off():
    pages = 40 * 2**20 // 4096  # a 40 MiB array's 4 KiB pages: the smaller temporary holds two such, the larger eight
    assert minor_faults_per_call("0")[0] > pages  # every call maps its temporary afresh
    reused, restored, after = minor_faults_per_call("1", after=True)
    assert reused < pages // 50  # the heap's pages again
    assert restored and after > 4 * pages  # glibc's defaults again: mapped afresh


def test_bad_input():
    with pytest.raises(jm.InputError, match="enabled = 'yes' must be True or False"):
        jm.reuse_host_memory("yes")
    assert host_memory._glibc() is not None or not host_memory.reuse_host_memory()  # elsewhere: nothing changes
