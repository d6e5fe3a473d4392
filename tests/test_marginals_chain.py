"""The chain's selected inversion (:func:`casm_graph.fit.solve.chain_marginals`) gives gtsam.Marginals' numbers: every
pose's covariance and the parameter block's, on a fitted action-table log and a fitted floor log, and a ridge on a
singular system only; its solves give the noise step's sparse LU's."""
from types import SimpleNamespace

import gtsam
import numpy as np
import pytest
import scipy.sparse as sp
from gtsam.symbol_shorthand import V, X

import casm_graph as cg
from casm_graph.fit import continuous as CT
from casm_graph.fit.methods import METHODS
from casm_graph.fit.solve import world_std
from casm_graph.fit.outliers import prune
from casm_graph.fit.solve import RIDGES, chain_marginals, marginals
from casm_graph.graph.chain import arrow_blocks, arrow_inverse, arrow_solver, solve_arrow
from casm_graph.graph import noise
from casm_graph.graph import table as G
from casm_graph.graph.problem import THETA, Problem
from casm_graph.models.effects import get as get_effect
from casm_graph.models.model import paper_start

RTOL = 1e-6


def gtsam_poses(mg: gtsam.Marginals, n: int) -> np.ndarray:
    return np.array([mg.marginalCovariance(X(i)) for i in range(n)])


@pytest.fixture(scope="module")
def table_fit():
    log, _ = cg.simulate("aibo", minutes=2, seed=1)
    fit = METHODS["graph"](log, paper_start(log), seed=1)
    pruned = np.zeros(len(log.obs_t), bool)
    pruned[fit.notes["outliers_pruned"]] = True
    return prune(log, pruned), fit


def test_table_graph_marginals_equal_gtsam(table_fit):
    log, fit = table_fit
    lay = G.layout(log, fit.model, stride=1)
    problem = Problem(log, fit.model, lay=lay)
    st = problem.state(fit.poses, fit.model)
    m, ridge = chain_marginals(problem, st)
    assert ridge == 0.0
    mg = gtsam.Marginals(problem.linearize(st), gtsam.VectorValues())
    ref = gtsam_poses(mg, lay.n_poses)
    np.testing.assert_allclose(m.pose_cov, ref, rtol=RTOL, atol=RTOL * np.abs(ref).max())
    joint = mg.marginalCovariance(THETA)               # table rows, then the curve
    np.testing.assert_allclose(m.param_cov, joint, rtol=RTOL, atol=RTOL * np.abs(joint).max())
    # what the fit reported: the pose std in the map frame, the velocity and polynomial std
    std = np.sqrt(np.diagonal(ref, axis1=1, axis2=2))
    np.testing.assert_allclose(fit.pose_std, world_std(fit.poses, std, ref[:, :2, :2]), rtol=RTOL)
    np.testing.assert_allclose(fit.model.velocity_std, np.sqrt(np.diag(joint)[:3 * lay.n_actions]).reshape(-1, 3),
                               rtol=RTOL)
    np.testing.assert_allclose(fit.model.reading_poly_std, np.sqrt(np.diag(joint)[3 * lay.n_actions:]), rtol=RTOL)


def test_noise_step_solves_equal_the_sparse_lu(table_fit):
    log, fit = table_fit
    lay = G.layout(log, fit.model, stride=1)
    problem = Problem(log, fit.model, lay=lay)
    st = problem.state(fit.poses, fit.model)
    A, _, groups = problem.jacobian(st)
    chain, lu = arrow_solver(A, lay.n_poses), noise.information_lu(A, np.arange(A.shape[1]))
    b = np.random.default_rng(0).normal(size=(A.shape[1], 5))
    np.testing.assert_allclose(chain.solve(b), lu.solve(b), rtol=1e-8, atol=1e-8 * np.abs(lu.solve(b)).max())
    np.testing.assert_allclose(chain.solve(b[:, 0]), lu.solve(b[:, 0]), rtol=1e-8,
                               atol=1e-8 * np.abs(lu.solve(b[:, 0])).max())
    ours, theirs = noise.hat_traces(A, groups, seed=2, lu=chain), noise.hat_traces(A, groups, seed=2, lu=lu)
    assert ours == pytest.approx(theirs, rel=1e-9)


def test_floor_graph_marginals_equal_gtsam():
    log, _ = cg.simulate("floor", minutes=2, seed=1)
    fit = CT.fit(log, marginals=False)
    lay = CT.layout(log, CT.DEFAULTS.full_knot_dt)
    kp = fit.poses[lay.knots]
    problem = Problem(log, fit.model, lay=lay, poses=kp)
    st = problem.state(kp, fit.model)
    m, ridge = chain_marginals(problem, st)
    assert ridge == 0.0
    mg = gtsam.Marginals(problem.linearize(st), gtsam.VectorValues())
    ref = gtsam_poses(mg, lay.n_poses)
    np.testing.assert_allclose(m.pose_cov, ref, rtol=RTOL, atol=RTOL * np.abs(ref).max())
    for key in (THETA,):
        np.testing.assert_allclose(m.marginalCovariance(key), mg.marginalCovariance(key), rtol=RTOL,
                                   atol=RTOL * np.abs(mg.marginalCovariance(key)).max())
    np.testing.assert_allclose(m.marginalCovariance(X(5)), ref[5])


@pytest.mark.parametrize("hooked", [(), ("battery_fade", "camera_latency")])
def test_floor_graph_damped_step_equals_gtsam(hooked):
    """The continuous graph's own elimination (what least_squares uses) solves GTSAM's damped linear graph."""
    log, _ = cg.simulate("floor", minutes=1, seed=2)
    effects = [get_effect(n)(log) for n in hooked]
    lay = CT.layout(log, CT.DEFAULTS.coarse_knot_dt)
    m = CT.start_model(log).with_(command=CT.for_commands(log.controls, 2, 1, gain=0.95),
                                  reading_poly=np.array([0.01, 1.0, 0.0, 0.0]))
    problem = Problem(log, m, effects, lay=lay, poses=log.truth[lay.knots, 1:] + 0.02)
    st = problem.state(log.truth[lay.knots, 1:] + 0.02, m)
    st.theta[:] = 0.01
    lam = 1e-3
    ours = problem.retract(st, problem.solve_damped(problem.normal_equations(st), lam))
    g = problem.linearize(st)
    for key, dim in problem.keys_dims():
        g.add(key, np.sqrt(lam) * np.eye(dim), np.zeros(dim), gtsam.noiseModel.Unit.Create(dim))
    theirs = problem.retract(st, g.optimize())
    for a, b in ((ours.poses, theirs.poses), (ours.params, theirs.params), (ours.poly, theirs.poly),
                 (ours.theta, theirs.theta)):
        np.testing.assert_allclose(a, b, rtol=1e-7, atol=1e-9)


@pytest.mark.parametrize("anchor", [None, 0.3])
def test_table_pose_chain_step_equals_gtsam(table_fit, anchor):
    """The table graph's poses alone (graph-em's E-step), with and without the ranges-only heading anchor: the
    chain's own damped step (the problem's poses-only normal equations) solves GTSAM's damped poses-only graph."""
    log, fit = table_fit
    lay = G.layout(log, fit.model, stride=1)
    problem = Problem(log, fit.model, lay=lay, anchor=anchor)
    st = problem.state(fit.poses + np.random.default_rng(0).normal(0.0, 0.02, fit.poses.shape), fit.model)
    lam = 1e-3
    dp, _ = solve_arrow(*problem.normal_equations(st, poses_only=True), lam)
    g = problem.linearize(st, poses_only=True)
    for i in range(lay.n_poses):
        g.add(X(i), np.sqrt(lam) * np.eye(3), np.zeros(3), gtsam.noiseModel.Unit.Create(3))
    delta = g.optimize()
    np.testing.assert_allclose(dp, np.array([delta.at(X(i)) for i in range(lay.n_poses)]), rtol=1e-7, atol=1e-10)


def tiny(pin: np.ndarray):
    """Three poses joined by relative factors that also read a 2-vector parameter; ``pin`` observes pose 0."""
    rng = np.random.default_rng(0)
    Hv = rng.normal(size=(2, 3, 2))
    rows = [np.hstack([-np.eye(3), np.eye(3), np.zeros((3, 3)), Hv[0]]),
            np.hstack([np.zeros((3, 3)), -np.eye(3), np.eye(3), Hv[1]]),
            np.hstack([pin, np.zeros((3, 8))]),
            np.hstack([np.zeros((2, 9)), 0.1 * np.eye(2)])]
    A = sp.csr_matrix(np.vstack(rows))
    keys_dims = [(X(0), 3), (X(1), 3), (X(2), 3), (V(0), 2)]
    problem = SimpleNamespace(lay=SimpleNamespace(n_poses=3), keys_dims=lambda: keys_dims,
                              jacobian=lambda st: (A, None, None))
    g = gtsam.GaussianFactorGraph()
    unit3 = gtsam.noiseModel.Unit.Create(3)
    g.add(X(0), -np.eye(3), X(1), np.eye(3), V(0), Hv[0], np.zeros(3), unit3)
    g.add(X(1), -np.eye(3), X(2), np.eye(3), V(0), Hv[1], np.zeros(3), unit3)
    g.add(X(0), pin, np.zeros(3), unit3)
    g.add(V(0), 0.1 * np.eye(2), np.zeros(2), gtsam.noiseModel.Unit.Create(2))
    return problem, g, keys_dims


def test_well_posed_system_needs_no_ridge():
    problem, g, keys_dims = tiny(np.eye(3))
    m, ridge = chain_marginals(problem, None)
    ref, ref_ridge = marginals(g, keys_dims)
    assert ridge == ref_ridge == 0.0
    for key in (X(0), X(1), X(2), V(0)):
        np.testing.assert_allclose(m.marginalCovariance(key), ref.marginalCovariance(key), rtol=RTOL,
                                   atol=RTOL * np.abs(ref.marginalCovariance(key)).max())


def test_singular_system_gets_the_smallest_ridge_that_works():
    problem, _, _ = tiny(np.diag([1.0, 1.0, 0.0]))    # the chain's heading is not observed at all
    m, ridge = chain_marginals(problem, None)
    assert ridge > 0
    blocks = arrow_blocks(problem.jacobian(None)[0], 3)
    for smaller in [0.0, *(r for r in RIDGES if r < ridge)]:
        with pytest.raises(np.linalg.LinAlgError):
            arrow_inverse(blocks, smaller * blocks["top"])
    A = problem.jacobian(None)[0].toarray()
    H = A.T @ A
    cov = np.linalg.inv(H + ridge * np.diag(H).max() * np.eye(len(H)))
    for i in range(3):
        np.testing.assert_allclose(m.pose_cov[i], cov[3 * i:3 * i + 3, 3 * i:3 * i + 3], rtol=RTOL,
                                   atol=RTOL * np.abs(cov).max())
    np.testing.assert_allclose(m.param_cov, cov[9:, 9:], rtol=RTOL, atol=RTOL * np.abs(cov).max())
    assert m.pose_cov[1][0, 0] < 10 and m.pose_cov[1][2, 2] > 1e5      # determined directions stay, the free one shows


def test_a_factor_across_the_chain_is_refused():
    A = sp.csr_matrix(np.hstack([np.eye(3), np.zeros((3, 3)), np.eye(3)]))
    with pytest.raises(ValueError, match="not a pose chain"):
        arrow_blocks(A, 3)
