"""Every ```python block of README.md (and of the docs pages the README's long sections moved to,
``DOC_PAGES``) runs on its own (a fresh interpreter, nothing from the other
blocks) at a reduced size: the explicit substitutions below shrink step counts and end times, and
each must match the README exactly as often as stated, so the test fails when the README drifts."""

import os
import re
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
#: the docs pages whose python blocks were README blocks (the other docs pages' examples run in their own tests:
#: docs/extending.md in tests/test_extending.py)
DOC_PAGES = [ROOT / "docs" / "contact.md", ROOT / "docs" / "transport.md", ROOT / "docs" / "colliders.md",
             ROOT / "docs" / "performance.md"]
FENCE = re.compile(r"^```\s*(\w*)\s*$")


@dataclass
class Block:
    substitutions: list = field(default_factory=list)  # (README text, reduced text, times it occurs)


SHORT_BAR = ('jm.scene("bar", scheme=jm.FMPM(order=2))',
             'jm.scene("bar", scheme=jm.FMPM(order=2), t_end=0.5, frames=4)')

# README section heading -> its python block
BLOCKS = {
    "Quickstart (Python)": Block([
        ("steps=2000, save_every=20", "steps=20, save_every=10", 1),
        SHORT_BAR + (1,),
    ]),
    "Bodies from meshes and point clouds": Block(),  # small as it stands: fills, no run
    "Differentiation, calibration, ensembles": Block(
        [SHORT_BAR + (1,),
         ("setup.dt, 400, 20", "setup.dt, 20, 10", 2),  # the calibrated rollout and the ensemble
         ("steps=200", "steps=3", 1),
         ("linspace(0, 1, 16)", "linspace(0, 1, 2)", 1)],
    ),
    "Contact (multimaterial mode)": Block([('t_end=0.5, frames=10)', 't_end=0.01, frames=2)', 1),
                                           ("final, hist = sim.run(state, 1e-3, 100, 10)",
                                            "final, hist = sim.run(state, 1e-3, 10, 5)", 1)]),
    "Transport (heat conduction and diffusion)": Block([("sim.run(state, dt, 800, 80)", "sim.run(state, dt, 8, 4)",
                                                         1)]),
    "Materials, fluids, boundary conditions": Block([("steps=1200, save_every=60", "steps=20, save_every=10", 1)]),
    "Plasticity, viscous fluids, rigid colliders": Block([("steps=4000, save_every=400", "steps=20, save_every=10",
                                                           1)]),
    "Your own scene": Block([("E=E, dtype=dtype)\n",  # the file's scene, built and run
                              "E=E, dtype=dtype)\n\n\nscene(cells=8, t_end=0.5, frames=2).run()\n", 1)]),
    "Outputs: HDF5, XDMF, pictures": Block([("t_end=2.0, frames=4", "t_end=0.5, frames=2", 1)]),
    "Interrupt and resume": Block([('jm.scene("bar", t_end=4.0, frames=20)', 'jm.scene("bar", t_end=0.5, frames=2)',
                                    1)]),
    "Transfer kernels: XLA or fused Pallas": Block(),  # one model, no run
    "Particles shared among the CPU's devices": Block(),  # one model, no run (2 CPU devices in its own process)
    "One simulation on several devices": Block([("setup.dt, 200)", "setup.dt, 20)", 1)]),
    "Colliders, tractions, transport and symmetry planes": Block([("setup.dt, 200)", "setup.dt, 20)", 1)]),
    "Load balance: slabs that move with the particles": Block([('jm.scene("column_collapse")',
                                                               'jm.scene("column_collapse", cells=2)', 1),
                                                              ("rebalance_every=200", "rebalance_every=10", 1),
                                                              ("setup.dt, 800)", "setup.dt, 20)", 1)]),
    "Rigid colliders": Block(),  # docs/colliders.md: one model, no run
    "Extending jaxmpm": Block(
        [('scheme="newpic:0.3")', 'scheme="newpic:0.3", t_end=0.5, frames=2); setup.run()', 1)],  # run the new scheme
    ),
}


def python_blocks(text: str) -> list[tuple[str, str]]:
    """(the heading above it, code) for every ```python fenced block."""
    blocks, heading, language, lines = [], None, None, []
    for line in text.splitlines():
        fence = FENCE.match(line)
        if language is None:
            if fence:
                language, lines = fence.group(1), []
            elif line.startswith("#"):
                heading = line.lstrip("#").strip()
        elif fence and not fence.group(1):
            if language in ("python", "py"):
                blocks.append((heading, "\n".join(lines) + "\n"))
            language = None
        else:
            lines.append(line)
    return blocks


def reduced(code: str, block: Block, heading: str) -> str:
    for old, new, times in block.substitutions:
        assert code.count(old) == times, (f"README block under {heading!r}: {old!r} occurs {code.count(old)} times, "
                                          f"expected {times}; update the substitutions in {Path(__file__).name}")
        code = code.replace(old, new)
    return code


def run_alone(code: str, cwd: Path) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT)] + os.environ.get("PYTHONPATH", "").split(os.pathsep)),
               MPLBACKEND="Agg")
    return subprocess.run([sys.executable, "-c", code], cwd=cwd, env=env, capture_output=True, text=True, timeout=300)


README_BLOCKS = [block for page in [README, *DOC_PAGES] for block in python_blocks(page.read_text())]


def test_every_block_is_known():
    headings = [heading for heading, _ in README_BLOCKS]
    assert len(headings) == len(set(headings)), "two python blocks under one heading: key BLOCKS differently"
    assert set(headings) == set(BLOCKS), (f"README python blocks are under {headings}; BLOCKS in "
                                          f"{Path(__file__).name} lists {list(BLOCKS)}")


@pytest.mark.slow
@pytest.mark.parametrize("heading, code", README_BLOCKS, ids=[h for h, _ in README_BLOCKS])
def test_block_runs_alone(tmp_path, heading, code):
    block = BLOCKS[heading]
    code = reduced(code, block, heading)
    result = run_alone(code, tmp_path)
    assert result.returncode == 0, f"README block under {heading!r} fails alone:\n{result.stderr[-3000:]}"
