"""A differential-drive robot from tests/worlds/wheel_world.py, written apart from the library by a helper that
read only the user documentation: commands ``v, w`` turned into wheel set-points with the firmware's nominal
track, each wheel with its own gain, a deadband and a saturation, slipping as an Ornstein-Uhlenbeck process in a
200 Hz integration, ranges and bearings on the sensor's own clock with dropouts.

Unequal wheel gains make the turn rate depend on the forward command, (g_r - g_l) / track per m/s. The
calibration's turn map holds that term when BIC supports it (``cross_terms="auto"``); without it (the paper's
form, ``cross_terms=False``) the diagnosis names the coupling with its equation, and adding that proposal brings
the error down.
"""
from __future__ import annotations

import json
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

import casm_graph as cg

GENERATOR = Path(__file__).parent / "worlds" / "wheel_world.py"


def world(tmp_path: Path, seed: int, minutes: float, sensor: str = "range") -> tuple[Path, dict]:
    """A log of the wheel world with a near-instant wheel response (0.002 s: no actuator lag to find)."""
    out = tmp_path / f"wheel_{sensor}_{seed}"
    subprocess.run([sys.executable, str(GENERATOR), str(out), "--minutes", str(minutes), "--seed", str(seed),
                    "--base-tau", "0.002", "--sensor", sensor], check=True, capture_output=True)
    return out, json.loads((out / "world_truth.json").read_text())


def position_rms(cal, path: Path) -> float:
    truth = np.genfromtxt(path / "truth.csv", delimiter=",", names=True)
    tr = cal.trajectory
    x, y = (np.interp(tr["t"], truth["t"], truth[c]) for c in ("x", "y"))
    return float(np.sqrt(np.mean((tr["x"] - x) ** 2 + (tr["y"] - y) ** 2)))


def test_a_differential_drive_is_calibrated_to_the_best_maps_of_its_form(tmp_path):
    """Seed 1 (wheel gains 1.096 and 1.092, little coupling), three minutes: the maps within 1 % of the true
    velocities' range over the commands run, the path within 2 cm, the noise levels within 10 %."""
    path, truth = world(tmp_path, 1, 3)
    log = cg.load_log(path)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        cal = cg.calibrate(log)
    assert not [w for w in caught if "heading loose" in str(w.message)]
    cmd = np.genfromtxt(path / "cmd_truth.csv", delimiter=",", names=True)
    controls = np.column_stack([cmd["v"], cmd["w"]])
    fitted = cal.model.command.velocities(controls)
    true = np.column_stack([cmd["v_true"], cmd["w_true"]])
    err = np.sqrt(np.mean((fitted[:, [0, 2]] - true) ** 2, axis=0)) / np.ptp(true, axis=0)
    assert np.all(err < 0.01), err
    assert position_rms(cal, path) < 0.02
    sensor = truth["sensor"]
    assert abs(cal.model.reading_sigma / sensor["reading_sigma"] - 1) < 0.1
    assert abs(cal.model.bearing_sigma / sensor["bearing_sigma"] - 1) < 0.1


def map_errors(cal, path: Path) -> np.ndarray:
    """RMS of the learned speed and turn maps against the true velocities over the commands run, per range."""
    cmd = np.genfromtxt(path / "cmd_truth.csv", delimiter=",", names=True)
    fitted = cal.model.command.velocities(np.column_stack([cmd["v"], cmd["w"]]))
    true = np.column_stack([cmd["v_true"], cmd["w_true"]])
    return np.sqrt(np.mean((fitted[:, [0, 2]] - true) ** 2, axis=0)) / np.ptp(true, axis=0)


@pytest.mark.science
def test_unequal_wheels_are_calibrated_or_discovered_as_a_turn_that_follows_the_speed(tmp_path):
    """Seed 3 (wheel gains 0.900 and 1.095, track 0.359 m: the turn rate gains 0.542 rad/s per m/s of forward
    command), four minutes. By default the turn map keeps its term in v, within 5 % of 0.542, the turn map within
    1 % of the true turn rates (2.6 % without the term); graph-em and ekfs-em asked for the term fit it within 5 %. In the paper's form the verdict is ``unexplained:speed``
    and the proposal's turn term in the forward velocity is within 10 % of 0.542 (the words point to
    ``--cross-terms on``); added, the path comes closer to the truth."""
    path, truth = world(tmp_path, 3, 4)
    log = cg.load_log(path)
    coupling = truth["linear_map_no_saturation"]["w_from_v"]
    auto = cg.calibrate(log)
    ct = auto.model.fit["cross_term"]
    assert ct["kept"] and abs(ct["w_per_v"] / coupling - 1) < 0.05, (ct, coupling)
    cal = cg.calibrate(log, cross_terms=False)
    print(f"turn per forward speed {ct['w_per_v']:.3f} (truth {coupling:.3f}, delta BIC {ct['delta_bic']:,.0f}); "
          f"maps (speed, turn) {np.round(100 * map_errors(auto, path), 2)} % with the term, "
          f"{np.round(100 * map_errors(cal, path), 2)} % without")
    assert map_errors(auto, path)[1] < 0.01 < map_errors(cal, path)[1]
    for method in ("graph-em", "ekfs-em"):          # the EM methods fit the term when asked (auto is graph's choice)
        em = cg.calibrate(log, method=method, cross_terms=True).model.command
        assert abs(em.cross_coefficient("w")[0] / em.scale[0] / coupling - 1) < 0.05, method
    diag = cg.diagnose(log, cal)
    assert diag.verdict == "unexplained:speed", diag.verdict
    term = diag.proposal["terms"]["turn: v_forward"]
    assert any("--cross-terms on" in w and "made without it" in w for w in diag.words)
    assert abs(term / coupling - 1) < 0.1, (term, coupling)
    added = cg.calibrate(log, effects=[diag.proposal_effect()])
    before, after = position_rms(cal, path), position_rms(added, path)
    print(f"proposal {diag.proposal['equation']} (turn per forward speed: {term:.3f}, truth {coupling:.3f}); "
          f"position RMS {before:.4f} -> {after:.4f} m")
    assert after < before


def test_a_radio_log_that_leaves_the_heading_loose_is_warned_of(tmp_path):
    """Seed 1 with a radio's signal strength in dB (2-4 dB of noise, no bearings), six minutes: the fit lands in
    a wrong basin, about 50 degrees off in heading and 0.7 m in position, and its posterior says the heading is
    loose (a median std of 0.54 rad, where the range logs have 0.01): calibrate warns. The three-minute range log above does not."""
    path, _ = world(tmp_path, 1, 6, sensor="rssi")
    with pytest.warns(RuntimeWarning, match="heading loose"):
        cg.calibrate(cg.load_log(path))
