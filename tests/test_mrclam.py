"""Issue 7: the MRCLAM importer, the continuous-command factor and model, and a short real calibration.

The data are the real run-7 files in ../shared/data/mrclam7 (CASM_MRCLAM overrides the place).
"""
import json
import os

import numpy as np
import pytest

import factors
from casm_graph.analysis import groundtruth
from casm_graph.analysis.diagnosis import BIC_SUPPORT
from casm_graph.cli import main
from casm_graph.fit import continuous as CT
from casm_graph.io import mrclam
from casm_graph.io.log import load
from casm_graph.models.command_model import CommandModel, for_commands
from casm_graph.models.model import Model
from casm_graph.pipeline import calibrate as calibrate_run
from casm_graph.pipeline import diagnose as diagnose_run
from casm_graph.sim.protocols import write_log

DATA = mrclam.find_data()
needs_data = pytest.mark.skipif(not (DATA / "Robot1_Odometry.dat").is_file(), reason=f"no MRCLAM data at {DATA}")
FULL = os.environ.get("CASM_FULL") == "1"


@pytest.fixture(scope="module")
def robot1(tmp_path_factory):
    out = tmp_path_factory.mktemp("mrclam") / "robot1"
    assert main(["import-mrclam", str(DATA), "--robot", "1", "--out", str(out)]) == 0
    return out


@needs_data
def test_import_keeps_landmarks_only_and_truth_at_pose_times(robot1):
    log = load(robot1)
    assert log.control_names == ("v", "w") and log.action is None
    raw = np.loadtxt(DATA / "Robot1_Measurement.dat", comments="#")
    bar = np.loadtxt(DATA / "Barcodes.dat", comments="#").astype(int)
    robot_codes = set(bar[bar[:, 0] <= 5, 1].tolist())
    is_mark = np.array([int(b) not in robot_codes for b in raw[:, 1]])
    assert len(log.obs_t) == int(is_mark.sum())          # robot 1's sightings all fall inside its commands
    assert set(np.unique(log.obs_landmark)) <= set(range(6, 21))
    assert np.allclose(np.sort(log.obs_reading), np.sort(raw[is_mark, 2]))
    assert log.truth.shape == (log.steps + 1, 4)
    gt = np.loadtxt(DATA / "Robot1_Groundtruth.dat", comments="#")
    epoch = json.loads((robot1 / "mrclam.json").read_text())["epoch"]
    i = log.steps // 2
    j = np.argmin(np.abs(gt[:, 0] - epoch - log.t[i]))
    assert np.hypot(*(log.truth[i, 1:3] - gt[j, 1:3])) < 0.02


@needs_data
def test_import_bad_input_exit_2_nothing_written(tmp_path, capsys):
    out = tmp_path / "none"
    assert main(["import-mrclam", str(tmp_path), "--robot", "1", "--out", str(out)]) == 2
    assert "Barcodes.dat: missing file" in capsys.readouterr().err
    assert not out.exists()
    assert main(["import-mrclam", str(DATA), "--robot", "7", "--out", str(out)]) == 2
    assert not out.exists()


def test_command_factor_jacobians_match_numerical():
    rng = np.random.default_rng(4)
    n, k = 5, 7
    a = rng.normal(size=(n, 3))
    b = a + rng.normal(scale=0.3, size=(n, 3))
    cm = for_commands(rng.uniform(-0.5, 0.5, size=(50, 2)), 2, 1)
    ctl = rng.uniform(-0.5, 0.5, size=(n * k, 2))
    bv, _, bw = cm.basis(ctl)
    Bv, Bw = bv.reshape(n, k, -1), bw.reshape(n, k, -1)
    dt = rng.uniform(0.05, 0.2, size=(n, k))
    dt[0, 4:] = 0.0                                      # padding
    p = rng.normal(scale=0.5, size=cm.params.shape)
    e, (Ha, Hb, Hp) = factors.command.error(a, b, p, Bv, Bw, dt)
    h = 1e-6
    for i in range(len(p)):
        d = np.zeros_like(p)
        d[i] = h
        num = (factors.command.error(a, b, p + d, Bv, Bw, dt)[0] - factors.command.error(a, b, p - d, Bv, Bw, dt)[0]) / (2 * h)
        assert np.allclose(Hp[:, :, i], num, atol=1e-6)

    def moved(x, j, eps):            # body-frame tangent step, as GTSAM's Pose2 retract to first order
        c, s = np.cos(x[:, 2]), np.sin(x[:, 2])
        t = np.zeros(3)
        t[j] = eps
        return np.column_stack([x[:, 0] + c * t[0] - s * t[1], x[:, 1] + s * t[0] + c * t[1], x[:, 2] + t[2]])

    for j in range(3):
        na = (factors.command.error(moved(a, j, h), b, p, Bv, Bw, dt)[0] - factors.command.error(moved(a, j, -h), b, p, Bv, Bw, dt)[0]) / (2 * h)
        nb = (factors.command.error(a, moved(b, j, h), p, Bv, Bw, dt)[0] - factors.command.error(a, moved(b, j, -h), p, Bv, Bw, dt)[0]) / (2 * h)
        assert np.allclose(Ha[:, :, j], na, atol=1e-5) and np.allclose(Hb[:, :, j], nb, atol=1e-5)


def test_command_model_json_round_trip(tmp_path):
    cm = CommandModel(scale=(0.1, 0.5), v_coef=np.array([0.0, 0.08, -0.01]), w_coef=np.array([0.01, 0.45]),
                      v_std=np.array([0.001, 0.002, 0.003]), w_std=np.array([0.01, 0.02]),
                      command_range=((0.0, 0.1), (-0.5, 0.5)))
    m = Model(action_ids=np.array([], int), velocities=np.zeros((0, 3)), reading_poly=np.array([0.0, 1.0]),
              reading_sigma=0.05, bearing_sigma=0.02, command=cm)
    m.save(tmp_path / "model.json")
    data = json.loads((tmp_path / "model.json").read_text())
    assert data["action_model"]["kind"] == "command_poly"
    back = Model.load(tmp_path / "model.json").command
    ctl = np.array([[0.05, 0.2], [0.1, -0.5]])
    assert np.allclose(back.velocities(ctl), cm.velocities(ctl))
    assert np.allclose(cm.velocities(ctl)[:, 1], 0.0)                  # wheeled: no sideways motion


def test_truth_fit_recovers_the_map_of_a_dead_reckoned_path():
    """Poses generated by a known map are fitted back to that map (the reference the calibration is judged by)."""
    from casm_graph.io.log import Log
    rng = np.random.default_rng(2)
    T = 3000
    t = np.arange(T) * 0.01
    ctl = np.column_stack([np.repeat(rng.choice([0.0, 0.04, 0.07, 0.09], T // 100), 100),
                           np.repeat(rng.choice([-0.4, 0.0, 0.4], T // 100), 100)])
    true = for_commands(ctl, 2, 1).with_params(np.array([0.0, 0.12, -0.04, 0.01, 0.37]))
    mdl = Model(action_ids=np.array([], int), velocities=np.zeros((0, 3)), reading_poly=np.zeros(2),
                reading_sigma=1.0, bearing_sigma=1.0, command=true)
    poses = CT.dead_reckon(ctl, np.full(T, 0.01), mdl, np.zeros(3))
    log = Log(landmark_ids=np.array([1]), landmark_xy=np.zeros((1, 2)), t=t, action=None, controls=ctl,
              control_names=("v", "w"), obs_t=np.array([0.0]), obs_landmark=np.array([1]),
              obs_reading=np.array([1.0]), obs_bearing=np.array([0.0]),
              truth=np.column_stack([np.append(t, t[-1] + 0.01), poses]))
    got = groundtruth.truth_fit(log, for_commands(ctl, 2, 1))
    assert np.allclose(got.velocities(ctl), true.velocities(ctl), atol=2e-4)


def _against_vicon(bundle, run):
    """Map errors of RUN/model.json against the same map form fitted on Vicon, and the trajectory's RMS."""
    log, fit_model = load(bundle), Model.load(run / "model.json")
    ref = groundtruth.truth_fit(log, fit_model.command)
    err = groundtruth.map_errors(fit_model.command, ref, log.controls, log.dt)
    traj = np.loadtxt(run / "trajectory.csv", delimiter=",", skiprows=1, usecols=(1, 2))
    return err, float(np.sqrt(np.mean(np.sum((traj - log.truth[:, 1:3]) ** 2, axis=1))))


@needs_data
@pytest.mark.science
def test_short_window_calibration_of_robot1_against_vicon(robot1, tmp_path):
    """A window of robot 1 (2 min in CI; CASM_FULL=1: the whole log) through `calibrate`, judged against Vicon."""
    log = load(robot1)
    if not FULL:
        from casm_graph.io.log import write
        write(log.window(0.0, 120.0), tmp_path / "win")
        robot1 = tmp_path / "win"
    run = tmp_path / "run"
    assert main(["calibrate", str(robot1), "--out", str(run), "--quiet"]) == 0
    model = json.loads((run / "model.json").read_text())
    assert model["action_model"]["kind"] == "command_poly"
    assert (run / "report.html").stat().st_size > 10_000
    err, pos = _against_vicon(robot1, run)
    print(f"turn map {100 * err['w']['fraction']:.1f} % of range, speed map {100 * err['v']['fraction']:.1f} %, "
          f"position RMS {pos:.3f} m")
    # measured bounds of the base model (no effects; the issue's targets are met with the effects the
    # diagnosis finds, see test_issue7_targets_...). A 2-minute window holds too few sightings to pin
    # the trajectory (~1.3 m RMS); the whole log reaches ~0.25 m.
    assert err["w"]["fraction"] < 0.15
    assert pos < (0.4 if FULL else 2.0)


@needs_data
@pytest.mark.science
def test_robot4_whole_log_lands_in_the_right_basin(tmp_path):
    """Robot 4 has the fewest sightings (1822); before the command-map prior was centred on the
    nominal map it ran to 0.12 m/s at zero command (speed map 120 % of range off, 4.46 m RMS), and
    until the coarse graph held the maps for its first rounds it did so again on an AMD EPYC host
    (speed map 130.9 % off, 4.46 m; log-likelihood 22,036 against 42,665 in the right basin). On an
    AVX-512 host the best-agreeing start slope then led to 21.9 % (40,959); the three best slopes are
    now each taken through the held rounds and the likeliest goes on (6.5 %, 44,762)."""
    bundle = tmp_path / "robot4"
    assert main(["import-mrclam", str(DATA), "--robot", "4", "--out", str(bundle)]) == 0
    run = tmp_path / "run"
    assert main(["calibrate", str(bundle), "--out", str(run), "--quiet"]) == 0
    err, pos = _against_vicon(bundle, run)
    assert len(json.loads((run / "model.json").read_text())["fit"]["start_slopes"]) == 3
    print(f"robot 4: turn map {100 * err['w']['fraction']:.1f} %, speed map {100 * err['v']['fraction']:.1f} %, "
          f"position RMS {pos:.3f} m")
    # measured 0.8 %, 6.5 %, 0.498 m (2026-11-25, three start slopes); the identity-model graph 0.695 m
    assert err["w"]["fraction"] < 0.05
    assert err["v"]["fraction"] < 0.20
    assert pos < 1.0


@needs_data
def test_graph_em_weighs_wild_sightings_as_its_e_step_does():
    """graph-EM's E-step smooths through Huber's loss; its M-step set the sigmas from the plain mean of the
    expected squared residuals, so on robot 4's first four minutes the bearing sigma grew to 0.0130 rad (graph:
    0.0038) and EM steps lowered the marginal likelihood by up to 12 nats, ending below its start (2,440 against
    2,471). Weighed as the E-step weighs them, every EM step raises it (measured: 2,471 to 2,636, bearing sigma
    0.0033)."""
    whole, _ = mrclam.load_robot(DATA, 4)
    log = whole.window(whole.t[0], whole.t[0] + 240.0)
    em = calibrate_run.calibrate(log, method="graph-em")
    graph = calibrate_run.calibrate(log)
    h = np.array(em.fit.notes["history"]["log_likelihood"])
    em_steps = [(h[i], h[i + 1]) for i in range(0, len(h) - 1, 3)]     # SQUAREM: two EM steps, then a trial
    assert all(b >= a - 0.5 for a, b in em_steps), em_steps
    assert h[-1] > h[0] + 50
    assert em.model.bearing_sigma < 1.5 * graph.model.bearing_sigma


@needs_data
def test_graph_em_agrees_with_graph_on_a_log_whose_steps_vary_in_length():
    """MRCLAM's odometry steps run 0.01 s to 1 s (a tenth of the time in steps over 0.05 s). graph-em's step graph
    gave every step the noise of one median step and its M-step weighed a one-second step's displacement as much as
    a hundred short ones, so on robot 1's first five minutes its speed map ended 9.4 % of the velocity range from
    graph's (the issue's bound: 5 %). With the noise grown with each step's time, as graph's motion factors have it,
    and each step weighed by 1 / its length in the regression: 2.4 %."""
    whole, _ = mrclam.load_robot(DATA, 1)
    log = whole.window(whole.t[0], whole.t[0] + 300.0)
    v = {m: calibrate_run.calibrate(log, method=m).model.command.velocities(log.controls, log.dt)
         for m in ("graph", "graph-em")}
    speed_turn = [0, 2]                      # a v,w robot has no sideways velocity
    apart = (np.sqrt(np.mean((v["graph-em"] - v["graph"])[:, speed_turn] ** 2, axis=0))
             / np.ptp(v["graph"][:, speed_turn], axis=0))
    assert np.all(apart < 0.05), apart


@needs_data
def test_the_paper_s_filters_set_aside_the_wild_sightings_graph_em_does():
    """The paper's innovation test, judged against the filter's covariance at its loose start, set aside none of
    robot 5's wild sightings, and on its first five minutes EKFS-EM's smoothed path lay 0.84 m RMS from Vicon's
    (graph's: 0.18 m). With graph-em's gross outliers set aside first (88 sightings): 0.57 m, its speed map 14.6 %
    of the range from graph-em's; with the paper's Sigma_A per 1/30 s carried to the log's 0.01-s steps (taken per
    step it is a heading noise of 1 rad per square-root second): 0.24 m and 1.8 %."""
    whole, _ = mrclam.load_robot(DATA, 5)
    log = whole.window(whole.t[0], whole.t[0] + 300.0)
    em = calibrate_run.calibrate(log, method="graph-em")
    ekfs = calibrate_run.calibrate(log, method="ekfs-em")
    assert ekfs.model.fit["outliers_pruned"] >= em.model.fit["outliers_pruned"] > 0
    tr = ekfs.trajectory
    assert np.sqrt(np.mean((tr["x"] - log.truth[:, 1]) ** 2 + (tr["y"] - log.truth[:, 2]) ** 2)) < 0.4
    ve, vg = (c.model.command.velocities(log.controls, log.dt) for c in (ekfs, em))
    apart = np.sqrt(np.mean((ve - vg) ** 2, axis=0))[[0, 2]] / np.ptp(vg, axis=0)[[0, 2]]
    assert np.all(apart < 0.05), apart


@needs_data
@pytest.mark.science
@pytest.mark.parametrize("robot", [1, 2, 3, 4, 5] if FULL else [1])
def test_issue7_targets_with_the_effects_the_diagnosis_finds(robot, tmp_path):
    """Whole log: calibrate, diagnose, add every strongly supported candidate, judge against Vicon.

    The issue's targets: turn map < 5 % and speed map < 10 % of range, position RMS at most half the
    identity-model graph's. CI runs the first 5.2 of robot 1's 14.9 minutes with the two effects the diagnosis
    finds on every robot (turn 0.3 %, speed 2.5 %, 0.069 m against 0.271 m; whole log: 0.2 %, 2.5 %, 0.062 m
    against 0.246 m); CASM_FULL=1 runs the diagnosis itself on all five whole logs.
    """
    bundle = tmp_path / f"robot{robot}"
    assert main(["import-mrclam", str(DATA), "--robot", str(robot), "--out", str(bundle)]) == 0
    if not FULL:
        whole = load(bundle)
        bundle = tmp_path / f"robot{robot}-5min"
        write_log(whole.window(whole.t[0], whole.t[0] + 312.0), bundle)
    if FULL:
        _, base = calibrate_run.run(bundle, tmp_path / "base")
        diag = diagnose_run.run(bundle, tmp_path / "base" / "model.json", tmp_path / "diag")
        added = [c.effect for c in diag.candidates if c.delta_bic <= BIC_SUPPORT]
        assert "lens_distortion" in added
    else:
        added = ["lens_distortion", "actuator_lag"]
    _, fit = calibrate_run.run(bundle, tmp_path / "run", effects=added)
    ev = groundtruth.evaluate(load(bundle), fit)
    me, pr = ev["map_error"], ev["position_rms"]
    print(f"robot {robot} with {added}: turn map {100 * me['w']['fraction']:.1f} %, speed map "
          f"{100 * me['v']['fraction']:.1f} %, position {pr['calibrated_graph']:.3f} m vs identity-model graph "
          f"{pr['identity_graph']:.3f} m (ratio {ev['ratio_to_identity']:.2f}), effects {fit.model.effects}")
    assert ev["meets"] == {"turn": True, "speed": True, "half_identity": True}


@needs_data
@pytest.mark.science
def test_a_user_effect_and_catalog_effects_fit_on_a_real_robot(robot1, tmp_path):
    """Issue 20: the docs' user-written HeadingSlip and two catalog effects through ``cg.calibrate`` on robot 1's
    first 4 minutes (continuous commands): finite values with their std in model.json, a log-likelihood no lower
    than without them."""
    import casm_graph as cg
    from tests.test_api import HeadingSlip          # the README's own effect

    whole = load(robot1)
    log = whole.window(whole.t[0], whole.t[0] + 240.0)
    base = cg.calibrate(log)
    cal = cg.calibrate(log, effects=[HeadingSlip, "battery_fade", "camera_latency"])
    std = cal.model.fit["effects_std"]
    for name, param in (("heading_slip", "k"), ("battery_fade", "loss_per_minute"), ("camera_latency", "delay")):
        value = cal.model.effects[name][param]
        assert np.isfinite(value) and 0 < std[name][param] < 1.0, (name, value, std[name][param])
    assert abs(cal.model.effects["heading_slip"]["k"]) < 0.2          # the robot has no carpet
    assert cal.fit.log_likelihood > base.fit.log_likelihood - 10
    cal.save(tmp_path / "run")
    saved = json.loads((tmp_path / "run" / "model.json").read_text())
    assert set(saved["effects"]) == {"heading_slip", "battery_fade", "camera_latency"}
