"""Initialisation from nothing but the log and the map, free of local minima.

Plain LM from zero velocities and a poor sensor model lands in a wrong minimum, so the start is
built in three global steps before any least squares runs:

1. **Where was the robot?** A histogram (grid) forward-backward smoother over position with a
   random-walk motion model needs no velocities. The sensor curve is unknown, so it is run under
   a family of physical hypotheses, reading = k * d**p (p = -1: apparent size, p = +1: range), and
   the hypothesis with the highest evidence p(readings | hypothesis) wins; a few EM rounds then
   refit the curve as a polynomial against the smoothed distances.
2. **Which way did it face?** Within each constant-action segment the heading is theta0 + w t; a
   circular regression of (direction to landmark - measured bearing) on time gives theta0 and w.
3. **How fast?** With the headings fixed, the segment's positions are linear in its body-frame
   velocity; per-action averages of the per-segment fits give the starting table, and dead
   reckoning each segment from its own fit gives the starting trajectory.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from casm_graph.graph import robust
from casm_graph.io.log import Log, wrap
from casm_graph.models.model import Model

OUTLIER_Z2 = np.float32(8.0)


@dataclass
class Start:
    """The initial guess: poses at every pose step, the model, and what the search found."""

    poses: np.ndarray           # (T+1, 3)
    model: Model
    hypothesis: tuple[float, float]   # (p, k) of the winning sensor hypothesis
    log_evidence: float


@dataclass
class _Grid:
    x: np.ndarray
    y: np.ndarray
    cell: float
    dist: np.ndarray            # (L, ny, nx) distance from each cell to each landmark


def _grid(log: Log, cell: float, margin: float) -> _Grid:
    lo = log.landmark_xy.min(0) - margin
    hi = log.landmark_xy.max(0) + margin
    x = np.arange(lo[0], hi[0] + cell, cell)
    y = np.arange(lo[1], hi[1] + cell, cell)
    X, Y = np.meshgrid(x, y)
    dist = np.hypot(X[None] - log.landmark_xy[:, 0, None, None], Y[None] - log.landmark_xy[:, 1, None, None])
    return _Grid(x, y, cell, dist)


def _blur_matrix(n: int, blur: float) -> np.ndarray:
    """(n, n) Gaussian blur along one axis with zero outside the grid (mass leaving the field is lost)."""
    i = np.arange(n)
    K = np.exp(-0.5 * ((i[:, None] - i[None, :]) / blur) ** 2)
    K[np.abs(i[:, None] - i[None, :]) > max(1, int(np.ceil(3 * blur)))] = 0.0
    return K / K.sum(axis=1, keepdims=True).max()


def _log_likelihood(grid: _Grid, step_of_obs, lm_of_obs, reading, predict, sigma):
    """Steps with readings, and the (n, ny, nx) summed log-likelihood of each at every cell.

    The Gaussian term is capped at ``OUTLIER_Z2`` so a reading that fits nowhere cannot veto a cell.
    """
    pred = np.stack([predict(d) for d in grid.dist]).astype(np.float32)
    s = (np.asarray(sigma(reading), np.float32) * np.ones(len(reading), np.float32))
    order = np.argsort(step_of_obs, kind="stable")
    steps = step_of_obs[order]
    first = np.flatnonzero(np.r_[True, np.diff(steps) != 0])
    out = np.empty((len(first), *grid.dist.shape[1:]), dtype=np.float32)
    _summed_terms(pred, np.asarray(lm_of_obs, np.int64), np.asarray(reading).astype(np.float32), s,
                  order.astype(np.int64), np.append(first, len(order)).astype(np.int64), out)
    return steps[first], out


@njit(cache=True)
def _summed_terms(pred, lm, reading, s, order, bounds, out):
    """out[g] = sum over sightings order[bounds[g]:bounds[g+1]] of -0.5 min(z^2, OUTLIER_Z2) at every cell,
    z = (reading - pred[lm]) / s, in float32 and in the order numpy's ``add.reduceat`` adds them, the
    first term plus the running sum of the others (one pass over the sightings, where the array form
    made six passes over (sightings, ny, nx) arrays)."""
    cap = np.float32(OUTLIER_Z2)
    half = np.float32(-0.5)
    ny, nx = pred.shape[1], pred.shape[2]
    for g in range(len(bounds) - 1):
        lo, hi = bounds[g], bounds[g + 1]
        for k in list(range(lo + 1, hi)) + [lo]:
            j = order[k]
            r, sj, p = reading[j], s[j], pred[lm[j]]
            for y in range(ny):
                for x in range(nx):
                    z = (r - p[y, x]) / sj
                    zz = z * z
                    if zz > cap:
                        zz = cap
                    v = half * zz
                    if k == lo + 1 or (k == lo and hi == lo + 1):
                        out[g, y, x] = v
                    else:
                        out[g, y, x] += v


def _smooth(grid: _Grid, step_of_obs: np.ndarray, lm_of_obs: np.ndarray, reading: np.ndarray,
            predict, sigma, n_steps: int, blur: float, means: bool = True):
    """Histogram forward-backward smoother; returns posterior mean positions and log evidence.

    With ``means=False`` only the forward pass runs (the evidence needs nothing more).
    """
    steps, ll = _log_likelihood(grid, step_of_obs, lm_of_obs, reading, predict, sigma)
    row = np.full(n_steps, -1)
    row[steps] = np.arange(len(steps))
    shape = grid.dist.shape[1:]
    Ky, Kx = _blur_matrix(shape[0], blur), _blur_matrix(shape[1], blur).T
    alpha = np.empty((n_steps, *shape), dtype=np.float32)
    a = np.full(shape, 1.0 / np.prod(shape))
    log_ev = 0.0
    for k in range(n_steps):
        if k:
            a = Ky @ a @ Kx
        if row[k] >= 0:
            lk = ll[row[k]]
            m = float(lk.max())
            a = a * np.exp(lk - m)
            log_ev += m
        z = a.sum()
        log_ev += np.log(z)
        a /= z
        alpha[k] = a
    if not means:
        return None, log_ev
    mean = np.empty((n_steps, 2))
    b = np.ones(shape)
    X, Y = np.meshgrid(grid.x, grid.y)
    for k in range(n_steps - 1, -1, -1):
        if k < n_steps - 1:
            if row[k + 1] >= 0:
                lk = ll[row[k + 1]]
                b = b * np.exp(lk - lk.max())
            b = Ky @ b @ Kx
            b /= b.max()
        g = alpha[k] * b
        g /= g.sum()
        mean[k] = ((g * X).sum(), (g * Y).sum())
    return mean, log_ev


def _headings(seg_of_knot, seg_act, t_knot, obs_knot, dirs, bearing, w_max=3.0):
    """Circular regression of heading samples on time: (theta0 at segment start, w) per segment.

    Segments of the same action share one turn rate, so w is chosen per action by maximising the
    summed resultant lengths of its segments; each segment keeps its own theta0.
    """
    n_seg = len(seg_act)
    theta_obs = wrap(dirs - bearing)
    ws = np.linspace(-w_max, w_max, 1201)
    seg_obs = seg_of_knot[obs_knot]
    # seg_of_knot is non-decreasing: each segment's knots (and, sorted stably, its sightings) are one slice
    first = np.searchsorted(seg_of_knot, np.arange(n_seg))
    t0 = t_knot[np.minimum(first, len(t_knot) - 1)]   # a run too short to hold a knot has no sighting either
    tt = t_knot[obs_knot] - t0[seg_obs]
    by_seg = np.argsort(seg_obs, kind="stable")
    cut = np.searchsorted(seg_obs[by_seg], np.arange(n_seg + 1))
    out = np.full((n_seg, 2), np.nan)
    for a in np.unique(seg_act):
        segs = np.flatnonzero(seg_act == a)
        sums = []
        for s in segs:
            sel = by_seg[cut[s]:cut[s + 1]]
            sums.append(np.exp(1j * (theta_obs[sel][None, :] - ws[:, None] * tt[sel][None, :])).sum(axis=1))
        sums = np.array(sums)
        if sums.size == 0 or not np.any(np.abs(sums)):
            continue
        i = np.argmax(np.abs(sums).sum(axis=0))
        for s, z in zip(segs, sums[:, i]):
            if abs(z) > 0:
                out[s] = (np.angle(z), ws[i])
    return out


@dataclass
class Located:
    """Step 1's answer: smoothed positions at the knots and the sensor curve fitted against them."""

    mean: np.ndarray            # (K, 2) posterior mean position at each knot
    poly: np.ndarray            # reading polynomial against the smoothed distances
    residual: np.ndarray        # reading residuals under ``poly``
    hypothesis: tuple[float, float]
    log_evidence: float


def locate(log: Log, obs_knot: np.ndarray, n_knots: int, dt_k: float, c_knot: np.ndarray, n_c_knots: int,
           degree: int, cell: float = 0.1, speed: float = 0.6) -> Located:
    """Step 1: where was the robot at each knot, with no velocities and an unknown sensor curve.

    ``obs_knot`` maps observations to knots ``dt_k`` seconds apart; ``c_knot`` maps them to the
    coarser knots (about 3 ``dt_k`` apart) on which the hypotheses are scored. ``speed`` (m/s) sets
    the random walk; it should exceed how fast the robot moves.
    """
    has_r = ~np.isnan(log.obs_reading)
    lm_idx = log.landmark_index
    grid = _grid(log, cell, margin=1.5)
    blur = speed * dt_k / cell       # random walk of ~0.6 m/s: faster than a walking Aibo
    reading = log.obs_reading[has_r]
    r_med = float(np.median(reading))
    r_scale = float(np.median(np.abs(reading - r_med))) + 1e-9
    args = (obs_knot[has_r], lm_idx[has_r], reading)

    # sensor hypotheses reading = k d^p, scored by evidence on a coarser grid (3x stride, 2x cell)
    c_cell = 2 * cell
    c_grid = _grid(log, c_cell, margin=1.5)
    c_blur = speed * dt_k * 3 / c_cell
    c_args = (c_knot[has_r], lm_idx[has_r], reading)
    d_typ = np.geomspace(0.5, 2.0 * np.ptp(log.landmark_xy, axis=0).max() + 0.5, 10)
    best = None
    for p in (-1.0, 1.0):
        for dt_ in d_typ:
            k = r_med / dt_ ** p
            _, ev = _smooth(c_grid, *c_args, lambda d, k=k, p=p: k * d ** p,
                            lambda r: 0.15 * abs(r) + 0.1 * r_scale, n_c_knots, c_blur,
                            means=False)
            if best is None or ev > best[2]:
                best = (p, k, ev)
    p, k, ev = best
    mean, ev = _smooth(grid, *args, lambda d: k * d ** p, lambda r: 0.15 * abs(r) + 0.1 * r_scale,
                       n_knots, blur)
    # EM rounds: refit the curve as a polynomial against the smoothed distances
    lm = log.landmark_xy[lm_idx]
    for _ in range(2):
        d_obs = np.hypot(*(mean[obs_knot] - lm).T)
        poly = robust.polyfit(d_obs[has_r], reading, degree)
        res = reading - np.polynomial.polynomial.polyval(d_obs[has_r], poly)
        s = 1.4826 * np.median(np.abs(res)) + 1e-9
        lo, hi = np.percentile(d_obs[has_r], [1, 99])
        predict = (lambda d, poly=poly, lo=lo, hi=hi:
                   np.polynomial.polynomial.polyval(np.clip(d, lo, hi), poly))
        mean, ev = _smooth(grid, *args, predict, lambda r, s=s: 2.0 * s, n_knots, blur)
    d_obs = np.hypot(*(mean[obs_knot] - lm).T)
    poly = robust.polyfit(d_obs[has_r], reading, degree)
    return Located(mean, poly, res, (p, k), float(ev))


def initialise(log: Log, model: Model, stride: int = 5, cell: float = 0.1) -> Start:
    """Global start for ``calibrate``: trajectory, velocity table and sensor polynomial."""
    T = log.steps
    knots = np.arange(0, T + 1, stride)
    t_pose = log.pose_times
    t_knot = t_pose[knots]
    obs_knot = np.clip(np.round(log.obs_step / stride).astype(int), 0, len(knots) - 1)
    lm_idx = log.landmark_index
    lm = log.landmark_xy[lm_idx]
    c_stride = 3 * stride
    c_knot = np.clip(np.round(log.obs_step / c_stride).astype(int), 0, T // c_stride)
    loc = locate(log, obs_knot, len(knots), float(np.median(np.diff(t_knot))), c_knot, T // c_stride + 1,
                 len(model.reading_poly) - 1, cell)
    mean, poly, res, (p, k), ev = loc.mean, loc.poly, loc.residual, loc.hypothesis, loc.log_evidence

    # 2. headings per constant-action segment from bearings
    act = log.action
    seg_start = np.concatenate([[0], np.flatnonzero(np.diff(act) != 0) + 1])
    seg_of_step = np.cumsum(np.isin(np.arange(T), seg_start)) - 1
    seg_of_knot = seg_of_step[np.minimum(knots, T - 1)]
    n_seg = len(seg_start)
    has_b = ~np.isnan(log.obs_bearing)
    dirs = np.arctan2(lm[:, 1] - mean[obs_knot, 1], lm[:, 0] - mean[obs_knot, 0])
    seg_act = np.searchsorted(model.action_ids, act[seg_start])
    head = _headings(seg_of_knot, seg_act, t_knot, obs_knot[has_b], dirs[has_b], log.obs_bearing[has_b])

    # 3. body-frame velocity per segment, then per action
    seg_v = np.full((n_seg, 3), np.nan)
    knot_cut = np.searchsorted(seg_of_knot, np.arange(n_seg + 1))      # seg_of_knot is non-decreasing
    for s in range(n_seg):
        sel = np.arange(knot_cut[s], knot_cut[s + 1])
        if len(sel) < 3 or np.isnan(head[s, 0]):
            continue
        tt = t_knot[sel] - t_knot[sel[0]]
        th0, w = head[s]
        # integral of R(th0 + w tau) d tau from 0 to t, by the trapezoid rule on a fine grid
        tau = np.linspace(0, tt[-1], 8 * len(tt))
        c, sn = np.cos(th0 + w * tau), np.sin(th0 + w * tau)
        ic = np.concatenate([[0], np.cumsum((c[1:] + c[:-1]) / 2 * np.diff(tau))])
        is_ = np.concatenate([[0], np.cumsum((sn[1:] + sn[:-1]) / 2 * np.diff(tau))])
        ic, is_ = np.interp(tt, tau, ic), np.interp(tt, tau, is_)
        n = len(sel)
        A = np.zeros((2 * n, 4))
        A[0::2, 0] = 1
        A[1::2, 1] = 1
        A[0::2, 2], A[0::2, 3] = ic, -is_
        A[1::2, 2], A[1::2, 3] = is_, ic
        sol, *_ = np.linalg.lstsq(A, mean[sel].reshape(-1), rcond=None)
        seg_v[s] = (sol[2], sol[3], w)

    vel = np.zeros_like(model.velocities)
    for a in range(len(model.action_ids)):
        rows = seg_v[(seg_act == a) & ~np.isnan(seg_v[:, 0])]
        if len(rows):
            vel[a] = np.median(rows, axis=0)

    # trajectory: each segment dead-reckoned from its own start with its own fit
    poses = np.empty((T + 1, 3))
    dt = log.dt
    for s in range(n_seg):
        a0 = seg_start[s]
        a1 = seg_start[s + 1] if s + 1 < n_seg else T
        v = seg_v[s] if not np.isnan(seg_v[s, 0]) else vel[seg_act[s]]
        th0 = head[s, 0] if not np.isnan(head[s, 0]) else 0.0
        kk = np.clip(np.round(np.arange(a0, a1 + 1) / stride).astype(int), 0, len(knots) - 1)
        th = th0 + v[2] * (t_pose[a0:a1 + 1] - t_pose[a0])
        c, sn = np.cos(th[:-1]), np.sin(th[:-1])
        x = mean[kk[0], 0] + np.concatenate([[0], np.cumsum((c * v[0] - sn * v[1]) * dt[a0:a1])])
        y = mean[kk[0], 1] + np.concatenate([[0], np.cumsum((sn * v[0] + c * v[1]) * dt[a0:a1])])
        poses[a0:a1 + 1] = np.column_stack([x, y, wrap(th)])

    out = model.with_(velocities=vel, reading_poly=poly,
                      reading_sigma=float(max(1.4826 * np.median(np.abs(res)), 1e-6)))
    return Start(poses=poses, model=out, hypothesis=(p, k), log_evidence=float(ev))
