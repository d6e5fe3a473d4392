"""``casm-graph calibrate`` end to end on a real CSV bundle: the files INTERFACE promises, in their shapes."""
import csv
import json
import subprocess
import sys

import numpy as np

from casm_graph.models.model import Model


def test_calibrate_writes_model_trajectory_and_report(short_bundle, tmp_path):
    d, log, truth = short_bundle
    out = tmp_path / "run"
    r = subprocess.run([sys.executable, "-m", "casm_graph.cli", "calibrate", str(d), "--out", str(out)],
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert "full graph" in r.stderr                     # the progress bar ran
    data = json.loads((out / "model.json").read_text())
    assert data["schema"] == "casm-graph/model/1"
    assert data["action_model"]["kind"] == "table"
    ids = {str(a) for a in np.unique(log.action)}
    assert set(data["action_model"]["velocities"]) == ids == set(data["action_model"]["std"])
    assert all(len(v) == 3 and all(s > 0 for s in data["action_model"]["std"][a])
               for a, v in data["action_model"]["velocities"].items())
    sm = data["sensor_model"]
    assert len(sm["reading_poly"]) == 4 and sm["distance_range"][0] < sm["distance_range"][1]
    assert abs(sm["reading_sigma"] - 1.0) < 0.15 and abs(sm["bearing_sigma"] - 0.5) < 0.08
    assert len(data["motion_noise"]) == 3
    fit = data["fit"]
    assert fit["method"] == "graph" and fit["iterations"] > 0 and np.isfinite(fit["log_likelihood"])
    model = Model.load(out / "model.json")               # reads back
    assert model.velocity_std.shape == (len(ids), 3)

    with open(out / "trajectory.csv") as f:
        rows = list(csv.DictReader(f))
    assert list(rows[0]) == ["t", "x", "y", "theta", "sx", "sy", "stheta"]
    assert len(rows) == log.steps + 1
    P = np.array([[float(r[c]) for c in ("x", "y", "theta", "sx", "sy", "stheta")] for r in rows])
    assert np.all(P[:, 3:] > 0)
    err = np.hypot(*(P[:, :2] - log.truth[:, 1:3]).T)
    assert np.sqrt(np.mean(err ** 2)) < 0.15             # the trajectory is where the robot was
    z = err / np.hypot(P[:, 3], P[:, 4])
    assert np.median(z) < 2.5                            # and its error bars are honest in scale

    html = (out / "report.html").read_text()
    assert html.count("data:image/png;base64") >= 4
    for words in ("Sensor model", "Cost per iteration", "Trajectory", "Residuals", "Action table", "true"):
        assert words in html


def test_unknown_method_and_effect_are_bad_input(short_bundle, tmp_path):
    d = short_bundle[0]
    r = subprocess.run([sys.executable, "-m", "casm_graph.cli", "calibrate", str(d), "--out", str(tmp_path / "r"),
                        "--effect", "gremlins"], capture_output=True, text=True)
    assert r.returncode == 2 and "unknown effect" in r.stderr and not (tmp_path / "r").exists()
    r = subprocess.run([sys.executable, "-m", "casm_graph.cli", "calibrate", str(d), "--out", str(tmp_path / "r"),
                        "--method", "magic"], capture_output=True, text=True)
    assert r.returncode == 2 and not (tmp_path / "r").exists()


def test_a_continuous_log_too_short_to_calibrate_is_refused_clearly(short_bundle, tmp_path):
    d = short_bundle[0]
    import shutil
    shutil.copytree(d, tmp_path / "log")
    (tmp_path / "log" / "commands.csv").write_text("t,v,w\n0,0.1,0\n0.1,0.1,0\n")
    (tmp_path / "log" / "observations.csv").write_text("t,landmark,reading,bearing\n0.05,0,20,0.1\n")
    r = subprocess.run([sys.executable, "-m", "casm_graph.cli", "calibrate", str(tmp_path / "log"), "--out",
                        str(tmp_path / "r")], capture_output=True, text=True)
    assert r.returncode == 2 and "action" in r.stderr and "Traceback" not in r.stderr
