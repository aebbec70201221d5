"""Write ``values.npz``: the numbers of ``configs.py`` as the library produced them before the
open-core refactor.  Run on commit 025c38f (run again only to store a deliberate change of numbers,
and say so in the commit):

    git worktree add /tmp/baseline 025c38f
    cp -r tests/reference /tmp/baseline/tests/ && cd /tmp/baseline
    PYTHONPATH=. python tests/reference/generate.py   # writes tests/reference/values.npz there

``--v2`` writes ``values_v2.npz`` instead, the core v2 configurations, run on commit 6c6f418 (the
last commit before the core v2 refactor, issue 27) the same way.
"""

from __future__ import annotations

import os
import sys

import jax

jax.config.update("jax_enable_x64", True)

import equinox as eqx  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import configs  # noqa: E402

import jaxmpm as jm  # noqa: E402


@eqx.filter_jit
def _step(sim, state, dt):
    return sim.step(state, dt)


def main_v2():
    """``values_v2.npz``: the core v2 configurations (configs.v2_step_cases, configs.RUNS_V2), stored
    on commit 6c6f418, the last commit before the core v2 refactor (issue 27)."""
    values = {}
    for name, kwargs in configs.v2_step_cases().items():
        sim, state, dt = configs.build_v2(**kwargs)
        for key, arr in configs.v2_step_values(sim, state, dt, _step).items():
            values[f"step/{name}/{key}"] = arr
    for name in configs.RUNS_V2:
        for key, arr in configs.run_values_v2(configs.run_setup_v2(name)).items():
            values[f"run/{name}/{key}"] = arr
    return "values_v2.npz", values


def main():
    print("jaxmpm from", jm.__file__)
    if "--v2" in sys.argv:
        name, values = main_v2()
        path = os.path.join(os.path.dirname(os.path.abspath(__file__)), name)
        np.savez_compressed(path, **values)
        print(f"wrote {len(values)} arrays to {path} ({os.path.getsize(path) / 1e6:.2f} MB)")
        return
    values = {}
    for name, kwargs in configs.one_step_cases().items():
        sim, state, dt = configs.build(**kwargs)
        for key, arr in configs.one_step_values(sim, state, dt, _step).items():
            values[f"step/{name}/{key}"] = arr
    for name in configs.RUNS:
        for key, arr in configs.run_values(configs.run_setup(name)).items():
            values[f"run/{name}/{key}"] = arr
    path = os.path.join(os.path.dirname(os.path.abspath(__file__)), "values.npz")
    np.savez_compressed(path, **values)
    print(f"wrote {len(values)} arrays to {path} ({os.path.getsize(path) / 1e6:.2f} MB)")


if __name__ == "__main__":
    main()
