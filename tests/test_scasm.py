"""SCASM (the paper's online algorithm and its evaluation) and the 1-D ISAM2 graph on the same logs.

The science check runs 10 trials of 2.5 minutes with CASM_FULL=1 (the paper's protocol) and 2 in CI;
benchmarks/seed_baselines.py prints the full table.
"""
import numpy as np
import pytest

from casm_graph.baselines import scasm
from casm_graph.cli import main
from casm_graph.io.log import LogError
from casm_graph.sim.aibo import SimConfig, simulate
from casm_graph.sim.walk_1d import Sim1DConfig, write
from casm_graph.sim.walk_1d import simulate as simulate_1d

from .conftest import FULL

PAPER_ACTION = 29.6 + 12.4      # mm/s, mean + one std over the paper's 10 trials
PAPER_SENSOR = 70.4 + 13.9      # mm
PAPER_RATIO = 0.14


def test_discounted_sums_equal_weighted_least_squares():
    rng = np.random.default_rng(3)
    V = rng.normal(size=(400, 3)) * [1, 10, 100]
    y = 2.0 + V @ [0.5, -0.1, 0.003] + rng.normal(0, 0.1, 400)
    reg = scasm.DiscountedRegression(3, gamma=0.99)
    for v, yy in zip(V, y):
        reg.add(v, yy)
    alpha, beta = reg.solve()
    w = np.sqrt(0.99 ** np.arange(399, -1, -1))
    coef = np.linalg.lstsq(np.column_stack([np.ones(400), V]) * w[:, None], y * w, rcond=None)[0]
    assert np.allclose([alpha, *beta], coef, rtol=1e-7, atol=1e-9)


def test_isam2_reaches_the_batch_solution():
    log, _ = simulate_1d(Sim1DConfig(minutes=0.5, seed=4))
    walk = scasm.walk_of(log)
    res = scasm.graph_online(walk)
    g = scasm.Graph1D(walk)
    sol = g.solve(scasm.MOTION_SIGMA, scasm.SENSOR_SIGMA)
    assert np.allclose(res.action.coef, sol.at(scasm.KA), rtol=1e-6, atol=1e-9)
    assert np.allclose(res.sensor.coef, sol.at(scasm.KS), rtol=1e-6, atol=1e-9)
    assert np.allclose(res.x, [sol.at(scasm._x(k))[0] for k in range(len(res.x))], atol=1e-8)


def test_score_is_zero_for_the_truth_up_to_scale_and_offset():
    _, truth = simulate_1d(Sim1DConfig(minutes=0.2, seed=0))
    c, v = np.array(truth["action_model"]["commands"]), np.array(truth["action_model"]["velocities"])
    r, d = np.array(truth["sensor_model"]["readings"]), np.array(truth["sensor_model"]["distances"])
    s = scasm.score(lambda x: 3.0 * np.interp(x, c, v), lambda o: 7.0 - 3.0 * np.interp(o, r[::-1], d[::-1]), truth)
    assert s.action_rms < 1e-9 and s.sensor_rms < 1e-9 and s.consistency < 1e-12


@pytest.mark.science
def test_scasm_and_graph_on_the_paper_protocol():
    trials = range(10) if FULL else range(2)
    on, gr = [], []
    for seed in trials:
        log, truth = simulate_1d(Sim1DConfig(minutes=2.5, seed=seed))
        walk = scasm.walk_of(log)
        for out, res in ((on, scasm.online(walk)), (gr, scasm.graph_online(walk))):
            s = scasm.score(res.action, res.sensor, truth)
            out.append((s.action_rms, s.sensor_rms, s.consistency))
    on, gr = np.mean(on, axis=0), np.mean(gr, axis=0)
    print(f"SCASM {on}, graph {gr} over {len(trials)} trials")
    assert on[0] < PAPER_ACTION and on[1] < PAPER_SENSOR and on[2] < PAPER_RATIO
    assert gr[0] <= on[0] and gr[1] <= on[1] and gr[2] < PAPER_RATIO


def test_one_dimensional_logs_only():
    log, _ = simulate(SimConfig(minutes=0.2, seed=1))
    with pytest.raises(LogError, match="one landmark"):
        scasm.walk_of(log)


def test_cli_scasm_run_and_bad_input(tmp_path, capsys):
    log, truth = simulate_1d(Sim1DConfig(minutes=0.7, seed=2))
    write(log, truth, tmp_path / "walk")
    for method in ("scasm", "scasm-graph"):
        assert main(["calibrate", str(tmp_path / "walk"), "--out", str(tmp_path / method), "--method", method,
                     "--quiet"]) == 0
        for f in ("model.json", "trajectory.csv", "report.html"):
            assert (tmp_path / method / f).stat().st_size > 0
    assert "action_rms_mm_s" in capsys.readouterr().out
    cmd = tmp_path / "walk" / "commands.csv"
    rows = cmd.read_text().splitlines()
    rows[5] = rows[5].rsplit(",", 1)[0] + ",0.2"
    cmd.write_text("\n".join(rows) + "\n")
    assert main(["calibrate", str(tmp_path / "walk"), "--out", str(tmp_path / "bad"), "--method", "scasm",
                 "--quiet"]) == 2
    assert "row 5, column 'w'" in capsys.readouterr().err
    assert not (tmp_path / "bad").exists()


def test_cli_simulates_the_1d_protocol(tmp_path):
    assert main(["simulate", str(tmp_path / "w"), "--protocol", "scasm-1d", "--minutes", "0.5"]) == 0
    assert (tmp_path / "w" / "truth_model.json").is_file()
