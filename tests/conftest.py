"""Shared fixtures: simulated logs written to real CSV bundles."""
import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")    # two test workers (and diagnose's pools) share two cores: no BLAS threads

import numpy as np  # noqa: E402
import pytest  # noqa: E402

from casm_graph.analysis.groundtruth import trajectory_rms  # noqa: E402
from casm_graph.models.effects import REGISTRY  # noqa: E402
from casm_graph.sim.aibo import SimConfig, simulate, write  # noqa: E402

FULL = os.environ.get("CASM_FULL") == "1"

# Modules whose module- or session-scoped fixtures are costly (minutes): all their tests on one xdist
# worker, so each fixture is built once. pytest-xdist's own xdist_group mark does nothing under pytest 9
# (it rewrites ``item._nodeid``, which pytest 9 no longer reads): both workers built the cross-check's
# 700-second fixture. Every other test is its own unit, as with --dist load.
ONE_WORKER = {f"tests/{m}.py" for m in ("test_crosscheck", "test_diagnose", "test_effects", "test_em_parts",
                                         "test_mrclam", "test_uncertainty", "test_uncertainty_continuous",
                                         "test_one_channel")}


def pytest_xdist_make_scheduler(config, log):
    from xdist.scheduler import LoadScopeScheduling

    class ModuleGroups(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            module = nodeid.split("::", 1)[0]
            return module if module in ONE_WORKER else nodeid

    return ModuleGroups(config, log)


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


def position_rms(cal, log) -> float:
    """Position RMS (m) of a calibration's trajectory against the log's truth."""
    return trajectory_rms(cal.trajectory, log.truth)


def slow_on_patch(entry: dict, log, patch: dict) -> tuple[np.ndarray, np.ndarray]:
    """A fitted surface_friction field's slow-down at every true pose, and whether the pose is on the world's
    rectangular ``patch`` (xmin, xmax, ymin, ymax)."""
    field = REGISTRY["surface_friction"](log)
    field.restore(entry)
    slow = field.slow(np.array([entry[p] for p in field.params]), log.truth[:, 1:3])
    x, y = log.truth[:, 1], log.truth[:, 2]
    return slow, (x >= patch["xmin"]) & (x <= patch["xmax"]) & (y >= patch["ymin"]) & (y <= patch["ymax"])


def patch_contrast(entry: dict, log, truth: dict) -> float:
    """Mean slow-down of a fitted surface_friction field on the world's patch minus off it, along the true path."""
    slow, on = slow_on_patch(entry, log, truth["geometry"]["patch"])
    return float(slow[on].mean() - slow[~on].mean())
