"""Range-only and bearing-only simulated logs, the time-of-flight range curve and NLOS tails (issue 22)."""
import hashlib
import json

import numpy as np
import pytest

from casm_graph.cli import main
from casm_graph.io.log import LogError, load
from casm_graph.sim import protocols
from casm_graph.sim.aibo import SimConfig
from casm_graph.sim.aibo import simulate as simulate_aibo
from casm_graph.sim.floor import FloorConfig
from casm_graph.sim.floor import simulate as simulate_floor

# Digests of logs written by the simulators before the sensor options existed (same seeds, default options; the
# floor's since its step moves along the middle heading).
REFERENCE = {"floor": "239f01b39c472a54", "aibo": "e8eff659650b05ae", "aibo-false-detections": "a671959cc529fdba"}


def digest(log) -> str:
    """A short hash of every array of a log, rounded to the 9 digits the CSV files keep."""
    h = hashlib.sha256()
    for a in (log.landmark_xy, log.t, log.controls if log.controls is not None else log.action, log.obs_t,
              log.obs_landmark, log.obs_reading, log.obs_bearing, log.truth):
        h.update(np.ascontiguousarray(np.round(np.asarray(a, float), 9)).tobytes())
    return h.hexdigest()[:16]


def true_geometry(log):
    """True distance and bearing of each observation, from the truth poses."""
    p = log.truth[log.obs_step, 1:]
    rel = log.landmark_xy[log.obs_landmark] - p[:, :2]
    b = np.arctan2(rel[:, 1], rel[:, 0]) - p[:, 2]
    return np.hypot(rel[:, 0], rel[:, 1]), np.arctan2(np.sin(b), np.cos(b))


def run(protocol, **options):
    return simulate_floor(FloorConfig(**options)) if protocol == "floor" else simulate_aibo(SimConfig(**options))


SHORT = {"floor": {"minutes": 1, "seed": 3}, "aibo": {"minutes": 0.5, "seed": 3}}


def test_both_is_todays_log():
    assert digest(run("floor", **SHORT["floor"])[0]) == REFERENCE["floor"]
    assert digest(run("floor", sensor="both", **SHORT["floor"])[0]) == REFERENCE["floor"]
    assert digest(run("aibo", **SHORT["aibo"])[0]) == REFERENCE["aibo"]
    assert digest(run("aibo", sensor="both", **SHORT["aibo"])[0]) == REFERENCE["aibo"]
    hidden = run("aibo", effects={"false_detections": 0.1}, **SHORT["aibo"])[0]
    assert digest(hidden) == REFERENCE["aibo-false-detections"]


@pytest.mark.parametrize("protocol", ["floor", "aibo"])
@pytest.mark.parametrize("sensor", ["range", "bearing", "both"])
def test_sensor_mode_empties_the_right_column(protocol, sensor):
    log, truth = run(protocol, sensor=sensor, **SHORT[protocol])
    assert len(log.obs_t) > 50
    assert np.all(np.isnan(log.obs_bearing)) == (sensor == "range")
    assert np.all(np.isfinite(log.obs_bearing)) == (sensor != "range")
    assert np.all(np.isnan(log.obs_reading)) == (sensor == "bearing")
    assert np.all(np.isfinite(log.obs_reading)) == (sensor != "bearing")
    sm = truth["sensor_model"]
    assert sm["sensor"] == sensor and truth["simulation"]["sensor"] == sensor
    assert sm["channels"] == {"range": ["reading"], "bearing": ["bearing"], "both": ["reading", "bearing"]}[sensor]


@pytest.mark.parametrize("protocol", ["floor", "aibo"])
def test_bearing_only_is_the_both_log_without_readings(protocol):
    both, _ = run(protocol, **SHORT[protocol])
    bearing, _ = run(protocol, sensor="bearing", **SHORT[protocol])
    np.testing.assert_array_equal(bearing.obs_t, both.obs_t)
    np.testing.assert_array_equal(bearing.obs_landmark, both.obs_landmark)
    np.testing.assert_array_equal(bearing.obs_bearing, both.obs_bearing)
    np.testing.assert_array_equal(bearing.truth, both.truth)


def test_aibo_range_only_keeps_the_camera_readings():
    both, _ = run("aibo", **SHORT["aibo"])
    rng_only, _ = run("aibo", sensor="range", **SHORT["aibo"])
    np.testing.assert_array_equal(rng_only.obs_t, both.obs_t)
    np.testing.assert_array_equal(rng_only.obs_reading, both.obs_reading)


def test_floor_range_only_sees_all_around():
    log, truth = run("floor", sensor="range", minutes=2, seed=4)
    d, b = true_geometry(log)
    assert np.all(d < 5.0)
    assert np.mean(np.abs(b) > np.pi / 2) > 0.2          # behind the robot too
    assert truth["sensor_model"]["half_fov"] == pytest.approx(np.pi)
    _, b_front = true_geometry(run("floor", sensor="both", minutes=2, seed=4)[0])
    assert np.all(np.abs(b_front) < np.pi / 2)


def test_range_curve_recovered_by_a_line_fit():
    log, truth = run("floor", sensor="range", minutes=2, seed=5, range_scale=1.07, range_offset=0.3, n_landmarks=4)
    assert len(log.landmark_ids) == 4
    d, _ = true_geometry(log)
    slope, offset = np.polyfit(d, log.obs_reading, 1)
    assert slope == pytest.approx(1.07, abs=0.01) and offset == pytest.approx(0.3, abs=0.03)
    res = log.obs_reading - (offset + slope * d)
    assert np.std(res) == pytest.approx(0.05, rel=0.15)
    sm = truth["sensor_model"]
    assert sm["range_scale"] == 1.07 and sm["range_offset"] == 0.3 and sm["reading_poly"] == [0.3, 1.07]
    assert sm["n_landmarks"] == 4


def test_nlos_tail_is_one_sided_with_the_asked_fraction():
    opts = dict(sensor="range", minutes=2, seed=6, detect_prob=1.0, range_sigma=0.01)
    clean, _ = run("floor", **opts)
    log, truth = run("floor", nlos_fraction=0.2, nlos_scale=1.0, **opts)
    np.testing.assert_array_equal(log.obs_t, clean.obs_t)                  # NLOS draws leave the rest alone
    np.testing.assert_array_equal(log.obs_landmark, clean.obs_landmark)
    d, _ = true_geometry(log)
    res = log.obs_reading - d
    assert len(res) > 1000
    assert res.min() > -0.05                                               # no negative tail
    late = res > 0.05
    assert np.mean(late) == pytest.approx(0.2 * np.exp(-0.05), abs=0.03)
    assert np.mean(res[late]) - 0.05 == pytest.approx(1.0, abs=0.15)     # exponential: memoryless mean
    extra = log.obs_reading - clean.obs_reading
    assert np.all(extra >= 0) and np.mean(extra > 0) == pytest.approx(0.2, abs=0.03)
    sm = truth["sensor_model"]
    assert sm["nlos_fraction"] == 0.2 and sm["nlos_scale"] == 1.0


def test_seeds_reproducible():
    opts = dict(sensor="range", minutes=1, range_scale=1.02, nlos_fraction=0.1, n_landmarks=5)
    assert digest(run("floor", seed=8, **opts)[0]) == digest(run("floor", seed=8, **opts)[0])
    assert digest(run("floor", seed=8, **opts)[0]) != digest(run("floor", seed=9, **opts)[0])
    assert digest(run("aibo", seed=8, minutes=0.3, sensor="bearing")[0]) == \
        digest(run("aibo", seed=8, minutes=0.3, sensor="bearing")[0])


@pytest.mark.parametrize("options, words", [
    ({"sensor": "sonar"}, "sensor must be one of"),
    ({"nlos_fraction": 1.5}, "nlos_fraction"),
    ({"nlos_scale": 0.0}, "nlos_scale"),
    ({"range_scale": -1.0}, "range_scale"),
    ({"n_landmarks": 0}, "n_landmarks"),
])
def test_floor_rejects_bad_options(options, words):
    with pytest.raises(LogError, match=words):
        simulate_floor(FloorConfig(minutes=0.2, **options))


def test_aibo_and_scasm_reject_sensor_modes():
    with pytest.raises(LogError, match="sensor must be one of"):
        simulate_aibo(SimConfig(minutes=0.1, sensor="sonar"))
    with pytest.raises(LogError, match="scasm-1d"):
        protocols.simulate("scasm-1d", minutes=0.1, sensor="range")
    log, _ = protocols.simulate("scasm-1d", minutes=0.1, sensor="both")
    assert np.all(np.isfinite(log.obs_reading))


def test_cli_writes_a_range_only_floor_log(tmp_path, capsys):
    out = tmp_path / "uwb"
    assert main(["simulate", str(out), "--protocol", "floor", "--minutes", "1", "--seed", "2", "--sensor", "range",
                 "--option", "n_landmarks=4", "--option", "range_scale=1.05", "--option", "range_offset=0.2",
                 "--option", "nlos_fraction=0.1", "--option", "nlos_scale=0.8"]) == 0
    log = load(out)
    assert len(log.landmark_ids) == 4 and len(log.obs_t) > 20
    assert np.all(np.isnan(log.obs_bearing)) and np.all(np.isfinite(log.obs_reading))
    rows = (out / "observations.csv").read_text().splitlines()
    assert rows[0].startswith("t,landmark,reading,bearing") and all(r.split(",")[3] == "" for r in rows[1:])
    sm = json.loads((out / "truth_model.json").read_text())["sensor_model"]
    assert (sm["sensor"], sm["range_scale"], sm["range_offset"], sm["nlos_fraction"], sm["nlos_scale"]) == \
        ("range", 1.05, 0.2, 0.1, 0.8)
    expected, _ = protocols.simulate("floor", minutes=1, seed=2, sensor="range", n_landmarks=4, range_scale=1.05,
                                     range_offset=0.2, nlos_fraction=0.1, nlos_scale=0.8)
    np.testing.assert_allclose(log.obs_reading, expected.obs_reading, atol=1e-8)


def test_cli_bearing_only_aibo_and_default_unchanged(tmp_path):
    assert main(["simulate", str(tmp_path / "b"), "--minutes", "0.3", "--sensor", "bearing"]) == 0
    log = load(tmp_path / "b")
    assert np.all(np.isnan(log.obs_reading)) and np.all(np.isfinite(log.obs_bearing))
    assert main(["simulate", str(tmp_path / "f"), "--protocol", "floor", "--minutes", "1", "--seed", "3"]) == 0
    written = load(tmp_path / "f")
    ref, _ = run("floor", **SHORT["floor"])
    np.testing.assert_allclose(written.obs_reading, ref.obs_reading, atol=1e-8)
    np.testing.assert_allclose(written.obs_bearing, ref.obs_bearing, atol=1e-8)


@pytest.mark.parametrize("argv, words", [
    (["--protocol", "scasm-1d", "--sensor", "range"], "scasm-1d"),
    (["--protocol", "floor", "--option", "gremlins=1"], "not an option of the floor simulator"),
    (["--protocol", "floor", "--option", "n_landmarks=four"], "whole number"),
    (["--protocol", "floor", "--option", "nlos_fraction=2"], "nlos_fraction"),
    (["--protocol", "floor", "--option", "seed=4"], "--seed"),
    (["--option", "reading_sigma=2"], "--reading-sigma"),
    (["--protocol", "floor", "--option", "range_scale"], "NAME=VALUE"),
])
def test_cli_rejects_bad_sensor_options(tmp_path, capsys, argv, words):
    out = tmp_path / "bad"
    assert main(["simulate", str(out), "--minutes", "0.2", *argv]) == 2
    err = capsys.readouterr().err
    assert words in err and len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert not out.exists()
