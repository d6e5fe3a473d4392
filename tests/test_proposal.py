"""Discovery beyond the catalog: the diagnosis proposes an effect equation, the user adds it, the error falls.

The science test hides an uncataloged effect (forward speed scaled by 1 + s cos(heading - phi)) in the
independent world (tests/worlds), which produces it by physics in its own 200 Hz integration.
"""
import dataclasses
import json
import pickle

import numpy as np
import pytest

import casm_graph as cg
from casm_graph.analysis.diagnosis import Candidate, discover
from casm_graph.analysis.proposal import covariate, distinct, propose
from casm_graph.cli import main
from casm_graph.fit.residuals import Channel
from casm_graph.io.log import LogError
from casm_graph.models.effects import of_model
from casm_graph.models.effects.proposal import (SPEED_FLOOR, equation, features, from_diagnosis, library, parse,
                                                proposal_effect)

from .conftest import FULL
from .worlds.independent_world import generate

TERMS = {"forward: v_forward*cos(heading)": -0.08, "forward: v_forward*sin(heading)": 0.12, "turn: speed": 0.2,
         "lateral: sin(2pi t/120s)": 0.01}


def test_a_proposal_is_named_by_its_strongest_terms_covariate():
    def prop(t_values):
        return {"axes": {a: {"t_values": {k: v for k, v in t_values.items() if k.startswith(a)}}
                         for a in {k.split(":")[0] for k in t_values}}}
    assert covariate(prop({"forward: v_forward*cos(heading)": 6.0, "turn: speed": -9.0})) == "speed"
    assert covariate(prop({"forward: v_forward*sin(2pi t/120s)": 7.0, "lateral: x": 5.5})) == "time"
    assert covariate(prop({"turn: w*y": 8.0})) == "y"
    assert covariate(prop({"lateral: |w|": 5.1})) == "turn_rate"
    assert covariate(prop({"turn: w/speed": 6.2, "turn: w*cos(heading)": 5.5})) == "speed"


def test_a_proposal_is_its_equation_and_survives_model_json_and_pickle():
    cls = proposal_effect(TERMS)
    assert cls.params == tuple(TERMS) and cls.start == tuple(TERMS.values())
    assert pickle.loads(pickle.dumps(cls)) is cls                       # worker processes get the very class
    assert of_model({"proposal": {k: 0.0 for k in TERMS}})[0].params == cls.params
    pose = np.array([[1.0, 2.0, 0.3], [-1.0, 0.5, 2.0]])
    t = np.array([10.0, 70.0])
    v = np.array([[0.2, 0.05, 0.4], [-0.1, 0.0, -0.2]])
    out = cls(None).velocity(np.array(cls.start), v, {"pose": pose, "t": t})
    fwd = v[:, 0] * (1 - 0.08 * np.cos(pose[:, 2]) + 0.12 * np.sin(pose[:, 2]))
    assert np.allclose(out[:, 0], fwd)
    assert np.allclose(out[:, 1], v[:, 1] + 0.01 * np.sin(2 * np.pi * t / 120))
    assert np.allclose(out[:, 2], v[:, 2] + 0.2 * np.hypot(v[:, 0], v[:, 1]))
    assert equation(TERMS)[0] == "forward velocity (m/s) += - 0.08 v_forward*cos(heading) + 0.12 v_forward*sin(heading)"
    assert features("turn", ["w*x"], {"pose": pose, "t": t}, v)[:, 0] == pytest.approx(v[:, 2] * pose[:, 0])


def test_a_turn_rate_over_the_speed_is_a_term_of_the_turn_only():
    """A car steering for its commanded speed turns at w v_true / v: ``w/speed``, the speed floored where the
    robot turns in place."""
    v = np.array([[0.2, 0.0, 0.4], [0.0, 0.01, -0.3], [-0.5, 0.0, 0.1]])
    ctx = {"pose": np.zeros((3, 3)), "t": np.zeros(3)}
    got = features("turn", ["w/speed"], ctx, v)[:, 0]
    assert got == pytest.approx([0.4 / 0.2, -0.3 / SPEED_FLOOR, 0.1 / 0.5])
    assert "w/speed" in library("turn") and not any("speed" in t and "/" in t for t in library("forward"))
    assert not any(t.endswith("1/speed") for a in ("forward", "lateral", "turn") for t in library(a))
    for bad in ("forward: v_forward/speed", "turn: 1/speed", "turn: w*1/speed"):
        with pytest.raises(LogError):
            parse([bad])
    cls = proposal_effect({"turn: w/speed": 0.03})
    assert np.allclose(cls(None).velocity(np.array([0.03]), v, ctx)[:, 2], v[:, 2] + 0.03 * got)
    assert equation({"turn: w/speed": 0.03}) == ["turn velocity (rad/s) += 0.03 w/speed"]


def motion_channels(turn_extra, seed: int = 0, steps: int = 3600, dt: float = 0.1) -> dict:
    """Motion residual channels of a car-like drive (1-2 m/s forward, a wandering turn rate) whose turn residual is
    ``turn_extra(v, w)`` plus white noise; the other axes noise only."""
    rng = np.random.default_rng(seed)
    t = np.arange(steps) * dt
    v = 1.2 + 0.5 * np.sin(2 * np.pi * t / 37) + 0.2 * rng.standard_normal(steps).cumsum() / np.sqrt(steps)
    v = np.clip(v, 0.4, 2.0)
    w = np.clip(np.convolve(rng.normal(0, 0.3, steps), np.ones(20) / np.sqrt(20), "same"), -1, 1)
    heading = np.cumsum(w * dt)
    x, y = np.cumsum(v * np.cos(heading) * dt), np.cumsum(v * np.sin(heading) * dt)
    cov = {"x": x, "y": y, "heading": heading, "time": t}
    vel = {"forward": v, "lateral": np.zeros(steps), "turn": w}
    extra = {"forward": 0.0, "lateral": 0.0, "turn": turn_extra(v, w)}
    span = np.full(steps, dt)
    return {a: Channel(a, np.zeros(steps), (extra[a] + rng.normal(0, 0.05, steps)) * span, t, cov,
                       command=vel[a], span=span) for a in ("forward", "lateral", "turn")}


def test_the_regression_tells_a_turn_over_the_speed_from_a_turn_times_the_speed():
    """Synthetic residuals: a turn term 0.03 w/v is proposed as ``w/speed`` (within 25 %), 0.03 w v as ``w*speed``."""
    over = propose(motion_channels(lambda v, w: 0.03 * w / v))["terms"]
    assert set(over) == {"turn: w/speed"} and over["turn: w/speed"] == pytest.approx(0.03, rel=0.25)
    times = propose(motion_channels(lambda v, w: 0.03 * w * v, seed=1))["terms"]
    assert set(times) == {"turn: w*speed"} and times["turn: w*speed"] == pytest.approx(0.03, rel=0.25)
    assert propose(motion_channels(lambda v, w: 0.0 * w, seed=2)) == {}


def test_a_library_term_repeating_another_is_left_out():
    """A robot that never reverses has speed = v_forward: one column of the two is kept, not both at half."""
    rng = np.random.default_rng(0)
    X = rng.normal(size=(60, 4))
    X[:, 2], X[:, 3] = 3 * X[:, 0] + 1, -X[:, 1]
    assert distinct(X, np.ones(4, bool)).tolist() == [True, True, False, False]
    assert distinct(X, np.array([False, True, True, True])).tolist() == [False, True, True, False]


def test_the_own_velocity_is_not_a_term_and_bad_terms_fail_in_one_line(tmp_path):
    assert "v_forward" not in library("forward") and "w" not in library("turn") and "v_forward" in library("turn")
    for bad in ("forward: v_forward", "sideways: x", "forward: x**2", "forward:x"):
        with pytest.raises(LogError):
            parse([bad])
    (tmp_path / "diag").mkdir()
    (tmp_path / "diag" / "diagnosis.json").write_text(json.dumps({"verdict": "none"}))
    with pytest.raises(LogError, match="proposed no effect"):
        from_diagnosis(tmp_path / "diag")
    log = tmp_path / "log"
    generate(log, kind="table", minutes=0.5, seed=1)
    assert main(["calibrate", str(log), "--out", str(tmp_path / "r"), "--effect", "proposal", "--quiet"]) == 2
    assert main(["calibrate", str(log), "--out", str(tmp_path / "r"), "--effect", "proposal", "--quiet",
                 "--proposal", str(tmp_path / "diag")]) == 2
    assert not (tmp_path / "r").exists()
    (tmp_path / "diag" / "diagnosis.json").write_text(json.dumps({"proposal": {"terms": {
        "forward: v_forward*cos(heading)": 0.05}}}))
    generate(tmp_path / "cont", kind="continuous", minutes=0.5, seed=1)       # continuous fits take it through its hook
    assert main(["calibrate", str(tmp_path / "cont"), "--out", str(tmp_path / "r"), "--effect", "proposal", "--quiet",
                 "--proposal", str(tmp_path / "diag")]) == 0
    got = json.loads((tmp_path / "r" / "model.json").read_text())["effects"]["proposal"]
    assert set(got) == {"forward: v_forward*cos(heading)"}


@pytest.mark.science
def test_a_heading_dependent_speed_is_proposed_added_and_the_error_falls(tmp_path):
    """Table world, seed 0, 6 minutes, s = 0.145 at phi = 2.17 rad; measured: proposal -0.039 v cos + 0.047 v sin
    (the smoothed trajectory takes part of it), fitted -0.088 / +0.117 (truth -0.082 / +0.120), position RMS
    0.039 -> 0.028 m, verdict none afterwards."""
    generate(tmp_path / "log", kind="table", minutes=6, seed=0, effect="heading_speed", min_range=0.8)
    truth = json.loads((tmp_path / "log" / "world_truth.json").read_text())
    s, phi = truth["strength"], truth["geometry"]["phi"]
    log = cg.load_log(tmp_path / "log")
    cal = cg.calibrate(log)
    diag = cg.diagnose(log, cal)
    assert diag.verdict.startswith("unexplained:"), diag.verdict
    terms = diag.proposal["terms"]
    assert set(terms) <= {"forward: v_forward*cos(heading)", "forward: v_forward*sin(heading)"}, terms
    assert "Add it with" in diag.summary()
    used = dataclasses.asdict(cg.ProposalOptions())       # recorded with it (found by the covariate tests or, when
    if diag.proposal["options"]["periods"] == 0:          # they pass, by the regression's own test without periods)
        used["periods"] = 0
    assert diag.proposal["options"] == used
    assert discover(diag.verdict, [], diag.residuals, cg.ProposalOptions(min_t=1e9))[2] == {}   # options passed in
    v, words, found = discover("none", ["fits"], diag.residuals, cg.ProposalOptions())   # the regression as last test
    assert v == "unexplained:heading" and found["terms"] == terms and "sparse regression" in words[0]
    assert discover("none", ["fits"], diag.residuals, cg.ProposalOptions(min_t=1e9)) == ("none", ["fits"], {})

    # a catalog verdict yields to the proposal only when the proposal, fitted, explains much more than it
    named = Candidate("battery_fade", "motion", -40.0, float("nan"), "", 25.0)
    asked = []

    def challenge(cls):
        asked.append(cls.params)
        return 60.0, -100.0
    v, words, found = discover("battery_fade", ["fade"], diag.residuals, cg.ProposalOptions(), [named],
                               challenge=challenge, ratio=2.0)
    assert v == "unexplained:heading" and asked == [tuple(found["terms"])]
    assert found["fitted"]["instead_of"]["effect"] == "battery_fade" and "battery_fade" in words[0]
    for gain, dbic in ((40.0, -60.0), (60.0, -44.0)):       # about the fade's gain; or within the look-alike margin
        assert discover("battery_fade", ["fade"], diag.residuals, cg.ProposalOptions(), [named],
                        challenge=lambda cls: (gain, dbic), ratio=2.0) == ("battery_fade", ["fade"], {})

    cal2 = cg.calibrate(log, effects=[diag.proposal_effect()])
    got = cal2.model.effects["proposal"]
    c, sn = got.get("forward: v_forward*cos(heading)", 0.0), got.get("forward: v_forward*sin(heading)", 0.0)
    assert np.hypot(c, sn) == pytest.approx(s, rel=0.25)
    assert abs(np.angle(np.exp(1j * (np.arctan2(sn, c) - phi)))) < 0.25

    def position_rms(k):
        tr = k.trajectory
        return float(np.sqrt(np.mean((tr["x"] - log.truth[:, 1]) ** 2 + (tr["y"] - log.truth[:, 2]) ** 2)))
    assert position_rms(cal2) < 0.85 * position_rms(cal)
    after = cg.diagnose(log, cal2, before=diag)
    assert after.verdict == "none"
    assert after.before_after["channels"]["forward"]["rms_raw"][1] < 0.6 * after.before_after["channels"]["forward"]["rms_raw"][0]


@pytest.mark.science
def test_a_turn_rate_growing_with_speed_is_proposed_not_named_a_fade(tmp_path):
    """Continuous world, seed 1, 4 minutes: turn += 0.152 x forward speed. By default the calibration's turn map
    holds it (its term in v kept, within 25 %). In the paper's form (``cross_terms=False``) the battery fade's fit
    has the robot faster at the log's end, not physical, and the turn residuals' binned structure is against time;
    the proposal, every term weighed together, puts it on the speed: unexplained:speed, turn += 0.126 speed; once
    added the heading error falls and the next verdict is none (benchmarks/proposal.py --kind continuous).
    CI tries the catalog effects that took such verdicts; ``CASM_FULL=1`` every candidate."""
    candidates = None if FULL else ["battery_fade", "surface_friction"]
    generate(tmp_path / "log", kind="continuous", minutes=4, seed=1, effect="speed_turn", min_range=0.8)
    gain = json.loads((tmp_path / "log" / "world_truth.json").read_text())["geometry"]["gain"]
    log = cg.load_log(tmp_path / "log")
    held = cg.calibrate(log).model.fit["cross_term"]
    assert held["kept"] and held["w_per_v"] == pytest.approx(gain, rel=0.25), (held, gain)
    cal = cg.calibrate(log, cross_terms=False)
    diag = cg.diagnose(log, cal, candidates=candidates)
    assert diag.verdict == "unexplained:speed", diag.verdict
    assert next(c for c in diag.candidates if c.effect == "battery_fade").implausible
    assert set(diag.proposal["terms"]) == {"turn: speed"}
    cal2 = cg.calibrate(log, effects=[diag.proposal_effect()], cross_terms=False)
    assert cal2.model.effects["proposal"]["turn: speed"] == pytest.approx(gain, rel=0.25)

    def heading_rms(k):
        return float(np.sqrt(np.mean(np.angle(np.exp(1j * (k.trajectory["theta"] - log.truth[:, 3]))) ** 2)))
    assert heading_rms(cal2) < heading_rms(cal)
    assert cg.diagnose(log, cal2, candidates=candidates).verdict == "none"
