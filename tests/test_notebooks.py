"""The tutorial notebooks under notebooks/ run, cell by cell, as a user runs them (nbclient, a fresh kernel of this
Python): each runs its shipped workflow into one folder and asserts what it shows (the ideal frame against the
captured one, white relighting against T's sum, the RMSE against reconstruction_error's)."""

from __future__ import annotations

from pathlib import Path

import nbformat
import pytest
from nbclient import NotebookClient

NOTEBOOKS = sorted((Path(__file__).resolve().parents[1] / "notebooks").glob("*.ipynb"))


def test_every_notebook_is_listed_and_ships_without_outputs():
    assert [n.name for n in NOTEBOOKS] == ["procam-tour.ipynb", "tomography-tour.ipynb"]
    for path in NOTEBOOKS:
        notebook = nbformat.read(path, as_version=4)
        nbformat.validate(notebook)
        assert not any(cell.get("outputs") for cell in notebook.cells if cell.cell_type == "code"), path.name


@pytest.mark.slow
@pytest.mark.parametrize("path", NOTEBOOKS, ids=[n.stem for n in NOTEBOOKS])
def test_the_notebook_runs(path, tmp_path, monkeypatch):
    """About 70–90 s each: most of it the workflow the notebook runs first."""
    monkeypatch.setenv("SELPATH_DEMO", str(tmp_path / "demo"))
    notebook = nbformat.read(path, as_version=4)
    NotebookClient(notebook, timeout=900, kernel_name="python3",  # the kernel inherits SELPATH_DEMO
                   resources={"metadata": {"path": str(tmp_path)}}).execute()
    images = sum("image/png" in output.get("data", {}) for cell in notebook.cells for output in cell.get("outputs", []))
    assert images >= 5, f"{path.name} drew {images} figures"
