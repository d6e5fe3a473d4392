"""Bad data never wrecks the table (issue targets): one wild reading moves its error by under 30 %, five do not
crash, 2 % swapped ids stay within 1.5x and 20 % false detections with the effect within 2x of the clean error.

CI runs one 4-minute seed; CASM_FULL=1 runs three 6-minute seeds (benchmarks/robustness.py prints the table).
"""
import pytest

from casm_graph.pipeline.bad_data import trial

from .conftest import FULL

SEEDS, MINUTES = ((0, 1, 2), 6.0) if FULL else ((0,), 4.0)
LIMIT = {"wild1": 1.3, "wild5": 1.3, "swap2": 1.5, "false20+fx": 2.0}


@pytest.mark.science
@pytest.mark.parametrize("seed", SEEDS)
def test_bad_data_leaves_the_table_near_its_clean_error(seed):
    clean = trial("clean", seed, MINUTES)
    assert clean["status"] == "ok"
    for case, limit in LIMIT.items():
        r = trial(case, seed, MINUTES)
        assert r["status"] == "ok", (case, r["status"])
        for k in ("vx", "vy"):
            assert r[k] <= limit * clean[k], (case, k, r[k], clean[k])
