"""Shared fixtures: simulated logs written to real CSV bundles."""
import os

import pytest

from casm_graph.simulate import SimConfig, simulate, write

FULL = os.environ.get("CASM_FULL") == "1"


@pytest.fixture(scope="session")
def short_bundle(tmp_path_factory):
    """A 2-minute simulated bundle on disk, with its truth."""
    d = tmp_path_factory.mktemp("aibo2")
    log, truth = simulate(SimConfig(minutes=2, seed=11))
    write(log, truth, d)
    return d, log, truth
