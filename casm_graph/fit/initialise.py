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

from casm_graph.fit.locate import grid_cell, locate
from casm_graph.io.log import Log, wrap
from casm_graph.models.model import Model

@dataclass
class Start:
    """The initial guess: poses at every pose step, the model, and what the search found."""

    poses: np.ndarray           # (T+1, 3)
    model: Model
    hypothesis: tuple[float, float]   # (p, k) of the winning sensor hypothesis
    log_evidence: float


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


def initialise(log: Log, model: Model, stride: int = 5, cell: float | None = None) -> Start:
    """Global start for ``calibrate``: trajectory, velocity table and sensor polynomial (``cell``: the grid
    smoother's, by default :func:`casm_graph.fit.locate.grid_cell`)."""
    cell = grid_cell(log) if cell is None else cell
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
