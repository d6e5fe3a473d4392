"""An action table's candidates fitted on worker processes (the base beside them, every held-out fold a task) give
the diagnosis one process gives."""
import numpy as np

import casm_graph as cg
from casm_graph.sim.aibo import SimConfig, simulate, write


def test_two_workers_give_the_one_process_diagnosis(tmp_path):
    log, truth = simulate(SimConfig(minutes=2, seed=3, effects={"actuator_lag": 0.3}))
    write(log, truth, tmp_path)
    log = cg.load_log(tmp_path)
    cal = cg.calibrate(log, seed=3)
    asked = ["actuator_lag", "camera_latency", "battery_fade", "surface_friction"]
    one, two = (cg.diagnose(log, cal, candidates=asked, workers=w) for w in (1, 2))
    assert one.verdict == two.verdict == "actuator_lag"
    lag = next(c for c in two.candidates if c.effect == "actuator_lag")
    assert lag.delta_bic < -10 and lag.heldout_nll_drop > 0               # fitted and scored on the folds
    assert any(c.screened for c in two.candidates)                       # the score test screened some out
    for a, b in zip(one.candidates, two.candidates):
        assert (a.spec, a.screened, a.heldout_skipped) == (b.spec, b.screened, b.heldout_skipped)
        np.testing.assert_array_equal([a.delta_bic, a.delta_log_likelihood, a.heldout_nll_drop],
                                      [b.delta_bic, b.delta_log_likelihood, b.heldout_nll_drop])
        assert a.parameters == b.parameters
