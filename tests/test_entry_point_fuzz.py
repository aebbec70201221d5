"""Bad values at every public entry point (tests/entry_point_fuzz.py, in a process of its own: it caps its address
space, and it changes process-wide settings such as the compilation cache's folder): each is an InputError naming
the argument, or a result; no other exception escapes.  An ad hoc run of this fuzz on 2026-11-29 found 37 kinds of
raw exception (a ZeroDivisionError for an empty ensemble, "The truth value of an empty array is ambiguous" for
array-valued choices, an MLIRError for rollout's frames = -1) and a negative frames_per_chunk that ran until the
machine's memory was spent."""

import os
import subprocess
import sys
from pathlib import Path

import pytest


@pytest.mark.slow
def test_no_raw_exception_escapes_an_entry_point(tmp_path):
    script = Path(__file__).with_name("entry_point_fuzz.py")
    env = {**os.environ, "JAX_PLATFORMS": "cpu", "JAXMPM_CACHE": "0", "MPLBACKEND": "Agg"}
    out = subprocess.run([sys.executable, str(script)], env=env, capture_output=True, text=True, timeout=600,
                         cwd=tmp_path)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip() == "", out.stdout
