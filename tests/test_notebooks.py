"""Every analysis notebook runs top to bottom (at reduced size) on a real kernel."""
import os
from pathlib import Path

import nbformat
import pytest
from nbclient import NotebookClient

NOTEBOOKS = sorted((Path(__file__).parent.parent / "notebooks").glob("*.ipynb"))
REDUCED = {"CASM_NB_MINUTES": "3", "CASM_NB_EKFS_MAX": "40", "CASM_NB_UNC_STEPS": "200", "CASM_NB_TRIALS": "1",
           "CASM_NB_CANDIDATES": "2"}


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.name for p in NOTEBOOKS])
def test_notebook_runs(path, monkeypatch, tmp_path):
    if os.environ.get("CASM_FULL") != "1":
        for k, v in REDUCED.items():
            monkeypatch.setenv(k, v)
    monkeypatch.setenv("MPLBACKEND", "Agg")
    nb = nbformat.read(path, as_version=4)
    NotebookClient(nb, timeout=1200, kernel_name="python3", resources={"metadata": {"path": str(tmp_path)}}).execute()
    outputs = [o for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])]
    assert not [o for o in outputs if o.get("output_type") == "error"]
