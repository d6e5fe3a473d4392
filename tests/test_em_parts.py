"""The pieces of the two EM methods, each against an independent computation."""
from dataclasses import replace

import gtsam
import numpy as np
import pytest
from gtsam.symbol_shorthand import X

from casm_graph.analysis.candidates import BENCHES
from casm_graph.fit import ekfs
from casm_graph.fit.methods.ekfs_em import _observations
from casm_graph.fit.methods.graph_em import expected_displacement, gaussian_moments, m_step, step_graph
from casm_graph.fit.residuals import distances
from casm_graph.fit.methods.kinds import KINDS, kind
from casm_graph.graph import chain
from casm_graph.graph import table as G
from casm_graph.graph.actions import ACTIONS, default_layout
from casm_graph.graph.problem import Problem
from casm_graph.models.command_model import for_commands
from casm_graph.models.model import ACTION_MODELS, paper_start
from casm_graph.sim.aibo import SimConfig, simulate
from casm_graph.sim.floor import FloorConfig
from casm_graph.sim.floor import simulate as simulate_floor
from factors.reading import curve


@pytest.fixture(scope="module")
def true_case():
    log, truth = simulate(SimConfig(minutes=2, seed=5))
    m = paper_start(log)
    tv = np.array([truth["action_model"]["velocities"][str(a)] for a in m.action_ids])
    m = m.with_(velocities=tv, reading_poly=np.array(truth["sensor_model"]["reading_poly_best_cubic"]),
                reading_sigma=1.0, bearing_sigma=0.5, motion_noise=np.array([0.002, 0.002, 0.004]))
    return log, m


def test_chain_marginals_equal_gtsam(true_case):
    log, m = true_case
    lay = G.layout(log, m, 1)
    problem = Problem(log, m, lay=lay)
    st = problem.state(log.truth[:, 1:], m)
    cov, cross, logdet = chain.select_inverse(*chain.information_blocks(problem, st))
    lin = problem.linearize(st, poses_only=True)
    mg = gtsam.Marginals(lin, gtsam.VectorValues())
    for i in (0, 1234, lay.n_poses - 1):
        np.testing.assert_allclose(cov[i], mg.marginalCovariance(X(i)), rtol=1e-8, atol=1e-14)
    for i in (0, 777):
        J = mg.jointMarginalCovariance(gtsam.KeyVector([X(i), X(i + 1)])).fullMatrix()
        np.testing.assert_allclose(cross[i], J[:3, 3:], rtol=1e-8, atol=1e-14)
    bt = lin.eliminateMultifrontal()                 # log det of the information matrix = 2 log det R
    assert logdet == pytest.approx(2 * bt.logDeterminant(), rel=1e-9)


def test_gaussian_moments_and_expected_displacement_match_sampling():
    rng = np.random.default_rng(0)
    mom = gaussian_moments(np.array([2.0]), np.array([0.09]), 6)[0]
    s = rng.normal(2.0, 0.3, 400_000)
    powers = s[:, None] ** np.arange(7)
    se = powers.std(0) / np.sqrt(len(s))                      # Monte Carlo standard error
    assert np.all(np.abs(mom - powers.mean(0)) < 5 * se + 1e-12)
    poses = np.array([[0.3, -0.2, 0.7], [0.35, -0.15, 0.9]])
    A = rng.normal(0, 1, (6, 6))
    S = A @ A.T * 0.01
    W = np.stack([S[:3, :3], S[3:, 3:]])
    Xc = S[:3, 3:][None]
    Ed, _ = expected_displacement(poses, W, Xc)
    z = rng.multivariate_normal(poses.ravel(), S, 400_000)
    a, b = z[:, :3], z[:, 3:]
    c, sn = np.cos(a[:, 2]), np.sin(a[:, 2])
    dx, dy = b[:, 0] - a[:, 0], b[:, 1] - a[:, 1]
    d = np.stack([c * dx + sn * dy, -sn * dx + c * dy, b[:, 2] - a[:, 2]], 1)
    se = d.std(0) / np.sqrt(len(d))
    assert np.all(np.abs(Ed[0] - d.mean(0)) < 5 * se)


def test_ekfs_smoother_with_the_true_model(true_case):
    log, m = true_case
    order, ptr, lm, zr, zb = _observations(log)
    act = np.searchsorted(m.action_ids, log.action)
    u = m.velocities[act] * log.dt[:, None]
    sig = ekfs.step_sigmas(m.motion_noise, log)              # the simulator's true motion noise
    use = np.ones(len(zr), bool)
    mu0, P0 = log.truth[0, 1:].copy(), np.diag([0.01, 0.01, 0.01])
    mu_a, P_a, ll, _ = ekfs.forward(mu0, P0, u, sig, ptr, lm, zr, zb, m.reading_poly, 1.0, 0.5, use)
    Lb, eb, Ld, ed = ekfs.backward(mu_a, u, sig, ptr, lm, zr, zb, m.reading_poly, 1.0, 0.5, use)
    mu_g, P_g = ekfs.smooth(mu_a, P_a, Lb, eb)
    tr = log.truth[:, 1:]
    err_f = np.sqrt(np.mean(np.sum((mu_a[:, :2] - tr[:, :2]) ** 2, 1)))
    err_s = np.sqrt(np.mean(np.sum((mu_g[:, :2] - tr[:, :2]) ** 2, 1)))
    assert err_s < 0.1 and err_s < err_f                       # smoothing beats filtering
    z = (mu_g[:, :2] - tr[:, :2]) / np.sqrt(np.stack([P_g[:, 0, 0], P_g[:, 1, 1]], 1))
    assert 0.4 < z.std() < 1.5                                 # covariances of the right size
    _, _, ll_bad, _ = ekfs.forward(mu0, P0, u * 0.5, sig, ptr, lm, zr, zb, m.reading_poly, 1.0, 0.5, use)
    assert ll > ll_bad + 100                                   # p(O | lambda) prefers the truth
    d, _ = ekfs.action_means(mu_a, P_a, Ld, ed, u, sig)
    vel = np.zeros_like(m.velocities)
    np.add.at(vel, act, d / log.dt[:, None])
    vel /= np.bincount(act, minlength=len(vel))[:, None]
    rms = np.sqrt(np.mean((vel - m.velocities) ** 2, axis=0))
    assert np.all(rms < [0.005, 0.005, 0.02])                   # eq. 6 at the truth stays near the truth


def test_both_action_models_answer_the_same_questions(true_case):
    """A velocity table and a command map round-trip their parameter vector through the model, and the M-step's
    least squares on noise-free displacements returns the velocities that made them."""
    from casm_graph.models.command_model import for_commands
    from casm_graph.sim.floor import FloorConfig, simulate as simulate_floor

    log, m = true_case
    floor_log, _ = simulate_floor(FloorConfig(minutes=2, seed=1))
    cm = for_commands(floor_log.controls, 2, 1, gain=1.0).with_params(np.array([0.01, 0.9, -0.05, 0.02, 1.1]))
    floor = m.with_action(cm)
    for lg, model in ((log, m), (floor_log, floor)):
        act = model.action
        p = act.params
        assert model.with_action_params(p + 0.5).action.params == pytest.approx(p + 0.5)
        moved = act.step_displacements(lg)
        refit = model.with_action_params(np.zeros_like(p)).fitted_to_steps(lg, moved)
        assert refit.action.params == pytest.approx(p, abs=1e-9)
        assert refit.to_json()["action_model"]["kind"] == act.kind
    assert m.action.std_summary() is None and m.action.describe().startswith("action table")


def test_each_kind_of_action_model_has_its_calibration_part(true_case):
    """Every action part of the graph has a calibration part and a diagnosis's candidate part of its kind; the
    calibration part starts a log of that kind with a model of that kind; graph-em's step graph moves each step as
    the model does, whichever the kind."""
    log, m = true_case
    floor_log, _ = simulate_floor(FloorConfig(minutes=2, seed=1))
    floor = m.with_action(for_commands(floor_log.controls, 2, 1, gain=1.0).with_params(
        np.array([0.01, 0.9, -0.05, 0.02, 1.1])))
    assert set(KINDS) == set(ACTIONS) == set(BENCHES) == set(ACTION_MODELS)
    for lg, model in ((log, m), (floor_log, floor)):
        part = kind(lg.action_model_kind)
        start = part.start_model(lg, 3)
        assert start.action.kind == part.name == lg.action_model_kind == model.action.kind
        assert isinstance(default_layout(lg, start), ACTIONS[part.name].layout_type)
        lay, seen = step_graph(lg, model)
        assert np.array_equal(lay.knots, np.arange(lg.steps + 1))
        assert np.allclose(seen.velocities[lay.seg_action] * lg.dt[:, None], model.step_displacements(lg))
    assert set(m.action.std_json()) == {"velocity_std"} and set(floor.action.std_json()) == {"command_std"}
    for model in (m, floor):       # the figures a fleet's drift follows, read from model.json by the part
        am = model.action.to_json()
        figures = ACTION_MODELS[am["kind"]].figures(am)
        assert len(figures) == len(model.action.params) and all(np.isfinite(v) for _, _, v, _ in figures)


def test_a_model_is_made_ready_for_a_log_or_says_why(true_case):
    """A table is indexed like the log's actions; a table missing one, or a map on a table log, is a LogError."""
    from casm_graph.io.log import LogError
    from casm_graph.models.command_model import for_commands

    log, m = true_case
    extra = m.with_(action_ids=np.append(m.action_ids, m.action_ids.max() + 1),
                    velocities=np.vstack([m.velocities, [9.0, 9.0, 9.0]]))
    ready = extra.for_log(log)
    assert np.array_equal(ready.action_ids, log.action_ids) and np.allclose(ready.velocities, m.velocities)
    with pytest.raises(LogError, match=r"no velocity for action\(s\) \[%d\]" % m.action_ids[0]):
        m.with_(action_ids=m.action_ids[1:], velocities=m.velocities[1:]).for_log(log)
    with pytest.raises(LogError, match="command map .* runs discrete actions"):
        m.with_action(for_commands(np.ones((3, 2)))).for_log(log)


def test_the_em_m_step_regresses_the_curve_in_its_own_variable(true_case):
    """graph-EM's M-step fits the sensor curve in the model's variable: readings that are exactly a cubic in 1/d,
    the poses known, give back that cubic. It regressed on powers of d whatever the basis, so a curve in 1/d ran
    away (graph-em --sensor-basis inverse_distance 0.45-1.6 m from the truth on the omni worlds)."""
    log, m = true_case
    poses = log.truth[:, 1:]
    c = np.array([2.0, 150.0, -20.0, 3.0])
    exact = curve(distances(poses[log.obs_step], log), c, "inverse_distance")
    log = replace(log, obs_reading=np.where(np.isnan(log.obs_reading), np.nan, exact))
    W, X = np.zeros((len(poses), 3, 3)), np.zeros((len(poses) - 1, 3, 3))
    fitted = m_step(log, m.with_(reading_poly=np.zeros(4), reading_basis="inverse_distance"), poses, W, X)
    assert fitted.reading_poly == pytest.approx(c, rel=1e-6)
    assert fitted.reading_sigma < 1e-6
