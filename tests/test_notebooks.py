"""The notebooks run top to bottom at reduced size (JAXMPM_NOTEBOOK_QUICK=1) without an error, and are
committed without outputs.  Each notebook also asserts its own physics (exact free fall, FLIP energy,
recovered parameters, batch = single runs), so a cell that raises is a real failure."""

import os
import pathlib

import ipykernel  # noqa: F401  (the "python3" kernel that executes the notebooks)
import nbformat
import pytest
from nbclient import NotebookClient

NOTEBOOKS = sorted((pathlib.Path(__file__).parent.parent / "notebooks").glob("*.ipynb"))
QUICK_LINE = 'QUICK = os.environ.get("JAXMPM_NOTEBOOK_QUICK") == "1"'


def code_cells(nb):
    return [cell for cell in nb.cells if cell.cell_type == "code"]


def test_the_six_notebooks_exist():
    names = [p.stem for p in NOTEBOOKS]
    assert names == ["01_quickstart", "02_schemes_compared", "03_calibrate_damping", "04_ensembles", "05_contact",
                     "06_friction_angle_calibration"]


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.stem)
def test_committed_without_outputs(path):
    nb = nbformat.read(path, as_version=4)
    nbformat.validate(nb)
    for cell in code_cells(nb):
        assert cell.outputs == [] and cell.execution_count is None, path.name


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.stem)
def test_float64_first_and_a_quick_switch(path):
    """float64 is enabled in the first code cell (before any array exists); a parameter cell near the top
    reads the QUICK switch the test below sets."""
    cells = code_cells(nbformat.read(path, as_version=4))
    assert 'jax.config.update("jax_enable_x64", True)' in cells[0].source, path.name
    assert any(QUICK_LINE in cell.source for cell in cells[:3]), path.name


@pytest.mark.slow
@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.stem)
def test_notebook_executes(path, tmp_path, monkeypatch):
    monkeypatch.setenv("JAXMPM_NOTEBOOK_QUICK", "1")
    monkeypatch.setenv("MPLBACKEND", "Agg")
    # jm.compilation_cache() in the first cell keeps the programs in the suite's folder (tests/conftest.py,
    # shared with the other tests and kept for a run again); never in the user's own cache folder
    if not os.environ.get("JAXMPM_CACHE_DIR"):
        monkeypatch.setenv("JAXMPM_CACHE_DIR", str(tmp_path / "xla"))
    nb = nbformat.read(path, as_version=4)
    client = NotebookClient(nb, timeout=300, kernel_name="python3", resources={"metadata": {"path": str(tmp_path)}})
    client.execute()  # raises CellExecutionError on the first failing cell
    errors = [o for cell in code_cells(nb) for o in cell.outputs if o.output_type == "error"]
    assert not errors
    assert all(cell.execution_count is not None for cell in code_cells(nb)), "a code cell did not run"
