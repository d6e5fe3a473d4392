"""Every analysis notebook runs top to bottom on a real kernel.

CI runs the quickstart, the notebook the README points to, at reduced size; the other five repeat, as
demonstrations, what tests here check with assertions (graph_vs_ekfs_em: test_crosscheck;
find_the_missing_effect: test_detection and test_api's own effect; seed_baselines: test_scasm and
test_mcl; uncertainty_report: test_uncertainty; real_robots_mrclam: test_mrclam) and run with
``CASM_FULL=1``, at full size, as they were committed.
"""
from pathlib import Path

import nbformat
import pytest
from nbclient import NotebookClient

from .conftest import FULL

NOTEBOOKS = sorted((Path(__file__).parent.parent / "notebooks").glob("*.ipynb"))
IN_CI = {"00_quickstart.ipynb"}
REDUCED = {"CASM_NB_MINUTES": "1.5", "CASM_NB_UNC_STEPS": "100", "CASM_NB_TRIALS": "1",
           "CASM_NB_CANDIDATES": "1"}


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.name for p in NOTEBOOKS])
def test_notebook_runs(path, monkeypatch, tmp_path):
    if not FULL and path.name not in IN_CI:
        pytest.skip("full size only (CASM_FULL=1): its checks are the tests named in this module's docstring")
    if not FULL:
        for k, v in REDUCED.items():
            monkeypatch.setenv(k, v)
    monkeypatch.setenv("MPLBACKEND", "Agg")
    nb = nbformat.read(path, as_version=4)
    NotebookClient(nb, timeout=1800, kernel_name="python3", resources={"metadata": {"path": str(tmp_path)}}).execute()
    outputs = [o for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])]
    assert not [o for o in outputs if o.get("output_type") == "error"]
