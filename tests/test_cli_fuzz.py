"""Fuzzing the command line (issue 11, item 8): random `jaxmpm run` command lines drawn from valid
and invalid values.  Every outcome is a built scene with finite numbers or exit status 2 with one
line on stderr -- never another exception, a hang or a NaN.  The run itself is left out (each
would compile); `run_setup` is replaced by a check of what would run, and the memory limit is set
to 2 GiB so that oversized scenes must be refused before they are allocated.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import jaxmpm as jm
from jaxmpm import cli

NUMBERS = ["0", "-1", "1", "2", "3", "8", "0.5", "1e-12", "1e-3", "0.05", "2.5", "1e9", "1e300", "inf", "-inf",
           "nan", "abc", "", "100000000"]
SCHEMES = ["flip", "pic", "blend:0.3", "xpic:2", "fmpm:2", "apic", "tpic", "pic:3", "flip:0.5", "", "fmpm:1.5",
           "xpic:0", "xpic:-1", "blend:2", "blend:nan", "FLIP", "newton", "xpic:", ":", "fmpm:2:3"]
OPTIONS = {
    "--cells": NUMBERS, "--spacing": NUMBERS, "--ppc": NUMBERS, "--cfl": NUMBERS, "--dt": NUMBERS,
    "--t-end": NUMBERS, "--frames": NUMBERS, "--beta": NUMBERS, "--alpha-g": NUMBERS, "--alpha-p": NUMBERS,
    "--max-steps": NUMBERS, "--scheme": SCHEMES, "--shape": ["linear", "ugimp", "quadratic", "cubic", "hat"],
    "--update": ["USL", "USF", "MUSL", "usl"], "--dtype": ["f32", "f64", "f16"],
    "--contact": ["none", "stick", "frictionless", "coulomb", "glue", ""], "--friction": NUMBERS,
    "--E": NUMBERS, "--nu": NUMBERS + ["0.3", "-0.5", "0.49"], "--density": NUMBERS, "--theta": NUMBERS,
    "--gravity": NUMBERS + ["0,-9.8", "-1,0", "1,2,3", "1,2,3,4", ",", "1,nan", "0,1e300"],
}
SCENES = [*jm.SCENES, "nope"]


def checked_setup(setup, args, options, resume=False):
    """What `jaxmpm run` would run: finite, positive, consistent."""
    assert setup.steps >= 1 and setup.save_every >= 1 and setup.steps % setup.save_every == 0
    assert math.isfinite(setup.dt) and setup.dt > 0
    for leaf in (setup.state.x, setup.state.v, setup.state.mass):
        assert np.all(np.isfinite(np.asarray(leaf)))
    assert setup.state.x.shape[0] >= 1
    return 0


@pytest.fixture(scope="module")
def patched():
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(cli, "run_setup", checked_setup)
        mp.setenv("JAXMPM_MEMORY_BYTES", str(2 * 2**30))
        yield


@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(scene=st.sampled_from(SCENES),
       options=st.dictionaries(st.sampled_from(list(OPTIONS)), st.just(None), max_size=4).flatmap(
           lambda keys: st.fixed_dictionaries({k: st.sampled_from(OPTIONS[k]) for k in keys})))
def test_random_command_lines_succeed_or_fail_in_one_line(patched, tmp_path_factory, capsys, scene, options):
    out = tmp_path_factory.mktemp("fuzz") / "run.h5"
    argv = ["run", scene]
    for option, value in options.items():
        argv += [f"{option}={value}"]  # `=` keeps values such as -1 from reading as options
    argv += ["--out", str(out), "--no-progress"]
    try:
        status = cli.main(argv)
    except SystemExit as exc:
        status = exc.code
    err = capsys.readouterr().err
    if status == 0:
        return
    assert status == 2, (argv, status, err)
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("jaxmpm: error: "), (argv, err)
