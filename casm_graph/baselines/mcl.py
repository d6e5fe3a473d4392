"""Monte Carlo Localization with dynamic motion models (Milstein & Wang), and the graph's estimate.

The motion model is the differential-drive one with range, turn and drift error parameters
(k_r, k_t, k_d): per step r ~ N(r_cmd, k_r |r_cmd|), theta ~ N(theta_cmd, k_t |theta_cmd| + k_d |r_cmd|)
(variances, as the paper words it). Each MCL step yields a (reported, corrected) motion pair: the
reported motion is the command, the corrected one joins the particle means after two consecutive
updates. The paper's dynamic variant refits the k's by maximum likelihood (Nelder-Mead) over a
sliding window of recent pairs, globally or per region of a grid, so the map ends up annotated
with motion parameters. ``graph_em`` estimates the same per-region parameters jointly with the
trajectory on a GTSAM factor graph (built-in Pose2 and bearing-range factors) by EM.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import gtsam
import numpy as np
from scipy.optimize import minimize

from casm_graph.io.log import Log, LogError, wrap
from casm_graph.models.effects.regional_motion_noise import MIN_SEGMENTS, estimate, variances
from casm_graph.sim.floor import region_of, simulate, step

DEFAULT_K = (0.05, 0.2, 0.05)       # generic high-variance parameters (the paper's "default static")


# ----------------------------------------------------------------------------- the log as MCL sees it
@dataclass(frozen=True)
class Drive:
    """Reported motion per step and the observations grouped by the pose they follow."""

    r: np.ndarray               # (T,) reported translation per step (v dt)
    theta: np.ndarray           # (T,) reported rotation per step (w dt)
    obs_step: np.ndarray        # (N,)
    landmark_xy: np.ndarray     # (N, 2) where each observed landmark is
    obs_range: np.ndarray       # (N,)
    obs_bearing: np.ndarray     # (N,)
    start: np.ndarray           # (3,) initial pose (known, as in tracking)
    t: np.ndarray               # (T+1,)


def drive_of(log: Log, start: np.ndarray | None = None) -> Drive:
    """The MCL view of a log with continuous ``v, w`` commands and range (``reading``)/bearing observations."""
    if log.controls is None or log.control_names != ("v", "w"):
        raise LogError("commands.csv: MCL needs continuous commands 'v,w'")
    if start is None:
        if log.truth is None:
            raise LogError("MCL tracking needs the start pose (truth.csv's first row or start=...)")
        start = log.truth[0, 1:]
    ok = np.isfinite(log.obs_reading) & np.isfinite(log.obs_bearing)
    dt = log.dt
    return Drive(r=log.controls[:, 0] * dt, theta=log.controls[:, 1] * dt, obs_step=log.obs_step[ok],
                 landmark_xy=log.landmark_xy[log.landmark_index[ok]], obs_range=log.obs_reading[ok],
                 obs_bearing=log.obs_bearing[ok], start=np.asarray(start, float), t=log.pose_times)


# ----------------------------------------------------------------------------- the motion model
def neg_log_lik(k, r_hat, t_hat, r, t) -> float:
    """-log p(corrected | reported, k) of a set of motion pairs (paper section 3.2)."""
    vr, vt = variances(k, r_hat, t_hat)
    return float(0.5 * np.sum(np.log(vr) + (r - r_hat) ** 2 / vr + np.log(vt) + wrap(t - t_hat) ** 2 / vt))


def fit_k(r_hat, t_hat, r, t, start=DEFAULT_K) -> np.ndarray:
    """Maximum-likelihood (k_r, k_t, k_d) by Nelder-Mead from ``start`` (over log k, so they stay positive)."""
    f = lambda z: neg_log_lik(np.exp(z), r_hat, t_hat, r, t)  # noqa: E731
    res = minimize(f, np.log(np.maximum(start, 1e-9)), method="Nelder-Mead",
                   options={"xatol": 1e-3, "fatol": 1e-3, "maxiter": 600})
    return np.exp(res.x)


def fit_k_expected(r_hat, t_hat, e_r2, e_t2, start=DEFAULT_K) -> np.ndarray:
    """The same ML with the squared errors replaced by their posterior expectations (the EM M-step)."""
    return estimate(r_hat, t_hat, e_r2, e_t2, start)


# ----------------------------------------------------------------------------- MCL
@dataclass
class MCLResult:
    """Estimated poses, the (reported, corrected) pairs, and the parameters over time."""

    mode: str
    poses: np.ndarray                   # (T+1, 3) particle mean after each update
    pairs: np.ndarray                   # (T, 5) r_hat, theta_hat, r, theta, region
    k_final: np.ndarray                 # (R, 3) parameters in use at the end
    k_trace: list = field(default_factory=list)   # (step, region, k) at each refit
    seconds: float = 0.0


def _resample(w: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Low-variance (systematic) resampling indices."""
    n = len(w)
    c = np.cumsum(w)
    c[-1] = 1.0
    return np.searchsorted(c, (rng.random() + np.arange(n)) / n)


def _mean_pose(p: np.ndarray) -> np.ndarray:
    return np.array([p[:, 0].mean(), p[:, 1].mean(), np.arctan2(np.sin(p[:, 2]).mean(), np.cos(p[:, 2]).mean())])


def correction(P: np.ndarray, drive: Drive, sl: slice, range_sigma: float, bearing_sigma: float,
               rng: np.random.Generator) -> np.ndarray | None:
    """MCL's sensor update: resampling indices of the particles ``P`` weighed by the sightings ``sl`` (None if none)."""
    if sl.stop <= sl.start:
        return None
    rel = drive.landmark_xy[sl][None] - P[:, None, :2]
    dr = np.hypot(rel[..., 0], rel[..., 1]) - drive.obs_range[sl][None]
    db = wrap(np.arctan2(rel[..., 1], rel[..., 0]) - P[:, None, 2] - drive.obs_bearing[sl][None])
    logw = -0.5 * ((dr / range_sigma) ** 2 + (db / bearing_sigma) ** 2).sum(1)
    w = np.exp(logw - logw.max())
    return _resample(w / w.sum(), rng)


def run_mcl(drive: Drive, size, grid, mode: str = "default", k_static=None, particles: int = 500,
            window: int = 300, refit_every: int = 25, min_pairs: int = 60,
            range_sigma: float = 0.05, bearing_sigma: float = 0.02, seed: int = 0) -> MCLResult:
    """Track the robot with MCL; ``mode``: default, static (``k_static``), global or regional dynamic.

    Dynamic modes keep the last ``window`` pairs (globally or per region) and refit the k's by ML
    every ``refit_every`` new pairs, warm-started from the parameters in use; a region with fewer
    than ``min_pairs`` pairs keeps its previous parameters. The sensor model is known.
    """
    if mode not in ("default", "static", "global", "regional"):
        raise ValueError(f"unknown MCL mode {mode!r}")
    t0 = time.perf_counter()
    rng = np.random.default_rng(seed)
    R = grid[0] * grid[1]
    k0 = np.asarray(k_static if mode == "static" else DEFAULT_K, float)
    K = np.tile(k0, (R, 1))
    T = len(drive.r)
    P = np.tile(drive.start, (particles, 1))
    est = np.empty((T + 1, 3))
    est[0] = drive.start
    pairs = np.empty((T, 5))
    starts = np.searchsorted(drive.obs_step, np.arange(T + 2))
    windows: dict[int, list] = {}
    new: dict[int, int] = {}
    trace = []
    for k in range(T):
        reg = region_of(est[k, :2], size, grid)[0]
        vr, vt = variances(K[reg], drive.r[k], drive.theta[k])     # the parameters stored with the region
        P = step(P, drive.r[k] + rng.normal(size=particles) * np.sqrt(vr),
                 drive.theta[k] + rng.normal(size=particles) * np.sqrt(vt))
        idx = correction(P, drive, slice(starts[k + 1], starts[k + 2]), range_sigma, bearing_sigma, rng)
        if idx is not None:
            P = P[idx]
        est[k + 1] = _mean_pose(P)
        d = est[k + 1, :2] - est[k, :2]
        r = d[0] * np.cos(est[k, 2]) + d[1] * np.sin(est[k, 2])
        pairs[k] = (drive.r[k], drive.theta[k], r, wrap(est[k + 1, 2] - est[k, 2]), reg)
        if mode in ("global", "regional"):
            key = reg if mode == "regional" else 0
            win = windows.setdefault(key, [])
            win.append(pairs[k, :4])
            if len(win) > window:
                win.pop(0)
            new[key] = new.get(key, 0) + 1
            if new[key] >= refit_every and len(win) >= min_pairs:
                a = np.array(win)
                knew = fit_k(*a.T, start=K[reg])
                if mode == "regional":
                    K[reg] = knew
                else:
                    K[:] = knew
                new[key] = 0
                trace.append((k, int(key), knew))
    return MCLResult(mode=mode, poses=est, pairs=pairs, k_final=K.copy(), k_trace=trace,
                     seconds=time.perf_counter() - t0)


MODES = ("default", "optimal static", "global dynamic", "regional dynamic")     # the paper's Table 1 rows


def run_modes(drive: Drive, size, grid, seed: int = 0, **kw) -> dict[str, MCLResult]:
    """The paper's four MCL variants on one log; optimal static is the ML fit to the default run's pairs."""
    runs = {"default": run_mcl(drive, size, grid, "default", seed=seed, **kw)}
    k_opt = fit_k(*runs["default"].pairs[:, :4].T)
    runs["optimal static"] = run_mcl(drive, size, grid, "static", k_static=k_opt, seed=seed, **kw)
    runs["global dynamic"] = run_mcl(drive, size, grid, "global", seed=seed, **kw)
    runs["regional dynamic"] = run_mcl(drive, size, grid, "regional", seed=seed, **kw)
    return runs


def default_worst(errs: dict[str, dict], quantity: str) -> bool:
    """Is default static the worst of the four in ``quantity`` (a key of ``errors``), as in Table 1?"""
    return all(errs["default"][quantity] > errs[m][quantity] for m in MODES[1:])


def errors(poses: np.ndarray, truth: np.ndarray) -> dict:
    """Localisation error against truth: position and heading RMS, and the paper-style per-step
    range and angle errors as a percentage of the distance and angle really moved."""
    tp = truth[:, 1:]
    pos = np.hypot(*(poses[:, :2] - tp[:, :2]).T)
    head = wrap(poses[:, 2] - tp[:, 2])

    def motion(p):
        d = np.diff(p[:, :2], axis=0)
        return np.hypot(d[:, 0], d[:, 1]), wrap(np.diff(p[:, 2]))

    r_e, t_e = motion(poses)
    r_t, t_t = motion(tp)
    return {"position_rms": float(np.sqrt(np.mean(pos ** 2))), "heading_rms": float(np.sqrt(np.mean(head ** 2))),
            "range_error_pct": float(100 * np.sum(np.abs(r_e - r_t)) / np.sum(r_t)),
            "angle_error_pct": float(100 * np.sum(np.abs(wrap(t_e - t_t))) / np.sum(np.abs(t_t)))}


def regional_fit(pairs: np.ndarray, n_regions: int, start=DEFAULT_K, min_pairs: int = 60) -> np.ndarray:
    """ML k's per region from all of a run's MCL pairs (the MCL side of the comparison with the graph)."""
    K = np.tile(np.asarray(start, float), (n_regions, 1))
    for g in range(n_regions):
        a = pairs[pairs[:, 4] == g]
        if len(a) >= min_pairs:
            K[g] = fit_k(*a[:, :4].T, start=start)
    return K


def rough_regions(K: np.ndarray, r_ref: float = 0.2, theta_ref: float = 0.1) -> list[int]:
    """Which regions stand out: the log motion variances each region's k's predict for a reference
    step, relative to the median region, split at the largest gap (robust to one k trading off
    against another, e.g. drift against turn error)."""
    vr, vt = variances(np.asarray(K, float), r_ref, theta_ref)
    score = 0.5 * (np.log(vr / np.median(vr)) + np.log(vt / np.median(vt)))
    order = np.argsort(score)
    gaps = np.diff(score[order])
    cut = int(np.argmax(gaps)) + 1
    return sorted(int(i) for i in order[cut:])


def rough_among(K: np.ndarray, seen: np.ndarray) -> list[int]:
    """``rough_regions`` judged among the regions ``seen`` (the path's data), as region ids."""
    idx = np.flatnonzero(seen)
    return [int(idx[i]) for i in rough_regions(np.asarray(K)[seen])]


def regions_seen(truth: np.ndarray, size, grid, min_steps: int = MIN_SEGMENTS) -> np.ndarray:
    """(R,) bool: the regions the true path (truth.csv rows: t, x, y, theta) spent at least ``min_steps`` steps in;
    elsewhere no method has data and every estimate is its start."""
    return np.bincount(region_of(truth[:-1, 1:3], size, grid), minlength=grid[0] * grid[1]) >= min_steps


def map_right(K: np.ndarray, seen: np.ndarray, rough) -> bool:
    """Does the regional map ``K`` single out exactly the true ``rough`` regions, among those ``seen``?"""
    return rough_among(K, seen) == sorted(set(rough) & set(np.flatnonzero(seen).tolist()))


def log_error(K: np.ndarray, K_true: np.ndarray) -> float:
    """RMS of log(k_est / k_true) over regions and parameters (0 is perfect; 0.69 is a factor 2)."""
    return float(np.sqrt(np.mean(np.log(np.asarray(K) / np.asarray(K_true)) ** 2)))


def variance_error(K: np.ndarray, K_true: np.ndarray, r_ref: float = 0.2, theta_ref: float = 0.1) -> float:
    """RMS of log(predicted / true) translation and rotation variance for a reference step, over regions:
    how wrong the motion noise a region's k's predict is, whatever the split between k_t and k_d."""
    vr, vt = variances(np.asarray(K, float), r_ref, theta_ref)
    tr, tt = variances(np.asarray(K_true, float), r_ref, theta_ref)
    return float(np.sqrt(np.mean(np.concatenate([np.log(vr / tr), np.log(vt / tt)]) ** 2)))


def floor_trial(cfg, min_steps: int = MIN_SEGMENTS) -> dict:
    """The paper's four variants on one simulated floor, scored against its truth: is default static the worst
    (range %, angle %, position RMS) and does the regional map single out the rough regions among those the
    path spent at least ``min_steps`` steps in (RMS log(var/var_true) there too)."""
    log, truth = simulate(cfg)
    K_true = np.array(truth["motion_model"]["region_k"])
    runs = run_modes(drive_of(log), cfg.size, cfg.grid, seed=cfg.seed, range_sigma=cfg.range_sigma,
                     bearing_sigma=cfg.bearing_sigma)
    err = {m: errors(r.poses, log.truth) for m, r in runs.items()}
    seen = regions_seen(log.truth, cfg.size, cfg.grid, min_steps)
    K = runs["regional dynamic"].k_final
    return {"errors": err, "map_right": map_right(K, seen, cfg.rough),
            "default_worst": {q: default_worst(err, q) for q in ("range_error_pct", "angle_error_pct", "position_rms")},
            "variance_error": variance_error(K[seen], K_true[seen])}


# ----------------------------------------------------------------------------- the factor graph, jointly
@dataclass
class GraphEMResult:
    """Per-region k's and the smoothed trajectory from EM on the factor graph."""

    k: np.ndarray
    poses: np.ndarray
    k_trace: list
    iterations: int
    seconds: float


LATERAL_SIGMA = 1e-3     # the model has no sideways motion within a step; a small sigma keeps it solvable


def _graph(drive: Drive, regions: np.ndarray, K: np.ndarray, range_sigma: float, bearing_sigma: float):
    X = lambda i: gtsam.symbol("x", i)  # noqa: E731
    L = lambda j: gtsam.symbol("l", j)  # noqa: E731
    g = gtsam.NonlinearFactorGraph()
    g.add(gtsam.PriorFactorPose2(X(0), gtsam.Pose2(*drive.start), gtsam.noiseModel.Isotropic.Sigma(3, 1e-4)))
    vr, vt = variances(K[regions], drive.r, drive.theta)
    for i in range(len(drive.r)):
        g.add(gtsam.BetweenFactorPose2(X(i), X(i + 1), gtsam.Pose2(drive.r[i], 0.0, drive.theta[i]),
                                       gtsam.noiseModel.Diagonal.Sigmas(np.array([np.sqrt(vr[i]), LATERAL_SIGMA, np.sqrt(vt[i])]))))
    lms, lm_index = np.unique(drive.landmark_xy, axis=0, return_inverse=True)
    lm_index = lm_index.ravel()
    obs_noise = gtsam.noiseModel.Diagonal.Sigmas(np.array([bearing_sigma, range_sigma]))
    for j, xy in enumerate(lms):
        g.add(gtsam.PriorFactorPoint2(L(j), xy, gtsam.noiseModel.Isotropic.Sigma(2, 1e-6)))
    for n in range(len(drive.obs_range)):
        g.add(gtsam.BearingRangeFactor2D(X(int(drive.obs_step[n])), L(int(lm_index[n])),
                                         gtsam.Rot2(drive.obs_bearing[n]), drive.obs_range[n], obs_noise))
    return g, X, L, lms


def graph_em(drive: Drive, size, grid, init_poses: np.ndarray, k_start=DEFAULT_K, iterations: int = 40,
             range_sigma: float = 0.05, bearing_sigma: float = 0.02, tol: float = 0.02) -> GraphEMResult:
    """EM on the factor graph: E-step smooths the whole trajectory (Levenberg-Marquardt on built-in
    factors) and takes the joint marginals of consecutive poses; M-step refits each region's k's
    by ML with the expected squared motion errors (mean error squared plus its posterior variance)."""
    t0 = time.perf_counter()
    R = grid[0] * grid[1]
    T = len(drive.r)
    K = np.tile(np.asarray(k_start, float), (R, 1))
    poses = np.asarray(init_poses, float).copy()
    trace = [K.copy()]
    it = 0
    for it in range(1, iterations + 1):
        regions = region_of(poses[:-1, :2], size, grid)
        g, X, L, lms = _graph(drive, regions, K, range_sigma, bearing_sigma)
        init = gtsam.Values()
        for i in range(T + 1):
            init.insert(X(i), gtsam.Pose2(*poses[i]))
        for j, xy in enumerate(lms):
            init.insert(L(j), np.asarray(xy, float))
        est = gtsam.LevenbergMarquardtOptimizer(g, init, gtsam.LevenbergMarquardtParams()).optimize()
        poses = np.array([[p.x(), p.y(), p.theta()] for p in (est.atPose2(X(i)) for i in range(T + 1))])
        marg = gtsam.Marginals(g, est)
        e_r2, e_t2 = np.empty(T), np.empty(T)
        for i in range(T):
            a, b = est.atPose2(X(i)), est.atPose2(X(i + 1))
            rel = a.between(b)
            J = np.hstack([-rel.inverse().AdjointMap(), np.eye(3)])
            keys = gtsam.KeyVector([X(i), X(i + 1)])
            S = marg.jointMarginalCovariance(keys).fullMatrix()
            C = J @ S @ J.T
            e_r2[i] = (rel.x() - drive.r[i]) ** 2 + C[0, 0]
            e_t2[i] = wrap(rel.theta() - drive.theta[i]) ** 2 + C[2, 2]
        regions = region_of(poses[:-1, :2], size, grid)
        K_new = K.copy()
        for gi in range(R):
            m = regions == gi
            if m.sum() >= 30:
                K_new[gi] = fit_k_expected(drive.r[m], drive.theta[m], e_r2[m], e_t2[m], start=K[gi])
        change = np.max(np.abs(np.log(K_new / K)))
        K = K_new
        trace.append(K.copy())
        if change < tol:
            break
    return GraphEMResult(k=K, poses=poses, k_trace=trace, iterations=it, seconds=time.perf_counter() - t0)
