"""graph, graph-em and ekfs-em on one shared 8-minute log: they agree, and each is near the paper's errors.

Runs at full size in CI (about three minutes): an 8-minute log is already the reduced protocol.
"""
import numpy as np
import pytest

from casm_graph.hidden_effect import PAPER_SIM_RMS     # vx m/s, vy m/s, w rad/s (PAPERS.md section 1)
from casm_graph.methods import METHODS
from casm_graph.model import paper_start
from casm_graph.simulate import SimConfig, simulate

from .conftest import largest_early_drop

pytestmark = pytest.mark.xdist_group("test_crosscheck")    # its module fixtures are costly: one worker


@pytest.fixture(scope="module")
def shared():
    log, truth = simulate(SimConfig(minutes=8, seed=1))
    fits = {name: METHODS[name](log, paper_start(log), seed=1, **({"truth": truth} if name != "graph" else {}))
            for name in ("graph", "graph-em", "ekfs-em")}
    tv = np.array([truth["action_model"]["velocities"][str(a)] for a in log.action_ids])
    return log, truth, tv, fits


@pytest.mark.science
def test_each_method_within_one_and_a_half_times_the_paper(shared):
    _, _, tv, fits = shared
    for name, f in fits.items():
        rms = np.sqrt(np.mean((f.model.velocities - tv) ** 2, axis=0))
        assert np.all(rms < 1.5 * PAPER_SIM_RMS), f"{name}: {rms}"


def _table_rms(a, b):
    return np.sqrt(np.mean((a.model.velocities - b.model.velocities) ** 2, axis=0))


@pytest.mark.science
def test_graph_and_graph_em_agree(shared):
    fits = shared[3]
    d = _table_rms(fits["graph"], fits["graph-em"])
    assert np.all(d[:2] < 0.020), f"graph vs graph-em: {d}"


@pytest.mark.science
@pytest.mark.xfail(strict=False, reason="open in issue 3: on this seed EKFS-EM's vy differs from graph-em's "
                   "by 23 mm/s RMS (the issue asks < 20); the test keeps reporting the gap")
def test_ekfs_em_agrees_with_the_graph_methods(shared):
    fits = shared[3]
    for other in ("graph", "graph-em"):
        d = _table_rms(fits["ekfs-em"], fits[other])
        assert np.all(d[:2] < 0.020), f"ekfs-em vs {other}: {d}"


@pytest.mark.science
def test_ekfs_likelihood_rises_until_approximation_noise(shared):
    drop, gain = largest_early_drop(shared[3]["ekfs-em"].notes["history"]["log_likelihood"])
    assert gain > 0 and drop < 0.05 * gain, f"largest early drop {drop} of gain {gain}"
    assert shared[3]["ekfs-em"].converged                     # 50 iterations without a new best
