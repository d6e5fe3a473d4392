"""graph-EM: the EM-style alternative on the factor graph.

E-step: with the model fixed, smooth the poses on the graph (poses-only Levenberg-Marquardt) and
take their Gaussian marginals, each pose's covariance and the cross-covariance of consecutive
poses (:mod:`casm_graph.graph.chain`, equal to ``gtsam.Marginals`` to machine precision). M-step: closed
form, with exact Gaussian expectations and no sampling: E[R(-theta) dp] by Stein's lemma for the
table, Gaussian moments of the curve's linearised variable (d or 1/d) for the polynomial regression,
expected squared residuals for the sigmas and the motion noise. The objective recorded per iteration is the Laplace
marginal likelihood log p(O | model). On continuous ``v,w`` logs the E-step holds each step's velocity
at the command map's (:func:`step_graph`) and the M-step regresses the expected displacements on the
map's basis; the start is the continuous graph's coarse start, as a table's is the table graph's.
"""
from __future__ import annotations

import time

import numpy as np

from casm_graph.fit.methods.base import Fit, Progress, register
from casm_graph.fit.methods.graph import GraphOptions
from casm_graph.fit.methods.kinds import kind
from casm_graph.fit.outliers import set_aside
from casm_graph.fit.solve import least_squares
from casm_graph.graph import chain, robust
from casm_graph.graph import table as G
from casm_graph.graph.actions import ACTIONS
from casm_graph.graph.problem import Problem, State
from casm_graph.io.log import Log
from casm_graph.models.model import Model
from factors.reading import curve, features

MAX_ITERATIONS = 40
TOL = 1e-6           # stop when the marginal likelihood improves by less than this fraction


def _world(poses, cov, cross):
    """Body-tangent covariances to map-frame (x, y, theta) ones."""
    c, s = np.cos(poses[:, 2]), np.sin(poses[:, 2])
    J = np.zeros((len(poses), 3, 3))
    J[:, 0, 0], J[:, 0, 1], J[:, 1, 0], J[:, 1, 1], J[:, 2, 2] = c, -s, s, c, 1.0
    W = J @ cov @ np.transpose(J, (0, 2, 1))
    X = J[:-1] @ cross @ np.transpose(J[1:], (0, 2, 1))
    return W, X


def gaussian_moments(mu: np.ndarray, var: np.ndarray, n: int) -> np.ndarray:
    """(N, n+1) raw moments E[d^k] of d ~ N(mu, var), k = 0..n."""
    m = np.empty((len(mu), n + 1))
    m[:, 0] = 1.0
    if n:
        m[:, 1] = mu
    for k in range(2, n + 1):
        m[:, k] = mu * m[:, k - 1] + (k - 1) * var * m[:, k - 2]
    return m


def expected_displacement(poses, W, X):
    """E[d] and Cov[d] per step for d = (R(-theta_i)(p_{i+1} - p_i), theta_{i+1} - theta_i)."""
    a, b = poses[:-1], poses[1:]
    th = a[:, 2]
    c, s = np.cos(th), np.sin(th)
    Wa, Wb = W[:-1], W[1:]
    dp = b[:, :2] - a[:, :2]
    cov_dp_th = np.transpose(X, (0, 2, 1))[:, :2, 2] - Wa[:, :2, 2]    # Cov(p_{i+1} - p_i, theta_i)
    var_th = Wa[:, 2, 2]
    damp = np.exp(-0.5 * var_th)
    e_cos_dp = damp[:, None] * (c[:, None] * dp - s[:, None] * cov_dp_th)
    e_sin_dp = damp[:, None] * (s[:, None] * dp + c[:, None] * cov_dp_th)
    Ed = np.column_stack([e_cos_dp[:, 0] + e_sin_dp[:, 1], -e_sin_dp[:, 0] + e_cos_dp[:, 1],
                          b[:, 2] - a[:, 2]])
    Ed[:, 2] = (Ed[:, 2] + np.pi) % (2 * np.pi) - np.pi
    # first-order covariance of d through the 6-D pair covariance
    ex, ey = dp[:, 0], dp[:, 1]
    L = np.zeros((len(a), 3, 6))
    L[:, 0, 0], L[:, 0, 1], L[:, 0, 2] = -c, -s, -s * ex + c * ey
    L[:, 1, 0], L[:, 1, 1], L[:, 1, 2] = s, -c, -c * ex - s * ey
    L[:, 2, 2] = -1.0
    L[:, 0, 3], L[:, 0, 4], L[:, 1, 3], L[:, 1, 4], L[:, 2, 5] = c, s, -s, c, 1.0
    S = np.zeros((len(a), 6, 6))
    S[:, :3, :3], S[:, 3:, 3:], S[:, :3, 3:] = Wa, Wb, X
    S[:, 3:, :3] = np.transpose(X, (0, 2, 1))
    return Ed, L @ S @ np.transpose(L, (0, 2, 1))


def huber_sigma(expected_sq: np.ndarray, z: np.ndarray, efficiency: float) -> float:
    """A sighting sigma from expected squared residuals and the whitened residuals ``z`` that set their Huber (IRLS)
    weights, by the noise step's rule (:func:`casm_graph.graph.noise.group_scales`): the rows within the gate, their
    Huber-weighted sum divided by ``efficiency`` (the weighting's Gaussian efficiency where the action part's noise
    rules correct for it, else 1). A plain mean let wild sightings set the sigma, which the E-step's Huber loss then
    did not weigh as assumed (MRCLAM robot 4: the bearing sigma grew to 3.6 times graph's, and EM steps lowered the
    marginal likelihood)."""
    keep = np.abs(z) <= robust.GATE
    if not keep.any():
        keep = np.ones(len(z), bool)
    w = robust.huber(z[keep]) ** 2
    return float(np.sqrt(max(float(np.sum(w * expected_sq[keep])), 0.0) / (efficiency * keep.sum())))


def m_step(log: Log, model: Model, poses, W, X) -> Model:
    """Closed-form model update from the smoothed poses (one per step) and their covariances; sightings weighed
    through Huber's loss as the E-step's graph weighs them."""
    Ed, Cd = expected_displacement(poses, W, X)
    new = model.fitted_to_steps(log, Ed)
    res = Ed - new.step_displacements(log)
    rules = ACTIONS[model.action.kind].rules(model)          # what graph's noise step assumes of this robot
    steps = log.in_median_steps(log.dt)[:, None]                # the levels are per step of the median length
    motion = rules.apply(np.sqrt(np.mean((res ** 2 + np.diagonal(Cd, axis1=1, axis2=2)) / steps, axis=0)))
    efficiency = robust.HUBER_EFFICIENCY if rules.huber_efficiency else 1.0

    lm = log.landmark_xy[log.landmark_index]
    p = poses[log.obs_step]
    Wp = W[log.obs_step]
    rel = lm - p[:, :2]
    d = np.hypot(rel[:, 0], rel[:, 1])
    g = -rel / d[:, None]                         # d dist / d (x, y)
    var_d = np.einsum("ni,nij,nj->n", g, Wp[:, :2, :2], g)
    ok = ~np.isnan(log.obs_reading)
    poly, s_r = np.asarray(model.reading_poly, float), float(model.reading_sigma)
    if ok.any():
        deg = len(poly) - 1
        u, du = (f[:, 1] for f in features(d[ok], 2, model.reading_basis))   # the curve's variable (d or 1/d)
        mom = gaussian_moments(u, du ** 2 * var_d[ok], 2 * deg)
        idx = np.arange(deg + 1)
        EPP = mom[:, idx[:, None] + idx[None, :]]     # E[phi phi^T]
        EP = mom[:, :deg + 1]
        z = log.obs_reading[ok]
        zr = (z - curve(d[ok], poly, model.reading_basis)) / s_r      # whitened at the model the E-step used
        w = robust.huber(zr) ** 2       # Huber weights, as the E-step's graph weighs the sightings
        A, b = np.einsum("n,nij->ij", w, EPP), (w[:, None] * EP * z[:, None]).sum(0)
        if model.reading_basis == "distance":
            poly = np.linalg.solve(A, b)
        else:                                         # powers of 1/d span decades: solved with the columns scaled
            sc = 1.0 / np.sqrt(np.maximum(np.diag(A), 1e-300))
            poly = sc * np.linalg.solve(A * np.outer(sc, sc), b * sc)
        s_r = huber_sigma(np.einsum("i,nij,j->n", poly, EPP, poly) - 2 * z * (EP @ poly) + z * z, zr, efficiency)

    okb = ~np.isnan(log.obs_bearing)
    s_b = float(model.bearing_sigma)
    if okb.any():
        r2 = d ** 2
        h = np.column_stack([rel[:, 1] / r2, -rel[:, 0] / r2, -np.ones(len(d))])   # d bearing / d (x, y, theta)
        eb = (log.obs_bearing - (np.arctan2(rel[:, 1], rel[:, 0]) - p[:, 2]) + np.pi) % (2 * np.pi) - np.pi
        s_b = huber_sigma(eb[okb] ** 2 + np.einsum("ni,nij,nj->n", h, Wp, h)[okb], eb[okb] / s_b, efficiency)
    return new.with_(reading_poly=poly, reading_sigma=float(s_r), bearing_sigma=float(s_b), motion_noise=motion)


def laplace_log_likelihood(problem: Problem, st: State, logdet: float) -> float:
    """log p(O | model) with the poses integrated out around their mode (flat prior on the first pose)."""
    r = problem.rows(st, jacobians=False)
    cost = 0.5 * float(np.sum(r.action_e ** 2) + np.sum(r.reading_e ** 2) + np.sum(r.bearing_e ** 2))
    n = r.action_e.size + r.reading_e.size + r.bearing_e.size
    log_sig = (np.sum(np.log(problem.motion_sigma)) + r.reading_e.size * np.log(problem.reading_sigma)
               + r.bearing_e.size * np.log(problem.bearing_sigma))
    k = 3 * problem.lay.n_poses
    return float(-cost - log_sig - 0.5 * n * np.log(2 * np.pi) + 0.5 * k * np.log(2 * np.pi) - 0.5 * logdet)


def _vec(m: Model) -> np.ndarray:
    return np.concatenate([m.action.params, m.reading_poly, np.log([m.reading_sigma, m.bearing_sigma]),
                           np.log(m.motion_noise)])


def _unvec(x: np.ndarray, like: Model) -> Model:
    A = len(like.action.params)
    D = len(like.reading_poly)
    sig = np.exp(x[A + D:])
    return like.with_action_params(x[:A]).with_(reading_poly=x[A:A + D], reading_sigma=float(sig[0]),
                                                bearing_sigma=float(sig[1]), motion_noise=sig[2:5])


def step_graph(log: Log, model: Model) -> tuple[G.Layout, Model]:
    """A pose at every step and the model as the graph of a table sees it: a table's own layout, or, for a command
    map, every step its own action whose velocity is the map's at that step (the E-step holds them fixed)."""
    rows, table = model.action.step_table(log)
    T = log.steps
    lay = G.Layout(np.arange(T + 1), rows, np.ones(T, int), log.dt.copy(), log.obs_step.copy(), len(table.action_ids))
    return lay, model.with_action(table)


def em_map(log: Log, model: Model, poses: np.ndarray):
    """One EM step: E-step at ``model`` (warm-started from ``poses``), then the M-step.

    Returns log p(O | model), the updated model, the smoothed poses and their marginals.
    """
    lay, seen = step_graph(log, model)
    problem = Problem(log, seen, lay=lay)
    st, _ = least_squares(problem, problem.state(poses, seen), max_iterations=10, freeze_parameters=True)
    D, B = chain.information_blocks(problem, st)
    cov, cross, logdet = chain.select_inverse(D, B)
    ll = laplace_log_likelihood(problem, st, logdet)
    W, X = _world(st.poses, cov, cross)
    return ll, m_step(log, model, st.poses, W, X), st.poses, W


@register("graph-em")
def fit(log: Log, start: Model, seed: int = 0, progress: Progress | None = None,
        max_iterations: int = MAX_ITERATIONS, tol: float = TOL, truth: dict | None = None,
        options: GraphOptions | None = None) -> Fit:
    """Calibrate ``log`` by EM on the full factor graph, from the same coarse start as ``graph`` (``options``:
    that start's)."""
    progress = progress or Progress()
    t0 = time.perf_counter()
    co = kind(start.action.kind).coarse(log, start, seed, progress, options=options)
    model, poses = co.model, co.poses
    log, pruned = set_aside(log, model, poses)    # gross outliers out, as graph prunes them: the M-step is Gaussian
    history = {"log_likelihood": [], "velocity_rms": [], "seconds": [], "squarem": []}
    progress.stage("graph-em", max_iterations)
    tv = None
    if truth is not None:
        tv = np.array([truth["action_model"]["velocities"][str(int(a))] for a in model.action_ids])

    def step(m, p):
        ll, new, p, W = em_map(log, m, p)
        history["log_likelihood"].append(ll)
        if tv is not None:
            history["velocity_rms"].append(np.sqrt(np.mean((m.velocities - tv) ** 2, axis=0)).tolist())
        history["seconds"].append(time.perf_counter() - t0)
        progress.step(1, cost=-ll)
        return ll, new, p, W

    converged = False
    best = -np.inf
    it = 0
    while it < max_iterations:
        # SQUAREM (Varadhan & Roland 2008): two EM steps, a squared extrapolation, one stabilising step
        ll0, m1, poses, W = step(model, poses)
        ll1, m2, poses1, W1 = step(m1, poses)
        it += 2
        if ll1 - max(ll0, best) < tol * abs(ll1) and ll1 >= ll0:
            model, poses, W, ll, converged = m1, poses1, W1, ll1, True
            break
        best = max(best, ll1)
        x0, x1, x2 = _vec(model), _vec(m1), _vec(m2)
        r, v = x1 - x0, x2 - 2 * x1 + x0
        alpha = min(-1.0, -np.linalg.norm(r) / max(np.linalg.norm(v), 1e-300))
        trial = _unvec(x0 - 2 * alpha * r + alpha ** 2 * v, model)
        llp, mp, posesp, Wp = step(trial, poses1)
        it += 1
        if np.isfinite(llp) and llp >= ll1:
            model, poses, W, ll = mp, posesp, Wp, llp
            history["squarem"].append(float(alpha))
        else:
            model, poses, W, ll = m2, poses1, W1, ll1
            history["squarem"].append(None)
    pose_std = np.sqrt(np.stack([W[:, 0, 0], W[:, 1, 1], W[:, 2, 2]], axis=1))
    d = np.hypot(*(log.landmark_xy[log.landmark_index] - poses[log.obs_step, :2]).T)[~np.isnan(log.obs_reading)]
    model = model.with_(distance_range=(float(d.min()), float(d.max())) if len(d) else (0.0, 0.0),
                        fit={"method": "graph-em", "iterations": it + 1, "seconds": round(time.perf_counter() - t0, 3),
                             "log_likelihood": float(ll), "converged": converged,
                             "outliers_pruned": int(pruned.sum())})
    lls = history["log_likelihood"]
    return Fit(model=model, poses=poses, pose_std=pose_std, cost=[-x for x in lls], stages=["graph-em"] * len(lls),
               iterations=it + 1, converged=converged, log_likelihood=float(ll),
               notes={"history": history, "outliers_pruned": np.flatnonzero(pruned).tolist()})
