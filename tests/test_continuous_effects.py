"""The actuator_lag effect on continuous-command logs and ``diagnose`` for them (issue 7, item 4).

A floor log (simulate_floor) whose robot follows its (v, w) commands through a known first-order
lag: the lag's profile finds it, ``calibrate --effect actuator_lag`` writes it, ``diagnose`` ranks
it as a candidate and reports the residual channels.
"""
import json
from dataclasses import replace

import numpy as np
import pytest

from casm_graph.cli import main
from casm_graph.command_model import CommandModel, lagged
from casm_graph.log import write
from casm_graph.model import Model
from casm_graph.simulate_floor import FloorConfig, simulate

TRUE_LAG = 0.3


def test_first_order_lag_recursion_and_steady_state():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(200, 3))
    dt = rng.uniform(0.005, 0.02, 200)
    y = lagged(x, dt, 0.1)
    ref = x.copy()
    for k in range(1, 200):
        a = np.exp(-dt[k] / 0.1)
        ref[k] = a * ref[k - 1] + (1 - a) * x[k]
    assert np.allclose(y, ref)
    step = lagged(np.r_[np.zeros(10), np.ones(2000)][:, None], np.full(2010, 0.01), 0.1)
    assert step[19, 0] == pytest.approx(1 - np.exp(-1))           # one time constant after the jump: 63 %
    assert step[-1, 0] == pytest.approx(1.0)
    cm = CommandModel(scale=(0.1, 0.5), v_coef=np.array([0.0, 0.1]), w_coef=np.array([0.0, 0.5]), lag=0.2)
    ctl = rng.uniform(-0.1, 0.1, size=(50, 2))
    assert np.allclose(cm.velocities(ctl), replace(cm, lag=0.0).velocities(ctl))   # no dt: the steady-state map
    assert not np.allclose(cm.velocities(ctl, np.full(50, 0.01)), cm.velocities(ctl))


def test_lag_survives_model_json(tmp_path):
    cm = CommandModel(scale=(0.1, 0.5), v_coef=np.array([0.0, 0.1]), w_coef=np.array([0.0, 0.5]), lag=0.25)
    m = Model(action_ids=np.array([], int), velocities=np.zeros((0, 3)), reading_poly=np.array([0.0, 1.0]),
              reading_sigma=0.05, bearing_sigma=0.02, command=cm)
    m.save(tmp_path / "model.json")
    assert json.loads((tmp_path / "model.json").read_text())["action_model"]["lag"] == 0.25
    assert Model.load(tmp_path / "model.json").command.lag == 0.25


@pytest.fixture(scope="module")
def lag_floor(tmp_path_factory):
    log, truth = simulate(FloorConfig(minutes=4, seed=0, dt=0.1, lag=TRUE_LAG))
    d = tmp_path_factory.mktemp("floorlag")
    write(log, d)
    return d, log


@pytest.mark.science
def test_profile_finds_the_lag_and_calibrate_writes_it(lag_floor, tmp_path):
    d, _ = lag_floor
    assert main(["calibrate", str(d), "--out", str(tmp_path / "run"), "--effect", "actuator_lag", "--quiet"]) == 0
    data = json.loads((tmp_path / "run" / "model.json").read_text())
    lag = data["action_model"]["lag"]
    assert lag == pytest.approx(TRUE_LAG, rel=0.25), lag
    assert data["effects"]["actuator_lag"]["tau"] == pytest.approx(lag)


@pytest.mark.science
def test_diagnose_a_continuous_log(lag_floor, tmp_path):
    d, _ = lag_floor
    assert main(["calibrate", str(d), "--out", str(tmp_path / "run"), "--quiet"]) == 0
    assert main(["diagnose", str(d), "--model", str(tmp_path / "run" / "model.json"), "--out",
                 str(tmp_path / "diag"), "--quiet"]) == 0
    diag = json.loads((tmp_path / "diag" / "diagnosis.json").read_text())
    assert set(diag["channels"]) == {"forward", "lateral", "turn", "reading", "bearing"}
    (cand,) = diag["candidates"]
    assert cand["effect"] == "actuator_lag" and cand["delta_bic"] < -10
    assert cand["parameters"]["tau"] == pytest.approx(TRUE_LAG, rel=0.25)
    assert cand["heldout_nll_drop"] is None and "continuous" in cand["heldout_skipped"]
    assert "lens_distortion" in diag["not_applicable"]
    assert (tmp_path / "diag" / "report.html").stat().st_size > 10_000


def test_other_effects_refused_on_continuous_logs(lag_floor, tmp_path, capsys):
    d, _ = lag_floor
    assert main(["calibrate", str(d), "--out", str(tmp_path / "run"), "--effect", "lens_distortion", "--quiet"]) == 2
    assert "only actuator_lag" in capsys.readouterr().err
    assert not (tmp_path / "run").exists()


def test_diagnose_refuses_a_table_model_on_a_continuous_log(lag_floor, tmp_path, capsys):
    d, _ = lag_floor
    m = Model(action_ids=np.array([1]), velocities=np.zeros((1, 3)), reading_poly=np.array([0.0, 1.0]),
              reading_sigma=0.05, bearing_sigma=0.02)
    m.save(tmp_path / "model.json")
    assert main(["diagnose", str(d), "--model", str(tmp_path / "model.json"), "--out", str(tmp_path / "diag"),
                 "--quiet"]) == 2
    assert "no command map" in capsys.readouterr().err
    assert not (tmp_path / "diag").exists()
