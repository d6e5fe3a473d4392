"""The actuator_lag effect on continuous-command logs and ``diagnose`` for them (issue 7, item 4).

A floor log (simulate_floor) whose robot follows its (v, w) commands through a known first-order
lag: ``diagnose`` ranks the lag first with its mean delay near the truth, and reports
the residual channels (the lag written by calibrate: tests/test_hooked_effects.py, on the independent world). Another floor's range reads long or short with the
square of the bearing (a lens): ``calibrate --effect lens_distortion`` finds its coefficient.
"""
import json
from dataclasses import replace

import numpy as np
import pytest

import casm_graph as cg
from casm_graph.cli import main
from casm_graph.fit import continuous as CT
from casm_graph.graph.problem import Problem, State
from casm_graph.graph import robust
from casm_graph.io.log import LogError, write
from casm_graph.models.command_model import CommandModel, lagged
from casm_graph.models.model import Model
from casm_graph.sim.floor import FloorConfig, simulate

TRUE_LAG = 0.3


def test_first_order_lag_recursion_and_steady_state():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(200, 3))
    dt = rng.uniform(0.005, 0.02, 200)
    y = lagged(x, dt, 0.1)
    ref, end = x.copy(), x[0].copy()
    for k in range(1, 200):                  # each row: the mean over its step of the lag's exact response
        a = np.exp(-dt[k] / 0.1)
        ref[k] = x[k] + (end - x[k]) * 0.1 / dt[k] * (1 - a)
        end = a * end + (1 - a) * x[k]
    assert np.allclose(y, ref)
    step = lagged(np.r_[np.zeros(10), np.ones(2000)][:, None], np.full(2010, 0.01), 0.1)
    assert step[19, 0] == pytest.approx(1 - 10 * (np.exp(-0.9) - np.exp(-1.0)))   # mean over 0.09-0.1 s after the jump
    assert step[-1, 0] == pytest.approx(1.0)
    cm = CommandModel(scale=(0.1, 0.5), v_coef=np.array([0.0, 0.1]), w_coef=np.array([0.0, 0.5]), lag=0.2)
    ctl = rng.uniform(-0.1, 0.1, size=(50, 2))
    assert np.allclose(cm.velocities(ctl), replace(cm, lag=0.0).velocities(ctl))   # no dt: the steady-state map
    assert not np.allclose(cm.velocities(ctl, np.full(50, 0.01)), cm.velocities(ctl))


def test_two_stage_lag_is_two_cascaded_stages_with_the_same_mean_delay():
    """Order 2: the first-order recursion applied twice with half the time constant, so ``lag`` stays the mean
    delay (the area above a unit step's response) whatever the order."""
    rng = np.random.default_rng(1)
    x, dt = rng.normal(size=(300, 2)), rng.uniform(0.005, 0.02, 300)
    assert np.allclose(lagged(x, dt, 0.2, order=2), lagged(lagged(x, dt, 0.1), dt, 0.1))
    unit = np.r_[np.zeros(10), np.ones(4000)][:, None]
    for order in (1, 2):
        step = lagged(unit, np.full(4010, 0.001), 0.3, order=order)
        assert np.sum(1 - step[10:, 0]) * 0.001 == pytest.approx(0.3, rel=0.01)
    s1, s2 = (lagged(unit, np.full(4010, 0.001), 0.3, order=o)[:, 0] for o in (1, 2))
    assert s2[10 + 30] < s1[10 + 30] and np.all(np.diff(s2[10:]) >= 0)     # slower start, no overshoot


def test_lag_order_survives_model_json_and_a_bad_one_is_refused(tmp_path):
    cm = CommandModel(scale=(0.1, 0.5), v_coef=np.array([0.0, 0.1]), w_coef=np.array([0.0, 0.5]), lag=0.25,
                      lag_order=2)
    m = Model(action_ids=np.array([], int), velocities=np.zeros((0, 3)), reading_poly=np.array([0.0, 1.0]),
              reading_sigma=0.05, bearing_sigma=0.02, command=cm)
    m = CT.with_effect(m, "actuator_lag", 0.25, order=2)
    m.save(tmp_path / "model.json")
    data = json.loads((tmp_path / "model.json").read_text())
    assert data["action_model"]["lag_order"] == 2 and data["effects"]["actuator_lag"] == {"tau": 0.25, "order": 2}
    back = Model.load(tmp_path / "model.json")
    assert back.command.lag_order == 2 and back.command.lag == 0.25
    assert CT.with_effect(back, "actuator_lag", 0.0).command.lag_order == 1          # off: no stages left
    with pytest.raises(ValueError, match="not profiled"):             # a lens acts through its hook, not a profile
        CT.with_effect(back, "lens_distortion", 0.1)
    data["action_model"]["lag_order"] = 3
    (tmp_path / "bad.json").write_text(json.dumps(data))
    with pytest.raises(ValueError, match="lag_order"):
        Model.load(tmp_path / "bad.json")


def test_lag_survives_model_json(tmp_path):
    cm = CommandModel(scale=(0.1, 0.5), v_coef=np.array([0.0, 0.1]), w_coef=np.array([0.0, 0.5]), lag=0.25)
    m = Model(action_ids=np.array([], int), velocities=np.zeros((0, 3)), reading_poly=np.array([0.0, 1.0]),
              reading_sigma=0.05, bearing_sigma=0.02, command=cm)
    m.save(tmp_path / "model.json")
    assert json.loads((tmp_path / "model.json").read_text())["action_model"]["lag"] == 0.25
    assert Model.load(tmp_path / "model.json").command.lag == 0.25


@pytest.fixture(scope="module")
def lag_floor(tmp_path_factory):
    """Seed 2's floor with the lag (on seed 0 the profile finds 0.11 s and the latency ranks first: BENCHMARKS.md,
    "Continuous-command effects on simulated floors", has every seed)."""
    log, truth = simulate(FloorConfig(minutes=4, seed=2, dt=0.1, lag=TRUE_LAG))
    d = tmp_path_factory.mktemp("floorlag")
    write(log, d)
    return d, log


@pytest.mark.science
def test_diagnose_a_continuous_log(lag_floor, tmp_path):
    d, _ = lag_floor
    assert main(["calibrate", str(d), "--out", str(tmp_path / "run"), "--quiet"]) == 0
    assert main(["diagnose", str(d), "--model", str(tmp_path / "run" / "model.json"), "--out",
                 str(tmp_path / "diag"), "--quiet"]) == 0
    diag = json.loads((tmp_path / "diag" / "diagnosis.json").read_text())
    assert set(diag["channels"]) == {"forward", "lateral", "turn", "reading", "bearing"}
    lag = diag["candidates"][0]                              # most supported first
    assert lag["effect"] == "actuator_lag" and lag["delta_bic"] < -10
    assert {c["effect"] for c in diag["candidates"]} == {"actuator_lag", "lens_distortion", "battery_fade",
                                                          "camera_latency", "landmark_offset", "range_dependent_noise",
                                                          "surface_friction", "false_detections"}
    assert lag["parameters"]["tau"] == pytest.approx(TRUE_LAG, rel=0.25)
    assert lag["parameters"].get("order", 1) == 2            # the floor's discrete stage, half a step ahead of the
                                                             # model's step mean, reads as two (BENCHMARKS.md)
    assert lag["heldout_nll_drop"] is None and "continuous" in lag["heldout_skipped"]
    assert "nan" not in " ".join(diag["summary"])            # an unmeasured held-out score is said so, not printed
    false = next(c for c in diag["candidates"] if c["effect"] == "false_detections")
    assert false["delta_bic"] > 0 and false["heldout_nll_drop"] is not None     # scored on folds; none to find
    assert "sighting_change" not in false                    # scored at the base's poses: it moves no sighting
    assert 0.0 < lag["sighting_change"] < 10.0               # how far the lag moves the predicted sightings, in sigmas
    pred = diag["predictive"]                                # open-loop error grows with the horizon
    assert pred["horizons_s"][0] == 0 and set(pred["channels"]) == {"reading", "bearing"}
    assert all(v[-1] > v[0] for v in pred["channels"].values())
    friction = next(c for c in diag["candidates"] if c["effect"] == "surface_friction")
    assert set(friction["orders"]) == {"0", "1", "2", "3", "4"}                 # every member fitted, the best kept
    assert friction["delta_bic"] == friction["orders"][str(friction["order"])]
    if "confirmed" not in friction:                          # else the member BIC keeps on the calibration's graph
        assert friction["delta_bic"] == min(friction["orders"].values())
    shown = "surface_friction" + (f":{friction['order']}" if friction["order"] != 4 else "")   # 4 x 4: the default
    assert f"<td style='text-align:left'>{shown}</td>" in (tmp_path / "diag" / "report.html").read_text()
    assert (tmp_path / "diag" / "report.html").stat().st_size > 10_000
    assert f"<td>{lag['sighting_change']:.3f}</td>" in (tmp_path / "diag" / "report.html").read_text()


def test_a_motion_noise_effect_other_than_regional_is_refused_on_continuous_logs(lag_floor):
    class Jitter(cg.Effect):
        name, channel, params, start, scale, noise_only = "jitter", "motion", ("k",), (0.1,), (0.1,), True

    d, _ = lag_floor
    with pytest.raises(LogError, match="a motion noise effect"):
        cg.calibrate(cg.load_log(d), effects=[Jitter])


def test_diagnose_refuses_a_table_model_on_a_continuous_log(lag_floor, tmp_path, capsys):
    d, _ = lag_floor
    m = Model(action_ids=np.array([1]), velocities=np.zeros((1, 3)), reading_poly=np.array([0.0, 1.0]),
              reading_sigma=0.05, bearing_sigma=0.02)
    m.save(tmp_path / "model.json")
    assert main(["diagnose", str(d), "--model", str(tmp_path / "model.json"), "--out", str(tmp_path / "diag"),
                 "--quiet"]) == 2
    assert "no command map" in capsys.readouterr().err
    assert not (tmp_path / "diag").exists()


def test_lens_rows_jacobian_matches_numerical():
    """The lens acts through its own hook on continuous logs (a fixed camera: the image angle is the bearing); the
    reading rows' Jacobians over the poses, the polynomial and k match central differences."""
    log, _ = simulate(FloorConfig(minutes=0.5, seed=3, dt=0.1, lens_k=-0.1))
    m = CT.start_model(log).with_(reading_poly=np.array([0.02, 1.01, 0.0, -0.001]), reading_sigma=10.0,
                                  effects={"lens_distortion": {"k": -0.15}})
    effects = CT.hooked_effects(log, m)
    assert [e.name for e in effects] == ["lens_distortion"]
    lay = CT.layout(log, CT.DEFAULTS.coarse_knot_dt)
    problem = Problem(log, m, effects, lay=lay, poses=log.truth[lay.knots, 1:] + 0.01)
    st = problem.state(log.truth[lay.knots, 1:] + 0.01, m)
    r = problem.rows(st)
    re, Jp, Jt = r.reading_e, r.reading_J[0], r.reading_J[1]
    na, D = problem.n_action, problem.D
    Jc, Jm = Jt[:, na:na + D], Jt[:, na + D:]
    assert np.all(robust.huber(re) == 1.0)         # a wide sigma keeps every row inside Huber's core

    def reading_rows(poses=st.poses, poly=st.poly, theta=st.theta):
        return problem.rows(State(poses, st.params, poly, theta)).reading_e

    h = 1e-6
    for j in range(3):                  # body-frame tangent step, as GTSAM's Pose2 retract to first order
        def moved(eps):
            P = st.poses
            c, s = np.cos(P[:, 2]), np.sin(P[:, 2])
            t = np.zeros(3)
            t[j] = eps
            return np.column_stack([P[:, 0] + c * t[0] - s * t[1], P[:, 1] + s * t[0] + c * t[1], P[:, 2] + t[2]])
        num = (reading_rows(poses=moved(h)) - reading_rows(poses=moved(-h))) / (2 * h)
        assert np.allclose(Jp[:, j], num, atol=1e-6)
    for i in range(len(st.poly)):
        d = np.zeros_like(st.poly)
        d[i] = h
        num = (reading_rows(poly=st.poly + d) - reading_rows(poly=st.poly - d)) / (2 * h)
        assert np.allclose(Jc[:, i], num, atol=1e-6)
    num = (reading_rows(theta=st.theta + h) - reading_rows(theta=st.theta - h)) / (2 * h)
    assert np.abs(num).max() > 1e-3 and np.allclose(Jm[:, 0], num, atol=1e-6)


@pytest.mark.science
def test_calibrate_finds_a_lens(tmp_path):
    log, _ = simulate(FloorConfig(minutes=2, seed=1, dt=0.1, lens_k=-0.1, detect_prob=0.4))
    write(log, tmp_path / "lens")
    assert main(["calibrate", str(tmp_path / "lens"), "--out", str(tmp_path / "run"), "--effect", "lens_distortion",
                 "--quiet"]) == 0
    k = json.loads((tmp_path / "run" / "model.json").read_text())["effects"]["lens_distortion"]["k"]
    assert k == pytest.approx(-0.1, abs=0.03), k        # 2 minutes: -0.1014 (4-minute profiles: -0.098 to -0.102)


def test_the_em_methods_take_effects_on_continuous_commands(tmp_path):
    """As on action tables, effects start from the fit of the method asked for: on a continuous-command log of the
    independent world, a second-order actuator lag made by its physics is found from EKFS-EM's fit as from the
    graph's (the EM fit settled on the full graph before the lag's profile reads its poses)."""
    from tests.worlds.independent_world import generate

    truth = generate(tmp_path / "log", kind="continuous", minutes=2, seed=1, effect="actuator_lag")
    log = cg.load_log(tmp_path / "log")
    delay = 2 * truth["strength"]                     # two stages of the drawn time constant
    graph = cg.calibrate(log, effects=["actuator_lag"]).model.effects["actuator_lag"]
    em = cg.calibrate(log, method="ekfs-em", effects=["actuator_lag"]).model.effects["actuator_lag"]
    assert em["order"] == graph["order"] == 2
    assert abs(em["tau"] - graph["tau"]) < 0.01 and abs(em["tau"] - delay) < 0.2 * delay
