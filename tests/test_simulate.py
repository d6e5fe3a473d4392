"""The simulator follows the paper's protocol."""
import json
import subprocess
import sys

import numpy as np

from casm_graph.io.log import wrap
from casm_graph.models.aibo import attempted_table
from casm_graph.sim.aibo import BEACONS, FIELD, SimConfig, simulate


def test_protocol():
    log, truth = simulate(SimConfig(minutes=8, seed=2))
    assert log.steps == 8 * 60 * 30
    np.testing.assert_allclose(np.diff(log.t), 1 / 30)
    x, y = log.truth[:, 1], log.truth[:, 2]
    assert np.all(np.abs(x) <= FIELD[0] / 2) and np.all(np.abs(y) <= FIELD[1] / 2)
    change = np.flatnonzero(np.diff(log.action)) + 1
    assert np.all(change % 150 == 0)                        # a new action every 5 s
    counts = np.bincount(log.action[::150], minlength=40)
    assert counts.max() - counts.min() <= 3                 # counts evened out
    assert 0.3 < len(log.obs_t) / log.steps < 0.9           # frames with no sighting
    assert len(np.unique(log.obs_t)) == len(log.obs_t)      # one beacon at a time
    lm = BEACONS[log.obs_landmark]
    p = log.truth[log.obs_step, 1:]
    true_b = np.arctan2(lm[:, 1] - p[:, 1], lm[:, 0] - p[:, 0]) - p[:, 2]
    assert abs(np.std(wrap(log.obs_bearing - true_b)) - 0.5) < 0.03
    assert np.all(np.abs(wrap(true_b - log.obs_pan)) < 0.5)  # in the camera's field of view


def test_true_table_is_not_a_function_of_attempted():
    _, truth = simulate(SimConfig(minutes=0.2, seed=0))
    tab = np.array([truth["action_model"]["velocities"][str(a)] for a in range(40)])
    att = attempted_table()
    for j in range(3):   # no exact linear map from the attempted velocities
        A = np.column_stack([att, np.ones(40)])
        res = tab[:, j] - A @ np.linalg.lstsq(A, tab[:, j], rcond=None)[0]
        assert np.std(res) > 0.01


def test_cli_writes_bundle_and_rejects_unknown_effect(tmp_path):
    r = subprocess.run([sys.executable, "-m", "casm_graph.cli", "simulate", str(tmp_path / "a"), "--minutes", "0.5",
                        "--seed", "3"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    for f in ("landmarks.csv", "commands.csv", "observations.csv", "actions.csv", "truth.csv", "truth_model.json"):
        assert (tmp_path / "a" / f).is_file()
    assert json.loads((tmp_path / "a" / "truth_model.json").read_text())["sensor_model"]["reading_sigma"] == 1.0
    r = subprocess.run([sys.executable, "-m", "casm_graph.cli", "simulate", str(tmp_path / "b"), "--effect",
                        "gremlins=1"], capture_output=True, text=True)
    assert r.returncode == 2 and "unknown effect" in r.stderr and not (tmp_path / "b").exists()
