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
from scipy.ndimage import gaussian_filter

from .log import Log, wrap
from .model import Model


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


def _smooth(grid: _Grid, step_of_obs: np.ndarray, lm_of_obs: np.ndarray, reading: np.ndarray,
            predict, sigma, n_steps: int, blur: float):
    """Histogram forward-backward smoother; returns posterior mean positions and log evidence."""
    order = np.argsort(step_of_obs, kind="stable")
    bounds = np.searchsorted(step_of_obs[order], np.arange(n_steps + 1))
    pred = [predict(grid.dist[l]) for l in range(len(grid.dist))]
    shape = grid.dist.shape[1:]

    def likelihood(k):
        out = None
        for j in order[bounds[k]:bounds[k + 1]]:
            r = reading[j]
            s = sigma(r)
            lik = 0.02 + np.exp(-0.5 * ((r - pred[lm_of_obs[j]]) / s) ** 2)
            out = lik if out is None else out * lik
        return out

    alpha = np.empty((n_steps, *shape), dtype=np.float32)
    a = np.full(shape, 1.0 / np.prod(shape))
    log_ev = 0.0
    for k in range(n_steps):
        if k:
            a = gaussian_filter(a, blur, mode="constant")
        lik = likelihood(k)
        if lik is not None:
            a = a * lik
        z = a.sum()
        log_ev += np.log(z)
        a /= z
        alpha[k] = a
    mean = np.empty((n_steps, 2))
    b = np.ones(shape)
    X, Y = np.meshgrid(grid.x, grid.y)
    for k in range(n_steps - 1, -1, -1):
        if k < n_steps - 1:
            lik = likelihood(k + 1)
            b = gaussian_filter(b if lik is None else b * lik, blur, mode="constant")
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
    t0 = np.array([t_knot[seg_of_knot == s].min() for s in range(n_seg)])
    tt = t_knot[obs_knot] - t0[seg_obs]
    out = np.full((n_seg, 2), np.nan)
    for a in np.unique(seg_act):
        segs = np.flatnonzero(seg_act == a)
        sums = []
        for s in segs:
            sel = seg_obs == s
            sums.append(np.exp(1j * (theta_obs[sel][None, :] - ws[:, None] * tt[sel][None, :])).sum(axis=1))
        sums = np.array(sums)
        if sums.size == 0 or not np.any(np.abs(sums)):
            continue
        i = np.argmax(np.abs(sums).sum(axis=0))
        for s, z in zip(segs, sums[:, i]):
            if abs(z) > 0:
                out[s] = (np.angle(z), ws[i])
    return out


def initialise(log: Log, model: Model, stride: int = 5, cell: float = 0.1) -> Start:
    """Global start for ``calibrate``: trajectory, velocity table and sensor polynomial."""
    T = log.steps
    knots = np.arange(0, T + 1, stride)
    t_pose = log.pose_times
    t_knot = t_pose[knots]
    obs_knot = np.clip(np.round(log.obs_step / stride).astype(int), 0, len(knots) - 1)
    has_r = ~np.isnan(log.obs_reading)
    lm_idx = log.landmark_index
    grid = _grid(log, cell, margin=1.5)
    dt_k = float(np.median(np.diff(t_knot)))
    blur = 0.6 * dt_k / cell       # random walk of ~0.6 m/s: faster than a walking Aibo
    reading = log.obs_reading[has_r]
    r_med = float(np.median(reading))
    r_scale = float(np.median(np.abs(reading - r_med))) + 1e-9
    args = (obs_knot[has_r], lm_idx[has_r], reading)

    # 1. sensor hypotheses reading = k d^p, scored by evidence
    d_typ = np.geomspace(0.5, 2.0 * np.ptp(log.landmark_xy, axis=0).max() + 0.5, 10)
    best = None
    for p in (-1.0, 1.0):
        for dt_ in d_typ:
            k = r_med / dt_ ** p
            mean, ev = _smooth(grid, *args, lambda d, k=k, p=p: k * d ** p,
                               lambda r: 0.15 * abs(r) + 0.1 * r_scale, len(knots), blur)
            if best is None or ev > best[2]:
                best = (p, k, ev, mean)
    p, k, ev, mean = best

    # EM rounds: refit the curve as a polynomial against the smoothed distances
    deg = len(model.reading_poly) - 1
    lm = log.landmark_xy[lm_idx]
    for _ in range(3):
        d_obs = np.hypot(*(mean[obs_knot] - lm).T)
        poly = np.polynomial.polynomial.polyfit(d_obs[has_r], reading, deg)
        res = reading - np.polynomial.polynomial.polyval(d_obs[has_r], poly)
        s = 1.4826 * np.median(np.abs(res)) + 1e-9
        lo, hi = np.percentile(d_obs[has_r], [1, 99])
        predict = (lambda d, poly=poly, lo=lo, hi=hi:
                   np.polynomial.polynomial.polyval(np.clip(d, lo, hi), poly))
        mean, ev = _smooth(grid, *args, predict, lambda r, s=s: 2.0 * s, len(knots), blur)
    d_obs = np.hypot(*(mean[obs_knot] - lm).T)
    poly = np.polynomial.polynomial.polyfit(d_obs[has_r], reading, deg)

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
    for s in range(n_seg):
        sel = np.flatnonzero(seg_of_knot == s)
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
