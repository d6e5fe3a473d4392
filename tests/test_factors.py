"""Analytic Jacobians of every factor against central differences taken through GTSAM's own retraction."""
import gtsam
import numpy as np
import pytest
from gtsam.symbol_shorthand import C, V, X

import factors
from casm_graph.graph import table as G
from casm_graph.graph.problem import THETA, Problem
from casm_graph.models.model import paper_start
from casm_graph.sim.aibo import SimConfig, simulate


def numerical_jacobians(factor, values, keys, eps=1e-6):
    """d error / d tangent of each variable, by central differences through ``retract``."""
    out = []
    for key in keys:
        is_pose = values.exists(key) and isinstance(_get(values, key), gtsam.Pose2)
        dim = 3 if is_pose else len(values.atVector(key))
        J = []
        for i in range(dim):
            d = np.zeros(dim)
            d[i] = eps
            e = []
            for sign in (1, -1):
                v = gtsam.Values(values)
                if is_pose:
                    v.update(key, values.atPose2(key).retract(sign * d))
                else:
                    v.update(key, values.atVector(key) + sign * d)
                e.append(factor.unwhitenedError(v))
            J.append((e[0] - e[1]) / (2 * eps))
        out.append(np.array(J).T)
    return out


def _get(values, key):
    try:
        return values.atPose2(key)
    except RuntimeError:
        return values.atVector(key)


def analytic_jacobians(factor, values):
    lin = factor.linearize(values)
    A, _ = lin.jacobian()
    return A


def check(factor, values, keys, tol=1e-6):
    A = analytic_jacobians(factor, values)
    N = np.hstack(numerical_jacobians(factor, values, keys))
    assert A.shape == N.shape
    np.testing.assert_allclose(A, N, atol=tol, rtol=1e-5)


unit = lambda n: gtsam.noiseModel.Unit.Create(n)  # noqa: E731


@pytest.mark.parametrize("k", [1, 2, 7, 30])
@pytest.mark.parametrize("seed", range(4))
def test_action_jacobians(k, seed):
    rng = np.random.default_rng(seed)
    v = gtsam.Values()
    v.insert(X(0), gtsam.Pose2(*rng.normal(0, 1, 2), rng.uniform(-3, 3)))
    v.insert(X(1), gtsam.Pose2(*rng.normal(0, 1, 2), rng.uniform(-3, 3)))
    v.insert(V(0), rng.normal(0, [0.3, 0.3, 2.0]))
    f = factors.REGISTRY["action"].build(unit(3), (X(0), X(1), V(0)), k, 1 / 30)
    check(f, v, [X(0), X(1), V(0)])


@pytest.mark.parametrize("seed", range(6))
def test_reading_jacobians(seed):
    rng = np.random.default_rng(seed)
    v = gtsam.Values()
    v.insert(X(0), gtsam.Pose2(*rng.normal(0, 1, 2), rng.uniform(-3, 3)))
    v.insert(C(0), rng.normal(0, [30, 10, 3, 0.5]))
    f = factors.REGISTRY["reading"].build(unit(1), (X(0), C(0)), rng.normal(0, 2, 2), 17.0)
    check(f, v, [X(0), C(0)], tol=1e-4)


@pytest.mark.parametrize("seed", range(6))
def test_bearing_jacobians(seed):
    rng = np.random.default_rng(seed)
    v = gtsam.Values()
    v.insert(X(0), gtsam.Pose2(*rng.normal(0, 1, 2), rng.uniform(-3, 3)))
    f = factors.REGISTRY["bearing"].build(unit(1), (X(0),), rng.normal(0, 2, 2), rng.uniform(-3, 3))
    check(f, v, [X(0)])


def test_action_displacement_matches_stepwise_integration():
    rng = np.random.default_rng(3)
    v = rng.normal(0, [0.3, 0.3, 2.0], size=(5, 3))
    d, _ = factors.action.displacement(v, np.full(5, 12), np.full(5, 0.05))
    for vi, di in zip(v, d):
        p = np.zeros(3)
        for _ in range(12):
            c, s = np.cos(p[2]), np.sin(p[2])
            p = p + 0.05 * np.array([c * vi[0] - s * vi[1], s * vi[0] + c * vi[1], vi[2]])
        np.testing.assert_allclose(di, p, atol=1e-12)


@pytest.mark.parametrize("stride", [1])
def test_numpy_problem_matches_gtsam_graph(stride):
    """The vectorised hot path and the CustomFactor graph give the same cost and the same linear system."""
    log, truth = simulate(SimConfig(minutes=0.5, seed=4))
    m = paper_start(log)
    rng = np.random.default_rng(0)
    m = m.with_(velocities=rng.normal(0, 0.2, m.velocities.shape), reading_poly=np.array([40.0, -15, 3, -0.2]),
                reading_sigma=1.3, bearing_sigma=0.4, motion_noise=np.array([0.003, 0.004, 0.01]))
    lay = G.layout(log, m, stride)
    poses = log.truth[lay.knots, 1:] + rng.normal(0, 0.02, (lay.n_poses, 3))
    problem = Problem(log, m, lay=lay)
    st = problem.state(poses, m)
    graph = G.build(log, lay, m)
    vals = G.values(poses, m)
    assert problem.cost(st) == pytest.approx(graph.error(vals), rel=1e-9)
    ours = problem.linearize(st).optimize()
    ref = graph.linearize(vals).optimize()
    for key in [X(0), X(lay.n_poses - 1)]:
        np.testing.assert_allclose(ours.at(key), ref.at(key), rtol=1e-6, atol=1e-8)
    theta = ours.at(THETA)                    # the parameter vector: table rows, then the curve
    np.testing.assert_allclose(theta[9:12], ref.at(V(3)), rtol=1e-6, atol=1e-8)
    np.testing.assert_allclose(theta[3 * lay.n_actions:], ref.at(C(0)), rtol=1e-6, atol=1e-8)


def test_coarse_graph_jacobian_matches_numerical_differentiation():
    """A coarse layout sees each sighting from its knot's pose carried by the table velocity to the sighting's step
    (graph.problem.Problem.sighting_poses): its Jacobian, poses and table columns, against central differences."""
    log, _ = simulate(SimConfig(minutes=0.5, seed=4))
    rng = np.random.default_rng(0)
    m = paper_start(log).with_(velocities=rng.normal(0, 0.2, (len(paper_start(log).action_ids), 3)),
                               reading_poly=np.array([40.0, -15, 3, -0.2]), reading_sigma=1.3, bearing_sigma=0.4,
                               motion_noise=np.array([0.003, 0.004, 0.01]))
    lay = G.layout(log, m, 10)
    assert np.any(log.obs_step != lay.knots[lay.obs_knot])          # sightings between knots
    p = Problem(log, m, lay=lay, huber=False)
    st = p.state(log.truth[lay.knots, 1:] + rng.normal(0, 0.02, (lay.n_poses, 3)), m)
    A = p.jacobian(st)[0].toarray()
    K, h = lay.n_poses, 1e-6
    for col in list(rng.choice(3 * K, 15, replace=False)) + list(3 * K + np.arange(p.n_theta)):
        def resid(sign):
            dp, dt = np.zeros((K, 3)), np.zeros(p.n_theta)
            if col < 3 * K:
                dp[col // 3, col % 3] = sign * h
            else:
                dt[col - 3 * K] = sign * h
            return p.jacobian(p.retract(st, (dp, dt)))[1]
        num = (resid(1) - resid(-1)) / (2 * h)
        assert np.abs(num - A[:, col]).max() < 1e-6 * max(1.0, np.abs(num).max()), col


@pytest.mark.parametrize("lead", [0.0, 0.5])
def test_command_displacement_jacobian(lead):
    """The command factor's derivative with respect to the maps' coefficients, along the start or the middle
    heading of each step, against central differences."""
    rng = np.random.default_rng(3)
    n, k = 4, 9
    Bv, Bw, By = rng.normal(0, 1, (n, k, 3)), rng.normal(0, 1, (n, k, 2)), rng.normal(0, 1, (n, k, 2))
    dt = rng.uniform(0.02, 0.2, (n, k))
    p = rng.normal(0, 0.5, 7)
    _, J = factors.command.displacement(p, Bv, Bw, dt, By, lead)
    for i in range(len(p)):
        h = np.zeros(len(p))
        h[i] = 1e-6
        num = (factors.command.displacement(p + h, Bv, Bw, dt, By, lead)[0]
               - factors.command.displacement(p - h, Bv, Bw, dt, By, lead)[0]) / 2e-6
        np.testing.assert_allclose(J[:, :, i], num, atol=1e-7)


def test_a_step_along_its_middle_heading_follows_the_arc():
    """A command held over steps drives an arc: stepping along each step's middle heading ends where the arc does
    to within (w dt)^2 of the distance; along its start heading it falls v w dt / 2 per second to the outside."""
    v, w, dt, k = 1.5, 0.8, 0.1, 20
    vel, steps = np.tile([v, 0.0, w], (1, k, 1)), np.full((1, k), dt)
    T = k * dt
    arc = np.array([v / w * np.sin(w * T), v / w * (1 - np.cos(w * T))])
    mid = factors.command.integrate(vel, steps, 0.5)[0][0, :2]
    start = factors.command.integrate(vel, steps, 0.0)[0][0, :2]
    assert np.hypot(*(mid - arc)) < (w * dt) ** 2 * v * T
    assert np.hypot(*(start - arc)) == pytest.approx(v * w * dt / 2 * T, rel=0.2)
    d, _ = factors.command.displacement(np.array([v, w]), np.ones((1, k, 1)), np.ones((1, k, 1)), steps, lead=0.5)
    np.testing.assert_allclose(d[0, :2], mid)
