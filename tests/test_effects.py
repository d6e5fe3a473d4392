"""The effect catalog: simulator switches, the effect graph's Jacobians and solver, and fitting each effect."""
import warnings

import gtsam
import numpy as np
import pytest
from scipy.integrate import quad

import casm_graph as cg
from casm_graph.fit import effect_fit
from casm_graph.fit.solve import _damping
from casm_graph.graph import augmented as AU
from casm_graph.graph.problem import THETA, Problem
from casm_graph.models.effects import REGISTRY, catalog, get, of_model, spec, unphysical
from casm_graph.models.effects.base import held
from casm_graph.models.effects.surface_friction import NODES, bilinear, extent_around, patch_start
from casm_graph.models.model import Model, paper_start
from casm_graph.sim.aibo import SimConfig, simulate

ALL = sorted(REGISTRY)
TABLE = [n for n in ALL if not REGISTRY[n].continuous_only]      # effects the action-table simulator and graph take


def true_model(log, truth):
    m = paper_start(log)
    tv = np.array([truth["action_model"]["velocities"][str(a)] for a in m.action_ids])
    return m.with_(velocities=tv, reading_poly=np.array(truth["sensor_model"]["reading_poly_best_cubic"]),
                   reading_sigma=1.0, bearing_sigma=0.5, motion_noise=np.array([0.002, 0.002, 0.004]))


@pytest.fixture(scope="module")
def short():
    log, truth = simulate(SimConfig(minutes=1, seed=3))
    return log, true_model(log, truth)


def test_catalog_names_follow_the_interface():
    assert TABLE == sorted(["battery_fade", "surface_friction", "actuator_lag", "camera_latency",
                            "lens_distortion", "range_dependent_noise", "false_detections", "landmark_offset"])
    assert set(ALL) - set(TABLE) == {"regional_motion_noise"}      # continuous commands only (issue 6)
    for c in catalog():
        assert c["channel"] in ("motion", "sensor") and c["physics"].endswith(".") and c["parameters"]


@pytest.mark.parametrize("name", TABLE)
def test_simulator_switch_changes_the_log_and_records_the_truth(name):
    base, _ = simulate(SimConfig(minutes=1, seed=4))
    log, truth = simulate(SimConfig(minutes=1, seed=4, effects={name: 0.3}))
    assert name in truth["effects"] and truth["effects"][name]
    if REGISTRY[name].channel == "motion":
        assert np.abs(log.truth[-1, 1:3] - base.truth[-1, 1:3]).max() > 0.01
        np.testing.assert_array_equal(log.action[:150], base.action[:150])
    else:
        np.testing.assert_array_equal(log.truth, base.truth)
        if len(log.obs_t) == len(base.obs_t):
            changed = (log.obs_reading != base.obs_reading) | (log.obs_bearing != base.obs_bearing) \
                | (log.obs_landmark != base.obs_landmark)
            assert changed.mean() > 0.01


def _theta_for(problem, rng):
    th = problem.theta_noise.copy()
    for e, s in zip(problem.effects, problem.slices):
        th[s] = np.asarray(e.start) + rng.normal(0, 5, s.stop - s.start) * np.asarray(e.scale)
    return th


@pytest.mark.parametrize("names", [
    ["battery_fade", "surface_friction", "actuator_lag", "lens_distortion", "landmark_offset"],
    ["camera_latency", "lens_distortion", "landmark_offset"]])
def test_effect_graph_jacobian_matches_numerical_differentiation(short, names):
    """Exact but for one documented shortcut: the latency's velocity is differentiated through the table only."""
    log, m = short
    effects = AU.instantiate(names, log)
    p = Problem(log, m, effects, huber=False)
    st = p.state(log.truth[:, 1:], m, _theta_for(p, np.random.default_rng(0)))
    A, e, _ = p.jacobian(st)
    A = A.toarray()
    K = p.lay.n_poses
    rng = np.random.default_rng(1)
    cols = list(rng.choice(3 * K, 12, replace=False)) + list(3 * K + np.arange(p.n_theta))
    for col in cols:
        h = 1e-6
        def resid(sign):
            if col < 3 * K:
                dp = np.zeros((K, 3))
                dp[col // 3, col % 3] = sign * h
                s2 = p.retract(st, (dp, np.zeros(0)))
            else:
                dth = np.zeros(p.n_theta)
                dth[col - 3 * K] = sign * h
                s2 = p.retract(st, (np.zeros((K, 3)), dth))
            return p.jacobian(s2)[1]
        num = (resid(1) - resid(-1)) / (2 * h)
        scale = max(1.0, np.abs(num).max())
        assert np.abs(num - A[:, col]).max() < 2e-4 * scale, f"column {col}"


def test_own_solver_equals_gtsam_on_the_effect_graph(short):
    log, m = short
    effects = AU.instantiate(["battery_fade", "actuator_lag", "lens_distortion"], log)
    p = Problem(log, m, effects, huber=False)
    st = p.state(log.truth[:, 1:] + 0.01, m, _theta_for(p, np.random.default_rng(2)))
    dp, dt = p.solve_damped(p.normal_equations(st), 1e-3)
    g = p.linearize(st)
    g.push_back(_damping(p.keys_dims(), 1e-3))
    dv = g.optimize()
    ref = np.array([dv.at(gtsam.symbol_shorthand.X(i)) for i in range(p.lay.n_poses)])
    np.testing.assert_allclose(dp, ref, atol=1e-8)
    np.testing.assert_allclose(dt, dv.at(THETA), atol=1e-8)


def test_held_effect_keeps_its_parameters_while_the_rest_is_fitted(short):
    """What the held-out score relies on: a held effect and the noise stay put, table and poses move."""
    log, m = short
    lag = REGISTRY["actuator_lag"]
    m = m.with_(effects={"actuator_lag": {"tau": 0.2}})
    poses = log.truth[:, 1:] + 0.01
    free = effect_fit.fit(log, m, poses, [lag], rounds=1, iterations=3, fit_noise=False)
    fixed = effect_fit.fit(log, m, poses, [held(lag)], rounds=1, iterations=3, fit_noise=False)
    assert held(lag).name == "actuator_lag" and not lag.noise_only
    assert free.model.effects["actuator_lag"]["tau"] != pytest.approx(0.2, abs=1e-6)
    assert fixed.model.effects["actuator_lag"]["tau"] == pytest.approx(0.2, abs=1e-12)
    assert fixed.model.reading_sigma == m.reading_sigma and np.all(fixed.model.motion_noise == m.motion_noise)
    assert np.abs(fixed.model.velocities - m.velocities).max() > 1e-6
    assert np.abs(fixed.poses - poses).max() > 1e-3


def test_friction_field_is_bilinear_through_its_nodes_and_clamped_outside():
    ext = (-2.0, -1.0, 2.0, 1.0)
    rng = np.random.default_rng(0)
    xy = np.column_stack([rng.uniform(-3, 3, 500), rng.uniform(-2, 2, 500)])
    W = bilinear(xy, ext)
    np.testing.assert_allclose(W.sum(axis=1), 1.0)
    gx, gy = np.meshgrid(np.linspace(-2, 2, NODES), np.linspace(-1, 1, NODES))
    plane = (0.3 * gx - 0.2 * gy + 0.1).ravel()                      # a plane through the nodes is reproduced
    inside = np.clip(xy, [-2, -1], [2, 1])
    np.testing.assert_allclose(W @ plane, 0.3 * inside[:, 0] - 0.2 * inside[:, 1] + 0.1, atol=1e-12)
    x0, y0, x1, y1 = extent_around(xy)
    assert x0 < np.percentile(xy[:, 0], 1) and x1 > np.percentile(xy[:, 0], 99) and y1 - y0 < 4.5


def test_friction_field_extent_is_recorded_restored_and_drawn(tmp_path):
    """The simulator's field is the playing field; a fit records its own extent, a refit takes it back."""
    log, truth = simulate(SimConfig(minutes=1, seed=5, effects={"surface_friction": 0.2}))
    t = truth["effects"]["surface_friction"]
    assert t["extent"] == [-2.7, -1.8, 2.7, 1.8]
    assert t[f"slow_{NODES - 1}_0"] - t["slow_0_0"] == pytest.approx(0.2)          # east slower than west by 0.2
    assert np.mean([t[p] for p in REGISTRY["surface_friction"].params[:-1]]) == pytest.approx(0.0, abs=1e-12)
    assert t["turn_share"] == 1.0
    cal = cg.calibrate(log, effects=["surface_friction"], seed=5)
    entry = cal.model.effects["surface_friction"]
    x0, y0, x1, y1 = entry["extent"]
    tr = cal.trajectory
    assert x0 <= np.percentile(tr["x"], 1) and x1 >= np.percentile(tr["x"], 99) and y1 > y0
    again = AU.instantiate(["surface_friction"], log)
    AU.theta_from_model(again, cal.model)
    assert list(again[0].extent) == entry["extent"]
    cal.save(tmp_path / "run")
    assert "Surface friction on the field" in (tmp_path / "run" / "report.html").read_text()


def test_friction_grid_level_is_the_visited_floors():
    """A grid's level is measured over the steps the robot ran (``visits``), not over its nodes: the field averages
    zero where the robot went, whatever the nodes it never reached hold, so the field cannot trade the visited
    floor's speed with the action model (an omni world's calibration had the visited floor 88 % slower, empty
    corners five times faster and the command map eight times faster). model.json carries ``visits``; an entry
    without it keeps the nodes' mean."""
    rng = np.random.default_rng(3)
    e = get("surface_friction")(extent=(0.0, 0.0, 4.0, 4.0))
    poses = np.column_stack([rng.uniform(0, 2, 500), rng.uniform(0, 1.5, 500), np.zeros(500)])   # one corner
    e.begin(None, poses)
    assert e.visits.sum() == pytest.approx(1.0) and np.count_nonzero(e.visits > 0) < NODES ** 2
    theta = np.append(rng.normal(0, 0.3, NODES ** 2), 1.0)
    ran = e.slow(theta, poses[:, :2])
    assert ran.mean() == pytest.approx(0.0, abs=1e-12)
    empty = np.flatnonzero(e.visits == 0)
    pushed = theta.copy()
    pushed[empty] -= 5.0                                   # empty corners far faster: the visited floor unmoved
    assert np.allclose(e.slow(pushed, poses[:, :2]), ran)
    assert e.slow(pushed, poses[:, :2]).mean() == pytest.approx(0.0, abs=1e-12)
    entry = e.describe(theta)
    back = get("surface_friction")()
    back.restore(entry)
    values = np.array([entry[p] for p in back.params])
    assert np.allclose(back.slow(values, poses[:, :2]), ran)
    m = Model.from_json({**paper_start(simulate(SimConfig(minutes=0.2, seed=1))[0]).to_json(),
                         "effects": {"surface_friction": entry}})       # model.json takes it back
    assert m.effects["surface_friction"]["visits"] == entry["visits"]
    with pytest.raises(cg.LogError, match="visits"):
        Model.from_json({**m.to_json(), "effects": {"surface_friction": {**entry, "visits": [0.5] * NODES ** 2}}})
    old = get("surface_friction")()
    old.restore({k: v for k, v in entry.items() if k != "visits"})
    assert old.visits is None and np.allclose(old.slow(values, poses[:, :2]),
                                              bilinear(poses[:, :2], e.extent) @ (values[:-1] - values[:-1].mean()))


def test_a_friction_entry_written_before_the_turn_share_slows_turns_alike():
    """A model.json friction entry without ``turn_share`` (written before the family had it) is read with the turn
    rate slowed as much as driving: the share 1 the family starts from."""
    log, _ = simulate(SimConfig(minutes=0.2, seed=1))
    entry = {"slow_0_0": 0.1, "slow_1_0": 0.0, "slow_0_1": 0.0, "slow_1_1": 0.0, "order": 2, "grid": [2, 2],
             "extent": [0.0, 0.0, 1.0, 1.0]}
    m = Model.from_json({**paper_start(log).to_json(), "effects": {"surface_friction": entry}})
    (e,) = AU.instantiate(["surface_friction:2"], log)
    theta = AU.theta_from_model([e], m)
    assert e.params[-1] == "turn_share" and theta[-1] == 1.0 and theta[0] == pytest.approx(0.1)
    v = e.velocity(theta, np.ones((1, 3)), {"pose": np.array([[0.0, 0.0, 0.0]])})
    assert v[0, 0] == pytest.approx(v[0, 2]) and v[0, 0] < 1.0


def test_a_floor_that_changes_the_speed_beyond_physics_is_implausible():
    """A friction fit that has one part of the floor let the robot run more than three times as fast as another
    (driving or turning), or stop it, cannot happen; a carpet that costs 40 % of the speed can, of every member. The
    glare notebook's patch (slow -3.16: 4.2 times as fast) is the case it catches."""
    patch = get("surface_friction:0")(extent=(0.0, 0.0, 4.0, 4.0))
    assert patch.implausible(np.array([0.4, 1.0, 2.0, 0.0, 4.0, 0.5])) is None
    assert patch.implausible(np.array([-1.5, 1.0, 2.0, 0.0, 4.0, 1.0])) is None          # the fast part is the patch
    assert "4.2 times as fast" in patch.implausible(np.array([-3.16, 1.0, 2.0, 0.0, 4.0, 0.02]))
    assert "drive 3.3 times" in patch.implausible(np.array([0.7, 1.0, 2.0, 0.0, 4.0, 1.0]))
    assert "stop the robot's turn" in patch.implausible(np.array([0.3, 1.0, 2.0, 0.0, 4.0, 4.0]))
    plane = get("surface_friction:1")(extent=(0.0, 0.0, 4.0, 4.0))
    assert plane.implausible(np.array([0.3, -0.3, 1.0])) is None                       # 1.3 against 0.7
    assert plane.implausible(np.array([0.7, -0.6, 1.0])) is not None                   # 1.65 against 0.35
    grid = get("surface_friction:2")(extent=(0.0, 0.0, 4.0, 4.0))
    grid.visits = np.array([0.5, 0.5, 0.0, 0.0])                    # the north nodes never reached
    assert grid.implausible(np.array([0.2, -0.2, 5.0, -5.0, 1.0])) is None
    assert grid.implausible(np.array([0.9, -0.9, 0.0, 0.0, 1.0])) is not None          # 0.1 against 1.9
    entry = {**grid.describe(np.array([0.9, -0.9, 0.0, 0.0, 1.0]))}
    assert unphysical(get("surface_friction:2"), entry) == grid.implausible(np.array([0.9, -0.9, 0.0, 0.0, 1.0]))
    assert unphysical(get("camera_latency"), {"rate": 50.0}) is None                  # effects without the hook
    assert unphysical(get("regional_motion_noise"), {"k_r": [1.0, 2.0]}) is None      # list-valued entries too


def test_a_fade_that_speeds_the_robot_up_is_implausible(short):
    """A battery only loses charge: a fade fit that leaves the robot faster at the log's end (one minute here) than at
    its start cannot happen, of either member, nor one that regains more than half the speed it had lost at its
    slowest; a quadratic that rises early and ends slower can, or one that regains a little. Without a log there is
    no end to judge by."""
    log, _ = short
    minutes = (log.pose_times[-1] - log.pose_times[0]) / 60.0
    assert minutes == pytest.approx(1.0, abs=0.01)
    line, bend = get("battery_fade")(log), get("battery_fade:2")(log)
    assert line.implausible(np.array([0.02])) is None
    assert "2.0 % faster at the log's end" in line.implausible(np.array([-0.02]))
    assert bend.implausible(np.array([-0.01, 0.03])) is None                           # ends 2 % slower
    assert "1.0 % faster" in bend.implausible(np.array([0.02, -0.03]))
    assert "regain 1.0 %" in bend.implausible(np.array([0.04, -0.04]))       # down 1 % by half a minute, all back
    assert bend.implausible(np.array([0.03, -0.02])) is None                 # down 1.1 %, a ninth of it back
    assert get("battery_fade")(None).implausible(np.array([-0.02])) is None
    entry = line.describe(np.array([-0.02]))
    assert unphysical(get("battery_fade"), entry, log) == line.implausible(np.array([-0.02]))


def test_friction_is_a_family_of_grids_named_restored_and_checked(tmp_path):
    """``surface_friction:K`` is the K x K member; it travels as its name, records its order in model.json and
    comes back as the same member; an order the family lacks is one LogError."""
    assert REGISTRY["surface_friction"].orders == (0, 1, 2, 3, NODES)
    two = get("surface_friction:2")
    assert two is get("surface_friction:2") and two is not REGISTRY["surface_friction"]
    assert get(f"surface_friction:{NODES}") is REGISTRY["surface_friction"]
    assert spec(two) == "surface_friction:2" and spec(REGISTRY["surface_friction"]) == "surface_friction"
    e = two()
    assert e.params == ("slow_0_0", "slow_1_0", "slow_0_1", "slow_1_1", "turn_share") and e.free_parameters() == 4
    plane = get("surface_friction:1")(extent=(-1.0, -1.0, 1.0, 1.0))
    assert plane.params == ("tilt_east", "tilt_north", "turn_share") and plane.free_parameters() == 3
    np.testing.assert_allclose(plane.slow(np.array([0.2, 0.1, 1.0]), np.array([[1, 0], [-1, 0], [0, 1], [9, 9]])),
                               [0.1, -0.1, 0.05, 0.15])         # east edge 0.2 slower than west; clamped outside
    patch = get("surface_friction:0")(extent=(-2.0, -2.0, 2.0, 2.0))
    assert patch.params == ("slow", "west", "east", "south", "north", "turn_share") and patch.free_parameters() == 6
    theta = np.array([0.2, 0.0, 9.0, -1.0, 1.0, 0.5])
    np.testing.assert_allclose(patch.slow(theta, np.array([[1, 0], [-1, 0], [1, 2]])),
                               [0.2, 0.0, 0.0], atol=1e-4)       # on the rug, west of it, north of it
    v = patch.velocity(theta, np.ones((2, 3)), {"pose": np.array([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]])})
    np.testing.assert_allclose(v, [[0.8, 0.8, 0.9], [1.0, 1.0, 1.0]], atol=1e-4)   # turns lose half as much
    with pytest.raises(cg.LogError, match="order 5"):
        get("surface_friction:5")
    with pytest.raises(cg.LogError, match="whole number"):
        get("surface_friction:x")
    with pytest.raises(cg.LogError, match="one form"):
        get("camera_latency:2")
    log, _ = simulate(SimConfig(minutes=1, seed=5, effects={"surface_friction": 0.2}))
    cal = cg.calibrate(log, effects=["surface_friction:2"], seed=5)
    entry = cal.model.effects["surface_friction"]
    assert entry["order"] == 2 and entry["grid"] == [2, 2] and len([k for k in entry if k.startswith("slow_")]) == 4
    cal.save(tmp_path / "run")
    back = Model.load(tmp_path / "run" / "model.json")
    (cls,) = of_model(back.effects)
    assert cls is two
    inst = AU.instantiate([cls], log)
    np.testing.assert_allclose(AU.theta_from_model(inst, back), [entry[p] for p in e.params])
    by_name = AU.instantiate(["surface_friction"], log)       # a default instance takes the order back from the entry
    np.testing.assert_allclose(AU.theta_from_model(by_name, back), [entry[p] for p in e.params])
    lens = get("lens_distortion")()
    lens.restore({"k": 0.1, "k4": 0.2, "order": 2})            # any family, through the base hook
    assert lens.params == ("k", "k4") and lens.order == 2


def rug_sweep(rng, speed) -> tuple[np.ndarray, np.ndarray]:
    """A robot sweeping a 6 x 4 m floor in 17 rows, its steps noisy by 5 %, 20 % slower on a rug over x in [1, 3],
    y in [0.5, 2.5]; ``speed(row)`` is each step's commanded speed. Returns the poses and the commanded steps."""
    xy, heading, asked = [np.array([-3.0, -2.0])], [], []
    for row in range(17):
        going = 1.0 if row % 2 == 0 else -1.0
        while True:
            v = speed(row)
            if not -3.0 <= xy[-1][0] + going * v * 0.1 <= 3.0:
                break
            p = xy[-1]
            on = 1.0 <= p[0] <= 3.0 and 0.5 <= p[1] <= 2.5
            xy.append(p + [going * v * 0.1 * (0.8 if on else 1.0) * (1 + 0.05 * rng.standard_normal()), 0.0])
            heading.append(0.0 if going > 0 else np.pi)
            asked.append([v * 0.1, 0.0, 0.0])
        xy[-1] = xy[-1] + [0.0, 0.25]
    heading.append(heading[-1])
    return np.column_stack([np.array(xy), np.array(heading)]), np.array(asked)


def test_a_patch_starts_where_the_steps_fall_short_of_their_commands():
    """Rows swept at two speeds: the patch's start is the rug's cells and its slow-down."""
    poses, asked = rug_sweep(np.random.default_rng(3), lambda row: 0.2 if row % 2 == 0 else 0.15)
    start = patch_start(poses, asked, extent_around(poses))
    assert start[0] == pytest.approx(0.2, abs=0.05), start
    np.testing.assert_allclose(start[1:], [1.0, 3.0, 0.5, 2.5], atol=0.6)


def test_a_patch_starts_on_continuous_commands_whose_speeds_tie():
    """Continuous commands held at one speed most of the time (as MRCLAM's are) tie the speed bins' quantiles; the
    empty bins must not turn the start into NaN and lose it: the rug 20 % slower is still found."""
    rng = np.random.default_rng(4)
    poses, asked = rug_sweep(rng, lambda row: 0.2 if rng.random() < 0.8 else rng.uniform(0.1, 0.3))
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        start = patch_start(poses, asked, extent_around(poses))
    assert start is not None and start[0] == pytest.approx(0.2, abs=0.05), start
    np.testing.assert_allclose(start[1:], [1.0, 3.0, 0.5, 2.5], atol=0.6)


@pytest.mark.parametrize("order", [1, 2])
def test_lag_members_average_their_step_response_over_each_step(order):
    """actuator_lag:1 is one first-order stage, :2 two equal stages in cascade (a critically damped drive): the
    velocity of a step is the old one's share of the response averaged over the step, checked by quadrature."""
    tau, dt, since = 0.3, 0.1, np.array([0.0, 0.1, 0.5, 2.0])
    share = (lambda t: np.exp(-t / tau)) if order == 1 else (lambda t: (1 + t / tau) * np.exp(-t / tau))
    want = [quad(share, s, s + dt)[0] / dt for s in since]
    ctx = {"since": since, "dt": np.full(4, dt), "v_prev": np.tile([1.0, 0.5, -2.0], (4, 1))}
    got = get(f"actuator_lag:{order}")().velocity(np.array([tau]), np.zeros((4, 3)), ctx)
    np.testing.assert_allclose(got, np.outer(want, [1.0, 0.5, -2.0]), rtol=1e-10)


def test_a_table_latency_sees_the_mean_velocity_over_its_delay():
    """With a latency in the model the table's sighting velocity is the mean over the delay before each sighting
    (an action change inside it counts), exactly linear in the table rows; without one, the step before's."""
    from casm_graph.graph.actions.base import sighting_means

    log, truth = simulate(SimConfig(minutes=1, seed=2))
    m = paper_start(log)
    m = m.with_(velocities=np.array([truth["action_model"]["velocities"][str(a)] for a in m.action_ids]))
    poses = np.zeros((log.steps + 1, 3))
    step_v = m.step_velocities(log)
    plain = Problem(log, m, lay=None)
    v0, _ = plain.action.sighting_velocity(poses, plain.action.params(m), np.zeros(0))
    assert np.allclose(v0, step_v[np.clip(log.obs_step - 1, 0, log.steps - 1)])
    delay = 0.2
    late = m.with_(effects={"camera_latency": {"delay": delay}})
    pb = Problem(log, late, [REGISTRY["camera_latency"](log)], theta=np.array([delay]))
    x = pb.action.params(late)
    v, dv = pb.action.sighting_velocity(poses, x, np.array([delay]))
    assert np.allclose(v, sighting_means(log, step_v, delay))
    assert np.allclose(np.einsum("nci,i->nc", dv, np.ravel(x)), v)
    assert np.abs(v - v0).max() > 0.05               # some sightings follow an action change within the delay
