"""Shared fixtures: simulated logs written to real CSV bundles."""
import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")    # two test workers (and diagnose's pools) share two cores: no BLAS threads

import pytest  # noqa: E402

from casm_graph.simulate import SimConfig, simulate, write  # noqa: E402

FULL = os.environ.get("CASM_FULL") == "1"


@pytest.fixture(scope="session")
def short_bundle(tmp_path_factory):
    """A 2-minute simulated bundle on disk, with its truth."""
    d = tmp_path_factory.mktemp("aibo2")
    log, truth = simulate(SimConfig(minutes=2, seed=11))
    write(log, truth, d)
    return d, log, truth
