"""Calibration on a world written apart from the code (``tests/worlds/independent_world.py``).

That generator shares nothing with casm_graph's simulator: its own random field and landmarks, motion
at 200 Hz with slip, a sensor curve that is not a polynomial (an apparent size a / (d + b) + c for the
camera of the action-table robot, a time-of-flight range s d + o for the continuous one). Tolerances are
the paper's errors times 1.5 (PAPERS.md section 1: vx 23.06 mm/s, vy 18.34 mm/s, w 0.086 rad/s, sensor
curve 0.35 px) and, for the command map, a quarter of the error of taking the commands at face value
(the fit's is a tenth of it or less on seeds 0 and 1). The apparent-size curve over 0.3-8 m is too bent
for the paper's cubic (held at degree 3 it misses by 0.8-4.8 px and the table by up to 41 mm/s): the fit
raises the degree or takes the curve in 1/d when the readings demand (``fit.sensor_degree``, BENCHMARKS.md
"Independent world").
"""
import numpy as np
import pytest

import casm_graph as cg
from casm_graph.models.model import Model

from .conftest import FULL, patch_contrast, position_rms
from .worlds import traces
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
    sd = cal.model.fit["sensor_degree"]          # not the stiff cubic in d: a higher degree, or the curve in 1/d
    assert sd["asked"] == 3 and (sd["fitted"] > 3 or sd["basis"] == "inverse_distance"), sd
    true = np.array([truth["realized_velocities"][str(int(a))] for a in cal.model.action_ids])
    rms = np.sqrt(np.mean((cal.model.velocities - true) ** 2, axis=0))
    assert np.all(rms < 1.5 * PAPER), rms
    assert _curve_rms(cal, log, truth) < 1.5 * PAPER_CURVE
    assert cal.model.reading_sigma == pytest.approx(truth["noise"]["reading_sigma"], rel=0.15)


@pytest.mark.science
def test_an_apparent_size_seen_from_close_takes_the_inverse_distance_curve(tmp_path):
    """Sightings from 0.3 m: the apparent size a / (d + b) + c is beyond a polynomial in d (a cubic in d misses
    the near readings and prunes them; before the standoff factor kept poses off the landmarks, the fit in d
    parked near sightings on them: 0.16-0.24 m on seeds 3, 6, 7 at six minutes); a cubic in 1/d follows it.
    The default (``auto``) sees the marks of that misfit, fits the curve in 1/d too and keeps it on its
    likelihood over every sighting (BENCHMARKS.md "Independent world")."""
    truth = generate(tmp_path / "log", kind="table", minutes=6, seed=3, min_range=0.3)
    log = cg.load_log(tmp_path / "log")
    in_d = cg.calibrate(log, seed=3, sensor_basis="distance")
    auto = cg.calibrate(log, seed=3)
    assert in_d.model.reading_basis == "distance" and auto.model.reading_basis == "inverse_distance"
    assert [t["basis"] for t in auto.model.fit["sensor_degree"]["tried"]] == ["distance", "inverse_distance"]
    assert position_rms(auto, log) < 0.05
    assert position_rms(auto, log) < 0.75 * position_rms(in_d, log)
    assert _curve_rms(auto, log, truth) < truth["noise"]["reading_sigma"]
    auto.save(tmp_path / "run")                                  # model.json keeps the basis
    again = Model.load(tmp_path / "run" / "model.json")
    assert again.fit["options"]["sensor_basis"] == "auto" and again.reading_basis == "inverse_distance"
    assert np.allclose(again.reading(np.array([0.5, 2.0, 6.0])), auto.model.reading(np.array([0.5, 2.0, 6.0])))


def test_a_clean_log_keeps_the_curve_in_d_untouched(tmp_path):
    """On the project's Aibo (a clean log: nothing pruned, the cubic kept) ``auto`` fits once, in d: the same
    calibration as ``--sensor-basis distance``, to the bit."""
    log, _ = cg.simulate("aibo", minutes=2, seed=4)
    auto, in_d = cg.calibrate(log, seed=0), cg.calibrate(log, seed=0, sensor_basis="distance")
    assert auto.model.reading_basis == "distance" and "tried" not in auto.model.fit["sensor_degree"]
    assert np.array_equal(auto.model.reading_poly, in_d.model.reading_poly)
    assert np.array_equal(auto.trajectory["x"], in_d.trajectory["x"])


@pytest.mark.science
def test_an_effect_free_world_reads_none_once_its_curve_follows_the_readings(tmp_path):
    """Table robot, seed 10, sightings from 0.8 m, no effect: the cubic in d missed the apparent size by 0.14 of the
    reading sigma (RMS), too little for the curve's choice (which asked for 0.2) and enough for the diagnosis
    (2 % of the reading variance): ``unexplained:distance`` and 0.086 m from the truth. The curve now moves when the
    diagnosis would call its misfit material; the fit takes 1/d and the diagnosis says none."""
    generate(tmp_path / "log", kind="table", minutes=6, seed=10, min_range=0.8)
    log = cg.load_log(tmp_path / "log")
    cal = cg.calibrate(log, seed=10)
    sd = cal.model.fit["sensor_degree"]
    assert sd["fitted"] > 3 or sd["basis"] == "inverse_distance", sd
    assert position_rms(cal, log) < 0.05
    diag = cg.diagnose(log, cal, candidates=["lens_distortion", "range_dependent_noise"])
    assert diag.verdict == "none", (diag.verdict, diag.structure[:2])


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


def test_the_sensor_curve_changes_only_when_the_readings_demand():
    from casm_graph.fit.sensor_degree import choose_curve
    from factors.reading import curve
    rng = np.random.default_rng(0)
    d = rng.uniform(0.3, 8.0, 3000)
    cubic = np.array([40.0, -12.0, 1.5, -0.06])
    r = np.polynomial.polynomial.polyval(d, cubic) + rng.normal(0, 1.0, len(d))
    assert choose_curve(d, r, cubic, 1.0, 6) is None                     # a cubic sensor keeps its cubic
    size = 90.0 / (d + 0.15) + 1.0 + rng.normal(0, 1.0, len(d))           # an apparent size does not:
    fit3 = np.polynomial.polynomial.polyfit(d, size, 3)
    coef, basis = choose_curve(d, size, fit3, 1.0, 6)                    # a short polynomial in 1/d follows it
    assert basis == "inverse_distance" and len(coef) - 1 <= 3
    grid = np.linspace(0.3, 8.0, 200)
    assert np.sqrt(np.mean((curve(grid, coef, basis) - (90.0 / (grid + 0.15) + 1.0)) ** 2)) < 0.2
    assert choose_curve(d, size, fit3, 1.0, 3) is None                   # unless the user holds the degree
    P = np.polynomial.polynomial                                           # a bend of a tenth of the sigma, RMS, is
    bend = d ** 4 - P.polyval(d, P.polyfit(d, d ** 4, 3))                  # material (1 % of the reading variance,
    bend /= np.sqrt(np.mean(bend ** 2))                                    # what the diagnosis names); less is not
    near = P.polyval(d, cubic) + 0.05 * bend + rng.normal(0, 1.0, len(d))
    assert choose_curve(d, near, P.polyfit(d, near, 3), 1.0, 6) is None
    bent = P.polyval(d, cubic) + 0.15 * bend + rng.normal(0, 1.0, len(d))
    assert choose_curve(d, bent, P.polyfit(d, bent, 3), 1.0, 6)[1] == "distance"
    stiff = cg.SensorCurveOptions(material=0.2)                            # the share is an option (GraphOptions)
    assert choose_curve(d, bent, P.polyfit(d, bent, 3), 1.0, 6, options=stiff) is None
    steps = np.round(size / 100) * 100                                     # three distinct readings: nothing to raise
    assert choose_curve(d, steps, np.polynomial.polynomial.polyfit(d, steps, 3), 1.0, 6) is None


def test_the_inverse_distance_curve_has_exact_jacobians():
    import factors
    rng = np.random.default_rng(1)
    p = np.column_stack([rng.uniform(-2, 2, 20), rng.uniform(-2, 2, 20), rng.uniform(-3, 3, 20)])
    lm = rng.uniform(-3, 3, (20, 2))
    c = np.array([1.0, 60.0, -4.0, 0.5])
    z = rng.uniform(10, 50, 20)
    e, (Hp, Hc) = factors.reading.error(p, c[None], lm, z, "inverse_distance")
    h = 1e-6
    for k in range(3):                                   # body-frame tangent of the pose
        step = np.zeros(3)
        step[k] = h
        th = p[:, 2]
        world = np.column_stack([np.cos(th) * step[0] - np.sin(th) * step[1],
                                 np.sin(th) * step[0] + np.cos(th) * step[1], np.full(20, step[2])])
        ep = factors.reading.error(p + world, c[None], lm, z, "inverse_distance")[0]
        em = factors.reading.error(p - world, c[None], lm, z, "inverse_distance")[0]
        assert np.allclose((ep - em)[:, 0] / (2 * h), Hp[:, 0, k], rtol=1e-5, atol=1e-6)
    d = np.hypot(*(p[:, :2] - lm).T)
    assert np.allclose(e[:, 0], np.polynomial.polynomial.polyval(1 / d, c) - z)
    assert np.allclose(Hc[:, 0], (1 / d)[:, None] ** np.arange(4))


# ----------------------------------------------------------------------------- uncataloged physics effects
# Fast checks of the generator itself (numpy only): each effect changes the true motion as stated, measured
# against the same seed without the effect (same field, actions, noise streams), so the shared slip cancels.
def _bundle(path):
    """World truth as written to disk, the 10/20 Hz true body velocity between truth rows, and the
    effect-free body velocity the command of each row asks for."""
    import json
    truth = json.loads((path / "world_truth.json").read_text())
    tr = np.loadtxt(path / "truth.csv", delimiter=",", skiprows=1)
    cmd = np.loadtxt(path / "commands.csv", delimiter=",", skiprows=1, ndmin=2)
    d = np.diff(tr[:, 1:], axis=0)
    dth = np.angle(np.exp(1j * d[:, 2]))
    th = tr[:-1, 3] + dth / 2
    body = np.column_stack([np.cos(th) * d[:, 0] + np.sin(th) * d[:, 1],
                            -np.sin(th) * d[:, 0] + np.cos(th) * d[:, 1], dth]) * truth["rates"]["command_hz"]
    if truth["kind"] == "table":
        nominal = np.array([truth["velocities"][str(int(a))] for a in cmd[:, 1]])
    else:
        m = truth["command_map"]
        nominal = np.column_stack([m["forward"]["gain"] * cmd[:, 1] + m["forward"]["offset"],
                                   m["lateral"]["gain"] * cmd[:, 1] + m["lateral"]["offset"],
                                   m["turn"]["gain"] * cmd[:, 2] + m["turn"]["offset"]])
    return truth, tr[:-1, 0], body, nominal


def _pair(tmp_path, effect, kind, seed):
    generate(tmp_path / "with", kind=kind, minutes=1, seed=seed, effect=effect)
    generate(tmp_path / "without", kind=kind, minutes=1, seed=seed)
    return _bundle(tmp_path / "with"), _bundle(tmp_path / "without")


@pytest.mark.parametrize("kind", ["table", "continuous"])
def test_time_speed_scales_forward_speed_by_a_slow_sinusoid(tmp_path, kind):
    (truth, t, body, nom), (free, t0, body0, nom0) = _pair(tmp_path, "time_speed", kind, seed=3)
    g, s = truth["geometry"], truth["strength"]
    assert truth["field"] == free["field"] and truth["landmarks"] == free["landmarks"]

    def amplitude(t, body, nom):                  # forward = nominal (1 + k sin(2 pi t / period + phase))
        x = nom[:, 0] * np.sin(2 * np.pi * t / g["period"] + g["phase"])
        return float(x @ (body[:, 0] - nom[:, 0]) / (x @ x))

    k, k0 = amplitude(t, body, nom), amplitude(t0, body0, nom0)
    assert abs(k0) < 0.3 * s                                          # nothing of the sort without the effect
    assert k - k0 == pytest.approx(s, rel=0.2)
    # turn and lateral motion are untouched: their residuals look like the effect-free ones
    for j in (1, 2):
        assert np.std(body[:, j] - nom[:, j]) < 1.5 * np.std(body0[:, j] - nom0[:, j])


def test_time_speed_is_an_oscillation_not_a_fade():
    from .worlds.independent_world import _Physics
    geom = {"period": 120.0, "phase": 0.7}
    phys = _Physics("time_speed", 0.15, geom, None)
    pose = np.zeros((1, 3))
    t = np.linspace(0, 240, 481)
    f = np.array([phys.factor(pose, ti)[0] for ti in t])
    assert np.allclose(f[:, 1:], 1.0)                                 # forward speed only
    assert np.allclose(f[:, 0], 1 + 0.15 * np.sin(2 * np.pi * t / 120 + 0.7))
    assert f[:, 0].max() == pytest.approx(1.15, abs=1e-3) and f[:, 0].min() == pytest.approx(0.85, abs=1e-3)
    assert f[0, 0] == pytest.approx(f[240, 0]) == pytest.approx(f[480, 0])   # back where it started each period


@pytest.mark.parametrize("kind", ["table", "continuous"])
def test_speed_turn_pulls_aside_in_proportion_to_forward_speed(tmp_path, kind):
    (truth, t, body, nom), (free, t0, body0, nom0) = _pair(tmp_path, "speed_turn", kind, seed=3)
    g = truth["geometry"]
    assert truth["field"] == free["field"] and truth["landmarks"] == free["landmarks"]
    extra, extra0 = body[:, 2] - nom[:, 2], body0[:, 2] - nom0[:, 2]  # true turn rate beyond the commanded one
    slope = np.polyfit(body[:, 0], extra, 1)[0] - np.polyfit(body0[:, 0], extra0, 1)[0]
    assert slope == pytest.approx(g["gain"], rel=0.15)
    assert np.sign(slope) == g["sign"]
    moving = np.abs(body[:, 0]) > 0.1
    assert abs(np.corrcoef(body[moving, 0], extra[moving])[0, 1]) > 0.5
    assert abs(np.corrcoef(body0[np.abs(body0[:, 0]) > 0.1, 0], extra0[np.abs(body0[:, 0]) > 0.1])[0, 1]) < 0.3


@pytest.mark.parametrize("effect", ["time_speed", "speed_turn"])
def test_time_speed_and_speed_turn_geometry_in_world_truth(tmp_path, effect):
    import json

    from .worlds.independent_world import EFFECTS, UNCATALOGED
    assert effect in UNCATALOGED
    kinds = {"time_speed": "table", "speed_turn": "continuous"}
    signs = set()
    for seed in (0, 3):
        out = tmp_path / f"s{seed}"
        generate(out, kind=kinds[effect], minutes=1, seed=seed, effect=effect)
        truth = json.loads((out / "world_truth.json").read_text())
        g, s = truth["geometry"], truth["strength"]
        assert truth["effect"] == effect and g["uncataloged"] is True
        assert EFFECTS[effect][0] <= s <= EFFECTS[effect][1]
        if effect == "time_speed":
            assert 90.0 <= g["period"] <= 240.0 and -np.pi <= g["phase"] <= np.pi
        else:
            assert g["sign"] in (-1.0, 1.0) and g["gain"] == pytest.approx(g["sign"] * s)
            signs.add(g["sign"])
    if effect == "speed_turn":
        assert signs == {-1.0, 1.0}                                   # seeds 0 and 3 pull to opposite sides
    again = generate(tmp_path / "again", kind=kinds[effect], minutes=1, seed=3, effect=effect)
    assert again["geometry"] == g and again["strength"] == s          # reproducible from the seed
    given = generate(tmp_path / "given", kind=kinds[effect], minutes=1, seed=3, effect=effect, strength=0.3)
    assert given["strength"] == 0.3 and all(given["geometry"][k] == g[k] for k in g if k != "gain")


@pytest.mark.science
@pytest.mark.skipif(not FULL, reason="full size only (CASM_FULL=1): a 6-minute table log; CI runs the continuous one")
def test_a_carpet_anywhere_on_the_floor_is_named_and_mapped(tmp_path):
    """Independent world, action-table robot, seed 1, 6 minutes, sightings from 0.8 m: a carpet patch at a random
    place (15 % slower, edges clear of x = 0 and y = 0), produced in the world's physics. ``diagnose`` names
    surface_friction (the fixed split at x = 0, y = 0 it had before missed such patches), the fitted field is
    slower on the patch than off it, and the position error against the truth falls (0.0388 -> 0.0352 m). Named on
    seeds 1-3 of 0-3 (seed 0: delta BIC -393 but the held-out score -2.1 nats); at 4 minutes the field is not yet
    supported on most seeds: the table robot's speeds are seen through sparse sightings.
    benchmarks/independent_world.py runs every candidate (BENCHMARKS.md)."""
    truth = generate(tmp_path / "log", minutes=6, kind="table", seed=1, effect="surface_friction", min_range=0.8)
    log = cg.load_log(tmp_path / "log")
    base = cg.calibrate(log, seed=1)
    diag = cg.diagnose(log, base, candidates=["surface_friction", "battery_fade"])
    assert diag.verdict == "surface_friction", diag.verdict
    trace = traces.check(diag, "surface_friction", truth["geometry"])     # the report opens with the floor map
    assert trace["position"] == 0 and trace["shown"], trace
    cal = cg.calibrate(log, effects=["surface_friction"], seed=1)
    assert patch_contrast(cal.model.effects["surface_friction"], log, truth) > 0.5 * truth["strength"]
    assert position_rms(cal, log) < 0.95 * position_rms(base, log), (position_rms(base, log), position_rms(cal, log))


@pytest.mark.science
def test_a_rug_with_sharp_edges_is_fitted_as_a_patch_and_leaves_nothing_behind(tmp_path):
    """Independent world, action-table robot, seed 12, 6 minutes, sightings from 0.8 m: a carpet 18 % slower, the
    robot on it a fifth of the log. The 4 x 4 grid (delta BIC -323) smeared its sharp north edge and, once added,
    left the forward residuals following x (verdict unexplained:x); the patch (order 0: delta BIC -507, +301 nats
    held out) starts where the base's poses fell short of their commands, its north edge lands on the carpet's,
    and added it leaves none (benchmarks/independent_world.py, the randomised table worlds' friction row)."""
    truth = generate(tmp_path / "log", minutes=6, kind="table", seed=12, effect="surface_friction", min_range=0.8)
    log = cg.load_log(tmp_path / "log")
    diag = cg.diagnose(log, cg.calibrate(log, seed=12), candidates=["surface_friction", "battery_fade"])
    c = diag.candidates[0]
    assert diag.verdict == "surface_friction" and c.order == 0, (diag.verdict, c.orders)
    assert c.orders[0] < c.orders[4] - 100 and c.heldout_nll_drop > 100, (c.orders, c.heldout_nll_drop)
    assert c.parameters["north"] == pytest.approx(truth["geometry"]["patch"]["ymax"], abs=0.15), c.parameters
    cal = cg.calibrate(log, effects=[diag.to_add()], seed=12)
    assert patch_contrast(cal.model.effects["surface_friction"], log, truth) > 0.7 * truth["strength"]
    assert cg.diagnose(log, cal, candidates=[]).verdict == "none"



@pytest.mark.science
def test_a_strong_latency_of_a_continuous_robot_is_not_taken_for_a_lag(tmp_path):
    """Independent world, continuous robot, seed 7, 4 minutes: a camera latency of 0.175 s. The base's smoothed
    poses take the delayed images in, so they resemble the lag's; the latency has to move them back. With the
    leaders settled until the log-likelihood stops moving (``leader_rounds``, off by default), the latency wins
    (with two rounds the lag does, by 950 in BIC, the latency its look-alike; adding the lag leaves the trajectory
    0.051 m from the truth against 0.010 m with the latency)."""
    generate(tmp_path / "log", kind="continuous", minutes=4, seed=7, effect="camera_latency")
    log = cg.load_log(tmp_path / "log")
    diag = cg.diagnose(log, cg.calibrate(log, seed=7), candidates=["actuator_lag", "camera_latency"],
                       options=cg.DiagnoseOptions(leader_rounds=40))
    assert diag.verdict == "camera_latency", [(c.effect, c.delta_bic) for c in diag.candidates]
    assert abs(diag.candidates[0].parameters["delay"] - 0.175) < 0.01

@pytest.mark.science
def test_a_camera_latency_and_the_lag_are_one_lookalike_group(tmp_path):
    """The independent world's camera latency (0.168 s, seed 3, table robot): its back-projection takes the mean
    velocity over the delay, across an action change; in two rounds of least squares and the noise step it scores
    -1,820 against the lag's -1,912, the base's poses having taken the delayed images in. The two lead, so they and
    the base go on from their fits to a third round (``DiagnoseOptions.leader_rounds``), where the latency, whose
    poses must move back, reaches its optimum and is named (below -2,000); with the leaders' rounds off the lag
    is. The two fits change the predicted sightings alike: they are one look-alike group, with what would
    separate them."""
    generate(tmp_path / "log", kind="table", minutes=6, seed=3, effect="camera_latency", min_range=0.8)
    log = cg.load_log(tmp_path / "log")
    cal = cg.calibrate(log)
    diag = cg.diagnose(log, cal, candidates=["actuator_lag", "camera_latency"])
    assert diag.verdict == "camera_latency", [(c.effect, c.delta_bic) for c in diag.candidates]
    latency = diag.candidates[0]
    assert abs(latency.parameters["delay"] - 0.168) < 0.02 and latency.delta_bic < -2000
    two = cg.diagnose(log, cal, candidates=["actuator_lag", "camera_latency"],
                      options=cg.DiagnoseOptions(leader_rounds=0))
    assert two.verdict == "actuator_lag", [(c.effect, c.delta_bic) for c in two.candidates]
    assert [g["effects"] for g in diag.lookalikes] == [[diag.verdict, ({"actuator_lag", "camera_latency"}
                                                                       - {diag.verdict}).pop()]]
    trace = traces.check(diag, "camera_latency", {})          # one view for both: the path trailing the commands
    assert trace["position"] == 0 and trace["lead_effects"] == ["camera_latency", "actuator_lag"] and trace["shown"]
    text = " ".join(diag.words)
    assert "faster than the lag" in text and "commands steady" in text       # what would separate them


@pytest.mark.science
def test_a_strong_range_dependent_noise_is_named(tmp_path):
    """Seed 7's growth (0.71) was called unexplained:distance while the noise step left a sigma estimated under
    the old growth beside the new one (the candidate lost 185 nats); the sigma now follows its scales."""
    generate(tmp_path / "log", kind="table", minutes=6, seed=7, effect="range_dependent_noise", min_range=0.8)
    log = cg.load_log(tmp_path / "log")
    diag = cg.diagnose(log, cg.calibrate(log), candidates=["range_dependent_noise", "battery_fade"])
    assert diag.verdict == "range_dependent_noise" and diag.candidates[0].delta_bic < -300
    trace = traces.check(diag, "range_dependent_noise", {})
    assert trace["position"] == 0 and trace["measure"] == "reading vs distance" and trace["shown"], trace


@pytest.mark.science
def test_false_detections_on_continuous_commands_named_and_modelled(tmp_path):
    """Issues 20-21: a share of the sightings follows no landmark (uniform readings and bearings, the world's
    own draw); the continuous diagnosis scores the mixture on every sighting, the gated ones too, names it with
    a held-out gain, and once it is added the fitted share is the world's and nothing is named. The wild readings
    do not choose the sensor curve: the two curves are scored on the sightings one of them explains (scored on all,
    the fit without the mixture took a steep curve in 1/d, 0.018 m from the truth, and with the mixture the curve
    had to be chosen again, or the next diagnosis said ``unexplained:distance``)."""
    truth = generate(tmp_path / "log", kind="continuous", minutes=4, seed=7, effect="false_detections",
                     min_range=0.3)
    log = cg.load_log(tmp_path / "log")
    base = cg.calibrate(log, seed=7)
    assert base.model.reading_basis == "distance" and position_rms(base, log) < 0.012, base.model.fit["sensor_degree"]
    diag = cg.diagnose(log, base)
    assert diag.verdict == "false_detections", [(c.effect, c.delta_bic) for c in diag.candidates]
    top = diag.candidates[0]
    assert top.heldout_nll_drop > 0
    trace = traces.check(diag, "false_detections", {})        # the report opens with the sightings' tails
    assert trace["position"] == 0 and trace["shown"], trace
    fixed = cg.calibrate(log, effects=["false_detections"], seed=7)
    share = truth["stats"]["n_false"] / truth["stats"]["n_observations"]
    assert fixed.model.effects["false_detections"]["fraction"] == pytest.approx(share, rel=0.2)
    assert fixed.model.reading_basis == "distance", fixed.model.fit["sensor_degree"]
    assert position_rms(fixed, log) < 1.02 * position_rms(base, log)
    again = cg.diagnose(log, fixed)
    assert again.verdict == "none", [(c.effect, c.delta_bic) for c in again.candidates]


@pytest.mark.science
def test_a_lag_that_starts_from_rest_leaves_nothing_once_added(tmp_path):
    """Issue 21: the world's robot starts at rest and its second-order lag spins it up, while the log's first
    command is already a full turn. Taken as settled at that command, the lag had the first half-second turn 0.4
    rad the robot never turned: the first heading came out 0.44 rad off and its sightings, gated as outliers, were
    named false_detections (delta BIC -1,281) once the lag was added. The velocity before the log is unknown, so
    the lag's memory of it adds to the first segments' motion noise (``CommandModel.lag_memory``)."""
    truth = generate(tmp_path / "log", kind="continuous", minutes=4, seed=6, effect="actuator_lag")
    log = cg.load_log(tmp_path / "log")
    cal = cg.calibrate(log, effects=["actuator_lag"], seed=6)
    assert cal.model.command.lag == pytest.approx(2 * truth["strength"], rel=0.1)   # two stages of tau each
    heading = np.angle(np.exp(1j * (cal.trajectory["theta"][:10] - log.truth[:10, 3])))
    assert np.max(np.abs(heading)) < 0.05
    diag = cg.diagnose(log, cal, candidates=["false_detections", "range_dependent_noise"])
    assert diag.verdict == "none", [(c.effect, c.delta_bic) for c in diag.candidates]
    assert min(c.delta_bic for c in diag.candidates) > -10


@pytest.mark.science
def test_a_whole_turn_wound_into_a_few_knots_is_unwound(tmp_path):
    """The coarse graph on this world (continuous, seed 9, a strong lens) wound two whole turns into four and six
    knots: each segment turned 1.25 rad beyond the model, which no local step undoes, the turn noise came out
    0.06 rad a step (15 times the fit's without them) and the spins' 25 bearings were gated as outliers. Spins
    are unwound (``fit.turns``) and kept when the graph's cost agrees."""
    generate(tmp_path / "log", kind="continuous", minutes=4, seed=9, effect="lens_distortion")
    log = cg.load_log(tmp_path / "log")
    cal = cg.calibrate(log, seed=9)
    heading = np.angle(np.exp(1j * (cal.trajectory["theta"] - log.truth[:, 3])))
    assert np.max(np.abs(heading)) < 0.2
    assert cal.model.motion_noise[2] < 0.01
    assert cal.model.fit["outliers_set_aside"]["bearing"] < 5


@pytest.mark.science
def test_a_whole_turn_across_a_gap_in_the_sightings_is_unwound_on_an_action_table(tmp_path):
    """Table world, seed 12 (a second-order lag), six minutes: the start wound a whole turn into the six seconds
    without a sighting after t = 91 s (five coarse knots each 0.6-0.85 rad beyond the model) and the path kept it,
    its heading 2 pi off the truth's from there on (unwrapped; 0.079 m RMS, and after adding the lag the turn
    residuals followed time). The action table's coarse graph unwinds spins as the continuous one does."""
    generate(tmp_path / "log", kind="table", minutes=6, seed=12, effect="actuator_lag", min_range=0.8)
    log = cg.load_log(tmp_path / "log")
    cal = cg.calibrate(log, seed=12)
    off = np.unwrap(cal.trajectory["theta"]) - np.unwrap(log.truth[:, 3])
    assert np.max(np.abs(off - off[0])) < 1.0
    assert position_rms(cal, log) < 0.07


@pytest.mark.science
def test_a_spin_cut_by_a_knot_at_an_action_change_is_unwound(tmp_path):
    """Table world, seed 7, false detections, six minutes, calibrated with the mixture: a whole turn wound into four
    seconds near t = 278 s, its coarse segments 1.1-1.4 rad beyond the model but cut by knots at action changes into
    segments of one and two steps (0.13 and 0.27 rad), which broke the run of segments a spin is (path 0.053 m from
    the world's, and `unexplained:time` after adding). A segment counts by its turn per unit time."""
    generate(tmp_path / "log", kind="table", minutes=6, seed=7, effect="false_detections", min_range=0.8)
    log = cg.load_log(tmp_path / "log")
    cal = cg.calibrate(log, seed=7, effects=["false_detections"])
    off = np.unwrap(cal.trajectory["theta"]) - np.unwrap(log.truth[:, 3])
    assert np.max(np.abs(off - off[0])) < 1.0
    assert position_rms(cal, log) < 0.048


def test_a_spin_counts_its_segments_by_their_turn_per_unit_time():
    """Equal segments: the per-segment rule; a short segment inside a spin counts by its rate, not its size."""
    from casm_graph.fit.turns import spins
    e = np.array([0.0, 1.4, 0.27, 1.1, 1.2, 0.13, 1.2, 0.0])
    span = np.array([10, 10, 2, 10, 10, 1, 10, 10.0])
    assert spins(e) == []
    assert spins(e, span=span) == [(1, 7)]
    assert spins(e[[0, 1, 3, 4, 6, 7]], span=np.full(6, 10.0)) == spins(e[[0, 1, 3, 4, 6, 7]]) == [(1, 5)]
    assert spins(np.array([0.1, 0.3, 0.1]), span=np.array([10, 2, 10.0])) == []


def test_a_whole_turn_between_two_sighted_knots_is_a_spin_however_slowly_wound():
    """Between sighted knots with none between, the motion alone holds the path: a whole turn beyond the model there
    is a spin though no segment turns 0.5 rad; the same turn where sightings hold the path is not."""
    from casm_graph.fit.turns import spins, unsighted
    e = np.concatenate([np.zeros(5), np.full(20, -0.25), np.zeros(5)])
    sighted = np.ones(31, bool)
    sighted[6:25] = False
    assert unsighted(sighted) == [(5, 25)]
    assert spins(e) == [] and spins(e, sighted=np.ones(31, bool)) == []
    assert spins(e, sighted=sighted) == [(5, 25)]
    assert spins(e * 0.5, sighted=sighted) == []          # half a turn: the nearest alias is the one it has


@pytest.mark.science
def test_a_whole_turn_wound_slowly_across_a_gap_in_the_sightings_is_unwound(tmp_path):
    """Table world, seed 18 (a second-order lag, 0.23 s per stage), six minutes: the start wound a whole turn into
    the 13 s without a sighting after t = 221 s, 0.04 rad a step (under the 0.5 rad a coarse segment of a spin turns
    beyond the model), and the path kept it (heading 3.1 rad off the truth's at t = 229 s, the position 0.55 m off
    at t = 225 s; unwound 0.23 m, thirteen seconds dead-reckoned without the lag). Between two sighted knots only
    the motion holds the path, so a whole turn beyond the model there is unwound."""
    generate(tmp_path / "log", kind="table", minutes=6, seed=18, effect="actuator_lag", min_range=0.8)
    log = cg.load_log(tmp_path / "log")
    cal = cg.calibrate(log, seed=18)
    off = np.angle(np.exp(1j * (cal.trajectory["theta"] - log.truth[:, 3])))
    assert np.max(np.abs(off)) < 1.0
    gap = (log.truth[:, 0] > 221) & (log.truth[:, 0] < 234)
    assert np.max(np.hypot(cal.trajectory["x"] - log.truth[:, 1], cal.trajectory["y"] - log.truth[:, 2])[gap]) < 0.3


@pytest.mark.science
def test_a_camera_on_its_own_clock_is_no_latency(tmp_path):
    """Frames 0.04 s after each command row (a 10-Hz camera on its own clock): taken to the nearest pose, every
    image reads as the world a fixed time later, and an effect-free world was called camera_latency (delay
    -0.03 s on six minutes; delta BIC -44 on these three). Each sighting time now starts a step of its own."""
    generate(tmp_path / "log", minutes=3, seed=4, min_range=0.8, camera=(10.0, 0.04))
    log = cg.load_log(tmp_path / "log")
    assert log.command_row is not None and np.abs(log.obs_t - log.pose_times[log.obs_step]).max() < 1e-3
    np.testing.assert_array_equal(np.unique(log.command_row), np.arange(1800))
    cal = cg.calibrate(log, seed=0)
    assert cg.diagnose(log, cal).verdict == "none"
    assert cal.model_json["fit"]["held_commands"]["rows"] == 1800
