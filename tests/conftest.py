"""Shared fixtures: simulated logs written to real CSV bundles."""
import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")    # two test workers (and diagnose's pools) share two cores: no BLAS threads

import numpy as np  # noqa: E402
import pytest  # noqa: E402

from casm_graph.simulate import SimConfig, simulate, write  # noqa: E402

FULL = os.environ.get("CASM_FULL") == "1"


def largest_early_drop(ll) -> tuple[float, float]:
    """(largest fall, total gain) of a likelihood trace up to where it first reaches 95 % of its gain.

    "Rises monotonically until approximation noise" (the EKFS-EM paper) means the first is small
    next to the second.
    """
    ll = np.asarray(ll, float)
    gain = ll.max() - ll[0]
    i95 = int(np.argmax(ll >= ll[0] + 0.95 * gain))
    return float((-np.diff(ll[:i95 + 1])).max(initial=0.0)), float(gain)


@pytest.fixture(scope="session")
def short_bundle(tmp_path_factory):
    """A 2-minute simulated bundle on disk, with its truth."""
    d = tmp_path_factory.mktemp("aibo2")
    log, truth = simulate(SimConfig(minutes=2, seed=11))
    write(log, truth, d)
    return d, log, truth
