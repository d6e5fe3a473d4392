"""A diagnosis's candidates fitted on worker processes (an action table's base beside them and every held-out fold a
task; a command map's base, profiles and hooked effects side by side) give the diagnosis one process gives; the
workers start so that a stop signal finds every one of them."""
import multiprocessing
import signal

import numpy as np

import casm_graph as cg
from casm_graph.analysis.candidates.pool import STOP, parallel, picklable
from casm_graph.models.effects import get, spec
from casm_graph.sim.aibo import SimConfig, simulate, write
from tests.worlds.independent_world import generate


def same(one, two):
    """The two diagnoses' verdicts and candidates, number for number."""
    assert one.verdict == two.verdict
    assert [c.spec for c in one.candidates] == [c.spec for c in two.candidates]
    for a, b in zip(one.candidates, two.candidates):
        assert (a.screened, a.heldout_skipped) == (b.screened, b.heldout_skipped)
        np.testing.assert_array_equal([a.delta_bic, a.delta_log_likelihood, a.heldout_nll_drop],
                                      [b.delta_bic, b.delta_log_likelihood, b.heldout_nll_drop])
        assert a.parameters == b.parameters


def test_two_workers_give_the_one_process_diagnosis(tmp_path):
    log, truth = simulate(SimConfig(minutes=2, seed=3, effects={"actuator_lag": 0.3}))
    write(log, truth, tmp_path)
    log = cg.load_log(tmp_path)
    cal = cg.calibrate(log, seed=3)
    asked = ["actuator_lag", "camera_latency", "battery_fade", "surface_friction"]
    one, two = (cg.diagnose(log, cal, candidates=asked, workers=w) for w in (1, 2))
    assert two.verdict == "actuator_lag"
    lag = next(c for c in two.candidates if c.effect == "actuator_lag")
    assert lag.delta_bic < -10 and lag.heldout_nll_drop > 0               # fitted and scored on the folds
    assert any(c.screened for c in two.candidates)                       # the score test screened some out
    same(one, two)


def test_a_command_map_s_candidates_on_two_workers(tmp_path):
    """Continuous commands with a second-order lag (the independent world): the lag's profile, hooked effects (a
    latency, a fade, a friction field) and a noise effect, and, with ``leader_rounds``, the leaders (the lag and the
    latency) settled again on the workers."""
    generate(tmp_path / "log", kind="continuous", minutes=2, seed=1, effect="actuator_lag")
    log = cg.load_log(tmp_path / "log")
    cal = cg.calibrate(log, seed=1)
    asked = ["actuator_lag", "camera_latency", "battery_fade", "surface_friction", "range_dependent_noise"]
    decide = cg.DiagnoseOptions(leader_rounds=6)
    one, two = (cg.diagnose(log, cal, candidates=asked, workers=w, options=decide) for w in (1, 2))
    assert {c.effect for c in two.candidates[:2]} == {"actuator_lag", "camera_latency"}
    assert two.candidates[0].delta_bic < -10
    same(one, two)


def test_what_travels_to_the_workers():
    """A family member (its class made on demand) travels as an instance and by its spec; a class made inside a
    function cannot travel, so its calls run in this process instead, with the same results."""
    member = get("surface_friction:0")
    assert spec(member) == "surface_friction:0" and picklable([(abs, (member(), spec(member)))])

    class Local:
        pass

    assert not picklable([(abs, (Local,))])
    assert parallel([(len, ([Local, 1],)), (len, ([],))], workers=2) == [2, 0]
    assert parallel([(abs, (-3,)), (abs, (2,))], workers=2) == [3, 2]


def test_workers_start_with_the_stop_signals_held_and_run_with_them_free(monkeypatch):
    """A SIGTERM while the pool forks waits until the parent knows every worker, so the command line's handler
    terminates them all (a worker forked but not yet counted outlived it); the workers take the signals at once and
    the caller's own mask comes back as it was."""
    held, real = [], multiprocessing.Pool

    def pool(*args, **kw):                    # the real pool, the mask it was started under noted
        held.append(signal.pthread_sigmask(signal.SIG_BLOCK, []))
        return real(*args, **kw)

    monkeypatch.setattr(multiprocessing, "Pool", pool)
    before = signal.pthread_sigmask(signal.SIG_BLOCK, [])
    masks = parallel([(signal.pthread_sigmask, (signal.SIG_BLOCK, [])) for _ in range(2)], workers=2)
    assert len(held) == 1 and set(STOP) <= set(held[0])
    assert len(masks) == 2 and not any(set(STOP) & set(m) for m in masks)
    assert signal.pthread_sigmask(signal.SIG_BLOCK, []) == before
