"""The EKFS-EM paper's algorithm (PAPERS.md section 1), as the baseline the graph is checked against.

E-step: EKF forward pass with p(O|lambda), backward filter from infinite covariance, two-filter
smoothing (:mod:`casm_graph.fit.ekfs`). M-step: each action's per-step displacement is the average
over its steps of E[d(s_t, s_t+1)] under the pairwise posterior (paper eq. 6); the polynomial is
a regression on one sample per sighting from gamma_t; the sigmas are the sampled expected squared
residuals. First-iteration outliers are pruned by their innovation; it stops when ``patience``
iterations pass without a new best likelihood and returns the best model seen. Before the filters run, the
sightings graph-em sets aside as gross outliers at the graph methods' coarse start are set aside too: the
innovation test, judged against the filter's own covariance at the loose start, passed every one of MRCLAM robot
5's wild sightings, which then dragged the filters 2-3 m off Vicon's path (the paper's simulated logs have none:
at most one of 13,500 sightings is set aside there).

Sigma_A is the paper's per step of its 30-Hz log and is carried to a log of other step times as a noise per
unit time (:func:`paper_sigma_a`): unchanged on the paper's logs, 0.55 times on MRCLAM's 0.01-s steps.

The paper does not say what it knew of the first pose (pi). A vague pi (the map's centre, heading
unknown) lets the EKF lock onto a wrong heading on some logs, so pi is centred on the first pose
of the log-only global initialiser (:mod:`casm_graph.fit.initialise`) with a wide ``START_STD``; the
table and the sensor model still start from nothing, as in the paper, and pi is re-estimated
every iteration (its M-step is the smoothed first pose).

``ekfs-em-learned`` (:func:`fit_learned`) is the same algorithm with Sigma_A learned and the
initialiser's start: the variant the 8-minute cross-check compares with the graph methods.

On continuous ``v,w`` logs each step's displacement comes from the command map and the action M-step
regresses the expected displacements on the map's basis (``Model.fitted_to_steps``); the paper has no
start for a command map and a zero map never moves, so both variants start from the continuous window
start (:func:`casm_graph.fit.continuous.initialise`).
"""
from __future__ import annotations

import time

import numpy as np

from casm_graph.fit import ekfs
from casm_graph.fit.methods.base import Fit, Progress, register
from casm_graph.fit.methods.kinds import kind
from casm_graph.fit.outliers import set_aside
from casm_graph.io.log import Log, wrap
from casm_graph.models.model import Model

OUTLIER_M2 = 13.8          # chi-square, 2 dof, 0.999: an innovation this unlikely is pruned
PATIENCE = 50
MAX_ITERATIONS = 1500
START_STD = (0.5, 0.5, 0.5)     # prior std of the first pose around the log-only initialiser's guess
MIN_ACTION_SIGMA = 1e-4         # floor of a learned Sigma_A's std per axis (m, m, rad per step)
PAPER_STEP = 1.0 / 30.0         # s: the paper's Sigma_A is per step of its 30-Hz Aibo log


def paper_sigma_a(sigma, log: Log) -> np.ndarray:
    """The paper's fixed Sigma_A stds ``sigma`` (per step of its 1/30-s log) per median step of ``log``: motion
    noise as a random walk, its std growing with the square root of the time (as every method here scales a
    step's noise by its length). The paper's own logs keep it as written; MRCLAM's 0.01-s odometry steps would take
    it as a heading noise of 1 rad per square-root second, and the smoother then follows the sightings."""
    return np.asarray(sigma, float) / np.sqrt(log.in_median_steps(PAPER_STEP))


def _observations(log: Log):
    order = np.argsort(log.obs_step, kind="stable")
    steps = log.obs_step[order]
    ptr = np.searchsorted(steps, np.arange(log.steps + 2)).astype(np.int64)
    lm = log.landmark_xy[log.landmark_index[order]]
    return order, ptr, np.ascontiguousarray(lm), log.obs_reading[order].copy(), log.obs_bearing[order].copy()


def start_of(log: Log, start: Model):
    """The log-only start (poses and a model) of ``start``'s kind of action model."""
    return kind(start.action.kind).initialise(log, start)


def velocity_errors(model: Model, truth: dict | None) -> np.ndarray | None:
    if truth is None or "velocities" not in truth.get("action_model", {}):     # a table's truth only
        return None
    tv = np.array([truth["action_model"]["velocities"][str(int(a))] for a in model.action_ids])
    return np.sqrt(np.mean((model.velocities - tv) ** 2, axis=0))


@register("ekfs-em")
def fit(log: Log, start: Model, seed: int = 0, progress: Progress | None = None,
        max_iterations: int = MAX_ITERATIONS, patience: int = PATIENCE, truth: dict | None = None,
        start_pose: tuple | None = None, learn_action_noise: bool = False, from_initialiser: bool = False,
        overrelax: float = 1.0, outlier_m2: float = OUTLIER_M2, name: str = "ekfs-em") -> Fit:
    """Calibrate ``log`` with EKFS-EM from the paper's start; ``truth`` only records errors per iteration
    (table RMS, and the forward filter's heading RMS when the log has a trajectory).

    ``learn_action_noise`` departs from the paper, which keeps Sigma_A fixed: the M-step also sets
    Sigma_A (diagonal, shared by the actions) to the expected squared deviation of each step's
    displacement from its action's new mean under the pairwise posterior, as EM would.
    ``from_initialiser`` departs from the paper's zero-velocity start: the table and the polynomial
    start where the graph methods start, from the log-only initialiser. ``outlier_m2``: the squared Mahalanobis
    innovation beyond which a sighting is pruned at the first iteration. ``name`` is the method recorded in
    the model's fit section.
    """
    progress = progress or Progress()
    t0 = time.perf_counter()
    rng = np.random.default_rng(seed)
    co = kind(start.action.kind).coarse(log, start, seed, progress)
    log, gross = set_aside(log, co.model, co.poses)       # graph-em's gross outliers, before the filters see them
    from_initialiser = from_initialiser or not start.action.zero_start
    order, ptr, lm, z_r, z_b = _observations(log)
    dt = log.dt
    sig = np.asarray(start.motion_noise, float) if learn_action_noise else paper_sigma_a(start.motion_noise, log)
    model = start
    if start_pose is None or from_initialiser:
        progress.stage("start pose", None)
        init = start_of(log, start)
        if from_initialiser:
            model = start.with_action(init.model.action).with_(
                reading_poly=np.asarray(init.model.reading_poly, float).copy())
    poly = np.asarray(model.reading_poly, float).copy()
    s_r, s_b = float(start.reading_sigma), float(start.bearing_sigma)
    if start_pose is None:
        mu0 = init.poses[0]
        P0 = np.diag(np.square(START_STD))
    else:
        mu0, P0 = np.asarray(start_pose[0], float), np.asarray(start_pose[1], float)
    use = np.ones(len(z_r), bool)
    deg = len(poly) - 1
    history = {"log_likelihood": [], "velocity_rms": [], "velocities": [], "heading_rms": [], "seconds": []}
    true_heading = (log.truth[:, 3] if truth is not None and log.truth is not None and len(log.truth) == log.steps + 1
                    else None)
    best = None
    progress.stage("ekfs-em", max_iterations)
    for it in range(max_iterations):
        u = model.step_displacements(log)
        step_sig = ekfs.step_sigmas(sig, log)
        mu_a, P_a, ll, m2 = ekfs.forward(mu0, P0, u, step_sig, ptr, lm, z_r, z_b, poly, s_r, s_b, use)
        if it == 0:
            use = ~(m2 > outlier_m2)
            mu_a, P_a, ll, m2 = ekfs.forward(mu0, P0, u, step_sig, ptr, lm, z_r, z_b, poly, s_r, s_b, use)
        model = model.with_(reading_poly=poly.copy(), reading_sigma=s_r, bearing_sigma=s_b, motion_noise=sig.copy())
        history["log_likelihood"].append(float(ll))
        err = velocity_errors(model, truth)
        history["velocity_rms"].append(None if err is None else err.tolist())
        history["velocities"].append(model.action.params)
        history["heading_rms"].append(None if true_heading is None else
                                      float(np.sqrt(np.mean(wrap(mu_a[:, 2] - true_heading) ** 2))))
        history["seconds"].append(time.perf_counter() - t0)
        progress.step(1, cost=-ll)
        if best is None or ll > best[0]:
            best = (ll, it, model, None)
            need_poses = True
        else:
            need_poses = False
        if it - best[1] >= patience:
            break

        Lb, eb, Ld, ed = ekfs.backward(mu_a, u, step_sig, ptr, lm, z_r, z_b, poly, s_r, s_b, use)
        mu_g, P_g = ekfs.smooth(mu_a, P_a, Lb, eb)
        if need_poses:
            best = (best[0], best[1], best[2], (mu_g, P_g))
        d, d_var = ekfs.action_means(mu_a, P_a, Ld, ed, u, step_sig, variance=learn_action_noise)
        model = model.fitted_to_steps(log, d)
        if learn_action_noise:
            resid = d - model.step_displacements(log)
            resid[:, 2] = wrap(resid[:, 2])
            em = np.sqrt(np.mean((resid ** 2 + d_var) / log.in_median_steps(dt)[:, None], axis=0))   # per median step
            sig = np.maximum(sig * (em / sig) ** overrelax, MIN_ACTION_SIGMA)

        k = log.obs_step[order]
        L = np.linalg.cholesky(P_g[k] + 1e-12 * np.eye(3))
        s = mu_g[k] + np.einsum("nij,nj->ni", L, rng.standard_normal((len(k), 3)))
        rel = lm - s[:, :2]
        dist = np.hypot(rel[:, 0], rel[:, 1])
        ok_r = use & ~np.isnan(z_r)
        ok_b = use & ~np.isnan(z_b)
        if ok_r.any():
            poly = np.polynomial.polynomial.polyfit(dist[ok_r], z_r[ok_r], deg)
            s_r = float(np.sqrt(np.mean((np.polynomial.polynomial.polyval(dist[ok_r], poly) - z_r[ok_r]) ** 2)))
        if ok_b.any():
            s_b = float(np.sqrt(np.mean(wrap(np.arctan2(rel[ok_b, 1], rel[ok_b, 0]) - s[ok_b, 2] - z_b[ok_b]) ** 2)))
        mu0, P0 = mu_g[0].copy(), P_g[0] + np.diag([1e-4, 1e-4, 1e-4])

    ll, best_it, model, poses = best
    if poses is None:
        Lb, eb, _, _ = ekfs.backward(mu_a, u, step_sig, ptr, lm, z_r, z_b, poly, s_r, s_b, use)
        poses = ekfs.smooth(mu_a, P_a, Lb, eb)
    mu_g, P_g = poses
    d = np.hypot(*(log.landmark_xy[log.landmark_index] - mu_g[log.obs_step, :2]).T)
    d = d[~np.isnan(log.obs_reading)]
    pose_std = np.sqrt(np.stack([P_g[:, 0, 0], P_g[:, 1, 1], P_g[:, 2, 2]], axis=1))
    model = model.with_(distance_range=(float(d.min()), float(d.max())) if len(d) else (0.0, 0.0),
                        fit={"method": name, "iterations": it + 1, "best_iteration": best_it + 1,
                             "seconds": round(time.perf_counter() - t0, 3), "log_likelihood": float(ll),
                             "converged": bool(it - best_it >= patience),
                             "outliers_pruned": int(gross.sum() + (~use).sum()),
                             "ekfs": {"max_iterations": max_iterations, "patience": patience,
                                      "outlier_m2": outlier_m2, "learn_action_noise": learn_action_noise,
                                      "from_initialiser": from_initialiser, "overrelax": overrelax,
                                      "sigma_a_step": None if learn_action_noise else PAPER_STEP}})
    ll_hist = history["log_likelihood"]
    return Fit(model=model, poses=mu_g, pose_std=pose_std, cost=[-x for x in ll_hist],
               stages=["ekfs-em"] * len(ll_hist), iterations=it + 1, converged=model.fit["converged"],
               log_likelihood=float(ll), notes={"history": history})


LEARNED_OVERRELAX = 3.0          # log-space step on Sigma_A: EM's own step creeps (hundreds of iterations)
LEARNED_MAX_ITERATIONS = 500     # Sigma_A keeps creeping down, so the likelihood has no plateau to stop on


@register("ekfs-em-learned")
def fit_learned(log: Log, start: Model, seed: int = 0, progress: Progress | None = None,
                max_iterations: int = LEARNED_MAX_ITERATIONS, **kw) -> Fit:
    """EKFS-EM with two labelled departures from the paper: Sigma_A is learned (M-step, over-relaxed in
    log space) and the table and polynomial start from the log-only initialiser, as the graph methods do.

    The paper's fixed Sigma_A (10 mm, 0.1 rad per step) is five to twenty-five times the simulator's
    motion noise, so its smoother follows the sightings step by step; the zero start lets one action
    settle on a turn-rate alias on some 8-minute logs. This variant is what the cross-check compares.
    """
    return fit(log, start, seed=seed, progress=progress, max_iterations=max_iterations, learn_action_noise=True,
               from_initialiser=True, overrelax=LEARNED_OVERRELAX, name="ekfs-em-learned", **kw)
