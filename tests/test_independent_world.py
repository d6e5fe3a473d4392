"""Calibration on a world written apart from the code (``tests/worlds/independent_world.py``).

That generator shares nothing with casm_graph's simulator: its own random field and landmarks, motion
at 200 Hz with slip, a sensor curve that is not a polynomial (an apparent size a / (d + b) + c for the
camera of the action-table robot, a time-of-flight range s d + o for the continuous one). Tolerances are
the paper's errors times 1.5 (PAPERS.md section 1: vx 23.06 mm/s, vy 18.34 mm/s, w 0.086 rad/s, sensor
curve 0.35 px) and, for the command map, a quarter of the error of taking the commands at face value
(the fit's is a tenth of it or less on seeds 0 and 1). The apparent-size curve over 0.3-8 m is too bent
for the paper's cubic (held at degree 3 it misses by 0.8-4.8 px and the table by up to 41 mm/s): the fit
raises the degree when the readings demand (``fit.sensor_degree``, BENCHMARKS.md "Independent world").
"""
import numpy as np
import pytest

import casm_graph as cg

from .worlds.independent_world import generate

PAPER = np.array([0.02306, 0.01834, 0.086])
PAPER_CURVE = 0.35


def _world(tmp_path, **kw):
    truth = generate(tmp_path / "log", minutes=4, **kw)
    return truth, cg.load_log(tmp_path / "log")


def _curve_rms(cal, log, truth):
    tr = cal.trajectory
    d_seen = np.hypot(*(log.landmark_xy[log.landmark_index] - np.column_stack([tr["x"], tr["y"]])[log.obs_step]).T)
    lo, hi = np.percentile(d_seen, [2, 98])
    d, r = np.array(truth["sensor_curve"]["samples"]).T
    sel = (d >= lo) & (d <= hi)
    return float(np.sqrt(np.mean((cal.model.reading(d[sel]) - r[sel]) ** 2)))


@pytest.mark.science
def test_action_table_robot_of_another_world(tmp_path):
    truth, log = _world(tmp_path, kind="table", seed=1)
    cal = cg.calibrate(log, seed=1)
    assert cal.model.fit["sensor_degree"]["asked"] == 3 and cal.model.fit["sensor_degree"]["fitted"] > 3
    true = np.array([truth["realized_velocities"][str(int(a))] for a in cal.model.action_ids])
    rms = np.sqrt(np.mean((cal.model.velocities - true) ** 2, axis=0))
    assert np.all(rms < 1.5 * PAPER), rms
    assert _curve_rms(cal, log, truth) < 1.5 * PAPER_CURVE
    assert cal.model.reading_sigma == pytest.approx(truth["noise"]["reading_sigma"], rel=0.15)


@pytest.mark.science
def test_continuous_command_robot_of_another_world(tmp_path):
    truth, log = _world(tmp_path, kind="continuous", seed=0)
    cal = cg.calibrate(log, seed=0)
    m = truth["command_map"]
    (v0, v1), (w0, w1) = cal.model.command.command_range
    v, w = np.meshgrid(np.linspace(v0, v1, 15), np.linspace(w0, w1, 15))
    got = cal.model.command.velocities(np.column_stack([v.ravel(), w.ravel()]))
    fwd = m["forward"]["gain"] * v.ravel() + m["forward"]["offset"]
    turn = m["turn"]["gain"] * w.ravel() + m["turn"]["offset"]
    rms = (lambda a, b: float(np.sqrt(np.mean((a - b) ** 2))))
    assert rms(got[:, 0], fwd) < 0.25 * rms(v.ravel(), fwd)
    assert rms(got[:, 2], turn) < 0.25 * rms(w.ravel(), turn)
    assert _curve_rms(cal, log, truth) < truth["noise"]["reading_sigma"]          # within one noise sigma
    tr = cal.trajectory
    assert np.sqrt(np.mean((tr["x"] - log.truth[:, 1]) ** 2 + (tr["y"] - log.truth[:, 2]) ** 2)) < 0.1


def test_the_sensor_degree_rises_only_when_the_readings_demand():
    from casm_graph.fit.sensor_degree import choose_degree
    rng = np.random.default_rng(0)
    d = rng.uniform(0.3, 8.0, 3000)
    cubic = np.array([40.0, -12.0, 1.5, -0.06])
    r = np.polynomial.polynomial.polyval(d, cubic) + rng.normal(0, 1.0, len(d))
    assert choose_degree(d, r, cubic, 1.0, 6) is None                    # a cubic sensor keeps its cubic
    size = 90.0 / (d + 0.15) + 1.0 + rng.normal(0, 1.0, len(d))           # an apparent size does not
    fit3 = np.polynomial.polynomial.polyfit(d, size, 3)
    better = choose_degree(d, size, fit3, 1.0, 6)
    assert better is not None and len(better) - 1 > 3
    assert choose_degree(d, size, fit3, 1.0, 3) is None                  # unless the user holds the degree
    steps = np.round(size / 100) * 100                                     # three distinct readings: nothing to raise
    assert choose_degree(d, steps, np.polynomial.polynomial.polyfit(d, steps, 3), 1.0, 6) is None
