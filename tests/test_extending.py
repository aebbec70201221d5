"""docs/extending.md: each worked example -- a scheme, a physics term, a material, a shape
function, a transfer kernel, each one file plus one registration -- runs on its own in a fresh
interpreter, and its own assertions hold (the scheme equals FMPM(1) at theta = 0; the drag term
relaxes particles to the ambient velocity at its rate; the Saint Venant-Kirchhoff law conserves
energy and matches Hooke's law at small strain; the hardening law ends a strain path on the
closed-form hardening line and keeps a pulled bar inside its yield surface; the tent shape gives
jm.Linear's numbers in 1D and 2D; the column-by-column kernel gives the default kernel's numbers)."""

from pathlib import Path

import pytest
from test_readme import python_blocks, run_alone

DOC = Path(__file__).resolve().parents[1] / "docs" / "extending.md"
BLOCKS = python_blocks(DOC.read_text())
EXPECTED = ["A scheme", "A physics term", "A material", "A material with state", "A shape function",
            "A transfer kernel"]


def test_every_extension_axis_has_an_example():
    assert [heading for heading, _ in BLOCKS] == EXPECTED


@pytest.mark.slow
@pytest.mark.parametrize("heading, code", BLOCKS, ids=[h for h, _ in BLOCKS])
def test_example_runs_alone(tmp_path, heading, code):
    result = run_alone(code, tmp_path)
    assert result.returncode == 0, f"docs/extending.md example {heading!r} fails alone:\n{result.stderr[-3000:]}"
